"""The native scene format: parse, validate and resolve a JSON scene document.

A scene is one JSON object (`docs/scene-format.md` documents every field)::

    {
      "camera":   {"type": "perspective", "origin": [0, 0, 3.9], "target": [0, 0, 0],
                   "up": [0, 1, 0], "fov": 39.3077, "fov_axis": "x", "width": 256, "height": 256},
      "materials": {"white": {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]}},
      "shapes":   [{"type": "rectangle", "to_world": [[...], [...], [...], [...]],
                    "material": "white", "emitter": {"type": "area", "radiance": [1, 1, 1]}}],
      "emitters": [{"type": "point", "position": [0, 0, 0], "intensity": [1, 1, 1]}]
    }

`resolve_scene` turns any accepted input (a built-in name, a path, a dict)
into a *resolved document* and its assets: validated, defaults filled in,
every mesh (a file, inline arrays or a digest) an asset named by its digest
(renderer.assets), every transform a 4x4 matrix; `resolve_document` returns
the document carrying its assets (`ResolvedDocument`). The document names
each asset by digest, so its canonical JSON hash (`scene_hash`) identifies
the scene wherever it travels: the farm ships scenes to workers by that hash
and their assets by digest. Fields allowed in each object: `FIELDS`.

Errors are `SceneError`s whose `location` names the offending field, e.g.
``shapes[2].to_world``.

Limits. Every number is finite and of a magnitude the renderer handles:
coordinates (camera, vertices, centres, radii, point lights, transform
entries) within +-`MAX_COORDINATE`, in local space and again in world space
(after `to_world`); radiance and intensity at most `MAX_RADIANCE`, so sums
of samples and of their squares stay finite in the float32 EXR. Lengths the
renderer squares or divides by are at least `MIN_LENGTH` (a sphere's radius,
the camera's distance to its target, a rotation axis): 1e-320 squared is 0.
A glossy roughness (the GGX alpha) is at least `MIN_ROUGHNESS` and a field of
view at least `MIN_FOV` degrees (measured: roughness 1e-10 rendered NaN pixels
in path-mis and bdpt, alpha^2 being 0 beside 1 - cos^2; a film of fov 1e-320
has an area of 0, which the camera's importance divides by). An emitting
triangle must have an area (`MIN_EMITTER_AREA`, and not be a sliver:
`COLLINEAR`): the renderer samples lights by area, and a light whose
triangles have none crashes the render process (measured: SIGSEGV in every
method for a collinear or coincident-vertex mesh light, and for a sliver of
height 1e-200).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from .errors import SceneError
from .material_format import MATERIAL_TYPES, MIN_ROUGHNESS  # noqa: F401 (re-exported)
from .material_format import resolve_material as _resolve_material
from .material_format import resolve_texture as _resolve_texture
from .primitives import world_mesh
from .validators import (  # noqa: F401 (MAX_COORDINATE: re-exported)
    MAX_COORDINATE,
    _bool,
    _coordinate,
    _name_list,
    _number,
    _require,
    _vec3,
)
from .scene_meshes import AssetStore, MeshLimits, resolve_mesh

__all__ = [
    "builtin_scene_names",
    "resolve_document",
    "resolve_scene",
    "ResolvedDocument",
    "document_assets",
    "scene_asset_digests",
    "FIELDS",
    "scene_hash",
    "canonical_json",
    "MATERIAL_TYPES",
    "SHAPE_TYPES",
]

SHAPE_TYPES = ("rectangle", "disk", "cube", "sphere", "mesh")
EMITTER_TYPES = ("point",)
FOV_AXES = ("x", "y", "smaller", "larger", "diagonal")

MAX_IMAGE_SIDE = 8192
MAX_TRIANGLES = 5_000_000
MAX_FILE_BYTES = 256 * 1024 * 1024
SCENE_FORMAT = "rayfarm-scene/1"  # the one version this renderer reads
MAX_RADIANCE = 1e6  # area-light radiance and point-light intensity, per component
MIN_LENGTH = 1.0 / MAX_COORDINATE  # a sphere's radius, camera to target, a rotation axis
MIN_FOV = 1e-3  # degrees: a film of tan(fov/2)^2 far from underflow
MIN_EMITTER_AREA = 1e-12  # world-space area of an emitting triangle (or sphere)
COLLINEAR = 1e-9  # an emitting triangle's height / its longest edge, at least
MAX_NESTING = 16  # levels of lists and objects (shapes[i].to_world[j].rotate.axis: 6)

# The fields each object of the format may hold: anything else is refused
# with its location (a misspelt or unsupported field must not be silently
# ignored). One table, so that a new field is added in one place: "shape"
# holds every shape's fields, "shape.<type>" a type's own, likewise for
# materials and emitters.
FIELDS: dict[str, set[str]] = {
    "document": {"format", "camera", "materials", "shapes", "emitters", "name", "description",
                 "defaults", "textures"},
    "camera": {"type", "origin", "target", "up", "to_world", "fov", "fov_axis", "width",
               "height", "aperture_radius", "focus_distance", "filter"},
    "filter.box": {"type"},
    "filter.tent": {"type", "radius"},
    "filter.gaussian": {"type", "stddev"},
    # (material_format.MATERIAL_FIELDS: the same per type, checked there)
    "material": {"type", "twosided", "opacity", "opacity_cutoff"},
    "material.diffuse": {"albedo"},
    "material.mirror": {"tint"},
    "material.dielectric": {"ior"},
    "material.glossy": {"specular", "roughness", "distribution"},
    "shape": {"type", "material", "to_world", "flip_normals", "name", "emitter"},
    "shape.rectangle": set(),
    "shape.disk": set(),
    "shape.cube": set(),
    "shape.sphere": {"center", "radius"},
    # a mesh: one of `mesh` (an asset's digest), `file` (+ `shape_index` for a
    # .serialized file), inline `vertices` + `faces` [+ `normals`, `uvs`];
    # `triangles` is what resolving writes beside `mesh` (checked if given)
    "shape.mesh": {"mesh", "file", "shape_index", "vertices", "faces", "normals", "uvs",
                   "face_normals", "triangles"},
    "emitter.area": {"type", "radiance"},
    "emitter.point": {"type", "position", "intensity"},
    "transform.rotate": {"axis", "angle"},
}


def _check_fields(obj: dict, loc: str, *kinds: str) -> None:
    """Refuse a field of `obj` that none of the FIELDS tables `kinds` allows."""
    allowed = set().union(*(FIELDS.get(k, set()) for k in kinds))
    for key in obj:
        if key not in allowed:
            raise SceneError(f"unknown field '{str(key)[:40]}' (allowed: "
                             f"{', '.join(sorted(allowed))})", f"{loc}.{key}" if loc else str(key))


# ----------------------------------------------------------------------------
# Built-in scenes ship as JSON files inside the package.

def _builtin_dir():
    return resources.files("renderer") / "scenes"


def builtin_scene_names() -> list[str]:
    """Names of the built-in scenes, e.g. ``['cornell-box']``."""
    return sorted(p.name[: -len(".json")] for p in _builtin_dir().iterdir()
                  if p.name.endswith(".json"))


def _load_builtin(name: str) -> dict:
    text = (_builtin_dir() / f"{name}.json").read_text()
    return json.loads(text)


# ----------------------------------------------------------------------------
# Checks of the document's structure (the small validators: validators.py).

def _nesting(value: Any) -> int:
    """How many lists and objects deep `value` goes (iteratively: it may be deep)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            deepest = max(deepest, depth)
            children = item.values() if isinstance(item, dict) else item
            stack.extend((child, depth + 1) for child in children)
    return deepest


