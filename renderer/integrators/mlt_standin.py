"""TEMPORARY stand-in for BDPT's one-strategy kernel, used by `mlt` until
renderer/integrators/bdpt.py lands (branch m5-bdpt): delete once mlt.py
calls the BDPT kernel.

`standin_contribution(sc, cam, width, height, depth, u, stack)` returns
(r, g, b, film_x, film_y) for the primary-sample vector `u`: the camera
ray through film position (u[0] W, u[1] H) and the path of exactly `depth`
bounces that path-nee would count (no Russian roulette): next event
estimation at the last non-specular vertex, or emission found through a
specular last bounce (or seen directly at depth 0). Summed over depths
0..D it is path-nee's estimator at depth D, so its image is path-mis's.

Dimensions: u[0], u[1] the film position; vertex k (k bounces done) reads
2 + 6 k + (0, 1) its scattering direction, + 2 the glass choice, + 3 the
light pick, + (4, 5) the point on the light. `standin_dims(depth)` is the
length of u a path of that depth can read.
"""

from __future__ import annotations

import numpy as np

from ..kernels import kernel, kernel_inline
from ..kernels.bsdf import MAT_DIFFUSE, MAT_GLOSSY, MAT_MIRROR, dielectric_sample, \
    diffuse_eval, diffuse_sample, reflect
from ..kernels.ggx import glossy_eval, glossy_sample
from ..kernels.geometry import intersect_arrays, offset_origin, surface_at_arrays
from ..kernels.lights import sample_light
from .path import camera_ray, shadow_ray

STANDIN_DIMS_PER_VERTEX = 6


@kernel
def standin_dims(depth):
    return 2 + STANDIN_DIMS_PER_VERTEX * (depth + 1)


@kernel_inline
def standin_contribution(sc, cam, width, height, depth, u, stack):
    fx, fy = u[0] * width, u[1] * height
    ox, oy, oz = cam[0], cam[1], cam[2]
    dx, dy, dz = camera_ray(cam, width, height, fx, fy)
    br, bg, bb = 1.0, 1.0, 1.0
    specular = True  # the pinhole is a delta: emission seen directly counts
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    n_lights = sc.light_type.shape[0]
    for k in range(depth + 1):
        t, prim = intersect_arrays(nodes, info, prims, tri, sph, stack,
                                   ox, oy, oz, dx, dy, dz, np.inf, False)
        if prim < 0:
            break
        hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
        nx, ny, nz, mat, light = surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light, sph,
                                                   sc.sph_flip, sc.sph_mat, sc.sph_light,
                                                   prim, hx, hy, hz)
        cos_o = -(dx * nx + dy * ny + dz * nz)
        if k == depth:
            if light >= 0 and cos_o > 0.0 and specular:
                return (br * sc.light_rgb[light, 0], bg * sc.light_rgb[light, 1],
                        bb * sc.light_rgb[light, 2], fx, fy)
            break
        base = 2 + STANDIN_DIMS_PER_VERTEX * k
        mtype = sc.mat_type[mat]
        ar, ag, ab = sc.mat_rgb[mat, 0], sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2]
        if mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY:
            if cos_o <= 0.0:
                break
            alpha = sc.mat_param[mat, 1]
            if k == depth - 1:  # the last segment goes to a sampled light point
                if n_lights == 0:
                    break
                wx, wy, wz, dist, pl, er, eg, eb, delta = sample_light(
                    sc, hx, hy, hz, u[base + 3], u[base + 4], u[base + 5])
                cos_i = wx * nx + wy * ny + wz * nz
                if pl <= 0.0 or cos_i <= 0.0:
                    break
                if mtype == MAT_DIFFUSE:
                    f, _ = diffuse_eval(cos_o, cos_i)
                    fr, fg, fb = ar * f, ag * f, ab * f
                else:
                    fr, fg, fb, _ = glossy_eval(nx, ny, nz, -dx, -dy, -dz, wx, wy, wz,
                                                alpha, ar, ag, ab)
                sx, sy, sz, tx, ty, tz, tmax = shadow_ray(hx, hy, hz, nx, ny, nz, wx, wy, wz, dist)
                if intersect_arrays(nodes, info, prims, tri, sph, stack,
                                    sx, sy, sz, tx, ty, tz, tmax, True)[1] >= 0:
                    break
                w = cos_i / pl
                return br * fr * er * w, bg * fg * eg * w, bb * fb * eb * w, fx, fy
            if mtype == MAT_GLOSSY:
                wx, wy, wz, sr, sg, sb, pdf = glossy_sample(
                    nx, ny, nz, -dx, -dy, -dz, alpha, ar, ag, ab, u[base], u[base + 1])
            else:
                wx, wy, wz, _, pdf = diffuse_sample(nx, ny, nz, u[base], u[base + 1])
                sr, sg, sb = ar, ag, ab
            if pdf <= 0.0:
                break
            br, bg, bb = br * sr, bg * sg, bb * sb
            specular = False
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
            dx, dy, dz = wx, wy, wz
        elif mtype == MAT_MIRROR:
            if cos_o <= 0.0:
                break
            dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
            br, bg, bb = br * ar, bg * ag, bb * ab
            specular = True
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
        else:
            dx, dy, dz, weight, _, side = dielectric_sample(
                dx, dy, dz, nx, ny, nz, sc.mat_param[mat, 0], u[base + 2])
            br, bg, bb = br * weight, bg * weight, bb * weight
            specular = True
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, side)
    return 0.0, 0.0, 0.0, fx, fy
