"""Photon mapping: stochastic progressive photon mapping (default) and the
classic one-pass photon map with k-nearest-neighbour density estimation.

`photon` with `mode=sppm` (default) is Hachisuka & Jensen's stochastic
progressive photon mapping (2009), modelled on pbrt-v3's SPPMIntegrator.
Each iteration i (spp = iterations) has
- a camera pass: one camera sample per pixel (sample index i of the job's
  pixel sampler) follows mirrors and glass up to `depth` and stops at the
  first diffuse or glossy surface, the *visible point*. Emission seen along
  that specular chain (including at the visible point) and direct light at
  the visible point (a shadow ray to a point from `sample_light`, no MIS:
  emission found later is never counted by the camera pass) form the direct
  estimate Ld_i;
- a photon pass: `photons` photons leave the lights (`sample_emission`,
  random numbers from `stream_key(seed, STREAM_PHOTONS, g)` with the global
  photon index g = i * photons + j), bounce with adjoint BSDFs (no 1/eta^2
  on refraction: importance transport) and Russian roulette (survival =
  max(new throughput) / max(old), so photon power stays level), and are
  recorded at every diffuse or glossy hit except the first (the first hit is
  direct light, which the camera pass estimates); each record keeps the
  position, the travelling direction, the power and the hit count k;
- a gather: each visible point sums f(wo, wi) * power over the photons
  within its radius r that arrive from the front side of its surface (one
  sided: photons from behind are neither in M nor in Phi) and whose path is
  not too long (k + specular bounces before the visible point <= depth), then
  N' = N + alpha M, r'^2 = r^2 (N + alpha M) / (N + M),
  tau' = (tau + Phi) r'^2 / r^2 with alpha = 2/3 (`sppm_update`).
The final estimate is L = sum(Ld_i) / n + tau / (n * photons * pi r^2).

Depth: a photon's k counts its surface hits from the light, so a photon
gathered at a visible point reached after b specular bounces closes a path of
k + b bounces (pbrt's depth); direct light is k = 1 and emission is k = 0, as
in `path-mis`.

Radius: the `radius` option, or (0, auto) 1/100 of the scene's bounding box
diagonal. Photons per iteration: `photons`, or (0, auto) pbrt's default of
one per pixel with at least 16384.

Farm plan (DAG, family "photons", phases ("photons", "gather")): iterations
are grouped `iterations_per_unit` at a time (0 = auto: at most 16 groups;
1 = one gather round per iteration). For each group: `photons` units (each
a range of global photon indices of one iteration, at most 2^16 photons; the
region is 0x0, the result is the photon array as the artefact `photon_pos`,
`photon_dir`, `photon_power` (float32) and `photon_k`), then one `gather`
unit per tile that needs the group's photon units and the same tile's gather
unit of the previous group, whose per-pixel state (N, r2, tau, ld, s1, s2, M)
travels as artefacts. Every gather unit covers its tile, and its film is the
*change* of the tile's estimate over its round: the estimate film after the
round (see Variance) minus the one the previous round's state gives. The
merge (plain addition, in unit order) telescopes these to the final
estimate, equal to it up to float rounding (and bit-identical whatever the
tile size or the workers: each pixel sees the same additions in the same
order), while the service's running preview, which adds the units that have
landed, shows each round's estimate as it lands instead of nothing until
the last. `stats["samples"]` of a gather unit is pixels x iterations, so a
job totals width * height * spp.

Data volume: a photon record is 40 bytes (float32 position, direction and
power, int32 k); cornell-box at depth 5 stores about one record per emitted
photon (2.7 MB per 65536-photon unit). Every gather tile of a group reads all
of the group's photon units, so a 256x256, 256-iteration job with 64-pixel
tiles moves about 16 x 16 x 43 MB = 11 GB of inputs to gather units and
stores 0.7 GB of photon results; larger tiles divide the first figure.

Gather acceleration: a uniform hash grid over the photons (pbrt-v3 hashes
visible points instead), cell size = the initial radius (radii only shrink,
so a visible point's sphere overlaps at most 2x2x2 cells), photons sorted
into buckets by a stable counting sort, each photon tagged with its integer
cell so hash collisions never count a photon twice. Photons outside the
tile's visible points' bounding box (grown by the largest radius) are not
inserted. The summation order (cells in coordinate order, photons in index
order) does not depend on the tile, so results are bit-identical whatever
the tile size or the number of workers.

Bias (measured). The finite radius blurs, and where two surfaces meet (a
corner, a door jamb, the ceiling beside a light) a visible point also
gathers photons that landed on the other surface and arrive from its front
side, so such places read too bright. The bias shrinks with the radius, as
SPPM's consistency promises, but slowly (r^2 falls about as n^(-1/3)). On
`door-ajar` (48x48, depth 5, 256 iterations), against BDPT's image mean
0.0733 +- 0.0005 (R): radius 0.1 gives 0.0803 (+9.5 %), the default
(diagonal / 100 = 0.049) 0.0768 (+4.8 %), radius 0.02 0.0744 +- 0.0012
(+1.5 %). Lower `radius` where corners matter; it costs variance.

Variance (the EXR's var.R/G/B): from the per-iteration estimates
X_i = Ld_i + Phi_i / (photons * pi r_i^2), whose sums s1 = sum X_i and
s2 = sum X_i^2 travel with the state. Var(L) is estimated as the batch-means
variance of the X_i: (s2 - s1^2 / n) / ((n - 1) n). Assumptions: iterations
are independent (each has its own camera samples and photons; the radius
they share through the state makes them weakly dependent) and the final
progressive estimate has about the variance of the plain average of the X_i
(it weights the photon part a little differently). It ignores the bias of
the finite radius (which vanishes as n grows). The estimate film
(`_estimate_film`, what the gather films telescope to) encodes weight = n,
sum = n L and sum_sq = n L^2 + (s2 - s1^2 / n), so
`Film.mean()` returns L and `Film.variance_of_mean()` returns that estimate
(+inf for n = 1). Measured over 24 seeds (16x16, 16 iterations, depth 3):
estimated / empirical per-pixel variance 1.02 (furnace-point) and 0.86
(cornell-box, median 1.04). Pixels are not independent (one photon path
deposits at several places, neighbouring visible points share photons), so
the sum of pixel variances underestimates the variance of an image average
(by 1.2x on the furnace, 1.7x on cornell-box in those runs).

`mode=photonmap` is Jensen's classic photon map: one photon pass of
`photons` photons (0 = auto: 4 per pixel, at least 65536), then gather tiles
with spp camera samples per pixel. The photon map is *visualised directly*
at the first diffuse or glossy hit (no final gather): L = emission along the
specular chain + direct light by light sampling + the k-nearest-neighbour
density estimate of indirect light, sum f * power / (photons * pi r_k^2),
with the `k` nearest front-side photons within the maximum search radius
`radius` (0 = auto: 1/40 of the scene diagonal; r_k = that radius if fewer
than k photons are found). It is biased and not consistent at a fixed photon
count; the film's variance is the camera samples' variance given the photon
map (the photon map's own noise is a fixed error pattern and is not in it).
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ..film import PartialFilm
from ..kernels import kernel, kernel_inline, kernel_parallel
from ..kernels.bsdf import (
    MAT_DIFFUSE,
    MAT_GLOSSY,
    MAT_MIRROR,
    dielectric_sample,
    diffuse_eval,
    diffuse_sample,
    reflect,
)
from ..kernels.camera import camera_ray
from ..kernels.geometry import (
    STACK_SIZE,
    intersect_arrays,
    offset_origin,
    shadow_ray,
    surface_at_arrays,
)
from ..kernels.ggx import glossy_eval, glossy_sample
from ..kernels.lights import sample_emission, sample_light
from ..kernels.rng import STREAM_PHOTONS, sample_key, stream_key, uniform
from ..kernels.sampling import INV_PI
from ..plan import Unit
from ..registry import SAMPLERS, Method, Option
from ..samplers import DIMS_PER_BOUNCE, u1d, u2d
from ..scene import camera_array

__all__ = ["ALPHA", "sppm_update", "plan_photon", "run_photon", "photons_per_iteration",
           "initial_radius", "trace_photons", "build_grid", "gather_pass"]

ALPHA = 2.0 / 3.0
PHOTON_UNIT_MAX = 1 << 16  # photons per photon unit at most
MAX_GROUPS = 16  # auto iterations_per_unit: at most this many gather rounds
# Random dimensions of a photon: 0 the light, 1-4 the emitted ray, then 4 per
# hit h >= 1 at 5 + 4 (h - 1): +0..1 the direction, +2 glass, +3 roulette.
PHOTON_DIMS, DIMS_PER_PHOTON_HIT = 5, 4
SPPM, PHOTONMAP = "sppm", "photonmap"


# ----------------------------------------------------------------- photons

@kernel
def trace_photons(sc, stack, seed, g0, g1, depth, pos, dirs, power, hits):
    """Trace photons g0..g1-1 (global indices) and record them at every
    diffuse or glossy hit from the second on (front side only) up to hit
    `depth`. Returns (records, rays); records = -1 if the buffers are full."""
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    tri_n, tri_mat, tri_light = sc.tri_n, sc.tri_mat, sc.tri_light
    sph_flip, sph_mat, sph_light = sc.sph_flip, sc.sph_mat, sc.sph_light
    mat_type, mat_rgb, mat_param = sc.mat_type, sc.mat_rgb, sc.mat_param
    cap = pos.shape[0]
    n = 0
    rays = 0
    if sc.light_type.shape[0] == 0 or depth < 2:
        return 0, 0
    for g in range(g0, g1):
        key = stream_key(seed, STREAM_PHOTONS, g)
        (li, prim, ox, oy, oz, nx, ny, nz, dx, dy, dz, er, eg, eb, pdf_pos, pdf_dir,
         delta) = sample_emission(sc, uniform(key, 0), uniform(key, 1), uniform(key, 2),
                                  uniform(key, 3), uniform(key, 4))
        if pdf_pos <= 0.0 or pdf_dir <= 0.0:
            continue
        if delta:
            k = 1.0 / (pdf_pos * pdf_dir)
        else:
            k = abs(nx * dx + ny * dy + nz * dz) / (pdf_pos * pdf_dir)
            ox, oy, oz = offset_origin(ox, oy, oz, nx, ny, nz, 1.0)
        br, bg, bb = er * k, eg * k, eb * k
        for hit in range(1, depth + 1):
            t, p = intersect_arrays(nodes, info, prims, tri, sph, stack,
                                    ox, oy, oz, dx, dy, dz, np.inf, False)
            rays += 1
            if p < 0:
                break
            hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
            nx, ny, nz, mat, light = surface_at_arrays(tri_n, tri_mat, tri_light, sph, sph_flip,
                                                       sph_mat, sph_light, p, hx, hy, hz)
            cos_in = -(dx * nx + dy * ny + dz * nz)
            mtype = mat_type[mat]
            base = PHOTON_DIMS + DIMS_PER_PHOTON_HIT * (hit - 1)
            side = 1.0
            if mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY:
                if cos_in <= 0.0:
                    break  # one-sided: the back of a diffuse or glossy surface absorbs
                if hit >= 2:
                    if n >= cap:
                        return -1, rays
                    pos[n, 0], pos[n, 1], pos[n, 2] = hx, hy, hz
                    dirs[n, 0], dirs[n, 1], dirs[n, 2] = dx, dy, dz
                    power[n, 0], power[n, 1], power[n, 2] = br, bg, bb
                    hits[n] = hit
                    n += 1
                if hit == depth:
                    break
                ua, ub = uniform(key, base), uniform(key, base + 1)
                ar, ag, ab = mat_rgb[mat, 0], mat_rgb[mat, 1], mat_rgb[mat, 2]
                if mtype == MAT_DIFFUSE:
                    wx, wy, wz, cos_w, pdf = diffuse_sample(nx, ny, nz, ua, ub)
                    sr, sg, sb = ar, ag, ab
                else:  # GGX is symmetric: sampling about -d gives f |cos wo| / pdf
                    wx, wy, wz, sr, sg, sb, pdf = glossy_sample(
                        nx, ny, nz, -dx, -dy, -dz, mat_param[mat, 1], ar, ag, ab, ua, ub)
                if pdf <= 0.0:
                    break
                dx, dy, dz = wx, wy, wz
            elif mtype == MAT_MIRROR:
                if cos_in <= 0.0 or hit == depth:
                    break
                dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
                sr, sg, sb = mat_rgb[mat, 0], mat_rgb[mat, 1], mat_rgb[mat, 2]
            else:  # dielectric: importance transport, no 1/eta^2, weight 1
                if hit == depth:
                    break
                dx, dy, dz, w, es, side = dielectric_sample(
                    dx, dy, dz, nx, ny, nz, mat_param[mat, 0], uniform(key, base + 2))
                sr, sg, sb = 1.0, 1.0, 1.0
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, side)
            m_old = max(br, max(bg, bb))
            nr, ng, nb = br * sr, bg * sg, bb * sb
            m_new = max(nr, max(ng, nb))
            if m_new <= 0.0:
                break
            if m_new < m_old:  # roulette: survive with m_new / m_old, power stays level
                q = m_new / m_old
                if uniform(key, base + 3) >= q:
                    break
                nr, ng, nb = nr / q, ng / q, nb / q
            br, bg, bb = nr, ng, nb
    return n, rays


# -------------------------------------------------------- visible points

@kernel_inline
def visible_point(sc, stack, ox, oy, oz, dx, dy, dz, depth, smp, key, seed, pixel, index, spp):
    """Follow a camera ray through mirrors and glass to the first diffuse or
    glossy surface. Returns (kmax, p, n, wo, beta, mat, Ld, rays): kmax =
    depth - specular bounces (the longest photon path k it may gather; -1
    when there is no visible point), Ld the emission seen along the chain
    plus direct light at the visible point by light sampling."""
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    tri_n, tri_mat, tri_light = sc.tri_n, sc.tri_mat, sc.tri_light
    sph_flip, sph_mat, sph_light = sc.sph_flip, sc.sph_mat, sc.sph_light
    light_rgb, mat_type, mat_rgb, mat_param = sc.light_rgb, sc.mat_type, sc.mat_rgb, sc.mat_param
    n_lights = sc.light_type.shape[0]
    lr, lg, lb = 0.0, 0.0, 0.0
    br, bg, bb = 1.0, 1.0, 1.0
    rays = 0
    kmax = -1
    hx, hy, hz, nx, ny, nz, mat = 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0
    for bounce in range(depth + 1):
        t, prim = intersect_arrays(nodes, info, prims, tri, sph, stack,
                                   ox, oy, oz, dx, dy, dz, np.inf, False)
        rays += 1
        if prim < 0:
            break
        hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
        nx, ny, nz, mat, light = surface_at_arrays(tri_n, tri_mat, tri_light, sph, sph_flip,
                                                   sph_mat, sph_light, prim, hx, hy, hz)
        cos_o = -(dx * nx + dy * ny + dz * nz)
        if light >= 0 and cos_o > 0.0:
            lr += br * light_rgb[light, 0]
            lg += bg * light_rgb[light, 1]
            lb += bb * light_rgb[light, 2]
        if bounce == depth:
            break
        base = 2 + DIMS_PER_BOUNCE * bounce
        mtype = mat_type[mat]
        if mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY:
            if cos_o <= 0.0:
                break
            if n_lights > 0:
                ua, ub = u2d(smp, key, seed, pixel, index, spp, base)
                wx, wy, wz, dist, pl, er, eg, eb, delta = sample_light(
                    sc, hx, hy, hz, u1d(smp, key, seed, pixel, index, spp, base + 4), ua, ub)
                cos_i = wx * nx + wy * ny + wz * nz
                if pl > 0.0 and cos_i > 0.0 and (er > 0.0 or eg > 0.0 or eb > 0.0):
                    if mtype == MAT_DIFFUSE:
                        f, pb = diffuse_eval(cos_o, cos_i)
                        fr, fg, fb = mat_rgb[mat, 0] * f, mat_rgb[mat, 1] * f, mat_rgb[mat, 2] * f
                    else:
                        fr, fg, fb, pb = glossy_eval(nx, ny, nz, -dx, -dy, -dz, wx, wy, wz,
                                                     mat_param[mat, 1], mat_rgb[mat, 0],
                                                     mat_rgb[mat, 1], mat_rgb[mat, 2])
                    sx, sy, sz, tx, ty, tz, tmax = shadow_ray(hx, hy, hz, nx, ny, nz, wx, wy, wz,
                                                              dist)
                    rays += 1
                    if (fr > 0.0 or fg > 0.0 or fb > 0.0) and intersect_arrays(
                            nodes, info, prims, tri, sph, stack, sx, sy, sz, tx, ty, tz, tmax,
                            True)[1] < 0:
                        w = cos_i / pl
                        lr += br * fr * er * w
                        lg += bg * fg * eg * w
                        lb += bb * fb * eb * w
            kmax = depth - bounce
            break
        elif mtype == MAT_MIRROR:
            if cos_o <= 0.0:
                break
            dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
            br *= mat_rgb[mat, 0]
            bg *= mat_rgb[mat, 1]
            bb *= mat_rgb[mat, 2]
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
        else:  # glass: radiance transport on the camera side (1/eta^2)
            dx, dy, dz, weight, es, side = dielectric_sample(
                dx, dy, dz, nx, ny, nz, mat_param[mat, 0],
                u1d(smp, key, seed, pixel, index, spp, base + 5))
            br *= weight
            bg *= weight
            bb *= weight
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, side)
    return kmax, hx, hy, hz, nx, ny, nz, -dx, -dy, -dz, br, bg, bb, mat, lr, lg, lb, rays


@kernel_parallel
def camera_pass(sc, cam, x0, y0, x1, y1, width, height, seed, index, spp, smp, depth,
                vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, ld, row_rays, stacks):
    """One camera sample (`index`) per pixel of the tile: its visible point and Ld."""
    ox, oy, oz = cam[0], cam[1], cam[2]
    for row in prange(y1 - y0):
        stack = stacks[row]
        y = y0 + row
        rays = 0
        for x in range(x0, x1):
            c = x - x0
            pixel = y * width + x
            key = sample_key(seed, pixel, index)
            fu, fv = u2d(smp, key, seed, pixel, index, spp, 0)
            dx, dy, dz = camera_ray(cam, width, height, x + fu, y + fv)
            (kmax, px, py, pz, nx, ny, nz, wx, wy, wz, br, bg, bb, mat, lr, lg, lb,
             nr) = visible_point(sc, stack, ox, oy, oz, dx, dy, dz, depth, smp, key, seed,
                                 pixel, index, spp)
            rays += nr
            vp_kmax[row, c] = kmax
            vp_p[row, c, 0], vp_p[row, c, 1], vp_p[row, c, 2] = px, py, pz
            vp_n[row, c, 0], vp_n[row, c, 1], vp_n[row, c, 2] = nx, ny, nz
            vp_wo[row, c, 0], vp_wo[row, c, 1], vp_wo[row, c, 2] = wx, wy, wz
            vp_beta[row, c, 0], vp_beta[row, c, 1], vp_beta[row, c, 2] = br, bg, bb
            vp_mat[row, c] = mat
            ld[row, c, 0], ld[row, c, 1], ld[row, c, 2] = lr, lg, lb
        row_rays[row] = rays


# ------------------------------------------------------------ hash grid

@kernel
def _hash(ix, iy, iz, mask):
    return ((ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791)) & mask


@kernel
def build_grid(ppos, inv_h, lo, hi, cell, bucket, start, cursor, order):
    """Counting-sort the photons inside the box [lo, hi] into hash buckets
    (table size len(start) - 1, a power of two). cell[i] = photon i's integer
    cell; order[start[b]:start[b+1]] = the photons of bucket b in index order.
    Returns the number inserted."""
    mask = start.shape[0] - 2
    start[:] = 0
    n = 0
    for i in range(ppos.shape[0]):
        x, y, z = ppos[i, 0], ppos[i, 1], ppos[i, 2]
        if x < lo[0] or y < lo[1] or z < lo[2] or x > hi[0] or y > hi[1] or z > hi[2]:
            bucket[i] = -1
            continue
        ix = np.int64(math.floor(x * inv_h))
        iy = np.int64(math.floor(y * inv_h))
        iz = np.int64(math.floor(z * inv_h))
        cell[i, 0], cell[i, 1], cell[i, 2] = ix, iy, iz
        b = _hash(ix, iy, iz, mask)
        bucket[i] = b
        start[b + 1] += 1
        n += 1
    for b in range(mask + 1):
        start[b + 1] += start[b]
    for b in range(mask + 1):
        cursor[b] = start[b]
    for i in range(ppos.shape[0]):
        b = bucket[i]
        if b >= 0:
            order[cursor[b]] = i
            cursor[b] += 1
    return n


@kernel_inline
def _photon_f(mat_type, mat_rgb, mat_param, mat, nx, ny, nz, wx, wy, wz, ix, iy, iz):
    """BSDF value at a visible point for a photon arriving along -wi."""
    if mat_type[mat] == MAT_DIFFUSE:
        return mat_rgb[mat, 0] * INV_PI, mat_rgb[mat, 1] * INV_PI, mat_rgb[mat, 2] * INV_PI
    fr, fg, fb, pdf = glossy_eval(nx, ny, nz, wx, wy, wz, ix, iy, iz, mat_param[mat, 1],
                                  mat_rgb[mat, 0], mat_rgb[mat, 1], mat_rgb[mat, 2])
    return fr, fg, fb


@kernel_parallel
def gather_pass(vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, r2, mat_type, mat_rgb, mat_param,
                ppos, pdir, ppow, phit, cell, start, order, inv_h, out_m, out_phi):
    """Every visible point sums beta f power over the photons within its
    radius sqrt(r2) that arrive from its front side with k <= kmax."""
    mask = start.shape[0] - 2
    for row in prange(vp_kmax.shape[0]):
        for c in range(vp_kmax.shape[1]):
            m = 0.0
            fr_s, fg_s, fb_s = 0.0, 0.0, 0.0
            kmax = vp_kmax[row, c]
            rr = r2[row, c]
            if kmax >= 2 and ppos.shape[0] > 0:
                px, py, pz = vp_p[row, c, 0], vp_p[row, c, 1], vp_p[row, c, 2]
                nx, ny, nz = vp_n[row, c, 0], vp_n[row, c, 1], vp_n[row, c, 2]
                wx, wy, wz = vp_wo[row, c, 0], vp_wo[row, c, 1], vp_wo[row, c, 2]
                mat = vp_mat[row, c]
                r = math.sqrt(rr)
                lx = np.int64(math.floor((px - r) * inv_h))
                ly = np.int64(math.floor((py - r) * inv_h))
                lz = np.int64(math.floor((pz - r) * inv_h))
                hx = np.int64(math.floor((px + r) * inv_h))
                hy = np.int64(math.floor((py + r) * inv_h))
                hz = np.int64(math.floor((pz + r) * inv_h))
                for ix in range(lx, hx + 1):
                    for iy in range(ly, hy + 1):
                        for iz in range(lz, hz + 1):
                            b = _hash(ix, iy, iz, mask)
                            for j in range(start[b], start[b + 1]):
                                q = order[j]
                                if cell[q, 0] != ix or cell[q, 1] != iy or cell[q, 2] != iz:
                                    continue
                                if phit[q] > kmax:
                                    continue
                                ex, ey, ez = ppos[q, 0] - px, ppos[q, 1] - py, ppos[q, 2] - pz
                                if ex * ex + ey * ey + ez * ez > rr:
                                    continue
                                ix_, iy_, iz_ = -pdir[q, 0], -pdir[q, 1], -pdir[q, 2]
                                if ix_ * nx + iy_ * ny + iz_ * nz <= 0.0:
                                    continue  # from behind the visible point's surface
                                fr, fg, fb = _photon_f(mat_type, mat_rgb, mat_param, mat,
                                                       nx, ny, nz, wx, wy, wz, ix_, iy_, iz_)
                                m += 1.0
                                fr_s += fr * ppow[q, 0]
                                fg_s += fg * ppow[q, 1]
                                fb_s += fb * ppow[q, 2]
            out_m[row, c] = m
            out_phi[row, c, 0] = vp_beta[row, c, 0] * fr_s
            out_phi[row, c, 1] = vp_beta[row, c, 1] * fg_s
            out_phi[row, c, 2] = vp_beta[row, c, 2] * fb_s


@kernel
def sppm_update(n, r2, tau, m, phi, alpha):
    """The progressive update of every pixel (Hachisuka & Jensen 2009):
    N' = N + alpha M, r'^2 = r^2 (N + alpha M) / (N + M),
    tau' = (tau + Phi) r'^2 / r^2; nothing changes where M = 0."""
    for i in range(n.shape[0]):
        for j in range(n.shape[1]):
            mm = m[i, j]
            if mm > 0.0:
                nn = n[i, j] + alpha * mm
                ratio = nn / (n[i, j] + mm)
                r2[i, j] = r2[i, j] * ratio
                for c in range(3):
                    tau[i, j, c] = (tau[i, j, c] + phi[i, j, c]) * ratio
                n[i, j] = nn


# ------------------------------------------------ k nearest neighbours

@kernel_parallel
def knn_render(sc, cam, x0, y0, x1, y1, width, height, seed, spp, smp, depth,
               ppos, pdir, ppow, phit, cell, start, order, inv_h, big_r2, k, n_emitted,
               out_sum, out_sq, out_w, row_rays, stacks, best_d, best_i):
    """Classic photon map, visualised directly at the visible point: Ld plus
    the k-nearest-neighbour estimate sum f power / (n_emitted pi r_k^2)."""
    ox, oy, oz = cam[0], cam[1], cam[2]
    mat_type, mat_rgb, mat_param = sc.mat_type, sc.mat_rgb, sc.mat_param
    mask = start.shape[0] - 2
    big_r = math.sqrt(big_r2)
    for row in prange(y1 - y0):
        stack = stacks[row]
        bd = best_d[row]
        bi = best_i[row]
        y = y0 + row
        rays = 0
        for x in range(x0, x1):
            c = x - x0
            pixel = y * width + x
            ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for s in range(spp):
                key = sample_key(seed, pixel, s)
                fu, fv = u2d(smp, key, seed, pixel, s, spp, 0)
                dx, dy, dz = camera_ray(cam, width, height, x + fu, y + fv)
                (kmax, px, py, pz, nx, ny, nz, wx, wy, wz, br, bg, bb, mat, lr, lg, lb,
                 nr) = visible_point(sc, stack, ox, oy, oz, dx, dy, dz, depth, smp, key, seed,
                                     pixel, s, spp)
                rays += nr
                if kmax >= 2 and ppos.shape[0] > 0:
                    cnt = 0
                    worst = big_r2
                    lx = np.int64(math.floor((px - big_r) * inv_h))
                    ly = np.int64(math.floor((py - big_r) * inv_h))
                    lz = np.int64(math.floor((pz - big_r) * inv_h))
                    hx = np.int64(math.floor((px + big_r) * inv_h))
                    hy = np.int64(math.floor((py + big_r) * inv_h))
                    hz = np.int64(math.floor((pz + big_r) * inv_h))
                    for ix in range(lx, hx + 1):
                        for iy in range(ly, hy + 1):
                            for iz in range(lz, hz + 1):
                                b = _hash(ix, iy, iz, mask)
                                for j in range(start[b], start[b + 1]):
                                    q = order[j]
                                    if cell[q, 0] != ix or cell[q, 1] != iy or cell[q, 2] != iz:
                                        continue
                                    if phit[q] > kmax:
                                        continue
                                    ex, ey, ez = ppos[q, 0] - px, ppos[q, 1] - py, ppos[q, 2] - pz
                                    d2 = ex * ex + ey * ey + ez * ez
                                    if d2 >= worst:
                                        continue
                                    if -(pdir[q, 0] * nx + pdir[q, 1] * ny + pdir[q, 2] * nz) <= 0.0:
                                        continue  # from behind the surface
                                    # insert into the sorted list (stable: after equals)
                                    pos_ = cnt if cnt < k else k - 1
                                    while pos_ > 0 and bd[pos_ - 1] > d2:
                                        if pos_ < k:
                                            bd[pos_] = bd[pos_ - 1]
                                            bi[pos_] = bi[pos_ - 1]
                                        pos_ -= 1
                                    bd[pos_] = d2
                                    bi[pos_] = q
                                    if cnt < k:
                                        cnt += 1
                                    if cnt == k:
                                        worst = bd[k - 1]
                    rk2 = bd[k - 1] if cnt == k else big_r2
                    sr_, sg_, sb_ = 0.0, 0.0, 0.0
                    for j in range(cnt):
                        q = bi[j]
                        fr, fg, fb = _photon_f(mat_type, mat_rgb, mat_param, mat, nx, ny, nz,
                                               wx, wy, wz, -pdir[q, 0], -pdir[q, 1], -pdir[q, 2])
                        sr_ += fr * ppow[q, 0]
                        sg_ += fg * ppow[q, 1]
                        sb_ += fb * ppow[q, 2]
                    if rk2 > 0.0:
                        scale = 1.0 / (n_emitted * math.pi * rk2)
                        lr += br * sr_ * scale
                        lg += bg * sg_ * scale
                        lb += bb * sb_ * scale
                ar += lr
                ag += lg
                ab += lb
                qr += lr * lr
                qg += lg * lg
                qb += lb * lb
            out_sum[row, c, 0], out_sum[row, c, 1], out_sum[row, c, 2] = ar, ag, ab
            out_sq[row, c, 0], out_sq[row, c, 1], out_sq[row, c, 2] = qr, qg, qb
            out_w[row, c] = spp
        row_rays[row] = rays


# ------------------------------------------------------------ plumbing

def _typed(options: dict) -> dict:
    """The checked options converted to their declared types (the CLI's
    --option KEY=VALUE passes strings; check_options does not convert)."""
    return {o.name: o.type(options[o.name]) for o in OPTIONS}


def photons_per_iteration(spec, options: dict) -> int:
    """Photons of one iteration (sppm) or of the whole map (photonmap)."""
    if options["photons"] > 0:
        return int(options["photons"])
    if options["mode"] == PHOTONMAP:
        return max(65536, 4 * spec.width * spec.height)
    return max(16384, spec.width * spec.height)


def initial_radius(scene, options: dict) -> float:
    """The `radius` option, or (0) a fraction of the scene's bounding box
    diagonal: 1/100 for SPPM's initial radius, 1/40 for the k-NN search."""
    if options["radius"] > 0:
        return float(options["radius"])
    box = scene.arrays.bvh_nodes[0]
    diag = float(np.linalg.norm(box[3:6] - box[0:3]))
    return diag * (0.025 if options["mode"] == PHOTONMAP else 0.01)


