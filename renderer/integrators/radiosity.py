"""`radiosity`: finite element radiosity, solved once, displayed by tiles.

| option | type | default | meaning |
|---|---|---|---|
| `patch_size` | float | 0 (auto) | patch edge length in world units (triangles split into k x k, k = ceil(second-longest edge / patch_size); sphere zones about patch_size on a side); 0 = the scene's bounding-box diagonal / (20 sqrt 3): 0.1 on cornell-box (a box of side 2), 1.6 on veach-mis; a job cutting its scene into more than MAX_PATCHES = 250,000 patches, or patches x rays per patch above MAX_HITS = 2^28, is refused at submission (`check_scene`) |
| `form_factors` | str | `montecarlo` | how F is estimated, both with visibility: `montecarlo` (area-to-area ray casting) or `hemicube` (point-to-area from each patch's centre, rays through the pixels of a hemicube) |
| `ff_rays` | int | 512 | Monte Carlo form-factor rays per patch, and light samples per patch (both estimators) |
| `hemicube_res` | int | 32 | hemicube resolution: res x res top face, 4 res x res/2 sides, so 3 res^2 rays per patch |
| `solver` | str | `jacobi` | `jacobi` (one bounce per iteration: honours `depth`), `gauss-seidel`, `progressive` (Southwell shooting) |
| `tolerance` | float | 1e-4 | stop when an iteration changes B by at most tolerance x the largest reflected radiosity max(B - E) (progressive: when the largest unshot power is tolerance x the first) |
| `direct` | str | `sampled` | first bounce: `sampled` = light sampling with shadow rays from every patch (area and point lights), `formfactor` = emitting patches shine through F like any patch (the textbook; point lights still sampled) |
| `display` | str | `flat` | `flat`: each pixel shows B / pi of its patch; `smooth`: Gouraud, B interpolated over the triangle patch from its vertices, each the area-weighted mean of the patches around it that share its normal, albedo and emission (sphere zones stay flat) |
| `final_gather` | str | `off` | `on`: at the visible diffuse point, emission + light sampling + one cosine-sampled ray into the patch solution's reflected part |

The method. Diffuse surfaces and every emitter are meshed into patches
(flat triangles; analytic spheres into equal-area zones: z bands split in
longitude, so no tessellation error in the geometry). Each patch i has its
albedo rho_i (0 for an emitter whose material is not diffuse), its emission
E_i = pi Le (radiance -> radiosity; front side only, as area lights emit)
and a constant radiosity B_i (W/m^2), solving

    B = E + D + rho F (B - X)

F is estimated by ray casting (kernels/radiosity.py): Monte Carlo, the
fraction of cosine-distributed rays from uniform points of i that reach the
front of j (unbiased for the area-to-area F_ij; rows of a closed scene sum
to 1 exactly; reciprocity A_i F_ij = A_j F_ji holds only within the noise:
we do not symmetrise, which would break the row sums), or a hemicube at
the centre of i whose pixels are ray cast (deterministic, but a
point-to-area F from one point, with the hemicube's aliasing).
D is the radiosity reflected straight from the lights, rho x irradiance,
estimated at the same points by light sampling with shadow rays. With
`direct=sampled` (default) D covers every light and X = E, so light leaves
emitters only through D (far less noise than counting the few rays that hit
a small light); with `direct=formfactor` D covers point lights only and X =
0, so emitters shine through F. Point lights are no patches: their direct
light enters as D, unshot radiosity of the patches they light.

Depth. B(0) = E and each Jacobi iteration adds one bounce, so B(k) holds the
light of at most k reflections: a camera ray reaching a patch after b
specular bounces shows B(depth - b) / pi, which is what `path-mis` at the
same depth sees (exactly so on the furnace scenes). The solve keeps every
B(k) up to convergence or 64 (the largest depth), so one solution serves
every depth. `gauss-seidel` and `progressive` have no bounce structure: they
store B(0) = E and the converged B, i.e. they honour depth 0 and "all".

Display. Tile units trace camera rays; mirrors and glass (and glossy
surfaces, by sampling their lobe) are followed from the camera as in
`direct`, each using one bounce of the depth; the first patch reached shows
its radiance B / pi (front side; the back of a one-sided surface is black).
With `final_gather=on`, the visible diffuse point x shows instead its own
emission, direct light by light sampling (all lights, exactly as path-mis's
NEE) and rho_x times the reflected radiance (B - E) / pi of the patch a
cosine-sampled ray from x reaches (full B / pi if that ray went through
mirrors or glass first, since light sampling cannot see through them). That
removes the patches' blockiness from direct light and hides the mesh in
indirect light; gather rays that pass through mirrors or glass to a light
also bring caustics onto the visible surfaces (noisily, as path tracing
does). `display=smooth` (without final gather) interpolates B over each
triangle patch from welded vertex values (Gouraud): no visible patches, the
same bias. Samples per pixel average the film position (anti-aliasing)
and, with final gather, the gather; var.R/G/B come from them as in tile
methods.

Specular surfaces (mirror, glass, glossy) are no patches: form-factor rays
that hit them count as lost, shadow rays are blocked by them (as in the path
tracers). So the solution has no caustics and no specular interreflection
(a diffuse wall sees no light through a mirror), and light passing through
glass does not reach patches behind it. Emitters are always patches (with
albedo 0 if their material is not diffuse). They appear in the image only by
what the camera sees through them.

Bias. Constant radiosity per patch (meshing) and a fixed set of form-factor
rays (their noise is frozen into the solution, the same for every pixel):
radiosity is consistent only as patch_size -> 0 and ff_rays -> inf. The
measured bias on cornell-box is in docs/radiosity.md.

Farm plan: unit 0 (kind "solve", a 0x0 region, 0 samples) meshes, casts the
form-factor rays and solves; its film carries the solution as the artefact
`radiosity` (B(k), k = 0..min(K, depth), shape (k + 1, P, 3) float64).
Solutions are cached by (scene hash, solution options, seed, code version) in-process (LRU) and on disk
in the renderer's "radiosity" cache (renderer/cache.py: `<cache root>/radiosity`, the farm's
`<data_dir>/cache/radiosity`, size-capped, least recently used evicted, written atomically),
so a second job on the same scene reuses it. Then the
ordinary tile plan, every unit needing unit 0.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
from collections import OrderedDict, namedtuple
from dataclasses import replace
from pathlib import Path

import numpy as np
from numba import prange

from ..cache import DiskCache
from ..cache import disk_cache as cache_of
from ..errors import SpecError
from ..film import PartialFilm
from ..kernels import kernel, kernel_inline, kernel_parallel
from ..kernels.bsdf import (
    MAT_DIELECTRIC,
    MAT_DIFFUSE,
    MAT_GLOSSY,
    MAT_MIRROR,
    dielectric_sample,
    diffuse_sample,
    reflect,
)
from ..kernels.camera import camera_ray
from ..kernels.geometry import (
    STACK_SIZE,
    intersect_arrays,
    offset_origin,
    shadow_ray,
    surface_at_arrays,
)
from ..kernels.ggx import glossy_sample
from ..kernels.lights import sample_light
from ..kernels.radiosity import (
    DIRECT_ALL,
    DIRECT_POINT,
    PATCH_SPHERE,
    PATCH_TRI,
    form_factor_rays,
    patch_of,
    solve_gauss_seidel,
    solve_jacobi,
    solve_progressive,
)
from ..kernels.rng import sample_key
from ..plan import Unit
from ..plan import plan as tile_plan
from ..primitives import world_mesh
from ..registry import SAMPLERS, Method, Option
from ..samplers import DIMS_PER_BOUNCE, u1d, u2d
from ..scene import camera_array
from .tile import unit_blocks

__all__ = ["Patches", "mesh_patches", "solve", "form_factor_hits", "clear_cache"]

MAX_DEPTH = 64  # BOUNDS["depth"][1]: the Jacobi history never needs more
MAX_PATCHES = 250_000  # the mesh is built in Python: ~15 s at this size
MAX_HITS = 1 << 28  # patches x rays per patch: 1 GiB of int32 hits
SOLVERS = ("jacobi", "gauss-seidel", "progressive")

Patches = namedtuple("Patches", [
    "kind",       # (P,) int32 PATCH_TRI or PATCH_SPHERE
    "geo",        # (P, 9) triangle v0, e1, e2 | sphere centre, r, z_lo, z_hi, phi0, phi1, side
    "normal",     # (P, 3) front normal of triangle patches
    "area",       # (P,)
    "rho",        # (P, 3) albedo
    "emit",       # (P, 3) emitted radiosity pi Le
    "tri_start",  # (T,) int32 first entry of the triangle's cells (-1: no patches)
    "tri_k",      # (T,) int32 subdivisions per edge
    "cells",      # (C,) int32 patch of cell (i, j, down) at tri_start + (i k + j) 2 + down
    "sph_start",  # (S,) int32 first patch of the sphere (-1: no patches)
    "sph_nz",     # (S,) int32 z bands
    "sph_nphi",   # (S,) int32 longitude sectors
])


def _tri_k(p: np.ndarray, patch_size: float) -> int:
    edges = sorted(np.linalg.norm(p[[1, 2, 2]] - p[[0, 0, 1]], axis=1))
    return max(1, math.ceil(edges[1] / patch_size - 1e-6))


def _sphere_grid(r: float, patch_size: float) -> tuple[int, int]:
    return (max(1, math.ceil(2 * r / patch_size - 1e-6)),
            max(3, math.ceil(2 * math.pi * r / patch_size - 1e-6)))


def _meshed(sc, mat, light) -> bool:
    return sc.mat_type[mat] == MAT_DIFFUSE or light >= 0


def _patch_total(tri_p: np.ndarray, sph_r: np.ndarray, patch_size: float) -> float:
    """Patches `mesh_patches` cuts triangles `tri_p` (T, 3, 3), none of them
    degenerate, and spheres of radii `sph_r` into (`_tri_k`, `_sphere_grid`,
    vectorized); a float, since a tiny patch_size makes an astronomical count."""
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        edges = np.sort(np.linalg.norm(tri_p[:, [1, 2, 2]] - tri_p[:, [0, 0, 1]], axis=2), axis=1)
        k = np.maximum(1.0, np.ceil(edges[:, 1] / patch_size - 1e-6))
        nz = np.maximum(1.0, np.ceil(2 * sph_r / patch_size - 1e-6))
        nphi = np.maximum(3.0, np.ceil(2 * math.pi * sph_r / patch_size - 1e-6))
        return float(np.sum(k * k) + np.sum(nz * nphi))


def _as_count(total: float) -> int | float:
    return int(total) if math.isfinite(total) else total


def patch_count(scene, patch_size: float) -> int | float:
    """How many patches `mesh_patches` would make (cheap: no patch is built;
    inf if it overflows)."""
    sc = scene.arrays
    meshed_mat = sc.mat_type == MAT_DIFFUSE
    tri = (meshed_mat[sc.tri_mat] | (sc.tri_light >= 0)) & np.any(sc.tri_n != 0, axis=1)
    sph = meshed_mat[sc.sph_mat] | (sc.sph_light >= 0)
    return _as_count(_patch_total(sc.tri_p[tri], sc.sph[sph, 3], patch_size))


def mesh_patches(scene, patch_size: float) -> Patches:
    """Split the diffuse and emitting primitives of `scene` into patches."""
    sc = scene.arrays
    expected = patch_count(scene, patch_size)
    if expected > MAX_PATCHES:
        raise SpecError("options.patch_size", f"patch_size {patch_size} makes {expected} patches "
                                              f"(at most {MAX_PATCHES}): choose a larger one")
    kind, geo, normal, area, rho, emit = [], [], [], [], [], []
    n_tri, n_sph = len(sc.tri_mat), len(sc.sph)
    tri_start = np.full(n_tri, -1, np.int32)
    tri_k = np.ones(n_tri, np.int32)
    cells: list[int] = []

    def material(mat, light):
        albedo = sc.mat_rgb[mat] if sc.mat_type[mat] == MAT_DIFFUSE else np.zeros(3)
        le = sc.light_rgb[light] * math.pi if light >= 0 else np.zeros(3)
        return albedo, le

    for t in range(n_tri):
        mat, light = sc.tri_mat[t], sc.tri_light[t]
        if not _meshed(sc, mat, light) or not np.any(sc.tri_n[t]):
            continue  # a specular surface, or a degenerate triangle
        v0, v1, v2 = sc.tri_p[t]
        e1, e2 = v1 - v0, v2 - v0
        cross = np.cross(e1, e2)
        k = _tri_k(sc.tri_p[t], patch_size)
        albedo, le = material(mat, light)
        tri_start[t], tri_k[t] = len(cells), k
        table = np.full(2 * k * k, -1, np.int32)
        sub_area = 0.5 * np.linalg.norm(cross) / (k * k)
        for i in range(k):
            for j in range(k - i):
                for down in ((0, 1) if i + j < k - 1 else (0,)):
                    if down:
                        a, b, c = (i + 1, j), (i + 1, j + 1), (i, j + 1)
                    else:
                        a, b, c = (i, j), (i + 1, j), (i, j + 1)
                    p0 = v0 + (a[0] * e1 + a[1] * e2) / k
                    p1 = v0 + (b[0] * e1 + b[1] * e2) / k
                    p2 = v0 + (c[0] * e1 + c[1] * e2) / k
                    table[(i * k + j) * 2 + down] = len(kind)
                    kind.append(PATCH_TRI)
                    geo.append([*p0, *(p1 - p0), *(p2 - p0)])
                    normal.append(sc.tri_n[t])
                    area.append(sub_area)
                    rho.append(albedo)
                    emit.append(le)
        cells.extend(table)

    sph_start = np.full(n_sph, -1, np.int32)
    sph_nz = np.ones(n_sph, np.int32)
    sph_nphi = np.ones(n_sph, np.int32)
    for s in range(n_sph):
        mat, light = sc.sph_mat[s], sc.sph_light[s]
        if not _meshed(sc, mat, light):
            continue
        cx, cy, cz, r = sc.sph[s]
        nz, nphi = _sphere_grid(r, patch_size)
        side = -1.0 if sc.sph_flip[s] else 1.0
        albedo, le = material(mat, light)
        sph_start[s], sph_nz[s], sph_nphi[s] = len(kind), nz, nphi
        for iz in range(nz):
            z_hi, z_lo = 1 - 2 * iz / nz, 1 - 2 * (iz + 1) / nz
            for ip in range(nphi):
                phi0, phi1 = 2 * math.pi * ip / nphi, 2 * math.pi * (ip + 1) / nphi
                kind.append(PATCH_SPHERE)
                geo.append([cx, cy, cz, r, z_lo, z_hi, phi0, phi1, side])
                normal.append([0.0, 0.0, 0.0])
                area.append(r * r * (z_hi - z_lo) * (phi1 - phi0))
                rho.append(albedo)
                emit.append(le)

    def f64(a, shape):
        return np.ascontiguousarray(np.asarray(a, np.float64).reshape(shape))

    return Patches(kind=np.asarray(kind, np.int32), geo=f64(geo, (-1, 9)),
                   normal=f64(normal, (-1, 3)), area=f64(area, (-1,)), rho=f64(rho, (-1, 3)),
                   emit=f64(emit, (-1, 3)), tri_start=tri_start, tri_k=tri_k,
                   cells=np.asarray(cells, np.int32), sph_start=sph_start, sph_nz=sph_nz,
                   sph_nphi=sph_nphi)


def weld_vertices(patches: Patches, tolerance: float) -> tuple[np.ndarray, int]:
    """Shared vertices of the triangle patches, for smooth display: corners
    within `tolerance` of each other, on patches with the same normal (to
    1e-3), albedo and emission, are one vertex (a crease, a change of
    material or a light's edge stays sharp). Returns ((P, 3) vertex ids,
    -1 for sphere zones; the vertex count)."""
    tri = patches.kind == PATCH_TRI
    g = patches.geo[tri]
    corners = np.stack([g[:, 0:3], g[:, 0:3] + g[:, 3:6], g[:, 0:3] + g[:, 6:9]], axis=1)
    attrs = np.concatenate([np.round(patches.normal[tri] * 1e3), np.round(patches.rho[tri] * 1e6),
                            np.round(patches.emit[tri] * 1e6)], axis=1)
    keys = np.concatenate([np.round(corners / tolerance).reshape(-1, 3),
                           np.repeat(attrs, 3, axis=0)], axis=1)
    _, ids = np.unique(keys, axis=0, return_inverse=True)
    patch_vert = np.full((len(patches.kind), 3), -1, np.int32)
    patch_vert[tri] = ids.reshape(-1, 3)
    return patch_vert, int(ids.max()) + 1 if len(ids) else 0


def vertex_radiosity(history: np.ndarray, area: np.ndarray, patch_vert: np.ndarray,
                     n_vert: int) -> np.ndarray:
    """B at the welded vertices: the area-weighted mean of the patches
    around each, for every B(k): (K+1, V, 3)."""
    tri = patch_vert[:, 0] >= 0
    verts = patch_vert[tri].ravel()
    weight = np.repeat(area[tri], 3)
    total = np.bincount(verts, weights=weight, minlength=n_vert)
    out = np.empty((history.shape[0], n_vert, 3))
    for k in range(history.shape[0]):
        for c in range(3):
            b = np.repeat(history[k, tri, c], 3)
            out[k, :, c] = np.bincount(verts, weights=weight * b, minlength=n_vert)
    return np.ascontiguousarray(out / np.maximum(total, 1e-300)[None, :, None])


_MESHES: OrderedDict = OrderedDict()
_WELDS: OrderedDict = OrderedDict()


def _welded_vertices(scene, patch_size: float) -> tuple[np.ndarray, int]:
    key = (scene.hash, float(patch_size))
    if key not in _WELDS:
        _WELDS[key] = weld_vertices(_mesh(scene, patch_size), 1e-6 * patch_size)
        while len(_WELDS) > 4:
            _WELDS.popitem(last=False)
    return _WELDS[key]


def _mesh(scene, patch_size: float) -> Patches:
    key = (scene.hash, float(patch_size))
    if key not in _MESHES:
        _MESHES[key] = mesh_patches(scene, patch_size)
        while len(_MESHES) > 4:
            _MESHES.popitem(last=False)
    _MESHES.move_to_end(key)
    return _MESHES[key]


def hemicube_directions(res: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixel-centre directions of a hemicube of `res` x `res` pixels on
    the top face (and res x res/2 on each side), in the local frame (z along
    the normal), with their delta form factors normalised to sum to 1:
    top dA / (pi (x^2 + y^2 + 1)^2), side z dA / (pi (y^2 + z^2 + 1)^2)."""
    if res < 2 or res % 2:
        raise ValueError(f"hemicube_res must be an even integer >= 2, got {res}")
    h = 2.0 / res
    c = -1.0 + (np.arange(res) + 0.5) * h
    z = (np.arange(res // 2) + 0.5) * h
    x, y = np.meshgrid(c, c, indexing="ij")
    top = np.stack([x.ravel(), y.ravel(), np.ones(res * res)], axis=1)
    w_top = h * h / (np.pi * (x.ravel() ** 2 + y.ravel() ** 2 + 1) ** 2)
    u, v = np.meshgrid(c, z, indexing="ij")
    u, v = u.ravel(), v.ravel()
    one = np.ones_like(u)
    sides = [np.stack([one, u, v], 1), np.stack([-one, u, v], 1), np.stack([u, one, v], 1),
             np.stack([u, -one, v], 1)]
    w_side = v * h * h / (np.pi * (u ** 2 + v ** 2 + 1) ** 2)
    dirs = np.concatenate([top, *sides])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    weight = np.concatenate([w_top] + [w_side] * 4)
    return np.ascontiguousarray(dirs), weight / weight.sum()


def form_factor_hits(scene, patches: Patches, options: dict, seed: int):
    """Cast every patch's form-factor rays: (hits (P, n) int32, weight (n,),
    irradiance from the lights (P, 3), rays traced), with
    F_ij = sum of weight[s] over the rays s of i with hits[i, s] == j."""
    p = len(patches.kind)
    n_light = int(options["ff_rays"])
    if options["form_factors"] == "hemicube":
        hemicube, weight = hemicube_directions(int(options["hemicube_res"]))
    else:
        hemicube = np.zeros((0, 3))
        weight = np.full(n_light, 1.0 / n_light)
    hits = np.empty((p, len(weight)), np.int32)
    irradiance = np.zeros((p, 3))
    rays = np.zeros(p, np.int64)
    stacks = np.empty((p, STACK_SIZE), np.int64)
    mode = DIRECT_ALL if options["direct"] == "sampled" else DIRECT_POINT
    form_factor_rays(scene.arrays, patches.kind, patches.geo, patches.normal, patches.tri_start,
                     patches.tri_k, patches.cells, patches.sph_start, patches.sph_nz,
                     patches.sph_nphi, seed, hemicube, n_light, mode, hits, irradiance, rays,
                     stacks)
    return hits, weight, irradiance, int(rays.sum())


def solve(scene, options: dict, seed: int) -> tuple[np.ndarray, dict]:
    """Mesh, cast the form-factor rays and solve: (B(k) history (K+1, P, 3),
    stats). Not cached (see `solution`)."""
    t0 = time.perf_counter()
    patches = _mesh(scene, float(options["patch_size"]) or auto_patch_size(scene))
    n_rays = (3 * int(options["hemicube_res"]) ** 2 if options["form_factors"] == "hemicube"
              else int(options["ff_rays"]))
    if len(patches.kind) * n_rays > MAX_HITS:
        raise SpecError("options", f"{len(patches.kind)} patches x {n_rays} rays per patch "
                                   f"exceeds {MAX_HITS} stored hits: fewer rays or larger patches")
    t1 = time.perf_counter()
    hits, weight, irradiance, rays = form_factor_hits(scene, patches, options, seed)
    t2 = time.perf_counter()
    emit, rho = patches.emit, patches.rho
    source = np.ascontiguousarray(emit + rho * irradiance)  # E + D
    offset = emit if options["direct"] == "sampled" else np.zeros_like(emit)
    tol = float(options["tolerance"])
    if options["solver"] == "jacobi":
        history = np.empty((MAX_DEPTH + 1, len(emit), 3))
        k = solve_jacobi(hits, weight, rho, emit, source, offset, tol, history)
        history = history[:k + 1].copy()
        iterations = k
    elif options["solver"] == "gauss-seidel":
        b = emit.copy()
        iterations = solve_gauss_seidel(hits, weight, rho, source, offset, tol, 100000, b)
        history = np.stack([emit, b])
    else:
        y = source - offset
        unshot = y.copy()
        # the hit lists transposed: who reaches j, with which ray weight
        src = np.repeat(np.arange(len(emit), dtype=np.int32), hits.shape[1])
        ray_weight = np.tile(weight, len(emit))
        dst = hits.ravel()
        order = np.argsort(dst, kind="stable")
        order = order[dst[order] >= 0]
        col_start = np.searchsorted(dst[order], np.arange(len(emit) + 1)).astype(np.int64)
        iterations = solve_progressive(col_start, np.ascontiguousarray(src[order]),
                                       np.ascontiguousarray(ray_weight[order]), rho, patches.area,
                                       tol, 1000 * len(emit) + 1000, y, unshot)
        history = np.stack([emit, y + offset])
    t3 = time.perf_counter()
    return history, {"patches": len(emit), "rays": rays, "iterations": int(iterations),
                     "mesh_seconds": t1 - t0, "form_factor_seconds": t2 - t1,
                     "solve_seconds": t3 - t2}


# ---------------------------------------------------------------- the cache

SOLUTION_OPTIONS = ("patch_size", "form_factors", "ff_rays", "hemicube_res", "solver", "tolerance",
                    "direct")
_SOLUTIONS: OrderedDict = OrderedDict()
LRU_CAPACITY = 4


def _code_version() -> str:
    """A digest of the sources a solution depends on (kernels, meshing)."""
    root = Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for src in sorted([*root.glob("kernels/*.py"), Path(__file__).resolve(), root / "scene.py",
                       root / "bvh.py"]):
        digest.update(src.read_bytes())
    return digest.hexdigest()[:16]


_VERSION = _code_version()


def disk_cache() -> DiskCache | None:
    """Where solutions are kept on disk (None: nowhere); see renderer/cache.py."""
    return cache_of("radiosity")


def solution_key(scene, options: dict, seed: int) -> str:
    what = {"scene": scene.hash, "seed": seed, "code": _VERSION,
            **{k: options[k] for k in SOLUTION_OPTIONS}}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()


def clear_cache() -> None:
    """Forget the in-process solutions (the disk cache stays)."""
    _SOLUTIONS.clear()


def solution(scene, options: dict, seed: int) -> tuple[np.ndarray, dict]:
    """The solution for (scene, options, seed): from the in-process LRU, the
    disk cache, or `solve` (then stored in both). stats["cached"] says which."""
    key = solution_key(scene, options, seed)
    if key in _SOLUTIONS:
        _SOLUTIONS.move_to_end(key)
        return _SOLUTIONS[key], {"cached": "memory", "rays": 0}
    disk = disk_cache()
    history, stats = None, None
    data = disk.get(key) if disk is not None else None
    if data is not None:
        try:
            history = np.load(io.BytesIO(data), allow_pickle=False)
            stats = {"cached": "disk", "rays": 0}
        except (OSError, ValueError):
            history = None
    if history is None:
        history, stats = solve(scene, options, seed)
        stats["cached"] = "no"
        if disk is not None:  # a full or read-only cache only costs the reuse
            buffer = io.BytesIO()
            np.save(buffer, history, allow_pickle=False)
            disk.put(key, buffer.getvalue())
    _SOLUTIONS[key] = history
    while len(_SOLUTIONS) > LRU_CAPACITY:
        _SOLUTIONS.popitem(last=False)
    return history, stats


# ---------------------------------------------------------------- display

@kernel_inline
def _patch_at(sc, pt, prim, hx, hy, hz):
    return patch_of(sc.tri_isect, pt.tri_start, pt.tri_k, pt.cells, sc.sph, pt.sph_start,
                    pt.sph_nz, pt.sph_nphi, prim, hx, hy, hz)


@kernel
def _patch_uv(geo, p, hx, hy, hz):
    """Barycentrics (u, v) of point h in triangle patch p (v0, e1, e2), clamped."""
    dx, dy, dz = hx - geo[p, 0], hy - geo[p, 1], hz - geo[p, 2]
    d11 = geo[p, 3] * geo[p, 3] + geo[p, 4] * geo[p, 4] + geo[p, 5] * geo[p, 5]
    d12 = geo[p, 3] * geo[p, 6] + geo[p, 4] * geo[p, 7] + geo[p, 5] * geo[p, 8]
    d22 = geo[p, 6] * geo[p, 6] + geo[p, 7] * geo[p, 7] + geo[p, 8] * geo[p, 8]
    d1 = dx * geo[p, 3] + dy * geo[p, 4] + dz * geo[p, 5]
    d2 = dx * geo[p, 6] + dy * geo[p, 7] + dz * geo[p, 8]
    den = d11 * d22 - d12 * d12
    u = min(max((d22 * d1 - d12 * d2) / den, 0.0), 1.0)
    v = min(max((d11 * d2 - d12 * d1) / den, 0.0), 1.0 - u)
    return u, v


@kernel_inline
def li_radiosity(sc, pt, hist, vert_b, patch_vert, stack, ox, oy, oz, dx, dy, dz, key, depth,
                 gather, smp, seed, pixel, index, spp):
    """Radiance arriving at o from -d through the patch solution: (r, g, b, rays)."""
    k_last = hist.shape[0] - 1
    br, bg, bb = 1.0, 1.0, 1.0
    lr, lg, lb = 0.0, 0.0, 0.0
    rays = 0
    nodes, info, prims, tri, sph = sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph
    n_lights = sc.light_type.shape[0]
    inv_pi = 1.0 / np.pi
    for bounce in range(depth + 1):
        t, prim = intersect_arrays(nodes, info, prims, tri, sph, stack, ox, oy, oz, dx, dy, dz,
                                   np.inf, False)
        rays += 1
        if prim < 0:
            break
        hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
        nx, ny, nz, mat, light = surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light, sph,
                                                   sc.sph_flip, sc.sph_mat, sc.sph_light,
                                                   prim, hx, hy, hz)
        cos_o = -(dx * nx + dy * ny + dz * nz)
        p = _patch_at(sc, pt, prim, hx, hy, hz)
        left = depth - bounce
        base = 2 + DIMS_PER_BOUNCE * bounce
        if p >= 0:
            if cos_o <= 0.0:
                break  # one-sided: the back of a patch is black
            if gather == 0 or left == 0:
                k = min(left, k_last)
                if vert_b.shape[1] > 0 and patch_vert[p, 0] >= 0:  # smooth: Gouraud
                    u, v = _patch_uv(pt.geo, p, hx, hy, hz)
                    w0 = (1.0 - u - v) * inv_pi
                    u, v = u * inv_pi, v * inv_pi
                    a, b, c = patch_vert[p, 0], patch_vert[p, 1], patch_vert[p, 2]
                    lr += br * (w0 * vert_b[k, a, 0] + u * vert_b[k, b, 0] + v * vert_b[k, c, 0])
                    lg += bg * (w0 * vert_b[k, a, 1] + u * vert_b[k, b, 1] + v * vert_b[k, c, 1])
                    lb += bb * (w0 * vert_b[k, a, 2] + u * vert_b[k, b, 2] + v * vert_b[k, c, 2])
                else:
                    lr += br * hist[k, p, 0] * inv_pi
                    lg += bg * hist[k, p, 1] * inv_pi
                    lb += bb * hist[k, p, 2] * inv_pi
                break
            # final gather at x: emission, light sampling, one ray into the solution
            lr += br * pt.emit[p, 0] * inv_pi
            lg += bg * pt.emit[p, 1] * inv_pi
            lb += bb * pt.emit[p, 2] * inv_pi
            ar, ag, ab = pt.rho[p, 0], pt.rho[p, 1], pt.rho[p, 2]
            if n_lights > 0:
                ua, ub = u2d(smp, key, seed, pixel, index, spp, base)
                wx, wy, wz, dist, pl, er, eg, eb, delta = sample_light(
                    sc, hx, hy, hz, u1d(smp, key, seed, pixel, index, spp, base + 4), ua, ub)
                cos_i = wx * nx + wy * ny + wz * nz
                if pl > 0.0 and cos_i > 0.0:
                    sx, sy, sz, tx, ty, tz, tmax = shadow_ray(hx, hy, hz, nx, ny, nz, wx, wy, wz,
                                                              dist)
                    rays += 1
                    if intersect_arrays(nodes, info, prims, tri, sph, stack, sx, sy, sz,
                                        tx, ty, tz, tmax, True)[1] < 0:
                        w = cos_i * inv_pi / pl
                        lr += br * ar * er * w
                        lg += bg * ag * eg * w
                        lb += bb * ab * eb * w
            ua, ub = u2d(smp, key, seed, pixel, index, spp, base + 2)
            gx, gy, gz, cos_g, pdf = diffuse_sample(nx, ny, nz, ua, ub)
            br, bg, bb = br * ar, bg * ag, bb * ab  # f cos / pdf = albedo
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
            dx, dy, dz = gx, gy, gz
            specular = False
            for g in range(bounce + 1, depth + 1):
                t, prim = intersect_arrays(nodes, info, prims, tri, sph, stack, ox, oy, oz,
                                           dx, dy, dz, np.inf, False)
                rays += 1
                if prim < 0:
                    break
                hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
                nx, ny, nz, mat, light = surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light,
                                                           sph, sc.sph_flip, sc.sph_mat,
                                                           sc.sph_light, prim, hx, hy, hz)
                cos_o = -(dx * nx + dy * ny + dz * nz)
                q = _patch_at(sc, pt, prim, hx, hy, hz)
                if q >= 0:
                    if cos_o > 0.0:
                        k = min(depth - g, k_last)
                        er, eg, eb = hist[k, q, 0], hist[k, q, 1], hist[k, q, 2]
                        if not specular:  # direct light was sampled at x
                            er -= pt.emit[q, 0]
                            eg -= pt.emit[q, 1]
                            eb -= pt.emit[q, 2]
                        lr += br * er * inv_pi
                        lg += bg * eg * inv_pi
                        lb += bb * eb * inv_pi
                    break
                if g == depth:
                    break
                mtype = sc.mat_type[mat]
                if mtype == MAT_MIRROR and cos_o > 0.0:
                    dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
                    br *= sc.mat_rgb[mat, 0]
                    bg *= sc.mat_rgb[mat, 1]
                    bb *= sc.mat_rgb[mat, 2]
                    ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
                elif mtype == MAT_DIELECTRIC:
                    dx, dy, dz, w, es, side = dielectric_sample(
                        dx, dy, dz, nx, ny, nz, sc.mat_param[mat, 0],
                        u1d(smp, key, seed, pixel, index, spp, 2 + DIMS_PER_BOUNCE * g + 5))
                    br, bg, bb = br * w, bg * w, bb * w
                    ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, side)
                else:
                    break  # glossy ends a gather ray (documented)
                specular = True
            break
        if left == 0:
            break
        mtype = sc.mat_type[mat]
        if mtype == MAT_MIRROR:
            if cos_o <= 0.0:
                break
            dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
            br *= sc.mat_rgb[mat, 0]
            bg *= sc.mat_rgb[mat, 1]
            bb *= sc.mat_rgb[mat, 2]
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
        elif mtype == MAT_DIELECTRIC:
            dx, dy, dz, w, es, side = dielectric_sample(
                dx, dy, dz, nx, ny, nz, sc.mat_param[mat, 0],
                u1d(smp, key, seed, pixel, index, spp, base + 5))
            br, bg, bb = br * w, bg * w, bb * w
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, side)
        elif mtype == MAT_GLOSSY:
            ua, ub = u2d(smp, key, seed, pixel, index, spp, base + 2)
            wx, wy, wz, sr, sg, sb, pdf = glossy_sample(
                nx, ny, nz, -dx, -dy, -dz, sc.mat_param[mat, 1], sc.mat_rgb[mat, 0],
                sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2], ua, ub)
            if pdf <= 0.0:
                break
            br, bg, bb = br * sr, bg * sg, bb * sb
            dx, dy, dz = wx, wy, wz
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
        else:
            break
    return lr, lg, lb, rays


