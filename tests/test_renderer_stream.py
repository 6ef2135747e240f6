"""The finished frame merged band by band from the stored unit films
(renderer.stream.merge_frame) is the whole-frame merge's frame bit for bit:
channels, PNG pixels, the error statistic, the stats; for tile methods (with
progressive units that span bands), splat methods (full-frame batches),
radiosity's jackknife sums, SPPM's telescoping gathers and a noise-target
job's units (some skipped); with bands that cut through tiles and single
rows. And it holds what the layout says it holds (renderer/memory.py), a
fraction of the whole-frame float64 merge."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from renderer import RenderSpec, images, load_scene, merge
from renderer.film import AOV_LAYERS, image_error
from renderer.memory import job_memory
from renderer.runtime import run_plan, run_unit
from renderer.stream import merge_frame
from renderer.target import Target, target_plan
from whole_frame import whole_frame

JOBS = {
    "path-mis grouped": (dict(method="path-mis", width=40, height=30, tile_size=8, spp=6), True),
    "raster one tile": (dict(method="raster", width=33, height=21, tile_size=64, spp=2), False),
    "bdpt": (dict(method="bdpt", width=24, height=20, tile_size=8, spp=3), False),
    "light": (dict(method="light", width=24, height=20, tile_size=8, spp=4), False),
    "radiosity": (dict(method="radiosity", width=24, height=16, tile_size=8, spp=2), False),
    "photon": (dict(method="photon", width=16, height=12, tile_size=8, spp=3), False),
}


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


def stored(tmp_path, films) -> list:
    paths = []
    for i, film in enumerate(films):
        path = tmp_path / f"{i}.film"
        path.write_bytes(film.to_bytes())
        paths.append(path)
    return paths


def assert_same_frame(expected: dict, got) -> None:
    assert list(got.channels) == list(expected["channels"])
    for name, a in expected["channels"].items():
        assert got.channels[name].dtype == np.float32
        assert np.array_equal(got.channels[name].view(np.uint32), a.view(np.uint32)), name
    assert (got.rel_error == expected["rel_error"]
            or (np.isnan(got.rel_error) and np.isnan(expected["rel_error"])))
    assert np.array_equal(got.preview, expected["preview"])
    assert np.array_equal(got.noise, expected["noise"])
    assert got.stats == expected["stats"]


@pytest.mark.parametrize("band_pixels", [37, images.BAND_PIXELS])
@pytest.mark.parametrize("job", sorted(JOBS))
def test01_the_banded_merge_is_the_whole_frame_merge_bit_for_bit(job, band_pixels, cornell,
                                                                  tmp_path, monkeypatch):
    monkeypatch.setattr(images, "BAND_PIXELS", band_pixels)  # 37: bands of one row or less
    monkeypatch.setattr(images, "_PAIRWISE_LEAF", 136)  # the frame mean from many pieces
    fields, progressive = JOBS[job]
    spec = RenderSpec(depth=3, seed=5, **fields).validate()
    films = run_plan(cornell, spec, progressive)
    expected = whole_frame(spec.width, spec.height, films)
    got = merge_frame(spec.width, spec.height, stored(tmp_path, films), tile=spec.tile_size,
                      preview=True, noise=True)
    assert_same_frame(expected, got)
    if job == "path-mis grouped":  # a progressive pass's unit spans rows of tiles
        assert any(f.height > spec.tile_size for f in films)
    if job in ("bdpt", "light"):
        assert all(f.splat is not None for f in films)
    if job == "radiosity":
        assert any(f.jackknife is not None for f in films)


def test02_a_noise_target_jobs_units_with_some_skipped(cornell, tmp_path, monkeypatch):
    monkeypatch.setattr(images, "BAND_PIXELS", 50)
    spec, units = target_plan(RenderSpec(method="path-mis", width=24, height=20, tile_size=8,
                                         depth=3, seed=3).validate(),
                              Target(rel_error=0.05, max_spp=8))
    films = [run_unit(cornell, spec, u) for u in units]
    # the later passes' units of every other tile skipped, as a decision does
    done = [f for u, f in zip(units, films) if u.pass_index < 2 or u.index % 2]
    assert len(done) < len(films)
    expected = whole_frame(spec.width, spec.height, done)
    got = merge_frame(spec.width, spec.height, stored(tmp_path, done), tile=spec.tile_size,
                      preview=True, noise=True)
    assert_same_frame(expected, got)


def test03_films_in_memory_bytes_and_files_merge_alike(cornell, tmp_path):
    spec = RenderSpec(method="bdpt", width=16, height=12, tile_size=8, spp=2, depth=3).validate()
    films = run_plan(cornell, spec)
    from_files = merge_frame(16, 12, stored(tmp_path, films), tile=8)
    for sources in (films, [f.to_bytes() for f in films]):
        other = merge_frame(16, 12, sources, tile=8)
        assert other.rel_error == from_files.rel_error
        for name, a in from_files.channels.items():
            assert np.array_equal(other.channels[name], a, equal_nan=True)


@pytest.mark.parametrize("n", [1, 7, 8, 129, 1000, 65537, 300001])
def test04_the_frame_mean_in_pieces_is_numpys_sum(n, monkeypatch):
    """The error statistic's floor is 1 % of np.mean of the frame's mean; the
    bands hand it over in pieces, and the sum is numpy's own, bit for bit."""
    monkeypatch.setattr(images, "_PAIRWISE_LEAF", 136)
    rng = np.random.default_rng(n)
    x = rng.random(n) * 10.0 ** rng.uniform(-8, 8, n)
    total = images._PairwiseSum(n)
    for piece in np.split(x, np.sort(rng.integers(0, n, 6))):
        total.add(piece)
    assert total.value() == np.add.reduce(x)
    assert total.value() / n == np.mean(x)


