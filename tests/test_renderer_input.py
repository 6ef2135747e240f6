"""What the renderer refuses before any render: method options that are no
numbers, and radiosity jobs whose patches could never be solved. (The scene
format's limits are in test_renderer_scene.py.)"""

from __future__ import annotations

import math

import pytest

from renderer import METHODS, RenderSpec, SpecError, build_scene, builtin_scene_names, \
    resolve_document
from renderer import radiosity_solve as FEM
from renderer.integrators import radiosity as R

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
