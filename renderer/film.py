"""Partial films, their merge, and the finished film's images (EXR, PNG).

A work unit returns a `PartialFilm` over its region: per pixel the sum of
sample values, the sum of their squares and the sample weight (with filter
importance sampling and a box filter every sample weighs 1, so the weight is
the sample count). Merging is plain addition in unit order, and one division
at the end (`Film.mean`).

Bit-identical merges. Float addition is not associative, so the summation
order is fixed by the *sample blocks* (`sample_blocks`): within a block the
kernel sums samples in index order starting from zero; a pixel's total is the
left fold of its block sums in block order. A unit that covers a whole pixel
range of blocks computes that fold itself; a unit that covers one later block
returns just that block's sum and the merge adds it next. Either way the bits
are the same, whatever the tile size, the executor or the pass plan.

Splats. Light tracing, BDPT's t = 1 strategies and Metropolis chains add
contributions anywhere on the frame, so they cannot be "samples of a pixel".
A unit's splats form one *batch*: a full-frame `splat` array holding the sum
of its n paths' (or mutations') contributions, with n in `splat_paths`. The
frame's splat estimate is sum(splat) / sum(n) over all batches: the scale is
the job's total path count, not a unit's (pbrt-v4 issue 347 was exactly this
bug). Its variance comes from the batches, which are independent: with batch
estimates X_b = S_b / n_b, the weighted sample variance
sigma^2 = sum n_b (X_b - X)^2 / (K - 1) = (sum S_b^2 / n_b - S^2 / n) / (K - 1),
and Var(X) = sigma^2 / n. So each batch also carries S_b^2 / n_b (`splat_sq`)
and the merge only adds. With equal batches this is the plain batch-means
variance; it needs K >= 2 batches (reported as +inf otherwise). A splat
image whose every batch is scaled by one shared estimate c (MLT's bootstrap
normalization b) carries c's relative variance in `splat_scale_rel_var`:
Var(c X) ~ Var_batches + (c X)^2 Var(c) / c^2 (first order, c independent of
the batches), added per pixel. That term is the same error in every pixel
(their covariance is the product of their splat means times it), which the
batches cannot see: they all share c.

AOVs. A method with camera samples (all but light tracing and MLT) also sums,
per pixel and in the same block fold as the radiance, each sample's first-hit
albedo (RGB), shading normal (XYZ) and depth: `aov`, (h, w, AOV_CHANNELS). The
merge adds them like `sum`, so they are tiling-invariant too; the EXR holds
their means (`AOV_LAYERS`: the layer names), and every film's `samples.Y`, the
camera samples per pixel (`weight`).

Shared estimates (jackknife). A radiosity image reads one solution, whose
random numbers (form-factor rays, light samples) every pixel shares: the
spread of the camera samples cannot see its noise. The solution carries J
delete-a-group jackknife replicates (renderer/radiosity_solve.py), and a
film sums, per pixel and in the same block fold, each sample's change under
each replicate: `jackknife`, (h, w, J, 3). With D_b that sum over the n
samples, the replicate's pixel moves by d_b = D_b / n, and the solution's
share of the pixel's variance is the jackknife's (J - 1) / J sum_b (d_b -
mean d)^2, added to the camera samples' (they are independent of it). It
carries the covariance of the patches a pixel sees, since each replicate
is a whole solution; neighbouring pixels' errors are correlated through it.

Artefacts. A prepass unit's result (a photon map, a radiosity solution, a
bootstrap estimate, per-pixel statistics carried to the next iteration) is a
film with named arrays in `artefact`, often over an empty region; the units
that need it receive it as input (renderer/plan.py) and the merge ignores it.

Wire format. `to_bytes` writes a JSON header (origin, stats, splat counts, and
each array's name, dtype and shape) followed by the arrays' raw bytes. Not
npz: numpy reads every .npy header with `ast.literal_eval`, and CPython 3.11
keeps the AST constructor's recursion depth in per-interpreter state, so two
threads parsing at once can raise a spurious "SystemError: AST constructor
recursion depth mismatch" (CPython gh-106905). The service reads films on its
scheduler and executor threads while others log tracebacks (which parse too),
so a unit's good result could fail as "unreadable". JSON has no such state.
"""

from __future__ import annotations

import importlib.metadata
import io
import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable

import numpy as np

__all__ = ["PartialFilm", "Film", "sample_blocks", "merge", "read_exr", "tonemap_srgb8",
           "relative_error", "error_floor", "image_error", "noise_srgb8", "NOISE_RANGE", "NOISE_COLORMAP",
           "AOV_LAYERS", "AOV_CHANNELS", "FrameImages", "frame_bands", "write_exr", "write_png",
           "tonemap_rows", "denoised_channels"]

# The AOV channels a film's `aov` sums, in order, and the EXR channels their
# means are written as: "layer.channel", the convention tev, Nuke and
# Blender's compositor show as layers (Nuke's own depth layer is depth.Z).
AOV_LAYERS = ("albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth.Z")
AOV_CHANNELS = len(AOV_LAYERS)

