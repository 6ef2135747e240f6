"""The API's schema families: `JobCreate` in, `Job` stored (models), `JobPublic` out.

Bounds and allowed names shown in the OpenAPI schema are read from the
renderer (`BOUNDS`, `METHODS`, `SAMPLERS`); the checks themselves are the
renderer's (`RenderSpec.validate`), so the API and the CLI refuse the same
things with the same words.

Every request body is a `RequestModel`: unknown fields are refused, and
nothing is coerced (strict: "4" is no integer, "yes" no boolean, 2.0 no
integer); numbers are finite. Python's JSON reader accepts NaN, Infinity
and 1e999 (= inf), which no JSON writer may send back: a typed field refuses
them, and the free-form parts (a job's `options`, an inline `scene`) refuse
them wherever they hide, naming the path, as they refuse nesting deeper than
MAX_JSON_DEPTH.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, StrictBool, StrictFloat,
                      StrictInt, StrictStr)
from pydantic_core import PydanticCustomError

from renderer import BOUNDS, METHODS, SAMPLERS, RenderSpec
from renderer.target import MAX_SECONDS, REL_ERROR_BOUNDS

from .executors import WorkerInfo
from .models import ApiToken, Job, User, WorkUnit
from .figures import job_figures

__all__ = ["ReportEntryPublic", "RequestModel", "UnitLogPublic", "UnitAttemptLog", "JobCreate", "TargetRequest", "JobUpdate", "JobPublic", "JobStats", "PRIORITY_BOUNDS",
           "Progress", "ScenePublic", "UnitPublic", "WorkerPublic", "LoginRequest", "Me", "UserCreate",
           "UserUpdate", "UserPublic", "TokenCreate", "TokenPublic", "TokenCreated"]

_DEFAULTS = RenderSpec()
PRIORITY_BOUNDS = (-100, 100)


class RequestModel(BaseModel):
    """A request body: strict types, finite numbers, no unknown fields."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


MAX_JSON_DEPTH = 32  # levels of lists and objects in a free-form part (a scene needs 6)


def _first_problem(value: Any) -> str | None:
    """What is wrong with parsed free-form JSON, naming the path: a NaN or an
    infinity, or nesting deeper than MAX_JSON_DEPTH (which would exhaust the
    stack of whatever reads it next); None if nothing. Iterative."""
    stack: list[tuple[str, Any, int]] = [("", value, 1)]
    while stack:
        path, item, depth = stack.pop()
        where = path or "the value"
        if isinstance(item, float) and not math.isfinite(item):
            return f"{where} must be a finite number, got {item!r} (JSON has no NaN or Infinity)"
        if isinstance(item, dict):
            children = [(f"{path}.{key}" if path else str(key), v) for key, v in item.items()]
        elif isinstance(item, list):
            children = [(f"{path}[{i}]", v) for i, v in enumerate(item)]
        else:
            continue
        if depth > MAX_JSON_DEPTH:
            return (f"nests lists and objects more than {MAX_JSON_DEPTH} levels deep "
                    f"(at {where[:40]}{'...' if len(where) > 40 else ''})")
        stack.extend((where_, child, depth + 1) for where_, child in reversed(children))
    return None


def _plain_json(value: Any) -> Any:
    problem = _first_problem(value)
    if problem:
        raise PydanticCustomError("plain_json", "{problem}", {"problem": problem})
    return value


# Free-form JSON with finite numbers and a sane depth (the renderer checks the rest).
PlainJson = AfterValidator(_plain_json)


Priority = Annotated[StrictInt, Field(
    ge=PRIORITY_BOUNDS[0], le=PRIORITY_BOUNDS[1],
    description=f"higher runs first ({PRIORITY_BOUNDS[0]}..{PRIORITY_BOUNDS[1]}); "
                "equal priorities: oldest first")]


def _bounded(name: str, description: str):
    lo, hi = BOUNDS[name]
    # Documented here, enforced by RenderSpec.validate (one set of words for every client).
    return Annotated[StrictInt, Field(description=f"{description} ({lo}..{hi})",
                                      json_schema_extra={"minimum": lo, "maximum": hi})]


