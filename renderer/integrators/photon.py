"""Photon mapping: stochastic progressive photon mapping (default) and the
classic one-pass photon map with k-nearest-neighbour density estimation.

`photon` with `mode=sppm` (default) is Hachisuka & Jensen's stochastic
progressive photon mapping (2009), modelled on pbrt-v3's SPPMIntegrator.
Each iteration i (spp = iterations) has
- a camera pass: one camera sample per pixel (sample index i of the job's
  pixel sampler) follows mirrors and glass up to `depth` and stops at the
  first diffuse or glossy surface, the *visible point*. Emission seen along
  that specular chain (including at the visible point) and direct light at
  the visible point (a shadow ray to a point from `sample_light`, no MIS:
  emission found later is never counted by the camera pass) form the direct
  estimate Ld_i;
- a photon pass: `photons` photons leave the lights (`sample_emission`,
  random numbers from `stream_key(seed, STREAM_PHOTONS, g)` with the global
  photon index g = i * photons + j), bounce with adjoint BSDFs (no 1/eta^2
  on refraction: importance transport) and Russian roulette (survival =
  max(new throughput) / max(old), so photon power stays level), and are
  recorded at every diffuse or glossy hit except the first (the first hit is
  direct light, which the camera pass estimates); each record keeps the
  position, the travelling direction, the power and the hit count k;
- a gather: each visible point sums f(wo, wi) * power over the photons
  within its radius r that arrive from the front side of its surface (one
  sided: photons from behind are neither in M nor in Phi) and whose path is
  not too long (k + specular bounces before the visible point <= depth), then
  N' = N + alpha M, r'^2 = r^2 (N + alpha M) / (N + M),
  tau' = (tau + Phi) r'^2 / r^2 with alpha = 2/3 (`sppm_update`).
The final estimate is L = sum(Ld_i) / n + tau / (n * photons * pi r^2).

Depth: a photon's k counts its surface hits from the light, so a photon
gathered at a visible point reached after b specular bounces closes a path of
k + b bounces (pbrt's depth); direct light is k = 1 and emission is k = 0, as
in `path-mis`.

Radius: the `radius` option, or (0, auto) 1/100 of the scene's bounding box
diagonal. Photons per iteration: `photons`, or (0, auto) pbrt's default of
one per pixel with at least 16384.

Farm plan (DAG, family "photons", phases ("photons", "gather")): iterations
are grouped `iterations_per_unit` at a time (0 = auto: at most 16 groups;
1 = one gather round per iteration). For each group: `photons` units (each
a range of global photon indices of one iteration, at most 2^16 photons; the
region is 0x0, the result is the photon array as the artefact `photon_pos`,
`photon_dir`, `photon_power` (float32) and `photon_k`), then one `gather`
unit per tile that needs the group's photon units and the same tile's gather
unit of the previous group, whose per-pixel state (N, r2, tau, ld, s1, s2, M)
travels as artefacts. Every gather unit covers its tile, and its film is the
*change* of the tile's estimate over its round: the estimate film after the
round (see Variance) minus the one the previous round's state gives. The
merge (plain addition, in unit order) telescopes these to the final
estimate, equal to it up to float rounding (and bit-identical whatever the
tile size or the workers: each pixel sees the same additions in the same
order), while the service's running preview, which adds the units that have
landed, shows each round's estimate as it lands instead of nothing until
the last. `stats["samples"]` of a gather unit is pixels x iterations, so a
job totals width * height * spp.

Data volume: a photon record is 40 bytes (float32 position, direction and
power, int32 k); cornell-box at depth 5 stores about one record per emitted
photon (2.7 MB per 65536-photon unit). Every gather tile of a group reads all
of the group's photon units, so a 256x256, 256-iteration job with 64-pixel
tiles moves about 16 x 16 x 43 MB = 11 GB of inputs to gather units and
stores 0.7 GB of photon results; larger tiles divide the first figure.

Gather acceleration: a uniform hash grid over the photons (pbrt-v3 hashes
visible points instead), cell size = the initial radius (radii only shrink,
so a visible point's sphere overlaps at most 2x2x2 cells), photons sorted
into buckets by a stable counting sort, each photon tagged with its integer
cell so hash collisions never count a photon twice. Photons outside the
tile's visible points' bounding box (grown by the largest radius) are not
inserted. The summation order (cells in coordinate order, photons in index
order) does not depend on the tile, so results are bit-identical whatever
the tile size or the number of workers.

Bias (measured). The finite radius blurs, and where two surfaces meet (a
corner, a door jamb, the ceiling beside a light) a visible point also
gathers photons that landed on the other surface and arrive from its front
side, so such places read too bright. The bias shrinks with the radius, as
SPPM's consistency promises, but slowly (r^2 falls about as n^(-1/3)). On
`door-ajar` (48x48, depth 5, 256 iterations), against BDPT's image mean
0.0733 +- 0.0005 (R): radius 0.1 gives 0.0803 (+9.5 %), the default
(diagonal / 100 = 0.049) 0.0768 (+4.8 %), radius 0.02 0.0744 +- 0.0012
(+1.5 %). Lower `radius` where corners matter; it costs variance.

Variance (the EXR's var.R/G/B): from the per-iteration estimates
X_i = Ld_i + Phi_i / (photons * pi r_i^2), whose sums s1 = sum X_i and
s2 = sum X_i^2 travel with the state. Var(L) is estimated as the batch-means
variance of the X_i: (s2 - s1^2 / n) / ((n - 1) n). Assumptions: iterations
are independent (each has its own camera samples and photons; the radius
they share through the state makes them weakly dependent) and the final
progressive estimate has about the variance of the plain average of the X_i
(it weights the photon part a little differently). It ignores the bias of
the finite radius (which vanishes as n grows). The estimate film
(`_estimate_film`, what the gather films telescope to) encodes weight = n,
sum = n L and sum_sq = n L^2 + (s2 - s1^2 / n), so
`Film.mean()` returns L and `Film.variance_of_mean()` returns that estimate
(+inf for n = 1). Measured over 24 seeds (16x16, 16 iterations, depth 3):
estimated / empirical per-pixel variance 1.02 (furnace-point) and 0.86
(cornell-box, median 1.04). Pixels are not independent (one photon path
deposits at several places, neighbouring visible points share photons), so
the sum of pixel variances underestimates the variance of an image average
(by 1.2x on the furnace, 1.7x on cornell-box in those runs).

`mode=photonmap` is Jensen's classic photon map: one photon pass of
`photons` photons (0 = auto: 4 per pixel, at least 65536), then gather tiles
with spp camera samples per pixel. The photon map is *visualised directly*
at the first diffuse or glossy hit (no final gather): L = emission along the
specular chain + direct light by light sampling + the k-nearest-neighbour
density estimate of indirect light, sum f * power / (photons * pi r_k^2),
with the `k` nearest front-side photons within the maximum search radius
`radius` (0 = auto: 1/40 of the scene diagonal; r_k = that radius if fewer
than k photons are found). It is biased and not consistent at a fixed photon
count; the film's variance is the camera samples' variance given the photon
map (the photon map's own noise is a fixed error pattern and is not in it).
"""