# Block sizes grow 1, 1, 2, 4, ... (pbrt-v4's doubling waves) up to this cap.
MAX_BLOCK = 64


def sample_blocks(spp: int) -> list[tuple[int, int]]:
    """The canonical sample blocks of a pixel: [(0,1), (1,2), (2,4), (4,8), ...]
    with sizes capped at MAX_BLOCK and the last one cut at spp."""
    blocks, start, size = [], 0, 1
    while start < spp:
        end = min(start + size, spp)
        blocks.append((start, end))
        if start > 0:
            size = min(size * 2, MAX_BLOCK)
        start = end
    return blocks


@dataclass
class PartialFilm:
    """A region's accumulated samples: `sum`, `sum_sq` (h, w, 3) and `weight` (h, w)."""

    x0: int
    y0: int
    sum: np.ndarray
    sum_sq: np.ndarray
    weight: np.ndarray
    stats: dict = field(default_factory=dict)  # samples, rays, seconds
    # The splat batch layer (module doc): full-frame (H, W, 3) arrays or None.
    splat: np.ndarray | None = None
    splat_sq: np.ndarray | None = None
    splat_paths: float = 0.0
    splat_batches: int = 0
    splat_scale_rel_var: float = 0.0  # the shared scale's (Var c) / c^2 (module doc, "Splats")
    artefact: dict = field(default_factory=dict)  # name -> numpy array
    aov: np.ndarray | None = None  # (h, w, AOV_CHANNELS) sums (module doc, "AOVs")
    jackknife: np.ndarray | None = None  # (h, w, J, 3) sums (module doc, "Shared estimates")

    @property
    def height(self) -> int:
        return self.sum.shape[0]

    @property
    def width(self) -> int:
        return self.sum.shape[1]

    @classmethod
    def zeros(cls, x0: int, y0: int, width: int, height: int,
              aov: bool = False) -> "PartialFilm":
        return cls(x0, y0, np.zeros((height, width, 3)), np.zeros((height, width, 3)),
                   np.zeros((height, width)), {"samples": 0, "rays": 0, "seconds": 0.0},
                   aov=np.zeros((height, width, AOV_CHANNELS)) if aov else None)

    @classmethod
    def splat_batch(cls, splat: np.ndarray, paths: float) -> "PartialFilm":
        """A film holding one batch of splats: `splat` (H, W, 3) is the sum of
        `paths` paths' contributions over the whole frame (no camera samples)."""
        film = cls.zeros(0, 0, 0, 0)
        film.splat = np.ascontiguousarray(splat, dtype=np.float64)
        film.splat_sq = film.splat * film.splat / paths if paths > 0 else np.zeros_like(film.splat)
        film.splat_paths = float(paths)
        film.splat_batches = 1
        return film

    def with_splats(self, other: "PartialFilm") -> "PartialFilm":
        """This film with `other`'s splat batch attached (a tile film plus the
        splats its camera paths made elsewhere, as BDPT's t = 1 strategies do)."""
        self.splat, self.splat_sq = other.splat, other.splat_sq
        self.splat_paths, self.splat_batches = other.splat_paths, other.splat_batches
        self.splat_scale_rel_var = other.splat_scale_rel_var
        return self

    def to_bytes(self) -> bytes:
        """Serialize losslessly for the store and the result backend (module
        doc, "Wire format"); equal films give equal bytes."""
        arrays = {"sum": self.sum, "sum_sq": self.sum_sq, "weight": self.weight}
        if self.splat is not None:
            arrays.update(splat=self.splat, splat_sq=self.splat_sq)
        if self.aov is not None:
            arrays["aov"] = self.aov
        if self.jackknife is not None:
            arrays["jackknife"] = self.jackknife
        for name, value in self.artefact.items():
            arrays[f"artefact.{name}"] = value
        header = {"origin": [int(self.x0), int(self.y0)], "stats": self.stats,
                  "splat_count": ([float(self.splat_paths), int(self.splat_batches)]
                                  if self.splat is not None else None),
                  "splat_scale_rel_var": float(self.splat_scale_rel_var),
                  "arrays": []}
        blobs = []
        for name, value in arrays.items():
            a = np.asarray(value)
            if a.dtype.kind not in _WIRE_KINDS:
                raise TypeError(f"film array {name!r} has dtype {a.dtype}, not a number type")
            a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))
            header["arrays"].append([name, a.dtype.str, list(a.shape)])
            # the array's own memory, not a copy of it: the join below is the
            # one copy (a tile of 1024^2 pixels with AOVs is 117 MB)
            blobs.append(memoryview(a.reshape(-1)).cast("B") if a.size else b"")
        head = json.dumps(header, allow_nan=True).encode()
        out = [_WIRE_MAGIC, len(head).to_bytes(4, "little"), head, b"\0" * _pad(len(head) + 12)]
        for blob in blobs:
            out += [blob, b"\0" * _pad(len(blob))]
        return b"".join(out)

    @staticmethod
    def _wire_header(data: bytes) -> tuple[dict, int]:
        """The header of film bytes and the offset of its first array."""
        if data[:8] != _WIRE_MAGIC:
            raise ValueError("not rayfarm film bytes (bad magic)")
        size = int.from_bytes(data[8:12], "little")
        if 12 + size > len(data):
            raise ValueError("film bytes cut short in the header")
        header = json.loads(data[12:12 + size].decode())
        if not isinstance(header, dict) or not isinstance(header.get("arrays"), list):
            raise ValueError("film header is not a rayfarm film header")
        return header, 12 + size + _pad(12 + size)

    @staticmethod
    def stats_from_bytes(data: bytes) -> dict:
        """Just the stats of serialized film bytes (reads no pixel array)."""
        if data[:2] == b"PK":
            return PartialFilm._from_npz(data).stats
        return PartialFilm._wire_header(data)[0]["stats"]

    @classmethod
    def from_bytes(cls, data: bytes) -> "PartialFilm":
        """The film `to_bytes` wrote (or the npz of rayfarm before the wire
        format, so a store written by it still merges). Raises ValueError on
        bytes that are not a whole film."""
        if data[:2] == b"PK":
            return cls._from_npz(data)
        header, offset = cls._wire_header(data)
        view = memoryview(data)
        arrays = {}
        for name, dtype, shape in header["arrays"]:
            dt = np.dtype(dtype)
            if dt.kind not in _WIRE_KINDS or not all(isinstance(n, int) and n >= 0 for n in shape):
                raise ValueError(f"film array {name!r}: bad dtype {dtype!r} or shape {shape!r}")
            nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
            if offset + nbytes > len(data):
                raise ValueError(f"film bytes cut short in array {name!r}")
            arrays[name] = np.frombuffer(view[offset:offset + nbytes], dt).reshape(shape).copy()
            offset += nbytes + _pad(nbytes)
        x0, y0 = (int(v) for v in header["origin"])
        film = cls(x0, y0, arrays["sum"], arrays["sum_sq"], arrays["weight"], header["stats"])
        if header.get("splat_count") is not None:
            film.splat, film.splat_sq = arrays["splat"], arrays["splat_sq"]
            paths, batches = header["splat_count"]
            film.splat_paths, film.splat_batches = float(paths), int(batches)
            film.splat_scale_rel_var = float(header.get("splat_scale_rel_var", 0.0))
        aov = arrays.get("aov")
        if aov is not None and (aov.ndim != 3 or aov.shape[:2] != film.weight.shape
                                or aov.shape[2] != AOV_CHANNELS):
            raise ValueError(f"film array 'aov' has shape {aov.shape}, not "
                             f"{film.weight.shape + (AOV_CHANNELS,)}")
        film.aov = aov
        jackknife = arrays.get("jackknife")
        if jackknife is not None and (jackknife.ndim != 4 or jackknife.shape[:2]
                                      != film.weight.shape or jackknife.shape[3] != 3):
            raise ValueError(f"film array 'jackknife' has shape {jackknife.shape}, not "
                             f"{film.weight.shape + ('J', 3)}")
        film.jackknife = jackknife
        film.artefact = {name[len("artefact."):]: value
                         for name, value in arrays.items() if name.startswith("artefact.")}
        return film

    @classmethod
    def _from_npz(cls, data: bytes) -> "PartialFilm":
        """A film in the npz layout rayfarm stored before the wire format."""
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            x0, y0 = (int(v) for v in z["origin"])
            film = cls(x0, y0, z["sum"].copy(), z["sum_sq"].copy(), z["weight"].copy(),
                       json.loads(z["stats"].tobytes().decode()))
            if "splat" in z.files:
                film.splat, film.splat_sq = z["splat"].copy(), z["splat_sq"].copy()
                paths, batches = z["splat_count"]
                film.splat_paths, film.splat_batches = float(paths), int(batches)
            film.artefact = {name[len("artefact."):]: z[name].copy()
                             for name in z.files if name.startswith("artefact.")}
            return film