class TargetRequest(RequestModel):
    """`target` of a job: render passes until the image's error statistic
    meets `rel_error`, or a budget runs out (renderer/target.py)."""

    # Documented here, enforced by Target.validate (as the job's bounds are).
    rel_error: float = Field(description="the relative standard error to reach, e.g. 0.01 for "
                                         "1 %: the 95th percentile over the pixels brighter than "
                                         "1 % of the image mean, from the var channels "
                                         f"({REL_ERROR_BOUNDS[0]:g}..{REL_ERROR_BOUNDS[1]:g})",
                             json_schema_extra={"minimum": REL_ERROR_BOUNDS[0],
                                                "maximum": REL_ERROR_BOUNDS[1]})
    max_spp: StrictInt | None = Field(None, description="samples per pixel at most (default: "
                                                        "the job's spp)",
                                      json_schema_extra={"minimum": BOUNDS["spp"][0],
                                                         "maximum": BOUNDS["spp"][1]})
    max_seconds: float | None = Field(None, description="stop after this many seconds of running "
                                                        "(checked between passes; at most "
                                                        f"{MAX_SECONDS:.0f}: 366 days)",
                                      json_schema_extra={"exclusiveMinimum": 0,
                                                         "maximum": MAX_SECONDS})


class JobCreate(RequestModel):
    """A render request: `POST /jobs`."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"scene": "cornell-box", "method": "path", "spp": 16, "depth": 5, "tile_size": 32,
         "seed": 0, "width": 128, "height": 128}]})

    scene: Annotated[str | dict[str, Any], PlainJson] = Field(
        description="a built-in scene's name, an uploaded scene's id (GET /scenes) "
                    "or an inline scene document")
    method: str = Field(description="rendering method (GET /methods)",
                        json_schema_extra={"enum": list(METHODS)})
    spp: _bounded("spp", "samples per pixel (with a target: at most, the default max_spp)") \
        | None = None
    depth: _bounded("depth", "maximum path depth; default: the scene's defaults.max_depth (an "
                             "imported file's integrator block), else 5") | None = None
    tile_size: _bounded("tile_size", "side of a work unit's tile in pixels") = _DEFAULTS.tile_size
    seed: _bounded("seed", "random seed; same seed, same pixels") = _DEFAULTS.seed
    sampler: str = Field(_DEFAULTS.sampler, description="pixel sampler",
                         json_schema_extra={"enum": list(SAMPLERS)})
    width: _bounded("width", "image width; default: the scene camera's") | None = None
    height: _bounded("height", "image height; default: the scene camera's") | None = None
    options: Annotated[dict[str, Any], PlainJson] = Field(
        default_factory=dict, description="method options (GET /methods lists them)")
    priority: Priority = 0
    progressive: StrictBool = Field(True, description="render in sample passes (1, 1, 2, 4, ... "
                                                      "spp per pass) so the preview improves "
                                                      "while the job runs; the final image is "
                                                      "the same")
    denoise: StrictBool = Field(False, description="when done, also denoise the merged frame "
                                                   "(Intel Open Image Denoise with the albedo "
                                                   "and normal AOVs): denoised.R/G/B in the EXR "
                                                   "beside the raw beauty, and denoised.png. A "
                                                   "biased post-process: the raw image and its "
                                                   "var channels stay as rendered")
    target: TargetRequest | None = Field(None, description="render to a noise target instead of "
                                                           "a fixed spp: passes are added, tile "
                                                           "by tile, until the error meets it "
                                                           "(tile methods only; GET /methods)")


class JobUpdate(RequestModel):
    """`PATCH /jobs/{id}`: what can change after submission."""

    priority: Priority


class Progress(BaseModel):
    """How far a job is, and how long the rest should take at the measured rate."""

    units_done: int
    units_total: int
    samples_done: int = Field(description="camera samples rendered so far")
    samples_total: int = Field(description="width x height x spp")
    fraction: float | None = Field(description="samples_done / samples_total")
    elapsed: float | None = Field(description="seconds the job has been able to run: from its "
                                              "start, pauses excluded (null before the start)")
    eta: float | None = Field(description="seconds left at the job's recent samples/s, at "
                                          "least a mean unit's render time while units are "
                                          "left (null unless running with a rate measured "
                                          "between two landings of units); a "
                                          "target job's: until its error meets the target")
    rel_error: float | None = Field(None, description="the image's error statistic (95th "
                                                      "percentile of the relative standard "
                                                      "error): after the last complete pass of "
                                                      "a progressive job, of the result once "
                                                      "done")
    target_rel_error: float | None = Field(None, description="a target job's target")
    units_skipped: int = Field(0, description="a target job's units skipped: their region met "
                                              "the target first (counted in units_done)")


class JobStats(BaseModel):
    """Throughput of a job so far."""

    samples_per_second: float | None = Field(description="camera samples / elapsed seconds")
    recent_samples_per_second: float | None = Field(
        description="samples/s over about the last ten seconds (drives the ETA)")
    rays_per_second: float | None = Field(description="rays traced / elapsed seconds")
    seconds_per_unit: float | None = Field(description="mean render seconds of a done unit, as "
                                                       "its worker measured it")
    units_retried: int = Field(description="done units that needed more than one task "
                                           "(their worker was lost, or an attempt failed)")


class JobPublic(BaseModel):
    """A job as the API shows it. A figure derived from its counters (progress,
    ETA, rates) that cannot be computed is null (service.figures)."""

    id: str
    status: str
    owner: str = Field(description="the user who submitted it")
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
    denoise: bool
    target: dict[str, Any] | None = Field(None, description="the noise target (rel_error, "
                                                            "max_spp, max_seconds), if any")
    target_stop: str | None = Field(None, description="why a target job stopped: target, "
                                                      "max_spp or max_seconds")
    passes: list[dict[str, Any]] = Field(default_factory=list, description=(
        "a progressive tile job's complete passes, in order (its convergence): pass, spp "
        "reached, samples and active seconds so far, rel_error of the passes so far merged "
        "(null while a pixel has one sample), pixels still refined (a target's skipped tiles "
        "are not)"))
    progress: Progress
    stats: JobStats
    created: datetime
    started: datetime | None
    finished: datetime | None
    seconds: float | None = Field(description="from start to finish (or until now), "
                                              "pauses excluded: progress.elapsed")
    error: str | None
    samples: int
    rays: int
    result_url: str | None = Field(description="the EXR: a done job's, or (`partial`) the units "
                                                "a canceled or failed job finished")
    partial: bool = Field(False, description="result_url and preview_url hold only the units "
                                             "that finished before the job was canceled or "
                                             "failed (the EXR header says rayfarm.partial = 1)")
    preview_url: str | None
    noise_url: str | None = Field(description="per-pixel noise heatmap (relative standard error)")
    denoised_url: str | None = Field(None, description="the denoised frame's preview (jobs "
                                                       "with `denoise`, once done): a biased "
                                                       "post-process of the raw image")
    events_url: str = Field(description="server-sent events of this job")

    @classmethod
    def from_job(cls, job: Job, now: datetime) -> "JobPublic":
        """The job as shown at `now`; never raises for a figure it derives
        (service.figures: one that cannot be computed is null)."""
        spec = job.spec
        figures = job_figures(job, now)
        done = job.status == "done"
        partial = job.status in ("canceled", "failed") and bool(job.units_done)
        return cls(
            id=job.id, status=job.status, owner=job.owner, scene=job.scene, scene_hash=job.scene_hash,
            method=spec["method"], spp=spec["spp"], depth=spec["depth"],
            tile_size=spec["tile_size"], seed=spec["seed"], sampler=spec["sampler"],
            width=job.width, height=job.height, options=spec.get("options", {}),
            priority=job.priority or 0, progressive=bool(job.progressive),
            denoise=bool(job.denoise), target=job.target, target_stop=job.target_stop,
            passes=job.pass_log or [],
            progress=Progress(units_done=job.units_done, units_total=job.units_total,
                              samples_done=job.samples, samples_total=job.samples_total,
                              fraction=figures["fraction"], elapsed=figures["elapsed"],
                              eta=figures["eta"], rel_error=figures["rel_error"],
                              target_rel_error=(job.target or {}).get("rel_error"),
                              units_skipped=job.units_skipped or 0),
            stats=JobStats(samples_per_second=figures["samples_per_second"],
                           recent_samples_per_second=figures["recent_samples_per_second"],
                           rays_per_second=figures["rays_per_second"],
                           seconds_per_unit=figures["seconds_per_unit"],
                           units_retried=job.units_retried or 0),
            created=job.created, started=job.started, finished=job.finished,
            seconds=figures["elapsed"],
            error=job.error, samples=job.samples, rays=job.rays,
            result_url=f"/jobs/{job.id}/result.exr" if done or partial else None,
            partial=partial,
            # The preview is written as units land (see Scheduler): there from the first one.
            preview_url=f"/jobs/{job.id}/preview.png" if done or job.units_done else None,
            noise_url=f"/jobs/{job.id}/noise.png" if done or job.units_done else None,
            denoised_url=f"/jobs/{job.id}/denoised.png" if done and job.denoise else None,
            events_url=f"/jobs/{job.id}/events")


class ReportEntryPublic(BaseModel):
    """One line of an import report: what rayfarm did not take as written."""

    element: str = Field(description='the element, e.g. bsdf type="roughplastic" id="Floor"')
    file: str = Field(description="the file holding it, its path in the upload")
    line: int | None = Field(description="its line in that file (null where it has none)")
    action: str = Field(description="what was done instead: approximated as X, ignored")


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
    source: str = Field("", description="an upload's scene file, its path in the upload "
                                        "(built-ins: empty)")
    report: list[ReportEntryPublic] = Field(
        default_factory=list, description="the import report: each element of the uploaded "
                                          "files rayfarm does not render as written, where it "
                                          "is and what was done instead (empty: all as written)")
    default_depth: int | None = Field(
        None, description="a job's depth when it gives none: the scene's defaults.max_depth "
                          "(an imported file's integrator), else the renderer's default; null: "
                          "an upload recorded before this field (its jobs read the file)")

    @classmethod
    def from_info(cls, info, thumbnail_ready: bool) -> "ScenePublic":
        """From a `service.scenes.SceneInfo`."""
        return cls(id=info.id, kind=info.kind, name=info.name, description=info.description,
                   width=info.width, height=info.height, triangles=info.triangles,
                   scene_hash=info.scene_hash, bytes=info.bytes, created=info.created,
                   thumbnail_url=f"/scenes/{info.id}/thumbnail.png" if thumbnail_ready else None,
                   source=info.source, report=[ReportEntryPublic(
                       element=str(e.get("element", "")), file=str(e.get("file", "")),
                       line=e["line"] if isinstance(e.get("line"), int) else None,
                       action=str(e.get("action", ""))) for e in info.report],
                   default_depth=info.default_depth)


class UnitPublic(BaseModel):
    """A work unit as the API shows it: where it ran, how often, how long."""

    index: int
    state: str
    region: dict[str, int] = Field(description="x0, y0, x1, y1, sample_start, sample_end, pass")
    stage: int = Field(0, description="DAG stage: a unit runs once the units it needs are done")
    kind: str = Field("tile", description="the unit's phase: tile, splat, bootstrap, chains, "
                                          "photons, gather, solve...")
    needs: list[int] = Field(default_factory=list, description="indices of the units it reads")
    attempts: int
    tasks: int = Field(description="task ids the unit had (more than attempts: re-enqueued)")
    worker: str | None
    enqueued_at: datetime | None
    started_at: datetime | None
    finished_at: datetime | None
    seconds: float | None = Field(description="render time reported by the worker")
    error: str | None
    requeue_reason: str | None = Field(
        None, description="why it was last enqueued again without spending an attempt: its "
                          "worker lost, no heartbeat for a lease, its message lost, declined "
                          "by a worker, withdrawn or preempted for another owner's fair share "
                          "of the render processes (null if never)")
    film_digest: str | None = Field(
        None, description="SHA-256 of the unit's stored partial film, once done: the name "
                          "later units of a DAG job and the workers know it by")

    @classmethod
    def from_unit(cls, unit: WorkUnit) -> "UnitPublic":
        u = unit.unit
        return cls(index=unit.index, state=unit.state,
                   region={"x0": u["x0"], "y0": u["y0"], "x1": u["x1"], "y1": u["y1"],
                           "sample_start": u["sample_start"], "sample_end": u["sample_end"],
                           "pass": u.get("pass_index", 0)},
                   stage=u.get("stage", 0), kind=u.get("kind", "tile"),
                   needs=list(u.get("needs") or ()), attempts=unit.attempts, tasks=len(unit.task_ids), worker=unit.worker,
                   enqueued_at=unit.enqueued_at, started_at=unit.started_at,
                   finished_at=unit.finished_at, seconds=unit.seconds, error=unit.error,
                   requeue_reason=unit.requeue_reason, film_digest=unit.film_digest)


class UnitAttemptLog(BaseModel):
    """What one task of a unit logged in its render process (renderer.unitlog)."""

    task: int = Field(description="the task's number among the unit's tasks (1 = first)")
    attempt: int = Field(description="the unit's attempt count when the task reported")
    outcome: str = Field(description="done or failed")
    worker: str | None
    error: str | None
    at: datetime | None = Field(None, description="when the service collected it")
    lines: list[str] = Field(description="the last log lines (INFO and above), oldest first")
    dropped: int = Field(0, description="earlier lines dropped to keep the log bounded")
    traceback: str | None = Field(description="the exception's traceback, if the task failed")


class UnitLogPublic(BaseModel):
    """A unit's logs, one per task that reported (GET /jobs/{id}/units/{i}/log)."""

    job_id: str
    index: int
    state: str
    error: str | None
    attempts: list[UnitAttemptLog]

    @classmethod
    def from_unit(cls, unit: WorkUnit, logs: list[dict]) -> "UnitLogPublic":
        return cls(job_id=unit.job_id, index=unit.index, state=unit.state, error=unit.error,
                   attempts=[UnitAttemptLog.model_validate(entry) for entry in logs])


