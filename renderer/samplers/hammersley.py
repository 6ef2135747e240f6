"""`hammersley`: the Hammersley point set (i/N, radical inverse base 2 of i).

For N = spp and j = 0..N-1: y_j = RI_2(j) xor r, with r a random 32-bit
digital shift per (seed, pixel, pair) (a random permutation of every base-2
digit, which keeps the net property), and

- in the image plane (pair 0, dims 0-1): x_j = j / N exactly, the lecture's
  set. Deterministic in x, so the pixel estimate is *biased*: every x sits at
  the left edge of its 1/N column, which shifts the box filter by -1/(2N)
  of a pixel on average. Consistent: the bias vanishes as 1/N (tested).
- in every later pair: x_j = (j + delta) / N with one shift delta per
  (seed, pixel, pair), so the path's decisions (light points, directions,
  Russian roulette) stay unbiased.

Sample i gets point j = perm(i), a hashed permutation of [0, N), so
different pairs are decorrelated.

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
    "pixel; a (0,m,2)-net when spp = 2^m. Every 2D pair; x = i/spp exactly in "
    "the image plane (biased, consistent), shifted in later pairs."))


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    b, i, n = split_block(index, spp, spp)
    key = block_key(pair_key(seed, pixel, pair, 5), b)
    j = permute(i, n, key)
    u = (j + (hash_u01(key, 0) if pair > 0 else 0.0)) / n
    v = float(reverse_bits32(j) ^ hash32(key, 1)) * INV_2_32
    return below_one(u), v
