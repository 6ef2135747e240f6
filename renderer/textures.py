"""Texture images read into linear float32 texels.

    texels = read_texture(path)            # (H, W, C) float32, C in 1, 3, 4

PNG and JPEG (through Pillow) hold sRGB-encoded values: they are decoded to
linear unless `raw` (normal maps, roughness maps authored as data), as
Mitsuba 3's bitmap texture does. OpenEXR and Radiance .hdr files hold
linear values already. Row 0 is the image's top row, as stored: texture
lookups (kernels/shading.py) put uv (0, 0) there, as Mitsuba 3 does.

Sizes are refused from the header, before anything is decoded: a file that
claims more than `MAX_TEXELS` texels (or a side beyond `MAX_TEXTURE_SIDE`)
is a SceneError naming it, as is every file the decoders cannot read.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .errors import SceneError

__all__ = ["read_texture", "srgb_to_linear", "MAX_TEXELS", "MAX_TEXTURE_SIDE"]

MAX_TEXTURE_SIDE = 32768
MAX_TEXELS = 64 * 1024 * 1024  # 768 MiB of float32 RGB: larger than any texture of the test sets


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), on values in [0, 1]."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _check_size(width: int, height: int, name: str) -> None:
    if width < 1 or height < 1:
        raise SceneError(f"texture {name} has no pixels ({width} x {height})", name)
    if width > MAX_TEXTURE_SIDE or height > MAX_TEXTURE_SIDE or width * height > MAX_TEXELS:
        raise SceneError(f"texture {name} is {width} x {height} pixels; the limit is "
                         f"{MAX_TEXTURE_SIDE} a side and {MAX_TEXELS} pixels in all", name)


def read_texture(path: Path | str, *, raw: bool = False, name: str | None = None) -> np.ndarray:
    """The texels of an image file as (H, W, C) float32 linear values.

    `name` is how errors call the file (default: its name), e.g. the path
    relative to the scene's folder."""
    path = Path(path)
    name = name or path.name
    if not path.is_file():
        raise SceneError(f"texture file not found: {name}", name)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        return _read_exr(path, name)
    if suffix in (".hdr", ".rgbe", ".pic"):
        return _read_hdr(path.read_bytes(), name)
    if suffix in (".png", ".jpg", ".jpeg"):
        return _read_pillow(path, name, raw)
    raise SceneError(f"unsupported texture file type '{path.suffix}' of {name} "
                     "(allowed: .png, .jpg, .jpeg, .exr, .hdr)", name)


def _read_pillow(path: Path, name: str, raw: bool) -> np.ndarray:
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path) as im:  # reads the header only
                _check_size(im.width, im.height, name)
                im.load()
                mode = im.mode
                if mode == "P":
                    im = im.convert("RGBA" if "transparency" in im.info else "RGB")
                elif mode in ("LA", "PA"):
                    im = im.convert("RGBA")
                elif mode == "CMYK" or mode == "YCbCr":
                    im = im.convert("RGB")
                elif mode == "1":
                    im = im.convert("L")
                mode = im.mode
                a = np.asarray(im)
    except SceneError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise SceneError(f"texture {name} is too large to decode (Pillow's decompression "
                         "bomb check)", name) from None
    except Exception as exc:  # Pillow raises many kinds for a broken file
        raise SceneError(f"cannot read texture {name}: {exc}", name) from None
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        v = a.astype(np.float64) / 65535.0
    elif mode == "F":
        v = a.astype(np.float64)
    else:
        v = a.astype(np.float64) / 255.0
    if v.ndim == 2:
        v = v[:, :, None]
    if v.shape[2] not in (1, 3, 4):
        raise SceneError(f"texture {name} has {v.shape[2]} channels (mode {mode}); "
                         "1, 3 or 4 are read", name)
    if not raw and mode != "F":
        colour = min(v.shape[2], 3)
        v[:, :, :colour] = srgb_to_linear(v[:, :, :colour])
    return np.ascontiguousarray(v, dtype=np.float32)


