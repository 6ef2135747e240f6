"""`multijitter`: correlated multi-jittered sampling (Kensler 2013).

Jittered and N-rooks at once: one sample per cell of the m x n grid and one
per column and row of the fine (m*n) x (m*n) grid, with Kensler's shuffles
(one permutation of the sub-columns shared by all the cells of a column, one
of the sub-rows shared by a row -- the "correlated" variant, which has lower
variance than independent shuffles).

Drives: every 2D pair, with independent shuffles per (seed, pixel, pair).
spp: m = floor(sqrt(spp)), n = ceil(spp / m). The spp samples are spp
distinct points of the full m*n pattern, chosen by a hashed permutation of
[0, m*n), so every sample stays uniform over the pixel (Kensler's paper takes
the first spp instead, which leaves the top row short). Tested property:
never two samples in a cell, a fine row or a fine column; exactly one in each
when spp is square. Indices past spp start a new, independently shuffled block.
"""

import numpy as np

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import below_one, block_key, hash_u01, isqrt, pair_key, permute, split_block

SAMPLER_MULTIJITTER = 4
_SALT_S = np.uint64(0x51633E2D)
_SALT_X = np.uint64(0xA511E9B3)
_SALT_Y = np.uint64(0x63D83595)

register_sampler(Sampler(
    "multijitter", SAMPLER_MULTIJITTER,
    "Correlated multi-jittered (Kensler 2013): jittered and N-rooks at once, "
    "for every 2D pair."))


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    b, i, count = split_block(index, spp, spp)
    key = block_key(pair_key(seed, pixel, pair, 4), b)
    m = isqrt(count)
    n = (count + m - 1) // m
    s = permute(i, m * n, key ^ _SALT_S)
    col = s % m
    row = s // m
    sx = permute(col, m, key ^ _SALT_X)
    sy = permute(row, n, key ^ _SALT_Y)
    u = (col + (sy + hash_u01(key, 2 * s)) / n) / m
    v = (row + (sx + hash_u01(key, 2 * s + 1)) / m) / n
    return below_one(u), below_one(v)
