"""`random`: independent uniform numbers, u = hash(seed, pixel, sample, dim).

Drives every dimension; any spp. Bit-identical to the integrators' original
`uniform(sample_key(seed, pixel, sample), dim)`, so renders made before the
sampler library existed keep their bytes. It is also the fallback the other
samplers use for dimensions their construction does not cover.
"""

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import random_pair

SAMPLER_RANDOM = 0

register_sampler(Sampler(
    "random", SAMPLER_RANDOM,
    "Independent uniform random numbers from a counter-based hash of "
    "(seed, pixel, sample, dimension)."))


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    return random_pair(seed, pixel, index, pair)