class RunningUnitPublic(BaseModel):
    job_id: str
    index: int
    since: datetime | None


class WorkerPublic(BaseModel):
    """A render worker: a Celery worker node or the embedded pool."""

    name: str
    kind: str = Field(description="celery or local")
    host: str
    state: str = Field(description="busy, idle, lost (heartbeats stopped) or offline "
                                   "(shut down cleanly)")
    concurrency: int = Field(description="render processes")
    running: list[RunningUnitPublic] = Field(description="units its processes render now")
    units_done: int
    samples: int
    rays: int
    seconds: float = Field(description="render seconds of the units it finished")
    samples_per_second: float | None = Field(description="samples / render seconds: the speed "
                                                         "of one of its render processes")
    started: datetime | None
    last_seen: datetime | None
    silent_seconds: float = Field(description="seconds since its last heartbeat")
    disabled: bool = Field(False, description="drained by an admin: finishes the units it "
                                              "runs, takes no new ones")

    @classmethod
    def from_info(cls, w: WorkerInfo) -> "WorkerPublic":
        return cls(name=w.name, kind=w.kind, host=w.host, state=w.state,
                   concurrency=w.concurrency,
                   running=[RunningUnitPublic(job_id=r.job_id, index=r.index, since=r.since)
                            for r in w.running],
                   units_done=w.units_done, samples=w.samples, rays=w.rays, seconds=w.seconds,
                   samples_per_second=w.samples / w.seconds if w.seconds > 0 else None,
                   started=w.started, last_seen=w.last_seen, silent_seconds=w.silent_seconds,
                   disabled=w.disabled)


