"""`raster`: a z-buffer rasterizer with local direct lighting.

| option | type | default | meaning |
|---|---|---|---|
| (none) | | | |

Triangles are projected to the image through the pinhole camera (clipped
against the near plane at 0.001), rasterized per sample position with edge
functions, and the nearest one wins by a depth test on perspective-correctly
interpolated camera depth. Spheres are tessellated (48 x 24 facets). Each
visible point is shaded locally: its emission (front side), plus, on diffuse
and glossy surfaces, the light of every light *without visibility*: point lights
exactly, area lights by one unshadowed light sample per pixel sample. Mirror
and glass surfaces have no local shading model here and show black.

`spp` supersamples: each pixel's sample positions come from the job's pixel
sampler like the path tracers' (dims 0-1; the light sample uses the pair
2-3 and dim 4), placed by the camera's filter (kernels/camera.py), so the
film converges to the filtered rasterized image. A thin-lens camera is
refused at submission (`check_scene`): a rasterizer has no lens. Neither consistent nor unbiased with
respect to the rendering equation (no shadows, no interreflection), as the
lecture's chart says; and fast: the cost is triangles x samples, with no
ray tracing at all. (Every triangle is tested against every tile; a real
rasterizer would bin triangles first: fine for the scenes here.)
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ..film import AOV_CHANNELS, PartialFilm
from ..kernels import kernel, kernel_parallel
from ..kernels.bsdf import MAT_DIFFUSE, MAT_GLOSSY
from ..kernels.camera import CAM_FILTER, CAM_FRADIUS, FILTER_BOX, camera_ray, film_position
from ..kernels.ggx import glossy_eval
from ..kernels.lights import sample_light
from ..kernels.rng import sample_key
from ..kernels.sampling import INV_PI
from ..errors import SpecError
from ..kernels.shading import shade_hit
from ..registry import SAMPLERS, Method
from ..samplers import NO_MEMO, u2d
from ..scene import camera_array
from .tile import tile_plan, unit_blocks

NEAR = 0.001
SPHERE_SEGMENTS, SPHERE_RINGS = 48, 24


def raster_mesh(scene):
    """(vertices (T, 3, 3), front normals, materials, lights) of every
    triangle plus the tessellated spheres; cached on the scene."""
    cached = getattr(scene, "_raster_mesh", None)
    if cached is not None:
        return cached
    a = scene.arrays
    verts, normals, mats, lights = [a.tri_p], [a.tri_n], [a.tri_mat], [a.tri_light]
    theta = np.linspace(0, math.pi, SPHERE_RINGS + 1)
    phi = np.linspace(0, 2 * math.pi, SPHERE_SEGMENTS + 1)
    unit = np.stack([np.sin(theta)[:, None] * np.cos(phi)[None, :],
                     np.sin(theta)[:, None] * np.sin(phi)[None, :],
                     np.cos(theta)[:, None] * np.ones_like(phi)[None, :]], axis=-1)
    for s in range(a.sph.shape[0]):
        p = a.sph[s, :3] + a.sph[s, 3] * unit
        quads = np.stack([p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]], axis=2).reshape(-1, 4, 3)
        tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        length = np.linalg.norm(n, axis=1)
        keep = length > 1e-12 * a.sph[s, 3] ** 2
        tris, n = tris[keep], n[keep] / length[keep, None]
        outward = np.sign(np.einsum("ij,ij->i", n, tris.mean(axis=1) - a.sph[s, :3]))
        n *= outward[:, None] * (-1.0 if a.sph_flip[s] else 1.0)
        verts.append(tris)
        normals.append(n)
        mats.append(np.full(len(tris), a.sph_mat[s], np.int32))
        lights.append(np.full(len(tris), a.sph_light[s], np.int32))
    mesh = (np.ascontiguousarray(np.concatenate(verts)), np.ascontiguousarray(np.concatenate(normals)),
            np.concatenate(mats).astype(np.int32), np.concatenate(lights).astype(np.int32))
    scene._raster_mesh = mesh
    return mesh


@kernel
def _to_camera(cam, px, py, pz):
    vx, vy, vz = px - cam[0], py - cam[1], pz - cam[2]
    return (vx * cam[3] + vy * cam[4] + vz * cam[5], vx * cam[6] + vy * cam[7] + vz * cam[8],
            vx * cam[9] + vy * cam[10] + vz * cam[11])


@kernel
def _rasterize_triangle(cam, width, height, c, x0, y0, x1, y1, tri, sample_x, sample_y,
                        zbuf, idbuf):
    """Depth-test the camera-space triangle c (3, 3) (all in front of the
    near plane) against the tile's sample positions; write zbuf/idbuf."""
    tx, ty = cam[12], cam[13]
    sx0 = ((c[0, 0] / c[0, 2]) / tx + 1.0) * 0.5 * width
    sy0 = (1.0 - (c[0, 1] / c[0, 2]) / ty) * 0.5 * height
    sx1 = ((c[1, 0] / c[1, 2]) / tx + 1.0) * 0.5 * width
    sy1 = (1.0 - (c[1, 1] / c[1, 2]) / ty) * 0.5 * height
    sx2 = ((c[2, 0] / c[2, 2]) / tx + 1.0) * 0.5 * width
    sy2 = (1.0 - (c[2, 1] / c[2, 2]) / ty) * 0.5 * height
    area = (sx1 - sx0) * (sy2 - sy0) - (sx2 - sx0) * (sy1 - sy0)
    if area == 0.0:
        return
    # a filter's sample may lie up to its radius outside its own pixel
    reach = 0 if cam[CAM_FILTER] == FILTER_BOX else int(math.ceil(cam[CAM_FRADIUS]))
    lo_x = max(x0, int(math.floor(min(sx0, min(sx1, sx2)))) - reach)
    hi_x = min(x1 - 1, int(math.floor(max(sx0, max(sx1, sx2)))) + reach)
    lo_y = max(y0, int(math.floor(min(sy0, min(sy1, sy2)))) - reach)
    hi_y = min(y1 - 1, int(math.floor(max(sy0, max(sy1, sy2)))) + reach)
    iz0, iz1, iz2 = 1.0 / c[0, 2], 1.0 / c[1, 2], 1.0 / c[2, 2]
    inv_area = 1.0 / area
    for y in range(lo_y, hi_y + 1):
        for x in range(lo_x, hi_x + 1):
            fx, fy = sample_x[y - y0, x - x0], sample_y[y - y0, x - x0]
            b0 = ((sx1 - fx) * (sy2 - fy) - (sx2 - fx) * (sy1 - fy)) * inv_area
            b1 = ((sx2 - fx) * (sy0 - fy) - (sx0 - fx) * (sy2 - fy)) * inv_area
            b2 = 1.0 - b0 - b1
            if b0 < 0.0 or b1 < 0.0 or b2 < 0.0:
                continue
            z = 1.0 / (b0 * iz0 + b1 * iz1 + b2 * iz2)  # perspective-correct depth
            if z < zbuf[y - y0, x - x0]:
                zbuf[y - y0, x - x0] = z
                idbuf[y - y0, x - x0] = tri