@kernel_parallel
def _display_tile(sc, pt, hist, vert_b, patch_vert, cam, x0, y0, x1, y1, width, height, blocks,
                  seed, depth, smp, spp, gather, out_sum, out_sq, out_w, row_rays, stacks):
    """The tile loop of integrators/path.py over `li_radiosity`."""
    ox, oy, oz = cam[0], cam[1], cam[2]
    for row in prange(y1 - y0):
        stack = stacks[row]
        y = y0 + row
        rays = 0
        for x in range(x0, x1):
            pixel = y * width + x
            ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            n = 0
            for bi in range(blocks.shape[0]):
                sr, sg, sb, tr, tg, tb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                for s in range(blocks[bi, 0], blocks[bi, 1]):
                    key = sample_key(seed, pixel, s)
                    fu, fv = u2d(smp, key, seed, pixel, s, spp, 0)
                    dx, dy, dz = camera_ray(cam, width, height, x + fu, y + fv)
                    r, g, b, nr = li_radiosity(sc, pt, hist, vert_b, patch_vert, stack, ox, oy, oz,
                                               dx, dy, dz, key, depth, gather, smp, seed, pixel,
                                               s, spp)
                    rays += nr
                    sr += r
                    sg += g
                    sb += b
                    tr += r * r
                    tg += g * g
                    tb += b * b
                ar += sr
                ag += sg
                ab += sb
                qr += tr
                qg += tg
                qb += tb
                n += blocks[bi, 1] - blocks[bi, 0]
            c = x - x0
            out_sum[row, c, 0] = ar
            out_sum[row, c, 1] = ag
            out_sum[row, c, 2] = ab
            out_sq[row, c, 0] = qr
            out_sq[row, c, 1] = qg
            out_sq[row, c, 2] = qb
            out_w[row, c] = n
        row_rays[row] = rays