def _read_exr(path: Path, name: str) -> np.ndarray:
    import OpenEXR

    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            (x0, y0), (x1, y1) = np.asarray(exr.parts[0].header["dataWindow"]).reshape(2, 2)
            _check_size(int(x1 - x0 + 1), int(y1 - y0 + 1), name)
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {k: np.asarray(ch.pixels) for k, ch in exr.parts[0].channels.items()}
    except SceneError:
        raise
    except Exception as exc:
        raise SceneError(f"cannot read texture {name}: {exc}", name) from None
    if all(c in channels for c in "RGB"):
        names = ["R", "G", "B"] + (["A"] if "A" in channels else [])
    elif "Y" in channels:
        names = ["Y"]
    else:
        raise SceneError(f"texture {name} has channels {', '.join(sorted(channels))}; an RGB "
                         "or luminance (Y) image is read", name)
    v = np.stack([channels[c].astype(np.float32) for c in names], axis=-1)
    if not np.all(np.isfinite(v)):
        raise SceneError(f"texture {name} holds NaN or infinite values", name)
    return np.ascontiguousarray(v)


def _read_hdr(data: bytes, name: str) -> np.ndarray:
    """Radiance RGBE: the header, then flat or new-style run-length scanlines
    (the old-style runs of 1 1 1 n pixels are refused)."""
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise SceneError(f"texture {name} is not a Radiance HDR file (no #?RADIANCE line)", name)
    pos, fmt = 0, None
    while True:
        end = data.find(b"\n", pos)
        if end < 0 or end - pos > 4096:
            raise SceneError(f"texture {name}: the Radiance header does not end", name)
        line = data[pos:end].strip()
        pos = end + 1
        if not line:
            break
        if line.startswith(b"FORMAT="):
            fmt = line[7:]
    if fmt not in (None, b"32-bit_rle_rgbe"):
        raise SceneError(f"texture {name}: Radiance format {fmt.decode(errors='replace')} is not "
                         "read (only 32-bit_rle_rgbe)", name)
    end = data.find(b"\n", pos)
    parts = data[pos:end if end >= 0 else len(data)].split()
    if len(parts) != 4 or parts[0] != b"-Y" or parts[2] != b"+X":
        raise SceneError(f"texture {name}: the Radiance resolution line must read '-Y H +X W'",
                         name)
    try:
        height, width = int(parts[1]), int(parts[3])
    except ValueError:
        raise SceneError(f"texture {name}: bad Radiance resolution line", name) from None
    _check_size(width, height, name)
    pos = end + 1
    buf = np.frombuffer(data, dtype=np.uint8)
    out = np.empty((height, width, 4), np.uint8)
    short = SceneError(f"texture {name}: the pixel data ends early", name)
    for y in range(height):
        if (8 <= width <= 0x7FFF and pos + 4 <= len(buf) and buf[pos] == 2 and buf[pos + 1] == 2
                and not buf[pos + 2] & 0x80):
            if (int(buf[pos + 2]) << 8 | int(buf[pos + 3])) != width:
                raise SceneError(f"texture {name}: scanline {y} has the wrong length", name)
            pos += 4
            for c in range(4):
                x = 0
                while x < width:
                    if pos >= len(buf):
                        raise short
                    count = int(buf[pos])
                    pos += 1
                    if count > 128:  # a run
                        count -= 128
                        if count == 0 or x + count > width or pos >= len(buf):
                            raise SceneError(f"texture {name}: bad run in scanline {y}", name)
                        out[y, x:x + count, c] = buf[pos]
                        pos += 1
                    else:
                        if count == 0 or x + count > width or pos + count > len(buf):
                            raise SceneError(f"texture {name}: bad run in scanline {y}", name)
                        out[y, x:x + count, c] = buf[pos:pos + count]
                        pos += count
                    x += count
        else:
            n = 4 * width
            if pos + n > len(buf):
                raise short
            row = buf[pos:pos + n].reshape(width, 4)
            if np.any((row[:, 0] == 1) & (row[:, 1] == 1) & (row[:, 2] == 1)):
                raise SceneError(f"texture {name}: old-style Radiance run-length encoding is "
                                 "not read", name)
            out[y] = row
            pos += n
    e = out[:, :, 3].astype(np.int32)
    scale = np.where(e == 0, 0.0, np.ldexp(1.0, e - (128 + 8)))
    return np.ascontiguousarray(out[:, :, :3] * scale[:, :, None], dtype=np.float32)
