"""`raster`: the z-buffer finds what rays find; shading is local and unshadowed."""

import math

import numpy as np
import pytest

from renderer import RenderSpec, build_scene, load_scene, merge, plan, resolve_document, run_unit
from renderer.kernels.camera import camera_ray
from renderer.integrators.raster import depth_at_pixel_centres
from renderer.kernels.geometry import STACK_SIZE, intersect
from renderer.scene import camera_array


def render_inline(scene, spec):
    return merge(spec.width, spec.height, [run_unit(scene, spec, u) for u in plan(spec)])


def test01_depth_buffer_equals_primary_ray_hit_distance():
    scene = load_scene("cornell-box")
    spec = RenderSpec(method="raster", spp=1, depth=1, width=64, height=64, tile_size=32)
    cam = camera_array(scene.camera, 64, 64)
    stack = np.empty(STACK_SIZE, np.int64)
    for unit in plan(spec):
        z = depth_at_pixel_centres(scene, spec, unit)
        ref = np.array([[intersect(scene.arrays, stack, *cam[:3],
                                   *camera_ray(cam, 64, 64, x + 0.5, y + 0.5), np.inf)[0]
                         for x in range(unit.x0, unit.x1)] for y in range(unit.y0, unit.y1)])
        assert np.allclose(z, ref, rtol=1e-12, atol=0)


def test02_near_plane_clipping_keeps_what_is_in_front():
    """A floor running under and behind the camera is clipped, not dropped."""
    scene = build_scene(resolve_document({
        "camera": {"origin": [0, 1, 0], "target": [0, 0.5, -3], "fov": 60, "width": 32, "height": 32},
        "materials": {"m": {"type": "diffuse", "albedo": 0.5}},
        "shapes": [{"type": "rectangle", "material": "m", "emitter": {"type": "area", "radiance": 1},
                    "to_world": [{"scale": [10, 10, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}}]}]}))
    spec = RenderSpec(method="raster", spp=1, depth=1, width=32, height=32, tile_size=32)
    z = depth_at_pixel_centres(scene, spec, plan(spec)[0])
    cam = camera_array(scene.camera, 32, 32)
    stack = np.empty(STACK_SIZE, np.int64)
    ref = np.array([[intersect(scene.arrays, stack, *cam[:3], *camera_ray(cam, 32, 32, x + 0.5, y + 0.5),
                               np.inf)[0] for x in range(32)] for y in range(32)])
    assert np.isfinite(ref).sum() > 300
    assert np.allclose(z, ref, rtol=1e-12)


def test03_point_light_shading_is_exact_and_unshadowed():
    """A floor lit by a point light with a blocker between them: raster ignores
    the blocker (no visibility) and is exact at the pixel under the light."""
    scene = build_scene(resolve_document({
        "camera": {"origin": [0, 0.5, 2], "target": [0, 0, 0], "fov": 0.1, "width": 2, "height": 2},
        "materials": {"m": {"type": "diffuse", "albedo": 0.5}},
        "shapes": [{"type": "rectangle", "material": "m",
                    "to_world": [{"scale": [10, 10, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}}]},
                   {"type": "rectangle", "material": "m",
                    "to_world": [{"scale": [0.2, 0.2, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                                 {"translate": [0, 0.5, 0]}]}],
        "emitters": [{"type": "point", "position": [0, 1, 0], "intensity": math.pi}]}))
    img = render_inline(scene, RenderSpec(method="raster", spp=4, depth=1, width=2, height=2,
                                          tile_size=2)).mean()
    # albedo/pi * pi / 1^2 at the centre, no shadow; over the pixels' footprint
    # (radius ~4e-3 on the floor) the cos^3 falloff lowers it by at most 1e-4
    assert img.mean() == pytest.approx(0.5, rel=1e-4)
    shadowed = render_inline(scene, RenderSpec(method="direct", spp=4, depth=1, width=2, height=2,
                                               tile_size=2)).mean()
    assert np.all(shadowed == 0)


def test04_raster_tiling_invariance_and_depth_independence():
    scene = load_scene("cornell-box")
    a = render_inline(scene, RenderSpec(method="raster", spp=3, depth=1, width=40, height=24,
                                        tile_size=8, seed=2))
    b = render_inline(scene, RenderSpec(method="raster", spp=3, depth=5, width=40, height=24,
                                        tile_size=64, seed=2))
    assert np.array_equal(a.sum, b.sum) and np.array_equal(a.sum_sq, b.sum_sq)
