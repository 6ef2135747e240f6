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
from .kernels.camera import filter_params
from .kernels.bsdf import MAT_DIELECTRIC, MAT_DIFFUSE, MAT_GLOSSY, MAT_MIRROR
from .kernels.lights import LIGHT_MESH, LIGHT_POINT, LIGHT_SPHERE
from .kernels.opacity import MAT_CUTOFF, MAT_OPACITY
from .kernels.shading import TEX_BITMAP, TEX_CHECKER, TEX_COLUMNS
from .errors import SceneError
from .primitives import DISK_SEGMENTS, FIXED, world_mesh, world_mesh_data  # noqa: F401
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
    "mat_param",    # (M, 4) [ior (dielectric), signed alpha (glossy: < 0 Beckmann), opacity, its cutoff or 0]
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
    # Shading (kernels/shading.py). Triangles with per-vertex normals or UVs
    # have a row in attr_n / attr_uv; the others (-1) shade with the
    # geometric normal and the barycentric uv (b1, b2), as Mitsuba does.
    "tri_attr",     # (T,) int32 row in attr_n / attr_uv, or -1
    "attr_n",       # (A, 9) float64 world vertex normals n0 n1 n2 (all 0: none)
    "attr_uv",      # (A, 6) float64 vertex uvs u0 v0 u1 v1 u2 v2
    "mat_tex",      # (M, 3) int32 texture of the colour input, roughness, opacity; -1 constant
    "mat_twosided",  # (M,) int32 1: the back side shades as the front (Mitsuba's twosided)
    "mat_masked",   # (M,) int32 1: an opacity mask (kernels/opacity.py), read on hits only
    "tex_info",     # (X, 16) float64 one row per texture (TEX_* columns, kernels/shading.py)
    "tex_data",     # (N,) float32 every bitmap's texels, row-major, channels interleaved
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


# Every bitmap's texels together, float32: what a scene may hold (1 GiB).
MAX_SCENE_TEXELS = 256 * 1024 * 1024


def _texels(digest: str, assets, loc: str) -> np.ndarray:
    """The (H, W, C) float32 texels of the image asset `digest`; `assets` is
    an asset source (renderer/assets.py: a mapping or a callable, digests
    checked) or, in tests, a mapping straight to texel arrays."""
    held = assets.get(digest) if isinstance(assets, dict) else None
    if isinstance(held, np.ndarray):
        a = held
    else:
        from .assets import decode_asset, load_asset

        asset = decode_asset(load_asset(assets, digest, loc))
        if asset.kind != "texture":
            raise SceneError(f"the asset {digest[:12]} is a {asset.kind}, not a texture", loc)
        a = asset.texels
    a = np.asarray(a, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] < 1 or a.shape[1] < 1:
        raise SceneError(f"the image asset {digest[:12]}... is not an (H, W, 1|3|4) image", loc)
    return a


def _texture_arrays(doc: dict, assets) -> tuple[dict, np.ndarray, np.ndarray]:
    """(index by texture name, tex_info, tex_data) of a resolved document."""
    textures = doc.get("textures", {})
    index = {name: i for i, name in enumerate(textures)}
    info = np.zeros((len(textures), TEX_COLUMNS))
    chunks, offset = [], 0
    for i, (name, tex) in enumerate(textures.items()):
        row = info[i]
        row[6:8] = tex["uv_scale"]
        row[8:10] = tex["uv_offset"]
        if tex["type"] == "checkerboard":
            row[0] = TEX_CHECKER
            row[10:13] = tex["color0"]
            row[13:16] = tex["color1"]
            continue
        a = _texels(tex["image"], assets, f"textures.{name}.image")
        h, w, c = a.shape
        if offset + a.size > MAX_SCENE_TEXELS:
            raise SceneError(f"the scene's textures hold more than {MAX_SCENE_TEXELS} texel "
                             "values in all", f"textures.{name}")
        row[0] = TEX_BITMAP
        row[1:6] = offset, w, h, c, 1.0 if tex["filter"] == "bilinear" else 0.0
        chunks.append(a.reshape(-1))
        offset += a.size
    data = np.concatenate(chunks) if chunks else np.zeros(0, np.float32)
    return index, info, np.ascontiguousarray(data, dtype=np.float32)