# Wire format (module doc): magic, a little-endian u32 header length, a JSON
# header, then each array's raw little-endian bytes, all 8-byte aligned.
_WIRE_MAGIC = b"RFFILM1\n"
_WIRE_KINDS = "biuf"  # bool, signed, unsigned, float: nothing that needs pickle


def _pad(n: int) -> int:
    return -n % 8


@dataclass
class Film(PartialFilm):
    """A whole frame's accumulated samples, with the estimates derived from them."""

    def mean(self) -> np.ndarray:
        """Per-pixel mean radiance (h, w, 3): the camera samples' mean plus
        the splat estimate (module doc)."""
        n = _per_channel(self.weight, self.sum.shape)
        with np.errstate(invalid="ignore", divide="ignore"):  # (1e-300 is 0 in float32)
            out = self.sum / np.maximum(n, 1e-300)
        np.copyto(out, 0.0, where=~(n > 0))
        if self.splat is not None and self.splat_paths > 0:
            out = out + self.splat / self.splat_paths
        return out

    def variance_of_mean(self) -> np.ndarray:
        """Per-pixel variance of the mean estimate: the camera samples'
        unbiased sample variance divided by their count, plus the splat
        estimate's batch variance. Undefined with fewer than two samples (or
        batches); reported as +inf there. A frame made of splats only has no
        camera-sample part."""
        # In place, over the count repeated per channel: max(sum_sq - n mean^2,
        # 0) / (n - 1) / n, the same operations in the same order as written
        # out, in a third of the time (every new array of a frame is fresh
        # pages to fault in, and an operand broadcast over the channel axis
        # makes numpy loop over three elements at a time).
        n = _per_channel(self.weight, self.sum.shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.sum / n
            out = n * mean
            out *= mean
            np.subtract(self.sum_sq, out, out=out)
            np.maximum(out, 0.0, out=out)
            out /= n - 1.0
            out /= n
        splats = self.splat is not None and self.splat_paths > 0
        few = n < 2  # (a weight is a count, never nan)
        np.copyto(out, 0.0 if splats else np.inf, where=few)
        if splats:  # (without them every pixel of fewer than two samples is inf already)
            out = np.where((n > 0) & few, np.inf, out)
            k, paths = self.splat_batches, self.splat_paths
            if k >= 2:
                spread = np.maximum(self.splat_sq - self.splat * self.splat / paths, 0.0)
                scaled = self.splat / paths
                out = out + spread / (k - 1.0) / paths + scaled * scaled * self.splat_scale_rel_var
            else:
                out = np.full_like(out, np.inf)
        if self.jackknife is not None and self.jackknife.shape[2] >= 2:
            j = self.jackknife.shape[2]
            with np.errstate(invalid="ignore", divide="ignore"):
                d = self.jackknife / np.maximum(self.weight, 1e-300)[..., None, None]
            spread = ((d - d.mean(axis=2, keepdims=True)) ** 2).sum(axis=2)
            out = out + np.where(n > 0, (j - 1.0) / j * spread, 0.0)
        return out

    def band(self, y0: int, y1: int) -> "Film":
        """This frame's rows [y0, y1) as a Film of views into its arrays, with
        the frame's splat counts (see BAND_PIXELS)."""
        return self.region(0, y0, self.width, y1)

    def region(self, x0: int, y0: int, x1: int, y1: int) -> "Film":
        """The pixels [x0, x1) x [y0, y1) of this frame as a Film of views
        into its arrays, with the frame's splat counts: its `mean()` and
        `variance_of_mean()` are those of the frame there, bit for bit."""
        rows, cols = slice(y0, y1), slice(x0, x1)

        def part(a):
            return None if a is None else a[rows, cols]

        return Film(self.x0 + x0, self.y0 + y0, self.sum[rows, cols], self.sum_sq[rows, cols],
                    self.weight[rows, cols], self.stats, splat=part(self.splat),
                    splat_sq=part(self.splat_sq), splat_paths=self.splat_paths,
                    splat_batches=self.splat_batches,
                    splat_scale_rel_var=self.splat_scale_rel_var, artefact=self.artefact,
                    aov=part(self.aov), jackknife=part(self.jackknife))

    def error_floor(self) -> float:
        """`error_floor` of this frame's mean, band by band (the same value)."""
        total = _PairwiseSum(3 * self.width * self.height)
        for y0, y1 in frame_bands(self.width, self.height):
            total.add(self.band(y0, y1).mean().reshape(-1))
        return ERROR_LEVEL * max(float(total.value() / total.n), 0.0)

    def images(self, **what: bool) -> "FrameImages":
        """`FrameImages` of this frame (`what`: which), made band by band."""
        images = FrameImages(self.width, self.height, aov=self.aov is not None, **what)
        for y0, y1 in frame_bands(self.width, self.height):
            images.add(y0, self.band(y0, y1))
        return images.finish()

    def image_error(self) -> float:
        """`image_error` of this frame's mean and variance (the same value,
        made band by band: `FrameImages`)."""
        return self.images(channels=False, error=True).rel_error

    def aovs(self) -> dict[str, np.ndarray]:
        """The AOVs' per-pixel means by EXR channel name (AOV_LAYERS; empty for
        a film without them), and `samples.Y`, the camera samples per pixel.
        Pixels with no sample read 0."""
        out = {"samples.Y": self.weight.copy()}
        if self.aov is not None:
            n = self.weight[..., None]
            with np.errstate(invalid="ignore", divide="ignore"):
                means = np.where(n > 0, self.aov / np.maximum(n, 1e-300), 0.0)
            out.update({name: means[..., i] for i, name in enumerate(AOV_LAYERS)})
        return out

    def add(self, part: PartialFilm) -> None:
        """Merge one partial film into this frame (plain addition)."""
        ys = slice(part.y0, part.y0 + part.height)
        xs = slice(part.x0, part.x0 + part.width)
        self.sum[ys, xs] += part.sum
        self.sum_sq[ys, xs] += part.sum_sq
        self.weight[ys, xs] += part.weight
        # Layers a part brings are added in the frame's own precision (a
        # running preview's frame is float32: service.previews)
        dtype = self.sum.dtype
        if part.aov is not None:
            if self.aov is None:
                self.aov = np.zeros((self.height, self.width, AOV_CHANNELS), dtype)
            self.aov[ys, xs] += part.aov
        if part.jackknife is not None:
            if self.jackknife is None:
                self.jackknife = np.zeros((self.height, self.width) + part.jackknife.shape[2:],
                                          dtype)
            self.jackknife[ys, xs] += part.jackknife
        if part.splat is not None:
            if self.splat is None:
                self.splat = np.zeros((self.height, self.width, 3), dtype)
                self.splat_sq = np.zeros((self.height, self.width, 3), dtype)
            self.splat += part.splat
            self.splat_sq += part.splat_sq
            self.splat_paths += part.splat_paths
            self.splat_batches += part.splat_batches
            # one shared scale: every batch carries the same value (or 0)
            self.splat_scale_rel_var = max(self.splat_scale_rel_var, part.splat_scale_rel_var)
        for key in ("samples", "rays", "seconds"):
            self.stats[key] = self.stats.get(key, 0) + part.stats.get(key, 0)

    def write_exr(self, path: str | Path, metadata: dict | None = None,
                  denoised: np.ndarray | None = None) -> None:
        """`write_exr` of this frame's `channels` (with `denoised`, its
        denoised beauty, beside the raw one)."""
        write_exr(path, self.channels(denoised), metadata)

    def channels(self, denoised: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The float32 (h, w) channels `write_exr` writes, by EXR name: R, G, B
        (mean radiance), var.R/G/B (variance of the mean), the AOVs (`aovs`:
        samples.Y, and albedo, normal and depth where the method made them),
        and given `denoised` (h, w, 3: renderer.denoise) denoised.R/G/B."""
        channels = self.images().channels
        if denoised is not None:
            channels.update(denoised_channels(denoised))
        return channels

    def write_png(self, path: str | Path, rgb: np.ndarray | None = None) -> None:
        """Write a tonemapped sRGB preview (exposure 1, clamped) of the film,
        or of `rgb` (its denoised beauty) if given."""
        write_png(path, self.images(channels=False, preview=True).preview if rgb is None
                  else tonemap_rows(rgb))

    def write_noise_png(self, path: str | Path) -> None:
        """Write the per-pixel noise heatmap (`noise_srgb8`) of this film."""
        write_png(path, self.images(channels=False, noise=True).noise)


# Bands. A frame's images are made band by band: every step from the merged
# sums to a channel, a PNG pixel or the error statistic is per pixel, so a
# band of rows gives the whole frame's values bit for bit, and the float64
# temporaries (the mean, the variance and theirs: up to about 500 bytes a
# pixel at once with a band's sums) exist for one band at a time, not for
# the frame. What remains whole is what is kept: the float32 channels, the
# 8-bit images, and the two float64 numbers a pixel that the error statistic
# needs at the end (a percentile over pixels chosen by the frame's mean
# brightness). renderer/memory.py counts these bytes.
BAND_PIXELS = 1 << 16


def frame_bands(width: int, height: int, tile: int = 0) -> list[tuple[int, int]]:
    """Row ranges [y0, y1) of a frame's bands, at most BAND_PIXELS each (or
    one row). With `tile` (the job's tile size) no larger than a band's rows,
    bands hold whole rows of tiles, so a tile is read in one piece."""
    rows = max(1, BAND_PIXELS // max(width, 1))
    if 0 < tile <= rows:
        rows -= rows % tile
    return [(y, min(y + rows, height)) for y in range(0, height, rows)]


class FrameImages:
    """What a frame's files are made of, filled band by band (`add`, the
    bands in order, then `finish`), each value the one the whole frame's
    computation gives:

    - `channels`: the EXR's float32 channels (`Film.channels`), by name;
    - `preview`, `noise`: the 8-bit sRGB preview and noise heatmap (h, w, 3);
    - `color`: the denoiser's input, the finite beauty as float32 (h, w, 3);
    - `rel_error`: `image_error` of the frame (after `finish`);
    - `stats`: the merged film's stats, where a merge fills them in.

    Only those asked for are made (`channels` by default)."""

    def __init__(self, width: int, height: int, *, aov: bool, channels: bool = True,
                 preview: bool = False, noise: bool = False, error: bool = False,
                 denoise: bool = False):
        self.width, self.height = width, height
        names = ["R", "G", "B", "var.R", "var.G", "var.B", "samples.Y"]
        names += list(AOV_LAYERS) if aov else []
        self.channels: dict[str, np.ndarray] = (
            {name: np.empty((height, width), np.float32) for name in names} if channels else {})
        self.preview = np.empty((height, width, 3), np.uint8) if preview else None
        self.noise = np.empty((height, width, 3), np.uint8) if noise else None
        self.color = np.empty((height, width, 3), np.float32) if denoise else None
        self._error = _ErrorStatistic(width * height) if error else None
        self.rel_error = float("nan")
        self.stats: dict = {}

    def add(self, y0: int, band: Film) -> None:
        """The frame's rows from y0 on: `band` (a Film over them)."""
        rows = slice(y0, y0 + band.height)
        mean = band.mean()
        var = (band.variance_of_mean()
               if self.channels or self.noise is not None or self._error is not None else None)
        if self.channels:
            for i, c in enumerate("RGB"):
                self.channels[c][rows] = mean[..., i]
                self.channels[f"var.{c}"][rows] = var[..., i]
            for name, a in band.aovs().items():
                self.channels[name][rows] = a
        if self.preview is not None:
            self.preview[rows] = tonemap_srgb8(mean)
        if self.noise is not None:
            self.noise[rows] = noise_srgb8(mean, var)
        if self.color is not None:  # renderer.denoise: non-finite pixels as black
            self.color[rows] = np.nan_to_num(mean, nan=0.0, posinf=0.0, neginf=0.0)
        if self._error is not None:
            self._error.add(mean, var)

    def finish(self) -> "FrameImages":
        """Every band added: the error statistic (its per-pixel arrays freed)."""
        if self._error is not None:
            self.rel_error, self._error = self._error.value(), None
        return self


class _ErrorStatistic:
    """`image_error` of a frame given band by band: per pixel its brightness
    (the channel average) and relative error, and the frame's mean made as
    numpy makes `np.mean(mean)` (`_PairwiseSum`), so the floor, the counted
    pixels and the percentile are the same."""

    def __init__(self, pixels: int):
        self.level = np.empty(pixels)
        self.error = np.empty(pixels)
        self.at = 0
        self.total = _PairwiseSum(3 * pixels)

    def add(self, mean: np.ndarray, variance_of_mean: np.ndarray) -> None:
        n = mean.shape[0] * mean.shape[1]
        self.level[self.at:self.at + n] = _channel_mean(mean).reshape(-1)
        self.error[self.at:self.at + n] = relative_error(mean, variance_of_mean).reshape(-1)
        self.total.add(np.ascontiguousarray(mean).reshape(-1))
        self.at += n

    def value(self) -> float:
        # error_floor: np.mean is numpy's sum divided by the count
        floor = ERROR_LEVEL * max(float(self.total.value() / self.total.n), 0.0)
        counted = self.level > floor
        self.level = None
        if not counted.any():
            return float("nan")
        err = self.error[counted]
        self.error = counted = None
        if not np.all(np.isfinite(err)):
            return float("inf")
        return float(np.percentile(err, ERROR_PERCENTILE, overwrite_input=True))


# numpy sums a contiguous float64 array pairwise: up to 128 values in 8
# lanes, above that the two halves' sums added, the split rounded down to a
# multiple of 8 (numpy/_core/src/umath/loops_utils.h, pairwise_sum). Any
# subtree of that split is numpy's own sum of its values, so handing numpy
# the subtrees of at most _PAIRWISE_LEAF values and adding their sums as the
# tree does gives np.sum's bits for values that arrive in pieces.
_PAIRWISE_LEAF = 1 << 16


def _pairwise_split(n: int) -> int:
    half = n // 2
    return half - half % 8


class _PairwiseSum:
    """`np.add.reduce` of n float64 values given in order in pieces (`add`),
    the same bits (see above); holds at most _PAIRWISE_LEAF of them."""

    def __init__(self, n: int):
        self.n = n
        self.sizes: list[int] = []  # the leaves' sizes, in order
        stack = [n]
        while stack:
            m = stack.pop()
            if m <= _PAIRWISE_LEAF:
                self.sizes.append(m)
            else:
                half = _pairwise_split(m)
                stack += [m - half, half]
        self.sums: list = []
        self.buffer = np.empty(min(n, _PAIRWISE_LEAF))
        self.filled = 0

    def add(self, values: np.ndarray) -> None:
        at = 0
        while at < values.size:
            need = self.sizes[len(self.sums)] - self.filled
            if self.filled == 0 and values.size - at >= need:
                self.sums.append(np.add.reduce(values[at:at + need]))
                at += need
                continue
            take = values[at:at + need]
            self.buffer[self.filled:self.filled + take.size] = take
            self.filled += take.size
            at += take.size
            if self.filled == self.sizes[len(self.sums)]:
                self.sums.append(np.add.reduce(self.buffer[:self.filled]))
                self.filled = 0

    def value(self) -> np.float64:
        if len(self.sums) != len(self.sizes) or self.filled:
            raise ValueError(f"{self.n} values expected, fewer given")
        sums = iter(self.sums)

        def total(m: int):
            if m <= _PAIRWISE_LEAF:
                return next(sums)
            half = _pairwise_split(m)
            left = total(half)
            return left + total(m - half)

        return total(self.n) if self.n else np.float64(0.0)


def write_exr(path: str | Path, channels: dict[str, np.ndarray],
              metadata: dict | None = None) -> None:
    """Write float32 (h, w) `channels` by EXR name (`Film.channels`), with
    `metadata` as `rayfarm.<key>` header attributes (see renderer.metadata:
    strings, 32-bit ints, floats; anything else as JSON) and the standard
    `software`, `capDate` and `utcOffset`, atomically."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "software": f"rayfarm {_version()}",
              "capDate": datetime.now(timezone.utc).strftime("%Y:%m:%d %H:%M:%S"),
              "utcOffset": 0.0}
    for key, value in (metadata or {}).items():
        header[f"rayfarm.{key}"] = _exr_attribute(key, value)
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    # The package writes from the arrays themselves (no copy: measured at
    # 4096^2 x 14 channels, +12 MB); it takes whole channels, not scanlines.
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(tmp))
    tmp.replace(path)  # readers never see a half-written file


def denoised_channels(denoised: np.ndarray) -> dict[str, np.ndarray]:
    """denoised.R/G/B of a denoised beauty (h, w, 3), as float32 channels."""
    return {f"denoised.{c}": np.ascontiguousarray(denoised[..., i], dtype=np.float32)
            for i, c in enumerate("RGB")}


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write 8-bit RGB pixels (h, w, 3) as a PNG, atomically."""
    from PIL import Image

    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    # compress_level 1: previews are rewritten while a job renders; zlib's
    # default level 6 takes longer for files about as small
    Image.fromarray(image).save(tmp, format="PNG", compress_level=1)
    tmp.replace(path)


def tonemap_rows(rgb: np.ndarray) -> np.ndarray:
    """`tonemap_srgb8` of a frame (h, w, 3), band by band (the same pixels)."""
    out = np.empty(rgb.shape, np.uint8)
    for y0, y1 in frame_bands(rgb.shape[1], rgb.shape[0]):
        out[y0:y1] = tonemap_srgb8(rgb[y0:y1])
    return out


def tonemap_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB (clamp to [0, 1], sRGB transfer curve)."""
    x = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=1.0), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (s * 255.0 + 0.5).astype(np.uint8)


# The noise heatmap shows the relative standard error on a log scale from
# NOISE_RANGE[0] (darkest) to NOISE_RANGE[1] (brightest) through an
# inferno-like colormap (stops at 0, 1/8, ..., 1); pixels whose variance is
# not known yet (fewer than two samples) are grey.
NOISE_RANGE = (1e-3, 1.0)
NOISE_COLORMAP = np.array([(0, 0, 4), (31, 12, 72), (85, 15, 109), (136, 34, 106),
                           (186, 54, 85), (227, 89, 51), (249, 140, 10), (249, 201, 50),
                           (252, 255, 164)], dtype=np.float64)
NOISE_UNKNOWN = (128, 128, 128)
ERROR_FLOOR = 1e-3  # radiance below which a pixel counts as black (avoids 0/0)


def relative_error(mean: np.ndarray, variance_of_mean: np.ndarray) -> np.ndarray:
    """Per-pixel relative standard error of the estimate (h, w): the standard
    error of the channel average over the channel average,
    sqrt(mean_c var_c) / max(mean_c mu_c, ERROR_FLOOR). +inf where the
    variance is unknown. (Channels are treated as independent here; they are
    correlated, so this is a display measure, not a confidence interval.)"""
    var = _channel_mean(variance_of_mean)
    level = np.maximum(_channel_mean(mean), ERROR_FLOOR)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(var), np.sqrt(np.maximum(var, 0.0)) / level, np.inf)


def _per_channel(weight: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The per-pixel `weight` (h, w) repeated over the channels of `shape`
    (h, w, c), contiguous (see `Film.variance_of_mean`)."""
    return np.repeat(weight[..., None], shape[-1], axis=-1)


def _channel_mean(x: np.ndarray) -> np.ndarray:
    """`np.mean(x, axis=-1)` of RGB pixels, the same bits (the sum of a row of
    three adds them in order, then divides by 3) at a tenth of its time: a
    reduction over an axis of three pays numpy's per-row overhead (0.76 ms
    against 0.06 ms for 256 x 256 pixels; `image_error` of such a frame, run
    on every pass of a progressive job by the service, took 5 to 8 ms)."""
    if x.shape[-1] != 3:
        return np.mean(x, axis=-1)
    return (x[..., 0] + x[..., 1] + x[..., 2]) / 3.0


# The image's error statistic (`image_error`): the ERROR_PERCENTILE-th
# percentile of the pixels' relative standard error, over the pixels brighter
# than ERROR_LEVEL times the image's mean.
ERROR_PERCENTILE = 95.0
ERROR_LEVEL = 0.01


def error_floor(mean: np.ndarray) -> float:
    """The brightness below which `image_error` does not count a pixel:
    ERROR_LEVEL times the image's mean (of the channel averages)."""
    return ERROR_LEVEL * max(float(np.mean(mean)), 0.0)


def image_error(mean: np.ndarray, variance_of_mean: np.ndarray,
                floor: float | None = None) -> float:
    """One number for how noisy an image is: the 95th percentile over pixels of
    `relative_error`, counting only pixels brighter than 1 % of the image's
    mean (black and near-black pixels have a relative error that means nothing
    to the eye and would decide the statistic). A percentile, not the mean: a
    mean hides a noisy region behind a clean one; not the maximum: one
    firefly or an edge pixel would decide it. +inf while some counted pixel's
    variance is unknown (fewer than two samples); nan for an image with no
    counted pixel. `floor` (default: `error_floor(mean)`) is the brightness a
    counted pixel exceeds: a region of an image is judged with the image's."""
    level = _channel_mean(mean)
    counted = level > (error_floor(mean) if floor is None else floor)
    if not counted.any():
        return float("nan")
    err = relative_error(mean, variance_of_mean)[counted]
    if not np.all(np.isfinite(err)):
        return float("inf")
    return float(np.percentile(err, ERROR_PERCENTILE))


def noise_srgb8(mean: np.ndarray, variance_of_mean: np.ndarray) -> np.ndarray:
    """The noise heatmap as 8-bit RGB (h, w, 3): `relative_error` through the
    colormap on a log scale over NOISE_RANGE; unknown variance in grey."""
    err = relative_error(mean, variance_of_mean)
    lo, hi = np.log10(NOISE_RANGE[0]), np.log10(NOISE_RANGE[1])
    with np.errstate(divide="ignore"):
        t = np.clip((np.log10(np.where(np.isfinite(err), err, 1.0)) - lo) / (hi - lo), 0.0, 1.0)
    x = t * (len(NOISE_COLORMAP) - 1)
    i = np.minimum(x.astype(np.int64), len(NOISE_COLORMAP) - 2)
    f = (x - i)[..., None]
    rgb = NOISE_COLORMAP[i] * (1.0 - f) + NOISE_COLORMAP[i + 1] * f
    rgb[~np.isfinite(err)] = NOISE_UNKNOWN
    return (rgb + 0.5).astype(np.uint8)


def merge(width: int, height: int, parts: Iterable[PartialFilm]) -> Film:
    """Merge partial films in the order given (callers pass unit order)."""
    film = Film.zeros(0, 0, width, height)
    film = Film(0, 0, film.sum, film.sum_sq, film.weight, film.stats)
    for part in parts:
        film.add(part)
    return film


def _exr_attribute(key: str, value):
    """A header value the OpenEXR package writes as the type it is: str, a
    32-bit int (bools as 0/1), a float; anything else as JSON text. The
    package stores an int beyond 32 bits as 0 without a word: refused here."""
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int):
        if not -(1 << 31) <= value < (1 << 31):
            raise ValueError(f"EXR attribute {key!r}: {value} does not fit a 32-bit int "
                             "(write it as a decimal string)")
        return value
    if isinstance(value, (str, float)):
        return value
    return json.dumps(value, sort_keys=True)


