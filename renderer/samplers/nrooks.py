"""`nrooks`: N-rooks (Latin hypercube) sampling.

Each of the spp columns and each of the spp rows of the spp x spp grid holds
exactly one sample: x stratum = perm_x(i), y stratum = perm_y(i), two
independent hashed permutations, plus a uniform jitter inside the cell.
The slides' "shuffle until the rooks condition holds" is replaced by drawing
the permutations directly (Kensler's hashed permute), so it always ends.

Drives: every 2D pair, with independent permutations per (seed, pixel, pair).
spp: any; the rook property holds for every spp. Indices past spp start a
new, independently scrambled block.
"""

import numpy as np

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import below_one, block_key, hash_u01, pair_key, permute, split_block

SAMPLER_NROOKS = 3
_SALT_X = np.uint64(0x5851F42D)
_SALT_Y = np.uint64(0x14057B7E)

register_sampler(Sampler(
    "nrooks", SAMPLER_NROOKS,
    "N-rooks (Latin hypercube): one sample in every row and every column of "
    "the spp x spp grid, for every 2D pair."))


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    b, i, n = split_block(index, spp, spp)
    key = block_key(pair_key(seed, pixel, pair, 3), b)
    kx = key ^ _SALT_X
    ky = key ^ _SALT_Y
    u = (permute(i, n, kx) + hash_u01(key, 2 * i)) / n
    v = (permute(i, n, ky) + hash_u01(key, 2 * i + 1)) / n
    return below_one(u), below_one(v)
