"""The tile loop's shared pieces: every tile-rendering integrator (path
family, BDPT's tile part, radiosity's display, photon mapping's k-NN pass)
keeps only its `prange` shell and its radiance estimate; the plan, the
canonical sample blocks and the Python side (film, camera, scratch, stats)
are here, once, and the per-pixel fold and the film store are the inline
kernels of renderer/kernels/tile.py.

The film contract (renderer/film.py): a pixel's sums of values and of
squares are formed per canonical sample block, the blocks then added in
order, so any tiling and any retry give the same bytes. A kernel's loop:

    for x in range(x0, x1):
        ar, ag, ab, qr, qg, qb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for bi in range(blocks.shape[0]):
            sr, sg, sb, tr, tg, tb = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for s in range(blocks[bi, 0], blocks[bi, 1]):
                r, g, b = ...                                  # the integrator's Li
                sr, sg, sb, tr, tg, tb = add_sample(sr, sg, sb, tr, tg, tb, r, g, b)
            ar, ag, ab, qr, qg, qb = add_block(ar, ag, ab, qr, qg, qb, sr, sg, sb, tr, tg, tb)
        store_pixel(out_sum, out_sq, out_w, row, x - x0, ar, ag, ab, qr, qg, qb, n_samples(blocks))

The path family traces a row's samples as packets of paths (integrators/
path.py): its samples finish out of order, wait in a per-row ring, and are
folded in this order by the same inline kernels.

Numba's on-disk cache cannot keep a kernel that takes another jitted
function as an argument (numba issues 2956, 2065), so there is no
higher-order loop: each integrator has its own module-level kernel over
these inline helpers, which compile to the same instructions as the loop
written out (bit-identical films).

The rows of a unit go to Numba's threads in equal contiguous shares (the
OpenMP layer's static schedule). Measured on 2026-11-27 (AMD EPYC, 2
threads, 256x256, 32 spp): smaller dynamic shares (numba.set_parallel_
chunksize 1 or 8) made no difference on cornell-box or veach-mis; their
halves cost about the same (cornell-box 1.32 s and 1.29 s on one thread).
Again with roulette 2 (Zen 5, 64 spp): the halves 1.09 s and 1.05 s on
one thread, the whole 2.17 s on one thread and 1.13 s on two; chunksize 1
or 4, or rows dealt out across the image (row = i x stride mod h, the
same film bytes): no difference beyond the noise of 3 %. What two threads
lose against two processes (1.91x against 1.98x in bench/throughput.py's
scaling) is not the rows' shares.

Compile time. Numba's parfor passes (fusion, prelowering, the gufunc's
lowering) run over everything inside a `prange` body, inlined helpers
included: for radiosity's display they were 28 of the 47 s its kernel took
to compile (Zen 5, cold cache; type inference and inlining most of the
rest). So radiosity's display and photon mapping's camera and k-NN passes
keep only the `prange` shell and call a row kernel of their own
(`_display_row`, `_camera_row`, `_knn_row`; the row passed as np.int64:
the parfor types its index uint64 in one compile and int64 in another,
which compiled the row kernel twice). Measured 2026-11-28 (AMD EPYC Zen 5,
every method warmed in one process on a cold cache): photon 45.4 -> 30.7 s,
radiosity 50.8 -> 36.8 s, all methods 198 -> 172 s; the films the same
bytes; photon maps 2-3 % faster, radiosity's display with final gather
29 % faster (0.110 -> 0.078 s, cornell-box 128x128, 16 spp, one thread).
Not done for the path tracer: as a row kernel it compiled in 44 s instead
of 58, but cornell-box at 64 spp rendered 10.6 % slower (2.23 s against
2.02 s, the same bytes) and veach-mis 5 % slower; the cause is in what
LLVM makes of the two contexts and was not found.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from ..film import AOV_CHANNELS, PartialFilm, sample_blocks
from ..kernels.geometry import STACK_SIZE
from ..plan import plan
from ..registry import SAMPLERS
from ..samplers import memo_rows
from ..scene import camera_array

__all__ = ["tile_plan", "unit_blocks", "TileRun", "start_tile"]


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


class TileRun(NamedTuple):
    """What a tile kernel is handed for one unit (`start_tile`): the unit's
    zeroed film, its canonical sample blocks, the camera, and per-row scratch
    (rays traced per row, a BVH traversal stack per row, the sampler's memo
    per Numba thread, samplers.memo_rows; the AOV fold's sums per row, kernels/tile.py:
    kernels allocate nothing)."""

    film: PartialFilm
    blocks: np.ndarray
    cam: np.ndarray
    row_rays: np.ndarray
    stacks: np.ndarray
    memos: np.ndarray
    aov_rows: np.ndarray

    def finish(self, unit, rays: int | None = None) -> PartialFilm:
        """The film with its stats (samples, rays: the rows' sum unless given)."""
        self.film.stats.update(samples=unit.samples,
                               rays=int(self.row_rays.sum() if rays is None else rays))
        return self.film


def start_tile(scene, spec, unit, aov: bool = False) -> TileRun:
    """The unit's TileRun; with `aov`, its film sums the AOVs (film.py) too.
    The tile kernels draw each pixel's samples in order, the film pair
    first, and none outside the unit's samples, so the sampler's memo
    takes the layout with pair tables over the unit's window of samples
    (samplers.memo_rows).

    The memo is one row per Numba thread, not per image row: a thread
    renders one row at a time, and the memo's tags name the pixel and block
    of every entry, so a row never reads another's (samplers/sobol.py).
    With a row each, a unit of 256 rows at 635 spp, or of 64 rows at 2048
    spp, went over the memo's budget and fell back to the slower entries
    layout: cornell-box's whole frame as one unit at 635 spp took 23.5 s on
    one thread, its two halves 20.1 s (2026-11-29, AMD EPYC Zen 5)."""
    w, h = unit.x1 - unit.x0, unit.y1 - unit.y0
    return TileRun(PartialFilm.zeros(unit.x0, unit.y0, w, h, aov=aov),
                   unit_blocks(spec.spp, unit.sample_start, unit.sample_end),
                   camera_array(scene.camera, spec.width, spec.height),
                   np.zeros(h, np.int64), np.empty((h, STACK_SIZE), np.int64),
                   memo_rows(SAMPLERS[spec.sampler].id, spec.spp, numba.get_num_threads(),
                             (unit.sample_start, unit.sample_end)),
                   np.zeros((h, 2 * AOV_CHANNELS)))
