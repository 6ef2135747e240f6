"""`bdpt`: bidirectional path tracing (Veach 1997; pbrt-v3's BDPTIntegrator).

    film = render_serial(load_scene("cornell-box"), RenderSpec(method="bdpt", depth=5))

Each camera sample traces a camera subpath (up to depth + 2 vertices, the
camera first) and a light subpath (up to depth + 1 vertices, a light point
first), then connects every prefix pair: strategy (s, t) uses s light and t
camera vertices, a path of s + t - 2 bounces; strategies up to `depth`
bounces run (the lecture's convention, the same paths as `path-mis`). t = 1
connects a light vertex straight to the camera (the pinhole, or a point it
draws on the thin lens) and splats anywhere on the film (through the
camera's filter, kernels/camera.py); the others add to the sample's pixel. (1, 1) is skipped as in pbrt:
a light seen directly is the (0, 2) strategy.

| option | default | meaning |
|---|---|---|
| `heuristic` | `balance` | MIS weights: Veach's balance or power (beta = 2) heuristic |
| `strategy` | `all` | `all`: every strategy, MIS-weighted. `s=K`: debug, each path length L by the one strategy s = min(K, L + 1) alone, unweighted (L = 0 always (0, 2)): every such image converges to the same answer (pbrt's "visualize strategies") |

The subpaths, their vertex records, the connections and the MIS weights are
renderer/kernels/subpaths.py (light tracing and MLT use them too).
"""

from __future__ import annotations

import numpy as np

from ..film import PartialFilm
from ..kernels import kernel
from ..kernels.camera import film_position, splat_add
from ..kernels.rng import sample_key, uniform
from ..kernels.sampling import BALANCE, POWER
from ..kernels.bsdf import MAT_DIFFUSE, MAT_GLOSSY
from ..kernels.subpaths import (
    V_ALB,
    V_MAT,
    V_NS,
    V_P,
    ALL_STRATEGIES,
    camera_subpath,
    conn0,
    connect,
    dims,
    light0,
    light_subpath,
    workspace,
)
from ..kernels.tile import (add_aov_block, add_aov_sample, add_block, add_sample, n_samples,
                            store_aov, store_pixel)
from ..registry import SAMPLERS, Method, Option
from ..samplers import u2d
from ..spec import BOUNDS
from .tile import start_tile


@kernel
def _camera_aovs(sc, V, nc):
    """A camera subpath's AOVs (film.py), as path tracing takes them: albedo
    and normal of its first diffuse or glossy vertex (through mirrors and
    glass; 0 if it reaches none), the distance to its first hit (0 for a miss)."""
    if nc < 2:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    dx, dy, dz = V[1, V_P] - V[0, V_P], V[1, V_P + 1] - V[0, V_P + 1], V[1, V_P + 2] - V[0, V_P + 2]
    dist = np.sqrt(dx * dx + dy * dy + dz * dz)
    for i in range(1, nc):
        mat = int(V[i, V_MAT])
        if mat >= 0 and (sc.mat_type[mat] == MAT_DIFFUSE or sc.mat_type[mat] == MAT_GLOSSY):
            return (V[i, V_ALB], V[i, V_ALB + 1], V[i, V_ALB + 2],
                    V[i, V_NS], V[i, V_NS + 1], V[i, V_NS + 2], dist)
    return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, dist


@kernel
def _render_tile(sc, cam, x0, y0, x1, y1, width, height, blocks, seed, depth, smp, spp,
                 heuristic, only_s, out_sum, out_sq, out_w, out_aov, scr, splat, u, V, stack,
                 memo):
    """BDPT over a tile's pixels and the sample blocks `blocks` (summed per
    block as in path.py, so tile films merge bit-identically); t = 1
    strategies add to the full-frame `splat`. A plain loop, no prange: two
    samples may splat to the same pixel. Returns the rays traced."""
    lrow = depth + 2
    srow = 2 * (depth + 2)
    l0 = light0(depth)
    c0 = conn0(depth)
    nd = u.shape[0]
    rays = 0
    n = n_samples(blocks)
    for y in range(y0, y1):
        for x in range(x0, x1):
            pixel = y * width + x
            ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for bi in range(blocks.shape[0]):
                sr, sg, sb, tr, tg, tb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                for si in range(blocks[bi, 0], blocks[bi, 1]):
                    key = sample_key(seed, pixel, si)
                    for d in range(0, l0, 2):
                        u[d], u[d + 1] = u2d(smp, key, seed, pixel, si, spp, d, memo)
                    for d in range(l0, nd):
                        u[d] = uniform(key, d)
                    fx, fy = film_position(cam, x, y, u[0], u[1])
                    nc, nr = camera_subpath(sc, cam, width, height, stack, V, fx, fy,
                                            depth + 2, u, 4)
                    # the camera ray's origin: a t = 1 strategy puts its own lens point there
                    c0x, c0y, c0z = V[0, 0], V[0, 1], V[0, 2]
                    rays += nr
                    alr, alg, alb, anx, any_, anz, dist = _camera_aovs(sc, V, nc)
                    add_aov_sample(scr, alr, alg, alb, anx, any_, anz, dist)
                    nl, nr = light_subpath(sc, stack, V, lrow, depth + 1, u, l0)
                    rays += nr
                    lr, lg, lb = 0.0, 0.0, 0.0
                    for t in range(1, nc + 1):
                        for s in range(0, nl + 1):
                            d = s + t - 2
                            if d < 0 or d > depth or (s == 1 and t == 1):
                                continue
                            if only_s >= 0:
                                want = 0 if d == 0 else min(only_s, d + 1)
                                if s != want:
                                    continue
                            r, g, b, fx, fy, nr = connect(sc, cam, width, height, stack, V, lrow,
                                                          srow, s, t, u, c0 + 4 * t, heuristic,
                                                          only_s < 0)
                            rays += nr
                            if t == 1:
                                V[0, 0], V[0, 1], V[0, 2] = c0x, c0y, c0z
                            if r == 0.0 and g == 0.0 and b == 0.0:
                                continue
                            if t == 1:
                                splat_add(splat, cam, fx, fy, r, g, b)
                            else:
                                lr += r
                                lg += g
                                lb += b
                    sr, sg, sb, tr, tg, tb = add_sample(sr, sg, sb, tr, tg, tb, lr, lg, lb)
                ar, ag, ab, qr, qg, qb = add_block(ar, ag, ab, qr, qg, qb,
                                                   sr, sg, sb, tr, tg, tb)
                add_aov_block(scr)
            store_pixel(out_sum, out_sq, out_w, y - y0, x - x0, ar, ag, ab, qr, qg, qb, n)
            store_aov(out_aov, y - y0, x - x0, scr)
    return rays


