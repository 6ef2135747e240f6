"""Partial films, their merge, and the finished film's estimates (its images,
EXR and PNG, are renderer/images.py).

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

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from .images import (AOV_CHANNELS, AOV_LAYERS, ERROR_LEVEL, NOISE_COLORMAP, NOISE_RANGE,  # noqa: F401
                     NOISE_UNKNOWN, FrameImages, _PairwiseSum, channel_layers, denoised_channels,
                     error_floor, frame_bands, image_error, noise_srgb8, read_exr, relative_error,
                     rgb_of, tonemap_rows, tonemap_srgb8, write_exr, write_png)

# The image functions and constants are renderer.images'; their names here
# stay for the code that imports them from the film.
__all__ = ["PartialFilm", "Film", "sample_blocks", "merge", "read_exr", "tonemap_srgb8",
           "relative_error", "error_floor", "image_error", "noise_srgb8", "NOISE_RANGE", "NOISE_COLORMAP",
           "AOV_LAYERS", "AOV_CHANNELS"]


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
            a = a.astype(a.dtype.newbyteorder("<"), order="C", copy=False)
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
    def from_bytes(cls, data: bytes, copy: bool = True) -> "PartialFilm":
        """The film `to_bytes` wrote (or the npz of rayfarm before the wire
        format, so a store written by it still merges). Raises ValueError on
        bytes that are not a whole film. `copy=False`: its arrays are
        read-only views into `data` (no second copy of a film that is only
        read)."""
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
            a = np.frombuffer(view[offset:offset + nbytes], dt).reshape(shape)
            arrays[name] = a.copy() if copy else a
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


def _per_channel(weight: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The per-pixel `weight` (h, w) repeated over the channels of `shape`
    (h, w, c), contiguous (see `Film.variance_of_mean`)."""
    return np.repeat(weight[..., None], shape[-1], axis=-1)


def merge(width: int, height: int, parts: Iterable[PartialFilm]) -> Film:
    """Merge partial films in the order given (callers pass unit order)."""
    film = Film.zeros(0, 0, width, height)
    film = Film(0, 0, film.sum, film.sum_sq, film.weight, film.stats)
    for part in parts:
        film.add(part)
    return film
