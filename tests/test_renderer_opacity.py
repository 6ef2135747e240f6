"""Opacity masks in every method that traces rays (kernels/opacity.py).

A hit on a surface of opacity a is kept with probability a, decided by a
hash of the ray while the ray is traced, so camera rays, shadow rays, BDPT's
connections and photons meet the same cut-out surface; a passed hit is no
bounce. Statistical tests take their tolerances from the films' own
variances (block z-tests as in test_renderer_light_bdpt.py, Sidak-corrected)
with fixed seeds; where the answer is exact (a mask of 0 and 1) pixels are
compared exactly.
"""

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2, norm, t as student_t

from renderer import RenderSpec, build_scene, render_serial, resolve_document
from renderer.errors import SceneError, SpecError
from renderer.integrators import mlt
from renderer.kernels.geometry import STACK_SIZE, intersect
from renderer.kernels.opacity import blocked, hash_ray, opacity, trace
from renderer.registry import shading_features
from renderer.runtime import run_plan
from renderer.scene import load_scene

from test_renderer_light_bdpt import block_stats, z_pass_rate

DIGEST = "c" * 64
ALPHA = 0.01  # each test's false-alarm rate


def shell_doc(shell="sphere", a=0.5, rho=0.5):
    """The masked shell furnace: inside a sphere that emits radiance 1
    inwards (and reflects nothing) a black shell of opacity `a` (a sphere,
    or a cube of 12 triangles) holds a floor of albedo `rho` and the camera,
    which sees only the floor. All light reaching the floor crosses the shell
    once, and nothing else reflects: the floor's radiance is rho (1 - a) at
    every depth from 1."""
    veil = ({"type": "sphere", "radius": 0.9, "material": "veil"} if shell == "sphere" else
            {"type": "cube", "material": "veil", "to_world": [{"scale": [0.55, 0.55, 0.55]}]})
    return resolve_document({
        "camera": {"origin": [0, 0, 0.45], "target": [0, 0, 0], "up": [0, 1, 0], "fov": 90,
                   "width": 16, "height": 16},
        "materials": {"sky": {"type": "diffuse", "albedo": 0.0},
                      "veil": {"type": "diffuse", "albedo": 0.0, "opacity": a},
                      "floor": {"type": "diffuse", "albedo": rho}},
        "shapes": [{"type": "sphere", "material": "sky", "flip_normals": True,
                    "emitter": {"type": "area", "radiance": [1, 1, 1]}},
                   veil,
                   {"type": "rectangle", "material": "floor",
                    "to_world": [{"scale": [0.5, 0.5, 1]}]}]})


def layers_scene(a1, a2):
    """Two parallel masked squares (z = 0 and z = -1, opacities a1, a2) over
    an opaque one (z = -2): primitives 0-1, 2-3 and 4-5."""
    return build_scene(resolve_document({
        "camera": {"origin": [0, 0, 3], "target": [0, 0, 0], "fov": 30, "width": 8,
                   "height": 8},
        "materials": {"m1": {"type": "diffuse", "opacity": a1},
                      "m2": {"type": "diffuse", "opacity": a2},
                      "solid": {"type": "diffuse"}},
        "shapes": [{"type": "rectangle", "material": m, "to_world": [
            {"scale": [4, 4, 1]}, {"translate": [0, 0, -z]}]}
            for z, m in enumerate(("m1", "m2", "solid"))]}))


def random_rays(n, seed):
    """Rays from z = 1 going down through the middle of the squares."""
    rng = np.random.default_rng(seed)
    o = np.column_stack([rng.uniform(-1, 1, (n, 2)), np.ones(n)])
    d = np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), -np.ones(n)])
    return o, d / np.linalg.norm(d, axis=1)[:, None]


# ----------------------------------------------------------------- the format

