"""BDPT's machinery, shared by `bdpt`, `light` (light tracing: s >= 1, t = 1)
and `mlt` (primary-sample-space MLT over BDPT strategies, `mlt_L`): the
vertex records, the camera and light subpath walks, the connection of an
(s, t) strategy and its MIS weight (Veach 1997; pbrt-v3's BDPTIntegrator).

MIS weights follow pbrt-v3's `MISWeight`: each vertex stores the area
density of being sampled from its neighbour in the subpath's own direction
(`pdf_fwd`) and in the reverse direction (`pdf_rev`); a strategy's weight is
1 / (1 + sum of ratios) with the ratios of neighbouring strategies chained
along the path (squared for the power heuristic). Specular (mirror, glass)
vertices are `delta`: their pdfs are 0, remapped to 1 in the ratios, and no
strategy connects at them or next to them; point lights are delta positions
(no s = 0 strategy). The camera (a pinhole, or a thin lens whose point t = 1
samples anew) is connectible (t = 1).
BSDFs are evaluated in the shading frame (V_NS) and are 0 where a direction
lies behind the geometric normal (V_N); geometry terms take the shading
cosines and density conversions the geometric ones (pbrt-v3). The light
subpath transports importance: refraction takes no 1/eta^2, and its BSDF
values carry Veach's adjoint correction for shading normals,
|wo.ns| |wi.ng| / (|wo.ng| |wi.ns|), so that light tracing and path tracing
agree (the adjoint BSDF, pbrt's TransportMode::Importance).
No Russian roulette (as pbrt-v3's BDPT): paths end at the depth limit.

Vertex records: a float64 row per vertex (fields V_* below) in one buffer per
sample (`workspace(depth)`): rows [0, depth + 2) the camera subpath, rows
[depth + 2, 2 depth + 4) the light subpath, row 2 depth + 4 the light vertex
sampled for s = 1 strategies.

Random numbers, one array `u` per path (`dims(depth)` entries), the layout
shared with `mlt_L` (pbrt-v3's MLTSampler streams, here flat):
- u[0], u[1]: film position as fractions of width and height;
- u[2]: the strategy choice (MLT only); u[3] and u[7]: the point on a thin
  lens (unread for a pinhole);
- camera bounce k (k = 0..depth): u[4 + 4k], u[5 + 4k] the BSDF direction,
  u[6 + 4k] glass reflect/refract, u[7 + 4k] unused (but u[7]);
- LIGHT0 = 8 + 4 depth: u[LIGHT0] the light pick, u[LIGHT0 + 1..2] the point
  on it, u[LIGHT0 + 3..4] the emitted direction, u[LIGHT0 + 5] unused; light
  bounce k: u[LIGHT0 + 6 + 4k ...] as for the camera;
- CONN0 = LIGHT0 + 10 + 4 depth: the s = 1 connection of the strategy with t
  camera vertices: u[CONN0 + 4t] the light pick, u[CONN0 + 4t + 1..2] the
  point on the light, u[CONN0 + 4t + 3] unused; for t = 1 (which samples no
  light point), u[CONN0 + 5..6] the point on a thin lens;
- total dims(depth) = CONN0 + 4 (depth + 3).
In a `bdpt` render, u[0:LIGHT0] come from the job's pixel sampler for the
camera sample (`u1d`/`u2d`, renderer/samplers/, at those dimensions) and u[LIGHT0:]
from the same sample's hash key (`uniform(key, dim)`): the light subpath's
dimensions never overlap the camera subpath's.
"""

from __future__ import annotations

import math

import numpy as np

