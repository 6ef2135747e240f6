"""What every tile-rendering integrator shares: the tile plan and the
canonical sample blocks of a unit (the film contract, renderer/film.py: a
pixel's sums are formed per block, so any tiling and any retry give the same
bytes)."""

from __future__ import annotations

import numpy as np

from ..film import sample_blocks
from ..plan import plan

__all__ = ["tile_plan", "unit_blocks"]


def tile_plan(spec, progressive: bool = False, options: dict | None = None) -> list:
    """A tile method's units: image tiles x sample passes (`renderer.plan.plan`)."""
    return plan(spec, progressive=progressive)


def unit_blocks(spp: int, sample_start: int, sample_end: int) -> np.ndarray:
    """The canonical sample blocks a unit's sample range covers (must align)."""
    blocks = [b for b in sample_blocks(spp) if sample_start <= b[0] and b[1] <= sample_end]
    if sum(e - s for s, e in blocks) != sample_end - sample_start:
        raise ValueError(f"sample range [{sample_start}, {sample_end}) does not align "
                         "with the canonical sample blocks")
    return np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
