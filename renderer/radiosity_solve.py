"""Finite element radiosity's solution: the patch mesh, the form factors
(Monte Carlo rays or hemicubes), the solve (Jacobi, Gauss-Seidel or
progressive refinement) and its cache. The method that displays it (and the
account of the whole algorithm) is renderer/integrators/radiosity.py.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
from collections import OrderedDict, namedtuple
from pathlib import Path

import numpy as np

from .cache import DiskCache
from .cache import disk_cache as cache_of
from .errors import SpecError
from .kernels.bsdf import (
    MAT_DIFFUSE,
)
from .kernels.geometry import (
    STACK_SIZE,
)
from .kernels.radiosity import (
    DIRECT_ALL,
    DIRECT_POINT,
    PATCH_SPHERE,
    PATCH_TRI,
    form_factor_rays,
    solve_gauss_seidel,
    solve_jacobi,
    solve_progressive,
)

__all__ = ["Patches", "mesh_patches", "solve", "solution", "form_factor_hits", "clear_cache",
           "patch_count", "patch_total", "as_count", "mesh", "welded_vertices",
           "vertex_radiosity", "weld_vertices", "hemicube_directions", "disk_cache",
           "solution_key", "auto_patch_size", "patch_size_of_bounds", "MAX_DEPTH", "MAX_PATCHES", "MAX_HITS", "SOLVERS"]

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


def patch_total(tri_p: np.ndarray, sph_r: np.ndarray, patch_size: float) -> float:
    """Patches `mesh_patches` cuts triangles `tri_p` (T, 3, 3), none of them
    degenerate, and spheres of radii `sph_r` into (`_tri_k`, `_sphere_grid`,
    vectorized); a float, since a tiny patch_size makes an astronomical count."""
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        edges = np.sort(np.linalg.norm(tri_p[:, [1, 2, 2]] - tri_p[:, [0, 0, 1]], axis=2), axis=1)
        k = np.maximum(1.0, np.ceil(edges[:, 1] / patch_size - 1e-6))
        nz = np.maximum(1.0, np.ceil(2 * sph_r / patch_size - 1e-6))
        nphi = np.maximum(3.0, np.ceil(2 * math.pi * sph_r / patch_size - 1e-6))
        return float(np.sum(k * k) + np.sum(nz * nphi))


def as_count(total: float) -> int | float:
    return int(total) if math.isfinite(total) else total


def patch_count(scene, patch_size: float) -> int | float:
    """How many patches `mesh_patches` would make (cheap: no patch is built;
    inf if it overflows)."""
    sc = scene.arrays
    meshed_mat = sc.mat_type == MAT_DIFFUSE
    tri = (meshed_mat[sc.tri_mat] | (sc.tri_light >= 0)) & np.any(sc.tri_n != 0, axis=1)
    sph = meshed_mat[sc.sph_mat] | (sc.sph_light >= 0)
    return as_count(patch_total(sc.tri_p[tri], sc.sph[sph, 3], patch_size))


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


def welded_vertices(scene, patch_size: float) -> tuple[np.ndarray, int]:
    key = (scene.hash, float(patch_size))
    if key not in _WELDS:
        _WELDS[key] = weld_vertices(mesh(scene, patch_size), 1e-6 * patch_size)
        while len(_WELDS) > 4:
            _WELDS.popitem(last=False)
    return _WELDS[key]


def mesh(scene, patch_size: float) -> Patches:
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


def form_factor_hits(scene, patches: Patches, options: dict, seed: int, batches: int = 0):
    """Cast every patch's form-factor rays: (hits (P, n) int32, weight (n,),
    irradiance from the lights (P, 3), its part from each of `batches`
    jackknife batches of light samples (P, batches, 3), rays traced), with
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
    irr_batches = np.zeros((p, batches, 3))
    rays = np.zeros(p, np.int64)
    stacks = np.empty((p, STACK_SIZE), np.int64)
    mode = DIRECT_ALL if options["direct"] == "sampled" else DIRECT_POINT
    form_factor_rays(scene.arrays, patches.kind, patches.geo, patches.normal, patches.tri_start,
                     patches.tri_k, patches.cells, patches.sph_start, patches.sph_nz,
                     patches.sph_nphi, seed, hemicube, n_light, mode, hits, irradiance,
                     irr_batches, rays, stacks)
    return hits, weight, irradiance, irr_batches, int(rays.sum())


# Jackknife batches of the solution's random numbers (its variance: `solve`).
JACKKNIFE = 8
# The replicates' changes are J times the solution's size, and travel to every
# tile unit: beyond this many bytes they are not made (the var channels then
# leave out the solution's share, as before they existed; stats say so).
JACKKNIFE_BYTES = 256 << 20


def _solve_system(options: dict, hits, weight, emit, rho, source, offset, area) -> tuple[np.ndarray, int]:
    """B = source + rho F (B - offset) by the options' solver: (history, iterations)."""
    tol = float(options["tolerance"])
    if options["solver"] == "jacobi":
        history = np.empty((MAX_DEPTH + 1, len(emit), 3))
        k = solve_jacobi(hits, weight, rho, emit, source, offset, tol, history)
        return history[:k + 1].copy(), k
    if options["solver"] == "gauss-seidel":
        b = emit.copy()
        iterations = solve_gauss_seidel(hits, weight, rho, source, offset, tol, 100000, b)
        return np.stack([emit, b]), iterations
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
                                   np.ascontiguousarray(ray_weight[order]), rho, area,
                                   tol, 1000 * len(emit) + 1000, y, unshot)
    return np.stack([emit, y + offset]), iterations


