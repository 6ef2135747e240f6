"""`hammersley`: the Hammersley point set (i/N, radical inverse base 2 of i).

For N = spp: x_j = (j + delta) / N and y_j = RI_2(j) xor r, j = 0..N-1, where
delta in [0, 1) is one shift per (seed, pixel, pair) -- the points stay at the
same offset inside their 1/N columns, but the estimator is unbiased (with
delta = 0 every x sits at the left edge of its column) -- and r is a random
32-bit digital shift of y (a random permutation of every base-2 digit), which
keeps the net property. Sample i gets point j = perm(i), a hashed permutation
of [0, N), so different pairs are decorrelated.

Drives: every 2D pair, independent delta, r and permutation per (seed,
pixel, pair). spp: any N; for N = 2^m the points form a (0, m, 2)-net: one
point in every elementary interval 2^-a x 2^-b, a + b = m (tested). For other
N it is still Hammersley's set for that N. Indices past spp start a new,
independently scrambled block of N points.
"""

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import (INV_2_32, below_one, block_key, hash32, hash_u01, pair_key, permute,
                     reverse_bits32, split_block)

SAMPLER_HAMMERSLEY = 5

register_sampler(Sampler(
    "hammersley", SAMPLER_HAMMERSLEY,
    "Hammersley set (i/spp, base-2 radical inverse), digitally shifted per "
    "pixel; a (0,m,2)-net when spp = 2^m. Every 2D pair."))


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    b, i, n = split_block(index, spp, spp)
    key = block_key(pair_key(seed, pixel, pair, 5), b)
    j = permute(i, n, key)
    u = (j + hash_u01(key, 0)) / n
    v = float(reverse_bits32(j) ^ hash32(key, 1)) * INV_2_32
    return below_one(u), v
