"""Issue 5, point 13: the methods that plan a DAG (prepass -> units -> merge)
give the same image however the job is cut and wherever its units run.

- Their plans are DAGs in unit order (every unit needs only earlier units,
  of earlier stages), and their units' samples add up to width x height x spp.
- Tile size: light tracing, MLT, photon mapping and radiosity split work by
  path, chain, photon and pixel ranges that do not depend on the tile size,
  and merge in unit order: bit-identical. BDPT's t = 1 splats are summed per
  tile unit, so a different tiling sums the same splats in another order:
  equal to float rounding, not bit for bit.
- Workers: one in-process run and the two-process local pool give the same
  bytes (the farm's Celery workers are in test_farm_celery.py).
- Every EXR carries finite var.R/G/B where the method has samples enough.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from renderer import METHODS, RenderSpec, load_scene, merge, render, render_serial
from renderer.film import read_exr

# Small but not degenerate: enough units for batch variances.
DAG_JOBS = {
    "light": dict(spp=4),
    "bdpt": dict(spp=4),
    "mlt": dict(spp=4),
    "photon": dict(spp=3),
    "radiosity": dict(spp=2),
}
BIT_IDENTICAL_ACROSS_TILES = {"light", "mlt", "photon", "radiosity"}


def spec_for(method: str, **kw) -> RenderSpec:
    base = dict(method=method, width=24, height=16, depth=3, seed=7, tile_size=8)
    base.update(DAG_JOBS[method])
    base.update(kw)
    return RenderSpec(**base).validate()


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


@pytest.mark.parametrize("method", sorted(DAG_JOBS))
def test01_plan_is_a_dag_in_unit_order_and_counts_every_sample(method, cornell):
    spec = spec_for(method)
    units = METHODS[method].make_plan(spec, False)
    assert [u.index for u in units] == list(range(len(units)))
    for u in units:
        assert all(0 <= i < u.index for i in u.needs), (u, "needs a later unit")
        assert all(units[i].stage < u.stage for i in u.needs), (u, "needs a unit of its stage")
    assert {u.kind for u in units} <= set(METHODS[method].phases)
    film = render_serial(cornell, spec)
    assert film.stats["samples"] == spec.width * spec.height * spec.spp


@pytest.mark.parametrize("method", sorted(DAG_JOBS))
def test02_tile_size_does_not_change_the_image(method, cornell):
    a = render_serial(cornell, spec_for(method, tile_size=8))
    b = render_serial(cornell, spec_for(method, tile_size=16))
    if method in BIT_IDENTICAL_ACROSS_TILES:
        assert np.array_equal(a.mean(), b.mean())
        assert np.array_equal(a.variance_of_mean(), b.variance_of_mean())
    else:
        np.testing.assert_allclose(a.mean(), b.mean(), rtol=1e-10, atol=1e-12)


@pytest.fixture(scope="module")
def pool():
    from renderer import LocalPool

    with LocalPool(2) as p:
        yield p


@pytest.mark.parametrize("method", sorted(DAG_JOBS))
def test03_local_pool_matches_one_process_bit_for_bit(method, cornell, pool, tmp_path):
    spec = spec_for(method)
    serial = render_serial(cornell, spec)
    pooled = render("cornell-box", spec, pool=pool)
    assert np.array_equal(serial.mean(), pooled.mean())
    assert np.array_equal(serial.variance_of_mean(), pooled.variance_of_mean())
    path = tmp_path / f"{method}.exr"
    pooled.write_exr(path)
    channels, _ = read_exr(path)
    assert {"R", "G", "B", "var.R", "var.G", "var.B"} <= set(channels)
    var = np.stack([channels[c] for c in ("var.R", "var.G", "var.B")], axis=-1)
    assert np.isfinite(var).mean() > 0.99, f"{method}: var channels mostly unknown"
    assert (var >= 0).all()


def test04_merge_scales_splats_by_the_jobs_total_paths_not_a_units():
    """The splat layer (film.py): two batches of 3 and 1 paths with per-path
    contribution 2 make a frame of 2, whatever the split (pbrt-v4 issue 347)."""
    from renderer import PartialFilm

    ones = np.ones((2, 2, 3))
    film = merge(2, 2, [PartialFilm.splat_batch(6.0 * ones, 3), PartialFilm.splat_batch(2.0 * ones, 1)])
    np.testing.assert_array_equal(film.mean(), 2.0 * ones)
    # Both batch estimates equal 2: no spread, variance 0.
    np.testing.assert_array_equal(film.variance_of_mean(), 0.0 * ones)
    film = merge(2, 2, [PartialFilm.splat_batch(6.0 * ones, 3), PartialFilm.splat_batch(4.0 * ones, 1)])
    # X = (2, 4) weighted by n = (3, 1): mean 10/4; sigma^2 = (3*0.25 + 2.25)/1 = 3; Var = 3/4.
    np.testing.assert_allclose(film.mean(), 2.5 * ones)
    np.testing.assert_allclose(film.variance_of_mean(), 0.75 * ones)


def test05_film_bytes_round_trip_without_parsing_python(monkeypatch):
    """The wire format (film.py): every field survives, equal films give equal
    bytes, truncated bytes are a ValueError, and reading never goes through
    `ast` (whose per-interpreter state races between threads on 3.11), while
    a film stored as npz by an earlier rayfarm still reads."""
    import ast
    import io

    from renderer import PartialFilm

    rng = np.random.default_rng(5)
    film = PartialFilm(2, 3, rng.random((4, 5, 3)), rng.random((4, 5, 3)), rng.random((4, 5)),
                       {"samples": 7, "rays": 11, "seconds": 0.25})
    film.splat, film.splat_sq = rng.random((6, 6, 3)), rng.random((6, 6, 3))
    film.splat_paths, film.splat_batches = 9.0, 1
    film.artefact = {"scalar": np.float64(1.5), "ints": np.arange(6, dtype=np.int32).reshape(2, 3)}
    data = film.to_bytes()

    def no_parsing(*args, **kwargs):
        raise AssertionError("film bytes were read through ast")
    monkeypatch.setattr(ast, "parse", no_parsing)
    back = PartialFilm.from_bytes(data)
    assert PartialFilm.stats_from_bytes(data) == film.stats
    monkeypatch.undo()

    assert back.to_bytes() == data
    assert (back.x0, back.y0, back.stats) == (2, 3, film.stats)
    for name in ("sum", "sum_sq", "weight", "splat", "splat_sq"):
        np.testing.assert_array_equal(getattr(back, name), getattr(film, name))
    assert (back.splat_paths, back.splat_batches) == (9.0, 1)
    assert back.artefact["scalar"].shape == () and back.artefact["scalar"] == 1.5
    assert back.artefact["ints"].dtype == np.int32
    np.testing.assert_array_equal(back.artefact["ints"], film.artefact["ints"])
    for cut in (0, 11, 40, len(data) - 8):
        with pytest.raises(ValueError):
            PartialFilm.from_bytes(data[:cut])

    legacy = io.BytesIO()
    np.savez(legacy, origin=np.array([2, 3]), sum=film.sum, sum_sq=film.sum_sq, weight=film.weight,
             stats=np.frombuffer(b'{"samples": 7, "rays": 11, "seconds": 0.25}', np.uint8))
    old = PartialFilm.from_bytes(legacy.getvalue())
    np.testing.assert_array_equal(old.sum, film.sum)
    assert old.stats == film.stats and old.splat is None


@pytest.mark.parametrize("method", dict.fromkeys(m.name for m in METHODS.values()))
def test06_plan_size_is_the_plans_length_without_building_it(method):
    """`plan_size` counts what `make_plan` builds, for every method, shape,
    pass layout and the options that change a plan's shape."""
    from renderer.plan_size import plan_size

    options = [{}]
    if METHODS[method].family == "photons":
        options += [{"iterations_per_unit": 1}, {"iterations_per_unit": 5},
                    {"photons": 200_000}, {"mode": "photonmap"},
                    {"mode": "photonmap", "photons": 300_000}]
    # A photon plan of one-pixel tiles is a gather unit per pixel and round (2560
    # x 64 of them here): seconds to build, no shape the 8-pixel tiles miss.
    tiles = (8, 16, 64) if METHODS[method].family == "photons" else (1, 8, 16, 64)
    checked = 0
    for width, height, tile, spp, progressive, opts in itertools.product(
            (1, 7, 33, 64), (1, 16, 40), tiles, (1, 2, 3, 17, 64), (False, True), options):
        spec = RenderSpec(method=method, spp=spp, width=width, height=height, tile_size=tile,
                          options=opts)
        assert plan_size(spec, progressive) == len(METHODS[method].make_plan(spec, progressive)), \
            (width, height, tile, spp, progressive, opts)
        checked += 1
    assert checked >= 480
