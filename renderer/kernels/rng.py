"""A counter-based random number generator: u = hash(seed, pixel, sample, dim).

No state is carried between calls, so any sample of any pixel can be
replayed on its own, on any worker, in any order (DESIGN.md, determinism).
The mixer is SplitMix64's finalizer (Steele et al. 2014), applied in a chain:
`sample_key(seed, pixel, sample)` once per camera sample, then
`uniform(key, dim)` per dimension.
"""

import numpy as np

from . import kernel

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_K_PIXEL = np.uint64(0xD1B54A32D192ED03)
_K_SAMPLE = np.uint64(0x8CB92BA72F3D8DD7)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_INV_2_53 = 1.0 / 9007199254740992.0


@kernel
def mix64(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@kernel
def sample_key(seed, pixel, sample):
    """The key of one camera sample; `seed`, `pixel`, `sample` are integers."""
    k = mix64(np.uint64(seed) * _GOLDEN + _GOLDEN)
    k = mix64(k ^ (np.uint64(pixel) * _K_PIXEL))
    return mix64(k ^ (np.uint64(sample) * _K_SAMPLE))


@kernel
def uniform(key, dim):
    """A uniform float64 in [0, 1) for dimension `dim` of the sample `key`."""
    return float(mix64(key + np.uint64(dim) * _GOLDEN) >> _S11) * _INV_2_53


# Streams of random numbers that are not camera samples, each keyed by
# (seed, stream, index): light paths, photons, chains... never collide with
# each other or with camera samples (whose keys mix a pixel instead).
STREAM_LIGHT_PATHS, STREAM_PHOTONS, STREAM_CHAINS, STREAM_BOOTSTRAP, STREAM_RADIOSITY = 1, 2, 3, 4, 5
_K_STREAM = np.uint64(0xA24BAED4963EE407)


@kernel
def stream_key(seed, stream, index):
    """The key of path (photon, chain...) `index` of stream `stream`: use it
    with `uniform(key, dim)` like a camera sample's key."""
    k = mix64(np.uint64(seed) * _GOLDEN + _K_STREAM)
    k = mix64(k ^ (np.uint64(stream) * _K_PIXEL))
    return mix64(k ^ (np.uint64(index) * _K_SAMPLE))
