"""`mlt`: primary-sample-space Metropolis light transport (Kelemen et al. 2002)
over bidirectional path tracing, the way pbrt-v3's MLTIntegrator does it.

| option | type | default | meaning |
|---|---|---|---|
| `heuristic` | str | `balance` | BDPT's MIS weights of the strategies: balance or power |
| `large_step` | float | 0.3 | probability of a large step (every primary sample drawn anew) |
| `sigma` | float | 0.01 | standard deviation of a small step's normal perturbation |
| `perturbation` | str | `normal` | small steps: pbrt-v3's wrapped normal, or Kelemen's exponential (s1 = 1/1024, s2 = 1/64) |
| `bootstrap` | int | 0 | bootstrap paths per depth; 0 = auto: W H spp / (4 (depth + 1)), clamped to [16384, 100000] (about a quarter of the mutations' work, at most pbrt-v3's default) |
| `chains` | int | 1024 | Markov chains, grouped into at most 8 chain units (pbrt-v3: 1000) |

The spec's spp is the number of mutations per pixel: the chains make
W x H x spp mutations in all. When to use it: on scenes where light arrives
through narrow paths (a door ajar, caustics) that chains, once they find
them, explore locally; on easy scenes BDPT or path-mis at equal time is less
noisy and has no start-up or normalisation error (cornell-box 128 x 128,
depth 5, on 2 processes of a shared machine: mlt at 32 mutations per pixel
in 0.9 s has an RMSE of 0.066 against path-mis at 1024 spp, path-mis at 64
spp in 0.7 s 0.030, bdpt at 16 spp in 1.0 s 0.086).

The state of a chain is a depth d (fixed for the chain, as in pbrt-v3) and a
vector u of primary samples in [0, 1)^D(d); BDPT's `mlt_L`
(renderer/kernels/subpaths.py: the layout of u is there) maps it to the MIS-weighted contribution of one
(s, t) strategy of paths with d bounces (the strategy drawn from u[2]),
times the number of strategies, and the film position it lands on (the
light subpath's projection for t = 1). The target density is its
luminance y.

The plan (a two-stage DAG):
- stage 0, one `bootstrap` unit (0 x 0 region, no samples): n bootstrap
  vectors per depth (`bootstrap_vector`: depth i mod (depth + 1), uniform
  numbers from stream_key(seed, STREAM_BOOTSTRAP, i), the film position
  jittered over the n vectors of a depth, which pbrt-v3 does not do: an
  unbiased, much less noisy b; its standard error `b_stderr` collapses
  neighbouring strata in pairs). b = (depth + 1) mean(y_i) is the image's
  mean luminance (pbrt-v3: b = bootstrap.funcInt * (maxDepth + 1)). Its
  artefact holds b, its standard error, the per-depth means and, for every
  chain, its starting bootstrap index drawn from the discrete distribution
  proportional to y_i (`chain_starts`: systematic resampling within each
  chain unit, with dimension 0 of the chain's own stream). The distribution
  itself is not shipped: it would be 8 bytes per bootstrap path to every
  chain unit.
- stage 1, `chains` units (full frame, `needs` the bootstrap): chain c owns
  the mutations [c M / C, (c + 1) M / C) of the M = W H spp in all and draws
  its random numbers from stream_key(seed, STREAM_CHAINS, c), dimensions 1,
  2, ... in order. Its first state is bootstrap vector start[c], regenerated.
  Every mutation splats both the proposal (weight a) and the current state
  (weight 1 - a), each as L / y(L) (pbrt-v3's expected-value splatting). The
  unit's splat batch holds those sums times b W H, with the unit's mutation
  count as its `paths`: the merged frame mean sum(splat) / M is pbrt-v3's
  film scaled by b / mutationsPerPixel.

Mutations are pbrt-v3's MLTSampler: per dimension a value, the iteration of
its last change and a backup; a large step redraws, a small step adds a
normal (sigma sqrt(n) for n missed iterations, the lazy catch-up) and wraps
into [0, 1); a rejection restores the backups and rewinds the iteration
counter; dimensions untouched since an accepted large step are redrawn
before use. mlt_L reads u as a flat array, so before each evaluation
`_ready_strategy` brings up to date the dimensions it will read: film and
strategy first, then those of the strategy u[2] selects (a superset of
them, from kernels/subpaths.py's layout); the others wait, as in pbrt-v3, and catch up
when next used.

Variance (the EXR's var channels): every chain unit is one splat batch.
The units hold disjoint sets of chains whose random numbers are independent
and each unit's chains start from their own systematic resample of the
bootstrap, so the batches are independent and the batch-means variance of
film.py applies with K = number of chain units (up to 8). Every batch is
scaled by the same b, so b's error is invisible to the batches: each chain
unit's film carries (b_stderr / b)^2 as `splat_scale_rel_var` and the var
channels add I^2 (b_stderr / b)^2 to each pixel's I (first order, b taken as
independent of the chains; film.py). That term is one error shared by every
pixel: two pixels' covariance is I_p I_q (b_stderr / b)^2, and the image
mean's relative error is at least b_stderr / b. With K this small the batch
part is itself noisy (K - 1 degrees of freedom).

Determinism: a chain's path depends on (seed, chain index, its unit's chain
range) only, and the grouping of chains into units is a function of
`chains` only (not of tile size or workers), so the image is a fixed
function of the spec and the EXR bit-identical across executors. Another
grouping (a different CHAIN_UNITS) resamples the starts per unit: a
different, equally valid image, with the same b and the same total
luminance.

The job's pixel sampler and tile size play no part: every primary sample
comes from the streams above, and the plan is not tiled.

Progressive jobs render in one pass (a chain's state would have to travel
between passes).

`toy_chains` runs the same Metropolis steps on analytic integrands for the
tests of the mutation kernel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ..errors import SpecError
from ..film import PartialFilm
from ..kernels import kernel, kernel_parallel
from ..kernels.camera import CAM_LENS, splat_add
from ..kernels.geometry import STACK_SIZE
from ..kernels.rng import STREAM_BOOTSTRAP, STREAM_CHAINS, stream_key, uniform
from ..kernels.sampling import BALANCE, ONE_MINUS_EPS, POWER
from ..kernels.subpaths import NV, conn0, light0, mlt_L
from ..kernels.subpaths import dims as bdpt_dims
from ..plan import Unit
from ..registry import Method, Option
from ..scene import camera_array

CHAIN_UNITS = 8  # at most this many chain units: the variance's batches
BOOTSTRAP_CHUNKS = 64  # prange work items of the bootstrap (each with its buffers)
NORMAL, EXPONENTIAL = 0, 1


@kernel
def luminance(r, g, b):
    """pbrt-v3's RGBSpectrum::y()."""
    return 0.212671 * r + 0.715160 * g + 0.072169 * b


