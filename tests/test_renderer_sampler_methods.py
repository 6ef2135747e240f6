"""Every pixel sampler drives every method: furnace means and tiling invariance.

The z-tests use the films' sample variance, which for the low-discrepancy
samplers overstates the error (their pixel estimates converge faster than
independent samples): conservative, never loose. Each pixel's pattern has
its own scramble, so pixels stay independent and the image mean's standard
error is the root of the summed pixel variances over the pixel count.
"""

import math

import numpy as np
import pytest

from renderer import METHODS, SAMPLERS, RenderSpec, build_scene, load_scene, merge, \
    render_serial, resolve_document, run_plan

Z = 4.5
PATH_METHODS = ["path-nee", "path-onesample", "path-mis"]


def render_inline(scene, spec):
    """The method's own plan (a tile plan or a DAG), run in unit order."""
    return merge(spec.width, spec.height, run_plan(scene, spec))


@pytest.fixture(scope="module")
def scenes():
    four = resolve_document("furnace-point")
    four["emitters"] = [dict(four["emitters"][0], intensity=[math.pi / 4] * 3)] * 4
    return {**{name: load_scene(name) for name in ("furnace-point", "furnace-emitter", "cornell-box")},
            "furnace-4-points": build_scene(four)}


@pytest.mark.parametrize("sampler", sorted(SAMPLERS))
@pytest.mark.parametrize("method", PATH_METHODS + ["path-bsdf"])
def test01_furnaces_for_every_sampler(scenes, sampler, method):
    cases = [("furnace-emitter", 3, 1 - 0.5 ** 4)]
    if method != "path-bsdf":  # BSDF sampling cannot reach a point light
        cases += [("furnace-point", 3, 1 - 0.5 ** 3), ("furnace-4-points", 2, 1 - 0.5 ** 2)]
    for name, depth, expected in cases:
        spec = RenderSpec(method=method, sampler=sampler, spp=64, depth=depth, width=12, height=12,
                          tile_size=12, seed=21)
        film = render_inline(scenes[name], spec)
        mean = film.mean()[..., 0]
        se = math.sqrt(film.variance_of_mean()[..., 0].sum()) / mean.size
        assert abs(mean.mean() - expected) <= Z * se + 1e-12, (name, mean.mean(), expected, se)


@pytest.mark.parametrize("sampler", sorted(SAMPLERS))
def test02_tiling_invariance_for_every_method_and_sampler(scenes, sampler):
    """Each method through its own plan (a DAG for light, bdpt, mlt, photon,
    radiosity): bit-identical across tile sizes, but BDPT, whose t = 1 splats
    are summed per tile unit (equal to rounding)."""
    for method in dict.fromkeys(m.name for m in METHODS.values()):
        base = dict(method=method, sampler=sampler, spp=5, depth=3, width=20, height=12, seed=6)
        a = render_serial(scenes["cornell-box"], RenderSpec(tile_size=4, **base))
        b = render_serial(scenes["cornell-box"], RenderSpec(tile_size=32, **base))
        if method == "bdpt":
            np.testing.assert_allclose(a.mean(), b.mean(), rtol=1e-10, atol=1e-13)
        else:
            assert np.array_equal(a.mean(), b.mean()), method
            assert np.array_equal(a.variance_of_mean(), b.variance_of_mean()), method


def test03_samplers_change_the_image_not_its_expectation(scenes):
    """Different samplers give different pixels (they are wired in), and the
    stratified ones reduce the error of a smooth pixel integral: a
    direct-lit Cornell box at depth 1 is closer to a long reference with
    sobol than with random at equal spp."""
    scene = scenes["cornell-box"]
    ref = render_inline(scene, RenderSpec(method="path-mis", spp=1024, depth=1, width=24, height=24,
                                          tile_size=24, seed=99)).mean()
    err = {}
    for sampler in ("random", "sobol"):
        img = render_inline(scene, RenderSpec(method="path-mis", sampler=sampler, spp=64, depth=1,
                                              width=24, height=24, tile_size=24, seed=5)).mean()
        err[sampler] = np.sqrt(np.mean((img - ref) ** 2))
    assert err["sobol"] < err["random"]
