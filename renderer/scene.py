"""A resolved scene document turned into structure-of-arrays data for the kernels.

`build_scene(doc)` flattens shapes into triangles and analytic spheres,
materials and lights into parallel arrays, and builds the BVH. Kernels take
the `SceneArrays` namedtuple; nothing in it is a Python object.

Primitive ids: 0..T-1 are triangles, T..T+S-1 are spheres (id - T).
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numpy as np

from .bvh import build_bvh, collapse_wide, wide_bounds
from .kernels.bsdf import MAT_DIELECTRIC, MAT_DIFFUSE, MAT_GLOSSY, MAT_MIRROR
from .kernels.lights import LIGHT_MESH, LIGHT_POINT, LIGHT_SPHERE
from .primitives import DISK_SEGMENTS, FIXED, world_mesh  # noqa: F401 (DISK_SEGMENTS: re-exported)
from .scene_format import document_assets, resolve_document, scene_hash

__all__ = ["Scene", "SceneArrays", "build_scene", "load_scene", "camera_array", "triangle_count",
           "MAT_DIFFUSE", "MAT_MIRROR", "MAT_DIELECTRIC", "MAT_GLOSSY", "LIGHT_MESH", "LIGHT_SPHERE",
           "LIGHT_POINT"]

_MAT_IDS = {"diffuse": MAT_DIFFUSE, "mirror": MAT_MIRROR, "dielectric": MAT_DIELECTRIC,
            "glossy": MAT_GLOSSY}

SceneArrays = namedtuple("SceneArrays", [
    "tri_p",        # (T, 3, 3) float64 vertices
    "tri_isect",    # (T, 9) v0, e1 = v1 - v0, e2 = v2 - v0: what ray tests read
    "tri_n",        # (T, 3) unit geometric normal (the emitting / front side)
    "tri_mat",      # (T,) int32 material index
    "tri_light",    # (T,) int32 light index or -1
    "sph",          # (S, 4) centre xyz, radius
    "sph_flip",     # (S,) int32: 1 if the front side faces inwards
    "sph_mat",      # (S,) int32
    "sph_light",    # (S,) int32 light index or -1
    "mat_type",     # (M,) int32 MAT_*
    "mat_rgb",      # (M, 3) albedo (diffuse), tint (mirror) or specular (glossy)
    "mat_param",    # (M, 4) [ior (dielectric), GGX alpha (glossy), 0, 0]
    "light_type",   # (L,) int32 LIGHT_*
    "light_rgb",    # (L, 3) radiance (area) or intensity (point)
    "light_pos",    # (L, 3) position (point lights)
    "light_start",  # (L,) int32 first entry in light_tris (mesh lights)
    "light_count",  # (L,) int32 number of triangles (mesh lights)
    "light_area",   # (L,) float64 total area (area lights)
    "light_sphere",  # (L,) int32 sphere index (sphere lights)
    "light_tris",   # (K,) int32 triangle ids of mesh lights, grouped per light
    "light_tri_cdf",  # (K,) float64 area CDF within each light's group, ending at 1
    "bvh_nodes",    # (N, 24) a 4-wide BVH's child boxes, lanes side by side (bvh.collapse_wide)
    "bvh_info",     # (N, 4) int32 its children: a node (>= 0) or a leaf -(first * 8 + count) - 1
    "bvh_prims",    # (P,) int32 primitive ids in leaf order
])


@dataclass
class Scene:
    """A built scene: the resolved document, its hash and the kernel arrays."""

    doc: dict
    hash: str
    arrays: SceneArrays

    @property
    def camera(self) -> dict:
        return self.doc["camera"]

    @property
    def triangle_count(self) -> int:
        return len(self.arrays.tri_mat)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounding box of everything in the scene: (lo xyz, hi xyz)."""
        return wide_bounds(self.arrays.bvh_nodes)


def _apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ m[:3, :3].T + m[:3, 3]


def _mesh_source(doc: dict, load_asset):
    """An asset lookup for build_scene: each digest fetched (and checked) and
    decoded once, however many shapes name it."""
    from .assets import decode_asset
    from .assets import load_asset as fetch

    source = load_asset if load_asset is not None else document_assets(doc)
    decoded: dict = {}

    def get(shape: dict):
        digest = shape["mesh"]
        if digest not in decoded:
            decoded[digest] = decode_asset(fetch(source, digest, "mesh"))
        return decoded[digest]
    return get