@kernel
def _raster_pass(verts, cam, width, height, x0, y0, x1, y1, sample_x, sample_y, zbuf, idbuf,
                 clip):
    """One depth-buffer pass over every triangle for the current samples."""
    zbuf[:, :] = np.inf
    idbuf[:, :] = -1
    for tri in range(verts.shape[0]):
        n_front = 0
        for k in range(3):
            cx, cy, cz = _to_camera(cam, verts[tri, k, 0], verts[tri, k, 1], verts[tri, k, 2])
            clip[k, 0], clip[k, 1], clip[k, 2] = cx, cy, cz
            if cz > NEAR:
                n_front += 1
        if n_front == 3:
            _rasterize_triangle(cam, width, height, clip, x0, y0, x1, y1, tri, sample_x,
                                sample_y, zbuf, idbuf)
        elif n_front > 0:
            # Sutherland-Hodgman against z = NEAR: a polygon of 3 or 4 vertices
            m = 0
            for k in range(3):
                a, b = k, (k + 1) % 3
                za, zb = clip[a, 2], clip[b, 2]
                if za > NEAR:
                    clip[3 + m, 0], clip[3 + m, 1], clip[3 + m, 2] = clip[a, 0], clip[a, 1], za
                    m += 1
                if (za > NEAR) != (zb > NEAR):
                    s = (NEAR - za) / (zb - za)
                    clip[3 + m, 0] = clip[a, 0] + s * (clip[b, 0] - clip[a, 0])
                    clip[3 + m, 1] = clip[a, 1] + s * (clip[b, 1] - clip[a, 1])
                    clip[3 + m, 2] = NEAR
                    m += 1
            for k in range(1, m - 1):  # fan
                for j, src in enumerate((3, 3 + k, 4 + k)):
                    clip[7 + j, 0], clip[7 + j, 1], clip[7 + j, 2] = \
                        clip[src, 0], clip[src, 1], clip[src, 2]
                _rasterize_triangle(cam, width, height, clip[7:10], x0, y0, x1, y1, tri,
                                    sample_x, sample_y, zbuf, idbuf)