def _iterations_per_unit(spec, options: dict) -> int:
    if options["iterations_per_unit"] > 0:
        return int(options["iterations_per_unit"])
    return max(1, -(-spec.spp // MAX_GROUPS))


def _tiles(spec) -> list[tuple[int, int, int, int]]:
    t = spec.tile_size
    return [(x, y, min(x + t, spec.width), min(y + t, spec.height))
            for y in range(0, spec.height, t) for x in range(0, spec.width, t)]


def _photon_ranges(total: int) -> list[tuple[int, int]]:
    parts = max(1, -(-total // PHOTON_UNIT_MAX))
    return [(total * i // parts, total * (i + 1) // parts) for i in range(parts)]


def plan_photon(spec, progressive: bool, options: dict) -> list[Unit]:
    """The DAG (module doc). `progressive` changes nothing: SPPM is
    progressive by construction (each gather round refines the image)."""
    options = _typed(options)
    n_photons = photons_per_iteration(spec, options)
    tiles = _tiles(spec)
    units: list[Unit] = []
    if options["mode"] == PHOTONMAP:
        needs = []
        for a, b in _photon_ranges(n_photons):
            needs.append(len(units))
            units.append(Unit(len(units), 0, 0, 0, 0, a, b, 0, 0, "photons"))
        for x0, y0, x1, y1 in tiles:
            units.append(Unit(len(units), x0, y0, x1, y1, 0, spec.spp, 0, 1, "gather",
                              tuple(needs)))
        return units
    group = _iterations_per_unit(spec, options)
    prev: list[int] | None = None
    for gi, i0 in enumerate(range(0, spec.spp, group)):
        i1 = min(i0 + group, spec.spp)
        needs = []
        for it in range(i0, i1):
            for a, b in _photon_ranges(n_photons):
                needs.append(len(units))
                units.append(Unit(len(units), 0, 0, 0, 0, it * n_photons + a, it * n_photons + b,
                                  gi, 2 * gi, "photons"))
        current = []
        for ti, (x0, y0, x1, y1) in enumerate(tiles):
            tile_needs = tuple(needs) + ((prev[ti],) if prev is not None else ())
            current.append(len(units))
            units.append(Unit(len(units), x0, y0, x1, y1, i0, i1, gi, 2 * gi + 1, "gather",
                              tile_needs))
        prev = current
    return units


def _run_photons(scene, spec, unit, options) -> PartialFilm:
    n = unit.sample_end - unit.sample_start
    # photon units never straddle iterations (photonmap: one "iteration" 0)
    iteration = unit.sample_start // photons_per_iteration(spec, options)
    depth = spec.depth
    cap = max(16, n * max(1, min(depth - 1, 4)))
    stack = np.empty(STACK_SIZE, np.int64)
    while True:
        pos = np.empty((cap, 3))
        dirs = np.empty((cap, 3))
        power = np.empty((cap, 3))
        hits = np.empty(cap, np.int32)
        count, rays = trace_photons(scene.arrays, stack, spec.seed, unit.sample_start,
                                    unit.sample_end, depth, pos, dirs, power, hits)
        if count >= 0:
            break
        cap *= 2
    film = PartialFilm.zeros(0, 0, 0, 0)
    film.artefact = {"photon_pos": pos[:count].astype(np.float32),
                     "photon_dir": dirs[:count].astype(np.float32),
                     "photon_power": power[:count].astype(np.float32),
                     "photon_k": hits[:count].copy(),
                     "iteration": np.array([iteration], np.int64)}
    film.stats.update(samples=0, rays=int(rays), photons=n)
    return film


def _photons_of(inputs: dict, needs, iteration: int | None):
    """The photon arrays of `iteration` (all iterations if None) from the
    inputs, concatenated in unit order (= photon index order)."""
    parts = [inputs[i].artefact for i in needs
             if "photon_pos" in inputs[i].artefact
             and (iteration is None or int(inputs[i].artefact["iteration"][0]) == iteration)]
    if not parts:
        return (np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 3)), np.empty(0, np.int32))
    return tuple(np.ascontiguousarray(np.concatenate([p[name] for p in parts]), dtype=dt)
                 for name, dt in (("photon_pos", np.float64), ("photon_dir", np.float64),
                                  ("photon_power", np.float64), ("photon_k", np.int32)))


class _Grid:
    """The buffers of `build_grid` for one photon array."""

    def __init__(self, ppos, cell_size, lo, hi):
        n = ppos.shape[0]
        size = 1 << max(4, int(n - 1).bit_length()) if n > 1 else 16
        self.inv_h = 1.0 / cell_size
        self.cell = np.zeros((n, 3), np.int64)
        bucket = np.empty(n, np.int64)
        self.start = np.zeros(size + 1, np.int64)
        cursor = np.empty(size, np.int64)
        self.order = np.zeros(n, np.int64)
        self.inserted = build_grid(ppos, self.inv_h, np.asarray(lo, np.float64),
                                   np.asarray(hi, np.float64), self.cell, bucket, self.start,
                                   cursor, self.order)


def _tile_of(spec, unit) -> tuple[int, int, int, int]:
    x0, y0 = unit.x0, unit.y0
    return x0, y0, min(x0 + spec.tile_size, spec.width), min(y0 + spec.tile_size, spec.height)


def _run_gather(scene, spec, unit, inputs, options) -> PartialFilm:
    x0, y0, x1, y1 = _tile_of(spec, unit)
    w, h = x1 - x0, y1 - y0
    sc = scene.arrays
    cam = camera_array(scene.camera, spec.width, spec.height)
    n_photons = photons_per_iteration(spec, options)
    r0 = initial_radius(scene, options)
    smp = SAMPLERS[spec.sampler].id
    prev = [inputs[i] for i in unit.needs if "N" in inputs[i].artefact]
    if prev:
        st = {k: v.copy() for k, v in prev[0].artefact.items()}
        before = _estimate_film(prev[0].artefact, float(unit.sample_start), n_photons, x0, y0)
    else:
        before = None
        st = {"N": np.zeros((h, w)), "r2": np.full((h, w), r0 * r0), "tau": np.zeros((h, w, 3)),
              "ld": np.zeros((h, w, 3)), "s1": np.zeros((h, w, 3)), "s2": np.zeros((h, w, 3)),
              "M": np.zeros((h, w))}
    vp_kmax = np.empty((h, w), np.int64)
    vp_p, vp_n, vp_wo, vp_beta = (np.empty((h, w, 3)) for _ in range(4))
    vp_mat = np.empty((h, w), np.int32)
    ld = np.empty((h, w, 3))
    phi = np.empty((h, w, 3))
    m = np.empty((h, w))
    row_rays = np.zeros(h, np.int64)
    stacks = np.empty((h, STACK_SIZE), np.int64)
    rays = 0
    for it in range(unit.sample_start, unit.sample_end):
        camera_pass(sc, cam, x0, y0, x1, y1, spec.width, spec.height, spec.seed, it, spec.spp,
                    smp, spec.depth, vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, ld, row_rays,
                    stacks)
        rays += int(row_rays.sum())
        ppos, pdir, ppow, phit = _photons_of(inputs, unit.needs, it)
        valid = vp_kmax >= 2
        if valid.any():
            rmax = math.sqrt(float(st["r2"][valid].max()))
            pts = vp_p[valid]
            lo, hi = pts.min(axis=0) - rmax, pts.max(axis=0) + rmax
        else:
            lo, hi = np.zeros(3), -np.ones(3)  # an empty box: nothing inserted
        grid = _Grid(ppos, r0, lo, hi)
        r2_before = st["r2"].copy()
        gather_pass(vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, st["r2"], sc.mat_type,
                    sc.mat_rgb, sc.mat_param, ppos, pdir, ppow, phit, grid.cell, grid.start,
                    grid.order, grid.inv_h, m, phi)
        x = ld + phi / (n_photons * math.pi * r2_before)[..., None]
        st["ld"] += ld
        st["s1"] += x
        st["s2"] += x * x
        st["M"] = m.copy()
        sppm_update(st["N"], st["r2"], st["tau"], m, phi, ALPHA)
    # The change of the tile's estimate over this round (module doc).
    film = _estimate_film(st, float(unit.sample_end), n_photons, x0, y0)
    if before is not None:
        film.weight -= before.weight
        film.sum -= before.sum
        film.sum_sq -= before.sum_sq
    film.artefact = st
    film.stats.update({"samples": w * h * (unit.sample_end - unit.sample_start), "rays": rays})
    return film


def _estimate_film(st: dict, n: float, n_photons: int, x0: int, y0: int) -> PartialFilm:
    """The tile's estimate after n iterations with state `st`, encoded so that
    `Film.mean()` is L and `Film.variance_of_mean()` its variance estimate:
    weight n, sum n L, sum_sq n L^2 + (s2 - s1^2 / n)."""
    h, w = st["N"].shape
    mean = st["ld"] / n + st["tau"] / (n * n_photons * math.pi * st["r2"])[..., None]
    film = PartialFilm.zeros(x0, y0, w, h)
    film.weight[:] = n
    film.sum[:] = n * mean
    film.sum_sq[:] = n * mean * mean + np.maximum(st["s2"] - st["s1"] * st["s1"] / n, 0.0)
    return film


def _run_knn(scene, spec, unit, inputs, options) -> PartialFilm:
    x0, y0, x1, y1 = unit.x0, unit.y0, unit.x1, unit.y1
    w, h = x1 - x0, y1 - y0
    n_photons = photons_per_iteration(spec, options)
    big_r = initial_radius(scene, options)
    k = int(options["k"])
    ppos, pdir, ppow, phit = _photons_of(inputs, unit.needs, None)
    grid = _Grid(ppos, big_r, np.full(3, -np.inf), np.full(3, np.inf))
    film = PartialFilm.zeros(x0, y0, w, h)
    row_rays = np.zeros(h, np.int64)
    stacks = np.empty((h, STACK_SIZE), np.int64)
    knn_render(scene.arrays, camera_array(scene.camera, spec.width, spec.height), x0, y0, x1, y1,
               spec.width, spec.height, spec.seed, spec.spp, SAMPLERS[spec.sampler].id,
               spec.depth, ppos, pdir, ppow, phit, grid.cell, grid.start, grid.order, grid.inv_h,
               big_r * big_r, k, float(n_photons), film.sum, film.sum_sq, film.weight, row_rays,
               stacks, np.empty((h, k)), np.empty((h, k), np.int64))
    film.stats.update(samples=unit.samples, rays=int(row_rays.sum()))
    return film


def run_photon(scene, spec, unit, inputs, options) -> PartialFilm:
    options = _typed(options)
    if unit.kind == "photons":
        return _run_photons(scene, spec, unit, options)
    if options["mode"] == PHOTONMAP:
        return _run_knn(scene, spec, unit, inputs, options)
    return _run_gather(scene, spec, unit, inputs, options)


OPTIONS = (
    Option("mode", str, SPPM, "sppm: stochastic progressive photon mapping (spp = "
           "iterations); photonmap: one photon pass, k-NN estimate at the first diffuse "
           "hit (direct visualisation, no final gather)", (SPPM, PHOTONMAP)),
    Option("photons", int, 0, "photons per iteration (sppm) or in the map (photonmap); "
           "0 = auto: one per pixel, at least 16384 (sppm); 4 per pixel, at least 65536 "
           "(photonmap)", bounds=(0, 1 << 26)),
    Option("radius", float, 0.0, "initial gather radius (sppm) or maximum k-NN search "
           "radius (photonmap) in scene units; 0 = auto: 1/100 (sppm) or 1/40 "
           "(photonmap) of the scene's bounding box diagonal", bounds=(0.0, None)),
    Option("k", int, 64, "photonmap: photons of the k-nearest-neighbour estimate",
           bounds=(1, 4096)),
    Option("iterations_per_unit", int, 0, "sppm: iterations per gather unit; 0 = auto "
           "(at most 16 gather rounds)", bounds=(0, 1 << 20)),
)

METHODS = (Method(
    name="photon",
    aliases=("sppm",),
    description="Photon mapping: stochastic progressive photon mapping (photon pass and "
                "gather per iteration, radius shrinking with alpha = 2/3), or the classic "
                "one-pass photon map with k-nearest-neighbour density estimation.",
    run=run_photon,
    options=OPTIONS,
    family="photons",
    plan=plan_photon,
    phases=("photons", "gather"),
),)
