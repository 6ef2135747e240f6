"""/healthz: is the service able to take and run jobs?"""

from __future__ import annotations

import shutil

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import text

from ..deps import FarmDep

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz(farm: FarmDep) -> JSONResponse:
    """200 with component states when the ledger answers and the scheduler
    runs (status "degraded" while the broker is unreachable, or while the data
    dir's file system has less than `min_free_bytes` free: unit films could
    not be stored); 503 otherwise. `leadership` says whether this replica runs
    the scheduler ("leader") or serves HTTP only ("standby") and who holds
    the scheduler lease (`service.leader`)."""
    report: dict = {"status": "ok", **farm.executor.health(),
                    "scheduler": "running" if farm.scheduler.alive else "stopped",
                    "scheduler_ticks": farm.scheduler.ticks,
                    "leadership": farm.leadership.status()}
    if report["leadership"]["role"] == "standby":
        report["scheduler"] = "standby" if farm.scheduler.alive else "stopped"
    if farm.scheduler.last_error:
        report["scheduler_error"] = farm.scheduler.last_error
    try:
        with farm.sessions() as session:
            session.execute(text("SELECT 1"))
        report["database"] = "ok"
    except Exception as exc:
        report["database"] = f"error: {type(exc).__name__}"
    try:  # the free space, not the path: /healthz answers anyone
        report["disk_free_bytes"] = shutil.disk_usage(farm.store.root).free
        low = report["disk_free_bytes"] < farm.settings.min_free_bytes
        report["disk"] = "low" if low else "ok"
    except OSError as exc:
        report["disk"] = f"error: {exc.strerror or type(exc).__name__}"
    if report["database"] != "ok" or not farm.scheduler.alive:
        report["status"] = "unhealthy"
    elif report.get("broker", "ok") != "ok" or report["disk"] != "ok":
        # jobs are accepted and wait for the broker, or for space to store their units
        report["status"] = "degraded"
    return JSONResponse(report, status_code=503 if report["status"] == "unhealthy" else 200)
