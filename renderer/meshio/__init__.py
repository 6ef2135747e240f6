"""Mesh files in full: Wavefront OBJ, PLY (ASCII and binary) and Mitsuba's
`.serialized`.

    mesh = read_mesh(Path("models/Mesh000.obj"), label="models/Mesh000.obj")
    mesh.positions (V, 3) float64, mesh.faces (F, 3) int64,
    mesh.normals (V, 3) float64 | None, mesh.uvs (V, 2) float64 | None

Every output vertex has one position, normal and UV: where an OBJ corner
pairs a position with another UV or normal than elsewhere, the vertex is
split. Polygons are fanned into triangles (0, j, j + 1). UVs are given as the
file holds them (Mitsuba's obj and ply loaders flip v by default; that
convention belongs to the importer). A file without normals gives
`normals=None` (Mitsuba 3 then computes smooth vertex normals unless
`face_normals` is set: again the importer's choice).

Speed: the text formats are parsed a block at a time with numpy (lines of
one kind joined, tokens counted and converted in bulk), so a 2M-triangle OBJ
takes seconds; a per-line Python path runs only to locate an error.
Bounds: the file's size, and every count a header announces is checked
against the bytes that remain before anything is allocated.

Errors are `SceneError`s whose location is ``label:line`` (`label` defaults
to the file's name).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SceneError
from .common import (MAX_HEADER_BYTES, MAX_MESH_FILE_BYTES, MAX_MESH_TRIANGLES, MESH_SUFFIXES,
                     MeshData, vertex_normals)
from .obj import _read_obj, read_mtl
from .ply import _read_ply
from .serialized import _read_serialized, write_serialized

__all__ = ["MeshData", "read_mesh", "read_mtl", "write_serialized", "vertex_normals", "MESH_SUFFIXES",
           "MAX_MESH_FILE_BYTES", "MAX_MESH_TRIANGLES", "MAX_HEADER_BYTES"]


def read_mesh(path: Path, *, fmt: str | None = None, shape_index: int = 0,
              label: str | None = None, max_bytes: int = MAX_MESH_FILE_BYTES,
              max_triangles: int = MAX_MESH_TRIANGLES) -> MeshData:
    """Read a mesh file; `fmt` is ``obj``, ``ply`` or ``serialized`` (default:
    from the suffix); `shape_index` picks a shape of a .serialized file."""
    path = Path(path)
    label = label or path.name
    if fmt is None:
        fmt = MESH_SUFFIXES.get(path.suffix.lower())
        if fmt is None:
            raise SceneError(f"unsupported mesh file type '{path.suffix}' (allowed: "
                             f"{', '.join(MESH_SUFFIXES)})", label)
    if fmt not in MESH_SUFFIXES.values():
        raise SceneError(f"unknown mesh format '{fmt}'", label)
    if not path.is_file():
        raise SceneError(f"mesh file not found: {label}", label)
    size = path.stat().st_size
    if size > max_bytes:
        raise SceneError(f"mesh file too large ({size} bytes; the limit is {max_bytes})", label)
    data = path.read_bytes()
    if fmt == "obj":
        mesh = _read_obj(data, label, max_triangles)
    elif fmt == "ply":
        mesh = _read_ply(data, label, max_triangles)
    else:
        mesh = _read_serialized(data, label, shape_index, max_triangles)
    _check_finite(mesh, label)
    return mesh


def _check_finite(mesh: MeshData, label: str) -> None:
    for name in ("positions", "normals", "uvs"):
        a = getattr(mesh, name)
        if a is not None and not np.all(np.isfinite(a)):
            j = int(np.argmax(~np.all(np.isfinite(a), axis=1)))
            raise SceneError(f"{name[:-1]} {j} is not finite: {a[j].tolist()}", label)