# ---------------------------------------------------------------- the method

def plan_radiosity(spec, progressive: bool = False, options: dict | None = None) -> list[Unit]:
    """Unit 0 solves; then the tile plan, every unit needing unit 0."""
    units = [Unit(0, 0, 0, 0, 0, 0, 0, stage=0, kind="solve")]
    for u in tile_plan(spec, progressive=progressive):
        units.append(replace(u, index=u.index + 1, stage=1, kind="tile", needs=(0,)))
    return units


def auto_patch_size(scene) -> float:
    """The default patch size: the bounding-box diagonal / (20 sqrt 3), so a
    scene as large as a cube of side 2 (cornell-box) gets 0.1."""
    bounds = scene.arrays.bvh_nodes[0]
    return _patch_size_of_bounds(bounds[:3], bounds[3:])


def _patch_size_of_bounds(lo: np.ndarray, hi: np.ndarray) -> float:
    return float(np.linalg.norm(hi - lo)) / (20.0 * math.sqrt(3.0))


def _document_geometry(doc: dict):
    """What `build_scene` would make of a resolved document, without building
    it (no BVH, no kernel): the world-space triangles and sphere radii that
    become patches, and the bounds of every primitive that can be hit."""
    diffuse = {name for name, m in doc["materials"].items() if m["type"] == "diffuse"}
    tris, tri_meshed, radii, sph_meshed, lo, hi = [], [], [], [], [], []
    for shape in doc["shapes"]:
        meshed = shape["material"] in diffuse or "emitter" in shape
        m = np.asarray(shape["to_world"], dtype=np.float64)
        if shape["type"] == "sphere":
            centre = m[:3, :3] @ np.asarray(shape["center"], dtype=np.float64) + m[:3, 3]
            radius = shape["radius"] * np.linalg.norm(m[:3, 0])
            radii.append(radius)
            sph_meshed.append(meshed)
            lo.append(centre - radius)
            hi.append(centre + radius)
            continue
        vertices, faces = world_mesh(shape)
        tri = vertices[faces]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        tri = tri[np.linalg.norm(cross, axis=1) > 0]  # build_scene's degenerate ones are no patches
        if len(tri):
            lo.append(tri.min(axis=(0, 1)))
            hi.append(tri.max(axis=(0, 1)))
        if meshed:
            tris.append(tri)
    tri_p = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
    sph_r = np.asarray(radii, dtype=np.float64)[np.asarray(sph_meshed, dtype=bool)]
    bounds = (np.min(lo, axis=0), np.max(hi, axis=0)) if lo else (np.zeros(3), np.zeros(3))
    return tri_p, sph_r, bounds


