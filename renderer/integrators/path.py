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
surviving throughput by the survival probability, so it adds noise, not bias;
the `roulette` option scales that probability (ROULETTE below).

Random dimensions of a camera sample (drawn from the job's pixel sampler,
renderer/samplers/): 0-1 the film position, then 8 per bounce b at 2 + 8 b:
the 2D pairs +0..1 the point on a light (its first number also picks the
light and the triangle, kernels/lights.py), +2..3 the BSDF direction; then
the 1D decisions +5 Russian roulette, +6 glass reflect/refract, +7 the
one-sample strategy choice (+4 is unused; samplers/dispatch.py names them).
"""

from __future__ import annotations

from functools import partial

import numpy as np
from numba import get_thread_id, prange

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
from ..kernels.camera import CAM_LENS, camera_ray_at, film_position
from ..kernels.geometry import (
    intersect_arrays,
    offset_origin,
    shadow_ray,
)
from ..kernels.ggx import glossy_eval, glossy_sample
from ..kernels.lights import light_pdf, sample_light
from ..kernels.opacity import blocked_after_masks, has_masks, masked, pass_masks
from ..kernels.packet import PACKET, packet_intersect
from ..kernels.shading import shade_hit
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
from ..samplers import (DIM_BSDF, DIM_GLASS, DIM_LENS, DIM_LIGHT, DIM_RR, DIM_STRATEGY,
                        DIMS_PER_BOUNCE,
                        u1d, u2d)
from .tile import start_tile, tile_plan

# The AOVs every method of the family writes (_shade_lane, film.py).
PATH_AOVS = ("albedo", "normal", "depth")

# Strategies of the path family (one kernel, switched at run time).
BSDF_ONLY, NEE, ONE_SAMPLE, MIS, DIRECT = 0, 1, 2, 3, 4
COSINE, UNIFORM = 0, 1


# A lane's state (rows of the per-row scratch `lane_floats` / `lane_ints`,
# one column per lane): the ray being traced, the shadow ray, and what one
# path carries from vertex to vertex. Floats:
OX, OY, OZ, DX, DY, DZ, IX, IY, IZ, T = range(10)  # the path's ray (IX..IZ scratch)
SOX, SOY, SOZ, SDX, SDY, SDZ, SIX, SIY, SIZ, ST = range(10, 20)  # the shadow ray
LR, LG, LB = range(20, 23)  # the radiance so far
ALB_R, ALB_G, ALB_B, AN_X, AN_Y, AN_Z, FIRST_T = range(23, 30)  # the AOVs
BR, BG, BB, ETA, PREV_PDF, VX, VY, VZ = range(30, 38)
CR, CG, CB = range(38, 41)  # the light sample's contribution, if the shadow ray is clear
SMAX = 41  # the shadow ray's tmax (ST holds its hit after the packet)
N_LANE_FLOATS = 42
# what a finished item leaves in the ring: rows LR..FIRST_T
RING_VALUES = 10
# ints: the hit primitive, tracing, the shadow ray's hit and tracing, the
# specular flag, one-sample MIS's choice, AOVs taken, rays traced, the row's
# item, the bounce, and the item's pixel and sample index (kept, not derived
# from the item at every vertex: a 64-bit division each time)
PRIM, ACT, SPRIM, SACT, SPEC, CHOSE, AOV_SET, RAYS, ITEM, BOUNCE, PIXEL, INDEX = range(12)
N_LANE_INTS = 12
# items a row's lanes may run ahead of the oldest one not yet folded
RING = 256


@kernel_inline
def _start_lane(fl, il, r, item, ox, oy, oz, dx, dy, dz):
    """Lane r starts the row's item `item`: the camera ray, unit throughput, nothing yet."""
    fl[OX, r], fl[OY, r], fl[OZ, r] = ox, oy, oz
    fl[DX, r], fl[DY, r], fl[DZ, r] = dx, dy, dz
    fl[VX, r], fl[VY, r], fl[VZ, r] = ox, oy, oz
    fl[T, r] = np.inf
    for k in (LR, LG, LB, PREV_PDF, ALB_R, ALB_G, ALB_B, AN_X, AN_Y, AN_Z, FIRST_T):
        fl[k, r] = 0.0
    fl[BR, r], fl[BG, r], fl[BB, r], fl[ETA, r] = 1.0, 1.0, 1.0, 1.0
    il[ACT, r] = 1
    il[SACT, r] = 0
    il[SPEC, r] = 1  # the camera is a delta "lobe" too: count emission in full
    il[CHOSE, r] = 1
    il[AOV_SET, r] = 0
    il[RAYS, r] = 0
    il[ITEM, r] = item
    il[BOUNCE, r] = 0


