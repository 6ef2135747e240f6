"""The embedded executor: units run on `renderer.LocalPool` in this machine.

It reports a unit `running` only while a pool process renders it (the pool's
`rendering` slots), not while it waits in the pool's queue, and counts the
units, samples and render seconds the pool has done: the one worker of the
embedded mode, as `workers()` shows it. A unit whose render process died is
`crashed` (an attempt spent); the pool replaced that process, and the other
units in flight never noticed. `cancel` and `stop` end a unit whether it
waits in the pool's queue or renders (the pool kills its process, which it
replaces); such a unit's outcome is never reported.

A DAG unit's inputs come by digest (`Ticket.inputs`) and go to the pool as
bytes: the films of units that later units read (`Ticket.is_input`) are kept
in memory when they land (`_films`, bounded), so the tiles of a photon round
share one copy and the store is read only for what fell out of it (or after
a restart).
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
import socket
import threading
import uuid
from collections import OrderedDict
from concurrent.futures import Future
from datetime import datetime, timezone
from typing import Callable, Sequence

from renderer import LocalPool, PartialFilm, RenderProcessDied

from ..settings import Settings
from .base import Executor, Flight, Observation, RunningUnit, Ticket, WorkerInfo

__all__ = ["LocalExecutor"]

log = logging.getLogger(__name__)


class LocalExecutor(Executor):
    """A process pool of `settings.local_workers` single-threaded renderers."""

    name = "local"
    blocklists_workers = False  # its one worker: max_attempts alone decides
    MAX_AHEAD = 16  # units in flight per process, at most (see `limit`)
    FILMS_KEPT_BYTES = 256 * 1024 * 1024  # input films kept in memory (see the module doc)

    def __init__(self, settings: Settings, load_scene_text: Callable[[str], str],
                 load_unit_film: Callable[[str, int], bytes] | None = None,
                 asset_dir=None):
        self.processes = settings.local_workers
        # the render processes read a scene's assets from the store's files
        self.asset_dir = None if asset_dir is None else str(asset_dir)
        self.poll_interval = settings.poll_interval  # the longest a unit waits for a tick
        self._load_scene_text = load_scene_text
        self._load_unit_film = load_unit_film
        self._films: OrderedDict[str, bytes] = OrderedDict()  # digest -> input film, LRU
        self._films_bytes = 0
        self._input_tasks: set[str] = set()  # tasks whose films later units read
        self.films_loaded = 0  # input films read from the store
        self._scene_texts: dict[str, str] = {}
        self._futures: dict[str, Future] = {}
        self._pool = LocalPool(self.processes)
        self.host = socket.gethostname()
        self.worker_name = f"local@{self.host}"
        self.started = datetime.now(timezone.utc)
        # Guards what `workers()` reads from other threads.
        self._lock = threading.Lock()
        self._tags = itertools.count(1)
        self._tag_of: dict[str, int] = {}  # task id -> its pool tag
        self._unit_of: dict[int, tuple[str, int]] = {}  # pool tag -> (job id, unit index)
        self._since: dict[int, datetime] = {}  # pool tag -> first seen rendering (by observe)
        self._counted: set[str] = set()  # done tasks already counted
        self.units_done = self.samples = self.rays = 0
        self.seconds = 0.0
        self._progress = lambda: None
        self._unit_seconds = 0.1  # a running mean of render seconds per unit (see capacity)
        self._news: set[str] = set()  # jobs with a unit finished since the last `news()`
        self._seen_rendering: set[int] = set()  # pool tags rendering at the last `news()`
        self.disabled = False  # drained by an admin: no new submissions (see capacity)

    def _scene(self, scene_hash: str) -> str:
        if scene_hash not in self._scene_texts:
            if len(self._scene_texts) >= 16:
                self._scene_texts.pop(next(iter(self._scene_texts)))
            self._scene_texts[scene_hash] = self._load_scene_text(scene_hash)
        return self._scene_texts[scene_hash]

    def _keep_film(self, digest: str, film: bytes) -> None:
        if digest in self._films:
            self._films.move_to_end(digest)
            return
        self._films[digest] = film
        self._films_bytes += len(film)
        while self._films_bytes > self.FILMS_KEPT_BYTES and len(self._films) > 1:
            self._films_bytes -= len(self._films.popitem(last=False)[1])

    def _input(self, job_id: str, index: int, digest: str) -> bytes:
        film = self._films.get(digest)
        if film is None:
            if self._load_unit_film is None:
                raise RuntimeError(f"input {digest[:12]} is not in memory and this executor "
                                   "cannot read the store")
            film = self._load_unit_film(job_id, index)
            self.films_loaded += 1
            self._keep_film(digest, film)
        else:
            self._films.move_to_end(digest)
        return film

    def drop_films(self, digests: Sequence[str]) -> None:
        for digest in digests:
            film = self._films.pop(digest, None)
            if film is not None:
                self._films_bytes -= len(film)

    def submit(self, ticket: Ticket) -> str:
        task_id = uuid.uuid4().hex
        tag = next(self._tags)
        inputs = {i: self._input(ticket.job_id, i, digest) for i, digest in ticket.inputs.items()}
        future = self._pool.submit(ticket.scene_hash, self._scene(ticket.scene_hash), ticket.spec,
                                   ticket.unit, tag=tag, inputs=inputs or None,
                                   job_id=ticket.job_id, asset_dir=self.asset_dir)
        if ticket.is_input:
            self._input_tasks.add(task_id)
        future.add_done_callback(lambda _future: self._landed(ticket.job_id))
        with self._lock:
            self._futures[task_id] = future
            self._tag_of[task_id] = tag
            self._unit_of[tag] = (ticket.job_id, ticket.index)
        return task_id

    def _landed(self, job_id: str) -> None:
        with self._lock:
            self._news.add(job_id)
        self._progress()

    def news(self) -> set[str]:
        rendering = set(self._pool.rendering())
        with self._lock:
            news, self._news = self._news, set()
            news.update(self._unit_of[tag][0] for tag in rendering - self._seen_rendering
                        if tag in self._unit_of)
            self._seen_rendering = rendering
        return news

    def observe(self, flights: Sequence[Flight], now: datetime) -> list[Observation]:
        rendering = set(self._pool.rendering())
        with self._lock:  # when each unit was first seen rendering (workers() shows it)
            for tag in rendering:
                self._since.setdefault(tag, now)
        return [self._observe(flight, rendering) for flight in flights]

    def _count(self, task_id: str, film: bytes) -> None:
        if task_id in self._counted:
            return
        stats = PartialFilm.stats_from_bytes(film)
        with self._lock:
            self._counted.add(task_id)
            self.units_done += 1
            self.samples += int(stats.get("samples", 0))
            self.rays += int(stats.get("rays", 0))
            self.seconds += float(stats.get("seconds", 0.0))
            self._unit_seconds += 0.2 * (float(stats.get("seconds", 0.0)) - self._unit_seconds)

    def _observe(self, flight: Flight, rendering: set[int]) -> Observation:
        for task_id in flight.task_ids:
            fut = self._futures.get(task_id)
            if fut is not None and fut.done() and not fut.cancelled() and fut.exception() is None:
                film = fut.result()
                self._count(task_id, film)
                digest = hashlib.sha256(film).hexdigest()
                if task_id in self._input_tasks:
                    self._keep_film(digest, film)
                return Observation("done", film=film, digest=digest, worker=self.worker_name,
                                   log=getattr(fut, "unit_log", None))
        latest = self._futures.get(flight.task_ids[-1]) if flight.task_ids else None
        if latest is None or latest.cancelled():
            return Observation("lost")  # e.g. the service restarted: the pool is new
        if latest.done():
            exc = latest.exception()
            if isinstance(exc, RenderProcessDied):
                return Observation("crashed", error=str(exc), worker=self.worker_name,
                                   log=getattr(latest, "unit_log", None))
            return Observation("failed", error=f"{type(exc).__name__}: {exc}",
                               worker=self.worker_name, log=getattr(latest, "unit_log", None))
        if self._tag_of.get(flight.task_ids[-1]) in rendering or flight.state == "running":
            return Observation("running", worker=self.worker_name)
        return Observation("queued")

    def _forget(self, task_id: str) -> tuple[Future | None, int | None]:
        with self._lock:
            fut = self._futures.pop(task_id, None)
            tag = self._tag_of.pop(task_id, None)
            self._unit_of.pop(tag, None)
            self._since.pop(tag, None)
            self._counted.discard(task_id)
            self._input_tasks.discard(task_id)
        return fut, tag

    def release(self, task_ids: Sequence[str]) -> None:
        for task_id in task_ids:
            self._forget(task_id)

    def stop(self, task_ids: Sequence[str]) -> None:
        for task_id in task_ids:
            fut, tag = self._forget(task_id)
            if fut is not None and not fut.done():
                self._pool.stop(tag)  # dropped if it waits, its process killed if it renders

    def cancel(self, job_id: str, task_ids: Sequence[str]) -> None:
        self.stop(task_ids)

    def render_processes(self) -> int:
        return 0 if self.disabled else self.processes

    def workers(self) -> list[WorkerInfo]:
        now = datetime.now(timezone.utc)
        rendering = self._pool.rendering()
        with self._lock:
            running = []
            for tag in rendering:
                if tag in self._unit_of:
                    since = self._since.setdefault(tag, now)
                    running.append(RunningUnit(*self._unit_of[tag], since=since))
            return [WorkerInfo(
                name=self.worker_name, kind="local", host=self.host,
                state="busy" if running else "idle", concurrency=self.processes,
                running=tuple(running), units_done=self.units_done, samples=self.samples,
                rays=self.rays, seconds=self.seconds, started=self.started, last_seen=now,
                disabled=self.disabled)]

    def set_worker_enabled(self, name: str, enabled: bool) -> None:
        if name != self.worker_name:
            raise KeyError(name)
        self.disabled = not enabled

    def on_progress(self, callback) -> None:
        self._progress = callback

    def limit(self) -> int:
        """Units to keep in flight: enough that every process still has a unit
        waiting when the scheduler, pacing its ticks, notices what landed (a
        poll interval later, or at once when a landing leaves fewer units
        waiting than processes: `work_ahead`): two each for long units, more
        for short ones (a progressive job's first passes take milliseconds
        per unit), up to `MAX_AHEAD` each, so that the pool's queue holds
        about one poll interval of work and a newcomer, a higher priority or
        a cancel never waits long behind it."""
        per_poll = math.ceil(self.poll_interval / max(self._unit_seconds, 1e-4)) + 2
        return min(max(per_poll, 3), self.MAX_AHEAD) * self.processes

    def work_ahead(self) -> bool:
        return self._pool.waiting() >= self.processes

    def capacity(self, in_flight: int) -> int:
        if self.disabled:  # drained: what is in the pool finishes, nothing new goes
            return 0
        return max(self.limit() - in_flight, 0)

    def health(self) -> dict:
        return {"executor": self.name, "workers": self.processes}

    def close(self) -> None:
        self._pool.shutdown(cancel=True)