# The largest K of 's=K': a path of the deepest job has depth + 1 <= 65 light
# vertices, so s = min(K, length + 1) is the same strategy for every larger K;
# a K beyond an int64 failed in the kernel's typing on every attempt.
MAX_STRATEGY = BOUNDS["depth"][1] + 1


def _check_strategy(value) -> str | None:
    name, _, k = str(value).partition("=")
    # ASCII digits only: str.isdigit() also accepts '¹' and '²', which int() refuses
    if value == "all" or (name == "s" and k.isascii() and k.isdigit()
                          and len(k) <= 20 and int(k) <= MAX_STRATEGY):
        return None
    return (f"must be 'all' or 's=K' with K a whole number from 0 to {MAX_STRATEGY}, "
            f"got {str(value)[:40]!r}")


def _options(options: dict):
    heuristic = POWER if options.get("heuristic") == "power" else BALANCE
    strategy = options.get("strategy", "all")
    if strategy == "all":
        only_s = ALL_STRATEGIES
    else:
        problem = _check_strategy(strategy)
        if problem is not None:
            from ..errors import SpecError
            raise SpecError("options.strategy", problem)
        only_s = int(strategy.partition("=")[2])
    return heuristic, only_s


MIN_BATCHES = 8


def plan_bdpt(spec, progressive: bool = False, options: dict | None = None) -> list:
    """The tile plan (tiles x sample passes). Each unit's t = 1 splats are one
    batch, and a pixel's splat variance needs several batches: a job of fewer
    than MIN_BATCHES tiles is also cut into its sample blocks (1, 1, 2, 4, ...
    samples: the progressive passes), when spp allows."""
    from ..plan import plan

    units = plan(spec, progressive=progressive, small_passes=True)
    if len(units) < MIN_BATCHES and not progressive:
        units = plan(spec, progressive=True, small_passes=True)
    return units


def render_bdpt(scene, spec, unit, inputs, options) -> PartialFilm:
    """One tile unit of `bdpt`: its tile film plus its t = 1 splats as one batch
    (one light subpath per camera sample)."""
    heuristic, only_s = _options(options)
    t = start_tile(scene, spec, unit, aov=True)
    splat = np.zeros((spec.height, spec.width, 3))
    u = np.zeros(dims(spec.depth))
    V = workspace(spec.depth)
    rays = _render_tile(scene.arrays, t.cam, unit.x0, unit.y0, unit.x1, unit.y1, spec.width,
                        spec.height, t.blocks, spec.seed, spec.depth, SAMPLERS[spec.sampler].id,
                        spec.spp, heuristic, only_s, t.film.sum, t.film.sum_sq, t.film.weight,
                        t.film.aov, t.aov_rows[0], splat, u, V, t.stacks[0], t.memos[0])
    film = t.finish(unit, rays)
    film.with_splats(PartialFilm.splat_batch(splat, unit.samples))
    return film


METHODS = (Method(
    name="bdpt",
    aovs=("albedo", "normal", "depth"),
    description="Bidirectional path tracing: camera and light subpaths connected by every "
                "(s, t) strategy, combined by multiple importance sampling; t = 1 splats.",
    run=render_bdpt,
    options=(Option("heuristic", str, "balance", "MIS weights: balance or power (beta = 2) "
                    "heuristic", ("balance", "power")),
             Option("strategy", str, "all", "'all' (MIS) or debug 's=K' (K from 0 to "
                    f"{MAX_STRATEGY}): each path length by the single strategy s = min(K, "
                    "length + 1), unweighted",
                    check=_check_strategy)),
    family="splat",
    plan=plan_bdpt,
    phases=("tile",),
),)