def _check_world_points(points: np.ndarray, loc: str, what: str) -> None:
    """World-space points must be finite and within +-MAX_COORDINATE; `what`
    names point j in the message (``"vertex {j}"``)."""
    bad = ~np.all(np.isfinite(points) & (np.abs(points) <= MAX_COORDINATE), axis=1)
    if np.any(bad):
        j = int(np.argmax(bad))
        raise SceneError(f"{what.format(j=j)} lies at {points[j].tolist()} after to_world; every "
                         f"coordinate must be within +-{MAX_COORDINATE:g}", loc)


def _rotation(axis: list[float], angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    t = math.radians(angle_deg)
    c, s = math.cos(t), math.sin(t)
    x, y, z = a
    r = np.eye(4)
    r[:3, :3] = [
        [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
        [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
        [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
    ]
    return r


def _transform(value: Any, loc: str) -> list[list[float]]:
    """A 4x4 row-major matrix, or a list of operations applied in order
    (the first listed is applied first, as in Mitsuba's XML):
    ``[{"scale": [sx, sy, sz]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
    {"translate": [x, y, z]}]``."""
    if value is None:
        return np.eye(4).tolist()
    if (isinstance(value, list) and len(value) == 4
            and all(isinstance(r, list) for r in value)):
        rows = []
        for i, row in enumerate(value):
            if len(row) != 4:
                raise SceneError("a matrix row needs 4 numbers", f"{loc}[{i}]")
            rows.append([_coordinate(v, f"{loc}[{i}][{j}]") for j, v in enumerate(row)])
        m = np.asarray(rows)
    elif isinstance(value, list):
        m = np.eye(4)
        for i, op in enumerate(value):
            oloc = f"{loc}[{i}]"
            if not isinstance(op, dict) or len(op) != 1:
                raise SceneError("expected one of {'translate': ..}, {'scale': ..}, "
                                 "{'rotate': {'axis': .., 'angle': ..}}", oloc)
            (kind, arg), = op.items()
            if kind == "translate":
                t = np.eye(4)
                t[:3, 3] = _vec3(arg, f"{oloc}.translate")
            elif kind == "scale":
                t = np.diag(_vec3(arg, f"{oloc}.scale") + [1.0])
            elif kind == "rotate":
                if not isinstance(arg, dict):
                    raise SceneError("expected {'axis': [x, y, z], 'angle': degrees}", f"{oloc}.rotate")
                _check_fields(arg, f"{oloc}.rotate", "transform.rotate")
                axis = _vec3(_require(arg, "axis", f"{oloc}.rotate"), f"{oloc}.rotate.axis")
                if not np.linalg.norm(axis) >= MIN_LENGTH:
                    raise SceneError(f"a rotation axis needs a length of at least "
                                     f"{MIN_LENGTH:g}", f"{oloc}.rotate.axis")
                t = _rotation(axis, _coordinate(_require(arg, "angle", f"{oloc}.rotate"),
                                                f"{oloc}.rotate.angle"))
            else:
                raise SceneError(f"unknown transform operation '{kind}' "
                                 "(allowed: translate, scale, rotate)", oloc)
            m = t @ m
        if not np.all(np.abs(m) <= MAX_COORDINATE):  # products of operations
            raise SceneError(f"the composed matrix has entries beyond +-{MAX_COORDINATE:g}", loc)
    else:
        raise SceneError("expected a 4x4 matrix or a list of transform operations", loc)
    if abs(np.linalg.det(m[:3, :3])) < 1e-12:
        raise SceneError("transform is singular", loc)
    if not np.allclose(m[3], [0, 0, 0, 1]):
        raise SceneError("last matrix row must be [0, 0, 0, 1] (no projective transforms)", loc)
    return m.tolist()


# ----------------------------------------------------------------------------

CAMERA_TYPES = ("perspective", "thinlens")
FILTER_TYPES = ("box", "tent", "gaussian")
MAX_FILTER_RADIUS = 8.0  # pixels: a light-tracing splat touches (2 r + 1)^2 pixels at most
ORTHONORMAL_TOLERANCE = 1e-3  # Mitsuba's has_scale() tolerance on a sensor's to_world


def _camera_to_world(value: Any, loc: str) -> list[list[float]]:
    """A sensor's to_world: a rotation (or a mirror: a rotation times a
    reflection) and a translation, as Mitsuba requires of sensors (it refuses
    scale factors); the rows of its 3x3 part orthonormal to 1e-3."""
    m = np.asarray(_transform(value, loc))
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), rtol=0.0, atol=ORTHONORMAL_TOLERANCE):
        raise SceneError("a camera's to_world must be a rotation (or a mirror) and a "
                         "translation: no scale or shear (Mitsuba refuses scale factors in a "
                         "sensor's transform)", loc)
    return m.tolist()


def _resolve_filter(value: Any, loc: str) -> dict:
    if isinstance(value, str):
        value = {"type": value}
    if not isinstance(value, dict):
        raise SceneError("expected {'type': 'box'}, {'type': 'tent', 'radius': r} or "
                         "{'type': 'gaussian', 'stddev': s}", loc)
    ftype = value.get("type")
    if ftype not in FILTER_TYPES:
        raise SceneError(f"unknown filter type {json.dumps(ftype)[:60]} (allowed: "
                         f"{_name_list(FILTER_TYPES)})", f"{loc}.type")
    _check_fields(value, loc, f"filter.{ftype}")
    out = {"type": ftype}
    # Mitsuba 3's defaults: a tent of radius 1 pixel, a Gaussian of standard
    # deviation 0.5 pixel (cut off at 4 standard deviations: kernels/camera.py)
    if ftype == "tent":
        out["radius"] = _number(value.get("radius", 1.0), f"{loc}.radius", lo=0.01,
                                hi=MAX_FILTER_RADIUS)
    elif ftype == "gaussian":
        out["stddev"] = _number(value.get("stddev", 0.5), f"{loc}.stddev", lo=0.01,
                                hi=MAX_FILTER_RADIUS / 4)
    return out


def _resolve_camera(cam: Any) -> dict:
    """The camera: either origin/target/up (a look-at) or `to_world`
    (Mitsuba's sensor convention: it looks along local +z, +y is up and +x
    points to the left of the image), and a `thinlens` type with
    `aperture_radius`, `focus_distance`. Fields left at their defaults are
    left out, so a pinhole scene keeps its document (and hash)."""
    loc = "camera"
    if not isinstance(cam, dict):
        raise SceneError("expected an object", loc)
    _check_fields(cam, loc, "camera")
    ctype = cam.get("type", "perspective")
    if ctype not in CAMERA_TYPES:
        raise SceneError(f"unknown camera type {json.dumps(ctype)[:60]} (allowed: "
                         f"{_name_list(CAMERA_TYPES)})", f"{loc}.type")
    out: dict[str, Any] = {"type": ctype}
    if "to_world" in cam:
        given = sorted(k for k in ("origin", "target", "up") if k in cam)
        if given:
            raise SceneError(f"give either to_world or origin/target/up, not both (also "
                             f"given: {', '.join(given)})", f"{loc}.to_world")
        out["to_world"] = _camera_to_world(cam["to_world"], f"{loc}.to_world")
    else:
        out["origin"] = _vec3(_require(cam, "origin", loc), f"{loc}.origin")
        out["target"] = _vec3(_require(cam, "target", loc), f"{loc}.target")
        out["up"] = _vec3(cam.get("up", [0, 1, 0]), f"{loc}.up")
    out.update({
        "fov": _number(_require(cam, "fov", loc), f"{loc}.fov", lo=MIN_FOV, hi=179.0),
        "fov_axis": cam.get("fov_axis", "x"),
        "width": cam.get("width", 256),
        "height": cam.get("height", 256),
    })
    if out["fov_axis"] not in FOV_AXES:
        raise SceneError(f"unknown fov_axis {json.dumps(out['fov_axis'])[:60]} (allowed: "
                         f"{_name_list(FOV_AXES)})", f"{loc}.fov_axis")
    for key in ("width", "height"):
        v = out[key]
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_IMAGE_SIDE:
            raise SceneError(f"must be an integer in [1, {MAX_IMAGE_SIDE}]", f"{loc}.{key}")
    if "origin" in out:
        forward = np.subtract(out["target"], out["origin"])
        if not np.linalg.norm(forward) >= MIN_LENGTH:
            raise SceneError(f"target must lie at least {MIN_LENGTH:g} from origin",
                             f"{loc}.target")
        if np.linalg.norm(np.cross(forward, out["up"])) < 1e-9 * np.linalg.norm(forward):
            raise SceneError("up is parallel to the viewing direction", f"{loc}.up")
    lens_fields = [k for k in ("aperture_radius", "focus_distance") if k in cam]
    if ctype == "thinlens":
        # Mitsuba's thinlens requires both (its defaults are no usable lens)
        out["aperture_radius"] = _number(_require(cam, "aperture_radius", loc),
                                         f"{loc}.aperture_radius", lo=0.0, hi=MAX_COORDINATE)
        out["focus_distance"] = _number(_require(cam, "focus_distance", loc),
                                        f"{loc}.focus_distance", lo=MIN_LENGTH,
                                        hi=MAX_COORDINATE)
    elif lens_fields:
        raise SceneError(f"{lens_fields[0]} needs \"type\": \"thinlens\" (a perspective "
                         "camera is a pinhole)", f"{loc}.{lens_fields[0]}")
    if "filter" in cam:
        filt = _resolve_filter(cam["filter"], f"{loc}.filter")
        if filt["type"] != "box":
            out["filter"] = filt
    return out


def _resolve_shape(i: int, shape: Any, materials: dict, base_dir: Path | None,
                   root: Path | None = None, store: AssetStore | None = None) -> dict:
    loc = f"shapes[{i}]"
    store = store if store is not None else AssetStore(None)
    if not isinstance(shape, dict):
        raise SceneError("expected an object", loc)
    stype = _require(shape, "type", loc)
    if stype not in SHAPE_TYPES:
        raise SceneError(f"unknown shape type '{stype}' (allowed: {_name_list(SHAPE_TYPES)})", f"{loc}.type")
    _check_fields(shape, loc, "shape", f"shape.{stype}")
    mat = _require(shape, "material", loc)
    if not isinstance(mat, str):
        raise SceneError("expected a material name (a string)", f"{loc}.material")
    if mat not in materials:
        raise SceneError(f"unknown material '{mat}' (defined: {_name_list(materials) or 'none'})",
                         f"{loc}.material")
    out: dict[str, Any] = {"type": stype, "material": mat,
                           "to_world": _transform(shape.get("to_world"), f"{loc}.to_world"),
                           "flip_normals": _bool(shape.get("flip_normals", False),
                                                 f"{loc}.flip_normals")}
    if "name" in shape:
        out["name"] = str(shape["name"])
    if stype == "sphere":
        # An analytic sphere: centre and radius in local space (default the unit
        # sphere), then to_world, which must be a similarity (no shear, uniform scale).
        out["center"] = _vec3(shape.get("center", [0, 0, 0]), f"{loc}.center")
        out["radius"] = _coordinate(shape.get("radius", 1.0), f"{loc}.radius", lo=MIN_LENGTH)
        m = np.asarray(out["to_world"])[:3, :3]
        mtm = m.T @ m
        s2 = mtm[0, 0]
        if not np.allclose(mtm, np.eye(3) * s2, rtol=1e-6, atol=1e-9 * max(s2, 1e-300)):
            raise SceneError("a sphere's to_world must be a similarity transform "
                             "(rotation, uniform scale, translation)", f"{loc}.to_world")
    asset = None
    where = f"{loc}.to_world"
    if stype == "mesh":
        asset = resolve_mesh(shape, out, loc, base_dir, root, store,
                             MeshLimits(MAX_COORDINATE, MAX_TRIANGLES, MAX_FILE_BYTES))
        where = f"{loc}.vertices" if "vertices" in shape else \
            f"{loc}.file" if "file" in shape else f"{loc}.mesh"
    em = shape.get("emitter")
    if em is not None:
        eloc = f"{loc}.emitter"
        if not isinstance(em, dict) or em.get("type") != "area":
            raise SceneError("a shape's emitter must be {'type': 'area', 'radiance': [r, g, b]}", eloc)
        _check_fields(em, eloc, "emitter.area")
        if "opacity" in materials[out["material"]]:
            # light sampling would see emission where the mask lets rays through
            raise SceneError(f"material '{out['material']}' has an opacity mask: an emitting "
                             "shape's material must be opaque", eloc)
        out["emitter"] = {"type": "area",
                          "radiance": _vec3(_require(em, "radiance", eloc), f"{eloc}.radiance",
                                            nonneg=True, limit=MAX_RADIANCE)}
    _check_world_geometry(out, loc, asset, where)
    return out


def _check_world_geometry(shape: dict, loc: str, asset=None, where: str | None = None) -> None:
    """A resolved shape in world space: its points within bounds, and if it
    emits, triangles with an area (see the module doc: a light without one
    crashes the renderer)."""
    m = np.asarray(shape["to_world"])
    where = where or f"{loc}.to_world"
    if shape["type"] == "sphere":
        centre = m[:3, :3] @ np.asarray(shape["center"]) + m[:3, 3]
        radius = shape["radius"] * float(np.linalg.norm(m[:3, 0]))  # a similarity
        _check_world_points(centre[None], f"{loc}.to_world", "the centre")
        if not MIN_LENGTH <= radius <= MAX_COORDINATE:
            raise SceneError(f"the radius is {radius:.3g} after to_world; from "
                             f"{MIN_LENGTH:g} to {MAX_COORDINATE:g}", f"{loc}.to_world")
        if "emitter" in shape and 4 * math.pi * radius * radius < MIN_EMITTER_AREA:
            raise SceneError(f"an emitting sphere needs an area of at least {MIN_EMITTER_AREA:g} "
                             f"(radius {radius:.3g} after to_world)", f"{loc}.radius")
        return
    vertices, faces = world_mesh(shape, asset)
    _check_world_points(vertices, where, "vertex {j}")
    if "emitter" not in shape:
        return  # degenerate triangles that emit nothing are merely never hit
    tri = vertices[faces]
    edges = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], tri[:, 2] - tri[:, 1]], axis=1)
    longest = np.max(np.linalg.norm(edges, axis=2), axis=1)
    double_area = np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)
    bad = (0.5 * double_area < MIN_EMITTER_AREA) | (double_area < COLLINEAR * longest * longest)
    if np.any(bad):
        j = int(np.argmax(bad))
        meshed = shape["type"] == "mesh"
        which = f"face {j}" if meshed else f"its triangle {j}"
        raise SceneError(f"an area light's triangles need an area: {which} is degenerate "
                         f"after to_world (area {0.5 * double_area[j]:.3g}, height "
                         f"{double_area[j] / max(longest[j], 1e-300):.3g} across a longest edge "
                         f"of {longest[j]:.3g}: collinear or coincident vertices); an emitting "
                         f"triangle needs an area of at least {MIN_EMITTER_AREA:g} and a height "
                         f"of at least {COLLINEAR:g} times its longest edge",
                         f"{loc}.faces[{j}]" if meshed and where.endswith(".vertices")
                         else where if meshed else f"{loc}.to_world")


