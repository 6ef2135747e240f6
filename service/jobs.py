"""Job use cases: create, look up, list, cancel, pause, resume, retry, requeue,
reprioritize, delete. Plain Python, no HTTP. Every status change goes through
`service.states` (an illegal one is a `Conflict`).

Every use case takes the caller (`actor`, a `service.access.Principal`) and
looks jobs up only among those it may see (`access.visible_jobs`): someone
else's job is not found, and a change needs `access.require_change`.

    job = create_job(session, store, settings, actor, JobCreate(scene="cornell-box",
                     method="path", spp=4, depth=3), now=utcnow())
"""

from __future__ import annotations

import math
import uuid
from datetime import datetime
from typing import Callable, TypeVar

from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError

from renderer import (METHODS, SAMPLERS, RenderSpec, SceneError, builtin_scene_names,
                      resolve_document, scene_text)
from renderer.target import Target, require_target_support

from . import admission, events, scenes, states
from .access import Principal, require_change, require_submit, visible_jobs
from .errors import Conflict, InvalidRequest, NotFound, ResultNotReady
from .models import Job, WorkUnit
from .schemas import JobCreate
from .settings import Settings
from .store import Store

__all__ = ["create_job", "get_job", "list_jobs", "visible_job_ids", "list_units", "unit_logs", "cancel_job", "cancel_job_retrying",
           "pause_job", "resume_job", "retry_job", "requeue_job", "set_priority", "delete_job",
           "retrying", "result_file", "new_job_id"]


T = TypeVar("T")


def new_job_id() -> str:
    return uuid.uuid4().hex[:12]


def _resolve_scene(session: Session, store: Store, actor: Principal, scene: str | dict,
                   method: str) -> tuple[dict, str, str | None]:
    """The resolved document, a display name and, for an upload (named by its
    id, its hash), that hash: its text is in the store already. Never reads
    server files other than the store's. An upload's document holds only its
    camera unless `method` checks the scene (radiosity): a large mesh's text
    is not parsed for nothing in the request."""
    if isinstance(scene, str):
        if scene in builtin_scene_names():
            return resolve_document(scene, allow_files=False), scene, None
        checks = getattr(METHODS.get(method), "check_scene", True) is not None
        uploaded = scenes.uploaded_document(session, store, actor, scene, whole=checks)
        if uploaded is None:
            hint = scenes.unknown_scene_hint()
            raise InvalidRequest("scene", f"unknown scene '{scene}' ({hint}; "
                                          "or an inline scene object)")
        return *uploaded, scene
    try:
        # an inline scene may name meshes already in the store by digest
        doc = resolve_document(scene, allow_files=False, assets=store.asset_bytes)
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
        # A malformed document the validator did not anticipate is still the
        # client's error, not the server's.
        raise SceneError(f"malformed scene document ({type(exc).__name__}: {exc})") from None
    return doc, f"inline:{doc['name']}" if doc.get("name") else "inline", None


def create_job(session: Session, store: Store, settings: Settings, actor: Principal,
               request: JobCreate, now: datetime) -> Job:
    """Validate a render request, store its scene and add a queued job of
    `actor` to `session`.

    Raises `InvalidRequest`, `SceneError` or `SpecError` naming what is wrong,
    `Forbidden` for a caller that may not submit, `RateLimited` for an owner
    with too many active jobs (`service.admission`: the role's limits).
    """
    require_submit(actor)
    doc, scene_name, key = _resolve_scene(session, store, actor, request.scene, request.method)
    camera = doc["camera"]
    target = _target(request)
    spec = RenderSpec(method=request.method,
                      spp=request.spp if target is None else target.max_spp, depth=request.depth,
                      width=camera["width"] if request.width is None else request.width,
                      height=camera["height"] if request.height is None else request.height,
                      tile_size=request.tile_size, seed=request.seed, sampler=request.sampler,
                      options=dict(request.options))
    spec.validate(settings.max_work, scene=doc)
    if target is not None:
        require_target_support(spec.method)
    tiles = math.ceil(spec.width / spec.tile_size) * math.ceil(spec.height / spec.tile_size)
    if tiles > settings.max_units:
        least = math.ceil(math.sqrt(spec.width * spec.height / settings.max_units))
        raise InvalidRequest("tile_size", f"{tiles} tiles exceed the limit of {settings.max_units} "
                                          f"work units; use tile_size >= {least}")
    admission.admit_job(session, settings, actor, spec, request.progressive, target,
                        denoise=request.denoise)
    if key is None:  # an upload's text is stored under its hash already
        key, text = scene_text(doc)
        store.put_assets(getattr(doc, "assets", None) or {})
        store.put_scene(key, text)
    job = Job(id=new_job_id(), created=now, status="queued", owner=actor.user,
              scene=scene_name[:200],
              scene_hash=key, spec=spec.to_dict(), width=spec.width, height=spec.height,
              units_total=0, units_done=0, samples=0, rays=0, priority=request.priority,
              progressive=request.progressive or target is not None, denoise=request.denoise,
              target=None if target is None else target.to_dict(), units_skipped=0,
              paused_seconds=0.0, unit_seconds=0.0,
              units_retried=0)
    session.add(job)
    events.note(job)
    return job


