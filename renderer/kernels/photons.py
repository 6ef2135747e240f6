"""Photon mapping's kernels: tracing photons, the camera pass's visible
points, the hash grid, the SPPM gather and update, and the k-nearest-neighbour
estimate. The method (its plan, units and the account of the algorithm) is
renderer/integrators/photon.py.
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_thread_id, prange

from ..samplers import DIM_GLASS, DIM_LENS, DIM_LIGHT, DIMS_PER_BOUNCE, u1d, u2d
from . import kernel, kernel_inline, kernel_parallel
from .bsdf import (
    MAT_DIELECTRIC,
    MAT_DIFFUSE,
    MAT_GLOSSY,
    MAT_MIRROR,
    dielectric_sample,
    diffuse_eval,
    diffuse_sample,
    reflect,
    specular_step,
)
from .camera import CAM_LENS, camera_ray_at, film_position
from .geometry import offset_origin, shadow_ray
from .ggx import glossy_eval, glossy_sample
from .lights import sample_emission, sample_light
from .opacity import blocked, trace
from .shading import shade_hit
from .rng import STREAM_PHOTONS, sample_key, stream_key, uniform
from .sampling import INV_PI
from .tile import (add_aov_block, add_aov_sample, add_block, add_sample, n_samples, store_aov,
                   store_pixel)

__all__ = ["trace_photons", "visible_point", "camera_pass", "build_grid", "gather_pass",
           "sppm_update", "knn_render", "PHOTON_DIMS", "DIMS_PER_PHOTON_HIT"]

# Random dimensions of a photon: 0 the light, 1-4 the emitted ray, then 4 per
# hit h >= 1 at 5 + 4 (h - 1): +0..1 the direction, +2 glass, +3 roulette.
PHOTON_DIMS, DIMS_PER_PHOTON_HIT = 5, 4


# ----------------------------------------------------------------- photons

@kernel
def trace_photons(sc, stack, seed, g0, g1, depth, pos, dirs, power, hits):
    """Trace photons g0..g1-1 (global indices) and record them at every
    diffuse or glossy hit from the second on (front side only) up to hit
    `depth`. Returns (records, rays); records = -1 if the buffers are full."""
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
            t, p = trace(sc, stack, ox, oy, oz, dx, dy, dz, np.inf)
            rays += 1
            if p < 0:
                break
            hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
            (fx, fy, fz, gx, gy, gz, nx, ny, nz, ar, ag, ab, alpha,
             mat, light) = shade_hit(sc, p, hx, hy, hz, dx, dy, dz)
            cos_in = -(dx * nx + dy * ny + dz * nz)
            cos_g = -(dx * gx + dy * gy + dz * gz)
            if cos_g <= 0.0 and mat_type[mat] != MAT_DIELECTRIC:
                break  # the back of a one-sided surface absorbs
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
                if mtype == MAT_DIFFUSE:
                    wx, wy, wz, cos_w, pdf = diffuse_sample(nx, ny, nz, ua, ub)
                    sr, sg, sb = ar, ag, ab
                else:  # GGX is symmetric: sampling about -d gives f |cos wo| / pdf
                    wx, wy, wz, sr, sg, sb, pdf = glossy_sample(
                        nx, ny, nz, -dx, -dy, -dz, alpha, ar, ag, ab, ua, ub)
                if pdf <= 0.0:
                    break
                dx, dy, dz = wx, wy, wz
            elif mtype == MAT_MIRROR:
                if cos_in <= 0.0 or hit == depth:
                    break
                dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
                sr, sg, sb = ar, ag, ab
            else:  # dielectric: importance transport, no 1/eta^2, weight 1
                if hit == depth:
                    break
                dx, dy, dz, w, es, side = dielectric_sample(
                    dx, dy, dz, nx, ny, nz, mat_param[mat, 0], uniform(key, base + 2))
                sr, sg, sb = 1.0, 1.0, 1.0
            if gx != nx or gy != ny or gz != nz:  # a shading normal: the side checks
                wig = dx * gx + dy * gy + dz * gz
                wis = dx * nx + dy * ny + dz * nz
                if ((mtype != MAT_DIELECTRIC and wig <= 0.0) or wig * wis <= 0.0
                        or cos_in * cos_g <= 0.0):
                    break
                c = abs(cos_in) * abs(wig) / (abs(cos_g) * abs(wis))  # Veach's adjoint BSDF
                sr, sg, sb = sr * c, sg * c, sb * c
            if mtype == MAT_DIELECTRIC:
                ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, side)
            else:
                ox, oy, oz = offset_origin(hx, hy, hz, gx, gy, gz, side)
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
def visible_point(sc, stack, ox, oy, oz, dx, dy, dz, depth, smp, key, seed, pixel, index, spp,
                  memo):
    """Follow a camera ray through mirrors and glass to the first diffuse or
    glossy surface. Returns (kmax, p, n, wo, beta, mat, Ld, rays, aov): kmax =
    depth - specular bounces (the longest photon path k it may gather; -1
    when there is no visible point), Ld the emission seen along the chain
    plus direct light at the visible point by light sampling, aov the
    sample's AOVs as path tracing gives them (albedo and normal of the first
    diffuse or glossy hit, distance to the first hit: 7 floats). `memo`: the
    sampler's row scratch (samplers/dispatch.py) or NO_MEMO."""
    tri_n, tri_mat, tri_light = sc.tri_n, sc.tri_mat, sc.tri_light
    sph_flip, sph_mat, sph_light = sc.sph_flip, sc.sph_mat, sc.sph_light
    light_rgb, mat_type, mat_rgb, mat_param = sc.light_rgb, sc.mat_type, sc.mat_rgb, sc.mat_param
    n_lights = sc.light_type.shape[0]
    lr, lg, lb = 0.0, 0.0, 0.0
    br, bg, bb = 1.0, 1.0, 1.0
    rays = 0
    kmax = -1
    hx, hy, hz, nx, ny, nz, mat = 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0
    aov_set = False
    alb_r, alb_g, alb_b, an_x, an_y, an_z, first_t = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for bounce in range(depth + 1):
        t, prim = trace(sc, stack, ox, oy, oz, dx, dy, dz, np.inf)
        rays += 1
        if prim < 0:
            break
        hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
        (fx, fy, fz, gx, gy, gz, nx, ny, nz, ar, ag, ab, alpha,
         mat, light) = shade_hit(sc, prim, hx, hy, hz, dx, dy, dz)
        if bounce == 0:
            first_t = t
        if not aov_set and (mat_type[mat] == MAT_DIFFUSE or mat_type[mat] == MAT_GLOSSY):
            aov_set = True
            alb_r, alb_g, alb_b = ar, ag, ab
            an_x, an_y, an_z = nx, ny, nz
        cos_o = -(dx * nx + dy * ny + dz * nz)
        cos_g = -(dx * gx + dy * gy + dz * gz)
        if light >= 0 and -(dx * fx + dy * fy + dz * fz) > 0.0:
            lr += br * light_rgb[light, 0]
            lg += bg * light_rgb[light, 1]
            lb += bb * light_rgb[light, 2]
        if bounce == depth:
            break
        base = 2 + DIMS_PER_BOUNCE * bounce
        mtype = mat_type[mat]
        if mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY:
            if cos_o <= 0.0 or cos_g <= 0.0:
                break
            if n_lights > 0:
                ua, ub = u2d(smp, key, seed, pixel, index, spp, base + DIM_LIGHT, memo)
                wx, wy, wz, dist, pl, er, eg, eb, delta = sample_light(sc, hx, hy, hz, ua, ub)
                cos_i = wx * nx + wy * ny + wz * nz
                if (pl > 0.0 and cos_i > 0.0 and wx * gx + wy * gy + wz * gz > 0.0
                        and (er > 0.0 or eg > 0.0 or eb > 0.0)):
                    if mtype == MAT_DIFFUSE:
                        f, pb = diffuse_eval(cos_o, cos_i)
                        fr, fg, fb = ar * f, ag * f, ab * f
                    else:
                        fr, fg, fb, pb = glossy_eval(nx, ny, nz, -dx, -dy, -dz, wx, wy, wz,
                                                     alpha, ar, ag, ab)
                    sx, sy, sz, tx, ty, tz, tmax = shadow_ray(hx, hy, hz, gx, gy, gz, wx, wy, wz,
                                                              dist)
                    rays += 1
                    if (fr > 0.0 or fg > 0.0 or fb > 0.0) and not blocked(
                            sc, stack, sx, sy, sz, tx, ty, tz, tmax):
                        w = cos_i / pl
                        lr += br * fr * er * w
                        lg += bg * fg * eg * w
                        lb += bb * fb * eb * w
            kmax = depth - bounce
            if mtype == MAT_DIFFUSE:  # the albedo (maybe textured) rides in beta (_photon_f)
                br, bg, bb = br * ar, bg * ag, bb * ab
            break
        else:  # a mirror or glass: radiance transport on the camera side (1/eta^2)
            if mtype == MAT_MIRROR and (cos_o <= 0.0 or cos_g <= 0.0):
                break
            u = 0.0 if mtype == MAT_MIRROR else u1d(smp, key, seed, pixel, index, spp,
                                                    base + DIM_GLASS, memo)
            dx, dy, dz, ox, oy, oz, wr, wg, wb, _es = specular_step(
                mtype, ar, ag, ab, mat_param[mat, 0], hx, hy, hz, nx, ny, nz, dx, dy, dz, u)
            if mtype == MAT_MIRROR and dx * gx + dy * gy + dz * gz <= 0.0:
                break  # the shading normal reflected it into the surface
            br *= wr
            bg *= wg
            bb *= wb
    return (kmax, hx, hy, hz, nx, ny, nz, -dx, -dy, -dz, br, bg, bb, mat, lr, lg, lb, rays,
            alb_r, alb_g, alb_b, an_x, an_y, an_z, first_t)