from . import kernel, kernel_inline
from .bsdf import (
    MAT_DIELECTRIC,
    MAT_DIFFUSE,
    MAT_GLOSSY,
    MAT_MIRROR,
    dielectric_sample,
    diffuse_sample,
    reflect,
)
from .camera import CAM_MARGIN, camera_connect, camera_pdf_dir, camera_ray_at
from .geometry import offset_origin
from .opacity import blocked, trace
from .shading import shade_hit
from .ggx import glossy_eval, glossy_sample
from .lights import LIGHT_POINT, sample_emission
from .sampling import BALANCE
from .vertices import (  # noqa: F401 (the record's layout: re-exported)
    V_P,
    V_N,
    V_BETA,
    V_PDF_FWD,
    V_PDF_REV,
    V_TYPE,
    V_DELTA,
    V_MAT,
    V_LIGHT,
    V_WO,
    V_DLIGHT,
    V_NS,
    V_ALB,
    V_ALPHA,
    V_FRONT,
    NV,
    T_CAMERA,
    T_LIGHT,
    T_SURFACE,
    _on_surface,
    _convert,
    _bsdf_f_pdf,
    shading_cos,
    _connectible,
    _dir,
    vertex_f,
)

ALL_STRATEGIES = -1


@kernel
def light0(depth):
    """First dimension of the light subpath in `u` (module doc)."""
    return 8 + 4 * depth


@kernel
def conn0(depth):
    """First dimension of the connections in `u` (module doc)."""
    return light0(depth) + 10 + 4 * depth


@kernel
def dims(depth):
    """Length of the random-number array `u` of one path (module doc)."""
    return conn0(depth) + 4 * (depth + 3)


def workspace(depth: int) -> np.ndarray:
    """The vertex buffer of one path: camera rows, light rows, sampled row."""
    return np.zeros((2 * (depth + 2) + 1, NV))


@kernel
def pdf_light(light_type, light_area, V, i, j):
    """Area density at j of a ray leaving light (or emitting surface) vertex i
    towards j as `sample_emission` draws it (pbrt's PdfLight; no pick)."""
    wx, wy, wz, d2 = _dir(V, i, j)
    if d2 == 0.0:
        return 0.0
    li = int(V[i, V_LIGHT])
    if light_type[li] == LIGHT_POINT:
        pdf = 0.25 / math.pi
    else:  # the emitting side: V_N turned back to the front where it was turned
        front = V[i, V_FRONT] * (V[i, V_N] * wx + V[i, V_N + 1] * wy + V[i, V_N + 2] * wz)
        pdf = max(front, 0.0) / math.pi
    if _on_surface(V, j):
        pdf *= abs(V[j, V_N] * wx + V[j, V_N + 1] * wy + V[j, V_N + 2] * wz)
    return pdf / d2


@kernel
def pdf_light_origin(light_type, light_area, V, i):
    """Area density (including the 1/L pick) of vertex i as a light path's origin."""
    li = int(V[i, V_LIGHT])
    n_lights = light_type.shape[0]
    if light_type[li] == LIGHT_POINT:
        return 1.0 / n_lights
    return 1.0 / (n_lights * light_area[li])


@kernel
def vertex_pdf(mat_type, mat_rgb, mat_param, light_type, light_area, cam, width, height, V,
               i, prev, j):
    """Area density at vertex j of vertex i sampling its next vertex j, having
    come from `prev` (-1: none): pbrt's Vertex::Pdf. 0 for delta lobes."""
    if V[i, V_TYPE] == T_LIGHT:
        return pdf_light(light_type, light_area, V, i, j)
    wx, wy, wz, d2 = _dir(V, i, j)
    if d2 == 0.0:
        return 0.0
    if V[i, V_TYPE] == T_CAMERA:
        pdf = camera_pdf_dir(cam, width, height, V[i, 0], V[i, 1], V[i, 2], wx, wy, wz)
    else:
        px, py, pz, e2 = _dir(V, i, prev)
        if e2 == 0.0:
            return 0.0
        pdf = _bsdf_f_pdf(mat_type, V, i, px, py, pz, wx, wy, wz)[3]
    return _convert(V, i, pdf, j)