def _target(request: JobCreate) -> Target | None:
    """The request's noise target, checked (its max_spp defaults to spp; one
    of them is needed, and they may not disagree), or None for a fixed spp."""
    t = request.target
    if t is None:
        if request.spp is None:
            raise InvalidRequest("spp", "is required (or give a target with max_spp)")
        return None
    if t.max_spp is None and request.spp is None:
        raise InvalidRequest("target.max_spp", "is required: the most samples per pixel to "
                                               "spend (or give spp)")
    if t.max_spp is not None and request.spp is not None and t.max_spp != request.spp:
        raise InvalidRequest("spp", f"is {request.spp} but target.max_spp is {t.max_spp}; give "
                                    "one of them (with a target, spp is the ceiling)")
    return Target(rel_error=t.rel_error, max_spp=t.max_spp if t.max_spp is not None
                  else request.spp, max_seconds=t.max_seconds).validate()


def get_job(session: Session, actor: Principal, job_id: str) -> Job:
    """The job `job_id` if `actor` may see it; else NotFound, as if there were none."""
    job = session.scalars(select(Job).where(Job.id == job_id,
                                            visible_jobs(actor, Job.owner))).first()
    if job is None:
        raise NotFound(f"no job '{job_id}'")
    return job


def _job_to_change(session: Session, actor: Principal, job_id: str) -> Job:
    """The job `job_id` if `actor` may change it (NotFound, or Forbidden for a viewer)."""
    job = get_job(session, actor, job_id)
    require_change(actor, job.owner, f"job '{job_id}'")
    return job


def check_query(names, allowed) -> None:
    """A 422 naming the first query parameter not in `allowed`."""
    for name in names:
        if name not in allowed:
            raise InvalidRequest(name, f"unknown query parameter (allowed: {', '.join(allowed)})",
                                 source="query")


def list_jobs(session: Session, actor: Principal, *, status: str | None = None,
              method: str | None = None, scene: str | None = None, sampler: str | None = None,
              owner: str | None = None, limit: int = 100, offset: int = 0) -> list[Job]:
    """The jobs `actor` may see, newest first, with the given status, method
    (an alias is resolved), scene (as jobs name it), sampler and owner."""
    query = (select(Job).where(visible_jobs(actor, Job.owner))
             .order_by(Job.created.desc(), Job.id).limit(limit).offset(offset))
    if method is not None:
        if method not in METHODS:
            raise InvalidRequest("method", f"unknown method '{method}' (allowed: "
                                           f"{', '.join(METHODS)})", source="query")
        query = query.where(Job.spec["method"].as_string() == METHODS[method].name)
    if sampler is not None:
        if sampler not in SAMPLERS:
            raise InvalidRequest("sampler", f"unknown sampler '{sampler}' (allowed: "
                                            f"{', '.join(SAMPLERS)})", source="query")
        query = query.where(Job.spec["sampler"].as_string() == sampler)
    if scene is not None:
        query = query.where(Job.scene == scene)
    if owner is not None:
        query = query.where(Job.owner == owner)
    if status is not None:
        if status not in states.JOB_STATUSES:
            raise InvalidRequest("status", f"unknown status '{status}' "
                                           f"(allowed: {', '.join(states.JOB_STATUSES)})",
                                 source="query")
        query = query.where(Job.status == status)
    return list(session.scalars(query))