class WorkerBlockPublic(BaseModel):
    """A worker that failed units of a job (`service.blocklist`)."""

    worker: str
    failures: int = Field(description="units of the job that failed on it")
    blocked: datetime | None = Field(description="when it was blocklisted for the job (it "
                                                 "takes none of its units); null: not yet")
    last_error: str | None

    @classmethod
    def from_row(cls, row) -> "WorkerBlockPublic":
        return cls(worker=row.worker, failures=row.failures, blocked=row.blocked,
                   last_error=row.last_error)


# -- accounts ------------------------------------------------------------------------

class LoginRequest(RequestModel):
    """`POST /auth/login`: trade an API token for the dashboard's session cookie."""

    token: StrictStr = Field(max_length=200)


class Me(BaseModel):
    """`GET /auth/me`: who the caller is."""

    user: str
    role: str
    via: str = Field(description="bearer (Authorization header) or cookie (the dashboard)")
    token_id: str | None = Field(description="the API token it authenticated with")


class UserCreate(RequestModel):
    name: StrictStr = Field(max_length=64, description="a-z, 0-9, '.', '_', '-'")
    role: Literal["admin", "artist", "viewer"] = "artist"
    share: StrictFloat | StrictInt = Field(1.0, ge=0.01, le=1000,
                                           description="weight in the fair share between owners")