@kernel
def path_dims(depth):
    """Primary samples a path of `depth` bounces can read (bdpt.dims)."""
    return bdpt_dims(depth)


def workspace_rows(max_depth: int) -> int:
    """Vertex rows of bdpt.mlt_L's scratch for any depth up to max_depth."""
    return 2 * (max_depth + 2) + 1


@kernel
def bootstrap_vector(seed, i, n, max_depth, width, height, u):
    """Fill u with bootstrap vector i of n (all depths); returns its depth.

    Vector i has depth i mod (max_depth + 1) and is number j = i div
    (max_depth + 1) of the m = n / (max_depth + 1) of its depth. Its film
    position is jittered on a gx x gy grid over the frame (gx gy <= m, cells
    about square; the j >= gx gy left over are uniform), which pbrt-v3 does
    not do: b stays unbiased (each part's mean is) and loses most of its
    variance, since a light seen directly is otherwise a rare event. Every
    dimension is drawn from uniform(stream_key(seed, STREAM_BOOTSTRAP, i), dim)."""
    depth = i % (max_depth + 1)
    m = n // (max_depth + 1)
    j = i // (max_depth + 1)
    key = stream_key(seed, STREAM_BOOTSTRAP, i)
    for k in range(path_dims(depth)):
        u[k] = uniform(key, k)
    gx = max(1, min(m, int(math.sqrt(m * width / height))))
    gy = max(1, m // gx)
    if j < gx * gy:
        u[0] = min(((j % gx) + u[0]) / gx, ONE_MINUS_EPS)
        u[1] = min(((j // gx) + u[1]) / gy, ONE_MINUS_EPS)
    return depth


@kernel_parallel
def _bootstrap(sc, cam, width, height, max_depth, heuristic, seed, n, weights, us, vs, stacks,
               rays):
    """weights[i] = y(mlt_L(bootstrap vector i)), i < n, in parallel chunks;
    rays[c] = the rays chunk c traced."""
    chunks = us.shape[0]
    for c in prange(chunks):
        u, V, stack = us[c], vs[c], stacks[c]
        traced = 0
        for i in range(c * n // chunks, (c + 1) * n // chunks):
            depth = bootstrap_vector(seed, i, n, max_depth, width, height, u)
            r, g, b, _, _, nr = mlt_L(sc, cam, width, height, depth, heuristic, u, V, stack)
            weights[i] = luminance(r, g, b)
            traced += nr
        rays[c] = traced


@kernel
def _small_step(x, n_small, sigma, perturbation, key, ctr):
    """x after n_small small steps, wrapped into [0, 1): (x, next counter)."""
    if perturbation == NORMAL:
        # n normal steps of sigma sum to one of sigma sqrt(n) (pbrt-v3's lazy catch-up)
        u1, u2 = uniform(key, ctr), uniform(key, ctr + 1)
        z = math.sqrt(-2.0 * math.log(1.0 - u1)) * math.cos(2.0 * math.pi * u2)
        x += z * sigma * math.sqrt(n_small)
        ctr += 2
    else:
        # Kelemen's exponential: |dx| = s2 exp(-ln(s2/s1) v), sign by the other number
        s1, s2 = 1.0 / 1024.0, 1.0 / 64.0
        for _ in range(n_small):
            dv = s2 * math.exp(-math.log(s2 / s1) * uniform(key, ctr + 1))
            x += dv if uniform(key, ctr) < 0.5 else -dv
            ctr += 2
    x -= math.floor(x)
    return min(x, ONE_MINUS_EPS), ctr


@kernel
def _mutate(x, last_mod, x_backup, mod_backup, lo, hi, iteration, last_large, large,
            sigma, perturbation, key, ctr):
    """pbrt-v3 MLTSampler::EnsureReady on dimensions [lo, hi); returns ctr."""
    for i in range(lo, hi):
        if last_mod[i] < last_large:  # untouched since an accepted large step: redraw
            x[i] = uniform(key, ctr)
            ctr += 1
            last_mod[i] = last_large
        x_backup[i] = x[i]
        mod_backup[i] = last_mod[i]
        if large:
            x[i] = uniform(key, ctr)
            ctr += 1
        else:
            v, ctr = _small_step(x[i], iteration - last_mod[i], sigma, perturbation, key, ctr)
            x[i] = v
        last_mod[i] = iteration
    return ctr


@kernel
def _ready_strategy(x, last_mod, x_backup, mod_backup, depth, iteration, last_large, large,
                    sigma, perturbation, key, ctr, lens=False):
    """Bring up to date the dimensions mlt_L will read (the lazy part of
    pbrt-v3's MLTSampler): film and strategy first, then, for the strategy
    (s, t) u[2] now selects (mlt_L's rule), the t camera vertices' bounces,
    the light subpath when s >= 2 and the connection (kernels/subpaths.py's layout; test09
    checks mlt_L reads nothing else; with a thin `lens`, also its point's numbers).
    Returns ctr."""
    ctr = _mutate(x, last_mod, x_backup, mod_backup, 0, 4, iteration, last_large, large,
                  sigma, perturbation, key, ctr)
    if depth == 0:
        s, t = 0, 2
    else:
        n = depth + 2
        s = min(int(x[2] * n), n - 1)
        t = n - s
    # t camera vertices: the camera, the camera ray's hit, then t - 2 bounces
    ctr = _mutate(x, last_mod, x_backup, mod_backup, 4, 4 + 4 * max(t - 2, 0), iteration,
                  last_large, large, sigma, perturbation, key, ctr)
    if s >= 2:  # the light point and its emitted ray (6), then s - 2 bounces
        l0 = light0(depth)
        ctr = _mutate(x, last_mod, x_backup, mod_backup, l0, l0 + 6 + 4 * (s - 2), iteration,
                      last_large, large, sigma, perturbation, key, ctr)
    if s == 1 or (lens and t == 1):  # the light point (or lens point) the connection samples
        c0 = conn0(depth) + 4 * t
        ctr = _mutate(x, last_mod, x_backup, mod_backup, c0, c0 + 3, iteration, last_large,
                      large, sigma, perturbation, key, ctr)
    if lens and t == 2:  # the lens point's second number (the first is u[3])
        ctr = _mutate(x, last_mod, x_backup, mod_backup, 7, 8, iteration, last_large, large,
                      sigma, perturbation, key, ctr)
    return ctr


@kernel
def _splat(splat, cam, fx, fy, r, g, b, scale):
    splat_add(splat, cam, fx, fy, r * scale, g * scale, b * scale)


@kernel
def _restore(x, last_mod, x_backup, mod_backup, dims, iteration):
    """pbrt-v3 MLTSampler::Reject: undo this iteration's changes; returns the
    rewound iteration counter."""
    for i in range(dims):
        if last_mod[i] == iteration:
            x[i] = x_backup[i]
            last_mod[i] = mod_backup[i]
    return iteration - 1


@kernel
def _acceptance(y_proposed, y_current):
    if y_current > 0.0:
        return min(1.0, y_proposed / y_current)
    return 1.0  # a zero current state (a toy chain's start): take any proposal


@kernel
def run_chain(sc, cam, width, height, max_depth, heuristic, seed, chain, start, n_boot,
              mutations, scale, large_step, sigma, perturbation, x, last_mod, x_backup,
              mod_backup, V, stack, splat):
    """Run `mutations` mutations of chain `chain` from bootstrap vector
    `start`, splatting into `splat` with the factor `scale` (b W H).
    Returns (accepted mutations, rays traced)."""
    depth = bootstrap_vector(seed, start, n_boot, max_depth, width, height, x)
    dims = path_dims(depth)
    for k in range(dims):
        last_mod[k] = 0
    key = stream_key(seed, STREAM_CHAINS, chain)
    ctr = 1  # dimension 0 chose the start (in the bootstrap unit)
    cr, cg, cb, cx, cy, rays = mlt_L(sc, cam, width, height, depth, heuristic, x, V, stack)
    cy_l = luminance(cr, cg, cb)
    iteration, last_large = 0, 0
    accepted = 0
    for _ in range(mutations):
        iteration += 1
        large = uniform(key, ctr) < large_step
        ctr = _ready_strategy(x, last_mod, x_backup, mod_backup, depth, iteration, last_large,
                              large, sigma, perturbation, key, ctr + 1, cam[CAM_LENS] > 0.0)
        pr, pg, pb, px, py, nr = mlt_L(sc, cam, width, height, depth, heuristic, x, V, stack)
        rays += nr
        py_l = luminance(pr, pg, pb)
        a = _acceptance(py_l, cy_l)
        # expected-value splatting: both states, weighted by the acceptance
        if a > 0.0 and py_l > 0.0:
            _splat(splat, cam, px, py, pr, pg, pb, scale * a / py_l)
        if a < 1.0 and cy_l > 0.0:
            _splat(splat, cam, cx, cy, cr, cg, cb, scale * (1.0 - a) / cy_l)
        if uniform(key, ctr) < a:
            cr, cg, cb, cx, cy, cy_l = pr, pg, pb, px, py, py_l
            if large:
                last_large = iteration
            accepted += 1
        else:
            iteration = _restore(x, last_mod, x_backup, mod_backup, dims, iteration)
        ctr += 1
    return accepted, rays


@kernel
def _run_chains(sc, cam, width, height, max_depth, heuristic, seed, c0, c1, chains, total,
                starts, n_boot, scale, large_step, sigma, perturbation, x, last_mod, x_backup,
                mod_backup, V, stack, splat):
    """Chains [c0, c1) of `chains`, sharing `total` mutations; returns
    (accepted mutations, rays traced)."""
    accepted, rays = 0, 0
    for c in range(c0, c1):
        m = (c + 1) * total // chains - c * total // chains
        if m > 0 and starts[c] >= 0:
            a, nr = run_chain(sc, cam, width, height, max_depth, heuristic, seed, c,
                              starts[c], n_boot, m, scale, large_step, sigma, perturbation,
                              x, last_mod, x_backup, mod_backup, V, stack, splat)
            accepted += a
            rays += nr
    return accepted, rays


@kernel
def _start_numbers(seed, out):
    """Dimension 0 of every chain's stream: the number that picks its start."""
    for c in range(out.shape[0]):
        out[c] = uniform(stream_key(seed, STREAM_CHAINS, c), 0)


def bootstrap_per_depth(spec, opts: dict) -> int:
    n = int(opts["bootstrap"])
    if n > 0:
        return n
    return int(min(100_000, max(16384, spec.width * spec.height * spec.spp // (4 * (spec.depth + 1)))))


# The bootstrap unit holds a weight per path, (depth + 1) x bootstrap of them,
# and sorts them: 10^7 per depth at depth 64 (the bound before) were 5 GB per
# array. 2^24 paths are 134 MB; the automatic count is at most 6.5 million.
MAX_BOOTSTRAP_PATHS = 1 << 24


def check_bootstrap(spec, doc: dict, opts: dict) -> None:
    """Refuse at submission a bootstrap of more than MAX_BOOTSTRAP_PATHS paths
    (the job's depth decides; the scene does not)."""
    per_depth = bootstrap_per_depth(spec, opts)
    if per_depth * (spec.depth + 1) > MAX_BOOTSTRAP_PATHS:
        raise SpecError("options.bootstrap", f"{per_depth} paths per depth x {spec.depth + 1} "
                                             f"depths exceed {MAX_BOOTSTRAP_PATHS} bootstrap "
                                             f"paths: at depth {spec.depth}, at most "
                                             f"{MAX_BOOTSTRAP_PATHS // (spec.depth + 1)}")


def chain_groups(chains: int) -> list[tuple[int, int]]:
    """The chain ranges of the chain units: min(chains, CHAIN_UNITS) near-equal
    contiguous ranges."""
    groups = min(chains, CHAIN_UNITS)
    return [(g * chains // groups, (g + 1) * chains // groups) for g in range(groups)]


def plan_mlt(spec, progressive: bool, opts: dict) -> list[Unit]:
    """One bootstrap unit, then up to CHAIN_UNITS chain units (one pass even
    when `progressive`: see the module doc)."""
    n_boot = bootstrap_per_depth(spec, opts) * (spec.depth + 1)
    units = [Unit(0, 0, 0, 0, 0, 0, n_boot, stage=0, kind="bootstrap")]
    for g, (c0, c1) in enumerate(chain_groups(int(opts["chains"]))):
        units.append(Unit(1 + g, 0, 0, spec.width, spec.height, c0, c1, stage=1, kind="chains",
                          needs=(0,)))
    return units


def chain_starts(seed: int, chains: int, weights: np.ndarray, max_depth: int) -> np.ndarray:
    """Each chain's starting bootstrap index (-1 for all when every weight is 0).

    Systematic resampling per chain unit: the bootstrap paths are ordered
    by depth (then by index), and the l-th of a unit's n chains takes the
    path at (l + xi) / n of their cumulative weight, xi from dimension 0 of
    the chain's own stream. So every unit's chains cover the depths in
    proportion to their weight (a chain never changes depth: with
    independent draws the number of chains per depth dominated the image's
    colour error), the chains of all units together still start from the
    bootstrap distribution, and the units stay independent batches."""
    order = np.arange(weights.size).reshape(-1, max_depth + 1).T.ravel()
    cdf = np.cumsum(weights[order])
    if cdf.size == 0 or not cdf[-1] > 0.0:
        return np.full(chains, -1, np.int64)
    xi = np.zeros(chains)
    _start_numbers(seed, xi)
    r = np.empty(chains)
    for c0, c1 in chain_groups(chains):
        r[c0:c1] = (np.arange(c1 - c0) + xi[c0:c1]) / (c1 - c0)
    pos = np.minimum(np.searchsorted(cdf, r * cdf[-1], side="right"), weights.size - 1)
    return order[pos].astype(np.int64)


def run_mlt(scene, spec, unit, inputs, opts: dict) -> PartialFilm:
    cam = camera_array(scene.camera, spec.width, spec.height)
    heuristic = POWER if opts["heuristic"] == "power" else BALANCE
    dims = int(path_dims(spec.depth))
    rows = workspace_rows(spec.depth)
    chains = int(opts["chains"])
    if unit.kind == "bootstrap":
        n = unit.sample_end - unit.sample_start
        weights = np.zeros(n)
        rays = np.zeros(BOOTSTRAP_CHUNKS, np.int64)
        _bootstrap(scene.arrays, cam, spec.width, spec.height, spec.depth, heuristic, spec.seed,
                   n, weights, np.zeros((BOOTSTRAP_CHUNKS, dims)),
                   np.zeros((BOOTSTRAP_CHUNKS, rows, NV)),
                   np.zeros((BOOTSTRAP_CHUNKS, STACK_SIZE), np.int64), rays)
        by_depth = weights.reshape(-1, spec.depth + 1)
        per_depth = by_depth.mean(axis=0)
        # b's standard error, from neighbouring strata collapsed in pairs (each
        # pair's squared difference estimates the sum of their variances, or
        # more): the depths' means are independent
        pairs = by_depth.shape[0] // 2
        diff = by_depth[0:2 * pairs:2] - by_depth[1:2 * pairs:2]
        b_stderr = math.sqrt(float((diff * diff).sum())) / by_depth.shape[0]
        film = PartialFilm.zeros(0, 0, 0, 0)
        film.artefact = {"b": np.array([float(per_depth.sum())]), "n": np.array([n]),
                         "b_stderr": np.array([b_stderr]), "depth_means": per_depth,
                         "starts": chain_starts(spec.seed, chains, weights, spec.depth)}
        film.stats.update(samples=0, rays=int(rays.sum()), paths=n)
        return film
    if unit.kind != "chains" or not unit.needs:
        raise ValueError(f"mlt runs its own plan (Method.make_plan), got a {unit.kind!r} unit")
    boot = inputs[unit.needs[0]].artefact
    b = float(boot["b"][0])
    total = spec.width * spec.height * spec.spp
    splat = np.zeros((spec.height, spec.width, 3))
    x, x_backup = np.zeros(dims), np.zeros(dims)
    last_mod, mod_backup = np.zeros(dims, np.int64), np.zeros(dims, np.int64)
    accepted, rays = _run_chains(
        scene.arrays, cam, spec.width, spec.height, spec.depth, heuristic, spec.seed,
        unit.sample_start, unit.sample_end, chains, total, boot["starts"], int(boot["n"][0]),
        b * spec.width * spec.height, float(opts["large_step"]), float(opts["sigma"]),
        EXPONENTIAL if opts["perturbation"] == "exponential" else NORMAL,
        x, last_mod, x_backup, mod_backup, np.zeros((rows, NV)), np.zeros(STACK_SIZE, np.int64),
        splat)
    mutations = sum((c + 1) * total // chains - c * total // chains
                    for c in range(unit.sample_start, unit.sample_end))
    film = PartialFilm.splat_batch(splat, mutations)
    # every chain unit is scaled by the same b: its error (b_stderr) is the same
    # relative error in every pixel, which the batches cannot show (film.py)
    film.splat_scale_rel_var = (float(boot["b_stderr"][0]) / b) ** 2 if b > 0 else 0.0
    film.stats.update(samples=mutations, rays=int(rays), paths=mutations, accepted=int(accepted))
    return film


METHODS = (Method(
    name="mlt",
    aov_note="its image is splatted from Markov chains of whole paths: no "
             "camera sample of a pixel has a first hit to take albedo, normal or depth from",
    description="Primary-sample-space Metropolis light transport (Kelemen) over BDPT: a "
                "bootstrap estimates the normalisation, independent chains splat; spp = "
                "mutations per pixel.",
    run=run_mlt,
    options=(
        Option("heuristic", str, "balance", "BDPT's MIS weights: balance or power (beta = 2) "
               "heuristic", ("balance", "power")),
        Option("large_step", float, 0.3, "probability of a large step (all primary samples "
               "redrawn)", bounds=(0.0, 1.0)),
        Option("sigma", float, 0.01, "standard deviation of the small steps' normal "
               "perturbation", bounds=(1e-6, 1.0)),
        Option("perturbation", str, "normal", "small steps: pbrt-v3's wrapped normal or "
               "Kelemen's exponential", ("normal", "exponential")),
        Option("bootstrap", int, 0, "bootstrap paths per depth (0 = auto from the image "
               f"size and spp); at most {MAX_BOOTSTRAP_PATHS} paths over the depth + 1 "
               "depths", bounds=(0, MAX_BOOTSTRAP_PATHS)),
        Option("chains", int, 1024, "Markov chains (grouped into at most 8 units)",
               bounds=(1, 1 << 20)),
    ),
    family="chains",
    plan=plan_mlt,
    phases=("bootstrap", "chains"),
    check_scene=check_bootstrap,
),)
