"""The path-tracing family: every estimator converges to the same answer.

Tolerances are z-tests on the films' own variance (see test_renderer_path.py):
Z = 4.5, fixed seeds.
"""

import math

import numpy as np
import pytest

from renderer import METHODS, RenderSpec, SpecError, build_scene, load_scene, merge, plan, \
    resolve_document, run_unit

Z = 4.5
LIGHT_SAMPLING = ["path-nee", "path-onesample", "path-mis", "path-mis/balance"]
ALL = ["path-bsdf", "path-bsdf/uniform"] + LIGHT_SAMPLING


def spec_for(method, **kw):
    name, _, option = method.partition("/")
    options = {}
    if option == "uniform":
        options["hemisphere"] = "uniform"
    if option == "balance":
        options["heuristic"] = "balance"
    return RenderSpec(method=name, options=options, **kw)


def render_inline(scene, spec):
    return merge(spec.width, spec.height, [run_unit(scene, spec, u) for u in plan(spec)])


def mean_and_stderr(film, channel=0):
    m = film.mean()[..., channel]
    return m.mean(), math.sqrt(film.variance_of_mean()[..., channel].sum()) / m.size


def furnace_points(n):
    """The point-light furnace with the intensity pi split over n coincident lights."""
    return build_scene(resolve_document({
        "camera": {"origin": [0, 0, 0], "target": [0, 0, -1], "fov": 60, "width": 16, "height": 16},
        "materials": {"grey": {"type": "diffuse", "albedo": 0.5}},
        "shapes": [{"type": "sphere", "material": "grey", "flip_normals": True}],
        "emitters": [{"type": "point", "position": [0, 0, 0], "intensity": math.pi / n}] * n}))


def test01_registry_lists_every_method_with_its_options():
    assert {"path-bsdf", "path-nee", "path-onesample", "path-mis", "path"} <= set(METHODS)
    assert METHODS["path"] is METHODS["path-mis"]
    assert [o.name for o in METHODS["path-bsdf"].options] == ["hemisphere", "roulette"]
    assert [o.name for o in METHODS["path-mis"].options] == ["heuristic", "roulette"]
    for name in ("path-nee", "path-onesample", "direct"):
        assert [o.name for o in METHODS[name].options] == ["roulette"]
    with pytest.raises(SpecError, match="unknown option"):
        RenderSpec(method="path-nee", options={"heuristic": "power"}).validate()
    with pytest.raises(SpecError, match="must be one of"):
        RenderSpec(method="path-mis", options={"heuristic": "max"}).validate()


@pytest.mark.parametrize("method", LIGHT_SAMPLING)
@pytest.mark.parametrize("lights", [1, 4])
@pytest.mark.parametrize("depth", [1, 3, 6])
def test02_point_light_furnace(method, lights, depth):
    film = render_inline(furnace_points(lights),
                         spec_for(method, spp=128, depth=depth, width=16, height=16, tile_size=16,
                                  seed=depth))
    mean, se = mean_and_stderr(film)
    assert abs(mean - (1 - 0.5 ** depth)) <= Z * se + 1e-12, (mean, se)


def test03_bsdf_sampling_cannot_find_point_lights():
    """The lecture: backward path tracing 'cannot intersect point lights'."""
    film = render_inline(load_scene("furnace-point"),
                         spec_for("path-bsdf", spp=16, depth=4, width=16, height=16, tile_size=16))
    assert np.all(film.sum == 0)


@pytest.mark.parametrize("method", ALL)
@pytest.mark.parametrize("depth", [0, 1, 4])
def test04_emitter_furnace(method, depth):
    film = render_inline(load_scene("furnace-emitter"),
                         spec_for(method, spp=128, depth=depth, width=16, height=16, tile_size=16,
                                  seed=10 + depth))
    mean, se = mean_and_stderr(film)
    assert abs(mean - (1 - 0.5 ** (depth + 1))) <= Z * se + 1e-12, (mean, se)


@pytest.mark.parametrize("method", ["path-bsdf", "path-mis"])
def test04_roulette_trades_rays_for_noise_never_for_bias(method):
    """Russian roulette's survival scale (the `roulette` option; 0 turns it
    off) in the emitter furnace at depth 8, where the throughput halves at
    every bounce: each scale gives the furnace's mean, a higher scale traces
    more rays (with 2 no path ends at the third vertex, with 1 half of them
    do), and roulette's noise is real: off has less variance than 0.5."""
    scene = load_scene("furnace-emitter")
    rays, variance = {}, {}
    for roulette in (0.0, 0.5, 1.0, 2.0):
        spec = RenderSpec(method=method, spp=64, depth=8, width=16, height=16, tile_size=16,
                          seed=21, sampler="random", options={"roulette": roulette})
        film = render_inline(scene, spec)
        mean, se = mean_and_stderr(film)
        assert abs(mean - (1 - 0.5 ** 9)) <= Z * se, (roulette, mean, se)
        rays[roulette] = film.stats["rays"]
        variance[roulette] = se ** 2
    assert rays[0.5] < rays[1.0] < rays[2.0] < rays[0.0], rays
    assert variance[0.0] < variance[0.5], variance
    with pytest.raises(SpecError, match="options.roulette"):
        RenderSpec(method="path-mis", options={"roulette": -1.0}).validate()