@kernel_inline
def random_walk(sc, stack, V, n0, n_end, sx, sy, sz, dx, dy, dz, br, bg, bb, pdf_fwd,
                importance, u, ubase):
    """Extend a subpath whose last vertex is row n0 - 1: the ray (s, d) leaves
    it with throughput beta and solid-angle pdf `pdf_fwd`. Fills rows n0 ..
    n_end - 1 at most (pbrt-v3's RandomWalk); bounce k reads u[ubase + 4k ..].
    Returns (end row, rays traced)."""
    n = n0
    rays = 0
    while n < n_end:
        t, prim = trace(sc, stack, sx, sy, sz, dx, dy, dz, np.inf)
        rays += 1
        if prim < 0:
            break
        hx, hy, hz = sx + t * dx, sy + t * dy, sz + t * dz
        (fx, fy, fz, gx, gy, gz, nx, ny, nz, ar, ag, ab, alpha,
         mat, light) = shade_hit(sc, prim, hx, hy, hz, dx, dy, dz)
        V[n, 0], V[n, 1], V[n, 2] = hx, hy, hz
        V[n, 3], V[n, 4], V[n, 5] = gx, gy, gz
        V[n, 6], V[n, 7], V[n, 8] = br, bg, bb
        V[n, V_PDF_REV] = 0.0
        V[n, V_TYPE] = T_SURFACE
        V[n, V_DELTA] = 0.0
        V[n, V_MAT] = mat
        V[n, V_LIGHT] = light
        V[n, V_WO], V[n, V_WO + 1], V[n, V_WO + 2] = -dx, -dy, -dz
        V[n, V_DLIGHT] = 0.0
        V[n, V_NS], V[n, V_NS + 1], V[n, V_NS + 2] = nx, ny, nz
        V[n, V_ALB], V[n, V_ALB + 1], V[n, V_ALB + 2] = ar, ag, ab
        V[n, V_ALPHA] = alpha
        V[n, V_FRONT] = 1.0 if fx * gx + fy * gy + fz * gz >= 0.0 else -1.0
        V[n, V_PDF_FWD] = _convert(V, n - 1, pdf_fwd, n)
        n += 1
        if n >= n_end:
            break
        k = ubase + 4 * (n - n0 - 1)
        mt = sc.mat_type[mat]
        cos_o = -(dx * nx + dy * ny + dz * nz)
        cos_g = -(dx * gx + dy * gy + dz * gz)
        side = 1.0
        delta = False
        if mt == MAT_DIFFUSE:
            if cos_o <= 0.0 or cos_g <= 0.0:
                break
            wx, wy, wz, cos_i, pdf = diffuse_sample(nx, ny, nz, u[k], u[k + 1])
            if pdf <= 0.0:
                break
            wr, wg, wb = ar, ag, ab
            pdf_rev = cos_o / math.pi
        elif mt == MAT_GLOSSY:
            if cos_g <= 0.0:
                break
            wx, wy, wz, wr, wg, wb, pdf = glossy_sample(
                nx, ny, nz, -dx, -dy, -dz, alpha, ar, ag, ab, u[k], u[k + 1])
            if pdf <= 0.0:
                break
            pdf_rev = glossy_eval(nx, ny, nz, wx, wy, wz, -dx, -dy, -dz, alpha, 1.0, 1.0, 1.0)[3]
        elif mt == MAT_MIRROR:
            if cos_o <= 0.0 or cos_g <= 0.0:
                break
            wx, wy, wz = reflect(dx, dy, dz, nx, ny, nz)
            wr, wg, wb = ar, ag, ab
            delta = True
            pdf = 0.0
            pdf_rev = 0.0
        else:  # MAT_DIELECTRIC
            wx, wy, wz, w, es, side = dielectric_sample(dx, dy, dz, nx, ny, nz,
                                                        sc.mat_param[mat, 0], u[k + 2])
            if importance:
                w *= es  # the adjoint BSDF: importance is not compressed by refraction
            wr, wg, wb = w, w, w
            delta = True
            pdf = 0.0
            pdf_rev = 0.0
        if gx != nx or gy != ny or gz != nz:  # a shading normal: the usual side checks
            wig = wx * gx + wy * gy + wz * gz
            wis = wx * nx + wy * ny + wz * nz
            if (mt != MAT_DIELECTRIC and wig <= 0.0) or wig * wis <= 0.0 or cos_o * cos_g <= 0.0:
                break  # (glass may leave through the surface, on the side it refracts to)
            if importance:  # Veach's adjoint BSDF for shading normals
                c = abs(cos_o) * abs(wig) / (abs(cos_g) * abs(wis))
                wr, wg, wb = wr * c, wg * c, wb * c
        if wr <= 0.0 and wg <= 0.0 and wb <= 0.0:
            break
        br *= wr
        bg *= wg
        bb *= wb
        if delta:
            V[n - 1, V_DELTA] = 1.0
        pdf_fwd = pdf
        V[n - 2, V_PDF_REV] = _convert(V, n - 1, pdf_rev, n - 2)
        if mt == MAT_DIELECTRIC:
            sx, sy, sz = offset_origin(hx, hy, hz, nx, ny, nz, side)
        else:
            sx, sy, sz = offset_origin(hx, hy, hz, gx, gy, gz, side)
        dx, dy, dz = wx, wy, wz
    return n, rays


