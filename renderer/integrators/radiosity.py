"""`radiosity`: finite element radiosity, solved once, displayed by tiles.

| option | type | default | meaning |
|---|---|---|---|
| `patch_size` | float | 0 (auto) | patch edge length in world units (triangles split into k x k, k = ceil(second-longest edge / patch_size); sphere zones about patch_size on a side); 0 = the scene's bounding-box diagonal / (20 sqrt 3): 0.1 on cornell-box (a box of side 2), 1.6 on veach-mis; a job cutting its scene into more than MAX_PATCHES = 250,000 patches, or patches x rays per patch above MAX_HITS = 2^28, is refused at submission (`check_scene`) |
| `form_factors` | str | `montecarlo` | how F is estimated, both with visibility: `montecarlo` (area-to-area ray casting) or `hemicube` (point-to-area from each patch's centre, rays through the pixels of a hemicube) |
| `ff_rays` | int | 512 | Monte Carlo form-factor rays per patch, and light samples per patch (both estimators) |
| `hemicube_res` | int | 32 | hemicube resolution: res x res top face, 4 res x res/2 sides, so 3 res^2 rays per patch |
| `solver` | str | `jacobi` | `jacobi` (one bounce per iteration: honours `depth`), `gauss-seidel`, `progressive` (Southwell shooting) |
| `tolerance` | float | 1e-4 | stop when an iteration changes B by at most tolerance x the largest reflected radiosity max(B - E) (progressive: when the largest unshot power is tolerance x the first) |
| `direct` | str | `sampled` | first bounce: `sampled` = light sampling with shadow rays from every patch (area and point lights), `formfactor` = emitting patches shine through F like any patch (the textbook; point lights still sampled) |
| `display` | str | `flat` | `flat`: each pixel shows B / pi of its patch; `smooth`: Gouraud, B interpolated over the triangle patch from its vertices, each the area-weighted mean of the patches around it that share its normal, albedo and emission (sphere zones stay flat) |
| `final_gather` | str | `off` | `on`: at the visible diffuse point, emission + light sampling + one cosine-sampled ray into the patch solution's reflected part |

The method. Diffuse surfaces and every emitter are meshed into patches
(flat triangles; analytic spheres into equal-area zones: z bands split in
longitude, so no tessellation error in the geometry). Each patch i has its
albedo rho_i (0 for an emitter whose material is not diffuse), its emission
E_i = pi Le (radiance -> radiosity; front side only, as area lights emit)
and a constant radiosity B_i (W/m^2), solving

    B = E + D + rho F (B - X)

F is estimated by ray casting (kernels/radiosity.py): Monte Carlo, the
fraction of cosine-distributed rays from uniform points of i that reach the
front of j (unbiased for the area-to-area F_ij; rows of a closed scene sum
to 1 exactly; reciprocity A_i F_ij = A_j F_ji holds only within the noise:
we do not symmetrise, which would break the row sums), or a hemicube at
the centre of i whose pixels are ray cast (deterministic, but a
point-to-area F from one point, with the hemicube's aliasing).
D is the radiosity reflected straight from the lights, rho x irradiance,
estimated at the same points by light sampling with shadow rays. With
`direct=sampled` (default) D covers every light and X = E, so light leaves
emitters only through D (far less noise than counting the few rays that hit
a small light); with `direct=formfactor` D covers point lights only and X =
0, so emitters shine through F. Point lights are no patches: their direct
light enters as D, unshot radiosity of the patches they light.

Depth. B(0) = E and each Jacobi iteration adds one bounce, so B(k) holds the
light of at most k reflections: a camera ray reaching a patch after b
specular bounces shows B(depth - b) / pi, which is what `path-mis` at the
same depth sees (exactly so on the furnace scenes). The solve keeps every
B(k) up to convergence or 64 (the largest depth), so one solution serves
every depth. `gauss-seidel` and `progressive` have no bounce structure: they
store B(0) = E and the converged B, i.e. they honour depth 0 and "all".

Display. Tile units trace camera rays; mirrors and glass (and glossy
surfaces, by sampling their lobe) are followed from the camera as in
`direct`, each using one bounce of the depth; the first patch reached shows
its radiance B / pi (front side; the back of a one-sided surface is black).
With `final_gather=on`, the visible diffuse point x shows instead its own
emission, direct light by light sampling (all lights, exactly as path-mis's
NEE) and rho_x times the reflected radiance (B - E) / pi of the patch a
cosine-sampled ray from x reaches (full B / pi if that ray went through
mirrors or glass first, since light sampling cannot see through them). That
removes the patches' blockiness from direct light and hides the mesh in
indirect light; gather rays that pass through mirrors or glass to a light
also bring caustics onto the visible surfaces (noisily, as path tracing
does). `display=smooth` (without final gather) interpolates B over each
triangle patch from welded vertex values (Gouraud): no visible patches, the
same bias. Samples per pixel average the film position (anti-aliasing)
and, with final gather, the gather; var.R/G/B come from them as in tile
methods.

Specular surfaces (mirror, glass, glossy) are no patches: form-factor rays
that hit them count as lost, shadow rays are blocked by them (as in the path
tracers). So the solution has no caustics and no specular interreflection
(a diffuse wall sees no light through a mirror), and light passing through
glass does not reach patches behind it. Emitters are always patches (with
albedo 0 if their material is not diffuse). They appear in the image only by
what the camera sees through them.

Bias. Constant radiosity per patch (meshing) and a fixed set of form-factor
rays (their noise is frozen into the solution, the same for every pixel):
radiosity is consistent only as patch_size -> 0 and ff_rays -> inf. The
measured bias on cornell-box is in docs/radiosity.md.

Variance. The var channels hold both parts of a pixel's error over seeds:
the display samples' (film position, final gather), from their spread, and
the solution's, which every pixel shares and no spread of samples can see.
The solve also solves J = 8 delete-a-group jackknife replicates (each
without one batch of the form-factor rays and light samples, s % 8 == b,
the rest reweighted), and a tile sums, per pixel, each sample's change under
each replicate (the value is linear in B, so the change is the value read
from the replicate's changes of B); film.py turns those sums into the
jackknife variance (module doc, "Shared estimates"). Measured when written
(8 seeds, cornell-box 32 x 32, tests/test_renderer_variance.py): without the
solution's share the spread was 1.5 times the var channels' prediction. The
jackknife costs 8 more solves (not more rays) and J x 3 sums per pixel. The
form-factor directions are stratified, which the jackknife (made for
independent draws) cannot credit: where the form factors dominate, it may
overstate the variance.

Farm plan: unit 0 (kind "solve", a 0x0 region, 0 samples) meshes, casts the
form-factor rays and solves; its film carries the solution as the artefact
`radiosity` (B(k), k = 0..min(K, depth), shape (k + 1, P, 3) float64).
Solutions are cached by (scene hash, solution options, seed, code version) in-process (LRU) and on disk
in the renderer's "radiosity" cache (renderer/cache.py: `<cache root>/radiosity`, the farm's
`<data_dir>/cache/radiosity`, size-capped, least recently used evicted, written atomically),
so a second job on the same scene reuses it. Then the
ordinary tile plan, every unit needing unit 0.

The mesh, the form factors, the solve and its cache are
renderer/radiosity_solve.py; this module displays the solution and is the
method (its plan, options and submission checks).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numba import get_thread_id, prange

from ..errors import SpecError
from ..film import PartialFilm
from ..kernels import kernel, kernel_inline, kernel_parallel
from ..kernels.bsdf import (
    MAT_DIELECTRIC,
    MAT_DIFFUSE,
    MAT_GLOSSY,
    MAT_MIRROR,
    diffuse_sample,
    specular_step,
)
from ..kernels.camera import CAM_LENS, camera_ray_at, film_position
from ..kernels.geometry import (
    intersect_arrays,
    offset_origin,
    shadow_ray,
    surface_at_arrays,
)
from ..kernels.ggx import glossy_sample
from ..kernels.lights import sample_light
from ..kernels.radiosity import (
    patch_of,
)
from ..kernels.rng import sample_key
from ..kernels.tile import (add_aov_block, add_aov_sample, add_block, add_sample, n_samples,
                            store_aov, store_pixel)
from ..plan import Unit
from ..plan import plan as tile_plan
from ..primitives import world_mesh
from ..radiosity_solve import (
    MAX_HITS,
    MAX_PATCHES,
    SOLVERS,
    as_count,
    auto_patch_size,
    mesh,
    patch_size_of_bounds,
    patch_total,
    solution,
    vertex_radiosity,
    welded_vertices,
)
from ..registry import SAMPLERS, Method, Option
from ..samplers import DIM_BSDF, DIM_GLASS, DIM_LENS, DIM_LIGHT, DIMS_PER_BOUNCE, u1d, u2d
from ..scene_format import MAX_COORDINATE
from .tile import start_tile

# ---------------------------------------------------------------- display

@kernel_inline
def _patch_at(sc, pt, prim, hx, hy, hz):
    return patch_of(sc.tri_isect, pt.tri_start, pt.tri_k, pt.cells, sc.sph, pt.sph_start,
                    pt.sph_nz, pt.sph_nphi, prim, hx, hy, hz)


@kernel
def _patch_uv(geo, p, hx, hy, hz):
    """Barycentrics (u, v) of point h in triangle patch p (v0, e1, e2), clamped."""
    dx, dy, dz = hx - geo[p, 0], hy - geo[p, 1], hz - geo[p, 2]
    d11 = geo[p, 3] * geo[p, 3] + geo[p, 4] * geo[p, 4] + geo[p, 5] * geo[p, 5]
    d12 = geo[p, 3] * geo[p, 6] + geo[p, 4] * geo[p, 7] + geo[p, 5] * geo[p, 8]
    d22 = geo[p, 6] * geo[p, 6] + geo[p, 7] * geo[p, 7] + geo[p, 8] * geo[p, 8]
    d1 = dx * geo[p, 3] + dy * geo[p, 4] + dz * geo[p, 5]
    d2 = dx * geo[p, 6] + dy * geo[p, 7] + dz * geo[p, 8]
    den = d11 * d22 - d12 * d12
    u = min(max((d22 * d1 - d12 * d2) / den, 0.0), 1.0)
    v = min(max((d11 * d2 - d12 * d1) / den, 0.0), 1.0 - u)
    return u, v


@kernel_inline
def li_radiosity(sc, pt, hist, vert_b, patch_vert, stack, ox, oy, oz, dx, dy, dz, key, depth,
                 gather, smp, seed, pixel, index, spp, memo):
    """Radiance arriving at o from -d through the patch solution: (r, g, b,
    rays), the sample's AOVs as path tracing gives them (albedo and normal
    of the first diffuse or glossy hit through mirrors and glass, distance to
    the first hit), and where it read the solution, for the jackknife
    (`_jackknife_sample`): the B(k) index, the patch (-1: nowhere), whether
    at its vertices (smooth), the weights of its value (flat: 1/pi and 0, 0;
    smooth: its three vertices') and the RGB throughput they were read with."""
    k_last = hist.shape[0] - 1
    br, bg, bb = 1.0, 1.0, 1.0
    lr, lg, lb = 0.0, 0.0, 0.0
    rays = 0
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    n_lights = sc.light_type.shape[0]
    inv_pi = 1.0 / np.pi
    aov_set = False
    alb_r, alb_g, alb_b, an_x, an_y, an_z, first_t = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    look_k, look_p, look_smooth, wa, wb, wc = 0, -1, False, 0.0, 0.0, 0.0
    for bounce in range(depth + 1):
        t, prim = intersect_arrays(nodes, info, prims, tri, sph, stack, ox, oy, oz, dx, dy, dz,
                                   np.inf, False)
        rays += 1
        if prim < 0:
            break
        hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
        nx, ny, nz, mat, light = surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light, sph,
                                                   sc.sph_flip, sc.sph_mat, sc.sph_light,
                                                   prim, hx, hy, hz)
        if bounce == 0:
            first_t = t
        if not aov_set and (sc.mat_type[mat] == MAT_DIFFUSE or sc.mat_type[mat] == MAT_GLOSSY):
            aov_set = True
            alb_r, alb_g, alb_b = sc.mat_rgb[mat, 0], sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2]
            an_x, an_y, an_z = nx, ny, nz
        cos_o = -(dx * nx + dy * ny + dz * nz)
        p = _patch_at(sc, pt, prim, hx, hy, hz)
        left = depth - bounce
        base = 2 + DIMS_PER_BOUNCE * bounce
        if p >= 0:
            if cos_o <= 0.0:
                break  # one-sided: the back of a patch is black
            if gather == 0 or left == 0:
                k = min(left, k_last)
                look_k, look_p = k, p
                if vert_b.shape[1] > 0 and patch_vert[p, 0] >= 0:  # smooth: Gouraud
                    u, v = _patch_uv(pt.geo, p, hx, hy, hz)
                    w0 = (1.0 - u - v) * inv_pi
                    u, v = u * inv_pi, v * inv_pi
                    a, b, c = patch_vert[p, 0], patch_vert[p, 1], patch_vert[p, 2]
                    lr += br * (w0 * vert_b[k, a, 0] + u * vert_b[k, b, 0] + v * vert_b[k, c, 0])
                    lg += bg * (w0 * vert_b[k, a, 1] + u * vert_b[k, b, 1] + v * vert_b[k, c, 1])
                    lb += bb * (w0 * vert_b[k, a, 2] + u * vert_b[k, b, 2] + v * vert_b[k, c, 2])
                    wa, wb, wc, look_smooth = w0, u, v, True
                else:
                    lr += br * hist[k, p, 0] * inv_pi
                    lg += bg * hist[k, p, 1] * inv_pi
                    lb += bb * hist[k, p, 2] * inv_pi
                    wa = inv_pi
                break
            # final gather at x: emission, light sampling, one ray into the solution
            lr += br * pt.emit[p, 0] * inv_pi
            lg += bg * pt.emit[p, 1] * inv_pi
            lb += bb * pt.emit[p, 2] * inv_pi
            ar, ag, ab = pt.rho[p, 0], pt.rho[p, 1], pt.rho[p, 2]
            if n_lights > 0:
                ua, ub = u2d(smp, key, seed, pixel, index, spp, base + DIM_LIGHT, memo)
                wx, wy, wz, dist, pl, er, eg, eb, delta = sample_light(sc, hx, hy, hz, ua, ub)
                cos_i = wx * nx + wy * ny + wz * nz
                if pl > 0.0 and cos_i > 0.0:
                    sx, sy, sz, tx, ty, tz, tmax = shadow_ray(hx, hy, hz, nx, ny, nz, wx, wy, wz,
                                                              dist)
                    rays += 1
                    if intersect_arrays(nodes, info, prims, tri, sph, stack, sx, sy, sz,
                                        tx, ty, tz, tmax, True)[1] < 0:
                        w = cos_i * inv_pi / pl
                        lr += br * ar * er * w
                        lg += bg * ag * eg * w
                        lb += bb * ab * eb * w
            ua, ub = u2d(smp, key, seed, pixel, index, spp, base + DIM_BSDF, memo)
            gx, gy, gz, cos_g, pdf = diffuse_sample(nx, ny, nz, ua, ub)
            br, bg, bb = br * ar, bg * ag, bb * ab  # f cos / pdf = albedo
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
            dx, dy, dz = gx, gy, gz
            specular = False
            for g in range(bounce + 1, depth + 1):
                t, prim = intersect_arrays(nodes, info, prims, tri, sph, stack, ox, oy, oz,
                                           dx, dy, dz, np.inf, False)
                rays += 1
                if prim < 0:
                    break
                hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
                nx, ny, nz, mat, light = surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light,
                                                           sph, sc.sph_flip, sc.sph_mat,
                                                           sc.sph_light, prim, hx, hy, hz)
                cos_o = -(dx * nx + dy * ny + dz * nz)
                q = _patch_at(sc, pt, prim, hx, hy, hz)
                if q >= 0:
                    if cos_o > 0.0:
                        k = min(depth - g, k_last)
                        er, eg, eb = hist[k, q, 0], hist[k, q, 1], hist[k, q, 2]
                        if not specular:  # direct light was sampled at x
                            er -= pt.emit[q, 0]
                            eg -= pt.emit[q, 1]
                            eb -= pt.emit[q, 2]
                        lr += br * er * inv_pi
                        lg += bg * eg * inv_pi
                        lb += bb * eb * inv_pi
                        look_k, look_p, wa = k, q, inv_pi  # flat lookup (E cancels in changes)
                    break
                if g == depth:
                    break
                mtype = sc.mat_type[mat]
                if (mtype == MAT_MIRROR and cos_o > 0.0) or mtype == MAT_DIELECTRIC:
                    u = 0.0 if mtype == MAT_MIRROR else u1d(smp, key, seed, pixel, index, spp,
                                                            2 + DIMS_PER_BOUNCE * g + DIM_GLASS,
                                                            memo)
                    dx, dy, dz, ox, oy, oz, wr, wg, wb, _es = specular_step(
                        mtype, sc.mat_rgb[mat, 0], sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2],
                        sc.mat_param[mat, 0], hx, hy, hz, nx, ny, nz, dx, dy, dz, u)
                    br, bg, bb = br * wr, bg * wg, bb * wb
                else:
                    break  # glossy ends a gather ray (documented)
                specular = True
            break
        if left == 0:
            break
        mtype = sc.mat_type[mat]
        if mtype == MAT_MIRROR or mtype == MAT_DIELECTRIC:
            if mtype == MAT_MIRROR and cos_o <= 0.0:
                break
            u = 0.0 if mtype == MAT_MIRROR else u1d(smp, key, seed, pixel, index, spp,
                                                    base + DIM_GLASS, memo)
            dx, dy, dz, ox, oy, oz, wr, wg, wb, _es = specular_step(
                mtype, sc.mat_rgb[mat, 0], sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2],
                sc.mat_param[mat, 0], hx, hy, hz, nx, ny, nz, dx, dy, dz, u)
            br, bg, bb = br * wr, bg * wg, bb * wb
        elif mtype == MAT_GLOSSY:
            ua, ub = u2d(smp, key, seed, pixel, index, spp, base + DIM_BSDF, memo)
            wx, wy, wz, sr, sg, sb, pdf = glossy_sample(
                nx, ny, nz, -dx, -dy, -dz, sc.mat_param[mat, 1], sc.mat_rgb[mat, 0],
                sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2], ua, ub)
            if pdf <= 0.0:
                break
            br, bg, bb = br * sr, bg * sg, bb * sb
            dx, dy, dz = wx, wy, wz
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
        else:
            break
    return (lr, lg, lb, rays, alb_r, alb_g, alb_b, an_x, an_y, an_z, first_t,
            look_k, look_p, look_smooth, wa, wb, wc, br, bg, bb)