from __future__ import annotations

import math

import numpy as np

from ..film import AOV_CHANNELS, PartialFilm
from ..kernels.geometry import (
    STACK_SIZE,
)
from ..kernels.photons import (
    build_grid,
    camera_pass,
    gather_pass,
    knn_render,
    sppm_update,
    trace_photons,
)
from ..plan import Unit
from ..registry import SAMPLERS, Method, Option
from ..samplers import NO_MEMO
from ..scene import camera_array
from ..scene_format import MAX_COORDINATE
from .tile import start_tile

__all__ = ["ALPHA", "plan_photon", "run_photon", "photons_per_iteration", "initial_radius"]

ALPHA = 2.0 / 3.0
PHOTON_UNIT_MAX = 1 << 16  # photons per photon unit at most
MAX_GROUPS = 16  # auto iterations_per_unit: at most this many gather rounds
SPPM, PHOTONMAP = "sppm", "photonmap"


# ------------------------------------------------------------ plumbing

def _typed(options: dict) -> dict:
    """The checked options converted to their declared types (the CLI's
    --option KEY=VALUE passes strings; check_options does not convert)."""
    return {o.name: o.type(options[o.name]) for o in OPTIONS}


def photons_per_iteration(spec, options: dict) -> int:
    """Photons of one iteration (sppm) or of the whole map (photonmap)."""
    if options["photons"] > 0:
        return int(options["photons"])
    if options["mode"] == PHOTONMAP:
        return max(65536, 4 * spec.width * spec.height)
    return max(16384, spec.width * spec.height)


def initial_radius(scene, options: dict) -> float:
    """The `radius` option, or (0) a fraction of the scene's bounding box
    diagonal: 1/100 for SPPM's initial radius, 1/40 for the k-NN search."""
    if options["radius"] > 0:
        return float(options["radius"])
    lo, hi = scene.bounds
    diag = float(np.linalg.norm(hi - lo))
    return diag * (0.025 if options["mode"] == PHOTONMAP else 0.01)