@kernel_inline
def camera_subpath(sc, cam, width, height, stack, V, fx, fy, n_max, u, ubase):
    """The camera subpath through film position (fx, fy): rows 0 .. n - 1 of
    V, at most n_max vertices (camera included; a thin lens's point from
    u[3], u[7]). Returns (n, rays)."""
    if n_max <= 0:
        return 0, 0
    ox, oy, oz, dx, dy, dz = camera_ray_at(cam, width, height, fx, fy, u[3], u[7])
    for c in range(NV):
        V[0, c] = 0.0
    V[0, 0], V[0, 1], V[0, 2] = ox, oy, oz
    V[0, 6], V[0, 7], V[0, 8] = 1.0, 1.0, 1.0
    V[0, V_TYPE] = T_CAMERA
    V[0, V_MAT] = -1.0
    V[0, V_LIGHT] = -1.0
    pdf_dir = camera_pdf_dir(cam, width, height, ox, oy, oz, dx, dy, dz)
    return random_walk(sc, stack, V, 1, n_max, ox, oy, oz, dx, dy, dz, 1.0, 1.0, 1.0, pdf_dir,
                       False, u, ubase)


@kernel_inline
def light_subpath(sc, stack, V, row0, n_max, u, ubase):
    """The light subpath: rows row0 .. row0 + n - 1 of V, at most n_max
    vertices (the light point first); u[ubase ..] as in the module doc.
    Returns (n, rays)."""
    if n_max <= 0 or sc.light_type.shape[0] == 0:
        return 0, 0
    (li, prim, ox, oy, oz, nx, ny, nz, dx, dy, dz, er, eg, eb, pdf_pos, pdf_dir,
     delta) = sample_emission(sc, u[ubase], u[ubase + 1], u[ubase + 2], u[ubase + 3],
                              u[ubase + 4])
    if pdf_pos <= 0.0 or pdf_dir <= 0.0:
        return 0, 0
    r = row0
    for c in range(NV):
        V[r, c] = 0.0
    V[r, 0], V[r, 1], V[r, 2] = ox, oy, oz
    V[r, 3], V[r, 4], V[r, 5] = nx, ny, nz
    V[r, V_NS], V[r, V_NS + 1], V[r, V_NS + 2] = nx, ny, nz
    V[r, V_FRONT] = 1.0
    V[r, 6], V[r, 7], V[r, 8] = er / pdf_pos, eg / pdf_pos, eb / pdf_pos
    V[r, V_PDF_FWD] = pdf_pos
    V[r, V_TYPE] = T_LIGHT
    V[r, V_MAT] = -1.0
    V[r, V_LIGHT] = li
    V[r, V_DLIGHT] = 1.0 if delta else 0.0
    if delta:
        k = 1.0 / (pdf_pos * pdf_dir)
        sx, sy, sz = ox, oy, oz
    else:
        k = abs(nx * dx + ny * dy + nz * dz) / (pdf_pos * pdf_dir)
        sx, sy, sz = offset_origin(ox, oy, oz, nx, ny, nz, 1.0)
    n, rays = random_walk(sc, stack, V, r + 1, r + n_max, sx, sy, sz, dx, dy, dz, er * k,
                          eg * k, eb * k, pdf_dir, True, u, ubase + 6)
    return n - r, rays


