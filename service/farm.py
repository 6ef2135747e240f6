"""The running service's parts, assembled from settings: ledger, store,
executor, scheduler, event hub and thumbnailer. Built by the app's lifespan, closed with it.

    with Farm.open(Settings(data_dir="/tmp/farm")) as farm:
        farm.scheduler.tick()
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from .admission import RateLimiter
from .auth import bootstrap_admin
from .db import open_ledger
from .events import EventHub, publish_commits
from .executors import Executor, make_executor
from .metrics import FarmMetrics
from .scenes import scene_hashes
from .scheduler import Scheduler
from .settings import Settings
from .store import Store
from .thumbnails import Thumbnailer

__all__ = ["Farm"]


@dataclass
class Farm:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    store: Store
    executor: Executor
    scheduler: Scheduler
    events: EventHub
    thumbnails: Thumbnailer
    limiter: RateLimiter  # submissions per token, uploads per owner (service.admission)

    @classmethod
    def open(cls, settings: Settings, metrics: FarmMetrics | None = None) -> "Farm":
        """Connect to everything; the scheduler and the thumbnailer are built but not
        started. The scheduler reports to `metrics` (by default nowhere)."""
        store = Store(settings.data_dir)
        settings.configure_renderer()  # before the pool warms up (it may solve radiosity)
        engine, sessions = open_ledger(settings)
        try:
            # A farm always has an admin (`rayfarm serve` made it already and printed its URL).
            bootstrap_admin(sessions, settings.data_dir, settings.admin_token)
            executor = make_executor(settings, store.scene_text, store.unit_film)
        except BaseException:
            engine.dispose()
            raise
        hub = EventHub()
        publish_commits(sessions, hub)
        return cls(settings, engine, sessions, store, executor,
                   Scheduler(settings, sessions, store, executor, hub=hub, metrics=metrics), hub,
                   Thumbnailer(store, lambda: scene_hashes(sessions, store)), RateLimiter())

    def close(self) -> None:
        self.thumbnails.stop()
        self.scheduler.stop()
        self.executor.close()
        self.engine.dispose()

    def __enter__(self) -> "Farm":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