@kernel_inline
def _shade_lane(sc, fl, il, r, bounce, key, depth, strategy, heuristic, hemisphere, roulette,
                smp, seed, pixel, index, spp, memo):
    """Vertex `bounce` of lane r's path, once its ray found (T, PRIM):
    emission met there, the light sample (its shadow ray left in the lane
    for the packet to trace, its contribution in CR..CB, added to L if the
    ray is clear), the next ray, Russian roulette. Clears ACT when the path
    ends. A lane's values depend on its own sample only, so they are the
    bytes a path traced on its own gives (same arithmetic, same order).

    `strategy` decides how direct light is estimated at non-specular vertices:
    BSDF_ONLY (emission found by BSDF-sampled rays counts in full; no light
    sampling, so point lights stay dark), NEE (a shadow ray to a sampled light
    point; emission found by BSDF rays counts only after specular bounces),
    ONE_SAMPLE (either of the two, chosen with probability 1/2, weighted by
    the mixture pdf 1/2 p_light + 1/2 p_bsdf), MIS (both, weighted by the
    `heuristic`), DIRECT (NEE at the first diffuse vertex, then stop: only
    specular chains continue). `hemisphere` picks cosine or uniform sampling
    of diffuse lobes. Random numbers come from the pixel sampler `smp` for
    sample `index` of `pixel` (`key` is that sample's hash key, the fast path
    of the `random` sampler; `memo` the row's sampler scratch, samplers/
    dispatch.py).

    The lane's AOVs (film.py): the albedo and shading normal of the first
    diffuse or glossy surface, followed through mirrors and glass as Intel
    Open Image Denoise expects (0 if the path never reaches one), and the
    distance to the first hit (0 for a miss)."""
    prim = il[PRIM, r]
    il[RAYS, r] += 1
    if prim < 0:
        il[ACT, r] = 0
        return
    ox, oy, oz = fl[OX, r], fl[OY, r], fl[OZ, r]
    dx, dy, dz = fl[DX, r], fl[DY, r], fl[DZ, r]
    t = fl[T, r]
    br, bg, bb = fl[BR, r], fl[BG, r], fl[BB, r]
    n_lights = sc.light_type.shape[0]
    light_rgb, mat_type = sc.light_rgb, sc.mat_type
    hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
    # f: the front (emitting) side; g, n: the geometric and shading normals
    # of the side the BSDF shades (kernels/shading.py)
    (fx, fy, fz, gx, gy, gz, nx, ny, nz, ar, ag, ab, alpha,
     mat, light) = shade_hit(sc, prim, hx, hy, hz, dx, dy, dz)
    if bounce == 0:
        fl[FIRST_T, r] = t
    mtype = mat_type[mat]
    if il[AOV_SET, r] == 0 and (mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY):
        il[AOV_SET, r] = 1
        fl[ALB_R, r], fl[ALB_G, r], fl[ALB_B, r] = ar, ag, ab
        fl[AN_X, r], fl[AN_Y, r], fl[AN_Z, r] = nx, ny, nz
    specular = il[SPEC, r] != 0
    cos_f = -(dx * fx + dy * fy + dz * fz)
    if light >= 0 and cos_f > 0.0:
        w = 1.0
        if not specular and strategy != BSDF_ONLY:
            if strategy == NEE or (strategy == ONE_SAMPLE and il[CHOSE, r] == 0):
                w = 0.0  # this light was (or will be) counted by light sampling
            else:
                pl = light_pdf(sc, light, prim, fl[VX, r], fl[VY, r], fl[VZ, r],
                               hx, hy, hz, cos_f)
                prev_pdf = fl[PREV_PDF, r]
                if strategy == MIS:
                    w = mis_weight(prev_pdf, pl, heuristic)
                else:  # ONE_SAMPLE drew the BSDF: f L cos / (1/2 pb + 1/2 pl) in all
                    w = prev_pdf / (0.5 * prev_pdf + 0.5 * pl)
        fl[LR, r] += br * w * light_rgb[light, 0]
        fl[LG, r] += bg * w * light_rgb[light, 1]
        fl[LB, r] += bb * w * light_rgb[light, 2]
    if bounce == depth:
        il[ACT, r] = 0
        return
    base = 2 + DIMS_PER_BOUNCE * bounce
    # cosines of wo = -d with the shading and the geometric normal: both must
    # be positive (the front of a one-sided surface, and no shading normal
    # turned away from where the light comes from)
    cos_o = -(dx * nx + dy * ny + dz * nz)
    cos_g = -(dx * gx + dy * gy + dz * gz)
    if mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY:
        if cos_o <= 0.0 or cos_g <= 0.0:
            il[ACT, r] = 0  # one-sided: the back of a diffuse or glossy surface is black
            return
        use_light = strategy == NEE or strategy == MIS or strategy == DIRECT
        light_scale = 1.0
        if strategy == ONE_SAMPLE:
            chose_bsdf = u1d(smp, key, seed, pixel, index, spp, base + DIM_STRATEGY,
                             memo) >= 0.5
            il[CHOSE, r] = 1 if chose_bsdf else 0
            use_light = not chose_bsdf
            light_scale = 2.0  # the light strategy was drawn with probability 1/2
        if use_light and n_lights > 0:
            ua, ub = u2d(smp, key, seed, pixel, index, spp, base + DIM_LIGHT, memo)
            wx, wy, wz, dist, pl, er, eg, eb, delta = sample_light(sc, hx, hy, hz, ua, ub)
            cos_i = wx * nx + wy * ny + wz * nz
            if (pl > 0.0 and cos_i > 0.0 and wx * gx + wy * gy + wz * gz > 0.0
                    and (er > 0.0 or eg > 0.0 or eb > 0.0)):
                if mtype == MAT_DIFFUSE:
                    f, pb = diffuse_eval(cos_o, cos_i)
                    fr, fg, fb = ar * f, ag * f, ab * f
                    if hemisphere == UNIFORM:
                        pb = 0.5 * INV_PI
                else:
                    fr, fg, fb, pb = glossy_eval(nx, ny, nz, -dx, -dy, -dz, wx, wy, wz,
                                                 alpha, ar, ag, ab)
                il[RAYS, r] += 1
                if fr > 0.0 or fg > 0.0 or fb > 0.0:
                    sx, sy, sz, tx, ty, tz, tmax = shadow_ray(hx, hy, hz, gx, gy, gz,
                                                              wx, wy, wz, dist)
                    if delta or strategy == NEE or strategy == DIRECT:
                        # delta lights: one-sample picks them with probability 1/2 pl
                        weight = light_scale * cos_i / pl
                    elif strategy == MIS:
                        weight = cos_i * mis_weight(pl, pb, heuristic) / pl
                    else:  # ONE_SAMPLE: one-sample MIS divides by the mixture pdf
                        weight = cos_i / (0.5 * pl + 0.5 * pb)
                    # added to L once the packet's shadow rays find this one clear
                    fl[CR, r] = br * fr * er * weight
                    fl[CG, r] = bg * fg * eg * weight
                    fl[CB, r] = bb * fb * eb * weight
                    fl[SOX, r], fl[SOY, r], fl[SOZ, r] = sx, sy, sz
                    fl[SDX, r], fl[SDY, r], fl[SDZ, r] = tx, ty, tz
                    fl[ST, r] = tmax
                    fl[SMAX, r] = tmax
                    il[SACT, r] = 1
        if strategy == DIRECT:
            il[ACT, r] = 0  # Whitted: light stops at the first non-specular surface
            return
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
        if (pdf <= 0.0 or (sr <= 0.0 and sg <= 0.0 and sb <= 0.0)
                or wx * gx + wy * gy + wz * gz <= 0.0):  # through the surface: no light
            il[ACT, r] = 0
            return
        br *= sr
        bg *= sg
        bb *= sb
        fl[PREV_PDF, r] = pdf
        il[SPEC, r] = 0
        fl[VX, r], fl[VY, r], fl[VZ, r] = hx, hy, hz
        ox, oy, oz = offset_origin(hx, hy, hz, gx, gy, gz, 1.0)
        dx, dy, dz = wx, wy, wz
    else:  # a mirror or glass
        if mtype == MAT_MIRROR and (cos_o <= 0.0 or cos_g <= 0.0):
            il[ACT, r] = 0
            return
        u = 0.0 if mtype == MAT_MIRROR else u1d(smp, key, seed, pixel, index, spp,
                                                base + DIM_GLASS, memo)
        dx, dy, dz, ox, oy, oz, wr, wg, wb, es = specular_step(
            mtype, ar, ag, ab, sc.mat_param[mat, 0], hx, hy, hz, nx, ny, nz, dx, dy, dz, u)
        if mtype == MAT_MIRROR and dx * gx + dy * gy + dz * gz <= 0.0:
            il[ACT, r] = 0  # the shading normal reflected it into the surface
            return
        br *= wr
        bg *= wg
        bb *= wb
        fl[ETA, r] *= es
        il[SPEC, r] = 1
    if bounce >= 1 and roulette > 0.0:
        m = roulette * max(br, max(bg, bb)) * fl[ETA, r]
        if m < 1.0:
            q = max(0.0, 1.0 - m)
            if u1d(smp, key, seed, pixel, index, spp, base + DIM_RR, memo) < q:
                il[ACT, r] = 0
                return
            s = 1.0 / (1.0 - q)
            br *= s
            bg *= s
            bb *= s
    fl[BR, r], fl[BG, r], fl[BB, r] = br, bg, bb
    fl[OX, r], fl[OY, r], fl[OZ, r] = ox, oy, oz
    fl[DX, r], fl[DY, r], fl[DZ, r] = dx, dy, dz
    fl[T, r] = np.inf


