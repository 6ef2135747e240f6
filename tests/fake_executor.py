"""A fake `Executor` for scheduler logic: it runs nothing. Units stay queued
until the test says they finished (`finish`), so what the scheduler chose to
put in flight, and in which order, can be read exactly.

    executor = FakeExecutor(slots=8)
    scheduler = Scheduler(settings, sessions, store, executor)
    scheduler.tick()
    executor.submitted          # the tickets, in the order they were enqueued
    executor.finish(job_id, 3)  # unit 3 lands at the next tick (an empty film)
    executor.fail(job_id, 4, "ValueError: x", worker="w1")  # its latest task failed on w1
    executor.lose(job_id, 5, cause="worker", error="worker w1 lost")
    executor.live = ["w1", "w2"]  # what workers() shows (idle Celery-like workers)
    executor.processes = 2      # render processes (fair share over them; None: unknown)
    executor.start(job_id, 6)   # its latest task renders (observed running)
    executor.stopped            # task ids the scheduler stopped (preempted, withdrawn...)
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Sequence

from renderer import PartialFilm
from service.executors import Executor, Flight, Observation, Ticket, WorkerInfo

__all__ = ["FakeExecutor"]


class FakeExecutor(Executor):
    """Keeps at most `slots` units in flight, as the ledger counts them."""

    name = "fake"

    def __init__(self, slots: int):
        self.slots = slots
        self.submitted: list[Ticket] = []
        self._tickets: dict[str, Ticket] = {}
        self._films: dict[str, bytes] = {}  # task id -> film of a finished task
        self.released: list[str] = []
        self.canceled: list[str] = []
        self._outcomes: dict[str, Observation] = {}  # task id -> a scripted failure or loss
        self.live: list[str] = []
        self.disabled: set[str] = set()
        self.processes: int | None = None
        self.rendering: set[str] = set()  # task ids observed running
        self.stopped: list[str] = []

    def submit(self, ticket: Ticket) -> str:
        task_id = uuid.uuid4().hex
        self._tickets[task_id] = ticket
        self.submitted.append(ticket)
        return task_id

    def finish(self, job_id: str, index: int) -> None:
        """Every task of the unit finishes with an empty film of its region."""
        for task_id, ticket in self._tickets.items():
            if (ticket.job_id, ticket.index) == (job_id, index):
                unit = ticket.unit
                film = PartialFilm.zeros(unit["x0"], unit["y0"], unit["x1"] - unit["x0"],
                                         unit["y1"] - unit["y0"])
                self._films[task_id] = film.to_bytes()

    def _latest_task(self, job_id: str, index: int) -> str:
        return [t for t, k in self._tickets.items() if (k.job_id, k.index) == (job_id, index)][-1]

    def fail(self, job_id: str, index: int, error: str, worker: str | None = None) -> None:
        """The unit's latest task fails (seen at the next tick), on `worker`."""
        self._outcomes[self._latest_task(job_id, index)] = Observation("failed", error=error,
                                                                       worker=worker)

    def lose(self, job_id: str, index: int, cause: str, error: str) -> None:
        """The unit's latest task is lost (seen at the next tick)."""
        self._outcomes[self._latest_task(job_id, index)] = Observation("lost", cause=cause,
                                                                       error=error)

    def start(self, job_id: str, index: int) -> None:
        """The unit's latest task renders (seen at the next tick)."""
        self.rendering.add(self._latest_task(job_id, index))

    def tickets_of(self, job_id: str, index: int) -> list[Ticket]:
        return [t for t in self.submitted if (t.job_id, t.index) == (job_id, index)]

    def observe(self, flights: Sequence[Flight], now: datetime) -> list[Observation]:
        out = []
        for flight in flights:
            films = [self._films[t] for t in flight.task_ids if t in self._films]
            scripted = self._outcomes.get(flight.task_ids[-1]) if flight.task_ids else None
            running = flight.task_ids and flight.task_ids[-1] in self.rendering
            out.append(Observation("done", film=films[0], worker="fake") if films
                       else scripted or Observation("running" if running else "queued",
                                                    worker="fake"))
        return out

    def workers(self) -> list[WorkerInfo]:
        return [WorkerInfo(name=n, kind="celery", host="fake", state="idle", concurrency=1,
                           running=(), units_done=0, samples=0, rays=0, seconds=0.0,
                           started=None, last_seen=None, disabled=n in self.disabled)
                for n in self.live]

    def release(self, task_ids: Sequence[str]) -> None:
        self.released.extend(task_ids)

    def cancel(self, job_id: str, task_ids: Sequence[str]) -> None:
        self.canceled.extend(task_ids)

    def stop(self, task_ids: Sequence[str]) -> None:
        self.stopped.extend(task_ids)
        self.rendering.difference_update(task_ids)

    def render_processes(self) -> int | None:
        return self.processes

    def capacity(self, in_flight: int) -> int:
        return max(self.slots - in_flight, 0)