@kernel_parallel
def camera_pass(sc, cam, x0, y0, x1, y1, width, height, seed, index, spp, smp, depth,
                vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, ld, vp_aov, row_rays, stacks,
                no_memo):
    """One camera sample (`index`) per pixel of the tile: its visible point,
    Ld and AOVs (`vp_aov`, added to: the sums over iterations). One sample of
    each pixel, so no sampler memo (`no_memo`)."""
    for row in prange(y1 - y0):
        row_rays[row] = _camera_row(sc, cam, x0, y0, x1, width, height, seed, index, spp, smp,
                                    depth, vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, ld,
                                    vp_aov, np.int64(row), stacks[row], no_memo)


@kernel
def _camera_row(sc, cam, x0, y0, x1, width, height, seed, index, spp, smp, depth, vp_kmax, vp_p,
                vp_n, vp_wo, vp_beta, vp_mat, ld, vp_aov, row, stack, no_memo):
    """Row `row` of `camera_pass`, its rays traced; a kernel of its own
    (integrators/tile.py, "Compile time")."""
    y = y0 + row
    rays = 0
    for x in range(x0, x1):
        c = x - x0
        pixel = y * width + x
        key = sample_key(seed, pixel, index)
        fu, fv = u2d(smp, key, seed, pixel, index, spp, 0, no_memo)
        fx, fy = film_position(cam, x, y, fu, fv)
        lu, lv = 0.0, 0.0
        if cam[CAM_LENS] > 0.0:
            lu, lv = u2d(smp, key, seed, pixel, index, spp, DIM_LENS, no_memo)
        ox, oy, oz, dx, dy, dz = camera_ray_at(cam, width, height, fx, fy, lu, lv)
        (kmax, px, py, pz, nx, ny, nz, wx, wy, wz, br, bg, bb, mat, lr, lg, lb,
         nr, alr, alg, alb, anx, any_, anz, dist) = visible_point(
            sc, stack, ox, oy, oz, dx, dy, dz, depth, smp, key, seed, pixel, index, spp,
            no_memo)
        rays += nr
        vp_aov[row, c, 0] += alr
        vp_aov[row, c, 1] += alg
        vp_aov[row, c, 2] += alb
        vp_aov[row, c, 3] += anx
        vp_aov[row, c, 4] += any_
        vp_aov[row, c, 5] += anz
        vp_aov[row, c, 6] += dist
        vp_kmax[row, c] = kmax
        vp_p[row, c, 0], vp_p[row, c, 1], vp_p[row, c, 2] = px, py, pz
        vp_n[row, c, 0], vp_n[row, c, 1], vp_n[row, c, 2] = nx, ny, nz
        vp_wo[row, c, 0], vp_wo[row, c, 1], vp_wo[row, c, 2] = wx, wy, wz
        vp_beta[row, c, 0], vp_beta[row, c, 1], vp_beta[row, c, 2] = br, bg, bb
        vp_mat[row, c] = mat
        ld[row, c, 0], ld[row, c, 1], ld[row, c, 2] = lr, lg, lb
    return rays


