"""The path-tracing family: one kernel, four ways to estimate direct light.

| method | direct light at a non-specular vertex | option (default) |
|---|---|---|
| `path-bsdf` | only emitters that BSDF-sampled rays happen to hit | `hemisphere`: `cosine` or `uniform` |
| `path-nee` | a shadow ray to a point sampled on a light (next event estimation); emission hit by BSDF rays counts only after specular bounces | |
| `path-onesample` | one of the two, chosen with probability 1/2, divided by the mixture pdf 1/2 p_light + 1/2 p_bsdf (single-sample MIS) | |
| `path-mis` (alias `path`) | both, weighted by Veach's multiple importance sampling | `heuristic`: `power` or `balance` |
| `direct` | Whitted: light sampling at the first diffuse vertex, and the path ends there; mirrors and glass are followed up to `depth` | |

When to use which: `path-mis` is the robust default; `path-nee` is as good on
diffuse scenes with small lights; `path-bsdf` is the lecture's baseline (it
finds large lights, misses small ones and never sees point lights: "cannot
intersect point lights"); `path-onesample` traces fewer shadow rays than MIS
at the price of more noise. All four are unbiased for area lights and share
the continuation: the BSDF-sampled ray carries the indirect light.

Diffuse and glossy (GGX) surfaces are the non-specular vertices. Perfect
mirrors and glass are delta lobes: no light sampling there, and emission
reached through them counts in full (`specular` below).

Depth (the lecture's convention): `depth` counts surface bounces; depth 0
shows emitters seen directly, depth 1 is direct illumination; a path has at
most depth + 1 segments. Russian roulette from the third vertex on divides
surviving throughput by the survival probability, so it adds noise, not bias.

Random dimensions of a camera sample (drawn from the job's pixel sampler,
renderer/samplers/): 0-1 the film position, then 8 per bounce b at 2 + 8 b:
the 2D pairs +0..1 the point on a light, +2..3 the BSDF direction; then the
1D decisions +4 which light, +5 Russian roulette (one pair: a stratified
sampler evaluates it once), +6 glass reflect/refract, +7 the one-sample
strategy choice (samplers/dispatch.py names them).
"""

from __future__ import annotations

from functools import partial

import numpy as np
from numba import prange

from ..film import PartialFilm
from ..kernels import kernel_inline, kernel_parallel
from ..kernels.bsdf import (
    MAT_DIFFUSE,
    MAT_GLOSSY,
    MAT_MIRROR,
    diffuse_eval,
    diffuse_sample,
    specular_step,
)
from ..kernels.camera import camera_ray
from ..kernels.geometry import (
    intersect_arrays,
    offset_origin,
    shadow_ray,
    surface_at_arrays,
)
from ..kernels.ggx import glossy_eval, glossy_sample
from ..kernels.lights import light_pdf, sample_light
from ..kernels.rng import sample_key
from ..kernels.sampling import (
    BALANCE,
    INV_PI,
    POWER,
    mis_weight,
    to_world,
    uniform_hemisphere,
)
from ..kernels.tile import (add_aov_block, add_aov_sample, add_block, add_sample, n_samples,
                            store_aov, store_pixel)
from ..registry import SAMPLERS, Method, Option
from ..samplers import (DIM_BSDF, DIM_GLASS, DIM_LIGHT, DIM_LIGHT_PICK, DIM_RR, DIM_STRATEGY,
                        DIMS_PER_BOUNCE, u1d, u2d)
from .tile import start_tile, tile_plan

# The AOVs every method of the family writes (li_path, film.py).
PATH_AOVS = ("albedo", "normal", "depth")

# Strategies of the path family (one kernel, switched at run time).
BSDF_ONLY, NEE, ONE_SAMPLE, MIS, DIRECT = 0, 1, 2, 3, 4
COSINE, UNIFORM = 0, 1


