"""`uniform`: the regular grid of cell centres, the same in every pixel.

The slides' first sampler: it keeps aliasing (jaggies, moire) because every
pixel sees the same pattern; useful to show why the others exist.

Drives: only pair 0 (dims 0-1, the position inside the pixel). Every other
dimension falls back to `random` -- a deterministic grid of bounce directions
would bias the estimate, not just alias it.

spp: an nx x ny grid with nx = floor(sqrt(spp)), ny = ceil(spp / nx);
sample i sits at the centre of cell (i mod nx, i div nx), row-major, so for
spp not square the top row is partly empty. Sample indices past spp repeat
the grid.
"""

from ..kernels import kernel
from ..registry import Sampler, register_sampler
from .common import isqrt, random_pair, split_block

SAMPLER_UNIFORM = 1

register_sampler(Sampler(
    "uniform", SAMPLER_UNIFORM,
    "Regular grid of cell centres, identical in every pixel (aliases; a "
    "teaching baseline). Drives the image plane; other dimensions are random."))


@kernel
def sample_pair(seed, pixel, index, spp, pair):
    if pair != 0:
        return random_pair(seed, pixel, index, pair)
    _, i, n = split_block(index, spp, spp)
    nx = isqrt(n)
    ny = (n + nx - 1) // nx
    return ((i % nx) + 0.5) / nx, ((i // nx) + 0.5) / ny