def check_scene(spec, doc: dict, options: dict) -> None:
    """Refuse at submission what the solve unit would refuse later, on the
    farm: more than MAX_PATCHES patches (the mesh is built in Python: ~15 s
    at that size) or more than MAX_HITS stored form-factor hits (1 GiB).
    Measured before this check: patch_size 1e-3 on cornell-box (58 million
    patches) was accepted and its solve failed with SpecError in every
    attempt; 5e-324 with OverflowError. The count is the exact one of
    `mesh_patches`, from the document's world-space triangles."""
    tri_p, sph_r, (lo, hi) = _document_geometry(doc)
    patch_size = float(options["patch_size"]) or _patch_size_of_bounds(lo, hi)
    total = _patch_total(tri_p, sph_r, patch_size) if patch_size > 0 else math.inf
    if total > MAX_PATCHES:
        count = f"{total:.3g}" if total >= 1e9 else str(_as_count(total))
        raise SpecError("options.patch_size",
                        f"patch_size {patch_size:g} cuts this scene into {count} patches (at "
                        f"most {MAX_PATCHES}): choose a larger patch_size")
    hemicube = options["form_factors"] == "hemicube"
    n_rays = 3 * int(options["hemicube_res"]) ** 2 if hemicube else int(options["ff_rays"])
    if total * n_rays > MAX_HITS:
        raise SpecError("options.hemicube_res" if hemicube else "options.ff_rays",
                        f"{int(total)} patches x {n_rays} rays per patch exceeds {MAX_HITS} "
                        "stored hits: fewer rays or larger patches")