def test01_the_format_takes_an_opacity_and_methods_refuse_what_they_cannot_render():
    doc = shell_doc(a=0.25)
    assert doc["materials"]["veil"]["opacity"] == 0.25
    assert "opacity masks" in shading_features(doc)
    opaque = resolve_document({**doc, "materials": {**doc["materials"],
                                                    "veil": {"type": "diffuse", "opacity": 1}}})
    assert opaque["materials"]["veil"] == {"type": "diffuse", "albedo": [0.5] * 3}  # same hash
    textured = resolve_document({**doc, "textures": {"t": {"type": "checkerboard"}},
                                 "materials": {**doc["materials"], "veil": {
                                     "type": "diffuse", "opacity": {"texture": "t"},
                                     "opacity_cutoff": 0.3}}})
    assert textured["materials"]["veil"]["opacity"] == {"texture": "t"}

    def refused(material, where, **extra):
        with pytest.raises(SceneError) as exc:
            resolve_document({**doc, **extra, "materials": {**doc["materials"], "veil": material}})
        assert exc.value.location.startswith(where), (exc.value.location, str(exc.value))

    refused({"type": "diffuse", "opacity": 1.5}, "materials.veil.opacity")
    refused({"type": "diffuse", "opacity": {"texture": "nope"}}, "materials.veil.opacity")
    refused({"type": "diffuse", "opacity": 0.5, "opacity_cutoff": 0.5},
            "materials.veil.opacity_cutoff")  # a cutoff thresholds a texture
    refused({"type": "diffuse", "opacity": {"texture": "t"}, "opacity_cutoff": 0},
            "materials.veil.opacity_cutoff", textures={"t": {"type": "checkerboard"}})
    with pytest.raises(SceneError) as exc:  # light sampling cannot see a mask
        resolve_document({**doc, "materials": {**doc["materials"],
                                               "sky": {"type": "diffuse", "opacity": 0.5}}})
    assert exc.value.location == "shapes[0].emitter"

    for method in ("raster", "radiosity"):
        with pytest.raises(SpecError, match=f"{method}.*opacity masks"):
            RenderSpec(method=method, width=8, height=8).validate(scene=doc)
    for method in ("path-bsdf", "path-nee", "path-onesample", "path-mis", "direct", "light",
                   "bdpt", "mlt", "photon"):
        RenderSpec(method=method, width=8, height=8).validate(scene=doc)


# ---------------------------------------------------------------- the kernels

