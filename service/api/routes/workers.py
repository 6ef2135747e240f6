"""/workers: the render workers the executor runs units on; admins drain
(disable), enable and remove them (`service.workers`)."""

from __future__ import annotations

from dataclasses import replace

from fastapi import APIRouter, Response, status

from ... import jobs, workers
from ...access import Principal
from ...executors import WorkerInfo
from ...schemas import WorkerPublic
from ..auth import ActorDep
from ..deps import FarmDep, SessionDep
from ..errors import responses

router = APIRouter(tags=["workers"])


def _public(worker: WorkerInfo, visible: set[str]) -> WorkerPublic:
    return WorkerPublic.from_info(replace(worker, running=tuple(
        r for r in worker.running if r.job_id in visible)))


def _shown(session, actor: Principal, worker: WorkerInfo) -> WorkerPublic:
    return _public(worker, jobs.visible_job_ids(session, actor,
                                                (r.job_id for r in worker.running)))


@router.get("/workers", response_model=list[WorkerPublic])
def list_workers(farm: FarmDep, actor: ActorDep, session: SessionDep) -> list[WorkerPublic]:
    """Every worker (Celery worker nodes, or the embedded pool): its state
    (busy, idle, lost when its heartbeats stopped, offline after a clean
    shutdown), whether an admin disabled it, the units it renders now (of the
    jobs the caller may see), and what it has done since it started."""
    found = farm.executor.workers()
    visible = jobs.visible_job_ids(session, actor, (r.job_id for w in found for r in w.running))
    return [_public(w, visible) for w in found]


@router.post("/workers/{name}/disable", response_model=WorkerPublic,
             responses=responses(403, 404))
def disable_worker(name: str, farm: FarmDep, actor: ActorDep,
                   session: SessionDep) -> WorkerPublic:
    """Drain a worker (admins): it finishes the units it renders and takes no
    new ones, also after a restart, until it is enabled again."""
    return _shown(session, actor, workers.set_enabled(farm.executor, actor, name, False))


@router.post("/workers/{name}/enable", response_model=WorkerPublic,
             responses=responses(403, 404))
def enable_worker(name: str, farm: FarmDep, actor: ActorDep,
                  session: SessionDep) -> WorkerPublic:
    """Let a disabled worker take units again (admins)."""
    return _shown(session, actor, workers.set_enabled(farm.executor, actor, name, True))


@router.delete("/workers/{name}", status_code=status.HTTP_204_NO_CONTENT,
               responses=responses(403, 404, 409))
def remove_worker(name: str, farm: FarmDep, actor: ActorDep) -> Response:
    """Remove a lost or offline worker from the list (admins; 409 for a live one)."""
    workers.remove(farm.executor, actor, name)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
