"""The oracle of the banded merge's tests: a finished frame's contents as the
whole-frame float64 merge made them before (tests/test_renderer_stream.py,
tests/test_service_results.py)."""

from __future__ import annotations

import numpy as np

from renderer import merge
from renderer.film import image_error, noise_srgb8, tonemap_srgb8


def whole_frame(width: int, height: int, films, denoise: bool = False) -> dict:
    """The files' contents as they were made before: the whole frame's
    float64 sums (`renderer.merge`), its mean and variance at once, the EXR's
    channels cast from them, OIDN on the whole frame's inputs."""
    film = merge(width, height, films)
    mean, var = film.mean(), film.variance_of_mean()
    m32, v32 = mean.astype(np.float32), var.astype(np.float32)
    channels = {c: m32[..., i].copy() for i, c in enumerate("RGB")}
    channels.update({f"var.{c}": v32[..., i].copy() for i, c in enumerate("RGB")})
    channels.update({name: np.ascontiguousarray(a, dtype=np.float32)
                     for name, a in film.aovs().items()})
    out = {"channels": channels, "rel_error": image_error(mean, var),
           "preview": tonemap_srgb8(mean), "noise": noise_srgb8(mean, var),
           "stats": film.stats}
    if denoise:
        import pyoidn

        color = np.ascontiguousarray(np.nan_to_num(mean, nan=0.0, posinf=0.0, neginf=0.0),
                                     dtype=np.float32)
        aovs = film.aovs()
        albedo = np.clip(np.stack([aovs[f"albedo.{c}"] for c in "RGB"], -1).astype(np.float32),
                         0.0, 1.0)
        normal = np.clip(np.stack([aovs[f"normal.{c}"] for c in "XYZ"], -1).astype(np.float32),
                         -1.0, 1.0)
        clean = pyoidn.denoise(np.maximum(color, 0.0), np.ascontiguousarray(albedo),
                               np.ascontiguousarray(normal), hdr=True, quality="high")
        channels.update({f"denoised.{c}": np.ascontiguousarray(clean[..., i], dtype=np.float32)
                         for i, c in enumerate("RGB")})
        out["denoised"] = tonemap_srgb8(clean)
    return out