@kernel_inline
def li_path(sc, stack, ox, oy, oz, dx, dy, dz, key, depth, strategy, heuristic, hemisphere,
            smp, seed, pixel, index, spp, memo):
    """Radiance arriving at o from direction -d: (r, g, b, rays traced).

    `strategy` decides how direct light is estimated at non-specular vertices:
    BSDF_ONLY (emission found by BSDF-sampled rays counts in full; no light
    sampling, so point lights stay dark), NEE (a shadow ray to a sampled light
    point; emission found by BSDF rays counts only after specular bounces),
    ONE_SAMPLE (either of the two, chosen with probability 1/2, weighted by
    the mixture pdf 1/2 p_light + 1/2 p_bsdf), MIS (both, weighted by the
    `heuristic`), DIRECT (NEE at the first diffuse vertex, then stop: only
    specular chains continue). `hemisphere` picks cosine or uniform sampling of diffuse
    lobes. Random numbers come from the pixel sampler `smp` for sample
    `index` of `pixel` (`key` is that sample's hash key, the fast path of the
    `random` sampler; `memo` the row's sampler scratch, samplers/dispatch.py).

    Also returns the sample's AOVs (film.py): the albedo and shading normal of
    the first diffuse or glossy surface, followed through mirrors and glass as
    Intel Open Image Denoise expects (0 if the path never reaches one), and
    the distance to the first hit (0 for a miss).
    """
    lr, lg, lb = 0.0, 0.0, 0.0
    br, bg, bb = 1.0, 1.0, 1.0
    eta_scale = 1.0
    specular = True  # the camera is a delta "lobe" too: count emission in full
    chose_bsdf = True  # one-sample MIS: which strategy the previous vertex drew
    prev_pdf = 0.0
    vx, vy, vz = ox, oy, oz  # the previous path vertex, on its surface (not offset)
    rays = 0
    aov_set = False
    alb_r, alb_g, alb_b, an_x, an_y, an_z, first_t = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    n_lights = sc.light_type.shape[0]
    # unpacked once: see geometry.py on passing SceneArrays into hot calls
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    tri_n, tri_mat, tri_light = sc.tri_n, sc.tri_mat, sc.tri_light
    sph_flip, sph_mat, sph_light = sc.sph_flip, sc.sph_mat, sc.sph_light
    light_rgb, mat_type, mat_rgb, mat_param = sc.light_rgb, sc.mat_type, sc.mat_rgb, sc.mat_param
    for bounce in range(depth + 1):
        t, prim = intersect_arrays(nodes, info, prims, tri, sph, stack,
                                   ox, oy, oz, dx, dy, dz, np.inf, False)
        rays += 1
        if prim < 0:
            break
        hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
        nx, ny, nz, mat, light = surface_at_arrays(tri_n, tri_mat, tri_light, sph, sph_flip,
                                                   sph_mat, sph_light, prim, hx, hy, hz)
        if bounce == 0:
            first_t = t
        mtype = mat_type[mat]
        if not aov_set and (mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY):
            aov_set = True
            alb_r, alb_g, alb_b = mat_rgb[mat, 0], mat_rgb[mat, 1], mat_rgb[mat, 2]
            an_x, an_y, an_z = nx, ny, nz
        cos_o = -(dx * nx + dy * ny + dz * nz)
        if light >= 0 and cos_o > 0.0:
            w = 1.0
            if not specular and strategy != BSDF_ONLY:
                if strategy == NEE or (strategy == ONE_SAMPLE and not chose_bsdf):
                    w = 0.0  # this light was (or will be) counted by light sampling
                else:
                    pl = light_pdf(sc, light, prim, vx, vy, vz, hx, hy, hz, cos_o)
                    if strategy == MIS:
                        w = mis_weight(prev_pdf, pl, heuristic)
                    else:  # ONE_SAMPLE drew the BSDF: f L cos / (1/2 pb + 1/2 pl) in all
                        w = prev_pdf / (0.5 * prev_pdf + 0.5 * pl)
            lr += br * w * light_rgb[light, 0]
            lg += bg * w * light_rgb[light, 1]
            lb += bb * w * light_rgb[light, 2]
        if bounce == depth:
            break
        base = 2 + DIMS_PER_BOUNCE * bounce
        have_rr = False  # the Russian roulette number, drawn with the light pick
        u_rr = 0.0
        if mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY:
            if cos_o <= 0.0:
                break  # one-sided: the back of a diffuse or glossy surface is black
            ar, ag, ab = mat_rgb[mat, 0], mat_rgb[mat, 1], mat_rgb[mat, 2]
            alpha = mat_param[mat, 1]
            use_light = strategy == NEE or strategy == MIS or strategy == DIRECT
            light_scale = 1.0
            if strategy == ONE_SAMPLE:
                chose_bsdf = u1d(smp, key, seed, pixel, index, spp, base + DIM_STRATEGY,
                                 memo) >= 0.5
                use_light = not chose_bsdf
                light_scale = 2.0  # the light strategy was drawn with probability 1/2
            if use_light and n_lights > 0:
                ua, ub = u2d(smp, key, seed, pixel, index, spp, base + DIM_LIGHT, memo)
                u_pick, u_rr = u2d(smp, key, seed, pixel, index, spp, base + DIM_LIGHT_PICK, memo)
                have_rr = True
                wx, wy, wz, dist, pl, er, eg, eb, delta = sample_light(sc, hx, hy, hz, u_pick, ua, ub)
                cos_i = wx * nx + wy * ny + wz * nz
                if pl > 0.0 and cos_i > 0.0 and (er > 0.0 or eg > 0.0 or eb > 0.0):
                    if mtype == MAT_DIFFUSE:
                        f, pb = diffuse_eval(cos_o, cos_i)
                        fr, fg, fb = ar * f, ag * f, ab * f
                        if hemisphere == UNIFORM:
                            pb = 0.5 * INV_PI
                    else:
                        fr, fg, fb, pb = glossy_eval(nx, ny, nz, -dx, -dy, -dz, wx, wy, wz,
                                                     alpha, ar, ag, ab)
                    sx, sy, sz, tx, ty, tz, tmax = shadow_ray(hx, hy, hz, nx, ny, nz, wx, wy, wz, dist)
                    rays += 1
                    if (fr > 0.0 or fg > 0.0 or fb > 0.0) and intersect_arrays(
                            nodes, info, prims, tri, sph, stack, sx, sy, sz, tx, ty, tz, tmax,
                            True)[1] < 0:
                        if delta or strategy == NEE or strategy == DIRECT:
                            # delta lights: one-sample picks them with probability 1/2 pl
                            weight = light_scale * cos_i / pl
                        elif strategy == MIS:
                            weight = cos_i * mis_weight(pl, pb, heuristic) / pl
                        else:  # ONE_SAMPLE: one-sample MIS divides by the mixture pdf
                            weight = cos_i / (0.5 * pl + 0.5 * pb)
                        lr += br * fr * er * weight
                        lg += bg * fg * eg * weight
                        lb += bb * fb * eb * weight
            if strategy == DIRECT:
                break  # Whitted: light stops at the first non-specular surface
            ua, ub = u2d(smp, key, seed, pixel, index, spp, base + DIM_BSDF, memo)
            if mtype == MAT_GLOSSY:
                wx, wy, wz, sr, sg, sb, pdf = glossy_sample(
                    nx, ny, nz, -dx, -dy, -dz, alpha, ar, ag, ab, ua, ub)
            elif hemisphere == UNIFORM:
                lx, ly, lz = uniform_hemisphere(ua, ub)
                wx, wy, wz = to_world(lx, ly, lz, nx, ny, nz)
                pdf = 0.5 * INV_PI
                k = lz * INV_PI / pdf  # f cos / pdf = albedo * 2 cos
                sr, sg, sb = ar * k, ag * k, ab * k
            else:
                wx, wy, wz, cos_i, pdf = diffuse_sample(nx, ny, nz, ua, ub)
                sr, sg, sb = ar, ag, ab  # f cos / pdf = albedo exactly
            if pdf <= 0.0 or (sr <= 0.0 and sg <= 0.0 and sb <= 0.0):
                break
            br *= sr
            bg *= sg
            bb *= sb
            prev_pdf = pdf
            specular = False
            vx, vy, vz = hx, hy, hz
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
            dx, dy, dz = wx, wy, wz
        else:  # a mirror or glass
            if mtype == MAT_MIRROR and cos_o <= 0.0:
                break
            u = 0.0 if mtype == MAT_MIRROR else u1d(smp, key, seed, pixel, index, spp,
                                                    base + DIM_GLASS, memo)
            dx, dy, dz, ox, oy, oz, wr, wg, wb, es = specular_step(
                mtype, mat_rgb[mat, 0], mat_rgb[mat, 1], mat_rgb[mat, 2], mat_param[mat, 0],
                hx, hy, hz, nx, ny, nz, dx, dy, dz, u)
            br *= wr
            bg *= wg
            bb *= wb
            eta_scale *= es
            specular = True
        if bounce >= 1:
            m = max(br, max(bg, bb)) * eta_scale
            if m < 1.0:
                q = max(0.0, 1.0 - m)
                if not have_rr:
                    u_rr = u1d(smp, key, seed, pixel, index, spp, base + DIM_RR, memo)
                if u_rr < q:
                    break
                s = 1.0 / (1.0 - q)
                br *= s
                bg *= s
                bb *= s
    return lr, lg, lb, rays, alb_r, alb_g, alb_b, an_x, an_y, an_z, first_t