def _jackknife(options: dict, hits, weight, emit, rho, irradiance, irr_batches, offset, area,
               history: np.ndarray) -> np.ndarray:
    """The delete-a-group jackknife replicates of the solution, as changes
    (J, K+1, P, 3): replicate b solves the same system without batch b of the
    random numbers (the Monte Carlo form-factor rays s with s % J == b, and
    the light samples likewise), the rest reweighted to stay unbiased. Their
    spread estimates the solution's variance over seeds (integrators/
    radiosity.py, "Variance"). A hemicube's rays are no random numbers: its
    replicates drop light samples only."""
    n_batches = irr_batches.shape[1]
    n_light = int(options["ff_rays"])
    out = np.empty((n_batches,) + history.shape)
    s = np.arange(len(weight))
    for b in range(n_batches):
        kept = n_light - len(range(b, n_light, n_batches))
        irr = (irradiance - irr_batches[:, b]) * (n_light / kept)
        if options["form_factors"] == "hemicube":
            w = weight
        else:
            w = np.where(s % n_batches == b, 0.0, 1.0 / np.count_nonzero(s % n_batches != b))
        source = np.ascontiguousarray(emit + rho * irr)
        rep, _ = _solve_system(options, hits, w, emit, rho, source, offset, area)
        last = len(rep) - 1
        for k in range(len(history)):  # a replicate may converge a step sooner or later
            out[b, k] = rep[min(k, last)] - history[k]
    return out


def solve(scene, options: dict, seed: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """Mesh, cast the form-factor rays and solve: (B(k) history (K+1, P, 3),
    its jackknife replicates' changes (J, K+1, P, 3), stats). Not cached (see
    `solution`)."""
    t0 = time.perf_counter()
    patches = mesh(scene, float(options["patch_size"]) or auto_patch_size(scene))
    n_rays = (3 * int(options["hemicube_res"]) ** 2 if options["form_factors"] == "hemicube"
              else int(options["ff_rays"]))
    if len(patches.kind) * n_rays > MAX_HITS:
        raise SpecError("options", f"{len(patches.kind)} patches x {n_rays} rays per patch "
                                   f"exceeds {MAX_HITS} stored hits: fewer rays or larger patches")
    t1 = time.perf_counter()
    batches = min(JACKKNIFE, int(options["ff_rays"]))
    batches = batches if batches >= 2 else 0  # one light sample: no replicate is possible
    hits, weight, irradiance, irr_batches, rays = form_factor_hits(scene, patches, options, seed,
                                                                   batches)
    t2 = time.perf_counter()
    emit, rho = patches.emit, patches.rho
    source = np.ascontiguousarray(emit + rho * irradiance)  # E + D
    offset = emit if options["direct"] == "sampled" else np.zeros_like(emit)
    history, iterations = _solve_system(options, hits, weight, emit, rho, source, offset,
                                        patches.area)
    t3 = time.perf_counter()
    if batches * history.nbytes <= JACKKNIFE_BYTES:
        deltas = _jackknife(options, hits, weight, emit, rho, irradiance, irr_batches, offset,
                            patches.area, history)
    else:
        deltas = np.zeros((0,) + history.shape)
    t4 = time.perf_counter()
    return history, deltas, {"patches": len(emit), "rays": rays, "iterations": int(iterations),
                             "mesh_seconds": t1 - t0, "form_factor_seconds": t2 - t1,
                             "solve_seconds": t3 - t2, "jackknife_seconds": t4 - t3,
                             "jackknife": len(deltas)}


# ---------------------------------------------------------------- the cache

SOLUTION_OPTIONS = ("patch_size", "form_factors", "ff_rays", "hemicube_res", "solver", "tolerance",
                    "direct")
_SOLUTIONS: OrderedDict = OrderedDict()
LRU_CAPACITY = 4


def _code_version() -> str:
    """A digest of the sources a solution depends on (kernels, meshing)."""
    root = Path(__file__).resolve().parent  # the renderer package
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


def solution(scene, options: dict, seed: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """The solution for (scene, options, seed) and its jackknife replicates'
    changes (`solve`): from the in-process LRU, the disk cache, or `solve`
    (then stored in both). stats["cached"] says which."""
    key = solution_key(scene, options, seed)
    if key in _SOLUTIONS:
        _SOLUTIONS.move_to_end(key)
        return (*_SOLUTIONS[key], {"cached": "memory", "rays": 0})
    disk = disk_cache()
    both, stats = None, None
    data = disk.get(key) if disk is not None else None
    if data is not None:
        try:
            stacked = np.load(io.BytesIO(data), allow_pickle=False)  # history, then replicates
            both, stats = (stacked[0], stacked[1:]), {"cached": "disk", "rays": 0}
        except (OSError, ValueError, IndexError):
            both = None
    if both is None:
        history, deltas, stats = solve(scene, options, seed)
        both = (history, deltas)
        stats["cached"] = "no"
        if disk is not None:  # a full or read-only cache only costs the reuse
            buffer = io.BytesIO()
            np.save(buffer, np.concatenate([history[None], deltas]), allow_pickle=False)
            disk.put(key, buffer.getvalue())
    _SOLUTIONS[key] = both
    while len(_SOLUTIONS) > LRU_CAPACITY:
        _SOLUTIONS.popitem(last=False)
    return (*both, stats)


def auto_patch_size(scene) -> float:
    """The default patch size: the bounding-box diagonal / (20 sqrt 3), so a
    scene as large as a cube of side 2 (cornell-box) gets 0.1."""
    return patch_size_of_bounds(*scene.bounds)


def patch_size_of_bounds(lo: np.ndarray, hi: np.ndarray) -> float:
    return float(np.linalg.norm(hi - lo)) / (20.0 * math.sqrt(3.0))
