"""Per-job worker blocklists (Deadline's and Flamenco's habit): a worker on
which `settings.worker_failures_per_job` units of a job failed is blocklisted
for that job, so its units go to other workers. Plain Python, no HTTP.

The ledger is the truth (`models.WorkerBlock`, one row per job and worker
that failed a unit of it). The scheduler counts failures (`note_failure`) and
hands the blocklisted names to the executor with every ticket of the job
(`Ticket.blocked`): a Celery worker that takes such a unit from the shared
queue declines it at once and the unit is enqueued again without spending an
attempt. When every live worker is blocklisted for a job nothing could run
it, so the job fails saying so (`all_blocked`): its owner clears the
blocklist (`clear`) and retries it. Only failures an executor attributes to a
worker count (`Observation.worker`): the Celery farm's. The embedded pool is
one worker that no other could replace; `max_attempts` alone decides there.

    note_failure(session, job_id, "rayfarm-12@host", "ValueError: ...", now, limit=3)
    blocked_workers(session, job_id)   # ("rayfarm-12@host",)
"""

from __future__ import annotations

from datetime import datetime
from typing import Iterable

from sqlalchemy import select
from sqlalchemy.orm import Session

from . import events
from .access import Principal, require_change
from .errors import NotFound
from .models import WorkerBlock

__all__ = ["note_failure", "blocked_workers", "all_blocked", "list_blocks", "clear"]


def note_failure(session: Session, job_id: str, worker: str, error: str | None,
                 now: datetime, limit: int) -> bool:
    """Count a failed unit of `job_id` on `worker`; returns whether this
    failure blocklisted the worker (`limit` 0: never)."""
    row = session.get(WorkerBlock, (job_id, worker))
    if row is None:
        row = WorkerBlock(job_id=job_id, worker=worker[:200], failures=0)
        session.add(row)
    row.failures = (row.failures or 0) + 1
    row.last_error = error
    if limit and row.blocked is None and row.failures >= limit:
        row.blocked = now
        return True
    return False


def blocked_workers(session: Session, job_id: str) -> tuple[str, ...]:
    """The workers blocklisted for the job, by name."""
    return tuple(session.scalars(select(WorkerBlock.worker).where(
        WorkerBlock.job_id == job_id, WorkerBlock.blocked.is_not(None))
        .order_by(WorkerBlock.worker)))


def all_blocked(blocked: Iterable[str], workers) -> str | None:
    """If every live (busy or idle, enabled) worker of `workers` (WorkerInfo)
    is in `blocked`, the job's error saying so; else None. No live worker at
    all is not this: the job waits for one."""
    live = [w.name for w in workers if w.state in ("busy", "idle") and not w.disabled]
    blocked = set(blocked)
    if live and blocked.issuperset(live):
        return (f"every live worker is blocklisted for this job ({', '.join(sorted(live))}); "
                "clear the blocklist and retry the job")
    return None


def list_blocks(session: Session, job_id: str) -> list[WorkerBlock]:
    """The job's rows: workers that failed its units, blocklisted or not yet."""
    return list(session.scalars(select(WorkerBlock).where(WorkerBlock.job_id == job_id)
                                .order_by(WorkerBlock.worker)))


def clear(session: Session, actor: Principal, job, worker: str) -> None:
    """Take `worker` off the job's blocklist, its failure count with it (the
    job's owner or an admin; `job` is the one the caller looked up)."""
    require_change(actor, job.owner, f"job '{job.id}'")
    row = session.get(WorkerBlock, (job.id, worker))
    if row is None:
        raise NotFound(f"worker '{worker}' has no failures on job '{job.id}'")
    session.delete(row)
    events.note(job)
