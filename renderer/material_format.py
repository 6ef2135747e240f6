"""Materials and textures of a scene document: validated and resolved
(docs/scene-format.md, "materials" and "Textures"); scene_format.py calls
`resolve_material` and `resolve_texture`."""

from __future__ import annotations

import json
from typing import Any

from .errors import SceneError
from .validators import _bool, _coordinate, _name_list, _number, _require, _vec3

MATERIAL_TYPES = ("diffuse", "mirror", "dielectric", "glossy")
# pbrt-v4 renders a GGX lobe of alpha below 1e-3 as a perfect mirror ("effectively
# smooth"); here the `mirror` material is that, and alpha^2 underflows far below.
MIN_ROUGHNESS = 1e-3

# Fields a material may hold beyond its type, by type (anything else is refused).
MATERIAL_FIELDS = {"diffuse": ("albedo",), "mirror": ("tint",), "dielectric": ("ior",),
                   "glossy": ("specular", "roughness", "distribution")}
COMMON_MATERIAL_FIELDS = ("type", "twosided", "opacity", "opacity_cutoff")
# The glossy lobe's microfacet distributions (kernels/ggx.py), Mitsuba's names.
DISTRIBUTIONS = ("ggx", "beckmann")
TEXTURE_TYPES = ("bitmap", "checkerboard")
TEXTURE_FILTERS = ("bilinear", "nearest")


def _colour_input(value: Any, loc: str, what: str, textures: dict) -> Any:
    """An RGB in [0, 1] (a scalar means grey) or ``{"texture": name}``."""
    if isinstance(value, dict):
        return _texture_ref(value, loc, textures)
    rgb = _vec3(value, loc, nonneg=True)
    if max(rgb) > 1.0:
        raise SceneError(f"{what} components must be <= 1 (energy conservation)", loc)
    return rgb


def _texture_ref(value: dict, loc: str, textures: dict) -> dict:
    if set(value) != {"texture"} or not isinstance(value["texture"], str):
        raise SceneError('a texture input is {"texture": "<name>"} and nothing else', loc)
    if value["texture"] not in textures:
        raise SceneError(f"unknown texture '{value['texture']}' (defined: "
                         f"{_name_list(textures) or 'none'})", f"{loc}.texture")
    return {"texture": value["texture"]}


def resolve_material(name: str, mat: Any, textures: dict | None = None) -> dict:
    loc = f"materials.{name}"
    textures = textures or {}
    if not isinstance(mat, dict):
        raise SceneError("expected an object", loc)
    mtype = _require(mat, "type", loc)
    if mtype not in MATERIAL_FIELDS:
        raise SceneError(f"unknown material type '{mtype}' (allowed: {_name_list(MATERIAL_TYPES)})",
                         f"{loc}.type")
    allowed = COMMON_MATERIAL_FIELDS + MATERIAL_FIELDS[mtype]
    unknown = sorted(set(mat) - set(allowed))
    if unknown:
        raise SceneError(f"unknown field(s) of a {mtype} material: {', '.join(unknown)} "
                         f"(allowed: {', '.join(allowed)})", f"{loc}.{unknown[0]}")
    out: dict[str, Any] = {"type": mtype}
    if mtype == "diffuse":
        out["albedo"] = _colour_input(mat.get("albedo", [0.5, 0.5, 0.5]), f"{loc}.albedo",
                                      "albedo", textures)
    elif mtype == "mirror":
        out["tint"] = _colour_input(mat.get("tint", [1.0, 1.0, 1.0]), f"{loc}.tint", "tint",
                                    textures)
    elif mtype == "dielectric":
        out["ior"] = _number(mat.get("ior", 1.5), f"{loc}.ior", lo=1.0, hi=4.0)
    else:
        out["specular"] = _colour_input(mat.get("specular", [1.0, 1.0, 1.0]), f"{loc}.specular",
                                        "specular", textures)
        rough = mat.get("roughness", 0.1)
        if isinstance(rough, dict):
            out["roughness"] = _texture_ref(rough, f"{loc}.roughness", textures)
        else:
            out["roughness"] = _number(rough, f"{loc}.roughness", lo=MIN_ROUGHNESS, hi=1.0)
        distribution = mat.get("distribution", "ggx")
        if distribution not in DISTRIBUTIONS:
            raise SceneError(f"unknown distribution {json.dumps(distribution)[:40]} (allowed: "
                             f"{_name_list(DISTRIBUTIONS)})", f"{loc}.distribution")
        if distribution != "ggx":  # the default is left out: older documents keep their hash
            out["distribution"] = distribution
    # The default (false) is left out of the resolved document, so the scenes
    # written before the field existed keep their hash.
    if _bool(mat.get("twosided", False), f"{loc}.twosided"):
        out["twosided"] = True
    out.update(_opacity(mat, loc, textures))
    return out


