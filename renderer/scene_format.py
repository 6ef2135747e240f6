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

`resolve_document` turns any accepted input (a built-in name, a path, a dict)
into a *resolved document*: validated, defaults filled in, mesh files read and
inlined, every transform a 4x4 matrix. The resolved document is
self-contained, so its canonical JSON hash (`scene_hash`) identifies the
scene wherever it travels: the farm ships scenes to workers by that hash.

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

from . import assets as _assets
from .errors import SceneError
from .meshio import MESH_SUFFIXES, read_mesh
from .primitives import world_mesh

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

MATERIAL_TYPES = ("diffuse", "mirror", "dielectric", "glossy")
SHAPE_TYPES = ("rectangle", "disk", "cube", "sphere", "mesh")
EMITTER_TYPES = ("point",)
FOV_AXES = ("x", "y", "smaller", "larger")

MAX_IMAGE_SIDE = 8192
MAX_TRIANGLES = 5_000_000
MAX_FILE_BYTES = 256 * 1024 * 1024
SCENE_FORMAT = "rayfarm-scene/1"  # the one version this renderer reads
MAX_COORDINATE = 1e6  # |x|, |y|, |z| of any point (local and world), transform entry, radius
MAX_RADIANCE = 1e6  # area-light radiance and point-light intensity, per component
MIN_LENGTH = 1.0 / MAX_COORDINATE  # a sphere's radius, camera to target, a rotation axis
# pbrt-v4 renders a GGX lobe of alpha below 1e-3 as a perfect mirror ("effectively
# smooth"); here the `mirror` material is that, and alpha^2 underflows far below.
MIN_ROUGHNESS = 1e-3
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
    "document": {"format", "camera", "materials", "shapes", "emitters", "name", "description"},
    "camera": {"type", "origin", "target", "up", "fov", "fov_axis", "width", "height"},
    "material": {"type"},
    "material.diffuse": {"albedo"},
    "material.mirror": {"tint"},
    "material.dielectric": {"ior"},
    "material.glossy": {"specular", "roughness"},
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
# Small validators; each raises SceneError naming the location.

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


def _require(obj: dict, key: str, loc: str) -> Any:
    if key not in obj:
        raise SceneError(f"missing required field '{key}'", loc)
    return obj[key]