@kernel_inline
def _jackknife_sample(jk_hist, jk_vert, patch_vert, smooth, k, p, wa, wb, wc, tr, tg, tb, out):
    """Add to out (J, 3) the sample's change under each jackknife replicate
    of the solution: the value it read, with the replicate's changes of B in
    place of B (the value is linear in B; li_radiosity says where it read)."""
    if p < 0:
        return
    for j in range(jk_hist.shape[0]):
        for c in range(3):
            t = tr if c == 0 else (tg if c == 1 else tb)
            if smooth:
                d = (wa * jk_vert[j, k, patch_vert[p, 0], c] + wb * jk_vert[j, k, patch_vert[p, 1], c]
                     + wc * jk_vert[j, k, patch_vert[p, 2], c])
            else:
                d = wa * jk_hist[j, k, p, c]
            out[j, c] += t * d


@kernel_inline
def _jackknife_fold(scratch, into):
    """scratch[into] += scratch[0]; scratch[0] = 0: a block's sums into its
    pixel's (the block fold of kernels/tile.py)."""
    for j in range(scratch.shape[1]):
        for c in range(3):
            scratch[into, j, c] += scratch[0, j, c]
            scratch[0, j, c] = 0.0


@kernel_parallel
def _display_tile(sc, pt, hist, vert_b, patch_vert, jk_hist, jk_vert, cam, x0, y0, x1, y1,
                  width, height, blocks, seed, depth, smp, spp, gather, out_sum, out_sq, out_w,
                  out_aov, out_jk, row_rays, stacks, memos, aov_rows, jk_rows):
    """The tile loop (integrators/tile.py) over `li_radiosity`, with the AOVs'
    and the jackknife changes' folds beside the radiance's; rows in parallel."""
    for row in prange(y1 - y0):
        row_rays[row] = _display_row(sc, pt, hist, vert_b, patch_vert, jk_hist, jk_vert, cam, x0,
                                     y0, x1, width, height, blocks, seed, depth, smp, spp, gather,
                                     out_sum, out_sq, out_w, out_aov, out_jk, np.int64(row),
                                     stacks[row], memos[get_thread_id()], aov_rows[row],
                                     jk_rows[row])


