"""The running service's parts, assembled from settings: ledger, store,
executor, scheduler, leadership, event hub (and its relay between replicas)
and thumbnailer. Built by the app's lifespan, closed with it.

    with Farm.open(Settings(data_dir="/tmp/farm")) as farm:
        farm.scheduler.tick()       # a test drives it by hand
        farm.start()                # or: lead (or stand by), relay, schedule
"""

from __future__ import annotations

import logging
import multiprocessing
from dataclasses import dataclass

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from .admission import RateLimiter
from .auth import bootstrap_admin
from .db import open_ledger
from .disk import DiskWatch
from .event_relay import PostgresRelay
from .events import EventHub, publish_commits
from .executors import Executor, make_executor
from .leader import Leadership, open_leadership
from .ledger_watch import LedgerWatch
from .revocations import RevocationWatch
from .metrics import FarmMetrics
from .scenes import UploadSlots, scene_hashes
from .scheduler import Scheduler
from .settings import Settings
from .store import Store
from .thumbnails import Thumbnailer

__all__ = ["Farm"]

log = logging.getLogger(__name__)


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
    leadership: Leadership  # whether this replica runs the scheduler (service.leader)
    relay: PostgresRelay | None  # events to and from other replicas (PostgreSQL only)
    # Events of the jobs another replica schedules, polled from the ledger while
    # this one stands by (SQLite only; service.ledger_watch).
    watch: LedgerWatch | None = None
    uploads: UploadSlots | None = None  # scene uploads at once (service.scenes)
    # Room for new work: the data dir's free space, the ledger's writes (service.disk).
    disk: DiskWatch | None = None
    # Ends the event streams of logins that ended (service.revocations).
    revocations: RevocationWatch | None = None

    @classmethod
    def open(cls, settings: Settings, metrics: FarmMetrics | None = None) -> "Farm":
        """Connect to everything; the scheduler and the thumbnailer are built but not
        started. The scheduler reports to `metrics` (by default nowhere)."""
        store = Store(settings.data_dir)
        # The service's children (upload checks, thumbnails) fork from a forkserver
        # that has imported what they run: each then starts in milliseconds, not
        # after the second or more an import of the renderer takes. (Only before
        # the forkserver starts; a later call changes nothing.)
        multiprocessing.set_forkserver_preload(["service.scenes", "service.thumbnails"])
        settings.configure_renderer()  # before the pool warms up (it may solve radiosity)
        engine, sessions = open_ledger(settings)
        leadership = open_leadership(settings, engine)
        try:
            # Before anything else: a service whose data dir is not the ledger's
            # other services' must not serve (DataDirConflict names both).
            leadership.join(settings.data_dir)
            # A farm always has an admin (`rayfarm serve` made it already and printed its URL).
            bootstrap_admin(sessions, settings.data_dir, settings.admin_token)
            executor = make_executor(settings, store.scene_text, store.unit_film,
                                     asset_dir=store.asset_dir)
        except BaseException:
            leadership.stop()
            engine.dispose()
            raise
        hub = EventHub()
        publish_commits(sessions, hub)
        disk = DiskWatch(settings.data_dir, settings.min_free_bytes)
        disk.watch_ledger(engine, sessions)
        relay = watch = None
        if engine.dialect.name == "postgresql":
            relay = PostgresRelay(engine, sessions, hub)  # attached by start()
        else:
            watch = LedgerWatch(sessions, hub, leading=leadership.leading)
        leadership.guard(sessions)
        scheduler = Scheduler(settings, sessions, store, executor, hub=hub, metrics=metrics,
                              leadership=leadership)
        return cls(settings, engine, sessions, store, executor, scheduler, hub,
                   Thumbnailer(store, lambda: scene_hashes(sessions, store)), RateLimiter(),
                   leadership, relay, watch, UploadSlots(settings.max_concurrent_uploads),
                   disk=disk, revocations=RevocationWatch(sessions, hub))

    def start(self) -> None:
        """Relay (or watch for) events, try to lead, and run the scheduler's thread (which ticks
        only while this replica leads) and the thumbnailer."""
        if self.relay is not None:
            self.relay.start()
            self.events.relay = self.relay
        self.leadership.start()
        if not self.leadership.leading():
            log.warning("%s", self.standby_message())
        if self.watch is not None:
            self.watch.start()
        self.revocations.start()
        self.scheduler.start()
        self.thumbnails.start()

    def standby_message(self) -> str:
        status = self.leadership.status()
        return (f"another service runs the scheduler on this ledger ({status.get('holder')}); "
                f"this one serves HTTP and stands by to take over when it stops")

    def close(self) -> None:
        self.thumbnails.stop()
        self.scheduler.stop()
        self.leadership.stop()  # after the scheduler: a standby may start at once
        if self.watch is not None:
            self.watch.stop()
        self.revocations.stop()
        if self.relay is not None:
            self.events.relay = None
            self.relay.stop()
        self.executor.close()
        self.engine.dispose()

    def __enter__(self) -> "Farm":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
