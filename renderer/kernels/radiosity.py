"""Radiosity kernels: patches, Monte Carlo form factors and the linear solvers.

Patches (built by renderer/radiosity_solve.py) are structure-of-arrays:
`kind` 0 = a flat triangle (geo = v0, e1, e2), 1 = a zone of an analytic
sphere (geo = centre, radius, z_lo, z_hi, phi0, phi1, +1 or -1 for the
front side outwards or inwards; z is the sphere's local z, so the zones are
equal-area bands split in longitude).

Form factors are estimated by ray casting (gathering form). Monte Carlo:
from patch i, `n` rays leave uniformly distributed points of i in
cosine-distributed directions; the fraction that reaches the front of patch
j estimates F_ij (the cosine density makes the hit probability exactly
F_ij). Directions are stratified on a sqrt(n) x sqrt(n) grid (proportional
allocation: never more variance than independent rays). Hemicube (Cohen and
Greenberg 1985): rays from the centre of i through the pixel centres of a
hemicube, each weighing that pixel's delta form factor (an item buffer
made by ray casting instead of rasterisation). The rays are not stored as a
matrix but as their hits: `hits[i, s]` is the patch ray s of i reached (-1:
nothing, a back side, or a surface that is no patch), and ray s weighs
`weight[s]` (1/n, or the hemicube's delta form factors, summing to 1). Then
(F X)_i = sum_s weight[s] X[hits[i, s]], O(n) per patch whatever the patch
count.
"""

import math

import numpy as np
from numba import prange

from . import kernel, kernel_parallel
from .geometry import intersect_arrays, offset_origin, surface_at_arrays
from .lights import sample_light
from .rng import STREAM_RADIOSITY, stream_key, uniform
from .sampling import cosine_hemisphere, to_world, uniform_triangle

PATCH_TRI, PATCH_SPHERE = 0, 1
DIMS_PER_RAY = 8  # point on the patch (2), direction (2), unused (1), light point (2)
DIRECT_NONE, DIRECT_POINT, DIRECT_ALL = 0, 1, 2
SOLVER_JACOBI, SOLVER_GAUSS_SEIDEL, SOLVER_PROGRESSIVE = 0, 1, 2


@kernel
def patch_of(tri_isect, tri_start, tri_k, cells, sph, sph_start, sph_nz, sph_nphi, prim,
             px, py, pz):
    """The patch holding point p of primitive `prim`, or -1 if it is no patch."""
    n_tri = tri_isect.shape[0]
    if prim < n_tri:
        start = tri_start[prim]
        if start < 0:
            return -1
        k = tri_k[prim]
        dx, dy, dz = px - tri_isect[prim, 0], py - tri_isect[prim, 1], pz - tri_isect[prim, 2]
        e1x, e1y, e1z = tri_isect[prim, 3], tri_isect[prim, 4], tri_isect[prim, 5]
        e2x, e2y, e2z = tri_isect[prim, 6], tri_isect[prim, 7], tri_isect[prim, 8]
        d11 = e1x * e1x + e1y * e1y + e1z * e1z
        d12 = e1x * e2x + e1y * e2y + e1z * e2z
        d22 = e2x * e2x + e2y * e2y + e2z * e2z
        d1 = dx * e1x + dy * e1y + dz * e1z
        d2 = dx * e2x + dy * e2y + dz * e2z
        den = d11 * d22 - d12 * d12
        a = (d22 * d1 - d12 * d2) / den * k
        b = (d11 * d2 - d12 * d1) / den * k
        i = min(max(int(math.floor(a)), 0), k - 1)
        j = min(max(int(math.floor(b)), 0), k - 1)
        if i + j > k - 1:  # rounding outside the hypotenuse
            j = k - 1 - i
        down = 1 if (a - i) + (b - j) > 1.0 and i + j < k - 1 else 0
        return cells[start + (i * k + j) * 2 + down]
    s = prim - n_tri
    start = sph_start[s]
    if start < 0:
        return -1
    r = sph[s, 3]
    lz = min(max((pz - sph[s, 2]) / r, -1.0), 1.0)
    nz, nphi = sph_nz[s], sph_nphi[s]
    iz = min(int((1.0 - lz) * 0.5 * nz), nz - 1)
    phi = math.atan2(py - sph[s, 1], px - sph[s, 0])
    if phi < 0.0:
        phi += 2.0 * math.pi
    ip = min(int(phi / (2.0 * math.pi) * nphi), nphi - 1)
    return start + iz * nphi + ip