@kernel_inline
def visible(sc, stack, V, i, j):
    """True if nothing blocks the segment between vertices i and j (both ends
    moved off their surfaces towards each other; opacity masks pass some)."""
    wx, wy, wz, d2 = _dir(V, i, j)
    if d2 == 0.0:
        return False
    ax, ay, az = V[i, 0], V[i, 1], V[i, 2]
    if _on_surface(V, i):
        side = 1.0 if V[i, V_N] * wx + V[i, V_N + 1] * wy + V[i, V_N + 2] * wz > 0.0 else -1.0
        ax, ay, az = offset_origin(ax, ay, az, V[i, V_N], V[i, V_N + 1], V[i, V_N + 2], side)
    bx, by, bz = V[j, 0], V[j, 1], V[j, 2]
    if _on_surface(V, j):
        side = 1.0 if V[j, V_N] * wx + V[j, V_N + 1] * wy + V[j, V_N + 2] * wz < 0.0 else -1.0
        bx, by, bz = offset_origin(bx, by, bz, V[j, V_N], V[j, V_N + 1], V[j, V_N + 2], side)
    dx, dy, dz = bx - ax, by - ay, bz - az
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    inv = 1.0 / d
    return not blocked(sc, stack, ax, ay, az, dx * inv, dy * inv, dz * inv, d * (1.0 - 1e-9))


@kernel
def _remap0(x):
    return x if x != 0.0 else 1.0


@kernel
def mis_weight(sc, cam, width, height, V, lrow, srow, s, t, heuristic):
    """`mis_weight_arrays` with the scene's arrays (for Python callers)."""
    return mis_weight_arrays(sc.mat_type, sc.mat_rgb, sc.mat_param, sc.light_type, sc.light_area,
                             cam, width, height, V, lrow, srow, s, t, heuristic)


# Hot calls take the arrays they read, not the SceneArrays tuple: passing the
# tuple into a non-inlined call copies every array's struct (geometry.py).
@kernel
def mis_weight_arrays(mt, mr, mp, lt, la, cam, width, height, V, lrow, srow, s, t, heuristic):
    """pbrt-v3's MISWeight for strategy (s, t): camera vertex i is row i,
    light vertex i row lrow + i, except that with s = 1 the light vertex is
    the sampled one in row srow. The reverse pdfs of the connection vertices
    and their neighbours are evaluated here (pbrt's ScopedAssignments,
    without writing them). Balance heuristic, or power with heuristic POWER."""
    if s + t == 2:
        return 1.0
    pt = t - 1
    ptm = t - 2  # -1: none
    qs = -1
    qsm = -1
    if s >= 1:
        qs = srow if s == 1 else lrow + s - 1
    if s >= 2:
        qsm = lrow + s - 2
    # reverse densities of the connection vertices and their neighbours
    if s > 0:
        pt_rev = vertex_pdf(mt, mr, mp, lt, la, cam, width, height, V, qs, qsm, pt)
    else:
        pt_rev = pdf_light_origin(lt, la, V, pt)
    ptm_rev = 0.0
    if ptm >= 0:
        if s > 0:
            ptm_rev = vertex_pdf(mt, mr, mp, lt, la, cam, width, height, V, pt, qs, ptm)
        else:
            ptm_rev = pdf_light(lt, la, V, pt, ptm)
    qs_rev = 0.0
    if qs >= 0:
        qs_rev = vertex_pdf(mt, mr, mp, lt, la, cam, width, height, V, pt, ptm, qs)
    qsm_rev = 0.0
    if qsm >= 0:
        qsm_rev = vertex_pdf(mt, mr, mp, lt, la, cam, width, height, V, qs, pt, qsm)
    total = 0.0
    ri = 1.0
    for i in range(t - 1, 0, -1):
        rev = pt_rev if i == pt else (ptm_rev if i == ptm else V[i, V_PDF_REV])
        ri *= _remap0(rev) / _remap0(V[i, V_PDF_FWD])
        delta_i = 0.0 if i == pt else V[i, V_DELTA]
        if delta_i == 0.0 and V[i - 1, V_DELTA] == 0.0:
            total += ri if heuristic == BALANCE else ri * ri
    ri = 1.0
    for i in range(s - 1, -1, -1):
        row = srow if (s == 1 and i == 0) else lrow + i
        rev = qs_rev if i == s - 1 else (qsm_rev if i == s - 2 else V[row, V_PDF_REV])
        ri *= _remap0(rev) / _remap0(V[row, V_PDF_FWD])
        delta_i = 0.0 if i == s - 1 else V[row, V_DELTA]
        if i > 0:
            prev_row = srow if (s == 1 and i - 1 == 0) else lrow + i - 1
            delta_prev = V[prev_row, V_DELTA]
        else:
            delta_prev = V[row, V_DLIGHT]
        if delta_i == 0.0 and delta_prev == 0.0:
            total += ri if heuristic == BALANCE else ri * ri
    return 1.0 / (1.0 + total)


