"""What the renderer refuses before any render: method options that are no
numbers or beyond what a render can honour, and radiosity jobs whose patches
could never be solved; the ends of each range render finite images. (The
scene format's limits are in test_renderer_scene.py.)"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from renderer import METHODS, RenderSpec, SpecError, build_scene, builtin_scene_names, \
    load_scene, render_serial, resolve_document
from renderer import radiosity_solve as FEM
from renderer.integrators import bdpt as B
from renderer.integrators import photon as P
from renderer.integrators import radiosity as R

ROOT = Path(__file__).resolve().parents[1]

NON_FINITE = [math.nan, math.inf, -math.inf]


def _bounded_options():
    for method in dict.fromkeys(METHODS.values()):
        for option in method.options:
            if option.bounds is not None:
                yield pytest.param(method.name, option.name, option.type,
                                   id=f"{method.name}-{option.name}")


@pytest.mark.parametrize("method, option, kind", list(_bounded_options()))
def test01_bounded_options_refuse_nan_and_infinities(method, option, kind):
    """NaN passes every comparison with a bound (photon radius, mlt sigma and
    radiosity patch_size took it); an infinite size is none either."""
    for value in NON_FINITE:
        spec = RenderSpec(method=method, spp=1, depth=1, options={option: value})
        with pytest.raises(SpecError) as err:
            spec.validate()
        expected = "must be a finite number" if kind is float else "must be an integer"
        assert err.value.field == f"options.{option}" and expected in err.value.message


def test02_the_cli_refuses_them_too(capsys):
    from renderer.cli import main

    assert main(["cornell-box", "--method", "photon", "--option", "radius=nan", "--quiet"]) == 2
    assert "options.radius: must be a finite number" in capsys.readouterr().err


def _radiosity(**options) -> RenderSpec:
    return RenderSpec(method="radiosity", spp=1, depth=1, width=8, height=8, options=options)


@pytest.mark.parametrize("options, field, words", [
    ({"patch_size": 1e-3}, "options.patch_size", "58090400 patches (at most 250000)"),
    ({"patch_size": 1e-100}, "options.patch_size", "5.81e+201 patches"),
    ({"patch_size": 5e-324}, "options.patch_size", "inf patches"),  # overflowed in the solve
    ({"patch_size": 0.02, "ff_rays": 65536}, "options.ff_rays", "stored hits"),
    ({"form_factors": "hemicube", "hemicube_res": 1024}, "options.hemicube_res", "stored hits"),
])
def test03_radiosity_counts_its_patches_at_submission(options, field, words):
    """Before, these were accepted and failed in the solve unit, every attempt."""
    doc = resolve_document("cornell-box")
    _radiosity(**options).validate()  # without the scene nothing can be counted
    with pytest.raises(SpecError) as err:
        _radiosity(**options).validate(scene=doc)
    assert err.value.field == field and words in err.value.message, err.value
    _radiosity().validate(scene=doc)  # the automatic patch size: 5978 patches
    _radiosity(patch_size=0.02).validate(scene=doc)


@pytest.mark.parametrize("name", builtin_scene_names())
def test04_the_submission_count_is_the_solver_s(name):
    """Counted from the document (no BVH, no kernel), the patches are exactly
    those mesh_patches cuts, so the refusal and the solve's limit agree."""
    doc = resolve_document(name)
    scene = build_scene(doc)
    tri_p, sph_r, (lo, hi) = R._document_geometry(doc)
    auto = FEM.auto_patch_size(scene)
    assert FEM.patch_size_of_bounds(lo, hi) == auto
    for size in (auto, 0.05, 0.3, 2.0):
        assert FEM.patch_total(tri_p, sph_r, size) == FEM.patch_count(scene, size)
    assert FEM.patch_count(scene, auto) == len(FEM.mesh_patches(scene, auto).kind)


def test05_an_alias_names_its_method_in_the_spec():
    """One method, one name: what is stored or written says `path-mis`, never `path`."""
    for alias, method in ((m, meth) for meth in set(METHODS.values()) for m in meth.aliases):
        spec = RenderSpec(method=alias, spp=1, depth=1, width=4, height=4).validate()
        assert spec.method == method.name and spec.to_dict()["method"] == method.name
    assert RenderSpec().method == "path-mis"
    assert RenderSpec(method="nonsense").method == "nonsense"  # left for validate to name


def test06_exr_attributes_are_typed_and_never_silently_wrong(tmp_path):
    """The OpenEXR package stores an int beyond 32 bits as 0: write_exr refuses
    one, and the metadata writes such counts (seed, samples, rays) as text."""
    from renderer import merge, read_exr
    from renderer.metadata import METADATA_KEYS, exr_metadata

    film = merge(2, 2, [])
    with pytest.raises(ValueError, match="32-bit"):
        film.write_exr(tmp_path / "big.exr", {"seed": 1 << 40})
    assert not (tmp_path / "big.exr").exists()
    spec = RenderSpec(method="path", spp=3, depth=2, width=2, height=2, seed=(1 << 63) - 1,
                      options={"heuristic": "balance"})
    stats = {"samples": 1 << 40, "rays": 5 << 40, "seconds": 1.25}
    film.write_exr(tmp_path / "m.exr", exr_metadata(spec, stats, scene="s", scene_hash="h"))
    _, header = read_exr(tmp_path / "m.exr")
    got = {k[len("rayfarm."):]: v for k, v in header.items() if k.startswith("rayfarm.")}
    assert tuple(sorted(got)) == tuple(sorted(METADATA_KEYS))
    assert got["seed"] == str((1 << 63) - 1) and got["samples"] == str(1 << 40)
    assert got["rays"] == str(5 << 40) and got["render_seconds"] == 1.25
    assert (got["spp"], got["depth"], got["denoised"]) == (3, 2, 0)
    assert got["method"] == "path-mis" and got["options"] == '{"heuristic": "balance"}'