def resolve_options(options: dict, scene) -> dict:
    """The checked options with the scene's automatic patch size resolved."""
    if float(options["patch_size"]) == 0.0:
        options = {**options, "patch_size": auto_patch_size(scene)}
    return options


def run_radiosity(scene, spec, unit, inputs, options) -> PartialFilm:
    options = resolve_options(options, scene)
    if unit.kind == "solve":
        history, stats = solution(scene, options, spec.seed)
        film = PartialFilm.zeros(0, 0, 0, 0)
        # the tiles read B(k) for k <= depth only: ship no more (the cache keeps all)
        film.artefact = {"radiosity": np.ascontiguousarray(history[:spec.depth + 1])}
        film.stats.update(stats)
        film.stats["samples"] = 0
        return film
    if unit.needs:
        history = inputs[unit.needs[0]].artefact["radiosity"]
    else:  # a tile from the plain tile plan: fetch (or solve) the solution here
        history = solution(scene, options, spec.seed)[0]
    history = np.ascontiguousarray(history)
    patches = _mesh(scene, options["patch_size"])
    if history.shape[1] != len(patches.kind):
        raise ValueError(f"radiosity solution has {history.shape[1]} patches, the mesh "
                         f"{len(patches.kind)}")
    w, h = unit.x1 - unit.x0, unit.y1 - unit.y0
    film = PartialFilm.zeros(unit.x0, unit.y0, w, h)
    row_rays = np.zeros(h, np.int64)
    stacks = np.empty((h, STACK_SIZE), np.int64)
    cam = camera_array(scene.camera, spec.width, spec.height)
    if options["display"] == "smooth":
        patch_vert, n_vert = _welded_vertices(scene, options["patch_size"])
        vert_b = vertex_radiosity(history, patches.area, patch_vert, n_vert)
    else:
        patch_vert, vert_b = np.zeros((0, 3), np.int32), np.zeros((history.shape[0], 0, 3))
    _display_tile(scene.arrays, patches, history, vert_b, patch_vert, cam, unit.x0, unit.y0,
                  unit.x1, unit.y1,
                  spec.width, spec.height,
                  unit_blocks(spec.spp, unit.sample_start, unit.sample_end),
                  spec.seed, spec.depth, SAMPLERS[spec.sampler].id, spec.spp,
                  1 if options["final_gather"] == "on" else 0,
                  film.sum, film.sum_sq, film.weight, row_rays, stacks)
    film.stats.update(samples=unit.samples, rays=int(row_rays.sum()))
    return film