def _face_attributes(shape: dict, mesh) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per-face vertex normals (F, 9) in world space and uvs (F, 6) of a
    shape's world mesh (primitives.world_mesh_data), or None where it has
    none. A rectangle has Mitsuba's uvs ((x + 1) / 2, (y + 1) / 2) of its
    local corners; the other fixed shapes the barycentric default."""
    f = mesh.faces
    normals = None if mesh.normals is None else mesh.normals[f].reshape(-1, 9)
    if mesh.uvs is not None:
        uvs = np.asarray(mesh.uvs, dtype=np.float64)[f].reshape(-1, 6)
    elif shape["type"] == "rectangle":
        v, _ = FIXED["rectangle"]
        uvs = (0.5 * (v[:, :2] + 1.0))[f].reshape(-1, 6)
    else:
        uvs = None
    return normals, uvs


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
    (scene_format.ResolvedDocument); texture images likewise (in tests, the
    mapping may hold (H, W, C) texel arrays instead of blobs)."""
    mesh_asset = _mesh_source(doc, load_asset)
    source = load_asset if load_asset is not None else document_assets(doc)
    mat_names = list(doc["materials"])
    mat_index = {name: i for i, name in enumerate(mat_names)}
    mats = [doc["materials"][n] for n in mat_names]
    mat_type = np.array([_MAT_IDS[m["type"]] for m in mats], dtype=np.int32)
    tex_index, tex_info, tex_data = _texture_arrays(doc, source)
    rgb_field = {"diffuse": "albedo", "mirror": "tint", "glossy": "specular"}
    mat_rgb = np.ones((len(mats), 3))
    mat_param = np.zeros((len(mats), 4))
    mat_param[:, MAT_OPACITY] = 1.0
    mat_tex = np.full((len(mats), 3), -1, np.int32)
    mat_twosided = np.zeros(len(mats), np.int32)
    mat_masked = np.zeros(len(mats), np.int32)
    for i, m in enumerate(mats):
        colour = m.get(rgb_field.get(m["type"], ""), [1.0, 1.0, 1.0])
        if isinstance(colour, dict):
            mat_tex[i, 0] = tex_index[colour["texture"]]
        else:
            mat_rgb[i] = colour
        mat_param[i, 0] = m.get("ior", 1.0)
        rough = m.get("roughness", 0.0)
        if isinstance(rough, dict):
            mat_tex[i, 1] = tex_index[rough["texture"]]
            rough = 1.0  # only its sign is read: the texture gives the magnitude
        mat_param[i, 1] = rough
        if m.get("distribution") == "beckmann":
            mat_param[i, 1] = -rough  # the signed roughness of kernels/ggx.py
        # the dielectric is two-sided already (its back is its inside)
        mat_twosided[i] = 1 if m.get("twosided") and m["type"] != "dielectric" else 0
        if "opacity" in m:  # resolved documents hold it only when it is not 1
            mat_masked[i] = 1
            if isinstance(m["opacity"], dict):
                mat_tex[i, 2] = tex_index[m["opacity"]["texture"]]
            else:
                mat_param[i, MAT_OPACITY] = m["opacity"]
            mat_param[i, MAT_CUTOFF] = m.get("opacity_cutoff", 0.0)

    tris, tri_mat, tri_light = [], [], []  # per shape: (F, 3, 3) corners, (F,) ids
    n_tris = 0
    attr_rows: list[np.ndarray] = []  # per shape: each triangle's attribute row or -1
    attr_n: list[np.ndarray] = []
    attr_uv: list[np.ndarray] = []
    n_attr = 0
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
        mesh = world_mesh_data(shape, mesh_asset(shape) if "mesh" in shape else None)
        wv, f = mesh.positions, mesh.faces
        first = n_tris
        tris.append(wv[f])
        tri_mat.append(np.full(len(f), material, np.int32))
        tri_light.append(np.full(len(f), light, np.int32))
        n_tris += len(f)
        normals, uvs = _face_attributes(shape, mesh)
        if normals is None and uvs is None:
            attr_rows.append(np.full(len(f), -1, np.int32))
        else:
            attr_rows.append(np.arange(n_attr, n_attr + len(f), dtype=np.int32))
            n_attr += len(f)
            attr_n.append(normals if normals is not None else np.zeros((len(f), 9)))
            if uvs is None:  # Mitsuba's default: the barycentrics (b1, b2)
                uvs = np.tile([0.0, 0.0, 1.0, 0.0, 0.0, 1.0], (len(f), 1))
            attr_uv.append(uvs)
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

    tri_p = np.concatenate(tris).astype(np.float64) if tris else np.zeros((0, 3, 3))
    tri_mat = np.concatenate(tri_mat) if tri_mat else np.zeros(0, np.int32)
    tri_light = np.concatenate(tri_light) if tri_light else np.zeros(0, np.int32)
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
        tri_attr=np.concatenate(attr_rows) if attr_rows else np.zeros(0, np.int32),
        attr_n=np.ascontiguousarray(np.concatenate(attr_n) if attr_n else np.zeros((0, 9))),
        attr_uv=np.ascontiguousarray(np.concatenate(attr_uv) if attr_uv else np.zeros((0, 6))),
        mat_tex=mat_tex, mat_twosided=mat_twosided, mat_masked=mat_masked, tex_info=tex_info,
        tex_data=tex_data,
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
    """The camera for the kernels (layout: kernels/camera.py, CAM_*): origin,
    right, up, forward (unit vectors), tan of the half field of view along x
    and y, the lens (radius, focus distance) and the filter.

    A film position (px, py) maps to the direction
    normalize(((2 px / W - 1) tx) right + ((1 - 2 py / H) ty) up + forward),
    row 0 at the top, exactly as in shared/scenes/cornell-box.md.

    With `to_world` (Mitsuba's sensor convention) forward is the matrix's
    local +z, up its +y and right its -x (Mitsuba's local +x points to the
    image's left); a mirroring matrix keeps its mirror, as in Mitsuba.
    """
    if "to_world" in camera:
        m = np.asarray(camera["to_world"], dtype=np.float64)
        origin = m[:3, 3].copy()
        # orthonormalised (the document allows 1e-3 of slack, as Mitsuba does)
        forward = m[:3, 2] / np.linalg.norm(m[:3, 2])
        up = m[:3, 1] - forward * (m[:3, 1] @ forward)
        up /= np.linalg.norm(up)
        left = m[:3, 0] - forward * (m[:3, 0] @ forward) - up * (m[:3, 0] @ up)
        right = -left / np.linalg.norm(left)
    else:
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
    elif axis == "y":
        tx, ty = t * width / height, t
    else:  # diagonal: t is the half diagonal's tangent (Mitsuba's parse_fov)
        d = math.hypot(width, height)
        tx, ty = t * width / d, t * height / d
    lens = [camera.get("aperture_radius", 0.0), camera.get("focus_distance", 1.0)]
    return np.concatenate([origin, right, up, forward, [tx, ty], lens,
                           filter_params(camera.get("filter", {"type": "box"}))])
