"""`halton`: the Halton sequence in bases (2, 3), randomly digit-permuted.

x = RI_2(j) with every base-2 digit flipped at random (a 32-bit xor), y =
RI_3(j) with every base-3 digit (20 of them, 3^-20 ~ 3e-10) passed through a
random permutation of {0, 1, 2}, one per digit position (Faure-Tezuka style
random digit permutations; the trailing zero digits are permuted too, so the
points fill their boxes continuously). All scrambles are hashed from (seed,
pixel, pair), so each pixel and each pair has its own.

Drives: every 2D pair, each with bases (2, 3) and its own scramble; sample i
of a block of spp uses sequence index j = block * spp + perm(i), a hashed
permutation of [0, spp), so the pairs are decorrelated (as pbrt's padded
samplers do) while each pixel's spp points are still the first spp of the
sequence. spp: any, it is a sequence; for N = 2^a 3^b there is exactly one
point in every 2^-a x 3^-b box (tested).
"""

import numpy as np

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import INV_2_32, block_key, hash32, pair_key, permute, reverse_bits32, split_block

SAMPLER_HALTON = 6
DIGITS3 = 20
_POW3 = 3486784401.0  # 3^20
U21 = np.uint64(21)
# The six permutations of {0, 1, 2}; see digit_choices3 for which row a digit uses.
PERMS3 = np.array([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]],
                  dtype=np.int64)

register_sampler(Sampler(
    "halton", SAMPLER_HALTON,
    "Halton sequence in bases 2 and 3 with random digit permutations per "
    "pixel and per 2D pair."))


@kernel
def digit_choices3(key):
    """The digit permutations of scramble `key`, packed: digit k uses PERMS3 row
    (choices // 6^k) mod 6. One 53-bit hash holds all 20 (6^20 < 2^53)."""
    return np.int64((hash32(key, 999) << U21) ^ hash32(key, 998))  # 53 random bits


@kernel
def radical_inverse3(j, key):
    """RI_3(j) with the digit permutations of `key`, in [0, 1)."""
    choices = digit_choices3(key)
    acc = 0  # sum of permuted digits times 3^(DIGITS3 - 1 - k)
    for _ in range(DIGITS3):
        acc = acc * 3 + PERMS3[choices % 6, j % 3]
        choices //= 6
        j //= 3
    return acc / _POW3


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    b, i, n = split_block(index, spp, spp)
    key = pair_key(seed, pixel, pair, 6)
    j = b * (spp if spp > 0 else 1) + permute(i, n, block_key(key, b))
    u = float(reverse_bits32(j) ^ hash32(key, 1000)) * INV_2_32
    v = radical_inverse3(j, key)
    return u, v
