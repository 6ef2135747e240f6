"""A finished job's images: its stored unit films merged in unit order (plain
addition, then one division) into `result.exr`, with the final
`preview.png` and `noise.png`. The merge reads the films band by band
(`renderer.stream.merge_frame`: the same bits as `renderer.merge`, without
the frame's float64 sums in memory).

    write_result(store, job_id, spec, range(16), scene="cornell-box", scene_hash=key)

A target job's skipped units have no film: `units` lists those merged.

The EXR's header is `renderer.metadata.exr_metadata`'s: the same keys as a
file from `rayfarm render`.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Iterable

from renderer import RenderSpec
from renderer.images import denoised_channels, tonemap_rows, write_exr, write_png
from renderer.metadata import exr_metadata
from renderer.stream import merge_frame
from renderer.target import Target

from .store import Store

__all__ = ["partial_result", "write_result", "return_free_memory"]


def write_result(store: Store, job_id: str, spec: RenderSpec, units: Iterable[int], *,
                 scene: str, scene_hash: str, denoise: bool = False,
                 target: Target | None = None) -> float:
    """Merge the job's `units` (indices, in unit order) and write its EXR and
    PNGs (with `denoise`, the whole merged frame denoised once:
    renderer.denoise); returns the image's error statistic
    (film.image_error); raises what reading or writing raises."""
    images = merge_frame(spec.width, spec.height, [store.unit_path(job_id, i) for i in units],
                         tile=spec.tile_size, preview=True, noise=True, denoise=denoise)
    rel_error = images.rel_error
    channels = images.channels
    if denoise:
        from renderer.denoise import denoise_images

        clean = denoise_images(images.color, channels)
        images.color = None
        write_png(store.denoised_path(job_id), tonemap_rows(clean))
        channels = {**channels, **denoised_channels(clean)}
        del clean
    write_exr(store.result_path(job_id), channels,
              exr_metadata(spec, images.stats, scene=scene, scene_hash=scene_hash, job_id=job_id,
                           rel_error=rel_error, target=target, denoised=denoise))
    channels = images.channels = None  # the channels go before the PNGs are encoded
    write_png(store.preview_path(job_id), images.preview)
    write_png(store.noise_path(job_id), images.noise)
    store.frame_path(job_id).unlink(missing_ok=True)  # the running frame: the EXR serves now
    del images
    return_free_memory()
    return rel_error


def partial_result(store: Store, job_id: str, spec: RenderSpec, units: list[int], *,
                   scene: str, scene_hash: str, target: Target | None = None
                   ) -> tuple[Path, Path]:
    """The EXR and PNG of a canceled or failed job's finished `units` (indices,
    in unit order), merged as a done job's are and marked partial in the
    header; written once per count of units, atomically (two requests at
    once write the same bytes)."""
    exr, png = store.partial_paths(job_id, len(units))
    if exr.is_file() and png.is_file():
        return exr, png
    images = merge_frame(spec.width, spec.height, [store.unit_path(job_id, i) for i in units],
                         tile=spec.tile_size, preview=True)
    meta = exr_metadata(spec, images.stats, scene=scene, scene_hash=scene_hash, job_id=job_id,
                        rel_error=images.rel_error, target=target, partial=True)
    for path, write in ((exr, lambda p: write_exr(p, images.channels, meta)),
                        (png, lambda p: write_png(p, images.preview))):
        tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}{path.suffix}")
        try:
            write(tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    store.clear_partials(job_id, keep=len(units))
    del images
    return_free_memory()
    return exr, png


def return_free_memory() -> None:
    """Give the C heap's free pages back to the system (glibc's malloc_trim;
    nothing elsewhere). Arrays above glibc's mmap threshold go back when
    freed, but the threshold rises to the largest array freed (up to 32 MB),
    and the band arrays of a merge and the films of landed units are below
    it: their pages stay in the service's heaps, freed but resident (the
    service kept 0.25 to 0.8 GB after a 1024^2 or 2048^2 job without this;
    docs/hardening.md)."""
    global _malloc_trim
    if _malloc_trim is None:
        try:
            import ctypes

            _malloc_trim = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _malloc_trim = False
    if _malloc_trim:
        _malloc_trim(0)


_malloc_trim = None  # libc's malloc_trim once looked up, False where there is none
