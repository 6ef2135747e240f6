"""/workers: the render workers the executor runs units on."""

from __future__ import annotations

from fastapi import APIRouter

from ...schemas import WorkerPublic
from ..deps import FarmDep

router = APIRouter(tags=["workers"])


@router.get("/workers", response_model=list[WorkerPublic])
def list_workers(farm: FarmDep) -> list[WorkerPublic]:
    """Every worker (Celery worker nodes, or the embedded pool): its state
    (busy, idle, lost when its heartbeats stopped, offline after a clean
    shutdown), the units it renders now, and what it has done since it started."""
    return [WorkerPublic.from_info(w) for w in farm.executor.workers()]