def test02_a_hit_is_kept_with_probability_its_opacity_layer_by_layer():
    """Rays through two masked layers over an opaque one stop at the first
    with probability a1, at the second with (1 - a1) a2, on the floor with
    (1 - a1)(1 - a2): the two decisions are independent, also for equal
    opacities (one hash for every surface along a ray, as pbrt-v4 draws it,
    would stop none at the second layer). A shadow ray that ends before the
    floor is blocked with probability 1 - (1 - a1)(1 - a2). Opacity 0 is
    always passed, 1 always kept. A chi-square test at ALPHA on 20000 rays."""
    stack = np.zeros(STACK_SIZE, np.int64)
    o, d = random_rays(20000, 1)
    for a1, a2 in ((0.3, 0.3), (0.5, 0.8), (0.0, 1.0)):
        sc = layers_scene(a1, a2).arrays
        first = np.array([trace(sc, stack, *o[i], *d[i], np.inf)[1] // 2 for i in range(len(o))])
        counts = np.bincount(first, minlength=3)
        p = np.array([a1, (1 - a1) * a2, (1 - a1) * (1 - a2)])
        if a1 in (0.0, 1.0):
            assert counts.tolist() == (p * len(o)).tolist(), (a1, a2, counts)
            continue
        stat = ((counts - p * len(o)) ** 2 / (p * len(o))).sum()
        assert stat < chi2.isf(ALPHA, 2), (a1, a2, counts, p * len(o))
        hidden = np.array([blocked(sc, stack, *o[i], *d[i], 2.5) for i in range(len(o))])
        q = 1 - p[2]
        assert abs(hidden.mean() - q) <= norm.isf(ALPHA / 2) * math.sqrt(q * (1 - q) / len(o))
        # the decision is the ray's: the same ray, the same answer
        assert trace(sc, stack, *o[7], *d[7], np.inf) == trace(sc, stack, *o[7], *d[7], np.inf)
    assert 0.0 <= hash_ray(*o[0], *d[0]) < 1.0


def test03_the_opacity_is_the_texture_luminance_or_its_threshold():
    """A bitmap's opacity is the luminance of its RGB texel (Mitsuba 3's
    eval_1), a one-channel image's value; with a cutoff, 1 where it is >= the
    cutoff, 0 elsewhere (after filtering)."""
    texels = np.array([[[0.2, 0.4, 0.6], [1.0, 1.0, 1.0]],
                       [[0.0, 0.0, 0.0], [0.5, 0.9, 0.1]]], np.float32)
    grey = np.array([[[0.3], [0.7]], [[0.1], [0.9]]], np.float32)
    tex = {"type": "bitmap", "image": DIGEST, "filter": "nearest"}
    luminance = texels @ np.array([0.212671, 0.715160, 0.072169], np.float32)
    for image, cutoff, want in ((texels, None, luminance), (grey, None, grey[..., 0]),
                                (texels, 0.5, (luminance >= 0.5) * 1.0),
                                (grey, 0.3, (grey[..., 0] >= 0.3) * 1.0)):
        material = {"type": "diffuse", "opacity": {"texture": "t"}}
        if cutoff is not None:
            material["opacity_cutoff"] = cutoff
        doc = resolve_document({
            "camera": {"origin": [0, 0, 3], "target": [0, 0, 0], "fov": 30, "width": 8,
                       "height": 8},
            "textures": {"t": tex}, "materials": {"m": material},
            "shapes": [{"type": "rectangle", "material": "m"}]})
        sc = build_scene(doc, {DIGEST: image}).arrays
        stack = np.zeros(STACK_SIZE, np.int64)
        for row in (0, 1):
            for col in (0, 1):
                # texel (row, col) at uv ((col + 1/2) / 2, (row + 1/2) / 2), uv = ((x + 1) / 2,
                # (y + 1) / 2) on the rectangle
                x, y = -0.5 + col, -0.5 + row
                prim = intersect(sc, stack, x, y, 1.0, 0.0, 0.0, -1.0, np.inf)[1]
                got = opacity(sc, prim, 0, x, y, 0.0)
                assert got == pytest.approx(want[row, col], abs=1e-6), (row, col, cutoff)


# ------------------------------------------------------------------- renders

@pytest.mark.parametrize("method, spp", [("path-bsdf", 64), ("path-mis", 32), ("direct", 128),
                                         ("light", 1024), ("bdpt", 64), ("photon", 128)])
@pytest.mark.parametrize("shell", ["sphere", "cube"])
def test04_a_half_opaque_shell_lets_half_the_light_through(method, spp, shell):
    """The masked shell furnace (shell_doc) at a = 1/2: every 4 x 4 block is
    rho (1 - a) = 1/4 (z-tests on the films' variances, Sidak over the
    blocks); the whole image's test would notice 1/4 of 0.9 or 1.1. Camera
    rays reach the floor unmasked; light reaches it through the shell by BSDF
    rays, shadow rays, light paths and connections. (Each light ray crosses
    the shell once, first tested with the ray's own hash: the sphere and the
    cube make the same decisions, through different intersection code.)"""
    expected = 0.25
    # photon: one tile, few photons (they add nothing here: all light is direct)
    tile, options = (16, {"photons": 1024}) if method == "photon" else (4, {})
    films = run_plan(build_scene(shell_doc(shell)), RenderSpec(
        method=method, spp=spp, depth=2, width=16, height=16, tile_size=tile, seed=3,
        options=options))
    mean, var = block_stats(films, 16, 16, 4)
    assert z_pass_rate(mean, var, np.full_like(mean, expected), 0 * var) == 1.0, mean[..., 0]
    mean, var = block_stats(films, 16, 16, 16)
    for scale in (0.9, 1.1):  # power
        assert z_pass_rate(mean, var, np.full_like(mean, expected), 0 * var, scale) == 0.0


def test05_mlt_finds_the_shell_furnace_mean(monkeypatch):
    """MLT on the masked shell: b (the bootstrap's mean luminance, through
    mlt_L's BDPT strategies) is rho (1 - a) by a z-test on b's own error, and
    each image quadrant agrees with b (a t-test on the chain units)."""
    monkeypatch.setattr(mlt, "CHAIN_UNITS", 16)
    films = run_plan(build_scene(shell_doc("cube")), RenderSpec(
        method="mlt", spp=64, depth=2, width=16, height=16, tile_size=16, seed=5,
        options={"bootstrap": 100_000}))
    b, b_se = films[0].artefact["b"][0], films[0].artefact["b_stderr"][0]
    assert abs(b - 0.25) <= norm.isf(ALPHA / 2) * b_se, (b, b_se)
    assert b_se < 0.01
    quads = np.array([f.splat.reshape(2, 8, 2, 8, 3).sum(axis=(1, 3, 4)) / 3 / 64 / f.splat_paths
                      for f in films[1:]])
    k = len(quads)
    est, spread = quads.mean(0), quads.std(0, ddof=1) / math.sqrt(k)
    limit = student_t.ppf(1 - (1 - (1 - ALPHA) ** 0.25) / 2, k - 1)
    assert np.all(np.abs(est - b) <= limit * spread), (est, b, spread)


def checker_doc():
    """A square of albedo 0.6 filling the frame of an 8 x 8 camera, cut out
    by a checkerboard of opacity 1 (color0) and 0 (color1), in front of a
    larger square emitting 1 (albedo 0.3). Cells are 4 x 4 pixels: opaque
    top-right and bottom-left (Mitsuba's checkerboard on the rectangle's uv)."""
    return resolve_document({
        "camera": {"origin": [0, 0, 1], "target": [0, 0, 0], "up": [0, 1, 0], "fov": 90,
                   "fov_axis": "x", "width": 8, "height": 8},
        "textures": {"holes": {"type": "checkerboard", "color0": 1.0, "color1": 0.0}},
        "materials": {"mask": {"type": "diffuse", "albedo": 0.6,
                               "opacity": {"texture": "holes"}},
                      "lamp": {"type": "diffuse", "albedo": 0.3}},
        "shapes": [{"type": "rectangle", "material": "mask"},
                   {"type": "rectangle", "material": "lamp",
                    "to_world": [{"scale": [3, 3, 1]}, {"translate": [0, 0, -1]}],
                    "emitter": {"type": "area", "radiance": [1, 1, 1]}}]})


def test06_a_checkerboard_mask_cuts_exact_holes():
    """Where the texture is 0 the lamp shows exactly (radiance 1, its albedo
    in the AOV), where it is 1 the unlit square exactly (0, albedo 0.6): no
    sample of those pixels decides otherwise. Pixels next to a cell edge or
    the square's border are left out. Light tracing and BDPT leave the opaque cells exactly black
    and light the holes; tile sizes do not change a bit."""
    scene = build_scene(checker_doc())
    inner = np.array([1, 2, 5, 6])  # away from cell edges and the square's border
    rows, cols = np.meshgrid(inner, inner, indexing="ij")
    opaque = (rows < 4) == (cols >= 4)
    for method in ("path-mis", "path-bsdf", "direct", "photon"):
        film = render_serial(scene, RenderSpec(method=method, width=8, height=8, spp=16,
                                               depth=2, seed=1))
        beauty = film.mean()[rows, cols, 0]
        assert np.all(beauty[opaque] == 0.0) and np.all(beauty[~opaque] == 1.0), method
        albedo = film.aovs()["albedo.R"][rows, cols]
        assert np.allclose(albedo[opaque], 0.6) and np.allclose(albedo[~opaque], 0.3), method
    for method, spp in (("light", 256), ("bdpt", 64)):
        spec = RenderSpec(method=method, width=8, height=8, spp=spp, depth=2, seed=1,
                          tile_size=4)
        film = render_serial(scene, spec)
        beauty = film.mean()[rows, cols, 0]
        assert np.all(beauty[opaque] == 0.0) and np.all(beauty[~opaque] > 0.5), method
        again = render_serial(scene, replace(spec, tile_size=8))
        assert np.array_equal(again.sum, film.sum) and np.array_equal(again.splat, film.splat)
    spec = RenderSpec(method="path-mis", width=8, height=8, spp=16, depth=2, seed=1, tile_size=4)
    assert np.array_equal(render_serial(scene, spec).sum,
                          render_serial(scene, replace(spec, tile_size=8)).sum)


def masked_box():
    """cornell-box with a masked panel across it: a square of albedo 0.8
    between the light and the floor whose checkerboard opacity is 0.3 and
    0.8; every kind of ray crosses it."""
    doc = load_scene("cornell-box").doc
    doc = {**doc, "textures": {"c": {"type": "checkerboard", "color0": 0.3, "color1": 0.8,
                                     "uv_scale": [3, 3]}},
           "materials": {**doc["materials"], "panel": {
               "type": "diffuse", "albedo": 0.8, "opacity": {"texture": "c"}, "twosided": True}},
           "shapes": doc["shapes"] + [{"type": "rectangle", "material": "panel", "to_world": [
               {"scale": [0.6, 0.6, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": 70}},
               {"translate": [0, 0.3, 0]}]}]}
    return build_scene(resolve_document(doc))


def test07_methods_agree_on_a_masked_scene():
    """On masked_box every unbiased method's 4 x 4 pixel blocks agree with
    path-mis (two-sided z-tests on both films' variances, Sidak over the
    blocks and channels) at depth 3, where light crosses the panel in every
    way a method traces it, and some block would show a 10 % error; photon
    mapping, biased at any finite radius, agrees over the whole image (as
    test_renderer_photon.py's test06), where 10 % would show."""
    scene = masked_box()
    kw = dict(depth=3, width=16, height=16)
    ref_films = run_plan(scene, RenderSpec(method="path-mis", spp=1024, seed=1, tile_size=4, **kw))
    ref, ref_var = block_stats(ref_films, 16, 16, 4)
    for method, spp in (("path-nee", 256), ("path-bsdf", 4096), ("light", 1024), ("bdpt", 256)):
        films = run_plan(scene, RenderSpec(method=method, spp=spp, seed=2, tile_size=4, **kw))
        mean, var = block_stats(films, 16, 16, 4)
        assert z_pass_rate(ref, ref_var, mean, var) == 1.0, method
        assert z_pass_rate(ref, ref_var, mean, var, 1.1) < 1.0, method  # power
    films = run_plan(scene, RenderSpec(method="photon", spp=128, seed=2, tile_size=16, **kw))
    mean, var = block_stats(films, 16, 16, 16)
    ref, ref_var = block_stats(ref_films, 16, 16, 16)
    assert z_pass_rate(ref, ref_var, mean, var) == 1.0, (mean, ref)
    for scale in (0.9, 1.1):
        assert z_pass_rate(ref, ref_var, mean, var, scale) == 0.0, scale