@kernel
def _display_row(sc, pt, hist, vert_b, patch_vert, jk_hist, jk_vert, cam, x0, y0, x1,
                 width, height, blocks, seed, depth, smp, spp, gather, out_sum, out_sq, out_w,
                 out_aov, out_jk, row, stack, memo, scr, jk):
    """Row `row` of `_display_tile`, its rays traced; a kernel of its own
    (integrators/tile.py, "Compile time"). `jk`: [0] the block's sums of the
    jackknife changes, [1] the pixel's (module doc of film.py)."""
    n = n_samples(blocks)
    y = y0 + row
    rays = 0
    for x in range(x0, x1):
        pixel = y * width + x
        ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for bi in range(blocks.shape[0]):
            sr, sg, sb, tr, tg, tb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for s in range(blocks[bi, 0], blocks[bi, 1]):
                key = sample_key(seed, pixel, s)
                fu, fv = u2d(smp, key, seed, pixel, s, spp, 0, memo)
                fx, fy = film_position(cam, x, y, fu, fv)
                lu, lv = 0.0, 0.0
                if cam[CAM_LENS] > 0.0:
                    lu, lv = u2d(smp, key, seed, pixel, s, spp, DIM_LENS, memo)
                ox, oy, oz, dx, dy, dz = camera_ray_at(cam, width, height, fx, fy, lu, lv)
                (r, g, b, nr, alr, alg, alb, anx, any_, anz, dist, lk, lp, lsm, wa, wb,
                 wc, thr, thg, thb) = li_radiosity(
                    sc, pt, hist, vert_b, patch_vert, stack, ox, oy, oz, dx, dy, dz, key,
                    depth, gather, smp, seed, pixel, s, spp, memo)
                rays += nr
                sr, sg, sb, tr, tg, tb = add_sample(sr, sg, sb, tr, tg, tb, r, g, b)
                add_aov_sample(scr, alr, alg, alb, anx, any_, anz, dist)
                _jackknife_sample(jk_hist, jk_vert, patch_vert, lsm, lk, lp, wa, wb, wc,
                                  thr, thg, thb, jk[0])
            ar, ag, ab, qr, qg, qb = add_block(ar, ag, ab, qr, qg, qb,
                                               sr, sg, sb, tr, tg, tb)
            add_aov_block(scr)
            _jackknife_fold(jk, 1)
        store_pixel(out_sum, out_sq, out_w, row, x - x0, ar, ag, ab, qr, qg, qb, n)
        store_aov(out_aov, row, x - x0, scr)
        for j in range(jk.shape[1]):
            for c in range(3):
                out_jk[row, x - x0, j, c] = jk[1, j, c]
                jk[1, j, c] = 0.0
    return rays