@kernel_parallel
def _render_tile(sc, cam, x0, y0, x1, y1, width, height, blocks, seed, depth, smp, spp,
                 strategy, heuristic, hemisphere, out_sum, out_sq, out_w, out_aov, row_rays, stacks,
                 memos, aov_rows):
    """The tile loop (integrators/tile.py) over `li_path`, with the AOVs'
    fold beside the radiance's; rows in parallel."""
    ox, oy, oz = cam[0], cam[1], cam[2]
    n = n_samples(blocks)
    for row in prange(y1 - y0):
        stack = stacks[row]
        memo = memos[row]
        scr = aov_rows[row]
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
                    dx, dy, dz = camera_ray(cam, width, height, x + fu, y + fv)
                    r, g, b, nr, alr, alg, alb, anx, any_, anz, dist = li_path(
                        sc, stack, ox, oy, oz, dx, dy, dz, key, depth, strategy, heuristic,
                        hemisphere, smp, seed, pixel, s, spp, memo)
                    rays += nr
                    sr, sg, sb, tr, tg, tb = add_sample(sr, sg, sb, tr, tg, tb, r, g, b)
                    add_aov_sample(scr, alr, alg, alb, anx, any_, anz, dist)
                ar, ag, ab, qr, qg, qb = add_block(ar, ag, ab, qr, qg, qb,
                                                   sr, sg, sb, tr, tg, tb)
                add_aov_block(scr)
            store_pixel(out_sum, out_sq, out_w, row, x - x0, ar, ag, ab, qr, qg, qb, n)
            store_aov(out_aov, row, x - x0, scr)
        row_rays[row] = rays