def _resolve_emitter(i: int, em: Any) -> dict:
    loc = f"emitters[{i}]"
    if not isinstance(em, dict):
        raise SceneError("expected an object", loc)
    etype = _require(em, "type", loc)
    if etype != "point":
        raise SceneError(f"unknown emitter type '{etype}' (allowed: point; area emitters "
                         "are attached to shapes)", f"{loc}.type")
    _check_fields(em, loc, "emitter.point")
    return {"type": "point",
            "position": _vec3(_require(em, "position", loc), f"{loc}.position"),
            "intensity": _vec3(_require(em, "intensity", loc), f"{loc}.intensity", nonneg=True,
                               limit=MAX_RADIANCE)}


def _resolve_defaults(value: Any) -> dict:
    """Render defaults a scene file gave (an importer's integrator block):
    `max_depth`, the depth of a job that names none."""
    if not isinstance(value, dict):
        raise SceneError("expected an object such as {\"max_depth\": 5}", "defaults")
    unknown = sorted(str(k) for k in value if k != "max_depth")
    if unknown:
        raise SceneError(f"unknown field(s): {', '.join(unknown)} (allowed: max_depth)",
                         "defaults")
    out = {}
    if "max_depth" in value:
        depth = value["max_depth"]
        if isinstance(depth, bool) or not isinstance(depth, int) or not 0 <= depth <= 64:
            raise SceneError("must be an integer from 0 to 64 (surface bounces)",
                             "defaults.max_depth")
        out["max_depth"] = depth
    return out


