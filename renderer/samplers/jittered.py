"""`jittered`: stratified sampling, one uniform point in each grid cell.

Drives: every 2D pair, each with its own per-(seed, pixel, pair) cell
assignment and jitter, so pairs are not correlated with each other.

spp: an nx x ny grid with nx = floor(sqrt(spp)), ny = ceil(spp / nx). The
spp samples go to spp *distinct* cells chosen by a hashed permutation of the
nx*ny cells; for square spp that is every cell exactly once. For spp not
square some cells stay empty, but which ones is random per pixel and pair,
so every sample is still uniform over the pixel (unbiased). Tested property:
never two samples in one cell; exactly one per cell when spp is square.
Indices past spp start a new, independently scrambled block of spp samples.
"""

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import below_one, block_key, hash_u01, isqrt, pair_key, permute, split_block

SAMPLER_JITTERED = 2

register_sampler(Sampler(
    "jittered", SAMPLER_JITTERED,
    "Stratified: one random point per cell of a sqrt(spp) x sqrt(spp) grid, "
    "for every 2D pair."))


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    b, i, n = split_block(index, spp, spp)
    key = block_key(pair_key(seed, pixel, pair, 2), b)
    nx = isqrt(n)
    ny = (n + nx - 1) // nx
    cell = permute(i, nx * ny, key)
    u = ((cell % nx) + hash_u01(key, 2 * i)) / nx
    v = ((cell // nx) + hash_u01(key, 2 * i + 1)) / ny
    return below_one(u), below_one(v)
