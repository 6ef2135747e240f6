"""/workers: the render workers the executor runs units on."""

from __future__ import annotations

from fastapi import APIRouter

from dataclasses import replace

from ... import jobs
from ...schemas import WorkerPublic
from ..auth import ActorDep
from ..deps import FarmDep, SessionDep

router = APIRouter(tags=["workers"])


@router.get("/workers", response_model=list[WorkerPublic])
def list_workers(farm: FarmDep, actor: ActorDep, session: SessionDep) -> list[WorkerPublic]:
    """Every worker (Celery worker nodes, or the embedded pool): its state
    (busy, idle, lost when its heartbeats stopped, offline after a clean
    shutdown), the units it renders now (of the jobs the caller may see), and
    what it has done since it started."""
    workers = farm.executor.workers()
    visible = jobs.visible_job_ids(session, actor, (r.job_id for w in workers for r in w.running))
    return [WorkerPublic.from_info(replace(w, running=tuple(r for r in w.running
                                                            if r.job_id in visible)))
            for w in workers]
