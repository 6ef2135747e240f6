"""Light sampling for next event estimation, and the matching pdfs.

A light is picked uniformly (probability 1/L, as Mitsuba does), then:
- mesh area lights: a triangle by area, a uniform point on it (area pdf 1/A);
- sphere lights seen from outside: a direction uniform in the cone the sphere
  subtends (pdf 1/(2 pi (1 - cos theta_max)), pbrt's Sphere::Sample);
  from inside: a uniform point on the sphere (area pdf 1/(4 pi r^2));
- point lights: the position itself (a delta: pdf 1, no MIS).
Area pdfs are converted to solid angle with dist^2 / |cos theta_light|.
Area lights emit only from their front side.

`sample_light` makes both picks with the first number of the light point's
pair and rescales it to [0, 1) within the chosen share (sample reuse, as
Mitsuba's Scene::sample_emitter_direction and Mesh::sample_position do), so
a stratified pair stays stratified over all the lights' surfaces. Picking
from another dimension splits each pixel's well-spread light points among
lights and triangles at random. Measured on cornell-box (one rectangle
light, two triangles; `sobol`, 64 spp, 2026-11-27): the variance over six
seeds of the direct light (depth 1) fell by 11 % (7.95e-6 to 7.04e-6), of
depth 2 by 4 %, and the whole image's RMSE from 0.01076 to 0.01071
(bench/throughput.py): deep indirect light dominates that error. On
veach-mis (four sphere lights) the RMSE at 16 / 64 / 256 spp fell from
0.862 / 0.485 / 0.192 to 0.833 / 0.473 / 0.188.
"""

import math

from . import kernel, kernel_inline
from .sampling import (ONE_MINUS_EPS, cosine_hemisphere, onb, sincos_turn, to_world,
                       uniform_sphere, uniform_triangle)

LIGHT_MESH, LIGHT_SPHERE, LIGHT_POINT = 0, 1, 2


@kernel
def _sphere_front_normal(sph, sph_flip, s, qx, qy, qz):
    inv_r = (-1.0 if sph_flip[s] != 0 else 1.0) / sph[s, 3]
    return (qx - sph[s, 0]) * inv_r, (qy - sph[s, 1]) * inv_r, (qz - sph[s, 2]) * inv_r


@kernel
def _sample_sphere(sph, sph_flip, s, area, px, py, pz, u1, u2):
    """A point on sphere s as seen from p: (ok, q, front normal at q, pdf).
    From outside, the direction is uniform in the cone the sphere subtends
    and pdf is that solid-angle pdf, 1/(2 pi (1 - cos theta_max)); from
    inside, q is uniform on the sphere and pdf = 0 (the caller uses the area
    pdf 1/area). Kept out of line: it is cold code in most scenes, and
    inlining it made every light sample several times slower."""
    cx, cy, cz, r = sph[s, 0], sph[s, 1], sph[s, 2], sph[s, 3]
    fx, fy, fz = cx - px, cy - py, cz - pz
    dc2 = fx * fx + fy * fy + fz * fz
    if dc2 > r * r * 1.0000001:
        dc = math.sqrt(dc2)
        sin2_max = r * r / dc2
        cos_max = math.sqrt(max(0.0, 1.0 - sin2_max))
        one_minus_cos_max = sin2_max / (1.0 + cos_max)  # 1 - cos without cancellation
        cos_t = 1.0 - u1 * one_minus_cos_max
        sin2_t = max(0.0, 1.0 - cos_t * cos_t)
        # distance to the nearest intersection along the sampled direction
        dist = dc * cos_t - math.sqrt(max(0.0, r * r - dc2 * sin2_t))
        sin_t = math.sqrt(sin2_t)
        cos_p, sin_p = sincos_turn(u2)
        wx_l, wy_l = sin_t * cos_p, sin_t * sin_p
        ax, ay, az = fx / dc, fy / dc, fz / dc
        sx, sy, sz, tx, ty, tz = onb(ax, ay, az)
        wx = wx_l * sx + wy_l * tx + cos_t * ax
        wy = wx_l * sy + wy_l * ty + cos_t * ay
        wz = wx_l * sz + wy_l * tz + cos_t * az
        qx, qy, qz = px + dist * wx, py + dist * wy, pz + dist * wz
        nx, ny, nz = _sphere_front_normal(sph, sph_flip, s, qx, qy, qz)
        if nx * wx + ny * wy + nz * wz >= 0.0:  # the visible side faces away: emits nothing here
            return False, qx, qy, qz, nx, ny, nz, 0.0
        return True, qx, qy, qz, nx, ny, nz, 1.0 / (2.0 * math.pi * one_minus_cos_max)
    ux, uy, uz = uniform_sphere(u1, u2)
    qx, qy, qz = cx + r * ux, cy + r * uy, cz + r * uz
    nx, ny, nz = _sphere_front_normal(sph, sph_flip, s, qx, qy, qz)
    return True, qx, qy, qz, nx, ny, nz, 0.0


