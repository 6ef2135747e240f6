"""The embedded executor: units run on `renderer.LocalPool` in this machine."""

from __future__ import annotations

import logging
import socket
import uuid
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from datetime import datetime
from typing import Callable, Sequence

from renderer import LocalPool

from ..settings import Settings
from .base import Executor, Flight, Observation, Ticket

__all__ = ["LocalExecutor"]

log = logging.getLogger(__name__)


class LocalExecutor(Executor):
    """A process pool of `settings.local_workers` single-threaded renderers."""

    name = "local"

    def __init__(self, settings: Settings, load_scene_text: Callable[[str], str]):
        self.workers = settings.local_workers
        self._load_scene_text = load_scene_text
        self._scene_texts: dict[str, str] = {}
        self._futures: dict[str, Future] = {}
        self._pool = LocalPool(self.workers)
        self._broken = False
        self.worker_name = f"local@{socket.gethostname()}"

    def _scene(self, scene_hash: str) -> str:
        if scene_hash not in self._scene_texts:
            if len(self._scene_texts) >= 16:
                self._scene_texts.pop(next(iter(self._scene_texts)))
            self._scene_texts[scene_hash] = self._load_scene_text(scene_hash)
        return self._scene_texts[scene_hash]

    def submit(self, ticket: Ticket) -> str:
        if self._broken:  # a child died; its futures are reported lost, start afresh
            self._pool.shutdown(cancel=True)
            self._pool = LocalPool(self.workers)
            self._broken = False
        task_id = uuid.uuid4().hex
        self._futures[task_id] = self._pool.submit(
            ticket.scene_hash, self._scene(ticket.scene_hash), ticket.spec, ticket.unit)
        return task_id

    def observe(self, flights: Sequence[Flight], now: datetime) -> list[Observation]:
        return [self._observe(flight) for flight in flights]

    def _observe(self, flight: Flight) -> Observation:
        for task_id in flight.task_ids:
            fut = self._futures.get(task_id)
            if fut is not None and fut.done() and not fut.cancelled() and fut.exception() is None:
                return Observation("done", film=fut.result(), worker=self.worker_name)
        latest = self._futures.get(flight.task_ids[-1]) if flight.task_ids else None
        if latest is None or latest.cancelled():
            return Observation("lost")  # e.g. the service restarted: the pool is new
        if latest.done():
            exc = latest.exception()
            if isinstance(exc, BrokenProcessPool):
                self._broken = True
                return Observation("lost")
            return Observation("failed", error=f"{type(exc).__name__}: {exc}")
        if latest.running():
            return Observation("running", worker=self.worker_name)
        return Observation("queued")

    def release(self, task_ids: Sequence[str]) -> None:
        for task_id in task_ids:
            self._futures.pop(task_id, None)

    def cancel(self, job_id: str, task_ids: Sequence[str]) -> None:
        for task_id in task_ids:
            fut = self._futures.pop(task_id, None)
            if fut is not None:
                fut.cancel()  # only units not yet started; running ones finish unseen

    def capacity(self) -> int:
        # Two per process keeps the pool busy while cancel stays quick.
        busy = sum(1 for fut in self._futures.values() if not fut.done())
        return max(2 * self.workers - busy, 0)

    def health(self) -> dict:
        return {"executor": self.name, "workers": self.workers}

    def close(self) -> None:
        self._pool.shutdown(cancel=True)
