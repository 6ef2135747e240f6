"""The API's schema families: `JobCreate` in, `Job` stored (models), `JobPublic` out.

Bounds and allowed names shown in the OpenAPI schema are read from the
renderer (`BOUNDS`, `METHODS`, `SAMPLERS`); the checks themselves are the
renderer's (`RenderSpec.validate`), so the API and the CLI refuse the same
things with the same words.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt

from renderer import BOUNDS, METHODS, SAMPLERS, RenderSpec

from .models import Job, WorkUnit

__all__ = ["JobCreate", "JobUpdate", "JobPublic", "PRIORITY_BOUNDS", "Progress", "ScenePublic", "UnitPublic"]

_DEFAULTS = RenderSpec()
PRIORITY_BOUNDS = (-100, 100)

Priority = Annotated[StrictInt, Field(
    ge=PRIORITY_BOUNDS[0], le=PRIORITY_BOUNDS[1],
    description=f"higher runs first ({PRIORITY_BOUNDS[0]}..{PRIORITY_BOUNDS[1]}); "
                "equal priorities: oldest first")]


def _bounded(name: str, description: str):
    lo, hi = BOUNDS[name]
    # Documented here, enforced by RenderSpec.validate (one set of words for every client).
    return Annotated[StrictInt, Field(description=f"{description} ({lo}..{hi})",
                                      json_schema_extra={"minimum": lo, "maximum": hi})]


class JobCreate(BaseModel):
    """A render request: `POST /jobs`."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"scene": "cornell-box", "method": "path", "spp": 16, "depth": 5, "tile_size": 32,
         "seed": 0, "width": 128, "height": 128}]})

    scene: str | dict[str, Any] = Field(
        description="a built-in scene's name, an uploaded scene's id (GET /scenes) "
                    "or an inline scene document")
    method: str = Field(description="rendering method (GET /methods)",
                        json_schema_extra={"enum": list(METHODS)})
    spp: _bounded("spp", "samples per pixel")
    depth: _bounded("depth", "maximum path depth")
    tile_size: _bounded("tile_size", "side of a work unit's tile in pixels") = _DEFAULTS.tile_size
    seed: _bounded("seed", "random seed; same seed, same pixels") = _DEFAULTS.seed
    sampler: str = Field(_DEFAULTS.sampler, description="pixel sampler",
                         json_schema_extra={"enum": list(SAMPLERS)})
    width: _bounded("width", "image width; default: the scene camera's") | None = None
    height: _bounded("height", "image height; default: the scene camera's") | None = None
    options: dict[str, Any] = Field(default_factory=dict,
                                    description="method options (GET /methods lists them)")
    priority: Priority = 0
    progressive: bool = Field(True, description="render in sample passes (1, 1, 2, 4, ... spp "
                                                "per pass) so the preview improves while the "
                                                "job runs; the final image is the same")


class JobUpdate(BaseModel):
    """`PATCH /jobs/{id}`: what can change after submission."""

    model_config = ConfigDict(extra="forbid")

    priority: Priority


class Progress(BaseModel):
    units_done: int
    units_total: int
    fraction: float


class JobPublic(BaseModel):
    """A job as the API shows it."""

    id: str
    status: str
    scene: str
    scene_hash: str
    method: str
    spp: int
    depth: int
    tile_size: int
    seed: int
    sampler: str
    width: int
    height: int
    options: dict[str, Any]
    priority: int
    progressive: bool
    progress: Progress
    created: datetime
    started: datetime | None
    finished: datetime | None
    seconds: float | None = Field(description="from start to finish (or until now)")
    error: str | None
    samples: int
    rays: int
    result_url: str | None
    preview_url: str | None

    @classmethod
    def from_job(cls, job: Job, now: datetime) -> "JobPublic":
        spec = job.spec
        seconds = None
        if job.started is not None:
            seconds = ((job.finished or now) - job.started).total_seconds()
        done = job.status == "done"
        return cls(
            id=job.id, status=job.status, scene=job.scene, scene_hash=job.scene_hash,
            method=spec["method"], spp=spec["spp"], depth=spec["depth"],
            tile_size=spec["tile_size"], seed=spec["seed"], sampler=spec["sampler"],
            width=job.width, height=job.height, options=spec.get("options", {}),
            priority=job.priority or 0, progressive=bool(job.progressive),
            progress=Progress(units_done=job.units_done, units_total=job.units_total,
                              fraction=job.units_done / job.units_total if job.units_total else 0.0),
            created=job.created, started=job.started, finished=job.finished, seconds=seconds,
            error=job.error, samples=job.samples, rays=job.rays,
            result_url=f"/jobs/{job.id}/result.exr" if done else None,
            # The preview is written as units land (see Scheduler): there from the first one.
            preview_url=f"/jobs/{job.id}/preview.png" if done or job.units_done else None)


class ScenePublic(BaseModel):
    """A scene as the API shows it: built in (id = name) or uploaded (id = hash)."""

    id: str = Field(description="what a job's `scene` names: a built-in's name, an upload's hash")
    kind: Literal["builtin", "uploaded"]
    name: str
    description: str
    width: int = Field(description="the camera's default image width")
    height: int
    triangles: int = Field(description="triangles after tessellation (analytic spheres: none)")
    scene_hash: str = Field(description="content hash of the resolved scene (jobs show it)")
    bytes: int = Field(description="size of the resolved scene's canonical text")
    created: datetime | None = Field(description="when it was uploaded (built-ins: null)")
    thumbnail_url: str | None = Field(description="its PNG thumbnail, null until rendered")

    @classmethod
    def from_info(cls, info, thumbnail_ready: bool) -> "ScenePublic":
        """From a `service.scenes.SceneInfo`."""
        return cls(id=info.id, kind=info.kind, name=info.name, description=info.description,
                   width=info.width, height=info.height, triangles=info.triangles,
                   scene_hash=info.scene_hash, bytes=info.bytes, created=info.created,
                   thumbnail_url=f"/scenes/{info.id}/thumbnail.png" if thumbnail_ready else None)


class UnitPublic(BaseModel):
    """A work unit as the API shows it: where it ran, how often, how long."""

    index: int
    state: str
    region: dict[str, int] = Field(description="x0, y0, x1, y1, sample_start, sample_end, pass")
    attempts: int
    tasks: int = Field(description="task ids the unit had (more than attempts: re-enqueued)")
    worker: str | None
    enqueued_at: datetime | None
    started_at: datetime | None
    finished_at: datetime | None
    seconds: float | None = Field(description="render time reported by the worker")
    error: str | None

    @classmethod
    def from_unit(cls, unit: WorkUnit) -> "UnitPublic":
        u = unit.unit
        return cls(index=unit.index, state=unit.state,
                   region={"x0": u["x0"], "y0": u["y0"], "x1": u["x1"], "y1": u["y1"],
                           "sample_start": u["sample_start"], "sample_end": u["sample_end"],
                           "pass": u.get("pass_index", 0)},
                   attempts=unit.attempts, tasks=len(unit.task_ids), worker=unit.worker,
                   enqueued_at=unit.enqueued_at, started_at=unit.started_at,
                   finished_at=unit.finished_at, seconds=unit.seconds, error=unit.error)