# ---------------------------------------------------------------- the method

def plan_radiosity(spec, progressive: bool = False, options: dict | None = None) -> list[Unit]:
    """Unit 0 solves; then the tile plan, every unit needing unit 0."""
    units = [Unit(0, 0, 0, 0, 0, 0, 0, stage=0, kind="solve")]
    for u in tile_plan(spec, progressive=progressive):
        units.append(replace(u, index=u.index + 1, stage=1, kind="tile", needs=(0,)))
    return units


def _document_geometry(doc: dict):
    """What `build_scene` would make of a resolved document, without building
    it (no BVH, no kernel): the world-space triangles and sphere radii that
    become patches, and the bounds of every primitive that can be hit."""
    diffuse = {name for name, m in doc["materials"].items() if m["type"] == "diffuse"}
    tris, tri_meshed, radii, sph_meshed, lo, hi = [], [], [], [], [], []
    for shape in doc["shapes"]:
        meshed = shape["material"] in diffuse or "emitter" in shape
        m = np.asarray(shape["to_world"], dtype=np.float64)
        if shape["type"] == "sphere":
            centre = m[:3, :3] @ np.asarray(shape["center"], dtype=np.float64) + m[:3, 3]
            radius = shape["radius"] * np.linalg.norm(m[:3, 0])
            radii.append(radius)
            sph_meshed.append(meshed)
            lo.append(centre - radius)
            hi.append(centre + radius)
            continue
        vertices, faces = world_mesh(shape, getattr(doc, "assets", None))
        tri = vertices[faces]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        tri = tri[np.linalg.norm(cross, axis=1) > 0]  # build_scene's degenerate ones are no patches
        if len(tri):
            lo.append(tri.min(axis=(0, 1)))
            hi.append(tri.max(axis=(0, 1)))
        if meshed:
            tris.append(tri)
    tri_p = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
    sph_r = np.asarray(radii, dtype=np.float64)[np.asarray(sph_meshed, dtype=bool)]
    bounds = (np.min(lo, axis=0), np.max(hi, axis=0)) if lo else (np.zeros(3), np.zeros(3))
    return tri_p, sph_r, bounds