@kernel
def patch_point(kind, geo, normal, i, u1, u2):
    """A uniform point on patch i and the front normal there."""
    if kind[i] == PATCH_TRI:
        b0, b1 = uniform_triangle(u1, u2)
        b2 = 1.0 - b0 - b1
        return (geo[i, 0] + b1 * geo[i, 3] + b2 * geo[i, 6],
                geo[i, 1] + b1 * geo[i, 4] + b2 * geo[i, 7],
                geo[i, 2] + b1 * geo[i, 5] + b2 * geo[i, 8],
                normal[i, 0], normal[i, 1], normal[i, 2])
    r = geo[i, 3]
    z = geo[i, 4] + u1 * (geo[i, 5] - geo[i, 4])
    phi = geo[i, 6] + u2 * (geo[i, 7] - geo[i, 6])
    rho = math.sqrt(max(0.0, 1.0 - z * z))
    lx, ly = rho * math.cos(phi), rho * math.sin(phi)
    f = geo[i, 8]
    return geo[i, 0] + r * lx, geo[i, 1] + r * ly, geo[i, 2] + r * z, f * lx, f * ly, f * z


@kernel
def patch_centre(kind, geo, normal, i):
    """The centroid of patch i (of a sphere zone: its middle in z and phi)
    and the front normal there: where a hemicube stands."""
    if kind[i] == PATCH_TRI:
        return (geo[i, 0] + (geo[i, 3] + geo[i, 6]) / 3.0,
                geo[i, 1] + (geo[i, 4] + geo[i, 7]) / 3.0,
                geo[i, 2] + (geo[i, 5] + geo[i, 8]) / 3.0,
                normal[i, 0], normal[i, 1], normal[i, 2])
    return patch_point(kind, geo, normal, i, 0.5, 0.5)


@kernel
def _trace_patch(sc, stack, tri_start, tri_k, cells, sph_start, sph_nz, sph_nphi,
                 ox, oy, oz, dx, dy, dz):
    """The patch whose front the ray meets first, or -1."""
    t, prim = intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                               stack, ox, oy, oz, dx, dy, dz, np.inf, False)
    if prim < 0:
        return -1
    hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
    mx, my, mz, mat, light = surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light, sc.sph,
                                               sc.sph_flip, sc.sph_mat, sc.sph_light,
                                               prim, hx, hy, hz)
    if mx * dx + my * dy + mz * dz >= 0.0:  # the back side reflects nothing
        return -1
    return patch_of(sc.tri_isect, tri_start, tri_k, cells, sc.sph, sph_start, sph_nz, sph_nphi,
                    prim, hx, hy, hz)


