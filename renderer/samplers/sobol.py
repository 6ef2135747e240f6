"""`sobol`: padded, Owen-scrambled Sobol' (pbrt-v4's PaddedSobolSampler).

Every 2D pair uses Sobol' dimensions 0 and 1 (the (0, 2)-sequence: van der
Corput and its Pascal-matrix partner), so no direction-number table is needed
beyond those two. Each pair of each pixel gets
- its own sample order: sample i of a block of spp uses sequence index
  j = block * spp + perm(i), a hashed permutation of [0, spp) (pbrt's
  `PermutationElement`), which decorrelates the pairs ("padding");
- its own Owen scramble per coordinate, Burley's (2020) hash-based nested
  uniform scramble with the improved Laine-Karras hash pbrt-v4 uses
  (`FastOwenScrambler`). Owen scrambling keeps the net property and makes
  every point uniform on [0, 1)^2.

Drives: every 2D pair. spp: any; each pixel's points are the first spp of the
scrambled (0, 2)-sequence. For spp = 2^m they form a (0, m, 2)-net: one point
in every elementary interval 2^-a x 2^-b with a + b = m (tested); for other
spp the prefix is still well spread, the guarantee holds per power-of-two
block. 32-bit precision: indices are taken mod 2^32.
"""

import numpy as np

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import (INV_2_32, MASK32, U1, U16, U31, block_key, hash32, pair_key, permute,
                     reverse_bits32, split_block)

SAMPLER_SOBOL = 7
_TOP = np.uint64(1) << U31
_H1 = np.uint64(0x3D20ADEA)
_H2 = np.uint64(0x05526C56)
_H3 = np.uint64(0x53A22864)

register_sampler(Sampler(
    "sobol", SAMPLER_SOBOL,
    "Owen-scrambled Sobol' (0,2)-sequence, padded: every 2D pair with its own "
    "scramble and sample order (pbrt-v4 PaddedSobolSampler)."))


@kernel
def sobol_bits(j, d):
    """The 32-bit fraction of Sobol' dimension `d` (0 or 1) at index `j`."""
    bits = np.uint64(j) & MASK32
    if d == 0:
        return reverse_bits32(bits)
    x = np.uint64(0)
    v = _TOP
    while bits != 0:
        if bits & U1:
            x ^= v
        bits >>= U1
        v ^= v >> U1
    return x


@kernel
def owen_scramble(v, seed):
    """Nested uniform (Owen) scramble of the 32-bit fraction `v` (Burley 2020)."""
    s = np.uint64(seed) & MASK32
    x = reverse_bits32(v)
    x ^= (x * _H1) & MASK32
    x = (x + s) & MASK32
    x = (x * ((s >> U16) | U1)) & MASK32
    x ^= (x * _H2) & MASK32
    x ^= (x * _H3) & MASK32
    return reverse_bits32(x)


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    b, i, n = split_block(index, spp, spp)
    key = pair_key(seed, pixel, pair, 7)
    j = b * (spp if spp > 0 else 1) + permute(i, n, block_key(key, b))
    u = float(owen_scramble(sobol_bits(j, 0), hash32(key, 1))) * INV_2_32
    v = float(owen_scramble(sobol_bits(j, 1), hash32(key, 2))) * INV_2_32
    return u, v
