"""What the mesh readers share: the MeshData they return, limits, and the
bulk text helpers (numbers of a block, tokens per line, polygon fans)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

MESH_SUFFIXES = {".obj": "obj", ".ply": "ply", ".serialized": "serialized"}
MAX_MESH_FILE_BYTES = 512 * 1024 * 1024
MAX_MESH_TRIANGLES = 5_000_000
MAX_HEADER_BYTES = 64 * 1024  # a PLY header, a .serialized shape's name


@dataclass
class MeshData:
    """One triangle mesh as read from a file (local space, 0-based faces)."""

    positions: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    # OBJ `usemtl` runs: (material name or None before the first, first face, face count)
    face_groups: list[tuple[str | None, int, int]] | None = None
    objects: list[tuple[str, int, int]] | None = None  # OBJ `o`/`g` runs, likewise
    mtllibs: list[str] = field(default_factory=list)  # OBJ `mtllib` names, in order
    face_normals: bool = False  # a .serialized file's FaceNormals flag
    notes: list[str] = field(default_factory=list)  # what was read other than as written

    @property
    def triangle_count(self) -> int:
        return len(self.faces)


def _floats(block: bytes, dtype=np.float64) -> np.ndarray | None:
    """All whitespace-separated numbers of `block`, or None if one does not parse."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            return np.fromstring(block, dtype=dtype, sep=" ")
        except (DeprecationWarning, ValueError):
            return None


def _token_starts(arr: np.ndarray) -> np.ndarray:
    """Offsets where a whitespace-separated token starts in the byte array."""
    space = (arr == 32) | (arr == 10) | (arr == 9) | (arr == 13)
    start = ~space
    start[1:] &= space[:-1]
    return np.flatnonzero(start)


def _per_line(positions: np.ndarray, line_ends: np.ndarray) -> np.ndarray:
    """How many of the sorted `positions` fall in each line (ends exclusive, sorted)."""
    upto = np.searchsorted(positions, line_ends)
    return np.diff(np.concatenate([[0], upto]))


def _fan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (as corner indices into the flat corner list) of polygons of
    `counts` corners, fanned (0, j, j + 1); and each triangle's polygon."""
    counts = counts.astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ntri = np.maximum(counts - 2, 0)
    poly = np.repeat(np.arange(len(counts)), ntri)
    first_tri = np.concatenate([[0], np.cumsum(ntri)[:-1]])
    j = np.arange(len(poly)) - first_tri[poly] + 1
    base = starts[poly]
    return np.stack([base, base + j, base + j + 1], axis=1), poly


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Smooth vertex normals as Mitsuba 3 computes them for a mesh file
    without any (unless face_normals): each face's unit normal weighted by
    its angle at the vertex (Thuermer and Wuethrich 1998), normalised; zero
    where no face around a vertex has an area."""
    p = np.asarray(positions, dtype=np.float64)[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(n, axis=1)
    valid = length > 0
    n = np.where(valid[:, None], n / np.where(valid, length, 1.0)[:, None], 0.0)
    out = np.zeros((len(positions), 3))
    for k in range(3):
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        angle = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
        for c in range(3):
            out[:, c] += np.bincount(faces[:, k], weights=n[:, c] * angle, minlength=len(out))
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(length > 0, out / np.where(length > 0, length, 1.0), 0.0)
