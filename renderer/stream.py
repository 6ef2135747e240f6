"""The merge of a job's stored unit films, band by band: the finished frame's
files without the frame's float64 sums in memory.

    images = merge_frame(256, 256, [store / "units" / f"{i}.film" for i in range(16)],
                         tile=64, preview=True, noise=True)
    write_exr("result.exr", images.channels, metadata)

`film.merge` adds every unit's film into whole-frame float64 arrays (sums,
squares, weights, AOVs, splats: 56 to 300 bytes a pixel) and the images
are made from those. Here the frame is made one band of rows at a time
(`images.frame_bands`): a band's sums are the units' rows in it added in unit
order, exactly as `Film.add` adds them (camera tiles at their region, splat
batches over the whole frame), then `FrameImages` turns the band into its
rows of the channels, the PNGs and the error statistic, and the band is
dropped. Every value is per pixel and its additions come in the same order,
so the channels, the images and `rel_error` are the whole-frame merge's, bit
for bit (tests/test_renderer_stream.py). A unit's film is read from its file
as the rows a band needs (`StoredFilm`): only its header is read up front.

What stays whole is what the files are made of: the float32 channels (7
or 14 a pixel, 28 or 56 bytes), two 8-bit images and, until the statistic
is made, two float64 numbers a pixel (renderer/memory.py counts it all).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .film import _WIRE_KINDS, _WIRE_MAGIC, AOV_CHANNELS, Film, PartialFilm, _pad
from .images import FrameImages, frame_bands

__all__ = ["StoredFilm", "merge_frame"]


class StoredFilm:
    """A unit's film read lazily: its header now (region, stats, splat counts,
    which layers), rows of its arrays on demand (`rows`). From a file in
    the wire format (film.py), or from a film in memory (or bytes, or a
    file in the old npz layout, read whole)."""

    def __init__(self, source: str | Path | bytes | PartialFilm):
        self._path: Path | None = None
        self._film: PartialFilm | None = None
        self._arrays: dict[str, tuple[int, np.dtype, tuple[int, ...]]] = {}
        if isinstance(source, PartialFilm):
            self._film = source
        elif isinstance(source, (bytes, bytearray, memoryview)):
            self._film = PartialFilm.from_bytes(bytes(source))
        else:
            self._path = Path(source)
            with open(self._path, "rb") as f:
                head = f.read(12)
                if head[:2] == b"PK":  # the npz layout of old stores: read whole
                    self._film = PartialFilm.from_bytes(head + f.read())
                else:
                    self._read_header(f, head)
        if self._film is not None:
            film = self._film
            self.x0, self.y0, self.stats = film.x0, film.y0, film.stats
            self.height, self.width = film.sum.shape[:2]
            self.splat = film.splat is not None
            self.splat_paths, self.splat_batches = film.splat_paths, film.splat_batches
            self.splat_scale_rel_var = film.splat_scale_rel_var
            self.aov = film.aov is not None
            self.jackknife = None if film.jackknife is None else film.jackknife.shape[2:]

    def _read_header(self, f, head: bytes) -> None:
        if head[:8] != _WIRE_MAGIC:
            raise ValueError(f"{self._path}: not rayfarm film bytes (bad magic)")
        size = int.from_bytes(head[8:12], "little")
        raw = f.read(size)
        if len(raw) != size:
            raise ValueError(f"{self._path}: film bytes cut short in the header")
        header = json.loads(raw.decode())
        offset = 12 + size + _pad(12 + size)
        end = os.fstat(f.fileno()).st_size
        for name, dtype, shape in header["arrays"]:
            dt = np.dtype(dtype)
            if dt.kind not in _WIRE_KINDS or not all(isinstance(n, int) and n >= 0 for n in shape):
                raise ValueError(f"{self._path}: film array {name!r}: bad dtype or shape")
            nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
            if offset + nbytes > end:
                raise ValueError(f"{self._path}: film bytes cut short in array {name!r}")
            self._arrays[name] = (offset, dt, tuple(shape))
            offset += nbytes + _pad(nbytes)
        self.x0, self.y0 = (int(v) for v in header["origin"])
        self.stats = header["stats"]
        self.height, self.width = self._arrays["sum"][2][:2]
        count = header.get("splat_count")
        self.splat = count is not None
        self.splat_paths, self.splat_batches = ((float(count[0]), int(count[1])) if self.splat
                                                else (0.0, 0))
        self.splat_scale_rel_var = float(header.get("splat_scale_rel_var", 0.0))
        self.aov = "aov" in self._arrays
        if self.aov and self._arrays["aov"][2] != (self.height, self.width, AOV_CHANNELS):
            raise ValueError(f"{self._path}: film array 'aov' has shape {self._arrays['aov'][2]}")
        jk = self._arrays.get("jackknife")
        self.jackknife = None if jk is None else jk[2][2:]

    def rows(self, names: Sequence[str], r0: int, r1: int) -> dict[str, np.ndarray]:
        """Rows [r0, r1) of the named arrays (their own row numbers)."""
        if self._film is not None:
            return {name: getattr(self._film, name)[r0:r1] for name in names}
        out = {}
        with open(self._path, "rb", buffering=0) as f:
            for name in names:
                offset, dt, shape = self._arrays[name]
                row = int(np.prod(shape[1:], dtype=np.int64)) * dt.itemsize
                a = np.empty((r1 - r0,) + shape[1:], dt)
                f.seek(offset + r0 * row)
                if f.readinto(memoryview(a.reshape(-1)).cast("B")) != a.nbytes:
                    raise ValueError(f"{self._path}: film bytes cut short in array {name!r}")
                out[name] = a if dt.isnative else a.astype(dt.newbyteorder("="))
        return out


def merge_frame(width: int, height: int, sources: Sequence[str | Path | bytes | PartialFilm], *,
                tile: int = 0, channels: bool = True, preview: bool = False,
                noise: bool = False, denoise: bool = False) -> FrameImages:
    """The frame of `sources` (unit films in unit order: paths, bytes or
    films) merged band by band (module doc): its `FrameImages` with the
    error statistic and the merged stats, and what else is asked for.
    `tile`: the job's tile size (bands then hold whole rows of tiles)."""
    films = [StoredFilm(s) for s in sources]
    # What Film.add makes of the films' headers, in unit order.
    stats = {"samples": 0, "rays": 0, "seconds": 0.0}
    paths, batches, rel_var = 0.0, 0, 0.0
    aov, jackknife, splat = False, None, False
    for film in films:
        for key in ("samples", "rays", "seconds"):
            stats[key] = stats.get(key, 0) + film.stats.get(key, 0)
        aov = aov or film.aov
        if jackknife is None and film.jackknife is not None:
            jackknife = film.jackknife
        if film.splat:
            splat = True
            paths += film.splat_paths
            batches += film.splat_batches
            rel_var = max(rel_var, film.splat_scale_rel_var)
    bands = frame_bands(width, height, tile)
    rows = bands[0][1] if bands else 1
    camera: list[list[StoredFilm]] = [[] for _ in bands]  # per band, in unit order
    for film in films:
        if film.width and film.height:
            for b in range(film.y0 // rows, (film.y0 + film.height - 1) // rows + 1):
                camera[b].append(film)
    splats = [film for film in films if film.splat]
    images = FrameImages(width, height, aov=aov, channels=channels, preview=preview,
                         noise=noise, error=True, denoise=denoise)
    names = ["sum", "sum_sq", "weight"] + (["aov"] if aov else [])
    for b, (y0, y1) in enumerate(bands):
        h = y1 - y0
        band = Film(0, y0, np.zeros((h, width, 3)), np.zeros((h, width, 3)), np.zeros((h, width)),
                    stats, splat_paths=paths, splat_batches=batches, splat_scale_rel_var=rel_var,
                    aov=np.zeros((h, width, AOV_CHANNELS)) if aov else None,
                    jackknife=(np.zeros((h, width) + tuple(jackknife))
                               if jackknife is not None else None))
        for film in camera[b]:
            r0, r1 = max(y0, film.y0), min(y1, film.y0 + film.height)
            xs = slice(film.x0, film.x0 + film.width)
            part = film.rows([n for n in names if n != "aov" or film.aov]
                             + (["jackknife"] if film.jackknife is not None else []),
                             r0 - film.y0, r1 - film.y0)
            ys = slice(r0 - y0, r1 - y0)
            band.sum[ys, xs] += part["sum"]
            band.sum_sq[ys, xs] += part["sum_sq"]
            band.weight[ys, xs] += part["weight"]
            if film.aov:
                band.aov[ys, xs] += part["aov"]
            if film.jackknife is not None:
                band.jackknife[ys, xs] += part["jackknife"]
        if splat:
            band.splat, band.splat_sq = np.zeros((h, width, 3)), np.zeros((h, width, 3))
            for film in splats:
                part = film.rows(["splat", "splat_sq"], y0, y1)
                band.splat += part["splat"]
                band.splat_sq += part["splat_sq"]
        images.add(y0, band)
    images.stats = stats
    return images.finish()
