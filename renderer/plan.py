"""The job compiler: a pure function from render parameters to work units.

`plan(spec)` knows no database, no Celery and no scene contents: it cuts the
image into tiles (row-major) and the samples into passes. A unit is
identified by its index in the plan; everything a worker needs to run it is
in the unit itself plus the spec and the scene hash.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from .film import sample_blocks
from .spec import RenderSpec

__all__ = ["Unit", "plan"]


@dataclass(frozen=True)
class Unit:
    """One work unit: a tile [x0, x1) x [y0, y1) and the samples
    [sample_start, sample_end) of each of its pixels, in pass `pass_index`."""

    index: int
    x0: int
    y0: int
    x1: int
    y1: int
    sample_start: int
    sample_end: int
    pass_index: int = 0

    @property
    def pixels(self) -> int:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    @property
    def samples(self) -> int:
        return self.pixels * (self.sample_end - self.sample_start)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "Unit":
        return cls(**data)


def _tiles(width: int, height: int, tile: int) -> list[tuple[int, int, int, int]]:
    return [(x, y, min(x + tile, width), min(y + tile, height))
            for y in range(0, height, tile) for x in range(0, width, tile)]


def sample_passes(spp: int, progressive: bool) -> list[tuple[int, int]]:
    """Sample ranges of the passes: one pass with every sample, or (progressive)
    one pass per canonical sample block, so each pass doubles the samples."""
    if not progressive:
        return [(0, spp)]
    return sample_blocks(spp)


def plan(spec: RenderSpec, *, progressive: bool = False) -> list[Unit]:
    """Units of a tile-local job, pass-major: every tile of pass 0, then pass 1...

    >>> len(plan(RenderSpec(width=256, height=256, tile_size=64)))
    16
    """
    units: list[Unit] = []
    for p, (s0, s1) in enumerate(sample_passes(spec.spp, progressive)):
        for (x0, y0, x1, y1) in _tiles(spec.width, spec.height, spec.tile_size):
            units.append(Unit(len(units), x0, y0, x1, y1, s0, s1, p))
    return units