@kernel
def _shade(sc, cam, width, height, fx, fy, z, tri, tri_n, tri_mat, tri_light, key, smp, seed,
           pixel, index, spp, memo):
    """Local shading of the visible point at camera depth z on triangle tri:
    (r, g, b, distance t to it; the camera ray is a unit vector; then the
    colour input and the shading normal there, for the AOVs). The scene's
    own triangles shade as every method does (kernels/shading.py); a
    sphere's tessellation (the rows past them) with its flat normals."""
    dx, dy, dz = camera_ray(cam, width, height, fx, fy)
    t = z / (dx * cam[9] + dy * cam[10] + dz * cam[11])
    px, py, pz = cam[0] + t * dx, cam[1] + t * dy, cam[2] + t * dz
    if tri < sc.tri_n.shape[0]:
        (fnx, fny, fnz, gx, gy, gz, nx, ny, nz, ar, ag, ab, alpha,
         mat, light) = shade_hit(sc, tri, px, py, pz, dx, dy, dz)
    else:
        nx, ny, nz = tri_n[tri, 0], tri_n[tri, 1], tri_n[tri, 2]
        fnx, fny, fnz, gx, gy, gz = nx, ny, nz, nx, ny, nz
        mat, light = tri_mat[tri], tri_light[tri]
        ar, ag, ab = sc.mat_rgb[mat, 0], sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2]
        alpha = sc.mat_param[mat, 1]
    r, g, b = 0.0, 0.0, 0.0
    if light >= 0 and -(dx * fnx + dy * fny + dz * fnz) > 0.0:  # emits from its front only
        r, g, b = sc.light_rgb[light, 0], sc.light_rgb[light, 1], sc.light_rgb[light, 2]
    cos_o = -(dx * nx + dy * ny + dz * nz)
    if cos_o <= 0.0 or -(dx * gx + dy * gy + dz * gz) <= 0.0:
        return r, g, b, t, ar, ag, ab, nx, ny, nz  # one-sided: the back side is black
    mtype = sc.mat_type[mat]
    if (mtype == MAT_DIFFUSE or mtype == MAT_GLOSSY) and sc.light_type.shape[0] > 0:
        ua, ub = u2d(smp, key, seed, pixel, index, spp, 2, memo)
        wx, wy, wz, dist, pdf, er, eg, eb, delta = sample_light(sc, px, py, pz, ua, ub)
        cos_i = wx * nx + wy * ny + wz * nz
        if pdf > 0.0 and cos_i > 0.0 and wx * gx + wy * gy + wz * gz > 0.0:
            if mtype == MAT_DIFFUSE:
                fr, fg, fb = ar * INV_PI, ag * INV_PI, ab * INV_PI
            else:
                fr, fg, fb, _ = glossy_eval(nx, ny, nz, -dx, -dy, -dz, wx, wy, wz,
                                            alpha, ar, ag, ab)
            k = cos_i / pdf  # unshadowed: no visibility test
            r += fr * er * k
            g += fg * eg * k
            b += fb * eb * k
    return r, g, b, t, ar, ag, ab, nx, ny, nz


@kernel_parallel
def _raster_tile(sc, verts, tri_n, tri_mat, tri_light, cam, x0, y0, x1, y1, width, height,
                 blocks, seed, smp, spp, centres, out_sum, out_sq, out_w, out_aov, sample_x, sample_y,
                 zbuf, idbuf, clip, block_acc, no_memo):
    """Render the tile: per sample index one z-buffer pass, then shading; sums
    formed per sample block like every other kernel (film.py), the AOVs'
    beside them (the visible triangle's albedo if it is diffuse or glossy, its
    normal, the distance; a rasterizer follows no mirror). Sample-major (one
    z-buffer pass per sample index), so no sampler memo (`no_memo`)."""
    h, w = y1 - y0, x1 - x0
    for bi in range(blocks.shape[0]):
        block_acc[:, :, :] = 0.0
        for s in range(blocks[bi, 0], blocks[bi, 1]):
            for row in prange(h):
                for c in range(w):
                    key = sample_key(seed, (y0 + row) * width + x0 + c, s)
                    if centres:
                        sample_x[row, c], sample_y[row, c] = x0 + c + 0.5, y0 + row + 0.5
                    else:
                        fu, fv = u2d(smp, key, seed, (y0 + row) * width + x0 + c, s, spp, 0,
                                     no_memo)
                        sample_x[row, c], sample_y[row, c] = film_position(
                            cam, x0 + c, y0 + row, fu, fv)
            _raster_pass(verts, cam, width, height, x0, y0, x1, y1, sample_x, sample_y, zbuf,
                         idbuf, clip)
            for row in prange(h):
                for c in range(w):
                    tri = idbuf[row, c]
                    if tri < 0:
                        continue
                    key = sample_key(seed, (y0 + row) * width + x0 + c, s)
                    r, g, b, dist, ar, ag, ab, nx, ny, nz = _shade(
                                           sc, cam, width, height, sample_x[row, c],
                                           sample_y[row, c], zbuf[row, c], tri, tri_n, tri_mat,
                                           tri_light, key, smp, seed,
                                           (y0 + row) * width + x0 + c, s, spp, no_memo)
                    block_acc[row, c, 0] += r
                    block_acc[row, c, 1] += g
                    block_acc[row, c, 2] += b
                    block_acc[row, c, 3] += r * r
                    block_acc[row, c, 4] += g * g
                    block_acc[row, c, 5] += b * b
                    mat = tri_mat[tri]
                    if sc.mat_type[mat] == MAT_DIFFUSE or sc.mat_type[mat] == MAT_GLOSSY:
                        block_acc[row, c, 6] += ar
                        block_acc[row, c, 7] += ag
                        block_acc[row, c, 8] += ab
                    block_acc[row, c, 9] += nx
                    block_acc[row, c, 10] += ny
                    block_acc[row, c, 11] += nz
                    block_acc[row, c, 12] += dist
        for row in prange(h):
            for c in range(w):
                for k in range(3):
                    out_sum[row, c, k] += block_acc[row, c, k]
                    out_sq[row, c, k] += block_acc[row, c, 3 + k]
                for k in range(7):
                    out_aov[row, c, k] += block_acc[row, c, 6 + k]
                out_w[row, c] += blocks[bi, 1] - blocks[bi, 0]


