"""The job compiler: a pure function from render parameters to work units.

`plan(spec)` knows no database, no Celery and no scene contents: it cuts the
image into tiles (row-major) and the samples into passes. A unit is
identified by its index in the plan; everything a worker needs to run it is
in the unit itself, the spec, the scene hash and the results of the units it
`needs`.

Methods whose work is not "one tile, one pixel" (light tracing, BDPT, MLT,
photon mapping, radiosity) plan a small DAG instead (`Method.plan`): every
unit has a `stage` and the indices of the earlier units whose results it
reads (`needs`: a photon map, a bootstrap normalisation, a radiosity
solution, the previous iteration's pixel statistics). A unit may run once all
of its needs are done; units are listed in stage order, so unit order is a
topological order. `kind` names the unit's role for its method and for the
dashboard's phases ("tile", "splat", "bootstrap", "chains", "photons",
"gather", "solve", ...). For units that are not tiles, `sample_start` and
`sample_end` are a range of path (or chain, or photon) indices and the
region is the part of the frame the unit's film covers (the whole frame for
splatting units, nothing for a pure prepass).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from .film import sample_blocks
from .spec import RenderSpec

__all__ = ["Unit", "plan", "count_units", "largest_unit"]


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
    stage: int = 0  # DAG stage (0 for every unit of a tile job)
    kind: str = "tile"  # the unit's role for its method (see the module doc)
    needs: tuple[int, ...] = ()  # indices of the units whose results this one reads

    @property
    def pixels(self) -> int:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    @property
    def samples(self) -> int:
        """Camera samples of a tile unit; for other kinds the methods report
        their own count in the film's stats."""
        return self.pixels * (self.sample_end - self.sample_start)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["needs"] = list(self.needs)
        return d

    @classmethod
    def from_dict(cls, data: dict) -> "Unit":
        data = dict(data)
        data["needs"] = tuple(data.get("needs", ()))
        return cls(**data)


def _tiles(width: int, height: int, tile: int) -> list[tuple[int, int, int, int]]:
    return [(x, y, min(x + tile, width), min(y + tile, height))
            for y in range(0, height, tile) for x in range(0, width, tile)]


# The camera samples a tile renders in a progressive job's first pass, at
# least: about 25 ms on one core. Each landed unit costs the service a
# scheduler tick (about 10 ms of CPU on the 2-core machine: its rows, its film
# stored and fsynced, its events), and a first pass of one sample on 64 x 64
# tiles renders in 3 ms: with passes of 1, 1, 2, 4, ... samples the service,
# not the render processes, set the pace of the first passes. The floor
# takes a 390-spp job on 64-pixel tiles from 208 units to 160.
MIN_PASS_SAMPLES = 1 << 15


