"""One denoise after the exact merge (renderer/denoise.py): no seams, and the
raw image untouched beside it."""

from __future__ import annotations

import numpy as np
import pytest

from renderer import RenderSpec, load_scene, merge, plan, run_unit

pytest.importorskip("pyoidn", reason="pyoidn is a dependency: pip install -e .")

from renderer.denoise import denoise_film  # noqa: E402

TILE = 16


def _gap_differences(image: np.ndarray) -> np.ndarray:
    """Mean absolute difference between neighbouring columns and between
    neighbouring rows, per gap: (gaps,) for gap k between k and k + 1."""
    lum = image.mean(axis=-1)
    cols = np.abs(np.diff(lum, axis=1)).mean(axis=0)
    rows = np.abs(np.diff(lum, axis=0)).mean(axis=1)
    return np.concatenate([cols, rows])


def _border_and_inside(error: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gaps' differences of an error image (denoised - reference), those
    across tile borders and those inside tiles. On the error, not the image:
    a wall's edge that happens to fall on a tile border is content, not a seam."""
    h, w = error.shape[:2]
    gaps = _gap_differences(error)
    border = np.array([k % TILE == TILE - 1 for k in range(w - 1)]
                      + [k % TILE == TILE - 1 for k in range(h - 1)])
    return gaps[border], gaps[~border]


def _seam_z(error: np.ndarray) -> float:
    """How many standard errors the border gaps' mean difference lies above
    the inside gaps' (a one-sided z statistic over the gaps)."""
    border, inside = _border_and_inside(error)
    return float((border.mean() - inside.mean()) / (inside.std(ddof=1) / np.sqrt(len(border))))


def _display(rgb: np.ndarray) -> np.ndarray:
    """Clamped to [0, 1] as the preview shows it: the emitter's radiance (~18)
    would otherwise outweigh every other pixel."""
    return np.clip(rgb, 0.0, 1.0)


@pytest.fixture(scope="module")
def reference():
    """The same frame at 256 spp in one tile."""
    spec = RenderSpec(spp=256, depth=5, width=96, height=96, tile_size=96, seed=4)
    scene = load_scene("cornell-box")
    return merge(96, 96, [run_unit(scene, spec, u) for u in plan(spec)]).mean()


@pytest.fixture(scope="module")
def tiled_film():
    """Cornell box at 8 spp, rendered as 16 x 16 tiles and merged."""
    spec = RenderSpec(spp=8, depth=5, width=96, height=96, tile_size=TILE, seed=3)
    scene = load_scene("cornell-box")
    units = plan(spec)
    assert len(units) == (96 // TILE) ** 2
    return merge(96, 96, [run_unit(scene, spec, u) for u in units])


def test01_denoising_the_merged_frame_leaves_no_seams_at_tile_borders(tiled_film, reference):
    """The frame is denoised whole, so across a tile border its error changes no
    more than inside a tile (z <= 3, one-sided). Denoising each tile on its own,
    what a farm that denoises per tile does, fails the same check."""
    clean = denoise_film(tiled_film)
    assert clean.shape == (96, 96, 3) and clean.dtype == np.float32
    assert np.all(np.isfinite(clean))
    assert _seam_z(_display(clean) - _display(reference)) <= 3.0
    from renderer.film import Film

    per_tile = np.empty_like(clean)
    for y in range(0, 96, TILE):
        for x in range(0, 96, TILE):
            window = (slice(y, y + TILE), slice(x, x + TILE))
            per_tile[window] = denoise_film(Film(
                0, 0, tiled_film.sum[window], tiled_film.sum_sq[window],
                tiled_film.weight[window], aov=tiled_film.aov[window]))
    assert _seam_z(_display(per_tile) - _display(reference)) > 3.0


def test02_denoising_lowers_the_error_and_keeps_the_raw_film(tiled_film, reference):
    """Against the 256-spp render, the denoised 8-spp image is closer than the
    raw one over the pixels that do not see the light (the point of it), and
    the film it came from is untouched."""
    before = tiled_film.mean().copy()
    clean = denoise_film(tiled_film)
    assert np.array_equal(tiled_film.mean(), before)
    lit = reference.max(axis=-1) < 1.0  # not the emitter, whose edges a denoiser softens
    raw_rmse = np.sqrt(((before - reference)[lit] ** 2).mean())
    den_rmse = np.sqrt(((clean - reference)[lit] ** 2).mean())
    assert den_rmse < 0.5 * raw_rmse, (raw_rmse, den_rmse)
