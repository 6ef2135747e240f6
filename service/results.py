"""A finished job's images: its stored unit films merged in unit order (plain
addition, then one division: `renderer.merge`) into `result.exr`, with the
final `preview.png` and `noise.png`.

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

from renderer import PartialFilm, RenderSpec, merge
from renderer.metadata import exr_metadata
from renderer.target import Target

from .store import Store

__all__ = ["partial_result", "write_result"]


def write_result(store: Store, job_id: str, spec: RenderSpec, units: Iterable[int], *,
                 scene: str, scene_hash: str, denoise: bool = False,
                 target: Target | None = None) -> float:
    """Merge the job's `units` (indices, in unit order) and write its EXR and
    PNGs (with `denoise`, the whole merged frame denoised once:
    renderer.denoise); returns the image's error statistic
    (film.image_error); raises what reading or writing raises."""
    film = merge(spec.width, spec.height, (PartialFilm.from_bytes(store.unit_film(job_id, i))
                                           for i in units))
    rel_error = film.image_error()
    clean = None
    if denoise:
        from renderer.denoise import denoise_film

        clean = denoise_film(film)
        film.write_png(store.denoised_path(job_id), clean)
    film.write_exr(store.result_path(job_id),
                   exr_metadata(spec, film.stats, scene=scene, scene_hash=scene_hash,
                                job_id=job_id, rel_error=rel_error, target=target,
                                denoised=clean is not None),
                   denoised=clean)
    film.write_png(store.preview_path(job_id))
    film.write_noise_png(store.noise_path(job_id))
    store.frame_path(job_id).unlink(missing_ok=True)  # the running frame: the EXR serves now
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
    film = merge(spec.width, spec.height, (PartialFilm.from_bytes(store.unit_film(job_id, i))
                                           for i in units))
    meta = exr_metadata(spec, film.stats, scene=scene, scene_hash=scene_hash, job_id=job_id,
                        rel_error=film.image_error(), target=target, partial=True)
    for path, write in ((exr, lambda p: film.write_exr(p, meta)), (png, film.write_png)):
        tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}{path.suffix}")
        try:
            write(tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    store.clear_partials(job_id, keep=len(units))
    return exr, png
