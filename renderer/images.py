"""A finished frame's images: the EXR's float32 channels and header, the
tonemapped preview, the per-pixel noise heatmap, and the one number for how
noisy an image is (`image_error`). The film (renderer/film.py) holds the
sums; this module turns a frame's estimates (its mean, the variance of the
mean and the AOVs' means) into what users see, band by band (`FrameImages`),
and reads an EXR back.
"""

from __future__ import annotations

import importlib.metadata
import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable

import numpy as np

__all__ = ["AOV_LAYERS", "AOV_CHANNELS", "BAND_PIXELS", "FrameImages", "frame_bands", "write_exr",
           "write_png", "tonemap_rows", "tonemap_srgb8", "denoised_channels", "relative_error",
           "error_floor", "image_error", "noise_srgb8", "NOISE_RANGE", "NOISE_COLORMAP",
           "NOISE_UNKNOWN", "channel_layers", "rgb_of", "read_exr"]

# The AOV channels a film's `aov` sums, in order, and the EXR channels their
# means are written as: "layer.channel", the convention tev, Nuke and
# Blender's compositor show as layers (Nuke's own depth layer is depth.Z).
AOV_LAYERS = ("albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth.Z")
AOV_CHANNELS = len(AOV_LAYERS)


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

    def add(self, y0: int, band) -> None:
        """The frame's rows from y0 on: `band`, a renderer.Film over them (its
        mean(), variance_of_mean() and aovs() are what is read)."""
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