@kernel_parallel
def _render_tile(sc, cam, x0, y0, x1, y1, width, height, blocks, seed, depth, smp, spp,
                 strategy, heuristic, hemisphere, roulette, out_sum, out_sq, out_w, out_aov,
                 row_rays, stacks, memos, aov_rows, lane_floats, lane_ints, lane_keys, rings,
                 ring_done):
    """The tile loop (integrators/tile.py) over packets of paths; rows in parallel.

    A row's camera samples, pixel by pixel and in sample order, are a queue
    of items. PACKET lanes trace one item's path each: every step, the live
    lanes' rays are one packet (kernels/packet.py), each lane is shaded on
    its own (`_shade_lane`, at its own bounce), the shadow rays are a second
    packet, and a lane whose path ended takes the next item, so the packets
    stay full while paths end at different depths. A finished item's values
    wait in the row's ring (RING items ahead of the oldest unfinished one at
    most) until every item before it is folded: the fold takes samples in
    the canonical order, so the film is the one a sample-at-a-time loop
    makes, whatever the tiling. An ended lane hands its values to the ring
    in the pass over the lanes that gives it its next item, at the start
    of the next step: one pass and one unpredictable test (is the lane
    live?) per lane and step where there were two. Measured on 2026-11-28
    (AMD EPYC Zen 4, 128x128, 64 spp, one thread, six interleaved pairs of
    processes), together with the items' column and sample kept as
    counters instead of a 64-bit division and remainder per item:
    cornell-box -4.1 %, veach-mis -4.3 % time, the same film bytes. The
    counters alone measured -0.6 % there; the next session took them out
    again (AMD EPYC Zen 1, the same method: +0.4 % / +0.3 %, noise, the
    same bytes), so the division stays, one state fewer to keep in step.
    The shadow rays' sums moved into that same pass as well: cornell-box
    -0.7 %, veach-mis +0.6 %, not kept.

    Each row's queue drains at its end: its last packets run part-empty.
    Measured 2026-11-28 (Zen 3, one thread, cornell-box 64 spp, the same
    image as tiles of 256 / 64 / 32 / 16 / 8 pixels, 3 rounds): rows of
    16384 / 4096 / 2048 / 1024 / 512 samples took 5.95 / 5.95 / 6.04 /
    6.08 / 6.59 s. Below about 1000 samples a row the drain starts to count.

    Measured and not kept (2026-11-28, AMD EPYC Zen 4, 128x128, 64 spp, one
    thread, six to eight interleaved pairs of processes, the same film bytes):
    - the light sample moved out of `_shade_lane` into a loop of its own
      over the lanes, after the shading. The light sample's chain (triangle
      pick, its division, the square root and division of the direction,
      the pdf's division) is the kernel's hottest code (bench/
      kernel_profile.py), and in a short loop the lanes' chains could
      overlap. cornell-box +3.1 %, veach-mis +5.3 % time: the lane rows it
      writes and reads back cost more;
    - the lane rows as one flat array per row (fl[OX + r] with OX a
      multiple of PACKET instead of fl[OX, r], no row stride to keep):
      cornell-box -0.7 %, veach-mis -1.7 %, inside the runs' noise.
    Measured and not kept (2026-11-28, the next session, the same machine
    and method; cornell-box unless said):
    - the shadow rays' sums as selects (no branch on the lane's shadow
      flag) and FIRST_T stored through a select: +1.7 % (an earlier
      session measured the first alone at +16 %, packet.py); FIRST_T's
      select alone 0.0 %; the sums moved into the refill pass: the
      paragraph above;
    - RING 64 instead of 256 (a ring that stays in L1): -0.7 %, noise;
    - the fold's twelve sums kept in the lane rows instead of registers,
      so that the loop keeps fewer values live: 0.0 %;
    - the row's loop as a kernel of its own, called with the default's
      strategy, sampler, heuristic and hemisphere as literals so that
      Numba compiles a specialization without the other cases: +2.4 %.
    Measured and not kept (2026-11-28, AMD EPYC Zen 1, the same method):
    - camera rays traced ahead, PACKET items at a time, as one coherent
      packet (a camera buffer in the lane rows), a starting lane taking
      its hit from there, so that the step's packet holds only the rays
      of paths that go on: cornell-box +4.8 %, veach-mis +5.7 % time, the
      same bytes. A packet's cost is the nodes and leaves it opens, nearly
      the same for the dozen live lanes left as for sixteen, and the
      camera packets came on top: full packets mattered more than
      coherent ones (bench/traversal.py's packets of sixteen camera rays
      trace about twice the rays/s of packets of bounce rays, and that
      did not pay for the part-empty packets).
    Measured and not kept (2026-11-29, AMD EPYC Zen 5, the same method):
    - the row's loop as a plain kernel of its own, called from a prange
      shell of three lines, for a shorter compile: Numba's parfor passes
      copy-propagate over the whole body with every helper inlined into it,
      and the parfor's body is typed and lowered a second time as its
      gufunc. The path family's cold compile took 43 s instead of 62 s
      (`runtime._warm_methods(["path-bsdf"])` on an empty cache), but
      rendering cornell-box +6.8 % and veach-mis +5.8 % time, the same
      bytes. Numba compiles a parfor body with `noalias` array arguments
      and a plain kernel cannot ask for them: with that flag forced on
      every kernel (an experiment, not an option Numba offers) the loss was
      +2.6 %. (The shell has to pass the row as an int64: the parfor's
      index is a uint64 in its body, and the row kernel was compiled three
      times, once for each type its arguments had in the passes.)
    Measured and not kept (2026-11-29, third session, AMD EPYC Zen 5, the
    same method, the same film bytes):
    - the cosine-sampled bounce (`diffuse_sample`: the concentric map's
      polynomials and division, the square root, the frame, the offset
      origin) taken out of `_shade_lane` into one branch-free loop over
      the lanes after the shading, the lane's numbers and normal left in
      five more lane rows. LLVM vectorized that loop (zmm throughout, packed
      divisions and square roots), yet cornell-box took +17.7 % time with
      the loop inlined here and +4.4 % as a kernel of its own. Lane by
      lane, that chain overlaps with the other lanes' work in the
      out-of-order core; the rows written and read back and the extra pass
      cost more than the vector arithmetic saves. The light sample's loop
      above (+3.1 %) had said the same."""
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    masks = has_masks(sc.mat_masked)  # else no hit needs a look (kernels/opacity.py)
    n = n_samples(blocks)
    s_lo = blocks[0, 0]
    total = (x1 - x0) * n
    for row in prange(y1 - y0):
        stack = stacks[row]
        memo = memos[get_thread_id()]  # one memo per thread (integrators/tile.py)
        scr = aov_rows[row]
        fl = lane_floats[row]
        il = lane_ints[row]
        keys = lane_keys[row]
        ring = rings[row]
        done = ring_done[row]
        y = y0 + row
        rays = 0
        for r in range(PACKET):
            il[ACT, r] = 0
            il[SACT, r] = 0
            il[ITEM, r] = -1
            fl[DX, r], fl[DY, r], fl[DZ, r] = 1.0, 1.0, 1.0
            fl[SDX, r], fl[SDY, r], fl[SDZ, r] = 1.0, 1.0, 1.0
        for k in range(RING):
            done[k] = 0
        k_next = 0  # the next item to start
        k_fold = 0  # the next item to fold
        # the fold's state: the pixel's sums, the block's, the block index
        ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        sr, sg, sb, tr, tg, tb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        bi = 0
        while k_fold < total:
            live = 0
            for r in range(PACKET):
                if il[ACT, r] != 0:
                    live += 1
                    continue
                item = il[ITEM, r]
                if item >= 0:  # the path ended: its values wait
                    slot = item % RING
                    for c in range(RING_VALUES):
                        ring[slot, c] = fl[LR + c, r]
                    done[slot] = 1
                    rays += il[RAYS, r]
                    il[ITEM, r] = -1
                if k_next < total and k_next < k_fold + RING:
                    x = x0 + k_next // n
                    s = s_lo + k_next % n
                    pixel = y * width + x
                    key = sample_key(seed, pixel, s)
                    keys[r] = key
                    fu, fv = u2d(smp, key, seed, pixel, s, spp, 0, memo)
                    fx, fy = film_position(cam, x, y, fu, fv)
                    lu, lv = 0.0, 0.0
                    if cam[CAM_LENS] > 0.0:
                        lu, lv = u2d(smp, key, seed, pixel, s, spp, DIM_LENS, memo)
                    ox, oy, oz, dx, dy, dz = camera_ray_at(cam, width, height, fx, fy, lu, lv)
                    _start_lane(fl, il, r, k_next, ox, oy, oz, dx, dy, dz)
                    il[PIXEL, r] = pixel
                    il[INDEX, r] = s
                    k_next += 1
                    live += 1
            if live > 0:
                packet_intersect(nodes, info, prims, tri, sph, stack,
                                 fl[OX], fl[OY], fl[OZ], fl[DX], fl[DY], fl[DZ],
                                 fl[IX], fl[IY], fl[IZ], fl[T], il[PRIM], il[ACT], False)
                if masks:  # a masked surface's hit: kept, or the ray goes on beyond it
                    for r in range(PACKET):
                        p = il[PRIM, r]
                        if il[ACT, r] != 0 and p >= 0 and masked(sc, p):
                            fl[T, r], il[PRIM, r] = pass_masks(
                                sc, stack, fl[OX, r], fl[OY, r], fl[OZ, r], fl[DX, r], fl[DY, r],
                                fl[DZ, r], np.inf, fl[T, r], p)
                shadows = 0
                for r in range(PACKET):
                    if il[ACT, r] != 0:
                        _shade_lane(sc, fl, il, r, il[BOUNCE, r], keys[r], depth, strategy,
                                    heuristic, hemisphere, roulette, smp, seed, il[PIXEL, r],
                                    il[INDEX, r], spp, memo)
                        il[BOUNCE, r] += 1
                        shadows += il[SACT, r]
                if shadows > 0:
                    packet_intersect(nodes, info, prims, tri, sph, stack,
                                     fl[SOX], fl[SOY], fl[SOZ], fl[SDX], fl[SDY], fl[SDZ],
                                     fl[SIX], fl[SIY], fl[SIZ], fl[ST], il[SPRIM], il[SACT], True)
                    if masks:  # stopped at a masked surface: traced again through the masks
                        for r in range(PACKET):
                            p = il[SPRIM, r]
                            if p >= 0 and masked(sc, p) and not blocked_after_masks(
                                    sc, stack, fl[SOX, r], fl[SOY, r], fl[SOZ, r], fl[SDX, r],
                                    fl[SDY, r], fl[SDZ, r], fl[SMAX, r]):
                                il[SACT, r] = 1
                    for r in range(PACKET):
                        # still set: the lane's shadow ray was traced and found nothing
                        if il[SACT, r] != 0:
                            fl[LR, r] += fl[CR, r]
                            fl[LG, r] += fl[CG, r]
                            fl[LB, r] += fl[CB, r]
                            il[SACT, r] = 0
            while k_fold < k_next and done[k_fold % RING] != 0:
                slot = k_fold % RING
                done[slot] = 0
                j = k_fold % n
                s = s_lo + j
                sr, sg, sb, tr, tg, tb = add_sample(sr, sg, sb, tr, tg, tb,
                                                    ring[slot, 0], ring[slot, 1], ring[slot, 2])
                add_aov_sample(scr, ring[slot, 3], ring[slot, 4], ring[slot, 5], ring[slot, 6],
                               ring[slot, 7], ring[slot, 8], ring[slot, 9])
                if s + 1 == blocks[bi, 1]:  # the end of a canonical block
                    ar, ag, ab, qr, qg, qb = add_block(ar, ag, ab, qr, qg, qb,
                                                       sr, sg, sb, tr, tg, tb)
                    add_aov_block(scr)
                    sr, sg, sb, tr, tg, tb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                    bi += 1
                if j == n - 1:  # the pixel's last sample
                    c = k_fold // n
                    store_pixel(out_sum, out_sq, out_w, row, c, ar, ag, ab, qr, qg, qb, n)
                    store_aov(out_aov, row, c, scr)
                    ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                    bi = 0
                k_fold += 1
        row_rays[row] = rays


