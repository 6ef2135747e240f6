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
