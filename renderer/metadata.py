"""What a rayfarm EXR says about itself: one set of header attributes for the
service's `result.exr` and for `rayfarm render`'s file, the same keys in both.

    film.write_exr(path, exr_metadata(spec, film.stats, scene="cornell-box",
                                      scene_hash=key, job_id=job.id))

Every key is written as `rayfarm.<key>` with an EXR type a tool can read back
as a number where the value is one (`exrheader`, tev, Nuke's metadata view):

| key | EXR type | value |
|---|---|---|
| job_id | string | the farm job's id; "" for a local render |
| scene, scene_hash | string | the scene's name and the hash of its canonical text |
| method | string | the method's name (an alias such as `path` is resolved to `path-mis`) |
| options | string | the method's options as JSON (sorted keys) |
| sampler | string | the pixel sampler |
| seed | string | decimal: seeds go up to 2^63 - 1 |
| spp, depth, width, height, tile_size | int | |
| samples, rays | string | decimal: they outgrow 32 bits |
| render_seconds | float | the units' render time, summed over units (not wall time) |
| rel_error | float | the raw image's error statistic (`film.image_error`): the 95th percentile over pixels brighter than 1 % of the image mean of the relative standard error from the var channels |
| target | string | the noise target as JSON (rel_error, max_spp, max_seconds; renderer/target.py), "" for a fixed spp |
| denoised | int | 1 if the file also holds denoised.R/G/B (the raw R/G/B stay as rendered), else 0 |
| partial | int | 1 for the units a canceled or failed job finished (pixels without a sample read 0, `samples.Y` says which), else 0 |

The OpenEXR package writes Python ints as 32-bit `int` attributes (a larger
value is stored as 0, silently) and Python floats as 32-bit `float`; it has no
way to write a `double` or a 64-bit integer. So counts that can pass 2^31 are
decimal strings, exact, and `Film.write_exr` refuses an int that does not fit.
`Film.write_exr` adds the standard attributes `software` ("rayfarm <version>"),
`capDate` (when the file was written, "YYYY:MM:DD hh:mm:ss" in UTC) and
`utcOffset` (0.0: capDate is UTC).
"""

from __future__ import annotations

import json
from typing import Any

from .spec import RenderSpec

__all__ = ["METADATA_KEYS", "exr_metadata"]

METADATA_KEYS = ("job_id", "scene", "scene_hash", "method", "options", "sampler", "seed", "spp",
                 "depth", "width", "height", "tile_size", "samples", "rays", "render_seconds",
                 "rel_error", "target", "denoised", "partial")


def exr_metadata(spec: RenderSpec, stats: dict[str, Any], *, scene: str, scene_hash: str,
                 job_id: str = "", rel_error: float = float("nan"), target=None,
                 denoised: bool = False, partial: bool = False) -> dict[str, str | int | float]:
    """The `rayfarm.*` attributes of an image rendered with `spec` (the
    statistics `stats` of its merged film: samples, rays, seconds; its
    `rel_error`, film.image_error)."""
    meta: dict[str, str | int | float] = {
        "job_id": job_id, "scene": scene, "scene_hash": scene_hash,
        "method": spec.method, "options": json.dumps(spec.options, sort_keys=True),
        "sampler": spec.sampler, "seed": str(spec.seed),
        "spp": spec.spp, "depth": spec.depth, "width": spec.width, "height": spec.height,
        "tile_size": spec.tile_size,
        "samples": str(int(stats.get("samples", 0))), "rays": str(int(stats.get("rays", 0))),
        "render_seconds": float(stats.get("seconds", 0.0)), "rel_error": float(rel_error),
        "target": "" if target is None else json.dumps(target.to_dict(), sort_keys=True),
        "denoised": int(bool(denoised)), "partial": int(bool(partial)),
    }
    assert tuple(meta) == METADATA_KEYS
    return meta