def check_scene(spec, doc: dict, options: dict) -> None:
    """Refuse at submission what the solve unit would refuse later, on the
    farm: more than MAX_PATCHES patches (the mesh is built in Python: ~15 s
    at that size) or more than MAX_HITS stored form-factor hits (1 GiB).
    Measured before this check: patch_size 1e-3 on cornell-box (58 million
    patches) was accepted and its solve failed with SpecError in every
    attempt; 5e-324 with OverflowError. The count is the exact one of
    `mesh_patches`, from the document's world-space triangles."""
    tri_p, sph_r, (lo, hi) = _document_geometry(doc)
    patch_size = float(options["patch_size"]) or patch_size_of_bounds(lo, hi)
    total = patch_total(tri_p, sph_r, patch_size) if patch_size > 0 else math.inf
    if total > MAX_PATCHES:
        count = f"{total:.3g}" if total >= 1e9 else str(as_count(total))
        raise SpecError("options.patch_size",
                        f"patch_size {patch_size:g} cuts this scene into {count} patches (at "
                        f"most {MAX_PATCHES}): choose a larger patch_size")
    hemicube = options["form_factors"] == "hemicube"
    n_rays = 3 * int(options["hemicube_res"]) ** 2 if hemicube else int(options["ff_rays"])
    if total * n_rays > MAX_HITS:
        raise SpecError("options.hemicube_res" if hemicube else "options.ff_rays",
                        f"{int(total)} patches x {n_rays} rays per patch exceeds {MAX_HITS} "
                        "stored hits: fewer rays or larger patches")