class ResolvedDocument(dict):
    """A resolved document (a plain dict to every reader) that carries the
    assets it names: `assets` is a mapping digest -> blob, or an asset
    source (a callable). `build_scene(doc)` reads meshes from it; what goes
    over a wire is the canonical text plus the assets, never this object."""

    assets: Any = None

    def __init__(self, doc: dict, assets: Any = None):
        super().__init__(doc)
        self.assets = assets


def document_assets(doc: dict) -> Any:
    """The assets a resolved document carries (see ResolvedDocument), or None."""
    return getattr(doc, "assets", None)


def scene_asset_digests(doc: dict) -> list[str]:
    """The digests a resolved document names (meshes, texture images), in
    order of first mention, without duplicates."""
    found: dict[str, None] = {}
    for shape in doc.get("shapes", ()):
        if isinstance(shape, dict) and isinstance(shape.get("mesh"), str):
            found.setdefault(shape["mesh"], None)
    textures = doc.get("textures")
    if isinstance(textures, dict):
        for tex in textures.values():
            if isinstance(tex, dict) and isinstance(tex.get("image"), str):
                found.setdefault(tex["image"], None)
    return list(found)


def resolve_document(source: str | Path | dict, *, allow_files: bool = True,
                     base_dir: Path | None = None, root: Path | None = None,
                     assets: Any = None) -> ResolvedDocument:
    """Validate a scene and return its resolved document, which carries the
    assets it names (`ResolvedDocument.assets`; `resolve_scene` returns them
    apart). Arguments as for `resolve_scene`."""
    doc, produced = resolve_scene(source, allow_files=allow_files, base_dir=base_dir, root=root,
                                  assets=assets)
    return ResolvedDocument(doc, produced)


