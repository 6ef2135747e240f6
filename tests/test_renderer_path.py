"""The path tracer against answers known in closed form, and its invariances.

Tolerances are z-tests: |estimate - truth| <= Z * standard error, where the
standard error comes from the film's own per-pixel variance channels
(pixels use independent random numbers, so the variance of the image mean is
the sum of the pixels' variances of the mean over pixels^2). Z = 4.5 gives a
two-sided false-alarm rate of 7e-6 per check; the seeds are fixed, so a run
is repeatable. Where an estimator has zero variance (e.g. the first bounces
of the point-light furnace) the check is exact up to float rounding.
"""

import numpy as np
import pytest

from renderer import RenderSpec, build_scene, load_scene, merge, plan, render, resolve_document, run_unit
from renderer.plan import MIN_PASS_SAMPLES
from renderer.integrators.tile import start_tile
from renderer.samplers import sobol

Z = 4.5
CORNELL_LIGHT = (18.387, 13.9873, 6.75357)


def render_inline(scene, spec):
    """plan -> run every unit in this process -> merge, in unit order."""
    return merge(spec.width, spec.height, [run_unit(scene, spec, u) for u in plan(spec)])


def image_mean_and_stderr(film, channel=0):
    mean = film.mean()[..., channel]
    var = film.variance_of_mean()[..., channel]
    return mean.mean(), np.sqrt(var.sum()) / mean.size


@pytest.fixture(scope="module")
def furnace_point():
    return load_scene("furnace-point")


@pytest.fixture(scope="module")
def furnace_emitter():
    return load_scene("furnace-emitter")


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