def _version() -> str:
    try:
        return importlib.metadata.version("rayfarm")
    except importlib.metadata.PackageNotFoundError:  # a source tree that was never installed
        return "unknown"


def channel_layers(names: Iterable[str]) -> dict[str, list[str]]:
    """EXR channel names grouped into layers, as tev and Nuke show them: a
    bare name (R, G, B) is the `beauty` layer, `layer.channel` belongs to
    `layer` (var, albedo, normal, depth, samples, denoised). Channels keep
    their order within a layer (R, G, B; X, Y, Z), layers the order given."""
    order = {c: i for i, c in enumerate("RGBAXYZ")}
    layers: dict[str, list[str]] = {}
    for name in names:
        layer, _, channel = name.rpartition(".")
        layers.setdefault(layer or "beauty", []).append(name)
    for layer, members in layers.items():
        members.sort(key=lambda n: (order.get(n.rpartition(".")[2], 99), n))
    return layers


def rgb_of(channels: dict[str, np.ndarray], layer: str = "") -> np.ndarray:
    """A layer's R, G, B channels of an EXR read back (`read_exr`) as one float64
    (h, w, 3) array: the beauty, or with `layer` "var" its variance."""
    prefix = f"{layer}." if layer else ""
    return np.stack([channels[f"{prefix}{c}"] for c in "RGB"], -1).astype(np.float64)


def read_exr(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """Read an EXR back: (channels by name as float32 (h, w) arrays, header)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as exr:
        part = exr.parts[0]
        channels = {name: np.array(ch.pixels) for name, ch in part.channels.items()}
        header = dict(part.header)
    return channels, header