def sample_passes(spp: int, progressive: bool, tile_pixels: int = 0) -> list[tuple[int, int]]:
    """Sample ranges of the passes: one pass with every sample, or (progressive)
    one pass per canonical sample block, so each pass doubles the samples.

    With `tile_pixels` (> 0), a progressive job's first pass takes the leading
    blocks until a tile of that many pixels renders `MIN_PASS_SAMPLES` in it,
    but no more than a quarter of spp (a job still shows passes). Pass
    boundaries are block boundaries, so the image's bytes do not change.

    >>> sample_passes(64, True)[:4]
    [(0, 1), (1, 2), (2, 4), (4, 8)]
    >>> sample_passes(64, True, tile_pixels=64 * 64)
    [(0, 8), (8, 16), (16, 32), (32, 64)]
    """
    if not progressive:
        return [(0, spp)]
    blocks = sample_blocks(spp)
    first = 1  # blocks the first pass takes
    while (first < len(blocks) and 0 < tile_pixels * blocks[first - 1][1] < MIN_PASS_SAMPLES
           and blocks[first][1] <= spp // 4):
        first += 1
    return [(0, blocks[first - 1][1])] + blocks[first:]


# The camera samples a progressive pass's unit renders, at least: 0.4 s on
# one core of the 2-core AVX-512 machine, 0.5 s on the AVX2 one. A unit costs
# the service the same whatever it holds (its rows, its film stored and
# fsynced, its events: 4-5 ms of CPU there), and the render processes wait
# for that CPU on a machine whose cores they use; a progressive job's passes
# hold at most 64 samples per pixel (sample_blocks), so a pass groups
# adjacent tiles into one unit: along a row of tiles, then whole rows. A
# 382-spp job of 64-pixel tiles on 256 x 256 pixels has 48 units (112 at
# 2^17: its service took 0.77 s of CPU at 2^19 instead of 1.00 s). Grouping
# changes no byte of the image: every pixel renders the same sample blocks
# in the same order, whatever unit it is in. Units stay well below a second,
# so fair share (service.fairshare) still switches jobs often.
#
# A progressive job costs more than a one-pass job with the same tiles:
# +6.2 +- 1.6 % in a pool of 2 on Zen 3 (2026-11-28, 176 spp, 10 pairs),
# on Zen 5 +13 to +19 % on one thread, on an Intel Xeon +14 %. The cause was
# the `sobol` sampler's memo: its pair tables took whole blocks of spp
# samples, so a pass's units went with the slower entries layout; with
# `random` a progressive job cost what one pass does (-1 to +0 %). Since the
# tables take the unit's window of samples (samplers/sobol.py "Windows"),
# the Intel Xeon measures +4 % on one thread (176 spp, five pairs of
# processes). Not the row queues' drain either: these units' rows hold 2048
# samples or more, where the path kernel's note measures it at about 1 %.
MIN_UNIT_SAMPLES = 1 << 19


def _group_shape(across: int, per_tile: int) -> tuple[int, int]:
    """(tiles along a row, rows of tiles) of a pass's units when a tile holds
    `per_tile` samples and a row `across` tiles: (1, 1) if a tile holds
    `MIN_UNIT_SAMPLES`; else runs of tiles along a row that do, or, if a whole
    row does not, bands of whole rows that do."""
    group = max(1, -(-MIN_UNIT_SAMPLES // max(per_tile, 1)))  # tiles per unit
    if group < across:
        return group, 1
    return across, -(-group // across)


def _tile_groups(width: int, height: int, tile: int, per_tile: int
                 ) -> list[tuple[int, int, int, int]]:
    """A pass's unit regions, row-major (`_group_shape`; the last run of a row
    and the last band may be shorter)."""
    run, rows = _group_shape(-(-width // tile), per_tile)
    xs, ys = run * tile, rows * tile
    return [(x, y, min(x + xs, width), min(y + ys, height))
            for y in range(0, height, ys) for x in range(0, width, xs)]


def tile_pixels(spec: RenderSpec) -> int:
    """Pixels of the job's full tile (what `sample_passes` sizes the first pass by)."""
    return min(spec.tile_size, spec.width) * min(spec.tile_size, spec.height)


def plan(spec: RenderSpec, *, progressive: bool = False, small_passes: bool = False) -> list[Unit]:
    """Units of a tile-local job, pass-major: every tile of pass 0, then pass 1...
    (`small_passes`: every canonical block its own pass, however few samples
    it holds, for a method that wants many units).

    >>> len(plan(RenderSpec(width=256, height=256, tile_size=64)))
    16
    """
    units: list[Unit] = []
    pixels = 0 if small_passes else tile_pixels(spec)
    for p, (s0, s1) in enumerate(sample_passes(spec.spp, progressive, pixels)):
        regions = (_tile_groups(spec.width, spec.height, spec.tile_size, pixels * (s1 - s0))
                   if progressive and pixels else _tiles(spec.width, spec.height, spec.tile_size))
        for (x0, y0, x1, y1) in regions:
            units.append(Unit(len(units), x0, y0, x1, y1, s0, s1, p))
    return units


def count_units(spec: RenderSpec, progressive: bool = False, small_passes: bool = False) -> int:
    """len(plan(spec, progressive=progressive, small_passes=small_passes)),
    without building the units (admission refuses a plan of millions of
    units on this)."""
    across = -(-spec.width // spec.tile_size)
    down = -(-spec.height // spec.tile_size)
    if small_passes:
        return across * down * len(sample_passes(spec.spp, progressive))
    pixels = tile_pixels(spec)
    total = 0
    for s0, s1 in sample_passes(spec.spp, progressive, pixels):
        run, rows = _group_shape(across, pixels * (s1 - s0)) if progressive else (1, 1)
        total += -(-across // run) * -(-down // rows)
    return total


def largest_unit(spec: RenderSpec, progressive: bool = False,
                 small_passes: bool = False) -> tuple[int, int]:
    """(max(u.pixels), max(u.y1 - u.y0)) over plan(spec, ...), without
    building the units (renderer/memory.py sizes a unit's film by them)."""
    across = -(-spec.width // spec.tile_size)
    tile_w, tile_h = min(spec.tile_size, spec.width), min(spec.tile_size, spec.height)
    pixels = 0 if small_passes else tile_pixels(spec)
    largest, tallest = tile_w * tile_h, tile_h
    if progressive and pixels:
        for s0, s1 in sample_passes(spec.spp, progressive, pixels):
            run, rows = _group_shape(across, pixels * (s1 - s0))
            height = min(rows * spec.tile_size, spec.height)
            largest = max(largest, min(run * spec.tile_size, spec.width) * height)
            tallest = max(tallest, height)
    return largest, tallest