def build_scene(doc: dict, load_asset=None) -> Scene:
    """Flatten a resolved document into kernel arrays and build the BVH.
    Meshes named by digest are read through `load_asset` (an asset source:
    a callable digest -> blob, or a mapping), each checked against its
    digest; by default from the assets the document carries
    (scene_format.ResolvedDocument)."""
    mesh_asset = _mesh_source(doc, load_asset)
    mat_names = list(doc["materials"])
    mat_index = {name: i for i, name in enumerate(mat_names)}
    mats = [doc["materials"][n] for n in mat_names]
    mat_type = np.array([_MAT_IDS[m["type"]] for m in mats], dtype=np.int32)
    rgb_field = {"diffuse": "albedo", "mirror": "tint", "glossy": "specular"}
    mat_rgb = np.array([m.get(rgb_field.get(m["type"], ""), [1.0, 1.0, 1.0]) for m in mats],
                       dtype=np.float64).reshape(-1, 3)
    mat_param = np.zeros((len(mats), 4))
    for i, m in enumerate(mats):
        mat_param[i, 0] = m.get("ior", 1.0)
        mat_param[i, 1] = m.get("roughness", 0.0)

    tris, tri_mat, tri_light = [], [], []
    sph, sph_flip, sph_mat, sph_light = [], [], [], []
    light_type, light_rgb, light_pos, light_sphere = [], [], [], []
    light_groups: list[list[int]] = []  # triangle ids per mesh light

    for shape in doc["shapes"]:
        m = np.asarray(shape["to_world"], dtype=np.float64)
        material = mat_index[shape["material"]]
        light = -1
        if "emitter" in shape:
            light = len(light_type)
            light_rgb.append(shape["emitter"]["radiance"])
            light_pos.append([0.0, 0.0, 0.0])
        if shape["type"] == "sphere":
            centre = _apply(m, np.asarray([shape["center"]]))[0]
            radius = shape["radius"] * np.linalg.norm(m[:3, 0])  # a similarity: uniform scale
            if light >= 0:
                light_type.append(LIGHT_SPHERE)
                light_sphere.append(len(sph))
                light_groups.append([])
            sph.append([*centre, radius])
            sph_flip.append(1 if shape["flip_normals"] else 0)
            sph_mat.append(material)
            sph_light.append(light)
            continue
        wv, f = world_mesh(shape, mesh_asset(shape) if "mesh" in shape else None)
        first = len(tris)
        tris.extend(wv[f])
        tri_mat.extend([material] * len(f))
        tri_light.extend([light] * len(f))
        if light >= 0:
            light_type.append(LIGHT_MESH)
            light_sphere.append(-1)
            light_groups.append(list(range(first, first + len(f))))

    for em in doc["emitters"]:
        light_type.append(LIGHT_POINT)
        light_rgb.append(em["intensity"])
        light_pos.append(em["position"])
        light_sphere.append(-1)
        light_groups.append([])

    tri_p = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
    cross = np.cross(tri_p[:, 1] - tri_p[:, 0], tri_p[:, 2] - tri_p[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    keep = double_area > 0  # degenerate triangles can never be hit or sampled
    tri_n = np.where(keep[:, None], cross / np.where(keep, double_area, 1.0)[:, None], 0.0)
    tri_area = 0.5 * double_area

    nl = len(light_type)
    light_start = np.zeros(nl, np.int32)
    light_count = np.zeros(nl, np.int32)
    light_area = np.zeros(nl)
    light_tris, light_cdf = [], []
    sph_arr = np.asarray(sph, dtype=np.float64).reshape(-1, 4)
    for li, group in enumerate(light_groups):
        if light_type[li] == LIGHT_MESH:
            group = [t for t in group if keep[t]]
            areas = tri_area[group]
            light_start[li] = len(light_tris)
            light_count[li] = len(group)
            light_area[li] = areas.sum()
            light_tris.extend(group)
            cdf = np.cumsum(areas) / max(areas.sum(), 1e-300)
            if len(cdf):
                cdf[-1] = 1.0
            light_cdf.extend(cdf)
        elif light_type[li] == LIGHT_SPHERE:
            r = sph_arr[light_sphere[li], 3]
            light_area[li] = 4 * math.pi * r * r

    n_tri = len(tri_p)
    # BVH over primitive bounds.
    lo = np.zeros((n_tri + len(sph_arr), 3))
    hi = np.zeros_like(lo)
    if n_tri:
        lo[:n_tri] = tri_p.min(axis=1)
        hi[:n_tri] = tri_p.max(axis=1)
    if len(sph_arr):
        lo[n_tri:] = sph_arr[:, :3] - sph_arr[:, 3:4]
        hi[n_tri:] = sph_arr[:, :3] + sph_arr[:, 3:4]
    valid = np.concatenate([keep, np.ones(len(sph_arr), bool)])
    prim_ids = np.nonzero(valid)[0].astype(np.int32)
    bvh_min, bvh_max, bvh_info, bvh_prims = build_bvh(lo, hi, prim_ids)
    wide_boxes, wide_kids = collapse_wide(bvh_min, bvh_max, bvh_info)
    tri_isect = np.concatenate([tri_p[:, 0], tri_p[:, 1] - tri_p[:, 0], tri_p[:, 2] - tri_p[:, 0]],
                               axis=1).reshape(-1, 9)

    arrays = SceneArrays(
        tri_p=np.ascontiguousarray(tri_p), tri_isect=np.ascontiguousarray(tri_isect),
        tri_n=np.ascontiguousarray(tri_n),
        tri_mat=np.asarray(tri_mat, np.int32), tri_light=np.asarray(tri_light, np.int32),
        sph=sph_arr, sph_flip=np.asarray(sph_flip, np.int32), sph_mat=np.asarray(sph_mat, np.int32),
        sph_light=np.asarray(sph_light, np.int32),
        mat_type=mat_type, mat_rgb=mat_rgb, mat_param=mat_param,
        light_type=np.asarray(light_type, np.int32),
        light_rgb=np.asarray(light_rgb, np.float64).reshape(-1, 3),
        light_pos=np.asarray(light_pos, np.float64).reshape(-1, 3),
        light_start=light_start, light_count=light_count, light_area=light_area,
        light_sphere=np.asarray(light_sphere, np.int32),
        light_tris=np.asarray(light_tris, np.int32), light_tri_cdf=np.asarray(light_cdf, np.float64),
        bvh_nodes=wide_boxes, bvh_info=wide_kids, bvh_prims=bvh_prims,
    )
    return Scene(doc=doc, hash=scene_hash(doc), arrays=arrays)


def triangle_count(doc: dict) -> int:
    """Triangles a resolved document becomes (analytic spheres count none),
    without building it: ``triangle_count(resolve_document("cornell-box"))``."""
    fixed = {**{name: len(faces) for name, (_, faces) in FIXED.items()}, "sphere": 0}
    return sum((s["triangles"] if "triangles" in s else len(s["faces"])) if s["type"] == "mesh"
               else fixed[s["type"]] for s in doc["shapes"])


def load_scene(source) -> Scene:
    """Resolve (name, path or dict) and build a scene."""
    return build_scene(resolve_document(source))


def camera_array(camera: dict, width: int, height: int) -> np.ndarray:
    """The pinhole camera for the kernels: origin, right, up, forward (unit
    vectors), then tan of the half field of view along x and y.

    A film position (px, py) maps to the direction
    normalize(((2 px / W - 1) tx) right + ((1 - 2 py / H) ty) up + forward),
    row 0 at the top, exactly as in shared/scenes/cornell-box.md.
    """
    origin = np.asarray(camera["origin"], dtype=np.float64)
    forward = np.asarray(camera["target"], dtype=np.float64) - origin
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(camera["up"], dtype=np.float64))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    t = math.tan(math.radians(camera["fov"]) / 2)
    axis = camera["fov_axis"]
    if axis == "smaller":
        axis = "x" if width <= height else "y"
    elif axis == "larger":
        axis = "x" if width >= height else "y"
    if axis == "x":
        tx, ty = t, t * height / width
    else:
        tx, ty = t * width / height, t
    return np.concatenate([origin, right, up, forward, [tx, ty]])
