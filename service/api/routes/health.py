"""/healthz: is the service able to take and run jobs?"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import text

from ..deps import FarmDep

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz(farm: FarmDep) -> JSONResponse:
    """200 with component states when the ledger answers and the scheduler
    runs (status "degraded" while the broker is unreachable, or while there is
    no room for new work: the data dir's file system has less than
    `min_free_bytes` free, or the ledger failed a write for want of room,
    service.disk: `ledger_writes` "failing"); 503 otherwise. `reasons` says,
    in words, why the status is not "ok". `leadership` says whether this replica runs the scheduler
    ("leader") or serves HTTP only ("standby") and who holds the scheduler
    lease (`service.leader`)."""
    report: dict = {"status": "ok", **farm.executor.health(),
                    "scheduler": "running" if farm.scheduler.alive else "stopped",
                    "scheduler_ticks": farm.scheduler.ticks,
                    "leadership": farm.leadership.status()}
    reasons: list[str] = []
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
        reasons.append(f"the ledger does not answer ({type(exc).__name__})")
    if not farm.scheduler.alive:
        reasons.append("the scheduler is stopped")
    if report.get("broker", "ok") != "ok":
        reasons.append(f"the broker is {report['broker']}: jobs wait for it")
    try:  # the free space, not the path: /healthz answers anyone
        report["disk_free_bytes"] = farm.disk.free_bytes()
        space = farm.disk.space_problem(report["disk_free_bytes"])
        report["disk"] = "low" if space else "ok"
    except OSError as exc:
        space = f"the data dir's free space is unknown ({exc.strerror or type(exc).__name__})"
        report["disk"] = f"error: {exc.strerror or type(exc).__name__}"
    ledger = farm.disk.ledger_problem()
    report["ledger_writes"] = "ok" if ledger is None else "failing"
    for problem in (space, ledger):
        if problem:
            reasons.append(f"disk: {problem}; new jobs, scenes and experiments are refused "
                           "(507) until there is room")
    if report["database"] != "ok" or not farm.scheduler.alive:
        report["status"] = "unhealthy"
    elif reasons:
        # jobs are accepted and wait for the broker; or stored work is served, new work waits
        report["status"] = "degraded"
    if reasons:
        report["reasons"] = reasons
    return JSONResponse(report, status_code=503 if report["status"] == "unhealthy" else 200)
