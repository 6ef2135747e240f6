"""A job's image as float data, for the dashboard's HDR viewer and for any
client that wants values rather than a tonemapped PNG.

`GET /jobs/{id}/pixels?layer=beauty` answers one layer's channels as
little-endian float32, row-major and interleaved (height x width x channels),
with the geometry and the channel names in headers. The data are the EXR's
own channels, as `renderer.film.channel_layers` groups them: `beauty` (R, G,
B), `var` (the variance of each pixel's mean), `samples`, and the AOV layers
(`albedo`, `normal`, `depth`) and `denoised` where the job has them.

Where they come from, by the job's state:
- done: its result.exr;
- canceled or failed with units finished: the partial EXR of those units
  (service.results.partial_result);
- running or paused: the frame the scheduler merged so far, which it writes
  (`Store.frame_path`) with the preview while someone fetches either
  (service.previews); a fetch here counts as watching the preview.

Not quantized, not tonemapped: exposure, display transform and channel
choice are the viewer's, and a pixel's value with its standard error
(the square root of var) is what the file holds.
"""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session

from renderer import Film
from renderer.film import channel_layers, read_exr

from . import states
from .access import Principal
from .errors import InvalidRequest, NotFound, ResultNotReady
from .jobs import get_job, partial_result_files
from .store import Store

__all__ = ["Pixels", "job_pixels", "write_frame"]


@dataclass(frozen=True)
class Pixels:
    width: int
    height: int
    layer: str
    channels: list[str]  # the layer's channel names, in the data's order
    layers: dict[str, list[str]]  # every layer the image has
    source: str  # "final", "partial" or "running"
    data: bytes  # float32 little-endian, (height, width, len(channels))


def write_frame(store: Store, job_id: str, film: Film) -> None:
    """Write a running job's merged frame (`Film.channels`) for `job_pixels`,
    atomically: a reader sees the previous frame or this one."""
    path = store.frame_path(job_id)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}.npz")
    try:
        with open(tmp, "wb") as out:
            np.savez(out, **film.channels())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _channels(session: Session, store: Store, actor: Principal,
              job_id: str) -> tuple[dict[str, np.ndarray], str]:
    job = get_job(session, actor, job_id)
    if job.status == "done":
        path = store.result_path(job.id)
        if not path.is_file():
            raise NotFound(f"job '{job_id}' has no result.exr")
        return read_exr(path)[0], "final"
    if job.status in ("canceled", "failed") and job.units_done:
        return read_exr(partial_result_files(session, store, job)[0])[0], "partial"
    if job.status in states.SCHEDULED_JOB:
        store.mark_watched(job.id, "preview")  # someone looks: keep the frame written
        try:
            with np.load(store.frame_path(job.id)) as frame:
                return {name: frame[name] for name in frame.files}, "running"
        except FileNotFoundError:
            pass
    raise ResultNotReady(f"job '{job_id}' is {job.status}; its pixels exist once its first "
                         "unit is done")


def job_pixels(session: Session, store: Store, actor: Principal, job_id: str,
               layer: str) -> Pixels:
    """One layer of the job's image (module doc); `InvalidRequest` naming the
    layers there are for one the image does not have."""
    channels, source = _channels(session, store, actor, job_id)
    layers = channel_layers(channels)
    if layer not in layers:
        raise InvalidRequest("layer", f"no layer {layer!r} in this image; it has "
                             + ", ".join(layers), source="query")
    names = layers[layer]
    stack = np.stack([channels[n] for n in names], axis=-1).astype("<f4", copy=False)
    height, width = stack.shape[:2]
    return Pixels(width, height, layer, names, layers, source,
                  np.ascontiguousarray(stack).tobytes())
