"""Job use cases: create, look up, list, cancel. Plain Python, no HTTP.

    job = create_job(session, store, settings, JobCreate(scene="cornell-box",
                     method="path", spp=4, depth=3), now=utcnow())
"""

from __future__ import annotations

import math
import uuid
from datetime import datetime
from typing import Callable

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError

from renderer import RenderSpec, SceneError, builtin_scene_names, resolve_document, scene_text

from . import states
from .errors import Conflict, InvalidRequest, NotFound, ResultNotReady
from .models import Job, WorkUnit
from .schemas import JobCreate
from .settings import Settings
from .store import Store

__all__ = ["create_job", "get_job", "list_jobs", "list_units", "cancel_job", "cancel_job_retrying",
           "result_file", "new_job_id"]


def new_job_id() -> str:
    return uuid.uuid4().hex[:12]


def _resolve_scene(scene: str | dict) -> tuple[dict, str]:
    """The resolved document and a display name; never reads server files."""
    if isinstance(scene, str):
        names = builtin_scene_names()
        if scene not in names:
            raise InvalidRequest("scene", f"unknown scene '{scene}' (allowed: {', '.join(names)}; "
                                          "or an inline scene object)")
        return resolve_document(scene, allow_files=False), scene
    try:
        doc = resolve_document(scene, allow_files=False)
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
        # A malformed document the validator did not anticipate is still the
        # client's error, not the server's.
        raise SceneError(f"malformed scene document ({type(exc).__name__}: {exc})") from None
    return doc, f"inline:{doc['name']}" if doc.get("name") else "inline"


def create_job(session: Session, store: Store, settings: Settings, request: JobCreate,
               now: datetime) -> Job:
    """Validate a render request, store its scene and add a queued job to `session`.

    Raises `InvalidRequest`, `SceneError` or `SpecError` naming what is wrong.
    """
    doc, scene_name = _resolve_scene(request.scene)
    camera = doc["camera"]
    spec = RenderSpec(method=request.method, spp=request.spp, depth=request.depth,
                      width=camera["width"] if request.width is None else request.width,
                      height=camera["height"] if request.height is None else request.height,
                      tile_size=request.tile_size, seed=request.seed, sampler=request.sampler,
                      options=dict(request.options))
    spec.validate(settings.max_work)
    tiles = math.ceil(spec.width / spec.tile_size) * math.ceil(spec.height / spec.tile_size)
    if tiles > settings.max_units:
        least = math.ceil(math.sqrt(spec.width * spec.height / settings.max_units))
        raise InvalidRequest("tile_size", f"{tiles} tiles exceed the limit of {settings.max_units} "
                                          f"work units; use tile_size >= {least}")
    key, text = scene_text(doc)
    store.put_scene(key, text)
    job = Job(id=new_job_id(), created=now, status="queued", scene=scene_name[:200],
              scene_hash=key, spec=spec.to_dict(), width=spec.width, height=spec.height,
              units_total=0, units_done=0, samples=0, rays=0)
    session.add(job)
    return job


def get_job(session: Session, job_id: str) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise NotFound(f"no job '{job_id}'")
    return job


def list_jobs(session: Session, *, status: str | None = None, limit: int = 100,
              offset: int = 0) -> list[Job]:
    """Jobs, newest first."""
    query = select(Job).order_by(Job.created.desc(), Job.id).limit(limit).offset(offset)
    if status is not None:
        if status not in states.JOB_STATUSES:
            raise InvalidRequest("status", f"unknown status '{status}' "
                                           f"(allowed: {', '.join(states.JOB_STATUSES)})",
                                 source="query")
        query = query.where(Job.status == status)
    return list(session.scalars(query))


def list_units(session: Session, job_id: str) -> list[WorkUnit]:
    """A job's units in plan order (empty until the scheduler planned it)."""
    job = get_job(session, job_id)
    return list(session.scalars(select(WorkUnit).where(WorkUnit.job_id == job.id)
                                .order_by(WorkUnit.index)))


def cancel_job(session: Session, job_id: str, now: datetime) -> Job:
    """Mark a job and its unfinished units canceled. The scheduler sees the
    units leave flight and revokes their tasks. A finished job is a Conflict."""
    job = get_job(session, job_id)
    states.change_job(job, "canceled", now, error="canceled by request")
    units = session.scalars(select(WorkUnit).where(
        WorkUnit.job_id == job.id, WorkUnit.state.not_in(states.FINAL_UNIT)))
    for unit in units:
        states.change_unit(unit, "canceled", now)
    return job


def cancel_job_retrying(sessions: sessionmaker[Session], job_id: str,
                        clock: Callable[[], datetime], tries: int = 5) -> Job:
    """`cancel_job` in its own transaction, again if the scheduler changed the
    job meanwhile (optimistic locking): the second try sees the new state."""
    for attempt in range(tries):
        try:
            with sessions.begin() as session:
                return cancel_job(session, job_id, clock())
        except StaleDataError:
            if attempt == tries - 1:
                raise Conflict(f"job '{job_id}' keeps changing; try again") from None
    raise AssertionError("unreachable")


def result_file(session: Session, store: Store, job_id: str, kind: str):
    """Path of a done job's `result.exr` or `preview.png` (else `ResultNotReady`)."""
    job = get_job(session, job_id)
    if job.status != "done":
        raise ResultNotReady(f"job '{job_id}' is {job.status}; its {kind} exists once it is done")
    path = store.result_path(job.id) if kind == "result.exr" else store.preview_path(job.id)
    if not path.is_file():
        raise NotFound(f"job '{job_id}' has no {kind}")
    return path