def render_tile(scene, spec, unit, inputs, options, *, strategy: int) -> PartialFilm:
    """Run the kernel over one unit's tile and sample range."""
    heuristic = BALANCE if options.get("heuristic") == "balance" else POWER
    hemisphere = UNIFORM if options.get("hemisphere") == "uniform" else COSINE
    t = start_tile(scene, spec, unit, aov=True)
    _render_tile(scene.arrays, t.cam, unit.x0, unit.y0, unit.x1, unit.y1, spec.width,
                 spec.height, t.blocks, spec.seed, spec.depth, SAMPLERS[spec.sampler].id,
                 spec.spp, strategy, heuristic, hemisphere, float(options["roulette"]),
                 t.film.sum, t.film.sum_sq, t.film.weight, t.film.aov, t.row_rays, t.stacks,
                 t.memos, t.aov_rows,
                 *lane_scratch(unit.y1 - unit.y0))
    return t.finish(unit)


def lane_scratch(rows: int):
    """Per-row scratch of `_render_tile`: the lanes' floats, ints and sample
    keys, the ring of finished items and its flags."""
    return (np.zeros((rows, N_LANE_FLOATS, PACKET)), np.zeros((rows, N_LANE_INTS, PACKET), np.int64),
            np.zeros((rows, PACKET), np.uint64), np.zeros((rows, RING, RING_VALUES)),
            np.zeros((rows, RING), np.int64))


