"""The one kernel entry point: `sample_2d` / `sample_1d` switch on the sampler id.

See the package docstring (renderer/samplers/__init__.py) for the contract.
"""

import numpy as np

from ..kernels import kernel, kernel_inline
from ..kernels.rng import uniform as hashed_uniform  # not the `uniform` sampler below
# Imported in id order: registration order is the order `GET /samplers` lists.
from . import random  # isort: skip
from . import uniform  # isort: skip
from . import jittered  # isort: skip
from . import nrooks  # isort: skip
from . import multijitter  # isort: skip
from . import hammersley  # isort: skip
from . import halton  # isort: skip
from . import sobol  # isort: skip
from . import bluenoise  # isort: skip

SAMPLER_RANDOM = random.SAMPLER_RANDOM
SAMPLER_UNIFORM = uniform.SAMPLER_UNIFORM
SAMPLER_JITTERED = jittered.SAMPLER_JITTERED
SAMPLER_NROOKS = nrooks.SAMPLER_NROOKS
SAMPLER_MULTIJITTER = multijitter.SAMPLER_MULTIJITTER
SAMPLER_HAMMERSLEY = hammersley.SAMPLER_HAMMERSLEY
SAMPLER_HALTON = halton.SAMPLER_HALTON
SAMPLER_SOBOL = sobol.SAMPLER_SOBOL
SAMPLER_BLUENOISE = bluenoise.SAMPLER_BLUENOISE

_random_pair = random.sample_pair
_uniform_pair = uniform.sample_pair
_jittered_pair = jittered.sample_pair
_nrooks_pair = nrooks.sample_pair
_multijitter_pair = multijitter.sample_pair
_hammersley_pair = hammersley.sample_pair
_halton_pair = halton.sample_pair
_sobol_pair = sobol.sample_pair
_sobol_pair_memo = sobol.sample_pair_memo
_bluenoise_pair = bluenoise.sample_pair


@kernel
def sample_pair(sampler_id, seed, pixel, index, spp, pair):
    """Dims (2*pair, 2*pair + 1) of sample `index` of `pixel`; unknown ids act as random."""
    if sampler_id == SAMPLER_SOBOL:
        return _sobol_pair(seed, pixel, index, spp, pair)
    if sampler_id == SAMPLER_HALTON:
        return _halton_pair(seed, pixel, index, spp, pair)
    if sampler_id == SAMPLER_MULTIJITTER:
        return _multijitter_pair(seed, pixel, index, spp, pair)
    if sampler_id == SAMPLER_JITTERED:
        return _jittered_pair(seed, pixel, index, spp, pair)
    if sampler_id == SAMPLER_BLUENOISE:
        return _bluenoise_pair(seed, pixel, index, spp, pair)
    if sampler_id == SAMPLER_HAMMERSLEY:
        return _hammersley_pair(seed, pixel, index, spp, pair)
    if sampler_id == SAMPLER_NROOKS:
        return _nrooks_pair(seed, pixel, index, spp, pair)
    if sampler_id == SAMPLER_UNIFORM:
        return _uniform_pair(seed, pixel, index, spp, pair)
    return _random_pair(seed, pixel, index, spp, pair)


@kernel
def sample_1d(sampler_id, seed, pixel, index, spp, dim):
    """Dimension `dim` of sample `index` of `pixel`: a float64 in [0, 1)."""
    u, v = sample_pair(sampler_id, seed, pixel, index, spp, dim >> 1)
    return v if dim & 1 else u


@kernel
def sample_2d(sampler_id, seed, pixel, index, spp, dim):
    """Dimensions (dim, dim + 1) of sample `index` of `pixel`: (u, v) in [0, 1)^2."""
    if dim & 1:  # an odd start straddles two pairs: read it as two 1D values
        return (sample_1d(sampler_id, seed, pixel, index, spp, dim),
                sample_1d(sampler_id, seed, pixel, index, spp, dim + 1))
    return sample_pair(sampler_id, seed, pixel, index, spp, dim >> 1)


@kernel
def fill_2d(sampler_id, seed, pixel, first, spp, dim, out):
    """out[k] = sample_2d(..., first + k, spp, dim) for k < len(out); for tests and tools."""
    for k in range(out.shape[0]):
        u, v = sample_2d(sampler_id, seed, pixel, first + k, spp, dim)
        out[k, 0] = u
        out[k, 1] = v


