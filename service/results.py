"""A finished job's images: its stored unit films merged in unit order (plain
addition, then one division: `renderer.merge`) into `result.exr`, with the
final `preview.png` and `noise.png`.

    write_result(store, job_id, spec, units=16, scene="cornell-box", scene_hash=key)

The EXR's header is `renderer.metadata.exr_metadata`'s: the same keys as a
file from `rayfarm render`.
"""

from __future__ import annotations

from renderer import PartialFilm, RenderSpec, merge
from renderer.metadata import exr_metadata

from .store import Store

__all__ = ["write_result"]


def write_result(store: Store, job_id: str, spec: RenderSpec, units: int, *, scene: str,
                 scene_hash: str, denoise: bool = False) -> None:
    """Merge units 0..units-1 of the job and write its EXR and PNGs (with
    `denoise`, the whole merged frame denoised once: renderer.denoise); raises
    what reading or writing raises."""
    film = merge(spec.width, spec.height, (PartialFilm.from_bytes(store.unit_film(job_id, i))
                                           for i in range(units)))
    clean = None
    if denoise:
        from renderer.denoise import denoise_film

        clean = denoise_film(film)
        film.write_png(store.denoised_path(job_id), clean)
    film.write_exr(store.result_path(job_id),
                   exr_metadata(spec, film.stats, scene=scene, scene_hash=scene_hash,
                                job_id=job_id, rel_error=film.image_error(),
                                denoised=clean is not None),
                   denoised=clean)
    film.write_png(store.preview_path(job_id))
    film.write_noise_png(store.noise_path(job_id))