METHODS = (Method(
    name="radiosity",
    description="Finite element radiosity: diffuse patches, Monte Carlo form factors with "
                "visibility, an iterative solve once per scene (cached), displayed by tiles "
                "(optionally with a final gather).",
    run=run_radiosity,
    options=(
        Option("patch_size", float, 0.0, "patch edge length in world units; 0 = auto: the "
               "scene's bounding-box diagonal / (20 sqrt 3), 0.1 for cornell-box",
               bounds=(0.0, None)),
        Option("form_factors", str, "montecarlo", "form factor estimator: Monte Carlo ray "
               "casting or a ray-cast hemicube, both with visibility", ("montecarlo", "hemicube")),
        Option("ff_rays", int, 512, "Monte Carlo form-factor rays and light samples per patch",
               bounds=(1, 1 << 16)),
        Option("hemicube_res", int, 32, "hemicube top-face resolution (3 res^2 rays per patch)",
               bounds=(2, 1024), check=lambda v: None if v % 2 == 0 else f"must be even, got {v}"),
        Option("solver", str, "jacobi", "jacobi (one bounce per iteration, honours depth), "
               "gauss-seidel or progressive (Southwell shooting)", SOLVERS),
        Option("tolerance", float, 1e-4, "relative change at which the solver stops",
               bounds=(1e-12, 1.0)),
        Option("direct", str, "sampled", "first bounce by light sampling from the patches "
               "(sampled) or through the form factors (formfactor)", ("sampled", "formfactor")),
        Option("display", str, "flat", "flat: B/pi of the patch; smooth: Gouraud "
               "interpolation of vertex radiosities (area-weighted means of the patches "
               "around each vertex)", ("flat", "smooth")),
        Option("final_gather", str, "off", "on: light sampling and one gather ray into the "
               "solution at the visible point", ("off", "on")),
    ),
    family="radiosity",
    plan=plan_radiosity,
    phases=("solve", "tile"),
    check_scene=check_scene,
),)