@kernel_parallel
def form_factor_rays(sc, kind, geo, normal, tri_start, tri_k, cells, sph_start, sph_nz, sph_nphi,
                     seed, hemicube, n_light, direct, hits, irradiance, irr_batches, rays,
                     stacks):
    """For every patch i (in parallel; each writes only its own rows):
    - the hits of its form-factor rays, hits.shape[1] of them: Monte Carlo
      (hemicube is empty: uniform points, stratified cosine directions) or
      the hemicube's pixel directions (hemicube (M, 3), local to the patch's
      frame, all from its centre);
    - with direct != DIRECT_NONE, the irradiance from the lights estimated
      by `n_light` light samples at uniform points of i with shadow rays:
      all lights (DIRECT_ALL) or point lights only (DIRECT_POINT); also per
      jackknife batch (irr_batches (P, J, 3): the light samples s with
      s % J == b, over n_light like the whole), for the solution's variance.
    Random numbers: stream_key(seed, STREAM_RADIOSITY, i), DIMS_PER_RAY
    dimensions per ray s (the light sample s uses the same dimensions)."""
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    n_lights = sc.light_type.shape[0]
    n_rays = hits.shape[1]
    # Ray s belongs to jackknife batch s % J; each batch stratifies its own
    # directions (m x m strata of its rays s // J), so the batches are
    # independent, identically distributed estimates, which the jackknife's
    # variance assumes: strata across all rays would make the batches
    # dependent and the jackknife overstate (measured: 2x where the light
    # comes through the form factors).
    groups = max(irr_batches.shape[1], 1)
    m = int(math.sqrt(n_rays // groups))
    for i in prange(kind.shape[0]):
        stack = stacks[i]
        key = stream_key(seed, STREAM_RADIOSITY, i)
        count = 0
        cx, cy, cz, cnx, cny, cnz = patch_centre(kind, geo, normal, i)
        for s in range(n_rays):
            if hemicube.shape[0] > 0:
                px, py, pz, nx, ny, nz = cx, cy, cz, cnx, cny, cnz
                dx, dy, dz = to_world(hemicube[s, 0], hemicube[s, 1], hemicube[s, 2],
                                      nx, ny, nz)
            else:
                base = DIMS_PER_RAY * s
                px, py, pz, nx, ny, nz = patch_point(kind, geo, normal, i, uniform(key, base),
                                                     uniform(key, base + 1))
                u3, u4 = uniform(key, base + 2), uniform(key, base + 3)
                r = s // groups  # the ray's index in its batch
                if r < m * m:  # stratified directions
                    u3 = ((r % m) + u3) / m
                    u4 = ((r // m) + u4) / m
                lx, ly, lz = cosine_hemisphere(u3, u4)
                dx, dy, dz = to_world(lx, ly, lz, nx, ny, nz)
            ox, oy, oz = offset_origin(px, py, pz, nx, ny, nz, 1.0)
            hits[i, s] = _trace_patch(sc, stack, tri_start, tri_k, cells, sph_start, sph_nz,
                                      sph_nphi, ox, oy, oz, dx, dy, dz)
            count += 1
        er, eg, eb = 0.0, 0.0, 0.0
        n_batches = irr_batches.shape[1]
        for b in range(n_batches):
            for c in range(3):
                irr_batches[i, b, c] = 0.0
        if direct != DIRECT_NONE and n_lights > 0:
            for s in range(n_light):
                base = DIMS_PER_RAY * s
                px, py, pz, nx, ny, nz = patch_point(kind, geo, normal, i, uniform(key, base),
                                                     uniform(key, base + 1))
                wx, wy, wz, dist, pdf, lr, lg, lb, delta = sample_light(
                    sc, px, py, pz, uniform(key, base + 5), uniform(key, base + 6))
                if direct == DIRECT_POINT and not delta:
                    continue
                cos_i = wx * nx + wy * ny + wz * nz
                if pdf <= 0.0 or cos_i <= 0.0:
                    continue
                # the shadow ray of kernels/geometry.py: measured from the offset origin
                ox, oy, oz = offset_origin(px, py, pz, nx, ny, nz, 1.0)
                qx, qy, qz = px + dist * wx, py + dist * wy, pz + dist * wz
                sx, sy, sz = qx - ox, qy - oy, qz - oz
                d = math.sqrt(sx * sx + sy * sy + sz * sz)
                count += 1
                if intersect_arrays(nodes, info, prims, tri, sph, stack, ox, oy, oz, sx / d,
                                    sy / d, sz / d, d * (1.0 - 1e-9), True)[1] < 0:
                    w = cos_i / pdf
                    er += lr * w
                    eg += lg * w
                    eb += lb * w
                    if n_batches > 0:
                        b = s % n_batches
                        irr_batches[i, b, 0] += lr * w / n_light
                        irr_batches[i, b, 1] += lg * w / n_light
                        irr_batches[i, b, 2] += lb * w / n_light
            er, eg, eb = er / n_light, eg / n_light, eb / n_light
        irradiance[i, 0] = er
        irradiance[i, 1] = eg
        irradiance[i, 2] = eb
        rays[i] = count


@kernel_parallel
def _jacobi_step(hits, weight, rho, source, offset, history, k):
    """history[k + 1] = source + rho F (history[k] - offset), rows in parallel."""
    n = hits.shape[1]
    for i in prange(hits.shape[0]):
        for c in range(3):
            acc = 0.0
            for s in range(n):
                j = hits[i, s]
                if j >= 0:
                    acc += weight[s] * (history[k, j, c] - offset[j, c])
            history[k + 1, i, c] = source[i, c] + rho[i, c] * acc


@kernel
def _change(history, k):
    """(max |B(k+1) - B(k)|, max |B(k+1) - B(0)|) over all entries: the
    change against the reflected radiosity (emitters would dwarf it)."""
    d, m = 0.0, 0.0
    for i in range(history.shape[1]):
        for c in range(3):
            d = max(d, abs(history[k + 1, i, c] - history[k, i, c]))
            m = max(m, abs(history[k + 1, i, c] - history[0, i, c]))
    return d, m


@kernel
def solve_jacobi(hits, weight, rho, emit, source, offset, tol, history):
    """Jacobi iteration B(k+1) = source + rho F (B(k) - offset) from B(0) =
    emit: iteration k adds the k-th bounce, so history[k] is the solution
    with at most k reflections (the depth convention). Stops after
    history.shape[0] - 1 iterations or when max|B(k+1) - B(k)| <= tol
    max|B(k+1) - E|; returns the last k written."""
    for i in range(emit.shape[0]):
        for c in range(3):
            history[0, i, c] = emit[i, c]
    k_max = history.shape[0] - 1
    for k in range(k_max):
        _jacobi_step(hits, weight, rho, source, offset, history, k)
        d, m = _change(history, k)
        if d <= tol * m:
            return k + 1
    return k_max


@kernel
def solve_gauss_seidel(hits, weight, rho, source, offset, tol, max_sweeps, b):
    """Gauss-Seidel: b_i = source_i + rho_i (F (b - offset))_i in place, patch
    order, until a sweep changes nothing by more than tol max|b|. `b` holds
    the start value; returns the sweeps done."""
    for sweep in range(max_sweeps):
        d, m = 0.0, 0.0
        for i in range(b.shape[0]):
            for c in range(3):
                acc = 0.0
                for s in range(hits.shape[1]):
                    j = hits[i, s]
                    if j >= 0:
                        acc += weight[s] * (b[j, c] - offset[j, c])
                v = source[i, c] + rho[i, c] * acc
                d = max(d, abs(v - b[i, c]))
                m = max(m, abs(v))
                b[i, c] = v
        if d <= tol * m:
            return sweep + 1
    return max_sweeps


@kernel
def solve_progressive(col_start, col_src, col_weight, rho, area, tol, max_shots, y, unshot):
    """Progressive refinement (Cohen et al. 1988, Southwell shooting) of
    Y = S + rho F Y (Y = B - offset, S = source - offset): `y` and `unshot`
    both start at S. The patch j with the most unshot power (sum over
    channels of unshot_j A_j) shoots: every patch i gains rho_i F_ij unshot_j,
    with F_ij from i's own rays (the transposed hit lists: col_src[col_start[j]
    : col_start[j + 1]] are the patches one of whose rays reached j, once per
    ray, with the ray's weight in col_weight), so all three solvers solve the
    same system. Stops when the largest
    unshot power is <= tol times the first one; returns the shots done."""
    first = -1.0
    for shot in range(max_shots):
        best, best_p = -1, -1.0
        for j in range(y.shape[0]):
            p = (abs(unshot[j, 0]) + abs(unshot[j, 1]) + abs(unshot[j, 2])) * area[j]
            if p > best_p:
                best, best_p = j, p
        if first < 0.0:
            first = best_p
        if best_p <= tol * first or best_p == 0.0:
            return shot
        j = best
        ur, ug, ub = unshot[j, 0], unshot[j, 1], unshot[j, 2]
        unshot[j, 0], unshot[j, 1], unshot[j, 2] = 0.0, 0.0, 0.0
        for e in range(col_start[j], col_start[j + 1]):
            i = col_src[e]
            w = col_weight[e]
            dr, dg, db = rho[i, 0] * ur * w, rho[i, 1] * ug * w, rho[i, 2] * ub * w
            y[i, 0] += dr
            y[i, 1] += dg
            y[i, 2] += db
            unshot[i, 0] += dr
            unshot[i, 1] += dg
            unshot[i, 2] += db
    return max_shots