class UserUpdate(RequestModel):
    role: Literal["admin", "artist", "viewer"] | None = None
    share: StrictFloat | StrictInt | None = Field(None, ge=0.01, le=1000)
    disabled: StrictBool | None = None


class UserPublic(BaseModel):
    name: str
    role: str
    share: float
    disabled: bool
    created: datetime

    @classmethod
    def from_user(cls, user: User) -> "UserPublic":
        return cls(name=user.name, role=user.role, share=user.share, disabled=bool(user.disabled),
                   created=user.created)


class TokenCreate(RequestModel):
    user: StrictStr = Field(max_length=64)
    label: StrictStr = Field("", max_length=200)
    expires_in_days: StrictFloat | StrictInt | None = Field(
        None, gt=0, le=36500, description="none: the token does not expire")


class TokenPublic(BaseModel):
    """A token as listed: never its secret (only its hash is stored)."""

    id: str
    user: str
    label: str
    created: datetime
    expires: datetime | None
    revoked: datetime | None
    last_used: datetime | None

    @classmethod
    def from_token(cls, token: ApiToken) -> "TokenPublic":
        return cls(id=token.id, user=token.user, label=token.label, created=token.created,
                   expires=token.expires, revoked=token.revoked, last_used=token.last_used)


class TokenCreated(TokenPublic):
    token: str = Field(description="the secret: shown this once, stored only as a hash")