def _run(scene, spec, unit, centres=False):
    verts, tri_n, tri_mat, tri_light = raster_mesh(scene)
    w, h = unit.x1 - unit.x0, unit.y1 - unit.y0
    film = PartialFilm.zeros(unit.x0, unit.y0, w, h, aov=True)
    buffers = (np.empty((h, w)), np.empty((h, w)), np.empty((h, w)), np.empty((h, w), np.int64),
               np.empty((10, 3)), np.empty((h, w, 6 + AOV_CHANNELS)))
    cam = camera_array(scene.camera, spec.width, spec.height)
    _raster_tile(scene.arrays, verts, tri_n, tri_mat, tri_light, cam, unit.x0, unit.y0, unit.x1,
                 unit.y1, spec.width, spec.height,
                 unit_blocks(spec.spp, unit.sample_start, unit.sample_end), spec.seed,
                 SAMPLERS[spec.sampler].id, spec.spp, centres,
                 film.sum, film.sum_sq, film.weight, film.aov, *buffers, NO_MEMO)
    film.stats.update(samples=unit.samples, rays=0)
    return film, buffers[2]


def check_scene(spec, doc: dict, options: dict) -> None:
    """A rasterizer projects through a pinhole: it has no lens to blur with,
    and a sharp image of a thin-lens scene would misstate it."""
    if doc["camera"].get("type") == "thinlens":
        raise SpecError("method", "raster cannot render a thinlens camera (depth of field): a "
                        "rasterizer projects through a pinhole; use a ray-tracing method "
                        "(path, bdpt, ...) or a perspective camera")


def render_tile(scene, spec, unit, inputs=None, options=None) -> PartialFilm:
    return _run(scene, spec, unit)[0]


def depth_at_pixel_centres(scene, spec, unit) -> np.ndarray:
    """The tile's depth buffer (distance along each pixel-centre ray; inf where
    nothing is visible) from a one-sample pass at pixel centres."""
    from ..plan import Unit

    one = Unit(unit.index, unit.x0, unit.y0, unit.x1, unit.y1, 0, 1)
    single = type(spec)(**{**spec.to_dict(), "spp": 1})
    _, zbuf = _run(scene, single, one, centres=True)
    cam = camera_array(scene.camera, spec.width, spec.height)
    ys, xs = np.mgrid[unit.y0:unit.y1, unit.x0:unit.x1] + 0.5
    dirs = np.array([camera_ray(cam, spec.width, spec.height, x, y)
                     for x, y in zip(xs.ravel(), ys.ravel())]).reshape(*xs.shape, 3)
    return zbuf / (dirs @ cam[9:12])


METHODS = (Method(
    name="raster",
    description="Z-buffer rasterization with local direct lighting: no shadows, no "
                "interreflection; spp supersamples for antialiasing.",
    run=render_tile,
    plan=tile_plan,
    aovs=("albedo", "normal", "depth"),
    check_scene=check_scene,
    unsupported={"opacity masks": "its z-buffer keeps the nearest surface of a pixel whole"},
),)
