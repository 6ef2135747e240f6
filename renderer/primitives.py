"""The triangles of a resolved shape, in local and in world space.

    vertices, faces = world_mesh(shape)   # (V, 3) float64, (F, 3) int64

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

import numpy as np

__all__ = ["DISK_SEGMENTS", "local_mesh", "world_mesh", "apply_transform"]

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


def local_mesh(shape: dict) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a resolved non-sphere shape in its local space."""
    if shape["type"] in FIXED:
        return FIXED[shape["type"]]
    return (np.asarray(shape["vertices"], dtype=np.float64).reshape(-1, 3),
            np.asarray(shape["faces"], dtype=np.int64).reshape(-1, 3))


def world_mesh(shape: dict) -> tuple[np.ndarray, np.ndarray]:
    """(world vertices, faces wound so their front side is the emitting one)."""
    m = np.asarray(shape["to_world"], dtype=np.float64)
    v, f = local_mesh(shape)
    with np.errstate(over="ignore", invalid="ignore"):  # the caller checks finiteness
        wv = apply_transform(m, v)
    if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform flips the winding
        f = f[:, ::-1]
    if shape.get("flip_normals"):
        f = f[:, ::-1]
    return wv, f