def render_tile(scene, spec, unit, inputs, options, *, strategy: int) -> PartialFilm:
    """Run the kernel over one unit's tile and sample range."""
    heuristic = BALANCE if options.get("heuristic") == "balance" else POWER
    hemisphere = UNIFORM if options.get("hemisphere") == "uniform" else COSINE
    t = start_tile(scene, spec, unit, aov=True)
    _render_tile(scene.arrays, t.cam, unit.x0, unit.y0, unit.x1, unit.y1, spec.width,
                 spec.height, t.blocks, spec.seed, spec.depth, SAMPLERS[spec.sampler].id,
                 spec.spp, strategy, heuristic, hemisphere, t.film.sum, t.film.sum_sq,
                 t.film.weight, t.film.aov, t.row_rays, t.stacks, t.memos, t.aov_rows)
    return t.finish(unit)


METHODS = (
    Method(
        name="path-bsdf",
        description="Backward path tracing with BSDF sampling only: emitters count when a "
                    "sampled ray hits them; point lights are never reached.",
        run=partial(render_tile, strategy=BSDF_ONLY),
        options=(Option("hemisphere", str, "cosine", "diffuse lobe sampling: cosine-weighted "
                        "(pdf cos/pi) or uniform (pdf 1/2pi)", ("cosine", "uniform")),),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
    Method(
        name="path-nee",
        description="Path tracing with next event estimation: a shadow ray to a sampled light "
                    "point at every non-specular vertex.",
        run=partial(render_tile, strategy=NEE),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
    Method(
        name="path-onesample",
        description="Single-sample importance sampling: at each non-specular vertex light or "
                    "BSDF sampling with probability 1/2, weighted by the mixture pdf.",
        run=partial(render_tile, strategy=ONE_SAMPLE),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
    Method(
        name="direct",
        description="Whitted-style direct lighting: emission seen directly, shadow rays at the "
                    "first diffuse hit, perfect mirror and glass chains followed up to depth.",
        run=partial(render_tile, strategy=DIRECT),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
    Method(
        name="path-mis",
        aliases=("path",),
        description="Path tracing: light and BSDF sampling combined by multiple importance "
                    "sampling; Russian roulette.",
        run=partial(render_tile, strategy=MIS),
        options=(Option("heuristic", str, "power", "MIS weights: Veach's power (beta = 2) or "
                        "balance heuristic", ("power", "balance")),),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
)