def _iterations_per_unit(spec, options: dict) -> int:
    if options["iterations_per_unit"] > 0:
        return int(options["iterations_per_unit"])
    return max(1, -(-spec.spp // MAX_GROUPS))


def _tiles(spec) -> list[tuple[int, int, int, int]]:
    t = spec.tile_size
    return [(x, y, min(x + t, spec.width), min(y + t, spec.height))
            for y in range(0, spec.height, t) for x in range(0, spec.width, t)]


def _photon_ranges(total: int) -> list[tuple[int, int]]:
    parts = max(1, -(-total // PHOTON_UNIT_MAX))
    return [(total * i // parts, total * (i + 1) // parts) for i in range(parts)]


def plan_photon(spec, progressive: bool, options: dict) -> list[Unit]:
    """The DAG (module doc). `progressive` changes nothing: SPPM is
    progressive by construction (each gather round refines the image)."""
    options = _typed(options)
    n_photons = photons_per_iteration(spec, options)
    tiles = _tiles(spec)
    units: list[Unit] = []
    if options["mode"] == PHOTONMAP:
        needs = []
        for a, b in _photon_ranges(n_photons):
            needs.append(len(units))
            units.append(Unit(len(units), 0, 0, 0, 0, a, b, 0, 0, "photons"))
        for x0, y0, x1, y1 in tiles:
            units.append(Unit(len(units), x0, y0, x1, y1, 0, spec.spp, 0, 1, "gather",
                              tuple(needs)))
        return units
    group = _iterations_per_unit(spec, options)
    prev: list[int] | None = None
    for gi, i0 in enumerate(range(0, spec.spp, group)):
        i1 = min(i0 + group, spec.spp)
        needs = []
        for it in range(i0, i1):
            for a, b in _photon_ranges(n_photons):
                needs.append(len(units))
                units.append(Unit(len(units), 0, 0, 0, 0, it * n_photons + a, it * n_photons + b,
                                  gi, 2 * gi, "photons"))
        current = []
        for ti, (x0, y0, x1, y1) in enumerate(tiles):
            tile_needs = tuple(needs) + ((prev[ti],) if prev is not None else ())
            current.append(len(units))
            units.append(Unit(len(units), x0, y0, x1, y1, i0, i1, gi, 2 * gi + 1, "gather",
                              tile_needs))
        prev = current
    return units


def _run_photons(scene, spec, unit, options) -> PartialFilm:
    n = unit.sample_end - unit.sample_start
    # photon units never straddle iterations (photonmap: one "iteration" 0)
    iteration = unit.sample_start // photons_per_iteration(spec, options)
    depth = spec.depth
    cap = max(16, n * max(1, min(depth - 1, 4)))
    stack = np.empty(STACK_SIZE, np.int64)
    while True:
        pos = np.empty((cap, 3))
        dirs = np.empty((cap, 3))
        power = np.empty((cap, 3))
        hits = np.empty(cap, np.int32)
        count, rays = trace_photons(scene.arrays, stack, spec.seed, unit.sample_start,
                                    unit.sample_end, depth, pos, dirs, power, hits)
        if count >= 0:
            break
        cap *= 2
    film = PartialFilm.zeros(0, 0, 0, 0)
    film.artefact = {"photon_pos": pos[:count].astype(np.float32),
                     "photon_dir": dirs[:count].astype(np.float32),
                     "photon_power": power[:count].astype(np.float32),
                     "photon_k": hits[:count].copy(),
                     "iteration": np.array([iteration], np.int64)}
    film.stats.update(samples=0, rays=int(rays), photons=n)
    return film


def _photons_of(inputs: dict, needs, iteration: int | None):
    """The photon arrays of `iteration` (all iterations if None) from the
    inputs, concatenated in unit order (= photon index order)."""
    parts = [inputs[i].artefact for i in needs
             if "photon_pos" in inputs[i].artefact
             and (iteration is None or int(inputs[i].artefact["iteration"][0]) == iteration)]
    if not parts:
        return (np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 3)), np.empty(0, np.int32))
    return tuple(np.ascontiguousarray(np.concatenate([p[name] for p in parts]), dtype=dt)
                 for name, dt in (("photon_pos", np.float64), ("photon_dir", np.float64),
                                  ("photon_power", np.float64), ("photon_k", np.int32)))


class _Grid:
    """The buffers of `build_grid` for one photon array."""

    def __init__(self, ppos, cell_size, lo, hi):
        n = ppos.shape[0]
        size = 1 << max(4, int(n - 1).bit_length()) if n > 1 else 16
        self.inv_h = 1.0 / cell_size
        self.cell = np.zeros((n, 3), np.int64)
        bucket = np.empty(n, np.int64)
        self.start = np.zeros(size + 1, np.int64)
        cursor = np.empty(size, np.int64)
        self.order = np.zeros(n, np.int64)
        self.inserted = build_grid(ppos, self.inv_h, np.asarray(lo, np.float64),
                                   np.asarray(hi, np.float64), self.cell, bucket, self.start,
                                   cursor, self.order)


def _tile_of(spec, unit) -> tuple[int, int, int, int]:
    x0, y0 = unit.x0, unit.y0
    return x0, y0, min(x0 + spec.tile_size, spec.width), min(y0 + spec.tile_size, spec.height)


def _run_gather(scene, spec, unit, inputs, options) -> PartialFilm:
    x0, y0, x1, y1 = _tile_of(spec, unit)
    w, h = x1 - x0, y1 - y0
    sc = scene.arrays
    cam = camera_array(scene.camera, spec.width, spec.height)
    n_photons = photons_per_iteration(spec, options)
    r0 = initial_radius(scene, options)
    smp = SAMPLERS[spec.sampler].id
    prev = [inputs[i] for i in unit.needs if "N" in inputs[i].artefact]
    if prev:
        st = {k: v.copy() for k, v in prev[0].artefact.items()}
        before = _estimate_film(prev[0].artefact, float(unit.sample_start), n_photons, x0, y0)
    else:
        before = None
        st = {"N": np.zeros((h, w)), "r2": np.full((h, w), r0 * r0), "tau": np.zeros((h, w, 3)),
              "ld": np.zeros((h, w, 3)), "s1": np.zeros((h, w, 3)), "s2": np.zeros((h, w, 3)),
              "M": np.zeros((h, w)), "aov": np.zeros((h, w, AOV_CHANNELS))}
    vp_kmax = np.empty((h, w), np.int64)
    vp_p, vp_n, vp_wo, vp_beta = (np.empty((h, w, 3)) for _ in range(4))
    vp_mat = np.empty((h, w), np.int32)
    ld = np.empty((h, w, 3))
    phi = np.empty((h, w, 3))
    m = np.empty((h, w))
    row_rays = np.zeros(h, np.int64)
    stacks = np.empty((h, STACK_SIZE), np.int64)
    rays = 0
    for it in range(unit.sample_start, unit.sample_end):
        camera_pass(sc, cam, x0, y0, x1, y1, spec.width, spec.height, spec.seed, it, spec.spp,
                    smp, spec.depth, vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, ld, st["aov"],
                    row_rays, stacks, NO_MEMO)
        rays += int(row_rays.sum())
        ppos, pdir, ppow, phit = _photons_of(inputs, unit.needs, it)
        valid = vp_kmax >= 2
        if valid.any():
            rmax = math.sqrt(float(st["r2"][valid].max()))
            pts = vp_p[valid]
            lo, hi = pts.min(axis=0) - rmax, pts.max(axis=0) + rmax
        else:
            lo, hi = np.zeros(3), -np.ones(3)  # an empty box: nothing inserted
        grid = _Grid(ppos, r0, lo, hi)
        r2_before = st["r2"].copy()
        gather_pass(vp_kmax, vp_p, vp_n, vp_wo, vp_beta, vp_mat, st["r2"], sc.mat_type,
                    sc.mat_rgb, sc.mat_param, ppos, pdir, ppow, phit, grid.cell, grid.start,
                    grid.order, grid.inv_h, m, phi)
        x = ld + phi / (n_photons * math.pi * r2_before)[..., None]
        st["ld"] += ld
        st["s1"] += x
        st["s2"] += x * x
        st["M"] = m.copy()
        sppm_update(st["N"], st["r2"], st["tau"], m, phi, ALPHA)
    # The change of the tile's estimate over this round (module doc).
    film = _estimate_film(st, float(unit.sample_end), n_photons, x0, y0)
    if before is not None:
        film.weight -= before.weight
        film.sum -= before.sum
        film.sum_sq -= before.sum_sq
        film.aov -= before.aov
    film.artefact = st
    film.stats.update({"samples": w * h * (unit.sample_end - unit.sample_start), "rays": rays})
    return film


def _estimate_film(st: dict, n: float, n_photons: int, x0: int, y0: int) -> PartialFilm:
    """The tile's estimate after n iterations with state `st`, encoded so that
    `Film.mean()` is L and `Film.variance_of_mean()` its variance estimate:
    weight n, sum n L, sum_sq n L^2 + (s2 - s1^2 / n)."""
    h, w = st["N"].shape
    mean = st["ld"] / n + st["tau"] / (n * n_photons * math.pi * st["r2"])[..., None]
    film = PartialFilm.zeros(x0, y0, w, h, aov=True)
    film.aov[:] = st["aov"]  # sums over the n iterations' camera samples (film.py, "AOVs")
    film.weight[:] = n
    film.sum[:] = n * mean
    film.sum_sq[:] = n * mean * mean + np.maximum(st["s2"] - st["s1"] * st["s1"] / n, 0.0)
    return film


def _run_knn(scene, spec, unit, inputs, options) -> PartialFilm:
    n_photons = photons_per_iteration(spec, options)
    big_r = initial_radius(scene, options)
    k = int(options["k"])
    ppos, pdir, ppow, phit = _photons_of(inputs, unit.needs, None)
    grid = _Grid(ppos, big_r, np.full(3, -np.inf), np.full(3, np.inf))
    t = start_tile(scene, spec, unit, aov=True)
    h = unit.y1 - unit.y0
    knn_render(scene.arrays, t.cam, unit.x0, unit.y0, unit.x1, unit.y1, spec.width, spec.height,
               spec.seed, spec.spp, t.blocks, SAMPLERS[spec.sampler].id, spec.depth, ppos, pdir,
               ppow, phit, grid.cell, grid.start, grid.order, grid.inv_h, big_r * big_r, k,
               float(n_photons), t.film.sum, t.film.sum_sq, t.film.weight, t.film.aov,
               t.row_rays, t.stacks, t.memos, t.aov_rows, np.empty((h, k)),
               np.empty((h, k), np.int64))
    return t.finish(unit)


def run_photon(scene, spec, unit, inputs, options) -> PartialFilm:
    options = _typed(options)
    if unit.kind == "photons":
        return _run_photons(scene, spec, unit, options)
    if options["mode"] == PHOTONMAP:
        return _run_knn(scene, spec, unit, inputs, options)
    return _run_gather(scene, spec, unit, inputs, options)


# A radius the estimate pi r^2 N can divide by. Measured on cornell-box:
# r = 1e-300 (sppm) and 1e-160 (photonmap) rendered NaN pixels (r^2 is 0), and
# from 1e155 r^2 is inf and the k-NN search silently found nothing. Scene
# coordinates lie within +-MAX_COORDINATE, so a radius of ten times that covers
# any scene; 1/MAX_COORDINATE keeps r^2 (and the estimate) far from both ends.
MIN_RADIUS, MAX_RADIUS = 1.0 / MAX_COORDINATE, 10.0 * MAX_COORDINATE


def _check_radius(value) -> str | None:
    if value == 0 or value >= MIN_RADIUS:
        return None
    return f"must be 0 (automatic) or at least {MIN_RADIUS:g}, got {value!r}"


OPTIONS = (
    Option("mode", str, SPPM, "sppm: stochastic progressive photon mapping (spp = "
           "iterations); photonmap: one photon pass, k-NN estimate at the first diffuse "
           "hit (direct visualisation, no final gather)", (SPPM, PHOTONMAP)),
    Option("photons", int, 0, "photons per iteration (sppm) or in the map (photonmap); "
           "0 = auto: one per pixel, at least 16384 (sppm); 4 per pixel, at least 65536 "
           "(photonmap)", bounds=(0, 1 << 26)),
    Option("radius", float, 0.0, "initial gather radius (sppm) or maximum k-NN search "
           "radius (photonmap) in scene units; 0 = auto: 1/100 (sppm) or 1/40 "
           f"(photonmap) of the scene's bounding box diagonal; else {MIN_RADIUS:g} to "
           f"{MAX_RADIUS:g}", bounds=(0.0, MAX_RADIUS), check=_check_radius),
    Option("k", int, 64, "photonmap: photons of the k-nearest-neighbour estimate",
           bounds=(1, 4096)),
    Option("iterations_per_unit", int, 0, "sppm: iterations per gather unit; 0 = auto "
           "(at most 16 gather rounds)", bounds=(0, 1 << 20)),
)

METHODS = (Method(
    unsupported={"textured glossy inputs": "its gather evaluates a glossy BSDF with the "
                                           "material's constant specular and roughness"},
    name="photon",
    aovs=("albedo", "normal", "depth"),
    aliases=("sppm",),
    description="Photon mapping: stochastic progressive photon mapping (photon pass and "
                "gather per iteration, radius shrinking with alpha = 2/3), or the classic "
                "one-pass photon map with k-nearest-neighbour density estimation.",
    run=run_photon,
    options=OPTIONS,
    family="photons",
    plan=plan_photon,
    phases=("photons", "gather"),
    warm_options=({"mode": "photonmap"},),
),)