@pytest.mark.parametrize("depth", [0, 1, 2, 3, 5, 8])
def test01_furnace_point_light_mean_is_one_minus_half_to_the_depth(furnace_point, depth):
    spec = RenderSpec(spp=256, depth=depth, width=16, height=16, tile_size=16, seed=11)
    film = render_inline(furnace_point, spec)
    mean, stderr = image_mean_and_stderr(film)
    expected = 1.0 - 0.5 ** depth
    assert abs(mean - expected) <= Z * stderr + 1e-12, (mean, expected, stderr)
    if depth <= 2:  # NEE to a point light from cosine-sampled bounces: no variance at all
        assert np.allclose(film.mean(), expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("depth", [0, 1, 2, 4, 8])
def test02_furnace_emitter_mean_is_one_minus_half_to_the_depth_plus_one(furnace_emitter, depth):
    spec = RenderSpec(spp=256, depth=depth, width=16, height=16, tile_size=16, seed=12)
    film = render_inline(furnace_emitter, spec)
    for c in range(3):
        mean, stderr = image_mean_and_stderr(film, c)
        expected = 1.0 - 0.5 ** (depth + 1)
        assert abs(mean - expected) <= Z * stderr + 1e-12, (c, mean, expected, stderr)


def _seed_spread(scene, sampler):
    """(observed std of 8 seeds' image means, the std their var channels predict)."""
    means, errs = [], []
    for seed in range(8):
        film = render_inline(scene, RenderSpec(spp=64, depth=4, width=16, height=16, tile_size=16,
                                               seed=100 + seed, sampler=sampler))
        m, e = image_mean_and_stderr(film)
        means.append(m)
        errs.append(e)
    return np.std(means, ddof=1), np.sqrt(np.mean(np.square(errs)))


def test03_furnace_standard_error_is_honest(furnace_emitter):
    """The var channels predict the spread of independent renders: eight seeds'
    image means scatter as the films' own standard errors say. The var channel
    is the variance of the mean of independent samples, so this holds for
    `random` exactly."""
    observed, predicted = _seed_spread(furnace_emitter, "random")
    # the sample std of 8 normals lies within [0.35, 1.75] x sigma with prob > 0.998
    assert 0.35 * predicted <= observed <= 1.75 * predicted, (observed, predicted)


def test03_furnace_standard_error_bounds_a_stratified_sampler(furnace_emitter):
    """With `sobol` (the default) a pixel's samples are stratified, not
    independent: the same var channel overstates the spread (here about 6x in
    standard deviation), so it is an upper bound, never an understatement."""
    observed, predicted = _seed_spread(furnace_emitter, "sobol")
    assert observed <= 1.75 * predicted, (observed, predicted)
    random_observed, _ = _seed_spread(furnace_emitter, "random")
    assert observed < random_observed, (observed, random_observed)


def test04_cornell_light_pixel_equals_emitter_radiance_at_depth_0(cornell):
    spec = RenderSpec(spp=16, depth=0, width=256, height=256, tile_size=32, seed=3)
    unit = next(u for u in plan(spec) if u.x0 <= 128 < u.x1 and u.y0 <= 36 < u.y1)
    film = merge(256, 256, [run_unit(cornell, spec, unit)])
    assert tuple(film.mean()[36, 128]) == pytest.approx(CORNELL_LIGHT, rel=1e-12)
    assert np.allclose(film.variance_of_mean()[36, 128], 0, atol=1e-12)
    # at depth 0 nothing but the emitter shows: the tile's pixels below the light are black
    assert np.all(film.mean()[unit.y1 - 1, unit.x0:unit.x1] == 0)


def test05_tiling_invariance_is_bit_exact(cornell):
    base = dict(spp=5, depth=4, width=48, height=40, seed=7)
    a = render_inline(cornell, RenderSpec(tile_size=16, **base))
    b = render_inline(cornell, RenderSpec(tile_size=64, **base))
    c = render_inline(cornell, RenderSpec(tile_size=7, **base))
    for other in (b, c):
        assert np.array_equal(a.sum, other.sum)
        assert np.array_equal(a.sum_sq, other.sum_sq)
        assert np.array_equal(a.weight, other.weight)
        assert np.array_equal(a.aov, other.aov)  # the AOVs take the same fold
    assert a.mean().max() > 0 and a.aov[..., 6].max() > 0


def test06_progressive_passes_merge_to_the_same_bits(cornell):
    spec = RenderSpec(spp=11, depth=3, width=24, height=24, tile_size=8, seed=5)
    whole = render_inline(cornell, spec)
    passes = merge(24, 24, [run_unit(cornell, spec, u) for u in plan(spec, progressive=True)])
    # one unit a pass: the frame holds fewer than MIN_UNIT_SAMPLES samples in each
    assert len(plan(spec, progressive=True)) == 4 and len(plan(spec)) == 9
    assert np.array_equal(whole.sum, passes.sum)
    assert np.array_equal(whole.sum_sq, passes.sum_sq)
    assert np.array_equal(whole.aov, passes.aov)
    # the first pass took two canonical blocks (64-pixel tiles are far below the floor,
    # a quarter of spp caps it): the bytes are the same whatever the passes
    assert sorted({(u.sample_start, u.sample_end) for u in plan(spec, progressive=True)}) == [
        (0, 2), (2, 4), (4, 8), (8, 11)]


def test06_progressive_passes_with_sobol_windows_merge_to_the_same_bits(cornell):
    # At 40 spp the eight-sample passes' samples plus the pairs' rotations
    # (sobol.TABLE_PAIRS - 1 positions) no longer cover a pixel's block, so
    # the `sobol` memo computes each such unit's window only (samplers/
    # sobol.py mark_window), the last pass's span wrapping around the block;
    # the pass of 16 covers it (a whole claim): the image's bytes are still
    # those of one pass.
    spec = RenderSpec(spp=40, depth=3, width=24, height=24, tile_size=8, seed=5)
    units = plan(spec, progressive=True)
    windows = sorted({(u.sample_start, u.sample_end) for u in units})
    assert windows == [(0, 8), (8, 16), (16, 32), (32, 40)]
    assert [w for w in windows if sobol.window_span(40, *w) < 40] == [(0, 8), (8, 16), (32, 40)]
    assert 32 + sobol.window_span(40, 32, 40) > 40  # the last window wraps around
    assert (start_tile(cornell, spec, units[-1]).memos < 0).any()  # the unit's memo is marked
    whole = render_inline(cornell, spec)
    passes = merge(24, 24, [run_unit(cornell, spec, u) for u in units])
    assert np.array_equal(whole.sum, passes.sum)
    assert np.array_equal(whole.sum_sq, passes.sum_sq)
    assert np.array_equal(whole.aov, passes.aov)


def test06_a_progressive_first_pass_renders_enough_to_outweigh_a_units_cost():
    # 64 x 64 tiles: 8 samples (32768 per tile) before the passes double
    spec = RenderSpec(spp=390, width=256, height=200, tile_size=64)
    passes = sorted({(u.sample_start, u.sample_end) for u in plan(spec, progressive=True)})
    assert passes[:4] == [(0, 8), (8, 16), (16, 32), (32, 64)]
    assert 64 * 64 * 8 >= MIN_PASS_SAMPLES > 64 * 64 * 4
    # a whole-frame tile of 256 x 200 pixels: one sample is enough
    whole = RenderSpec(spp=390, width=256, height=200, tile_size=256)
    assert plan(whole, progressive=True)[0].sample_end == 1
    # bdpt wants every small pass (its splat batches)
    assert plan(spec, progressive=True, small_passes=True)[0].sample_end == 1


@pytest.mark.parametrize("floor, shapes", [
    (3 * 64, {(16, 8)}),  # runs of two 8 x 8 tiles along a row (the last one shorter)
    (8 * 64, {(24, 16)}),  # bands of two whole rows of tiles
])
def test06_a_progressive_pass_groups_tiles_that_hold_few_samples(cornell, monkeypatch, floor,
                                                                  shapes):
    """A pass whose tiles hold fewer than MIN_UNIT_SAMPLES samples each is cut
    into runs of tiles along a row, or bands of whole rows, that hold that
    many; every pixel is in one unit of every pass, the unit count is what
    admission counts unplanned, and the bytes are those of one pass."""
    import importlib

    plan_module = importlib.import_module("renderer.plan")  # the module (`renderer.plan` is its function)

    monkeypatch.setattr(plan_module, "MIN_UNIT_SAMPLES", floor)
    spec = RenderSpec(spp=8, depth=3, width=24, height=24, tile_size=8, seed=5)
    units = plan(spec, progressive=True)
    assert [(u.sample_start, u.sample_end) for u in units if u.x0 == u.y0 == 0] == [
        (0, 2), (2, 4), (4, 8)]  # the first pass takes two blocks (a quarter of spp)
    assert len(units) == plan_module.count_units(spec, progressive=True)
    coverage = np.zeros((3, 24, 24), int)
    for u in units:
        coverage[u.pass_index, u.y0:u.y1, u.x0:u.x1] += 1
        assert u.samples >= floor or u.x1 == 24 or u.y1 == 24  # only the last of a row or band is short
    assert (coverage == 1).all()
    first = [u for u in units if u.pass_index == 0]
    assert {(u.x1 - u.x0, u.y1 - u.y0) for u in first[:1]} == shapes
    assert len(first) < 9  # 9 tiles
    whole = render_inline(cornell, spec)
    grouped = merge(24, 24, [run_unit(cornell, spec, u) for u in units])
    assert np.array_equal(whole.sum, grouped.sum)
    assert np.array_equal(whole.sum_sq, grouped.sum_sq)
    assert np.array_equal(whole.weight, grouped.weight)


def test07_local_process_pool_equals_inline(cornell):
    spec = RenderSpec(spp=4, depth=3, width=32, height=32, tile_size=16, seed=9)
    pooled = render("cornell-box", spec, workers=2)
    assert np.array_equal(pooled.sum, render_inline(cornell, spec).sum)


def test08_seed_changes_the_noise_not_the_mean(cornell):
    a = render_inline(cornell, RenderSpec(spp=4, depth=2, width=16, height=16, tile_size=16, seed=1))
    b = render_inline(cornell, RenderSpec(spp=4, depth=2, width=16, height=16, tile_size=16, seed=2))
    assert not np.array_equal(a.sum, b.sum)


def test09_cornell_is_lit_like_the_scene_says(cornell):
    """Coarse sanity of the layout at depth 1: red wall on the left, green on
    the right, row 0 at the top (the light's rows are bright)."""
    spec = RenderSpec(spp=16, depth=1, width=32, height=32, tile_size=32, seed=4)
    img = render_inline(cornell, spec).mean()
    left, right = img[16, 1], img[16, 30]
    assert left[0] > 3 * left[1] and right[1] > 2 * right[0]
    assert img[4:6, 14:18].mean() > img[26:28, 14:18].mean()


def _sphere_in_white_furnace(material, sky_albedo=0.0):
    """A unit sphere of `material` inside a sphere of radius 10 (diffuse, black
    unless `sky_albedo`) that emits radiance 1 inwards: whatever light the
    sphere reflects or transmits came from that uniform sky."""
    return build_scene(resolve_document({
        "camera": {"origin": [0, 0, 4], "target": [0, 0, 0], "fov": 40, "width": 16, "height": 16},
        "materials": {"black": {"type": "diffuse", "albedo": sky_albedo},
                      "glass": {"type": "dielectric", "ior": 1.5},
                      "mirror": {"type": "mirror", "tint": 0.8}},
        "shapes": [{"type": "sphere", "radius": 10, "material": "black", "flip_normals": True,
                    "emitter": {"type": "area", "radiance": 1}},
                   {"type": "sphere", "radius": 1, "material": material}]}))


def test10_glass_sphere_vanishes_in_a_white_furnace():
    """Smooth glass conserves energy and the 1/eta^2 radiance scaling on entry
    is undone on exit: with enough depth every pixel sees exactly the sky.
    (Forgetting either scaling gives 1/2.25 or 2.25 where the sphere is.)"""
    scene = _sphere_in_white_furnace("glass")
    film = render_inline(scene, RenderSpec(spp=16, depth=64, width=16, height=16, tile_size=16))
    assert np.allclose(film.mean(), 1.0, rtol=0, atol=1e-9)
    # depth 1 allows two segments: straight through the sphere needs three, so
    # only the Fresnel reflection (about 4 % head-on) is left at the centre
    shallow = render_inline(scene, RenderSpec(spp=16, depth=1, width=16, height=16, tile_size=16))
    assert shallow.mean()[8, 8, 0] < 0.5


def test11_mirror_sphere_reflects_the_sky_times_its_tint():
    scene = _sphere_in_white_furnace("mirror")
    img = render_inline(scene, RenderSpec(spp=16, depth=8, width=16, height=16, tile_size=16)).mean()
    assert img[8, 8] == pytest.approx([0.8, 0.8, 0.8], abs=1e-12)  # fully on the sphere
    assert img[0, 0] == pytest.approx([1.0, 1.0, 1.0], abs=1e-12)  # the sky itself
    assert np.all((img >= 0.8 - 1e-12) & (img <= 1.0 + 1e-12))



# -- AOVs (film.py): albedo, normal, depth of the first diffuse or glossy hit ----------------

def test12_albedo_aov_of_a_diffuse_furnace_is_its_reflectance(furnace_emitter):
    """Every camera sample of the furnace hits its grey sphere (albedo 0.5):
    the albedo layer is that reflectance in every pixel, whatever the noise
    of the beauty."""
    spec = RenderSpec(spp=16, depth=3, width=16, height=16, tile_size=8, seed=2)
    aovs = render_inline(furnace_emitter, spec).aovs()
    for c in "RGB":
        assert np.all(aovs[f"albedo.{c}"] == 0.5), c
    assert np.all(aovs["samples.Y"] == 16)
    # a pixel's normal is the mean of unit normals over its footprint on the
    # sphere: a hair shorter than 1, never longer
    length = np.linalg.norm(np.stack([aovs[f"normal.{c}"] for c in "XYZ"], axis=-1), axis=-1)
    assert np.all((length > 0.999) & (length <= 1.0 + 1e-12))


def test13_albedo_aov_follows_mirrors_and_glass_to_the_next_diffuse_surface():
    """A mirror or glass sphere in a grey-walled (albedo 0.25) emitting sphere:
    the albedo seen through it is the walls' 0.25 (Open Image Denoise's
    convention), not the mirror's tint 0.8 and not 0."""
    for material in ("mirror", "glass"):
        scene = _sphere_in_white_furnace(material, sky_albedo=0.25)
        spec = RenderSpec(spp=8, depth=16, width=16, height=16, tile_size=16)
        aovs = render_inline(scene, spec).aovs()
        assert np.allclose(aovs["albedo.G"], 0.25, rtol=0, atol=1e-15), material
        # depth is the first hit's distance: the sphere at the centre (4 - 1 = 3)
        assert 3.0 <= aovs["depth.Z"][8, 8] < 3.05 and aovs["depth.Z"][0, 0] > 10, material


def test14_normal_aov_of_an_axis_aligned_wall_is_that_axis(cornell):
    """Cornell box walls are axis-aligned: pixels that see only one wall hold
    its normal exactly (the red wall faces +x, the green one -x, the floor +y)."""
    spec = RenderSpec(spp=4, depth=1, width=32, height=32, tile_size=16, seed=3)
    aovs = render_inline(cornell, spec).aovs()
    n = np.stack([aovs[f"normal.{c}"] for c in "XYZ"], axis=-1)
    albedo = np.stack([aovs[f"albedo.{c}"] for c in "RGB"], axis=-1)
    assert albedo[16, 1, 0] > 3 * albedo[16, 1, 1]  # the red wall
    assert tuple(n[16, 1]) == (1.0, 0.0, 0.0)
    assert albedo[16, 30, 1] > 2 * albedo[16, 30, 0]  # the green wall
    assert tuple(n[16, 30]) == (-1.0, 0.0, 0.0)
    assert tuple(n[29, 8]) == (0.0, 1.0, 0.0)  # the floor


def test15_image_error_is_the_95th_percentile_of_lit_pixels_relative_error():
    """film.image_error: relative standard errors of the pixels brighter than
    1 % of the image mean, their 95th percentile; black pixels do not count,
    and an unknown variance makes it infinite."""
    from renderer.film import image_error, relative_error

    rng = np.random.default_rng(5)
    mean = rng.uniform(0.5, 2.0, (20, 30, 3))
    mean[:5] = 0.0  # a black band: its relative error means nothing
    var = (0.01 * mean) ** 2 * rng.uniform(0.5, 2.0, (20, 30, 1))
    lit = mean.mean(axis=-1) > 0.01 * mean.mean()
    expected = np.percentile(relative_error(mean, var)[lit], 95)
    assert image_error(mean, var) == expected and 0.005 < expected < 0.02
    var[10, 10] = np.inf
    assert image_error(mean, var) == np.inf
    # halving every variance lowers the statistic by sqrt(2)
    var[10, 10] = var[10, 11]
    assert image_error(mean, var / 2) == pytest.approx(image_error(mean, var) / np.sqrt(2))