def visible_job_ids(session: Session, actor: Principal, job_ids) -> set[str]:
    """Those of `job_ids` that `actor` may see."""
    job_ids = set(job_ids)
    if actor.sees_everything or not job_ids:
        return job_ids
    return set(session.scalars(select(Job.id).where(Job.id.in_(job_ids),
                                                    visible_jobs(actor, Job.owner))))


def list_units(session: Session, actor: Principal, job_id: str) -> list[WorkUnit]:
    """A job's units in plan order (empty until the scheduler planned it)."""
    job = get_job(session, actor, job_id)
    return list(session.scalars(select(WorkUnit).where(WorkUnit.job_id == job.id)
                                .order_by(WorkUnit.index)))


def unit_logs(session: Session, store: Store, actor: Principal, job_id: str,
              index: int) -> tuple[WorkUnit, list[dict]]:
    """Unit `index` of a job `actor` may see, and the logs its tasks left
    (oldest first); NotFound if there is no such job or unit."""
    job = get_job(session, actor, job_id)
    unit = session.get(WorkUnit, (job.id, index))
    if unit is None:
        raise NotFound(f"job '{job_id}' has no unit {index}"
                       + ("" if job.units_total else " (it is not planned yet)"))
    return unit, store.unit_logs(job.id, index)


def cancel_job(session: Session, actor: Principal, job_id: str, now: datetime) -> Job:
    """Mark a job and its unfinished units canceled. The scheduler sees the
    units leave flight and revokes their tasks. A finished job is a Conflict."""
    job = _job_to_change(session, actor, job_id)
    states.change_job(job, "canceled", now, error="canceled by request")
    units = session.scalars(select(WorkUnit).where(
        WorkUnit.job_id == job.id, WorkUnit.state.not_in(states.FINAL_UNIT)))
    for unit in units:
        states.change_unit(unit, "canceled", now)
    return job


def pause_job(session: Session, actor: Principal, job_id: str, now: datetime) -> Job:
    """Stop enqueuing a job's units; those in flight finish and are collected."""
    job = _job_to_change(session, actor, job_id)
    states.change_job(job, "paused", now)
    return job


def resume_job(session: Session, actor: Principal, job_id: str, now: datetime) -> Job:
    """A paused job continues (or waits to be planned, if it never was)."""
    job = _job_to_change(session, actor, job_id)
    if job.status != "paused":
        raise Conflict(f"job {job.id} is {job.status}, not paused; nothing to resume")
    states.change_job(job, "running" if job.units_total else "queued", now)
    return job


def retry_job(session: Session, actor: Principal, job_id: str, now: datetime) -> Job:
    """Failed units (and those canceled when their job failed) go back to
    pending; a failed job runs again, keeping the units it finished."""
    job = _job_to_change(session, actor, job_id)
    units = list(session.scalars(select(WorkUnit).where(
        WorkUnit.job_id == job.id, WorkUnit.state.in_(("failed", "canceled")))))
    failed = [u for u in units if u.state == "failed"]
    if job.status == "failed":
        states.change_job(job, "running" if job.units_total else "queued", now)
        again = units
    elif job.status in ("running", "paused") and failed:
        again = failed
    else:
        raise Conflict(f"job {job.id} is {job.status} and has no failed units to retry")
    for unit in again:
        states.change_unit(unit, "pending", now)
    return job


def requeue_job(session: Session, store: Store, actor: Principal, job_id: str,
                now: datetime) -> Job:
    """Start a job again from nothing: its units and results are forgotten and
    it is queued, so the scheduler plans it anew (all units pending)."""
    job = _job_to_change(session, actor, job_id)
    states.change_job(job, "queued", now)
    for unit in session.scalars(select(WorkUnit).where(WorkUnit.job_id == job.id)):
        session.delete(unit)  # in-flight tasks: the scheduler cancels units that left
    job.units_total = job.units_done = job.samples = job.rays = job.units_retried = 0
    job.units_skipped, job.units_open, job.rel_error = 0, None, None
    job.target_stop, job.pass_log = None, None
    job.unit_seconds = job.paused_seconds = 0.0
    job.started = job.paused_at = None
    session.flush()
    store.clear_results(job.id)
    return job