# ------------------------------------------------------------ hash grid

@kernel
def _hash(ix, iy, iz, mask):
    return ((ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791)) & mask


@kernel_inline
def cell_range(px, py, pz, r, inv_h):
    """The integer cells (lo xyz, hi xyz, inclusive) that a ball of radius r
    around p overlaps: the range a photon search walks."""
    return (np.int64(math.floor((px - r) * inv_h)), np.int64(math.floor((py - r) * inv_h)),
            np.int64(math.floor((pz - r) * inv_h)), np.int64(math.floor((px + r) * inv_h)),
            np.int64(math.floor((py + r) * inv_h)), np.int64(math.floor((pz + r) * inv_h)))


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
    """BSDF value at a visible point for a photon arriving along -wi; a
    diffuse point's albedo is in its beta already (visible_point: it may be
    textured), so its f here is 1 / pi. A glossy one's inputs are constants
    (the photon method refuses textured glossy materials)."""
    if mat_type[mat] == MAT_DIFFUSE:
        return INV_PI, INV_PI, INV_PI
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
                lx, ly, lz, hx, hy, hz = cell_range(px, py, pz, r, inv_h)
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
def knn_render(sc, cam, x0, y0, x1, y1, width, height, seed, spp, blocks, smp, depth,
               ppos, pdir, ppow, phit, cell, start, order, inv_h, big_r2, k, n_emitted,
               out_sum, out_sq, out_w, out_aov, row_rays, stacks, memos, aov_rows, best_d,
               best_i):
    """Classic photon map, visualised directly at the visible point: Ld plus
    the k-nearest-neighbour estimate sum f power / (n_emitted pi r_k^2). The
    tile loop of renderer/integrators/tile.py over the sample blocks, the
    AOVs' fold beside the radiance's."""
    for row in prange(y1 - y0):
        row_rays[row] = _knn_row(sc, cam, x0, y0, x1, width, height, seed, spp, blocks, smp,
                                 depth, ppos, pdir, ppow, phit, cell, start, order, inv_h,
                                 big_r2, k, n_emitted, out_sum, out_sq, out_w, out_aov,
                                 np.int64(row), stacks[row], memos[get_thread_id()], aov_rows[row],
                                 best_d[row], best_i[row])


