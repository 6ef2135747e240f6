"""A finished job's files (service.results.write_result), merged band by band
from the stored unit films, are those of the whole-frame float64 merge they
were made from before, bit for bit: the EXR's channels and rel_error, the
preview and noise PNGs, the denoised beauty; for a tile job, a splat job and
a noise-target job with skipped units, and a canceled job's partial result."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from conftest import assert_bit_identical
from whole_frame import whole_frame
from renderer import RenderSpec, images, load_scene, read_exr
from renderer.runtime import run_plan, run_unit
from renderer.target import Target, target_plan
from service.results import partial_result, write_result
from service.store import Store

JOB = "a1b2c3d4e5f6"


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


def store_films(tmp_path, films) -> Store:
    store = Store(tmp_path / "data")
    for i, film in enumerate(films):
        if film is not None:
            store.put_unit_film(JOB, i, film.to_bytes())
    return store


def assert_files(store: Store, spec: RenderSpec, expected: dict, rel_error: float) -> None:
    channels, header = read_exr(store.result_path(JOB))
    assert_bit_identical(channels, expected["channels"])
    assert rel_error == expected["rel_error"]
    assert header["rayfarm.rel_error"] == np.float32(expected["rel_error"])
    assert np.array_equal(np.asarray(Image.open(store.preview_path(JOB))), expected["preview"])
    assert np.array_equal(np.asarray(Image.open(store.noise_path(JOB))), expected["noise"])
    if "denoised" in expected:
        assert np.array_equal(np.asarray(Image.open(store.denoised_path(JOB))),
                              expected["denoised"])


@pytest.mark.parametrize("method,denoise", [("path-mis", True), ("bdpt", False)])
def test01_a_jobs_files_are_the_whole_frame_merges(method, denoise, cornell, tmp_path,
                                                   monkeypatch):
    monkeypatch.setattr(images, "BAND_PIXELS", 100)  # many bands, cutting through tiles
    spec = RenderSpec(method=method, width=40, height=28, tile_size=16, spp=4, depth=3,
                      seed=11).validate()
    films = run_plan(cornell, spec, True)
    store = store_films(tmp_path, films)
    rel_error = write_result(store, JOB, spec, range(len(films)), scene="cornell-box",
                             scene_hash="0" * 64, denoise=denoise)
    assert_files(store, spec, whole_frame(spec.width, spec.height, films, denoise), rel_error)


def test02_a_noise_target_jobs_files_with_skipped_units(cornell, tmp_path, monkeypatch):
    monkeypatch.setattr(images, "BAND_PIXELS", 64)
    target = Target(rel_error=0.05, max_spp=8)
    spec, units = target_plan(RenderSpec(method="path-mis", width=24, height=24, tile_size=8,
                                         depth=3, seed=2).validate(), target)
    done = [u.index for u in units if u.pass_index < 2 or u.index % 3]  # the rest skipped
    films = [run_unit(cornell, spec, u) if u.index in done else None for u in units]
    store = store_films(tmp_path, films)
    rel_error = write_result(store, JOB, spec, done, scene="cornell-box", scene_hash="0" * 64,
                             target=target)
    assert_files(store, spec, whole_frame(spec.width, spec.height,
                                          [films[i] for i in done]), rel_error)
    # a canceled job's finished units, as the partial result
    exr, png = partial_result(store, JOB, spec, done[:5], scene="cornell-box",
                              scene_hash="0" * 64)
    expected = whole_frame(spec.width, spec.height, [films[i] for i in done[:5]])
    channels, header = read_exr(exr)
    assert_bit_identical(channels, expected["channels"])
    assert header["rayfarm.partial"] == 1
    assert np.array_equal(np.asarray(Image.open(png)), expected["preview"])