# -- the estimator lab (service.experiments) ----------------------------------------------

class LabConfig(RequestModel):
    """One estimator of an experiment: a method with its sampler and options."""

    method: str = Field(description="rendering method (GET /methods)",
                        json_schema_extra={"enum": list(METHODS)})
    sampler: str = Field("random", description="pixel sampler; `random` (independent samples) "
                                               "by default, so that error falls as 1/sqrt(spp) "
                                               "for plain Monte Carlo",
                         json_schema_extra={"enum": list(SAMPLERS)})
    options: Annotated[dict[str, Any], PlainJson] = Field(
        default_factory=dict, description="method options (GET /methods lists them)")
    label: StrictStr | None = Field(None, max_length=64, description="its name in the report "
                                                                     "(default: method, sampler "
                                                                     "and options)")


class LabReference(RequestModel):
    """The experiment's reference: an existing done job of the same scene,
    size and depth, or a render the experiment makes."""

    job: StrictStr | None = Field(None, max_length=32, description="a done job's id")
    method: str = Field("path-mis", description="the reference render's method (unless `job`)")
    spp: StrictInt | None = Field(None, ge=1, le=BOUNDS["spp"][1],
                                  description="its spp (default: 16 x repeats x the largest spp "
                                              "level, at least 1024)")


