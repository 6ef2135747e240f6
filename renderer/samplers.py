"""Pixel samplers, registered by name; kernels switch on `Sampler.id`.

Every sampler is a pure function of (seed, pixel, sample index, dimension),
so a pixel's samples do not depend on which unit renders it (tiling
invariance) and any sample can be replayed alone.
"""

from .registry import Sampler, register_sampler

SAMPLER_RANDOM = 0

register_sampler(Sampler(
    "random", SAMPLER_RANDOM,
    "Independent uniform random numbers from a counter-based hash of "
    "(seed, pixel, sample, dimension)."))