@kernel_inline
def connect(sc, cam, width, height, stack, V, lrow, srow, s, t, u, ubase, heuristic, weighted):
    """Strategy (s, t) of the subpaths in V (pbrt-v3's ConnectBDPT): (r, g, b,
    fx, fy, rays), the (MIS-weighted if `weighted`) contribution and, for
    t = 1, the film position it splats to. s = 1 samples a new light point
    from u[ubase .. ubase + 2]."""
    r, g, b = 0.0, 0.0, 0.0
    fx, fy = -1.0, -1.0
    rays = 0
    pt = t - 1
    vi, vj = -1, -1  # the vertices whose segment must be clear
    if s == 0:
        li = int(V[pt, V_LIGHT])
        if V[pt, V_TYPE] == T_SURFACE and li >= 0:
            cos = V[pt, V_FRONT] * (V[pt, V_N] * V[pt, V_WO] + V[pt, V_N + 1] * V[pt, V_WO + 1]
                                    + V[pt, V_N + 2] * V[pt, V_WO + 2])
            if cos > 0.0:
                r = V[pt, 6] * sc.light_rgb[li, 0]
                g = V[pt, 7] * sc.light_rgb[li, 1]
                b = V[pt, 8] * sc.light_rgb[li, 2]
    elif t == 1:
        qs = lrow + s - 1
        if not _connectible(sc.mat_type, V, qs):
            return 0.0, 0.0, 0.0, fx, fy, 0
        px, py, pz = V[qs, 0], V[qs, 1], V[qs, 2]
        (fx, fy, we, cos_cam, dist, wx, wy, wz, lx, ly, lz) = camera_connect(
            cam, width, height, px, py, pz, u[ubase + 1], u[ubase + 2])
        if we <= 0.0:
            return 0.0, 0.0, 0.0, fx, fy, 0
        # the camera vertex of this strategy is the sampled lens point (row 0's
        # position is read after the camera subpath's walk only here)
        V[0, 0], V[0, 1], V[0, 2] = lx, ly, lz
        if V[qs, V_TYPE] == T_LIGHT:  # s = 1: the light point seen by the camera
            if V[qs, V_DLIGHT] != 0.0:
                return 0.0, 0.0, 0.0, fx, fy, 0  # point lights: not visible (as path-mis)
            cos_l = V[qs, 3] * wx + V[qs, 4] * wy + V[qs, 5] * wz
            if cos_l <= 0.0:
                return 0.0, 0.0, 0.0, fx, fy, 0
            fr, fg, fb = cos_l, cos_l, cos_l
        else:
            # one camera row of V holds the camera's point (row 0): connect to it
            fr, fg, fb = vertex_f(sc.mat_type, sc.mat_rgb, sc.mat_param, V, qs, 0)
            c = shading_cos(V, qs, wx, wy, wz, True)
            fr, fg, fb = fr * c, fg * c, fb * c
        k = we * cos_cam / (dist * dist)
        r, g, b = V[qs, 6] * fr * k, V[qs, 7] * fg * k, V[qs, 8] * fb * k
        vi, vj = qs, 0
    elif s == 1:
        if not _connectible(sc.mat_type, V, pt) or sc.light_type.shape[0] == 0:
            return 0.0, 0.0, 0.0, fx, fy, 0
        (li, prim, ox, oy, oz, nx, ny, nz, dx, dy, dz, er, eg, eb, pdf_pos, pdf_dir,
         delta) = sample_emission(sc, u[ubase], u[ubase + 1], u[ubase + 2], 0.5, 0.5)
        if pdf_pos <= 0.0:
            return 0.0, 0.0, 0.0, fx, fy, 0
        for c in range(NV):
            V[srow, c] = 0.0
        V[srow, 0], V[srow, 1], V[srow, 2] = ox, oy, oz
        V[srow, 3], V[srow, 4], V[srow, 5] = nx, ny, nz
        V[srow, V_NS], V[srow, V_NS + 1], V[srow, V_NS + 2] = nx, ny, nz
        V[srow, V_FRONT] = 1.0
        V[srow, V_TYPE] = T_LIGHT
        V[srow, V_MAT] = -1.0
        V[srow, V_LIGHT] = li
        V[srow, V_DLIGHT] = 1.0 if delta else 0.0
        V[srow, V_PDF_FWD] = pdf_pos
        wx, wy, wz, d2 = _dir(V, pt, srow)
        if d2 == 0.0:
            return 0.0, 0.0, 0.0, fx, fy, 0
        if delta:
            k = 1.0 / (pdf_pos * d2)
        else:
            cos_l = -(nx * wx + ny * wy + nz * wz)
            if cos_l <= 0.0:
                return 0.0, 0.0, 0.0, fx, fy, 0
            k = cos_l / (pdf_pos * d2)
        fr, fg, fb = vertex_f(sc.mat_type, sc.mat_rgb, sc.mat_param, V, pt, srow)
        c = shading_cos(V, pt, wx, wy, wz, False) * k
        r = V[pt, 6] * fr * er * c
        g = V[pt, 7] * fg * eg * c
        b = V[pt, 8] * fb * eb * c
        vi, vj = pt, srow
    else:
        qs = lrow + s - 1
        if not (_connectible(sc.mat_type, V, qs) and _connectible(sc.mat_type, V, pt)):
            return 0.0, 0.0, 0.0, fx, fy, 0
        wx, wy, wz, d2 = _dir(V, qs, pt)
        if d2 == 0.0:
            return 0.0, 0.0, 0.0, fx, fy, 0
        if V[qs, V_TYPE] == T_LIGHT:
            # only with s = 1, handled above; a light row at s > 1 cannot occur
            return 0.0, 0.0, 0.0, fx, fy, 0
        ar, ag, ab = vertex_f(sc.mat_type, sc.mat_rgb, sc.mat_param, V, qs, pt)
        cr, cg, cb = vertex_f(sc.mat_type, sc.mat_rgb, sc.mat_param, V, pt, qs)
        gterm = shading_cos(V, qs, wx, wy, wz, True) * shading_cos(V, pt, wx, wy, wz, False) / d2
        r = V[qs, 6] * ar * cr * V[pt, 6] * gterm
        g = V[qs, 7] * ag * cg * V[pt, 7] * gterm
        b = V[qs, 8] * ab * cb * V[pt, 8] * gterm
        vi, vj = qs, pt
    # the connection's segment (s = 0 has none), one call site: `visible` is inlined
    if vi >= 0 and (r > 0.0 or g > 0.0 or b > 0.0):
        rays += 1
        if not visible(sc, stack, V, vi, vj):
            return 0.0, 0.0, 0.0, fx, fy, rays
    if weighted and (r > 0.0 or g > 0.0 or b > 0.0):
        w = mis_weight_arrays(sc.mat_type, sc.mat_rgb, sc.mat_param, sc.light_type,
                              sc.light_area, cam, width, height, V, lrow, srow, s, t, heuristic)
        r, g, b = r * w, g * w, b * w
    return r, g, b, fx, fy, rays


