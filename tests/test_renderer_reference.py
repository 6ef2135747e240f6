"""`cornell-box` against an independent renderer (Mitsuba 3).

tests/data/cornell_mitsuba_8x8_blocks.npz holds Mitsuba 3's `path` renders
of the same scene (bench/mitsuba_reference.py: max_depth = depth + 1, box
filter, independent sampler; 4096 spp at depth 1, 8192 spp at depth 7, 32
independent passes each), averaged over 8x8 pixel blocks, with each block
mean's standard error. Our render's block means are z-tested against them
with the variance of both: alpha = 0.01 over all blocks and channels with
the Sidak correction. Where our low-spp render saw no sample variance (a
deep penumbra whose few lit samples it missed), its variance is taken as the
reference's scaled to our sample count, the null hypothesis' own estimate.

The block test renders with `random`: its statistics are those of
independent samples (the var channels, like the reference's). The default
sampler, `sobol`, stratifies a pixel's samples; its var channel overstates
its error, and a dark block that missed its rare bright paths in all 64
pixels reads as a 5-sigma event against that variance model (seen at seed
2024, block (26, 31), while the same block of 5 other seeds agreed), so it is
held to the image means instead.
"""

from pathlib import Path

import numpy as np
import pytest
from scipy.stats import norm

from renderer import RenderSpec, load_scene, merge, plan, run_unit

from conftest import real_scenes

DATA = np.load(Path(__file__).parent / "data" / "cornell_mitsuba_8x8_blocks.npz")
B = 8
REF_SPP = {1: 4096, 7: 8192}


@pytest.mark.parametrize("depth, spp", [(1, 32), (7, 64)])
def test01_cornell_box_block_means_agree_with_mitsuba(depth, spp):
    scene = load_scene("cornell-box")
    spec = RenderSpec(spp=spp, depth=depth, width=256, height=256, tile_size=128, seed=2024,
                      sampler="random")
    film = merge(256, 256, [run_unit(scene, spec, u) for u in plan(spec)])
    ours = film.mean().reshape(32, B, 32, B, 3).mean(axis=(1, 3))
    ours_var = film.variance_of_mean().reshape(32, B, 32, B, 3).sum(axis=(1, 3)) / B ** 4
    ref, ref_var = DATA[f"mean_d{depth}"], DATA[f"stderr_d{depth}"].astype(np.float64) ** 2
    ours_var = np.maximum(ours_var, ref_var * REF_SPP[depth] / spp)
    z = (ours - ref) / np.sqrt(ours_var + ref_var + 1e-30)
    n_tests = z.size
    z_crit = norm.isf((1 - (1 - 0.01) ** (1 / n_tests)) / 2)
    worst = np.unravel_index(np.argmax(np.abs(z)), z.shape)
    assert np.abs(z).max() <= z_crit, (worst, z[worst], ours[worst], ref[worst])
    # and the whole image's mean, per channel, to the combined standard error
    se = np.sqrt(ours_var.sum(axis=(0, 1)) + ref_var.sum(axis=(0, 1))) / 1024
    assert np.all(np.abs(ours.mean(axis=(0, 1)) - ref.mean(axis=(0, 1))) <= 4.5 * se)


def test02_cornell_box_image_mean_with_the_default_sampler_agrees_with_mitsuba():
    """`sobol` (the default) at depth 7: each channel's image mean within 4.5
    combined standard errors of Mitsuba's (ours from the var channels, an
    upper bound for a stratified sampler)."""
    scene = load_scene("cornell-box")
    spec = RenderSpec(spp=64, depth=7, width=256, height=256, tile_size=128, seed=2024)
    assert spec.sampler == "sobol"
    film = merge(256, 256, [run_unit(scene, spec, u) for u in plan(spec)])
    ref, ref_var = DATA["mean_d7"], DATA["stderr_d7"].astype(np.float64) ** 2
    ours = film.mean().reshape(32, B, 32, B, 3).mean(axis=(1, 3))
    ours_var = film.variance_of_mean().reshape(32, B, 32, B, 3).sum(axis=(1, 3)) / B ** 4
    se = np.sqrt(ours_var.sum(axis=(0, 1)) + ref_var.sum(axis=(0, 1))) / 1024
    assert np.all(np.abs(ours.mean(axis=(0, 1)) - ref.mean(axis=(0, 1))) <= 4.5 * se)


REAL_DATA = np.load(Path(__file__).parent / "data" / "real_mitsuba_8x8_blocks.npz")
REAL_REF_SPP = 16384


@pytest.mark.parametrize("name, spp", [
    ("cornell-box", 64),
    # 256 spp: the lamp's Beckmann lobe shows (rendered as GGX, blocks (3..5, 2)
    # were 0.8 to 1.35 of Mitsuba's; 64 spp hid that under the variance floor).
    # The image mean is heavy-tailed (a tiny light seen through glass): at 256
    # spp a typical one is half the true mean, Mitsuba's own too (docs/real-scenes.md).
    ("veach-bidir", 256),
])
def test03_published_mitsuba_scenes_agree_with_mitsuba_rendering_the_same_file(name, spp):
    """The published files, imported as written (tent filter, one-sided walls
    seen from behind, the file's max depth), rendered by `path-mis` at 64x64,
    against Mitsuba 3 rendering the same XML with a plain `path` of the same
    depth (Mitsuba's max_depth - 1 bounces): 16384 spp in 16 passes, 8x8 block means and their standard errors
    (tests/data/real_mitsuba_8x8_blocks.npz, made by `python
    bench/mitsuba_reference.py --xml <scene.xml> --size 64x64 --spp 16384`).
    The same block z-test as above, Sidak-corrected alpha = 0.01."""
    scene_xml = real_scenes(f"{name}/scene.xml") / name / "scene.xml"
    from renderer import build_scene, resolve_document
    from renderer.importers import import_scene

    imported = import_scene(scene_xml)
    doc = resolve_document(imported.doc, assets=imported.assets)
    scene = build_scene(doc)
    depth = doc["defaults"]["max_depth"]
    spec = RenderSpec(method="path-mis", spp=spp, depth=depth, width=64, height=64,
                      tile_size=32, seed=7, sampler="random")
    film = merge(64, 64, [run_unit(scene, spec, u) for u in plan(spec)])
    key = name.replace("-", "_")
    ours = film.mean().reshape(8, B, 8, B, 3).mean(axis=(1, 3))
    ours_var = film.variance_of_mean().reshape(8, B, 8, B, 3).sum(axis=(1, 3)) / B ** 4
    ref = REAL_DATA[f"mean_{key}"].astype(np.float64)
    ref_var = REAL_DATA[f"stderr_{key}"].astype(np.float64) ** 2
    ours_var = np.maximum(ours_var, ref_var * REAL_REF_SPP / spec.spp)
    z = (ours - ref) / np.sqrt(ours_var + ref_var + 1e-30)
    z_crit = norm.isf((1 - (1 - 0.01) ** (1 / z.size)) / 2)
    worst = np.unravel_index(np.argmax(np.abs(z)), z.shape)
    assert np.abs(z).max() <= z_crit, (worst, z[worst], ours[worst], ref[worst])
    se = np.sqrt(ours_var.sum(axis=(0, 1)) + ref_var.sum(axis=(0, 1))) / 64
    assert np.all(np.abs(ours.mean(axis=(0, 1)) - ref.mean(axis=(0, 1))) <= 4.5 * se)