def set_priority(session: Session, actor: Principal, job_id: str, priority: int,
                 now: datetime) -> Job:
    """Change a job's priority; the scheduler serves higher ones first (within
    its owner's fair share) from its next tick."""
    job = _job_to_change(session, actor, job_id)
    job.priority = priority
    events.note(job)
    return job


def delete_job(session: Session, store: Store, actor: Principal, job_id: str,
               now: datetime) -> str:
    """Forget a job: canceled first if it is still active, then its rows and
    files are removed. The scheduler cancels the tasks of units that vanished;
    anything it writes for the job afterwards it removes again. Returns its owner."""
    job = _job_to_change(session, actor, job_id)
    if job.status not in states.FINAL_JOB:
        cancel_job(session, actor, job_id, now)
        session.flush()
    owner = job.owner
    session.execute(delete(WorkUnit).where(WorkUnit.job_id == job.id))
    session.delete(job)
    session.flush()
    store.delete_job(job.id)
    return owner


def retrying(sessions: sessionmaker[Session], name: str,
             action: Callable[[Session], T], tries: int = 5, what: str = "job") -> T:
    """`action(session)` in its own transaction, again if the scheduler changed
    the rows it writes meanwhile (optimistic locking): the next try sees the
    new state. After `tries` a 409 naming the `what` `name`, never a 500."""
    for attempt in range(tries):
        try:
            with sessions.begin() as session:
                return action(session)
        except StaleDataError:
            if attempt == tries - 1:
                raise Conflict(f"{what} '{name}' keeps changing; try again") from None
    raise AssertionError("unreachable")


def cancel_job_retrying(sessions: sessionmaker[Session], actor: Principal, job_id: str,
                        clock: Callable[[], datetime], tries: int = 5) -> Job:
    """`cancel_job` in its own transaction, retried on concurrent changes."""
    return retrying(sessions, job_id,
                    lambda session: cancel_job(session, actor, job_id, clock()), tries)


def partial_result_files(session: Session, store: Store, job: Job):
    """The partial EXR and PNG of a canceled or failed job (service.results)."""
    from .results import partial_result
    from .targets import job_target

    done = list(session.scalars(select(WorkUnit.index).where(
        WorkUnit.job_id == job.id, WorkUnit.state == "done").order_by(WorkUnit.index)))
    return partial_result(store, job.id, RenderSpec.from_dict(job.spec), done, scene=job.scene,
                          scene_hash=job.scene_hash, target=job_target(job))


def result_file(session: Session, store: Store, actor: Principal, job_id: str, kind: str):
    """Path of a done job's `result.exr`, or of a job's `preview.png` or
    `noise.png` (written as its units land, so there before it is done); else
    `ResultNotReady`."""
    job = get_job(session, actor, job_id)
    if kind == "denoised.png":
        if job.status != "done" or not job.denoise:
            raise ResultNotReady(f"job '{job_id}' is {job.status}"
                                 + ("" if job.denoise else " and was not submitted with denoise")
                                 + f"; its {kind} exists once a denoised job is done")
        path = store.denoised_path(job.id)
        if not path.is_file():
            raise NotFound(f"job '{job_id}' has no {kind}")
        return path
    if job.status in ("canceled", "failed") and kind in ("result.exr", "preview.png") \
            and job.units_done:
        # What it finished, merged: the running preview may lag behind it.
        exr, png = partial_result_files(session, store, job)
        return exr if kind == "result.exr" else png
    if kind in ("preview.png", "noise.png"):
        if job.status in states.SCHEDULED_JOB:  # someone looks: keep it written (service.previews)
            store.mark_watched(job.id, kind.removesuffix(".png"))
        path = store.preview_path(job.id) if kind == "preview.png" else store.noise_path(job.id)
        if not path.is_file():
            raise ResultNotReady(f"job '{job_id}' is {job.status}; its {kind} exists once "
                                 "its first unit is done")
        return path
    if job.status != "done":
        raise ResultNotReady(f"job '{job_id}' is {job.status}; its {kind} exists once it is done"
                             + (" (or, partial, once it is canceled or failed with a unit "
                                "finished)" if kind == "result.exr" else ""))
    path = store.result_path(job.id)
    if not path.is_file():
        raise NotFound(f"job '{job_id}' has no {kind}")
    return path
