"""Every status change of jobs and units, checked against one table.

    job:   queued ──► running ──► done
              │  ▲     ▲  │
              ▼  │     │  ▼
              paused ◄─┴──┘          (pause / resume)
              queued, running, paused ──► failed | canceled
              failed ──► running     (retry: its failed units run again)
              running, paused, done, failed, canceled ──► queued   (requeue)

    unit:  pending ──► queued ◄──► running ──► done
              │          │  ▲         │
              │          └──┘ (enqueued again: lost message or retry)
              └──────────┴────────────┴──► failed | canceled
              failed | canceled ──► pending   (retry of a failed job)
              queued | running ──► pending    (withdrawn or preempted: fair share
                                               over render processes, no attempt spent)
              pending ──► skipped   (a target job's region met its target: service.targets)

Nothing else assigns `Job.status` or `WorkUnit.state`; a change the table does
not allow raises `IllegalTransition`. The timestamps that belong to a status
(started, finished, paused time, enqueued_at, ...) are set here too, and every
change is noted on its session (`service.events.note`), so it is published to
the event streams once the transaction commits: no status change goes unseen.
"""

from __future__ import annotations

from datetime import datetime

from . import events
from .errors import IllegalTransition
from .models import Job, WorkUnit

__all__ = ["JOB_STATUSES", "UNIT_STATES", "JOB_TRANSITIONS", "UNIT_TRANSITIONS", "ACTIVE_JOB",
           "SCHEDULED_JOB", "FINAL_JOB", "IN_FLIGHT", "FINAL_UNIT", "change_job", "change_unit"]

JOB_TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "paused", "failed", "canceled"}),
    "running": frozenset({"done", "paused", "queued", "failed", "canceled"}),
    # paused -> queued: resumed before it was planned, or requeued.
    "paused": frozenset({"queued", "running", "failed", "canceled"}),
    # Finished, but not forever: a requeue starts again, a retry continues a failed job.
    "done": frozenset({"queued"}),
    "failed": frozenset({"queued", "running"}),
    "canceled": frozenset({"queued"}),
}

UNIT_TRANSITIONS: dict[str, frozenset[str]] = {
    "pending": frozenset({"queued", "canceled", "skipped"}),
    # queued -> queued: the message was lost, or the attempt failed and is retried.
    # queued, running -> pending: withdrawn or preempted (service.fairshare), no attempt spent.
    "queued": frozenset({"queued", "running", "done", "failed", "canceled", "pending"}),
    "running": frozenset({"queued", "done", "failed", "canceled", "pending"}),
    "done": frozenset(),
    "skipped": frozenset(),
    # A retry of a failed job: its failed units and those canceled with it run again.
    "failed": frozenset({"pending"}),
    "canceled": frozenset({"pending"}),
}

JOB_STATUSES = tuple(JOB_TRANSITIONS)
UNIT_STATES = tuple(UNIT_TRANSITIONS)
ACTIVE_JOB = ("queued", "running")
SCHEDULED_JOB = ("queued", "running", "paused")  # the scheduler looks at these (paused: collect only)
FINAL_JOB = ("done", "failed", "canceled")
IN_FLIGHT = ("queued", "running")
FINAL_UNIT = ("done", "skipped", "failed", "canceled")


def change_job(job: Job, new: str, now: datetime, *, error: str | None = None) -> None:
    """Move `job` to status `new` (or raise `IllegalTransition`)."""
    allowed = JOB_TRANSITIONS[job.status]
    if new not in allowed:
        raise IllegalTransition("job", job.id, job.status, new, allowed)
    old, job.status = job.status, new
    if old == "paused" and job.paused_at is not None:
        if job.started is not None:  # a pause before the start is not running time
            job.paused_seconds = (job.paused_seconds or 0.0) + max(
                (now - job.paused_at).total_seconds(), 0.0)
        job.paused_at = None
    if new == "paused":
        job.paused_at = now
    # The recent rate is measured from when the job (re)starts running.
    job.recent_rate, job.recent_weight = None, None
    job.recent_rate_at = now if new == "running" else None
    if new == "running" and (old == "queued" or job.started is None):
        job.started = now  # a resume or a retry keeps the first start
    if new in FINAL_JOB:
        job.finished = now
    elif old in FINAL_JOB:  # requeued or retried: no longer finished
        if new == "running" and job.started is not None and job.finished is not None:
            # A retried failed job: the time it sat failed was not running time.
            job.paused_seconds = (job.paused_seconds or 0.0) + max(
                (now - job.finished).total_seconds(), 0.0)
        job.finished, job.error = None, None
    if error is not None:
        job.error = error
    events.note(job)


def change_unit(unit: WorkUnit, new: str, now: datetime, *, error: str | None = None) -> None:
    """Move `unit` to state `new` (or raise `IllegalTransition`)."""
    allowed = UNIT_TRANSITIONS[unit.state]
    if new not in allowed:
        raise IllegalTransition("unit", f"{unit.job_id}/{unit.index}", unit.state, new, allowed)
    old, unit.state = unit.state, new
    if new == "queued":
        unit.enqueued_at, unit.started_at = now, None
    elif new == "running":
        unit.started_at = now
    elif new == "pending":
        unit.enqueued_at = unit.started_at = None
        if old in FINAL_UNIT:  # retried: a fresh start
            unit.finished_at = unit.error = None
            unit.attempts = 0
    if new in FINAL_UNIT:
        unit.finished_at = now
    if error is not None:
        unit.error = error
    events.note(unit)
