"""The camera: Mitsuba's sensor convention (`to_world`, `fov_axis`), the thin
lens in every method, and reconstruction filters by filter importance
sampling (kernels/camera.py)."""

import copy
import math

import numpy as np
import pytest
from numba import njit

from chi2util import chi2_pvalue, sidak
from renderer import RenderSpec, SceneError, build_scene, render_serial, resolve_document
from renderer.errors import SpecError
from renderer.integrators import mlt
from renderer.kernels import camera as kc
from renderer.runtime import run_plan
from renderer.scene import camera_array
from test_renderer_light_bdpt import assert_agree, block_stats, z_pass_rate

ALPHA = 0.01
SEED = 2


def look_at(origin, target, up):
    """Mitsuba's Transform4f.look_at: columns (left, up, dir, origin), with
    left = normalize(up x dir) (src/core/transform.h)."""
    o, t, u = (np.asarray(v, float) for v in (origin, target, up))
    d = (t - o) / np.linalg.norm(t - o)
    left = np.cross(u / np.linalg.norm(u), d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def two_lights_doc(camera, radiance_left=(4.0, 0.0, 0.0), radiance_right=(0.0, 0.0, 4.0)):
    """A red emitter on the world's -x side and a blue one on +x, both facing
    a camera at the origin that looks down -z with +y up."""
    def panel(x, radiance):
        return {"type": "rectangle", "material": "m", "emitter": {"type": "area",
                                                                   "radiance": list(radiance)},
                "to_world": [{"scale": [0.4, 0.4, 1]}, {"translate": [x, 0, -3]}]}
    return {"camera": camera, "materials": {"m": {"type": "diffuse", "albedo": 0.5}},
            "shapes": [panel(-0.7, radiance_left), panel(0.7, radiance_right)]}


def small_render(doc, method="path-mis", **kw):
    spec = dict(method=method, spp=4, depth=0, width=16, height=8, tile_size=8, seed=1)
    spec.update(kw)
    return render_serial(build_scene(resolve_document(doc)), RenderSpec(**spec)).mean()


def test01_camera_fields_are_validated_with_their_location():
    good = {"origin": [0, 0, 0], "target": [0, 0, -1], "fov": 40}
    bad = [
        ({"type": "thinlens", "focus_distance": 1}, "camera", "aperture_radius"),
        ({"type": "thinlens", "aperture_radius": 0.1}, "camera", "focus_distance"),
        ({"type": "thinlens", "aperture_radius": -0.1, "focus_distance": 1},
         "camera.aperture_radius", ">="),
        ({"type": "thinlens", "aperture_radius": 0.1, "focus_distance": 0},
         "camera.focus_distance", ">="),
        ({"aperture_radius": 0.1}, "camera.aperture_radius", "thinlens"),
        ({"type": "orthographic"}, "camera.type", "thinlens"),
        ({"aperture": 0.1}, "camera.aperture", "unknown field"),
        ({"fov_axis": "diag"}, "camera.fov_axis", "diagonal"),
        ({"filter": {"type": "mitchell"}}, "camera.filter.type", "gaussian"),
        ({"filter": {"type": "tent", "stddev": 1}}, "camera.filter.stddev", "unknown field"),
        ({"filter": {"type": "tent", "radius": 0}}, "camera.filter.radius", ">="),
        ({"filter": {"type": "gaussian", "stddev": 50}}, "camera.filter.stddev", "<="),
        ({"to_world": np.diag([2.0, 2, 2, 1]).tolist(), "origin": None}, "camera.to_world",
         "either"),
    ]
    for extra, location, words in bad:
        cam = {**good, **extra}
        with pytest.raises(SceneError) as err:
            resolve_document(two_lights_doc({k: v for k, v in cam.items() if v is not None}))
        assert err.value.location == location and words in str(err.value), (extra, err.value)
    scaled = {"to_world": np.diag([2.0, 2, 2, 1]).tolist(), "fov": 40}
    with pytest.raises(SceneError, match="no scale") as err:
        resolve_document(two_lights_doc(scaled))
    assert err.value.location == "camera.to_world"
    lens = resolve_document(two_lights_doc({**good, "type": "thinlens", "aperture_radius": 0.1,
                                            "focus_distance": 2, "filter": "tent"}))["camera"]
    assert lens["filter"] == {"type": "tent", "radius": 1.0}
    assert lens["aperture_radius"] == 0.1 and lens["focus_distance"] == 2
    # a pinhole with the default box keeps its document (and so its hash)
    plain = resolve_document(two_lights_doc({**good, "filter": {"type": "box"}}))["camera"]
    assert plain == resolve_document(two_lights_doc(good))["camera"]
    assert "filter" not in plain and "aperture_radius" not in plain


def test02_to_world_is_mitsubas_sensor_convention():
    """A Mitsuba look-at gives the picture of origin/target/up: what lies to
    the camera's left (world -x here) is on the left of the image; a mirror
    (scale x = -1 first, as many published scenes have) swaps the sides as
    Mitsuba does; fov_axis diagonal spans the image's diagonal."""
    o, t, u = [0, 0, 0], [0, 0, -1], [0, 1, 0]
    lookat = {"origin": o, "target": t, "up": u, "fov": 60}
    mitsuba = {"to_world": look_at(o, t, u).tolist(), "fov": 60}
    for cam in (lookat, mitsuba):
        img = small_render(two_lights_doc(cam))
        left, right = img[:, :8], img[:, 8:]
        assert left[..., 0].sum() > 0 and left[..., 2].sum() == 0, cam
        assert right[..., 2].sum() > 0 and right[..., 0].sum() == 0, cam
    assert np.array_equal(small_render(two_lights_doc(lookat)), small_render(two_lights_doc(mitsuba)))
    mirrored = {"to_world": (look_at(o, t, u) @ np.diag([-1.0, 1, 1, 1])).tolist(), "fov": 60}
    img = small_render(two_lights_doc(mirrored))
    assert img[:, :8, 2].sum() > 0 and img[:, :8, 0].sum() == 0
    assert img[:, 8:, 0].sum() > 0 and img[:, 8:, 2].sum() == 0
    # the same matrix as a list of operations
    ops = {"to_world": [{"scale": [-1, 1, 1]}, {"rotate": {"axis": [0, 1, 0], "angle": 180}}],
           "fov": 60}
    assert np.allclose(camera_array(resolve_document(two_lights_doc(ops))["camera"], 16, 8),
                       camera_array(resolve_document(two_lights_doc(mirrored))["camera"], 16, 8))
    cam = camera_array({**lookat, "fov_axis": "diagonal"}, 16, 8)
    half_diagonal = math.hypot(cam[kc.CAM_TX], cam[kc.CAM_TY])
    assert half_diagonal == pytest.approx(math.tan(math.radians(30)))
    assert cam[kc.CAM_TX] / cam[kc.CAM_TY] == pytest.approx(2.0)


@njit(cache=False)
def _draw(cam, us, out):
    for i in range(us.shape[0]):
        out[i] = kc.filter_sample(cam, us[i])


@njit(cache=False)
def _lens(cam, us, out):
    for i in range(us.shape[0]):
        x, y, z = kc.lens_point(cam, us[i, 0], us[i, 1])
        out[i, 0], out[i, 1], out[i, 2] = x, y, z


def _cam(**camera):
    base = {"type": "perspective", "origin": [0, 0, 0], "target": [0, 0, -1], "up": [0, 1, 0],
            "fov": 40, "fov_axis": "x"}
    return camera_array({**base, **camera}, 8, 8)


def test03_filter_and_lens_sampling_match_their_densities():
    """chi^2 of the filters' offsets against filter_eval (which integrates to
    1) and of the lens points against the uniform disk."""
    rng = np.random.default_rng(3)
    n = 200_000
    filters = [{"type": "tent", "radius": 1.0}, {"type": "tent", "radius": 1.7},
               {"type": "gaussian", "stddev": 0.5}, {"type": "gaussian", "stddev": 0.3}]
    level = sidak(ALPHA, len(filters) + 1)
    for filt in filters:
        cam = _cam(filter=filt)
        rad = cam[kc.CAM_FRADIUS]
        edges = np.linspace(-rad, rad, 81)
        xs = np.linspace(-rad, rad, 80 * 64 + 1)
        g = np.array([kc.filter_eval(cam, x) for x in xs])
        cdf = np.concatenate([[0.0], np.cumsum((g[1:] + g[:-1]) / 2 * np.diff(xs))])
        assert cdf[-1] == pytest.approx(1.0, abs=1e-4), filt  # normalised: samples weigh 1
        out = np.empty(n)
        _draw(cam, rng.random(n), out)
        assert np.all(np.abs(out) <= rad), filt
        observed, _ = np.histogram(out, bins=edges)
        expected = n * np.diff(cdf[::64])
        assert chi2_pvalue(observed, expected) > level, filt
    box = _cam()  # the box keeps the uniform position in the pixel
    assert kc.film_position(box, 3, 5, 0.25, 0.75) == (3.25, 5.75)
    r = 0.3
    cam = _cam(type="thinlens", aperture_radius=r, focus_distance=2.0)
    pts = np.empty((n, 3))
    _lens(cam, rng.random((n, 2)), pts)
    assert np.allclose(pts[:, 2], 0.0) and np.all(np.hypot(pts[:, 0], pts[:, 1]) <= r * (1 + 1e-12))
    bins = 24
    observed, _, _ = np.histogram2d(pts[:, 0], pts[:, 1], bins=bins, range=[[-r, r], [-r, r]])
    fine = (np.arange(bins * 64) + 0.5) / (bins * 64) * 2 * r - r  # cell areas inside the disk
    inside = (fine[:, None] ** 2 + fine[None, :] ** 2 <= r * r).reshape(bins, 64, bins, 64)
    expected = n * inside.mean(axis=(1, 3)) * (2 * r / bins) ** 2 / (math.pi * r * r)
    assert chi2_pvalue(observed, expected) > level


def test04_thin_lens_of_aperture_zero_is_the_pinhole_bit_for_bit():
    pinhole = {"origin": [0, 0, 3.9], "target": [0, 0, 0], "fov": 39.3, "fov_axis": "smaller"}
    lens0 = {**pinhole, "type": "thinlens", "aperture_radius": 0.0, "focus_distance": 3.0}
    base = resolve_document("cornell-box")
    scenes = [build_scene(resolve_document({**base, "camera": c})) for c in (pinhole, lens0)]
    for method in ("path-mis", "bdpt", "light", "photon"):
        spec = RenderSpec(method=method, spp=2, depth=2, width=8, height=8, tile_size=8, seed=5)
        a, b = (render_serial(s, spec) for s in scenes)
        assert np.array_equal(a.sum, b.sum) and np.array_equal(a.weight, b.weight), method
        assert (a.splat is None) == (b.splat is None), method
        if a.splat is not None:
            assert np.array_equal(a.splat, b.splat), method


def test05_focus_plane_is_sharp_and_the_rest_blurs():
    """A lit panel on the focus plane gives the pinhole's image (every lens
    ray through a film position meets the panel where the pinhole's does);
    focused elsewhere the panel's light spreads (its edges blur)."""
    pinhole = {"origin": [0, 0, 0], "target": [0, 0, -1], "fov": 60}
    doc = two_lights_doc(pinhole, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    sharp = small_render(doc, spp=16)
    focused = small_render(two_lights_doc({**pinhole, "type": "thinlens", "aperture_radius": 0.2,
                                           "focus_distance": 3.0}, (1.0, 1.0, 1.0),
                                          (1.0, 1.0, 1.0)), spp=16)
    blurred = small_render(two_lights_doc({**pinhole, "type": "thinlens", "aperture_radius": 0.2,
                                           "focus_distance": 1.0}, (1.0, 1.0, 1.0),
                                          (1.0, 1.0, 1.0)), spp=16)
    assert np.allclose(focused, sharp, atol=1e-12)
    partial = lambda img: np.count_nonzero((img[..., 0] > 0.02) & (img[..., 0] < 0.98))
    assert partial(blurred) > partial(sharp) + 8  # soft edges


def _lens_scene(filt, lens=True):
    """A lit panel facing the camera over a diffuse floor it lights (no
    surface hugs the light: the z-tests below need tails that are not heavy)."""
    cam = {"origin": [0, 0.2, 0], "target": [0, -0.3, -3], "fov": 50, "filter": filt}
    if lens:
        cam.update(type="thinlens", aperture_radius=0.2, focus_distance=1.5)
    return build_scene(resolve_document({
        "camera": cam, "materials": {"m": {"type": "diffuse", "albedo": 0.7}},
        "shapes": [
            {"type": "rectangle", "material": "m", "emitter": {"type": "area", "radiance": 3},
             "to_world": [{"scale": [0.6, 0.4, 1]}, {"translate": [0.3, 0.0, -3]}]},
            {"type": "rectangle", "material": "m",
             "to_world": [{"scale": [3, 3, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}},
                          {"translate": [0, -1, -3]}]}]}))


def test06_light_tracing_bdpt_and_mlt_agree_with_path_tracing_through_lens_and_filter(
        monkeypatch):
    """Light tracing, BDPT's t = 1 strategies and MLT splat through the lens
    and the filter's weights (MLT also over the filter's margin); path
    tracing samples both on the camera side: the same image (2x2 blocks of a
    16x16 frame, z-test with each side's own variance, Sidak-corrected, and
    the test's own power against a scale of 10 %, 25 % for MLT). Only blocks
    the reference sees lit count: where the filter's tail reaches the light
    from the dark, path tracing's estimate is a handful of rare hits and its
    sample variance says nothing."""
    wide = {"type": "gaussian", "stddev": 1.0}  # 4 pixels' radius: a blur the blocks see
    scene = _lens_scene(wide)
    kw = dict(depth=2, width=16, height=16, tile_size=16)
    reference = run_plan(scene, RenderSpec(method="path-mis", spp=512, seed=1, **kw))

    def lit_blocks(films, block):
        mean, var = block_stats(films, 16, 16, block)
        ref_mean, ref_var = block_stats(reference, 16, 16, block)
        lit = ref_mean.min(axis=-1) > 0.05
        assert lit.sum() >= 16 // block  # a test of something
        return ref_mean[lit], ref_var[lit], mean[lit], var[lit]

    # the test sees both: light tracing without the lens, or without the filter, fails it
    for other in (_lens_scene(wide, lens=False), _lens_scene({"type": "box"})):
        films = run_plan(other, RenderSpec(method="light", spp=512, seed=2, **kw))
        assert z_pass_rate(*lit_blocks(films, 2)) < 0.99, other.camera
    # MLT's chains are noisier per mutation and its variance comes from its
    # chain units' batches: 32 of them, over 4x4 blocks, and less power
    monkeypatch.setattr(mlt, "CHAIN_UNITS", 32)
    runs = {"light": (dict(spp=512), 2, 0.1), "bdpt": (dict(spp=256), 2, 0.1),
            "mlt": (dict(spp=256, options={"bootstrap": 200_000}), 4, 0.25)}
    for method, (run, block, power) in runs.items():
        films = run_plan(scene, RenderSpec(method=method, seed=SEED, **run, **kw))
        ref_mean, ref_var, mean, var = lit_blocks(films, block)
        # MLT's normalisation b is one estimate for the whole frame: its error too
        var = var + mean ** 2 * max(f.splat_scale_rel_var for f in films)
        assert np.all(np.isfinite(var))
        assert z_pass_rate(ref_mean, ref_var, mean, var) >= 0.99, method
        assert z_pass_rate(ref_mean, ref_var, mean, var, 1 - power) < 0.99, method
        assert z_pass_rate(ref_mean, ref_var, mean, var, 1 + power) < 0.99, method


def test07_filters_are_tiling_invariant_and_raster_refuses_the_lens():
    for filt in ({"type": "tent", "radius": 1.5}, {"type": "gaussian", "stddev": 0.5}):
        for method in ("path-mis", "bdpt", "raster"):
            scene = _lens_scene(filt, lens=method != "raster")
            spec = dict(method=method, spp=4, depth=2, width=12, height=10, seed=4)
            a = render_serial(scene, RenderSpec(tile_size=4, **spec))
            b = render_serial(scene, RenderSpec(tile_size=5, **spec))
            assert np.array_equal(a.sum, b.sum) and np.array_equal(a.sum_sq, b.sum_sq), method
            if a.splat is not None:
                assert np.allclose(a.splat, b.splat, rtol=1e-12, atol=1e-12)
    with pytest.raises(SpecError, match="raster cannot render a thinlens camera"):
        RenderSpec(method="raster").validate(scene=_lens_scene({"type": "box"}).doc)