class ExperimentCreate(RequestModel):
    """`POST /experiments`: every configuration rendered at every spp level,
    `repeats` times with derived seeds, as ordinary jobs; measured against the
    reference when they are done (renderer.lab)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"scene": "cornell-box", "width": 32, "height": 32, "depth": 5, "repeats": 4,
         "spp": [1, 4, 16, 64], "configs": [{"method": "path-bsdf"}, {"method": "path-mis"},
                                            {"method": "bdpt"}, {"method": "photon"},
                                            {"method": "raster"}]}]})

    scene: StrictStr = Field(max_length=200, description="a built-in scene's name or an uploaded "
                                                         "scene's id (GET /scenes)")
    configs: list[LabConfig] = Field(min_length=1, max_length=16)
    spp: list[_bounded("spp", "samples per pixel")] = Field(
        min_length=1, max_length=8, description="spp levels, ascending (each within the job "
                                                "bounds)")
    repeats: StrictInt = Field(4, ge=2, le=64, description="independent renders per "
                                                           "configuration and level")
    depth: _bounded("depth", "maximum path depth") = 5
    width: _bounded("width", "image width; default: the scene camera's") | None = None
    height: _bounded("height", "image height; default: the scene camera's") | None = None
    block: StrictInt = Field(8, ge=1, le=256, description="side of the pixel blocks whose means "
                                                          "the bias test compares")
    seed: _bounded("seed", "base seed: each job's seed is derived from it, its configuration, "
                           "level and repeat") = 0
    reference: LabReference = Field(default_factory=LabReference)
    priority: Priority = 0


class LabLevel(BaseModel):
    spp: int
    bias_p: float = Field(description="the chance, without bias, of as many pixel blocks whose "
                                      "t test is significant at 5 % (renderer.lab); < 0.001: "
                                      "biased")
    biased_blocks: int = Field(description="the blocks significant at 5 %")
    block_t: list[list[float | None]] = Field(description="each pixel block's t statistic of "
                                                          "the bias (rows of blocks; null: "
                                                          "infinite)")
    blocks: int = Field(description="the blocks tested (luminance)")
    unbiased: bool
    relative_bias: float = Field(description="image mean over the repeats / reference's - 1")
    bias2: float = Field(description="squared error of the repeats' average less its noise and "
                                     "the reference's: the systematic error's energy")
    variance: float = Field(description="per-pixel variance over the repeats, mean over pixels")
    mse: float = Field(description="mean squared error against the reference, less its variance")
    rmse: float
    mse_reliable: bool = Field(description="false when the reference's own variance is over "
                                           "half the raw MSE: render a better reference")
    seconds: float = Field(description="render seconds of one render (mean over the repeats)")
    efficiency: float | None = Field(description="1 / (mse x seconds)")


class LabConfigReport(BaseModel):
    label: str
    method: str
    sampler: str
    options: dict[str, Any]
    levels: list[LabLevel]
    slope: float | None = Field(description="log-log slope of RMSE against spp, all levels")
    last_slope: float | None = Field(description="the same over the last step")
    unbiased: bool = Field(description="unbiased at every level")
    consistent: bool | None = Field(description="unbiased, or its bias^2 still falls at the "
                                                "last step (renderer.lab)")


class ExperimentPublic(BaseModel):
    """An experiment as the API shows it."""

    id: str
    owner: str
    status: str = Field(description="running, done, failed or canceled")
    created: datetime
    finished: datetime | None
    request: dict[str, Any]
    jobs_total: int
    jobs_done: int
    reference_job: str
    runs: list[dict[str, Any]] = Field(description="one per job: config, spp, repeat, job, status")
    report: list[LabConfigReport] | None = Field(description="per configuration, once done")
    error: str | None
    plot_url: str | None = Field(description="RMSE and bias against spp (PNG, matplotlib)")
    maps_url: str | None = Field(description="bias and variance maps at the largest spp (PNG)")
    csv_url: str | None