def test05_the_merge_holds_what_the_layout_says_a_fraction_of_the_whole_frame_merge(
        cornell, tmp_path, monkeypatch):
    """Traced allocations (numpy reports its arrays to tracemalloc): the banded
    merge of a W x H frame, its EXR and PNGs, stays under renderer.memory's
    figure for the merge (measured: 89 bytes a pixel here, the figure 112 with
    a band); the whole-frame float64 merge goes over it (216: its sums alone
    are 112 bytes a pixel)."""
    monkeypatch.setattr(images, "BAND_PIXELS", 4096)
    spec = RenderSpec(method="raster", width=512, height=384, tile_size=64, spp=1,
                      depth=1).validate()
    paths = stored(tmp_path, run_plan(cornell, spec))
    bound = job_memory(spec).merge
    pixels = spec.width * spec.height
    assert bound < 120 * pixels  # 91 bytes a pixel, and one band of 4096 pixels

    tracemalloc.start()
    try:
        got = merge_frame(spec.width, spec.height, paths, tile=spec.tile_size, preview=True,
                          noise=True)
        images.write_exr(tmp_path / "result.exr", got.channels, {"spp": 1})
        images.write_png(tmp_path / "preview.png", got.preview)
        images.write_png(tmp_path / "noise.png", got.noise)
        banded = tracemalloc.get_traced_memory()[1]
        del got
        tracemalloc.reset_peak()
        from renderer import PartialFilm

        film = merge(spec.width, spec.height, (PartialFilm.from_bytes(p.read_bytes())
                                               for p in paths))
        film.variance_of_mean()
        whole = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert banded < bound, (banded / pixels, bound / pixels)
    assert whole > bound, (whole / pixels, bound / pixels)
    assert set(AOV_LAYERS) <= set(images.read_exr(tmp_path / "result.exr")[0])


def test06_a_regions_statistic_is_the_whole_frames_there(cornell, monkeypatch):
    """A noise target's decisions read each unit's region of the frame
    (`Film.region`) against the frame's floor (`Film.error_floor`, band by
    band): the values the whole frame's mean and variance give."""
    from renderer.film import error_floor

    monkeypatch.setattr(images, "BAND_PIXELS", 40)
    monkeypatch.setattr(images, "_PAIRWISE_LEAF", 136)
    spec = RenderSpec(method="bdpt", width=30, height=22, tile_size=8, spp=3, depth=3).validate()
    film = merge(spec.width, spec.height, run_plan(cornell, spec))
    mean, var = film.mean(), film.variance_of_mean()
    floor = error_floor(mean)
    assert film.error_floor() == floor
    for x0, y0, x1, y1 in ((0, 0, 8, 8), (8, 16, 16, 22), (24, 8, 30, 16), (0, 0, 30, 22)):
        region = film.region(x0, y0, x1, y1)
        assert np.array_equal(region.mean(), mean[y0:y1, x0:x1])
        assert np.array_equal(region.variance_of_mean(), var[y0:y1, x0:x1])
        assert (image_error(region.mean(), region.variance_of_mean(), floor)
                == image_error(mean[y0:y1, x0:x1], var[y0:y1, x0:x1], floor))