def resolve_options(options: dict, scene) -> dict:
    """The checked options with the scene's automatic patch size resolved."""
    if float(options["patch_size"]) == 0.0:
        options = {**options, "patch_size": auto_patch_size(scene)}
    return options


def run_radiosity(scene, spec, unit, inputs, options) -> PartialFilm:
    options = resolve_options(options, scene)
    if unit.kind == "solve":
        history, deltas, stats = solution(scene, options, spec.seed)
        film = PartialFilm.zeros(0, 0, 0, 0)
        # the tiles read B(k) for k <= depth only: ship no more (the cache keeps all)
        film.artefact = {"radiosity": np.ascontiguousarray(history[:spec.depth + 1]),
                         "jackknife": np.ascontiguousarray(deltas[:, :spec.depth + 1])}
        film.stats.update(stats)
        film.stats["samples"] = 0
        return film
    if unit.needs:
        artefact = inputs[unit.needs[0]].artefact
        history, deltas = artefact["radiosity"], artefact["jackknife"]
    else:  # a tile from the plain tile plan: fetch (or solve) the solution here
        history, deltas, _ = solution(scene, options, spec.seed)
    history, deltas = np.ascontiguousarray(history), np.ascontiguousarray(deltas)
    patches = mesh(scene, options["patch_size"])
    if history.shape[1] != len(patches.kind):
        raise ValueError(f"radiosity solution has {history.shape[1]} patches, the mesh "
                         f"{len(patches.kind)}")
    t = start_tile(scene, spec, unit, aov=True)
    j = deltas.shape[0]
    if options["display"] == "smooth":
        patch_vert, n_vert = welded_vertices(scene, options["patch_size"])
        vert_b = vertex_radiosity(history, patches.area, patch_vert, n_vert)
        # linear in B: a replicate's vertex changes are its patch changes' means
        vert_d = np.stack([vertex_radiosity(d, patches.area, patch_vert, n_vert)
                           for d in deltas]) if j else np.zeros((0,) + vert_b.shape)
    else:
        patch_vert, vert_b = np.zeros((0, 3), np.int32), np.zeros((history.shape[0], 0, 3))
        vert_d = np.zeros((j,) + vert_b.shape)
    h, w = unit.y1 - unit.y0, unit.x1 - unit.x0
    t.film.jackknife = np.zeros((h, w, j, 3)) if j else None
    _display_tile(scene.arrays, patches, history, vert_b, patch_vert, deltas, vert_d, t.cam,
                  unit.x0, unit.y0, unit.x1, unit.y1, spec.width, spec.height, t.blocks,
                  spec.seed, spec.depth, SAMPLERS[spec.sampler].id, spec.spp,
                  1 if options["final_gather"] == "on" else 0,
                  t.film.sum, t.film.sum_sq, t.film.weight, t.film.aov,
                  t.film.jackknife if j else np.zeros((h, w, 0, 3)), t.row_rays, t.stacks,
                  t.memos, t.aov_rows, np.zeros((h, 2, j, 3)))
    return t.finish(unit)