@kernel
def mlt_L(sc, cam, width, height, depth, heuristic, u, V, stack):
    """One BDPT strategy of one path from primary samples, as pbrt-v3's
    MLTIntegrator::L: (r, g, b, film_x, film_y, rays).

    `depth` is the path's exact number of bounces (segments - 1); the
    strategy is drawn from u[2]: depth 0 uses (s, t) = (0, 2) alone; otherwise
    s = min(int(u[2] (depth + 2)), depth + 1), t = depth + 2 - s. The film
    position (pixels, x right, row 0 at top) is (u[0] width, u[1] height)
    except for t = 1 strategies, where it is the projection of the light
    subpath's last vertex; then the rays it traced. The contribution is MIS-weighted (balance, or
    power with heuristic = POWER = 0; BALANCE = 1) and multiplied by the
    number of strategies of that depth. Units (pbrt's): the value f(u) is
    the image contribution per unit of primary sample space, with the film
    position uniform over the whole film, so the depth-`depth` part of pixel
    j's radiance is width * height * E_u[f(u) 1(film position in j)]: splat
    f * width * height / N for N uniform u (t = 1 strategies, whose
    importance We is per pixel, are divided by width * height here to share
    these units). With a tent or Gaussian filter the film position is
    uniform over the frame and the filter's margin around it (m pixels,
    kernels/camera.py), f carries (W + 2m)(H + 2m) / (W H) for it, and the
    splat spreads f over the pixels by their filter weights in place of
    1(film position in j). Zero when a subpath ends early.

    Arguments: sc = scene.arrays, cam = camera_array(...), u = float64 array
    of dims(depth) numbers in [0, 1) laid out as in the module doc (film,
    strategy, camera bounces, light subpath, connection), V = workspace(depth)
    (scratch), stack = int64 array of STACK_SIZE (BVH traversal scratch).
    """
    if depth == 0:
        n_strategies = 1
        s = 0
        t = 2
    else:
        n_strategies = depth + 2
        s = min(int(u[2] * n_strategies), n_strategies - 1)
        t = n_strategies - s
    k = n_strategies
    m = cam[CAM_MARGIN]
    if m > 0.0:
        # a filter reaches m pixels beyond the frame: the film position is
        # uniform over the frame and that margin, a larger film
        fx = -m + u[0] * (width + 2.0 * m)
        fy = -m + u[1] * (height + 2.0 * m)
        k *= (width + 2.0 * m) * (height + 2.0 * m) / (width * height)
    else:
        fx, fy = u[0] * width, u[1] * height
    nc, rays = camera_subpath(sc, cam, width, height, stack, V, fx, fy, t, u, 4)
    if nc != t:
        return 0.0, 0.0, 0.0, fx, fy, rays
    lrow = depth + 2
    srow = 2 * (depth + 2)
    if s >= 2:
        nl, light_rays = light_subpath(sc, stack, V, lrow, s, u, light0(depth))
        rays += light_rays
        if nl != s:
            return 0.0, 0.0, 0.0, fx, fy, rays
    r, g, b, sx, sy, connect_rays = connect(sc, cam, width, height, stack, V, lrow, srow, s, t,
                                            u, conn0(depth) + 4 * t, heuristic, True)
    rays += connect_rays
    if t == 1:
        fx, fy = sx, sy
        k = n_strategies / (width * height)  # per-pixel We (kernels/camera.py) -> per film, as pbrt's
    return r * k, g * k, b * k, fx, fy, rays