def _square_light_scene():
    return build_scene(resolve_document({
        "camera": {"origin": [0, 0.5, 2], "target": [0, 0, 0], "fov": 0.1, "width": 4, "height": 4},
        "materials": {"floor": {"type": "diffuse", "albedo": 0.5},
                      "black": {"type": "diffuse", "albedo": 0}},
        "shapes": [{"type": "rectangle", "material": "floor",
                    "to_world": [{"scale": [10, 10, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}}]},
                   {"type": "rectangle", "material": "black",
                    "to_world": [{"scale": [0.5, 0.5, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                                 {"translate": [0, 1, 0]}],
                    "emitter": {"type": "area", "radiance": 1.0}}]}))


@pytest.mark.parametrize("method", ALL + ["direct"])
def test05_direct_light_under_a_square_light(method):
    """L = albedo * Le * F(point -> square): every estimator, by z-test. An
    up-facing floor under an overhead light is where light sampling and
    shadow rays meet head-on: a shadow ray measured from the un-offset hit
    point once let the light shadow its own samples here."""
    a = 0.5
    corner = (a / math.sqrt(1 + a * a)) * math.atan(a / math.sqrt(1 + a * a)) / math.pi
    expected = 0.5 * 1.0 * 4 * corner
    film = render_inline(_square_light_scene(),
                         spec_for(method, spp=4096, depth=1, width=4, height=4, tile_size=4, seed=3))
    mean, se = mean_and_stderr(film)
    assert se < 0.02 * expected
    assert abs(mean - expected) <= Z * se, (mean, expected, se)


def _floor_under_white_sky(rho):
    return build_scene(resolve_document({
        "camera": {"origin": [0, 1, 0], "target": [0, 0, 0], "up": [0, 0, -1], "fov": 20,
                   "width": 100, "height": 100},
        "materials": {"floor": {"type": "diffuse", "albedo": rho},
                      "sky": {"type": "diffuse", "albedo": 0}},
        "shapes": [{"type": "rectangle", "material": "floor",
                    "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": -90}}]},
                   {"type": "sphere", "radius": 1000, "material": "sky", "flip_normals": True,
                    "emitter": {"type": "area", "radiance": 1.0}}]}))


def test06_hemisphere_estimators_under_a_uniform_sky():
    """Cosine sampling of a diffuse floor under a white sky returns exactly the
    albedo; uniform sampling has mean albedo and variance albedo^2 / 3."""
    rho = 0.6
    scene = _floor_under_white_sky(rho)
    base = dict(depth=1, width=100, height=100, tile_size=100, seed=1, spp=100)  # 10^6 samples
    cos = render_inline(scene, spec_for("path-bsdf", **base))
    assert np.allclose(cos.mean(), rho, rtol=0, atol=1e-12)
    assert np.allclose(cos.variance_of_mean(), 0, atol=1e-20)
    uni = render_inline(scene, spec_for("path-bsdf/uniform", **base))
    n = uni.weight.sum()
    mean = uni.sum[..., 0].sum() / n
    var = uni.sum_sq[..., 0].sum() / n - mean ** 2
    assert abs(mean - rho) <= Z * math.sqrt(rho ** 2 / 3 / n)
    assert var == pytest.approx(rho ** 2 / 3, rel=0.02)


@pytest.mark.parametrize("method", ALL + ["direct"])
def test07_tiling_invariance_for_every_method(method):
    scene = load_scene("cornell-box")
    a = render_inline(scene, spec_for(method, spp=3, depth=3, width=24, height=20, tile_size=8, seed=4))
    b = render_inline(scene, spec_for(method, spp=3, depth=3, width=24, height=20, tile_size=32, seed=4))
    assert np.array_equal(a.sum, b.sum) and np.array_equal(a.sum_sq, b.sum_sq)
    # the AOV layers GET /methods lists are there, and tiling-invariant too
    assert (a.aov is not None) == bool(METHODS[method.partition("/")[0]].aovs), method
    if a.aov is not None:
        assert np.array_equal(a.aov, b.aov) and a.aov[..., 6].max() > 0
        # albedo in [0, 1], normals at most unit length, distances positive
        assert a.aov[..., :3].min() >= 0 and np.all(a.aov[..., :3] <= a.weight[..., None])