METHODS = (Method(
    # Patches are flat and hold one radiosity each: a texture or a back side
    # that shades would need patches of their own. (Vertex normals: a patch
    # is shaded with its geometric normal.)
    unsupported={**{f: "its patches are one-sided and of one constant albedo"
                    for f in ("textures", "two-sided materials")},
                 "opacity masks": "its patches are solid: form factors see every surface opaque"},
    name="radiosity",
    aovs=("albedo", "normal", "depth"),
    description="Finite element radiosity: diffuse patches, Monte Carlo form factors with "
                "visibility, an iterative solve once per scene (cached), displayed by tiles "
                "(optionally with a final gather).",
    run=run_radiosity,
    options=(
        # Scene coordinates lie within +-MAX_COORDINATE: a larger patch is one
        # patch per primitive already (the lower end is check_scene's count).
        Option("patch_size", float, 0.0, "patch edge length in world units; 0 = auto: the "
               "scene's bounding-box diagonal / (20 sqrt 3), 0.1 for cornell-box",
               bounds=(0.0, 10.0 * MAX_COORDINATE)),
        Option("form_factors", str, "montecarlo", "form factor estimator: Monte Carlo ray "
               "casting or a ray-cast hemicube, both with visibility", ("montecarlo", "hemicube")),
        Option("ff_rays", int, 512, "Monte Carlo form-factor rays and light samples per patch",
               bounds=(1, 1 << 16)),
        Option("hemicube_res", int, 32, "hemicube top-face resolution (3 res^2 rays per patch)",
               bounds=(2, 1024), check=lambda v: None if v % 2 == 0 else f"must be even, got {v}"),
        Option("solver", str, "jacobi", "jacobi (one bounce per iteration, honours depth), "
               "gauss-seidel or progressive (Southwell shooting)", SOLVERS),
        Option("tolerance", float, 1e-4, "relative change at which the solver stops",
               bounds=(1e-12, 1.0)),
        Option("direct", str, "sampled", "first bounce by light sampling from the patches "
               "(sampled) or through the form factors (formfactor)", ("sampled", "formfactor")),
        Option("display", str, "flat", "flat: B/pi of the patch; smooth: Gouraud "
               "interpolation of vertex radiosities (area-weighted means of the patches "
               "around each vertex)", ("flat", "smooth")),
        Option("final_gather", str, "off", "on: light sampling and one gather ray into the "
               "solution at the visible point", ("off", "on")),
    ),
    family="radiosity",
    plan=plan_radiosity,
    phases=("solve", "tile"),
    check_scene=check_scene,
    # Each solver is a kernel of its own (the default's solve may even be
    # skipped at warm-up: a cached solution needs none).
    warm_options=({"solver": "gauss-seidel"}, {"solver": "progressive"}),
    # Warm-up needs the kernels, not a solution: cornell-box's default mesh
    # (about 6000 patches, 512 rays each) and its jackknife took 14 s of every
    # render process's start on a 2-core AMD EPYC, the progressive solver
    # 9 s of it; with 0.5-unit patches (about 300) and 16 rays, 0.04 s, the same kernels
    # (tests/test_renderer_structure.py test10 checks that none is left over).
    warm_base={"patch_size": 0.5, "ff_rays": 16},
),)