# The dimensions a path vertex draws, at 2 + DIMS_PER_BOUNCE * bounce + the
# offsets below: path tracing and the specular continuations of photon
# mapping and radiosity's display pass read the same ones. The light point's
# first number also picks the light and its triangle (kernels/lights.py: a
# pick from a dimension of its own broke the pair's stratification), so +4
# is unused; a diffuse vertex costs a stratified sampler three pair
# evaluations.
DIMS_PER_BOUNCE = 8
DIM_LIGHT = 0  # 2D: the point on the light, and which light
DIM_BSDF = 2  # 2D: the BSDF-sampled direction
DIM_RR = 5  # 1D: Russian roulette
DIM_GLASS = 6  # 1D: reflect or refract at glass
DIM_STRATEGY = 7  # 1D: one-sample MIS's choice of strategy
# 2D: the point on a thin lens, past every bounce's dimensions (depth <= 64):
# drawn only for a lens, so a pinhole's samples keep their dimensions.
DIM_LENS = 2 + DIMS_PER_BOUNCE * 65


# The memo argument of kernels that keep none (sample-major loops, where a
# pixel's memo would not pay): any array whose length is not 2 * spp. Pass it
# in as an argument: a global array read inside a kernel is frozen read-only.
NO_MEMO = np.zeros(0, np.int64)


@kernel_inline
def u1d(smp, key, seed, pixel, index, spp, dim, memo):
    """Dimension `dim` of the sample from sampler `smp` (`random` straight from
    the sample's precomputed hash key: the common case stays cheap). `memo`:
    the row's scratch for `sobol`'s pixel permutation (`sobol.sample_pair_memo`),
    or NO_MEMO."""
    if smp == SAMPLER_RANDOM:
        return hashed_uniform(key, dim)
    if smp == SAMPLER_SOBOL:
        u, v = _sobol_pair_memo(seed, pixel, index, spp, dim >> 1, memo)
        return v if dim & 1 else u
    return sample_1d(smp, seed, pixel, index, spp, dim)


@kernel_inline
def u2d(smp, key, seed, pixel, index, spp, dim, memo):
    """Dimensions (dim, dim + 1), dim even: one 2D pair of the sampler."""
    if smp == SAMPLER_RANDOM:
        return hashed_uniform(key, dim), hashed_uniform(key, dim + 1)
    if smp == SAMPLER_SOBOL:
        return _sobol_pair_memo(seed, pixel, index, spp, dim >> 1, memo)
    return sample_2d(smp, seed, pixel, index, spp, dim)


# A unit's memo stays under this. The entries layout takes 64 KiB per row at
# 1024 spp, the tables layout 31 entries per sample instead of 2 (249 KiB
# per row at 256 spp, 3.9 MiB at MEMO_MAX_SPP, with sobol.TABLE_PAIRS 29)
# and falls back to the entries layout above this. The tile kernels keep one
# row per Numba thread (integrators/tile.py), so their units fit up to 33
# threads even at MEMO_MAX_SPP (26 with 17 pair tables and half this
# budget, before 2026-11-29's third session); with one row per image row,
# as before 2026-11-29, a 256-row unit at 635 spp or a 64-row tile at 2048
# spp went over and took the slower entries layout (+17 % time). np.zeros
# takes such a block from the kernel as untouched zero pages: the memory a
# render uses is the banks it reaches, not the budget.
MEMO_MAX_BYTES = 128 << 20


def memo_rows(sampler_id: int, spp: int, rows: int,
              window: tuple[int, int] | None = None) -> np.ndarray:
    """Per-row scratch for u1d/u2d's memo: (rows, sobol.MEMO_BANKS banks of
    sobol.memo_bank_width(spp, tables)) for `sobol` with spp up to
    sobol.MEMO_MAX_SPP and within MEMO_MAX_BYTES (tags start at 0, which no
    entry uses), else (rows, 0), no memo. `window` (lo, hi), for a kernel
    that draws only the samples [lo, hi) of each pixel, each pixel's in
    order, the film pair first (the tile kernels), asks for the layout with
    pair tables (over the window's positions only: sobol.mark_window),
    which falls back to the entries layout above the budget. The memo
    changes no value, only the time."""
    tables = window is not None
    layouts = ((True, False) if tables else (False,)) \
        if sampler_id == SAMPLER_SOBOL and spp <= sobol.MEMO_MAX_SPP else ()
    widths = [sobol.MEMO_BANKS * sobol.memo_bank_width(spp, layout) for layout in layouts]
    width = next((w for w in widths if rows * w * 8 <= MEMO_MAX_BYTES), 0)
    memos = np.zeros((rows, width), np.int64)
    if tables and width and width == widths[0]:
        sobol.mark_window(memos, spp, *window)
    return memos