def _opacity(mat: dict, loc: str, textures: dict) -> dict:
    """The mask fields of a resolved material: `opacity` (a number in [0, 1]
    or a texture's value) and `opacity_cutoff` (with a textured opacity: opaque
    where the value is >= it, cut out elsewhere). Opacity 1, the default, is
    left out, so scenes written before masks keep their hash."""
    op = mat.get("opacity", 1.0)
    if isinstance(op, dict):
        out: dict[str, Any] = {"opacity": _texture_ref(op, f"{loc}.opacity", textures)}
    else:
        op = _number(op, f"{loc}.opacity", lo=0.0, hi=1.0)
        out = {"opacity": op} if op < 1.0 else {}
    if "opacity_cutoff" in mat:
        if not isinstance(op, dict):
            raise SceneError("opacity_cutoff thresholds a textured opacity (here opacity is "
                             f"{op:g})", f"{loc}.opacity_cutoff")
        # (a cutoff of 0 would keep every hit: no mask at all)
        out["opacity_cutoff"] = _number(mat["opacity_cutoff"], f"{loc}.opacity_cutoff", lo=0.0,
                                        hi=1.0, lo_open=True)
    return out


def _uv_pair(value: Any, loc: str, default: list[float]) -> list[float]:
    if value is None:
        return list(default)
    if not isinstance(value, list) or len(value) != 2:
        raise SceneError("expected a list of 2 numbers", loc)
    return [_coordinate(v, f"{loc}[{i}]") for i, v in enumerate(value)]


def resolve_texture(name: str, tex: Any) -> dict:
    """A bitmap (an image asset named by its digest) or a procedural checkerboard."""
    loc = f"textures.{name}"
    if not isinstance(tex, dict):
        raise SceneError("expected an object", loc)
    ttype = _require(tex, "type", loc)
    fields = {"bitmap": ("type", "image", "filter", "uv_scale", "uv_offset"),
              "checkerboard": ("type", "color0", "color1", "uv_scale", "uv_offset")}
    if ttype not in fields:
        raise SceneError(f"unknown texture type '{ttype}' (allowed: {_name_list(TEXTURE_TYPES)})",
                         f"{loc}.type")
    unknown = sorted(set(tex) - set(fields[ttype]))
    if unknown:
        raise SceneError(f"unknown field(s) of a {ttype} texture: {', '.join(unknown)} "
                         f"(allowed: {', '.join(fields[ttype])})", f"{loc}.{unknown[0]}")
    out: dict[str, Any] = {"type": ttype,
                           "uv_scale": _uv_pair(tex.get("uv_scale"), f"{loc}.uv_scale", [1, 1]),
                           "uv_offset": _uv_pair(tex.get("uv_offset"), f"{loc}.uv_offset", [0, 0])}
    if ttype == "bitmap":
        digest = _require(tex, "image", loc)
        if (not isinstance(digest, str) or len(digest) != 64
                or any(c not in "0123456789abcdef" for c in digest)):
            raise SceneError("expected the image asset's SHA-256 digest (64 lower-case hex "
                             "digits)", f"{loc}.image")
        out["image"] = digest
        out["filter"] = tex.get("filter", "bilinear")
        if out["filter"] not in TEXTURE_FILTERS:
            raise SceneError(f"unknown filter {json.dumps(out['filter'])[:40]} (allowed: "
                             f"{_name_list(TEXTURE_FILTERS)})", f"{loc}.filter")
    else:
        # Mitsuba 3's checkerboard defaults
        out["color0"] = _vec3(tex.get("color0", 0.4), f"{loc}.color0", nonneg=True, limit=1.0)
        out["color1"] = _vec3(tex.get("color1", 0.2), f"{loc}.color1", nonneg=True, limit=1.0)
    return out