@kernel_inline
def _pick_light(n_lights, u):
    """A light picked uniformly by u, and u rescaled to [0, 1) within its share."""
    x = u * n_lights
    li = min(int(x), n_lights - 1)
    return li, min(x - li, ONE_MINUS_EPS)


@kernel_inline
def _pick_triangle(sc, light, u):
    """A triangle of the light by area (binary search of its area CDF), and
    u rescaled to [0, 1) within the triangle's share. The CDF's lower end
    is a select (a masked load), not a branch (sampling.concentric_disk
    has the measurement). The search's steps stay branches: written as
    selects, LLVM's x86 backend turned them back into a branch (its cmov
    converter does so for a select that carries a loop's state; the asm
    showed it), so each step, the only one for a quad light's two
    triangles, is a coin flip for the branch predictor either way. The
    if/else steps restored: +0.4 % cornell-box, +0.3 % veach-mis time
    together with path.py's counters taken out (AMD EPYC Zen 1, 2026-11-28,
    six pairs of processes), noise, the same film bytes.
    Measured and not kept (2026-11-28, Zen 4, cornell-box, six pairs of
    processes): the last eight entries counted (k += cdf[j] <= u, no
    branch) instead of searched, +1.3 % time."""
    first = sc.light_start[light]
    lo = first
    hi = lo + sc.light_count[light] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if sc.light_tri_cdf[mid] <= u:
            lo = mid + 1
        else:
            hi = mid
    prev = sc.light_tri_cdf[max(lo - 1, first)]
    c0 = prev if lo > first else 0.0
    return sc.light_tris[lo], min((u - c0) / (sc.light_tri_cdf[lo] - c0), ONE_MINUS_EPS)