def _number(value: Any, loc: str, *, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneError(f"expected a finite number, got {json.dumps(value)[:60]}", loc)
    v = float(value)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise SceneError(f"must be {'>' if lo_open else '>='} {lo}, got {v}", loc)
    if hi is not None and v > hi:
        raise SceneError(f"must be <= {hi}, got {v}", loc)
    return v


def _vec3(value: Any, loc: str, *, nonneg: bool = False,
          limit: float = MAX_COORDINATE) -> list[float]:
    """Three finite numbers within +-`limit` (0..limit if `nonneg`)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value, value, value]  # a scalar means grey
    if not isinstance(value, list) or len(value) != 3:
        raise SceneError("expected a list of 3 numbers", loc)
    return [_number(v, f"{loc}[{i}]", lo=0.0 if nonneg else -limit, hi=limit)
            for i, v in enumerate(value)]


def _coordinate(value: Any, loc: str, **bounds) -> float:
    """A finite number within +-MAX_COORDINATE (and `bounds`, if tighter)."""
    return _number(value, loc, **{"lo": -MAX_COORDINATE, "hi": MAX_COORDINATE, **bounds})


def _bool(value: Any, loc: str) -> bool:
    if not isinstance(value, bool):
        raise SceneError(f"expected true or false, got {json.dumps(value)[:60]}", loc)
    return value


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


def _name_list(allowed) -> str:
    return ", ".join(allowed)


# ----------------------------------------------------------------------------

def _resolve_camera(cam: Any) -> dict:
    loc = "camera"
    if not isinstance(cam, dict):
        raise SceneError("expected an object", loc)
    ctype = cam.get("type", "perspective")
    _check_fields(cam, loc, "camera")
    if ctype != "perspective":
        raise SceneError(f"unknown camera type '{ctype}' (allowed: perspective)", f"{loc}.type")
    out = {
        "type": "perspective",
        "origin": _vec3(_require(cam, "origin", loc), f"{loc}.origin"),
        "target": _vec3(_require(cam, "target", loc), f"{loc}.target"),
        "up": _vec3(cam.get("up", [0, 1, 0]), f"{loc}.up"),
        "fov": _number(_require(cam, "fov", loc), f"{loc}.fov", lo=MIN_FOV, hi=179.0),
        "fov_axis": cam.get("fov_axis", "x"),
        "width": cam.get("width", 256),
        "height": cam.get("height", 256),
    }
    if out["fov_axis"] not in FOV_AXES:
        raise SceneError(f"unknown fov_axis '{out['fov_axis']}' (allowed: {_name_list(FOV_AXES)})",
                         f"{loc}.fov_axis")
    for key in ("width", "height"):
        v = out[key]
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_IMAGE_SIDE:
            raise SceneError(f"must be an integer in [1, {MAX_IMAGE_SIDE}]", f"{loc}.{key}")
    forward = np.subtract(out["target"], out["origin"])
    if not np.linalg.norm(forward) >= MIN_LENGTH:
        raise SceneError(f"target must lie at least {MIN_LENGTH:g} from origin",
                         f"{loc}.target")
    if np.linalg.norm(np.cross(forward, out["up"])) < 1e-9 * np.linalg.norm(forward):
        raise SceneError("up is parallel to the viewing direction", f"{loc}.up")
    return out


def _resolve_material(name: str, mat: Any) -> dict:
    loc = f"materials.{name}"
    if not isinstance(mat, dict):
        raise SceneError("expected an object", loc)
    mtype = _require(mat, "type", loc)
    if isinstance(mtype, str) and mtype in MATERIAL_TYPES:
        _check_fields(mat, loc, "material", f"material.{mtype}")
    if mtype == "diffuse":
        albedo = _vec3(mat.get("albedo", [0.5, 0.5, 0.5]), f"{loc}.albedo", nonneg=True)
        if max(albedo) > 1.0:
            raise SceneError("albedo components must be <= 1 (energy conservation)", f"{loc}.albedo")
        return {"type": "diffuse", "albedo": albedo}
    if mtype == "mirror":
        tint = _vec3(mat.get("tint", [1.0, 1.0, 1.0]), f"{loc}.tint", nonneg=True)
        if max(tint) > 1.0:
            raise SceneError("tint components must be <= 1", f"{loc}.tint")
        return {"type": "mirror", "tint": tint}
    if mtype == "dielectric":
        ior = _number(mat.get("ior", 1.5), f"{loc}.ior", lo=1.0, hi=4.0)
        return {"type": "dielectric", "ior": ior}
    if mtype == "glossy":
        specular = _vec3(mat.get("specular", [1.0, 1.0, 1.0]), f"{loc}.specular", nonneg=True)
        if max(specular) > 1.0:
            raise SceneError("specular components must be <= 1", f"{loc}.specular")
        roughness = _number(mat.get("roughness", 0.1), f"{loc}.roughness", lo=MIN_ROUGHNESS,
                            hi=1.0)
        return {"type": "glossy", "specular": specular, "roughness": roughness}
    raise SceneError(f"unknown material type '{mtype}' (allowed: {_name_list(MATERIAL_TYPES)})",
                     f"{loc}.type")


class _Assets:
    """The assets a resolution produces and reads: `produced` (digest ->
    blob) becomes the resolved scene's assets; `source` is where a `mesh`
    digest that was not produced here is fetched from."""

    def __init__(self, source):
        self.source = source
        self.produced: dict[str, bytes] = {}
        self.decoded: dict[str, _assets.Asset] = {}

    def add(self, blob: bytes) -> str:
        digest = _assets.asset_digest(blob)
        self.produced.setdefault(digest, blob)
        return digest

    def fetch(self, digest: str, where: str) -> bytes:
        if digest in self.produced:
            return self.produced[digest]
        if isinstance(self.source, _Assets):
            blob = self.source.fetch(digest, where)
        else:
            blob = _assets.load_asset(self.source, digest, where)
        self.produced[digest] = blob
        return blob


def _mesh_arrays(shape: dict, loc: str, base_dir: Path | None, root: Path | None,
                 store: _Assets) -> tuple[tuple, str]:
    """(positions, faces, normals, uvs) of a mesh shape's one source (`mesh`,
    `file`, or inline `vertices`/`faces`) and the location to name in errors."""
    given = [k for k in ("mesh", "file", "vertices") if k in shape]
    if len(given) != 1:
        raise SceneError("a mesh needs exactly one of 'mesh' (an asset digest), 'file' or "
                         f"'vertices' + 'faces' (got {', '.join(given) or 'none'})", loc)
    if "shape_index" in shape and "file" not in shape:
        raise SceneError("shape_index goes with a .serialized 'file'", f"{loc}.shape_index")
    for key in ("faces", "normals", "uvs"):
        if key in shape and "vertices" not in shape:
            raise SceneError(f"'{key}' goes with inline 'vertices'", f"{loc}.{key}")
    if "mesh" in shape:
        where = f"{loc}.mesh"
        blob = store.fetch(shape["mesh"], where)
        asset = store.decoded.get(shape["mesh"])
        if asset is None:
            try:
                asset = _assets.decode_asset(blob)
            except SceneError as exc:
                raise SceneError(f"asset {shape['mesh'][:12]}: {exc.message}", where) from None
            if asset.kind != "mesh":
                raise SceneError(f"asset {shape['mesh'][:12]} is a {asset.kind}, not a mesh",
                                 where)
            store.decoded[shape["mesh"]] = asset
        return (asset.positions, asset.faces, asset.normals, asset.uvs), where
    if "file" in shape:
        where = f"{loc}.file"
        if base_dir is None:
            raise SceneError("mesh files need a scene file on disk (or inline vertices/faces)",
                             where)
        name = shape["file"]
        if not isinstance(name, str) or not name:
            raise SceneError("expected a relative path (a string)", where)
        rel = name.replace("\\", "/")
        top = Path(root if root is not None else base_dir).resolve()
        fpath = (Path(base_dir) / rel).resolve()
        if rel.startswith("/") or (top not in fpath.parents):
            raise SceneError("mesh file must lie inside the scene's directory", where)
        if fpath.suffix.lower() not in MESH_SUFFIXES:
            raise SceneError(f"unsupported mesh file type '{fpath.suffix}' (allowed: "
                             f"{', '.join(MESH_SUFFIXES)})", where)
        index = shape.get("shape_index", 0)
        if isinstance(index, bool) or not isinstance(index, int) or index < 0:
            raise SceneError("expected an integer >= 0", f"{loc}.shape_index")
        if "shape_index" in shape and fpath.suffix.lower() != ".serialized":
            raise SceneError("shape_index goes with a .serialized file", f"{loc}.shape_index")
        label = str(fpath.relative_to(top)) if top in fpath.parents else fpath.name
        try:
            mesh = read_mesh(fpath, shape_index=index, label=label,
                             max_bytes=MAX_FILE_BYTES, max_triangles=MAX_TRIANGLES)
        except SceneError as exc:  # named as the file says (models/a.obj:12), from the shape
            raise SceneError(f"{exc.location}: {exc.message}" if exc.location else exc.message,
                             where) from None
        return (mesh.positions, mesh.faces, mesh.normals, mesh.uvs), where
    where = f"{loc}.vertices"
    vertices = shape["vertices"]
    faces = _require(shape, "faces", loc)
    try:
        v = np.asarray(vertices, dtype=np.float64)
        f_raw = np.asarray(faces, dtype=np.float64)
    except (ValueError, TypeError):
        raise SceneError("vertices must be [[x, y, z], ...] and faces [[i, j, k], ...]", loc) from None
    if f_raw.size and (not np.all(np.isfinite(f_raw)) or np.any(f_raw != np.round(f_raw))):
        raise SceneError("face indices must be integers", f"{loc}.faces")
    if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        raise SceneError("vertices must be a list of finite [x, y, z]", f"{loc}.vertices")
    extra = []
    for key, width in (("normals", 3), ("uvs", 2)):
        if key not in shape:
            extra.append(None)
            continue
        try:
            a = np.asarray(shape[key], dtype=np.float64)
        except (ValueError, TypeError):
            a = np.zeros(0)
        if a.shape != (len(v), width) or not np.all(np.isfinite(a)):
            raise SceneError(f"{key} must be one finite [{', '.join('xyz'[:width] if width == 3 else 'uv')}] "
                             f"per vertex ({len(v)})", f"{loc}.{key}")
        extra.append(a)
    return (v, f_raw.astype(np.int64).reshape(-1, 3) if f_raw.ndim == 2 and f_raw.shape[1] == 3
            else f_raw, *extra), where


def _smooth_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (zero where no face has an area)."""
    tri = positions[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = np.zeros_like(positions)
    for k in range(3):
        np.add.at(out, faces[:, k], cross)
    return out


def _resolve_mesh(shape: dict, out: dict, loc: str, base_dir: Path | None, root: Path | None,
                  store: _Assets) -> tuple:
    (v, f, normals, uvs), where = _mesh_arrays(shape, loc, base_dir, root, store)
    if not np.all(np.abs(v) <= MAX_COORDINATE):
        j = int(np.argmax(np.any(np.abs(v) > MAX_COORDINATE, axis=1)))
        raise SceneError(f"vertex {j} is {v[j].tolist()}; every coordinate must be within "
                         f"+-{MAX_COORDINATE:g}", where)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise SceneError("faces must be a non-empty list of [i, j, k] triangles",
                         f"{loc}.faces" if "vertices" in shape else where)
    if f.min() < 0 or f.max() >= len(v):
        raise SceneError(f"face index out of range (mesh has {len(v)} vertices)",
                         f"{loc}.faces" if "vertices" in shape else where)
    if len(f) > MAX_TRIANGLES:
        raise SceneError(f"too many triangles (limit {MAX_TRIANGLES})",
                         f"{loc}.faces" if "vertices" in shape else where)
    face_normals = _bool(shape.get("face_normals", False), f"{loc}.face_normals")
    if face_normals:
        normals = None  # shading uses each triangle's own normal
    if normals is not None:
        length = np.linalg.norm(normals, axis=1)
        if np.any(length == 0):  # e.g. "vn 0 0 0": the faces around the vertex decide
            normals = np.array(normals, dtype=np.float64)
            zero = length == 0
            normals[zero] = _smooth_normals(v, f)[zero]
            still = np.linalg.norm(normals, axis=1) == 0
            normals[still] = [0.0, 0.0, 1.0]  # only degenerate faces touch it: never hit
    blob = _assets.encode_mesh(v, f, normals, uvs)
    digest = store.add(blob)
    if "mesh" not in shape or digest != shape["mesh"]:
        store.decoded[digest] = _assets.decode_asset(blob)
    if "triangles" in shape and shape["triangles"] != len(f):
        raise SceneError(f"the mesh has {len(f)} triangles, not {shape['triangles']}",
                         f"{loc}.triangles")
    out["mesh"] = digest
    out["triangles"] = int(len(f))
    out["face_normals"] = face_normals
    return store.decoded[digest]


def _resolve_shape(i: int, shape: Any, materials: dict, base_dir: Path | None,
                   root: Path | None = None, store: _Assets | None = None) -> dict:
    loc = f"shapes[{i}]"
    store = store if store is not None else _Assets(None)
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
        asset = _resolve_mesh(shape, out, loc, base_dir, root, store)
        where = f"{loc}.vertices" if "vertices" in shape else \
            f"{loc}.file" if "file" in shape else f"{loc}.mesh"
    em = shape.get("emitter")
    if em is not None:
        eloc = f"{loc}.emitter"
        if not isinstance(em, dict) or em.get("type") != "area":
            raise SceneError("a shape's emitter must be {'type': 'area', 'radiance': [r, g, b]}", eloc)
        _check_fields(em, eloc, "emitter.area")
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
    materials = {str(k): _resolve_material(str(k), v) for k, v in mats_in.items()}
    shapes_in = _require(doc, "shapes", "")
    if not isinstance(shapes_in, list):
        raise SceneError("expected a list of shapes", "shapes")
    emitters_in = doc.get("emitters", [])
    if not isinstance(emitters_in, list):
        raise SceneError("expected a list of emitters", "emitters")
    store = _Assets(assets)
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
    named = scene_asset_digests(resolved)
    return resolved, {d: store.produced[d] for d in named if d in store.produced}


def canonical_json(doc: dict) -> str:
    """The canonical text of a resolved document (sorted keys, no spaces)."""
    return json.dumps(doc, sort_keys=True, separators=(",", ":"))


def scene_hash(doc: dict) -> str:
    """Content hash of a resolved document: the scene's identity on the farm."""
    return hashlib.sha256(canonical_json(doc).encode()).hexdigest()