@pytest.mark.parametrize("method, options, field, words", [
    # failed in the kernel's typing (an int64 argument), every attempt
    ("bdpt", {"strategy": "s=" + "1" + "0" * 20}, "options.strategy", "from 0 to 65"),
    ("bdpt", {"strategy": "s=66"}, "options.strategy", "from 0 to 65"),
    # r^2 = 0: NaN pixels (sppm at 1e-300, photonmap at 1e-160)
    ("photon", {"radius": 1e-320}, "options.radius", "0 (automatic) or at least 1e-06"),
    ("photon", {"radius": 1e-160, "mode": "photonmap"}, "options.radius", "at least 1e-06"),
    # r^2 = inf: the k-NN search found no photon
    ("photon", {"radius": 1e308}, "options.radius", "between 0.0 and 10000000.0"),
    ("radiosity", {"patch_size": 1e308}, "options.patch_size", "between 0.0 and 10000000.0"),
    # (depth + 1) x bootstrap weights, sorted: 5 GB per array at depth 64
    ("mlt", {"bootstrap": 10_000_000}, "options.bootstrap",
     "x 2 depths exceed 16777216 bootstrap paths: at depth 1, at most 8388608"),
])
def test07_options_a_render_cannot_honour_are_refused_naming_them(method, options, field, words):
    """Before, each was accepted and its job failed on the farm or rendered a
    non-finite or wrong image (the measurements beside the bounds)."""
    with pytest.raises(SpecError) as err:
        RenderSpec(method=method, spp=1, depth=1, width=8, height=8,
                   options=options).validate(scene=resolve_document("cornell-box"))
    assert err.value.field == field and words in err.value.message, err.value


def _extreme_options():
    """Each float option at either end of what its method accepts (photon's
    radius also at its least non-automatic value), and BDPT's largest K."""
    for method in dict.fromkeys(METHODS.values()):
        for option in method.options:
            if option.type is float:
                ends = [b for b in option.bounds if b is not None]
                if method.name == "photon" and option.name == "radius":
                    ends.append(P.MIN_RADIUS)
                for value in ends:
                    # the other options at warm-up's cheap values (radiosity's coarse
                    # mesh): the end under test is what is checked, not a full solve
                    yield pytest.param(method.name, {**method.warm_base, option.name: value},
                                       id=f"{method.name}-{option.name}={value:g}")
    yield pytest.param("bdpt", {"strategy": f"s={B.MAX_STRATEGY}"}, id="bdpt-strategy=max")


@pytest.mark.parametrize("method, options", list(_extreme_options()))
def test08_the_ends_of_each_range_render_finite_images(method, options):
    spec = RenderSpec(method=method, spp=2, depth=3, width=8, height=8, tile_size=8,
                      options=options)
    film = render_serial(load_scene("cornell-box"), spec.validate(
        scene=resolve_document("cornell-box")))
    assert np.all(np.isfinite(film.mean().astype(np.float32))), options


def test09_the_ends_of_the_scene_ranges_render_finite_images():
    """The smallest roughness, field of view and sphere the scene format
    accepts. Measured before the bounds: roughness 1e-10 rendered NaN pixels
    in path-mis and bdpt (the GGX alpha^2 is 0 beside 1 - cos^2)."""
    from renderer.scene_format import MIN_FOV, MIN_LENGTH, MIN_ROUGHNESS

    doc = json.loads((ROOT / "renderer" / "scenes" / "cornell-box.json").read_text())
    doc["materials"]["gloss"] = {"type": "glossy", "roughness": MIN_ROUGHNESS}
    doc["shapes"] += [{"type": "rectangle", "material": "gloss",
                       "to_world": [{"scale": [0.5, 0.5, 1]}, {"translate": [0, 0, -0.9]}]},
                      {"type": "sphere", "material": "gloss", "radius": 0.3,
                       "center": [0.3, -0.6, 0.2]},
                      {"type": "sphere", "material": "gloss", "radius": MIN_LENGTH}]
    narrow = json.loads(json.dumps(doc))
    narrow["camera"]["fov"] = MIN_FOV
    for scene_doc in (doc, narrow):
        scene = build_scene(resolve_document(scene_doc))
        for method in ("path-mis", "bdpt", "light", "photon", "mlt"):
            film = render_serial(scene, RenderSpec(method=method, spp=16, depth=4, width=16,
                                                   height=16, tile_size=16))
            assert np.all(np.isfinite(film.mean().astype(np.float32))), method