@kernel_inline
def sample_light(sc, px, py, pz, u1, u2):
    """Sample an incident direction at point p towards a light: the light
    and its triangle picked by u1, reused for the point (module doc).

    Returns (wx, wy, wz, dist, pdf, Lr, Lg, Lb, delta): the unit direction
    to the light point, its distance, the pdf in solid angle (or the
    selection probability for point lights), the emitted radiance (or
    intensity / dist^2 for point lights) and whether it is a delta light.
    pdf == 0 means no contribution.
    """
    n_lights = sc.light_type.shape[0]
    li, u1 = _pick_light(n_lights, u1)
    p_pick = 1.0 / n_lights
    ltype = sc.light_type[li]
    if ltype == LIGHT_POINT:
        dx = sc.light_pos[li, 0] - px
        dy = sc.light_pos[li, 1] - py
        dz = sc.light_pos[li, 2] - pz
        d2 = dx * dx + dy * dy + dz * dz
        dist = math.sqrt(d2)
        if dist == 0.0:
            return 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, True
        inv = 1.0 / dist
        return (dx * inv, dy * inv, dz * inv, dist, p_pick,
                sc.light_rgb[li, 0] / d2, sc.light_rgb[li, 1] / d2, sc.light_rgb[li, 2] / d2, True)
    if ltype == LIGHT_MESH:
        tri, u1 = _pick_triangle(sc, li, u1)
        b0, b1 = uniform_triangle(u1, u2)
        b2 = 1.0 - b0 - b1
        qx = b0 * sc.tri_p[tri, 0, 0] + b1 * sc.tri_p[tri, 1, 0] + b2 * sc.tri_p[tri, 2, 0]
        qy = b0 * sc.tri_p[tri, 0, 1] + b1 * sc.tri_p[tri, 1, 1] + b2 * sc.tri_p[tri, 2, 1]
        qz = b0 * sc.tri_p[tri, 0, 2] + b1 * sc.tri_p[tri, 1, 2] + b2 * sc.tri_p[tri, 2, 2]
        nx, ny, nz = sc.tri_n[tri, 0], sc.tri_n[tri, 1], sc.tri_n[tri, 2]
        pdf_area = 1.0 / sc.light_area[li]
    else:
        ok, qx, qy, qz, nx, ny, nz, pdf_sa = _sample_sphere(
            sc.sph, sc.sph_flip, sc.light_sphere[li], sc.light_area[li], px, py, pz, u1, u2)
        if not ok:
            return 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, False
        if pdf_sa > 0.0:  # cone sampling gave a solid-angle pdf directly
            dx, dy, dz = qx - px, qy - py, qz - pz
            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
            inv = 1.0 / dist
            return (dx * inv, dy * inv, dz * inv, dist, p_pick * pdf_sa, sc.light_rgb[li, 0],
                    sc.light_rgb[li, 1], sc.light_rgb[li, 2], False)
        pdf_area = 1.0 / sc.light_area[li]
    dx, dy, dz = qx - px, qy - py, qz - pz
    d2 = dx * dx + dy * dy + dz * dz
    dist = math.sqrt(d2)
    if dist == 0.0:
        return 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, False
    inv = 1.0 / dist
    wx, wy, wz = dx * inv, dy * inv, dz * inv
    cos_l = -(nx * wx + ny * wy + nz * wz)
    if cos_l <= 0.0:  # back side of the emitter
        return 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, False
    pdf = p_pick * pdf_area * d2 / cos_l
    return wx, wy, wz, dist, pdf, sc.light_rgb[li, 0], sc.light_rgb[li, 1], sc.light_rgb[li, 2], False


@kernel_inline
def light_pdf(sc, light, prim, px, py, pz, qx, qy, qz, cos_l):
    """Solid-angle pdf with which `sample_light` at p would have produced the
    point q on `prim` of area light `light` (cos_l = cosine at q, > 0)."""
    n_lights = sc.light_type.shape[0]
    p_pick = 1.0 / n_lights
    dx, dy, dz = qx - px, qy - py, qz - pz
    d2 = dx * dx + dy * dy + dz * dz
    if sc.light_type[light] == LIGHT_SPHERE:
        s = sc.light_sphere[light]
        fx, fy, fz = sc.sph[s, 0] - px, sc.sph[s, 1] - py, sc.sph[s, 2] - pz
        dc2 = fx * fx + fy * fy + fz * fz
        r = sc.sph[s, 3]
        if dc2 > r * r * 1.0000001:
            sin2_max = r * r / dc2
            cos_max = math.sqrt(max(0.0, 1.0 - sin2_max))
            return p_pick / (2.0 * math.pi * (sin2_max / (1.0 + cos_max)))
    return p_pick * d2 / (cos_l * sc.light_area[light])


