"""Meshes of the native format as assets: a mesh shape's one source (an
asset digest, a mesh file, or inline arrays) read, checked and encoded into
a canonical blob named by its digest (renderer.assets). Used by
renderer.scene_format, which resolves the rest of a shape."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from . import assets
from .errors import SceneError
from .meshio import MESH_SUFFIXES, read_mesh, vertex_normals

__all__ = ["AssetStore", "MeshLimits", "resolve_mesh"]


class MeshLimits(NamedTuple):
    coordinate: float  # |x|, |y|, |z| of a vertex
    triangles: int
    file_bytes: int


def _require(obj: dict, key: str, loc: str) -> Any:
    if key not in obj:
        raise SceneError(f"missing required field '{key}'", loc)
    return obj[key]


def _bool(value: Any, loc: str) -> bool:
    if not isinstance(value, bool):
        raise SceneError(f"expected true or false, got {str(value)[:60]}", loc)
    return value


class AssetStore:
    """The assets a resolution produces and reads: `produced` (digest ->
    blob) becomes the resolved scene's assets; `source` is where a `mesh`
    digest that was not produced here is fetched from."""

    def __init__(self, source):
        self.source = source
        self.produced: dict[str, bytes] = {}
        self.decoded: dict[str, assets.Asset] = {}

    def add(self, blob: bytes) -> str:
        digest = assets.asset_digest(blob)
        self.produced.setdefault(digest, blob)
        return digest

    def fetch(self, digest: str, where: str) -> bytes:
        if digest in self.produced:
            return self.produced[digest]
        if isinstance(self.source, AssetStore):
            blob = self.source.fetch(digest, where)
        else:
            blob = assets.load_asset(self.source, digest, where)
        self.produced[digest] = blob
        return blob


def _mesh_arrays(shape: dict, loc: str, base_dir: Path | None, root: Path | None,
                 store: AssetStore, limits: MeshLimits) -> tuple[tuple, str]:
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
                asset = assets.decode_asset(blob)
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
                             max_bytes=limits.file_bytes, max_triangles=limits.triangles)
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


def resolve_mesh(shape: dict, out: dict, loc: str, base_dir: Path | None, root: Path | None,
                 store: AssetStore, limits: MeshLimits):
    """Resolve a mesh shape's source into an asset: `out` gets `mesh` (its
    digest), `triangles` and `face_normals`; returns the decoded asset."""
    (v, f, normals, uvs), where = _mesh_arrays(shape, loc, base_dir, root, store, limits)
    if not np.all(np.abs(v) <= limits.coordinate):
        j = int(np.argmax(np.any(np.abs(v) > limits.coordinate, axis=1)))
        raise SceneError(f"vertex {j} is {v[j].tolist()}; every coordinate must be within "
                         f"+-{limits.coordinate:g}", where)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise SceneError("faces must be a non-empty list of [i, j, k] triangles",
                         f"{loc}.faces" if "vertices" in shape else where)
    if f.min() < 0 or f.max() >= len(v):
        raise SceneError(f"face index out of range (mesh has {len(v)} vertices)",
                         f"{loc}.faces" if "vertices" in shape else where)
    if len(f) > limits.triangles:
        raise SceneError(f"too many triangles (limit {limits.triangles})",
                         f"{loc}.faces" if "vertices" in shape else where)
    face_normals = _bool(shape.get("face_normals", False), f"{loc}.face_normals")
    if face_normals:
        normals = None  # shading uses each triangle's own normal
    if normals is not None:
        length = np.linalg.norm(normals, axis=1)
        if np.any(length == 0):  # e.g. "vn 0 0 0": the faces around the vertex decide, as Mitsuba would
            normals = np.array(normals, dtype=np.float64)
            zero = length == 0
            normals[zero] = vertex_normals(v, f)[zero]
            still = np.linalg.norm(normals, axis=1) == 0
            normals[still] = [0.0, 0.0, 1.0]  # only degenerate faces touch it: never hit
    blob = assets.encode_mesh(v, f, normals, uvs)
    digest = store.add(blob)
    if "mesh" not in shape or digest != shape["mesh"]:
        store.decoded[digest] = assets.decode_asset(blob)
    if "triangles" in shape and shape["triangles"] != len(f):
        raise SceneError(f"the mesh has {len(f)} triangles, not {shape['triangles']}",
                         f"{loc}.triangles")
    out["mesh"] = digest
    out["triangles"] = int(len(f))
    out["face_normals"] = face_normals
    return store.decoded[digest]
