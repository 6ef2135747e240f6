"""Rendering to a noise target (renderer/target.py): passes added tile by tile
until the error statistic meets the target; the same bytes on any number of
processes; an achieved error the reference confirms; DAG methods refused."""

from __future__ import annotations

import numpy as np
import pytest

from renderer import LocalPool, RenderSpec, SpecError, load_scene, merge, plan, run_unit
from renderer.target import Target, render_to_target, supports_target

Z = 4.5
SPEC = RenderSpec(method="path-mis", depth=5, width=32, height=32, tile_size=8, seed=3)


@pytest.fixture(scope="module")
def pools():
    with LocalPool(1) as one, LocalPool(2) as two:
        yield one, two


def test01_the_same_bytes_on_one_process_or_two(pools):
    """Decisions read complete passes merged in unit order: which tiles stop,
    and so the image, do not depend on the worker count."""
    target = Target(rel_error=0.25, max_spp=1024)
    (a, ra), (b, rb) = (render_to_target("cornell-box", SPEC, target, pool=p) for p in pools)
    for name in ("sum", "sum_sq", "weight", "aov"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert (ra.passes, ra.units_run, ra.units_skipped, ra.stopped) == \
        (rb.passes, rb.units_run, rb.units_skipped, rb.stopped)
    # adaptive: some tiles stopped while others went on
    assert ra.stopped == "target" and ra.units_skipped > 0
    assert a.weight.min() < a.weight.max() <= 1024


@pytest.mark.parametrize("scene", ["cornell-box", "veach-mis"])
def test02_the_achieved_error_meets_the_target_and_the_reference_agrees(pools, scene):
    """The statistic (film.image_error) of the result is within the target, and
    the error it claims is the error there is: against an 8192-spp reference,
    z = (I - ref) / sqrt(var + var_ref) over the counted pixels has a mean
    square of 1 within Z empirical standard errors (measured: cornell-box
    0.96, z = -0.7; veach-mis 1.25, z = 2.6, where tiles that stop on a low
    variance estimate carry some of it into the image)."""
    film, report = render_to_target(scene, SPEC, Target(rel_error=0.2, max_spp=1024),
                                     pool=pools[1])
    assert report.stopped == "target" and film.image_error() <= 0.2
    ref_spec = RenderSpec(method="path-mis", depth=5, width=32, height=32, tile_size=32,
                          seed=99, spp=8192, sampler="random")
    sc = load_scene(scene)
    ref = merge(32, 32, [run_unit(sc, ref_spec, u) for u in plan(ref_spec)])
    mean, var = film.mean(), film.variance_of_mean()
    lum = mean.mean(axis=-1)
    counted = lum > 0.01 * lum.mean()
    with np.errstate(invalid="ignore", divide="ignore"):
        z = ((mean - ref.mean()) / np.sqrt(var + ref.variance_of_mean()))[..., 1][counted]
    z2 = z[np.isfinite(z)] ** 2
    assert z2.size > 500
    assert abs(z2.mean() - 1.0) <= Z * z2.std(ddof=1) / np.sqrt(z2.size), z2.mean()


@pytest.mark.parametrize("method", ["bdpt", "light", "mlt", "photon", "radiosity"])
def test03_dag_and_splatting_methods_are_refused_naming_the_target(method):
    assert not supports_target(method)
    with pytest.raises(SpecError) as info:
        render_to_target("cornell-box", RenderSpec(method=method, depth=3, width=8, height=8,
                                                   tile_size=8), Target(0.1, 16))
    assert info.value.field == "target" and "noise target" in str(info.value)


@pytest.mark.parametrize("field,target", [("target.rel_error", Target(0.0, 16)),
                                          ("target.rel_error", Target(1.5, 16)),
                                          ("target.max_spp", Target(0.1, 0)),
                                          ("target.max_seconds", Target(0.1, 16, -1.0)),
                                          # (error / target)^2 overflowed in the ETA
                                          ("target.rel_error", Target(1e-300, 16)),
                                          ("target.rel_error", Target(True, 16)),
                                          ("target.max_seconds", Target(0.1, 16, 1e308))])
def test04_bad_targets_name_their_field(field, target):
    with pytest.raises(SpecError) as info:
        target.validate()
    assert info.value.field == field