@kernel
def _knn_row(sc, cam, x0, y0, x1, width, height, seed, spp, blocks, smp, depth, ppos, pdir,
             ppow, phit, cell, start, order, inv_h, big_r2, k, n_emitted, out_sum, out_sq,
             out_w, out_aov, row, stack, memo, scr, bd, bi):
    """Row `row` of `knn_render`, its rays traced; a kernel of its own
    (integrators/tile.py, "Compile time")."""
    mat_type, mat_rgb, mat_param = sc.mat_type, sc.mat_rgb, sc.mat_param
    mask = start.shape[0] - 2
    big_r = math.sqrt(big_r2)
    n_blk = n_samples(blocks)
    y = y0 + row
    rays = 0
    for x in range(x0, x1):
        c = x - x0
        pixel = y * width + x
        ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for blk in range(blocks.shape[0]):
            sr, sg, sb, tr, tg, tb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for s in range(blocks[blk, 0], blocks[blk, 1]):
                key = sample_key(seed, pixel, s)
                fu, fv = u2d(smp, key, seed, pixel, s, spp, 0, memo)
                fx, fy = film_position(cam, x, y, fu, fv)
                lu, lv = 0.0, 0.0
                if cam[CAM_LENS] > 0.0:
                    lu, lv = u2d(smp, key, seed, pixel, s, spp, DIM_LENS, memo)
                ox, oy, oz, dx, dy, dz = camera_ray_at(cam, width, height, fx, fy, lu, lv)
                (kmax, px, py, pz, nx, ny, nz, wx, wy, wz, br, bg, bb, mat, lr, lg, lb,
                 nr, alr, alg, alb, anx, any_, anz, dist) = visible_point(
                    sc, stack, ox, oy, oz, dx, dy, dz, depth, smp, key, seed, pixel, s, spp,
                    memo)
                rays += nr
                add_aov_sample(scr, alr, alg, alb, anx, any_, anz, dist)
                if kmax >= 2 and ppos.shape[0] > 0:
                    cnt = 0
                    worst = big_r2
                    lx, ly, lz, hx, hy, hz = cell_range(px, py, pz, big_r, inv_h)
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
                                    ex = ppos[q, 0] - px
                                    ey = ppos[q, 1] - py
                                    ez = ppos[q, 2] - pz
                                    d2 = ex * ex + ey * ey + ez * ez
                                    if d2 >= worst:
                                        continue
                                    facing = -(pdir[q, 0] * nx + pdir[q, 1] * ny
                                               + pdir[q, 2] * nz)
                                    if facing <= 0.0:
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
                        fr, fg, fb = _photon_f(mat_type, mat_rgb, mat_param, mat, nx, ny,
                                               nz, wx, wy, wz, -pdir[q, 0], -pdir[q, 1],
                                               -pdir[q, 2])
                        sr_ += fr * ppow[q, 0]
                        sg_ += fg * ppow[q, 1]
                        sb_ += fb * ppow[q, 2]
                    if rk2 > 0.0:
                        scale = 1.0 / (n_emitted * math.pi * rk2)
                        lr += br * sr_ * scale
                        lg += bg * sg_ * scale
                        lb += bb * sb_ * scale
                sr, sg, sb, tr, tg, tb = add_sample(sr, sg, sb, tr, tg, tb, lr, lg, lb)
            ar, ag, ab, qr, qg, qb = add_block(ar, ag, ab, qr, qg, qb,
                                               sr, sg, sb, tr, tg, tb)
            add_aov_block(scr)
        store_pixel(out_sum, out_sq, out_w, row, c, ar, ag, ab, qr, qg, qb, n_blk)
        store_aov(out_aov, row, c, scr)
    return rays
