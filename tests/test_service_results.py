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
from renderer import RenderSpec, images, load_scene, merge, read_exr
from renderer.film import image_error, noise_srgb8, tonemap_srgb8
from renderer.runtime import run_plan, run_unit
from renderer.target import Target, target_plan
from service.results import partial_result, write_result
from service.store import Store

JOB = "a1b2c3d4e5f6"


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


def whole_frame(width: int, height: int, films, denoise: bool = False) -> dict:
    """The files' contents as they were made before: the whole frame's
    float64 sums (`renderer.merge`), its mean and variance at once, the EXR's
    channels cast from them, OIDN on the whole frame's inputs."""
    film = merge(width, height, films)
    mean, var = film.mean(), film.variance_of_mean()
    m32, v32 = mean.astype(np.float32), var.astype(np.float32)
    channels = {c: m32[..., i].copy() for i, c in enumerate("RGB")}
    channels.update({f"var.{c}": v32[..., i].copy() for i, c in enumerate("RGB")})
    channels.update({name: np.ascontiguousarray(a, dtype=np.float32)
                     for name, a in film.aovs().items()})
    out = {"channels": channels, "rel_error": image_error(mean, var),
           "preview": tonemap_srgb8(mean), "noise": noise_srgb8(mean, var)}
    if denoise:
        import pyoidn

        color = np.ascontiguousarray(np.nan_to_num(mean, nan=0.0, posinf=0.0, neginf=0.0),
                                     dtype=np.float32)
        aovs = film.aovs()
        albedo = np.clip(np.stack([aovs[f"albedo.{c}"] for c in "RGB"], -1).astype(np.float32),
                         0.0, 1.0)
        normal = np.clip(np.stack([aovs[f"normal.{c}"] for c in "XYZ"], -1).astype(np.float32),
                         -1.0, 1.0)
        clean = pyoidn.denoise(np.maximum(color, 0.0), np.ascontiguousarray(albedo),
                               np.ascontiguousarray(normal), hdr=True, quality="high")
        channels.update({f"denoised.{c}": np.ascontiguousarray(clean[..., i], dtype=np.float32)
                         for i, c in enumerate("RGB")})
        out["denoised"] = tonemap_srgb8(clean)
    return out


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
