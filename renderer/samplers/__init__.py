"""Pixel samplers: registered by name, one module each; kernels switch on `Sampler.id`.

The integrators call one kernel (compiled with `kernel`, allocating nothing)::

    from renderer.samplers import sample_1d, sample_2d
    u, v = sample_2d(sampler_id, seed, pixel, index, spp, dim)   # two float64 in [0, 1)
    u = sample_1d(sampler_id, seed, pixel, index, spp, dim)      # one float64 in [0, 1)

- `sampler_id`: `SAMPLERS[name].id` (int64), see the table below; unknown ids act as random.
- `seed`: the job seed; `pixel`: the linear pixel index (y * width + x);
- `index`: the sample index in [0, spp) (indices >= spp continue in new,
  independently scrambled blocks, for progressive rendering);
- `spp`: the job's samples per pixel (the same for every call of a job:
  stratified samplers build their pattern from it);
- `dim`: the dimension. 2D pairs start at even dims: dims 0-1 are the
  position inside the pixel, then the integrator's per-bounce pairs (e.g.
  bounce b uses dims 2 + 2k .. for its k-th pair). `sample_1d(dim)` is
  component `dim & 1` of the pair starting at `dim & ~1`, so 1D and 2D
  reads of the same dims agree; `sample_2d` at an odd dim returns
  `(sample_1d(dim), sample_1d(dim + 1))`. Give a 2D decision (a direction,
  a point on a light) an even dim so it gets the sampler's 2D stratification.

Every value is a pure function of (sampler_id, seed, pixel, index, spp, dim):
no state, nothing depends on which other samples are drawn, so tiles,
retries and single-sample replays give identical values (DESIGN.md,
determinism). `random` is bit-identical to the former
`uniform(sample_key(seed, pixel, index), dim)`.

| id | name          | drives                       | construction                          |
|----|---------------|------------------------------|---------------------------------------|
| 0  | `random`      | every dim                    | counter-based hash                    |
| 1  | `uniform`     | pair 0 only (rest: random)   | cell centres of a grid, same per pixel|
| 2  | `jittered`    | every pair                   | one point per grid cell               |
| 3  | `nrooks`      | every pair                   | Latin hypercube                       |
| 4  | `multijitter` | every pair                   | correlated multi-jittered (Kensler)   |
| 5  | `hammersley`  | every pair                   | Hammersley set, digitally shifted     |
| 6  | `halton`      | every pair                   | Halton (2, 3), random digit perms     |
| 7  | `sobol`       | every pair                   | padded Owen-scrambled Sobol' (0,2)    |
| 8  | `bluenoise`   | every pair                   | best-candidate table, toroidal shift  |

Each module's docstring says what happens when spp is not a square or a
power of two. Every pair of every pixel has its own scrambles, hashed from
(seed, pixel, pair). `points(name, seed, pixel, spp, dim)` is the plain-Python
wrapper returning one pixel's (spp, 2) points; `naive` holds slow,
obviously correct references.
"""

from __future__ import annotations

import numpy as np


# Numba's stale-cache guard for these modules lives with the others in
# renderer/kernels/__init__.py (imported by every sampler module first).
from .dispatch import (DIM_BSDF, DIM_GLASS, DIM_LENS, DIM_LIGHT, DIM_RR, DIM_STRATEGY,
                       DIMS_PER_BOUNCE, SAMPLER_BLUENOISE, SAMPLER_HALTON, SAMPLER_HAMMERSLEY,
                       SAMPLER_JITTERED, SAMPLER_MULTIJITTER, SAMPLER_NROOKS, SAMPLER_RANDOM,
                       SAMPLER_SOBOL, SAMPLER_UNIFORM, NO_MEMO, fill_2d, memo_rows, sample_1d,
                       sample_2d, u1d, u2d)

__all__ = ["DIM_BSDF", "DIM_GLASS", "DIM_LENS", "DIM_LIGHT", "DIM_RR", "DIM_STRATEGY",
           "DIMS_PER_BOUNCE", "SAMPLER_BLUENOISE", "SAMPLER_HALTON", "SAMPLER_HAMMERSLEY", "SAMPLER_JITTERED",
           "SAMPLER_MULTIJITTER", "SAMPLER_NROOKS", "SAMPLER_RANDOM", "SAMPLER_SOBOL",
           "SAMPLER_UNIFORM", "NO_MEMO", "fill_2d", "memo_rows", "points", "sample_1d", "sample_2d", "u1d", "u2d"]


def points(name: str, seed: int, pixel: int, spp: int, dim: int = 0,
           first: int = 0, count: int | None = None) -> np.ndarray:
    """One pixel's samples of sampler `name` at dims (dim, dim + 1): shape (count, 2).

    >>> points("sobol", seed=7, pixel=0, spp=4).shape
    (4, 2)
    """
    from ..registry import SAMPLERS
    if name not in SAMPLERS:
        raise ValueError(f"unknown sampler {name!r} (allowed: {', '.join(SAMPLERS)})")
    if spp < 1 or dim < 0 or first < 0:
        raise ValueError("spp must be >= 1, dim and first >= 0")
    out = np.empty((spp if count is None else count, 2))
    fill_2d(SAMPLERS[name].id, seed, pixel, first, spp, dim, out)
    return out
