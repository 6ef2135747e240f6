"""The triangles of a resolved shape, in local and in world space.

    vertices, faces = world_mesh(shape, assets)   # (V, 3) float64, (F, 3) int64
    mesh = world_mesh_data(shape, assets)         # and normals, uvs (or None)

Mitsuba's primitives (rectangle, disk, cube) are fixed meshes in local
space; a mesh shape carries its own. `world_mesh` applies `to_world` and
orients the faces the way `build_scene` does (a mirroring transform, or
`flip_normals`, reverses the winding). The scene format checks these
world-space triangles (coordinates, emitters' areas) and the radiosity
method counts its patches on them, before any scene is built.
Spheres are analytic: they have no triangles here.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["DISK_SEGMENTS", "MeshArrays", "local_mesh", "local_mesh_data", "world_mesh",
           "world_mesh_data", "apply_transform"]

# Mitsuba's primitives in local space.
RECT_V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64)
RECT_F = np.array([[0, 1, 2], [0, 2, 3]])


def _cube_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The cube [-1,1]^3 as 12 triangles wound counter-clockwise seen from outside."""
    verts, faces = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = (axis + 1) % 3, (axis + 2) % 3
            quad = []
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = [0.0, 0.0, 0.0]
                p[axis], p[u], p[v] = sign, a * sign, b
                quad.append(p)
            base = len(verts)
            verts.extend(quad)
            faces.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]])
    v = np.array(verts)
    f = np.array(faces)
    # Make every face's winding agree with its outward normal.
    for i, (a, b, c) in enumerate(f):
        n = np.cross(v[b] - v[a], v[c] - v[a])
        if np.dot(n, v[a] + v[b] + v[c]) < 0:
            f[i] = [a, c, b]
    return v, f


CUBE_V, CUBE_F = _cube_mesh()

# The disk: the unit disk in the local z = 0 plane, front normal +z (Mitsuba's),
# as a fan of DISK_SEGMENTS triangles: an inscribed regular polygon whose area
# is (N / 2 pi) sin(2 pi / N) = 1 - 1.0e-4 of the circle's for N = 256.
DISK_SEGMENTS = 256
_DISK_ANGLES = np.linspace(0.0, 2 * math.pi, DISK_SEGMENTS, endpoint=False)
DISK_V = np.concatenate([[[0.0, 0.0, 0.0]],
                         np.stack([np.cos(_DISK_ANGLES), np.sin(_DISK_ANGLES),
                                   np.zeros(DISK_SEGMENTS)], axis=1)])
DISK_F = np.array([[0, 1 + k, 1 + (k + 1) % DISK_SEGMENTS] for k in range(DISK_SEGMENTS)])

FIXED = {"rectangle": (RECT_V, RECT_F), "disk": (DISK_V, DISK_F), "cube": (CUBE_V, CUBE_F)}


def apply_transform(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points (N, 3) through the affine 4x4 matrix `m`."""
    return pts @ m[:3, :3].T + m[:3, 3]


def _mesh_asset(shape: dict, assets):
    """The decoded asset of a mesh shape named by digest; `assets` is the
    decoded Asset itself, a mapping digest -> blob or an asset source."""
    from .assets import Asset, decode_asset, load_asset

    if isinstance(assets, Asset):
        return assets
    return decode_asset(load_asset(assets, shape["mesh"], "mesh"))


def local_mesh(shape: dict, assets=None) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a resolved non-sphere shape in its local space."""
    mesh = local_mesh_data(shape, assets)
    return mesh.positions, mesh.faces


def local_mesh_data(shape: dict, assets=None) -> "MeshArrays":
    """Positions, faces, and the normals and UVs a mesh has (else None), in local space."""
    if shape["type"] in FIXED:
        v, f = FIXED[shape["type"]]
        return MeshArrays(v, f, None, None)
    if "mesh" in shape:
        a = _mesh_asset(shape, assets)
        return MeshArrays(np.asarray(a.positions, dtype=np.float64),
                          np.asarray(a.faces, dtype=np.int64),
                          None if a.normals is None else np.asarray(a.normals, np.float64),
                          None if a.uvs is None else np.asarray(a.uvs, np.float64))
    # documents resolved before meshes became assets inlined them
    return MeshArrays(np.asarray(shape["vertices"], dtype=np.float64).reshape(-1, 3),
                      np.asarray(shape["faces"], dtype=np.int64).reshape(-1, 3), None, None)


class MeshArrays(NamedTuple):
    positions: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    normals: np.ndarray | None  # (V, 3) float64, unit length in world space
    uvs: np.ndarray | None  # (V, 2) float64


def world_mesh_data(shape: dict, assets=None) -> MeshArrays:
    """A shape's triangles in world space: positions, faces wound so their
    front side is the emitting one, and the mesh's shading normals (through
    the inverse transpose, normalised, turned with the faces by
    `flip_normals`) and UVs where it has them. `assets`: where a mesh named
    by digest is read (the decoded Asset, a mapping or an asset source)."""
    m = np.asarray(shape["to_world"], dtype=np.float64)
    local = local_mesh_data(shape, assets)
    v, f, n = local.positions, local.faces, local.normals
    with np.errstate(over="ignore", invalid="ignore"):  # the caller checks finiteness
        wv = apply_transform(m, v)
    if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform flips the winding
        f = f[:, ::-1]
    if shape.get("flip_normals"):
        f = f[:, ::-1]
    if n is not None:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            n = n @ np.linalg.inv(m[:3, :3])  # rows: (M^-T n)^T = n^T M^-1
            length = np.linalg.norm(n, axis=1, keepdims=True)
            n = np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0)
        if shape.get("flip_normals"):
            n = -n
    return MeshArrays(wv, f, n, local.uvs)


def world_mesh(shape: dict, assets=None) -> tuple[np.ndarray, np.ndarray]:
    """(world vertices, faces wound so their front side is the emitting one)."""
    mesh = world_mesh_data(shape, assets)
    return mesh.positions, mesh.faces
