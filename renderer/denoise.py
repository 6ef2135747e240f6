"""One denoise of a finished frame: Intel Open Image Denoise (the `pyoidn`
package, CPU; its wheel ships the library) over the merged film.

    rgb = denoise_film(film)          # float32 (h, w, 3), beside film.mean()

Why after the merge and never per unit: a denoiser looks at a neighbourhood,
so a tile denoised alone is filtered differently at its border than inside,
and the seams show (Deadline's tile assembler has this problem). The merge
here is exact, so the frame it makes is the one a single machine would have
rendered, and one pass over it has no borders to disagree about.

The input is the beauty's per-pixel mean as HDR colour, with the film's
albedo and normal AOVs as auxiliary images when the method wrote them
(film.py; `prefilter` is left on: they are sample means, noisy where a pixel's
samples disagree). Without AOVs the colour is denoised alone, which OIDN
supports at a lower quality. The result is a biased estimate: it trades noise
for blur, and its error is not what the var channels describe, so it never
replaces the raw image.
"""

from __future__ import annotations

import numpy as np

from .film import Film

__all__ = ["denoise_film", "denoise_images", "denoiser_version"]


def denoise_film(film: Film) -> np.ndarray:
    """The film's beauty denoised by OIDN's RT filter (quality "high"), float32
    (h, w, 3); non-finite pixels (no sample yet) are passed as black."""
    images = film.images(denoise=True)
    return denoise_images(images.color, images.channels)


def denoise_images(color: np.ndarray, channels: dict[str, np.ndarray]) -> np.ndarray:
    """`denoise_film` of a frame given as its `FrameImages` parts (a merge
    made band by band: renderer.stream): `color`, the finite beauty as
    float32 (h, w, 3), and the float32 `channels`, whose albedo and normal
    AOVs guide the filter where the method wrote them."""
    import pyoidn

    albedo = normal = None
    if "albedo.R" in channels:
        albedo = np.stack([channels[f"albedo.{c}"] for c in "RGB"], axis=-1).astype(np.float32)
        normal = np.stack([channels[f"normal.{c}"] for c in "XYZ"], axis=-1).astype(np.float32)
        albedo = np.ascontiguousarray(np.clip(albedo, 0.0, 1.0))
        normal = np.ascontiguousarray(np.clip(normal, -1.0, 1.0))
    return pyoidn.denoise(np.maximum(color, 0.0), albedo, normal, hdr=True, quality="high")


def denoiser_version() -> str:
    """"Open Image Denoise via pyoidn <version>", for reports (bench/denoise.py)."""
    import importlib.metadata

    return f"Open Image Denoise via pyoidn {importlib.metadata.version('pyoidn')}"