@kernel_inline
def sample_emission(sc, u_pick, u1, u2, u3, u4):
    """Sample a ray leaving a light (light tracing, BDPT's light subpaths,
    photons), the way pbrt's Light::SampleLe does.

    The light is picked uniformly (1/L, as for `sample_light`); then
    - mesh light: a triangle by area and a uniform point on it, a
      cosine-distributed direction about its front normal;
    - sphere light: a uniform point on the sphere, a cosine direction about
      its front normal there;
    - point light: its position, a uniform direction on the sphere.
    Returns (light, prim, ox, oy, oz, nx, ny, nz, dx, dy, dz, Le_r, Le_g, Le_b,
    pdf_pos, pdf_dir, delta): the light and primitive hit, the origin, the
    front normal (0 for point lights), the direction, the emitted radiance
    along it (the intensity for point lights), the area pdf of the origin
    including the pick (the pick probability alone for point lights) and
    the solid-angle pdf of the direction. The picks here take u_pick, not
    the point's number as `sample_light` does: the callers' primary sample
    layouts (subpaths.py) keep a number for it. The light subpath's first
    throughput is Le |cos| / (pdf_pos pdf_dir) (no cos for point lights).
    """
    n_lights = sc.light_type.shape[0]
    li, u_tri = _pick_light(n_lights, u_pick)
    p_pick = 1.0 / n_lights
    ltype = sc.light_type[li]
    if ltype == LIGHT_POINT:
        dx, dy, dz = uniform_sphere(u3, u4)
        return (li, -1, sc.light_pos[li, 0], sc.light_pos[li, 1], sc.light_pos[li, 2],
                0.0, 0.0, 0.0, dx, dy, dz, sc.light_rgb[li, 0], sc.light_rgb[li, 1],
                sc.light_rgb[li, 2], p_pick, 1.0 / (4.0 * math.pi), True)
    if ltype == LIGHT_MESH:
        tri, _ = _pick_triangle(sc, li, u_tri)
        b0, b1 = uniform_triangle(u1, u2)
        b2 = 1.0 - b0 - b1
        ox = b0 * sc.tri_p[tri, 0, 0] + b1 * sc.tri_p[tri, 1, 0] + b2 * sc.tri_p[tri, 2, 0]
        oy = b0 * sc.tri_p[tri, 0, 1] + b1 * sc.tri_p[tri, 1, 1] + b2 * sc.tri_p[tri, 2, 1]
        oz = b0 * sc.tri_p[tri, 0, 2] + b1 * sc.tri_p[tri, 1, 2] + b2 * sc.tri_p[tri, 2, 2]
        nx, ny, nz = sc.tri_n[tri, 0], sc.tri_n[tri, 1], sc.tri_n[tri, 2]
        prim = tri
    else:
        s = sc.light_sphere[li]
        ux, uy, uz = uniform_sphere(u1, u2)
        r = sc.sph[s, 3]
        ox, oy, oz = sc.sph[s, 0] + r * ux, sc.sph[s, 1] + r * uy, sc.sph[s, 2] + r * uz
        nx, ny, nz = _sphere_front_normal(sc.sph, sc.sph_flip, s, ox, oy, oz)
        prim = sc.tri_p.shape[0] + s
    lx, ly, lz = cosine_hemisphere(u3, u4)
    dx, dy, dz = to_world(lx, ly, lz, nx, ny, nz)
    return (li, prim, ox, oy, oz, nx, ny, nz, dx, dy, dz, sc.light_rgb[li, 0], sc.light_rgb[li, 1],
            sc.light_rgb[li, 2], p_pick / sc.light_area[li], lz / math.pi, False)


@kernel_inline
def emission_pdfs(sc, light, cos_l):
    """(pdf_pos, pdf_dir) with which `sample_emission` produces a ray leaving
    area light `light` at any point with cosine `cos_l` to its front normal
    (pdf_dir 0 behind it); point lights: (pick probability, 1/(4 pi))."""
    p_pick = 1.0 / sc.light_type.shape[0]
    if sc.light_type[light] == LIGHT_POINT:
        return p_pick, 1.0 / (4.0 * math.pi)
    return p_pick / sc.light_area[light], max(cos_l, 0.0) / math.pi
