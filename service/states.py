"""Every status change of jobs and units, checked against one table.

    job:   queued ──► running ──► done
              │          │
              └──────────┴──► failed | canceled

    unit:  pending ──► queued ◄──► running ──► done
              │          │  ▲         │
              │          └──┘ (enqueued again: lost message or retry)
              └──────────┴────────────┴──► failed | canceled

Nothing else assigns `Job.status` or `WorkUnit.state`; a change the table does
not allow raises `IllegalTransition`. The timestamps that belong to a status
(started, finished, enqueued_at, ...) are set here too.
"""

from __future__ import annotations

from datetime import datetime

from .errors import IllegalTransition
from .models import Job, WorkUnit

__all__ = ["JOB_STATUSES", "UNIT_STATES", "JOB_TRANSITIONS", "UNIT_TRANSITIONS", "ACTIVE_JOB",
           "IN_FLIGHT", "FINAL_UNIT", "change_job", "change_unit"]

JOB_TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "failed", "canceled"}),
    "running": frozenset({"done", "failed", "canceled"}),
    "done": frozenset(),
    "failed": frozenset(),
    "canceled": frozenset(),
}

UNIT_TRANSITIONS: dict[str, frozenset[str]] = {
    "pending": frozenset({"queued", "canceled"}),
    # queued -> queued: the message was lost, or the attempt failed and is retried.
    "queued": frozenset({"queued", "running", "done", "failed", "canceled"}),
    "running": frozenset({"queued", "done", "failed", "canceled"}),
    "done": frozenset(),
    "failed": frozenset(),
    "canceled": frozenset(),
}

JOB_STATUSES = tuple(JOB_TRANSITIONS)
UNIT_STATES = tuple(UNIT_TRANSITIONS)
ACTIVE_JOB = ("queued", "running")
IN_FLIGHT = ("queued", "running")
FINAL_UNIT = ("done", "failed", "canceled")


def change_job(job: Job, new: str, now: datetime, *, error: str | None = None) -> None:
    """Move `job` to status `new` (or raise `IllegalTransition`)."""
    allowed = JOB_TRANSITIONS[job.status]
    if new not in allowed:
        raise IllegalTransition("job", job.id, job.status, new, allowed)
    job.status = new
    if new == "running":
        job.started = now
    if not JOB_TRANSITIONS[new]:
        job.finished = now
    if error is not None:
        job.error = error


def change_unit(unit: WorkUnit, new: str, now: datetime, *, error: str | None = None) -> None:
    """Move `unit` to state `new` (or raise `IllegalTransition`)."""
    allowed = UNIT_TRANSITIONS[unit.state]
    if new not in allowed:
        raise IllegalTransition("unit", f"{unit.job_id}/{unit.index}", unit.state, new, allowed)
    unit.state = new
    if new == "queued":
        unit.enqueued_at, unit.started_at = now, None
    elif new == "running":
        unit.started_at = now
    if not UNIT_TRANSITIONS[new]:
        unit.finished_at = now
    if error is not None:
        unit.error = error
