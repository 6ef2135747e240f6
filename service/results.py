"""A finished job's images: its stored unit films merged in unit order (plain
addition, then one division: `renderer.merge`) into `result.exr`, with the
final `preview.png` and `noise.png`.

    write_result(store, job_id, width, height, units=16, metadata={"method": "path", ...})
"""

from __future__ import annotations

from renderer import PartialFilm, merge

from .store import Store

__all__ = ["EXR_METADATA_KEYS", "write_result"]

EXR_METADATA_KEYS = ("job_id", "scene", "scene_hash", "method", "spp", "depth", "seed",
                     "sampler", "tile_size", "width", "height")


def write_result(store: Store, job_id: str, width: int, height: int, units: int,
                 metadata: dict) -> None:
    """Merge units 0..units-1 of the job and write its EXR (with `metadata` as
    `rayfarm.*` header attributes) and PNGs; raises what reading or writing raises."""
    film = merge(width, height, (PartialFilm.from_bytes(store.unit_film(job_id, i))
                                 for i in range(units)))
    film.write_exr(store.result_path(job_id), {k: str(metadata[k]) for k in EXR_METADATA_KEYS})
    film.write_png(store.preview_path(job_id))
    film.write_noise_png(store.noise_path(job_id))