def test08_direct_is_one_bounce_of_light_through_specular_chains():
    """`direct` lights the first diffuse surface only: the point-light furnace
    stays at 0.5 however deep; through a mirror it still sees direct light."""
    scene = furnace_points(1)
    for depth in (1, 4):
        film = render_inline(scene, RenderSpec(method="direct", spp=8, depth=depth, width=16,
                                               height=16, tile_size=16))
        assert np.allclose(film.mean(), 0.5, atol=1e-12)
    # equal to path-nee at depth 1 on a diffuse scene (the same samples: bit for bit)
    cornell = load_scene("cornell-box")
    a = render_inline(cornell, RenderSpec(method="direct", spp=4, depth=1, width=16, height=16,
                                          tile_size=16))
    b = render_inline(cornell, RenderSpec(method="path-nee", spp=4, depth=1, width=16, height=16,
                                          tile_size=16))
    assert np.array_equal(a.sum, b.sum)


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test09_glossy_floor_under_a_white_sky_reflects_its_directional_albedo(distribution):
    """Under a uniform sky of radiance 1, a surface's radiance is its
    directional albedo, the integral of f cos: measured here from the glossy
    sampler's own weights and compared with every estimator's render."""
    from numba import njit

    from renderer.kernels.ggx import glossy_sample
    from renderer.kernels.rng import sample_key, uniform

    alpha, spec = 0.3, 0.8
    signed = -alpha if distribution == "beckmann" else alpha  # the kernels' signed roughness
    wo = np.array([0.0, math.sin(math.radians(60)), math.cos(math.radians(60))])  # z up

    @njit
    def albedo(n):
        s = s2 = 0.0
        for i in range(n):
            key = sample_key(99, i, 0)
            w = glossy_sample(0.0, 0.0, 1.0, wo[0], wo[1], wo[2], signed, spec, spec, spec,
                              uniform(key, 0), uniform(key, 1))[3]
            s += w
            s2 += w * w
        return s / n, math.sqrt((s2 / n - (s / n) ** 2) / n)

    expected, expected_se = albedo(1_000_000)
    scene = build_scene(resolve_document({
        # looking down at 60 degrees from the normal, as wo above (floor normal +y here)
        "camera": {"origin": [0, math.cos(math.radians(60)), math.sin(math.radians(60))],
                   "target": [0, 0, 0], "fov": 0.5, "width": 4, "height": 4},
        "materials": {"floor": {"type": "glossy", "roughness": alpha, "specular": spec,
                                "distribution": distribution},
                      "sky": {"type": "diffuse", "albedo": 0}},
        "shapes": [{"type": "rectangle", "material": "floor",
                    "to_world": [{"scale": [50, 50, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}}]},
                   {"type": "sphere", "radius": 1000, "material": "sky", "flip_normals": True,
                    "emitter": {"type": "area", "radiance": 1.0}}]}))
    for method in ["path-bsdf", "path-nee", "path-onesample", "path-mis", "direct"]:
        film = render_inline(scene, RenderSpec(method=method, spp=4096, depth=1, width=4,
                                               height=4, tile_size=4, seed=8))
        mean, se = mean_and_stderr(film)
        assert abs(mean - expected) <= Z * math.hypot(se, expected_se), (method, mean, expected)


def polygon_form_factor(vertices, p, n):
    """Point-to-polygon form factor by Lambert's contour formula (exact):
    F = 1/(2 pi) sum over edges of theta_i (n . g_i), g_i the unit normal of
    the plane through p and edge i, theta_i the angle the edge subtends."""
    total = 0.0
    k = len(vertices)
    for i in range(k):
        a, b = vertices[i] - p, vertices[(i + 1) % k] - p
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        g = np.cross(a, b)
        total += math.atan2(np.linalg.norm(g), np.dot(a, b)) * np.dot(n, g / np.linalg.norm(g))
    return abs(total) / (2 * math.pi)


@pytest.mark.parametrize("method", ALL + ["direct"])
def test10_floor_under_a_coaxial_disk_light(method):
    """A diffuse floor of albedo rho under a coaxial disk light of radius r at
    height h: L = rho Le r^2 / (h^2 + r^2) for the disk; the scene's disk is
    a regular 256-gon, whose exact value (Lambert's formula) is 1.5e-4 below."""
    from renderer.scene import DISK_SEGMENTS

    rho, le, r, h = 0.7, 2.0, 0.6, 1.0
    scene = build_scene(resolve_document({
        "camera": {"origin": [0, 0.5, 2], "target": [0, 0, 0], "fov": 0.1, "width": 4, "height": 4},
        "materials": {"floor": {"type": "diffuse", "albedo": rho},
                      "black": {"type": "diffuse", "albedo": 0}},
        "shapes": [{"type": "rectangle", "material": "floor",
                    "to_world": [{"scale": [10, 10, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": -90}}]},
                   {"type": "disk", "material": "black",
                    "to_world": [{"scale": [r, r, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                                 {"translate": [0, h, 0]}],
                    "emitter": {"type": "area", "radiance": le}}]}))
    angles = np.linspace(0, 2 * math.pi, DISK_SEGMENTS, endpoint=False)
    polygon = np.stack([r * np.cos(angles), np.full_like(angles, h), r * np.sin(angles)], axis=1)
    expected = rho * le * polygon_form_factor(polygon, np.zeros(3), np.array([0.0, 1.0, 0.0]))
    disk = rho * le * r * r / (h * h + r * r)
    assert expected == pytest.approx(disk, rel=3e-4)
    film = render_inline(scene, spec_for(method, spp=4096, depth=1, width=4, height=4,
                                         tile_size=4, seed=13))
    mean, se = mean_and_stderr(film)
    assert se < 0.02 * expected
    assert abs(mean - expected) <= Z * se, (mean, expected, se)
