"""The executor interface and the plain data it exchanges with the scheduler."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from datetime import datetime
from typing import Literal, Sequence

__all__ = ["Ticket", "Flight", "Observation", "Executor", "RunningUnit", "WorkerInfo",
           "WORKER_STATES"]

WORKER_STATES = ("busy", "idle", "lost", "offline")


@dataclass(frozen=True)
class Ticket:
    """Everything needed to run one unit: ids and parameters, no scene text."""

    job_id: str
    index: int
    scene_hash: str
    spec: dict
    unit: dict
    priority: int = 0  # the job's; higher first (executors may pass it to the broker)
    # The SHA-256 of the stored films of the units this one needs (a DAG job's
    # photon map, bootstrap, radiosity solution...), by unit index; empty for
    # tile units. The executor finds the bytes by digest where the unit that
    # made them left them, or else in the store (`load_unit_film`).
    inputs: dict[int, str] = field(default_factory=dict)
    # Whether later units of the job read this unit's film: the executor keeps
    # it at hand (in Redis) for them after it is stored, instead of dropping it.
    is_input: bool = False
    # Workers blocklisted for the job (too many failed units): they decline it.
    blocked: tuple[str, ...] = ()


@dataclass(frozen=True)
class Flight:
    """A unit the ledger believes is queued or running, with every task id it had."""

    job_id: str
    index: int
    state: Literal["queued", "running"]
    task_ids: tuple[str, ...]
    enqueued_at: datetime
    started_at: datetime | None


@dataclass(frozen=True)
class Observation:
    """What an executor knows about a unit in flight.

    `lost`: no task of the unit will ever report (worker died, message gone);
    the scheduler enqueues it again without counting an attempt. `cause` says
    why, for the metrics and the unit's `requeue_reason` (with `error` as the
    sentence shown): "worker" (its worker's presence says lost), "lease" (no
    heartbeat of the unit for a lease), "message" (queued, but gone from the
    broker), "declined" (a blocklisted or disabled worker gave it back).
    `crashed`: the process rendering the unit died under it (a segfault in a
    kernel, a SIGKILL of that process); `error` says how, in
    `renderer.process_death`'s words. It spends an attempt, like `failed`: a
    unit that kills every process it runs in fails after `max_attempts`.
    `worker` of a failed unit is the worker the attempt failed on, when known
    (it counts towards that worker's blocklisting for the job).
    `log`: with done or failed, the unit's own log as its render process
    captured it (renderer.unitlog: lines, traceback, dropped), if any.
    """

    state: Literal["queued", "running", "done", "failed", "crashed", "lost"]
    film: bytes | None = None
    digest: str | None = None  # SHA-256 of `film`, if the executor verified it
    worker: str | None = None
    error: str | None = None
    log: dict | None = None
    cause: str | None = None


@dataclass(frozen=True)
class RunningUnit:
    job_id: str
    index: int
    since: datetime | None = None
    task_id: str | None = None  # the task rendering it (Celery), when known


@dataclass(frozen=True)
class WorkerInfo:
    """A render worker as an executor sees it: a Celery worker node or the
    embedded pool, each with `concurrency` render processes.

    `state`: busy (rendering), idle, lost (no heartbeat within the limit: killed
    or cut off) or offline (shut down cleanly). The counters are over the
    units it finished since it started; `seconds` is their render time."""

    name: str
    kind: Literal["local", "celery"]
    host: str
    state: Literal["busy", "idle", "lost", "offline"]
    concurrency: int
    running: tuple[RunningUnit, ...]
    units_done: int
    samples: int
    rays: int
    seconds: float
    started: datetime | None
    last_seen: datetime | None
    silent_seconds: float = 0.0  # since the last heartbeat, on the broker's clock
    disabled: bool = False  # drained by an admin: finishes what it runs, takes nothing new
    # Task ids whose messages the worker holds (prefetched or running), when known.
    reserved: tuple[str, ...] = ()
    # Task ids its previous process under the same name held when it died.
    abandoned: tuple[str, ...] = ()


class Executor(ABC):
    """Runs units somewhere; called from the scheduler thread only (but for
    `workers` and `health`, which any thread may call)."""

    name: str
    # Whether a worker that fails N units of a job is blocklisted for it
    # (service.blocklist): true where other workers can take its units.
    blocklists_workers: bool = True

    @abstractmethod
    def submit(self, ticket: Ticket) -> str:
        """Start running a unit; returns the new task id."""

    @abstractmethod
    def observe(self, flights: Sequence[Flight], now: datetime) -> list[Observation]:
        """One observation per flight, in order. Any task id's result counts."""

    @abstractmethod
    def release(self, task_ids: Sequence[str]) -> None:
        """Forget the results of these tasks (the unit's film is stored)."""

    def drop_films(self, digests: Sequence[str]) -> None:
        """The job these unit films belong to is over: let go of any copy kept
        for later units (`Ticket.is_input`). Optional."""

    @abstractmethod
    def cancel(self, job_id: str, task_ids: Sequence[str]) -> None:
        """The job is over for these tasks: stop them, queued or running (a
        running unit's process is stopped, not left to finish); their results
        will be ignored."""

    def stop(self, task_ids: Sequence[str]) -> None:
        """Stop these tasks, queued or running, and forget them; the job goes on
        (the unit was preempted, withdrawn or ran over its time budget, and the
        scheduler puts it back to pending or enqueues it again under a new
        task). A stopped task's outcome is never reported as a crash.
        Optional: an executor that cannot stop tasks lets them finish unseen."""

    def render_processes(self) -> int | None:
        """How many units this executor renders at once (its live, enabled
        render processes), for fair share over those processes
        (`service.fairshare.rebalance`); None if unknown: then no unit is
        preempted or withdrawn."""
        return None

    @abstractmethod
    def capacity(self, in_flight: int) -> int:
        """How many more units to submit now, given `in_flight` units the ledger
        has queued or running (the rest wait as `pending`).

        Every executor bounds its work in flight to a little more than it can
        run at once: what waits in an executor's own queue is served first in,
        first out, past the scheduler's fair share, so a deep queue would let one
        job hold the farm. The count comes from the ledger, the truth, since an
        executor's own count forgets a restart."""

    def on_progress(self, callback) -> None:
        """Call `callback()` (from any thread) whenever a unit may have finished,
        so the scheduler looks again before its next regular tick. Optional:
        without it, the scheduler just polls."""

    def news(self) -> set[str] | None:
        """The jobs whose units in flight this executor has news of (one
        finished, failed, died or began rendering) since the last call; None
        if it cannot tell (the default), and the scheduler then looks at every
        job with units in flight on every tick. A job it has no news of waits
        for the next tick without a transaction of its own."""
        return None

    def work_ahead(self) -> bool:
        """Has every render process a unit waiting for it behind the one it
        renders? Then the scheduler may pace its ticks (`Scheduler._pause`):
        units that land meanwhile are collected together, and no process
        idles for it. Unknown (the default): no, the scheduler ticks at once."""
        return False

    def workers(self) -> list[WorkerInfo]:
        """The workers this executor runs units on, as last seen."""
        return []

    def set_worker_enabled(self, name: str, enabled: bool) -> None:
        """Drain (`enabled=False`) or re-enable a worker: a disabled one finishes
        the units it runs and takes no new ones. The name is one of `workers()`."""
        raise NotImplementedError(f"the {self.name} executor cannot disable workers")

    def remove_worker(self, name: str) -> None:
        """Forget a lost or offline worker (one of `workers()`, not live)."""
        raise NotImplementedError(f"the {self.name} executor cannot remove workers")

    def health(self) -> dict:
        return {"executor": self.name}

    def close(self) -> None:
        pass