# Russian roulette's survival scale K: from the third vertex on a path goes
# on with probability q = min(1, K x the largest channel of its throughput
# (times the squared eta of its refractions)) and its throughput is divided
# by q. K = 1 is pbrt-v4's and Mitsuba 3's rule. K = 2 reached a given error
# sooner on cornell-box, door-ajar and cornell-caustic (+10 to +31 %) and
# lost a little on veach-mis, whose error is direct light (-3 to -9 %); the
# measurements of K = 1.5 / 2 / 3 / off, and why a roulette measured with
# `random` had stayed at 1, are in bench/throughput.py's notes
# (docs/throughput.md). Measured and not kept on top of K = 2: a survival
# floor of 0.25 or 0.5, or a start one vertex later (within the noise); a
# roulette on shadow rays was not built, since the shadow rays from the
# fourth vertex on were only 4-6 % of a cornell-box render at 64 spp.
ROULETTE = Option("roulette", float, 2.0, "Russian roulette from the third vertex: a path goes "
                  "on with probability min(1, roulette x its throughput's largest channel), "
                  "reweighted by 1/probability (1 is pbrt-v4's and Mitsuba's rule, higher keeps "
                  "more deep paths: less noise, more time); 0 turns it off", bounds=(0.0, 1e6))

METHODS = (
    Method(
        name="path-bsdf",
        description="Backward path tracing with BSDF sampling only: emitters count when a "
                    "sampled ray hits them; point lights are never reached.",
        run=partial(render_tile, strategy=BSDF_ONLY),
        options=(Option("hemisphere", str, "cosine", "diffuse lobe sampling: cosine-weighted "
                        "(pdf cos/pi) or uniform (pdf 1/2pi)", ("cosine", "uniform")), ROULETTE),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
    Method(
        name="path-nee",
        description="Path tracing with next event estimation: a shadow ray to a sampled light "
                    "point at every non-specular vertex.",
        run=partial(render_tile, strategy=NEE),
        options=(ROULETTE,),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
    Method(
        name="path-onesample",
        description="Single-sample importance sampling: at each non-specular vertex light or "
                    "BSDF sampling with probability 1/2, weighted by the mixture pdf.",
        run=partial(render_tile, strategy=ONE_SAMPLE),
        options=(ROULETTE,),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
    Method(
        name="direct",
        description="Whitted-style direct lighting: emission seen directly, shadow rays at the "
                    "first diffuse hit, perfect mirror and glass chains followed up to depth.",
        run=partial(render_tile, strategy=DIRECT),
        options=(ROULETTE,),
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
                        "balance heuristic", ("power", "balance")), ROULETTE),
        plan=tile_plan,
        aovs=PATH_AOVS,
    ),
)