def resolve_scene(source: str | Path | dict, *, allow_files: bool = True,
                  base_dir: Path | None = None, root: Path | None = None,
                  assets: Any = None) -> tuple[dict, dict[str, bytes]]:
    """Validate a scene: (its resolved document, the assets it names by digest).

    `source` is a built-in scene name (``"cornell-box"``), a path to a JSON
    scene file (only if `allow_files`), or an already-parsed dict. A dict's
    mesh `file`s are read from `base_dir` (and must lie inside `root`,
    default `base_dir`); without one, a dict must inline its meshes or name
    them by digest. `assets` is where a `mesh` digest is fetched from: a
    mapping digest -> blob or a callable (an asset source); a dict that
    carries assets (a ResolvedDocument) brings its own. Every mesh becomes
    an asset, named by digest in the document: the resolved document names
    exactly the returned assets, and resolving it again gives the same.
    """
    explicit = assets is not None
    if isinstance(source, dict):
        if _nesting(source) > MAX_NESTING:  # copying (or printing) it would exhaust the stack
            raise SceneError(f"the document nests lists and objects more than {MAX_NESTING} "
                             "levels deep")
        if assets is None:
            assets = document_assets(source)
        doc = copy.deepcopy(dict(source))
    elif isinstance(source, (str, Path)) and str(source) in builtin_scene_names():
        doc, base_dir = _load_builtin(str(source)), None
    elif isinstance(source, (str, Path)) and allow_files and Path(source).is_file():
        path = Path(source)
        if path.stat().st_size > MAX_FILE_BYTES:
            raise SceneError("scene file too large")
        try:
            doc = json.loads(path.read_text())
        except UnicodeDecodeError:
            raise SceneError(f"{path.name} is not a text file") from None
        except json.JSONDecodeError as exc:
            raise SceneError(f"invalid JSON in {path.name} at line {exc.lineno}, "
                             f"column {exc.colno}: {exc.msg}") from None
        except RecursionError:
            raise SceneError(f"{path.name} is nested too deeply") from None
        if _nesting(doc) > MAX_NESTING:
            raise SceneError(f"{path.name} nests lists and objects more than {MAX_NESTING} "
                             "levels deep")
        base_dir = path.parent
    else:
        raise SceneError(f"unknown scene '{source}' (built-in scenes: "
                         f"{_name_list(builtin_scene_names())}; or give a path to a scene file)")
    if not isinstance(doc, dict):
        raise SceneError("a scene document must be a JSON object")
    known = FIELDS["document"]
    unknown = sorted(str(k) for k in set(doc) - known)
    if unknown:
        raise SceneError(f"unknown top-level field(s): {', '.join(unknown)} "
                         f"(allowed: {', '.join(sorted(known))})")
    version = doc.get("format", SCENE_FORMAT)
    if version != SCENE_FORMAT:
        raise SceneError(f"unknown scene format {json.dumps(version)[:60]} (this renderer reads "
                         f"{SCENE_FORMAT}; or leave the field out)", "format")
    mats_in = doc.get("materials", {})
    if not isinstance(mats_in, dict):
        raise SceneError("expected an object mapping names to materials", "materials")
    tex_in = doc.get("textures", {})
    if not isinstance(tex_in, dict):
        raise SceneError("expected an object mapping names to textures", "textures")
    textures = {str(k): _resolve_texture(str(k), v) for k, v in tex_in.items()}
    materials = {str(k): _resolve_material(str(k), v, textures) for k, v in mats_in.items()}
    shapes_in = _require(doc, "shapes", "")
    if not isinstance(shapes_in, list):
        raise SceneError("expected a list of shapes", "shapes")
    emitters_in = doc.get("emitters", [])
    if not isinstance(emitters_in, list):
        raise SceneError("expected a list of emitters", "emitters")
    store = AssetStore(assets)
    resolved = {
        "format": SCENE_FORMAT,
        "name": str(doc.get("name", "")),
        "description": str(doc.get("description", "")),
        "camera": _resolve_camera(_require(doc, "camera", "")),
        "materials": materials,
        "shapes": [_resolve_shape(i, s, materials, base_dir, root, store)
                   for i, s in enumerate(shapes_in)],
        "emitters": [_resolve_emitter(i, e) for i, e in enumerate(emitters_in)],
    }
    if not resolved["shapes"]:
        raise SceneError("a scene needs at least one shape", "shapes")
    if "defaults" in doc:
        resolved["defaults"] = _resolve_defaults(doc["defaults"])
    if textures:  # absent when empty: older scenes keep their hash
        resolved["textures"] = textures
    named = scene_asset_digests(resolved)
    if explicit:
        # every asset the document names travels with it (a bitmap's image too,
        # which nothing above reads): a named asset the given source lacks is
        # refused here, before any render process could meet it
        for digest in named:
            store.fetch(digest, "textures" if digest not in store.produced else "")
    return resolved, {d: store.produced[d] for d in named if d in store.produced}


def canonical_json(doc: dict) -> str:
    """The canonical text of a resolved document (sorted keys, no spaces)."""
    return json.dumps(doc, sort_keys=True, separators=(",", ":"))


def scene_hash(doc: dict) -> str:
    """Content hash of a resolved document: the scene's identity on the farm."""
    return hashlib.sha256(canonical_json(doc).encode()).hexdigest()
