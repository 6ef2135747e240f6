"""Who runs the scheduler: exactly one service replica at a time.

    leadership = open_leadership(settings, engine)
    leadership.start()                       # a thread acquires, renews, takes over
    if leadership.leading():
        with leadership.fenced():            # the scheduler's commits check the lease
            scheduler.tick()
    leadership.status()                      # for /healthz: role, holder, epoch

Every replica serves HTTP; only the leader schedules.

**PostgreSQL** (`LeaseLeadership`): one row of `scheduler_lease` (name, holder,
epoch, expires_at). Times are the database's (`clock_timestamp()`), never a
machine's. A replica takes the row only once it has expired, bumping `epoch`;
the holder renews it every `lease/5` seconds. The holder stops scheduling
(`leading()` turns false) once `lease/2` seconds passed on its own monotonic
clock since the *start* of its last successful renewal; the row expires
`lease` seconds after the database executed that renewal, which is later. So a
leader cut off from the database stops before anyone may start. As a fence
for a tick that was already under way, each commit the scheduler makes checks
(and share-locks) the row: still ours, same epoch, not expired; a takeover's
UPDATE waits for that commit, and a commit after the takeover fails
(`LeadershipLost`) and rolls back. A clean stop releases the row at once.

**SQLite** (`FileLockLeadership`): an exclusive `flock` on
`<data_dir>/scheduler.lock`, which the kernel releases when its process dies
(however it dies). A second service on the same data dir serves HTTP as a
standby, says so in its log and in `/healthz`, and takes over when the first
one exits. A process holds its lock until it ends, so no fence is needed.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import secrets
import socket
import threading
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Iterator

from sqlalchemy import DateTime, Engine, event, func, select, update
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.orm import Session, sessionmaker

from .models import SchedulerLease
from .settings import Settings

__all__ = ["FileLockLeadership", "Leadership", "LeadershipLost", "LeaseLeadership",
           "open_leadership", "replica_identity"]

log = logging.getLogger(__name__)

LEASE_NAME = "scheduler"
_NEVER = datetime(1970, 1, 1, tzinfo=timezone.utc)


def _db_now():
    """The database's clock now (not the transaction's start, as `now()` is)."""
    return func.clock_timestamp(type_=DateTime(timezone=True))


class LeadershipLost(RuntimeError):
    """The scheduler's commit found that this replica no longer holds the lease."""


def replica_identity() -> str:
    """This process among the replicas: host, pid and a random tag (a pid is reused)."""
    return f"{socket.gethostname()}/{os.getpid()}/{secrets.token_hex(3)}"


class Leadership:
    """The common part: a thread that tries to become (and stay) the leader
    every `interval` seconds, and a thread-local fence for the scheduler."""

    kind = "none"

    def __init__(self, interval: float, identity: str | None = None):
        self.identity = identity or replica_identity()
        self.interval = interval
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fencing = threading.local()

    # -- the thread -----------------------------------------------------------------
    def start(self) -> None:
        self._stop.clear()
        self._attempt()  # the first replica leads from its first tick
        self._thread = threading.Thread(target=self._run, name="rayfarm-leader", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and give the leadership up (call after the scheduler stopped)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)
            self._thread = None
        try:
            self._release()
        except Exception:  # the lease then lapses by itself
            log.exception("releasing the scheduler lease failed")

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._attempt()

    def _attempt(self) -> None:
        was = self.leading()
        try:
            self._acquire_or_renew()
        except Exception as exc:  # the database is away: leading() lapses by itself
            log.warning("scheduler lease: %s: %s", type(exc).__name__, exc)
        now = self.leading()
        if now and not was:
            log.info("this replica (%s) now runs the scheduler%s", self.identity,
                     f" (epoch {self.epoch})" if self.epoch is not None else "")
        elif was and not now:
            log.warning("this replica (%s) lost the scheduler lease; standing by", self.identity)

    # -- the fence ------------------------------------------------------------------
    @contextlib.contextmanager
    def fenced(self) -> Iterator[None]:
        """Commits made by this thread inside the block check the lease first."""
        self._fencing.active = True
        try:
            yield
        finally:
            self._fencing.active = False

    def guard(self, sessions: sessionmaker[Session]) -> None:
        """Check the lease before each fenced commit of `sessions`."""
        def before_commit(session: Session) -> None:
            if getattr(self._fencing, "active", False):
                self.verify(session)
        event.listen(sessions, "before_commit", before_commit)

    # -- what subclasses provide ----------------------------------------------------
    epoch: int | None = None

    def leading(self) -> bool:
        raise NotImplementedError

    def verify(self, session: Session) -> None:
        """Raise LeadershipLost unless this replica still leads (in `session`)."""

    def status(self) -> dict:
        raise NotImplementedError

    def _acquire_or_renew(self) -> None:
        raise NotImplementedError

    def _release(self) -> None:
        pass


class LeaseLeadership(Leadership):
    """The lease row on a server ledger (PostgreSQL); see the module doc."""

    kind = "lease"

    def __init__(self, engine: Engine, lease_seconds: float, identity: str | None = None):
        super().__init__(lease_seconds / 5, identity)
        self.engine = engine
        self.lease = timedelta(seconds=lease_seconds)
        self.epoch: int | None = None
        self._renewed_at = 0.0  # monotonic start of the last successful acquire/renew
        self._lock = threading.Lock()

    def leading(self) -> bool:
        with self._lock:
            return (self.epoch is not None
                    and time.monotonic() - self._renewed_at < self.lease.total_seconds() / 2)

    def _acquire_or_renew(self) -> None:
        table = SchedulerLease.__table__
        now = _db_now()
        sent = time.monotonic()
        with self.engine.begin() as conn:
            if self.epoch is not None:  # renew, unless someone took it (then epoch differs)
                epoch = conn.execute(
                    update(table).where(table.c.name == LEASE_NAME,
                                        table.c.holder == self.identity,
                                        table.c.epoch == self.epoch)
                    .values(expires_at=now + self.lease, renewed_at=now)
                    .returning(table.c.epoch)).scalar()
            else:
                conn.execute(pg_insert(table).values(name=LEASE_NAME, holder="", epoch=0,
                                                     expires_at=_NEVER)
                             .on_conflict_do_nothing())
                epoch = conn.execute(
                    update(table).where(table.c.name == LEASE_NAME, table.c.expires_at < now)
                    .values(holder=self.identity, epoch=table.c.epoch + 1,
                            expires_at=now + self.lease, acquired_at=now, renewed_at=now)
                    .returning(table.c.epoch)).scalar()
        with self._lock:
            self.epoch = epoch
            if epoch is not None:
                self._renewed_at = sent

    def verify(self, session: Session) -> None:
        table = SchedulerLease.__table__
        held = self.epoch is not None and session.execute(
            select(table.c.epoch).where(table.c.name == LEASE_NAME,
                                        table.c.holder == self.identity,
                                        table.c.epoch == self.epoch,
                                        table.c.expires_at > _db_now())
            .with_for_update(read=True)).first() is not None
        if not held:
            with self._lock:
                self.epoch = None
            raise LeadershipLost(f"{self.identity} no longer holds the scheduler lease")

    def _release(self) -> None:
        if self.epoch is None:
            return
        table = SchedulerLease.__table__
        with self.engine.begin() as conn:
            conn.execute(update(table).where(table.c.name == LEASE_NAME,
                                             table.c.holder == self.identity,
                                             table.c.epoch == self.epoch)
                         .values(expires_at=_NEVER))
        with self._lock:
            self.epoch = None

    def status(self) -> dict:
        role = "leader" if self.leading() else "standby"
        report = {"role": role, "replica": self.identity, "lease": "ledger"}
        try:
            with self.engine.connect() as conn:
                row = conn.execute(select(SchedulerLease.__table__,
                                          _db_now().label("db_now"))
                                   .where(SchedulerLease.name == LEASE_NAME)).first()
        except Exception as exc:
            report["holder"] = f"unknown ({type(exc).__name__})"
            return report
        if row is not None:
            expires_in = (row.expires_at - row.db_now).total_seconds()
            report.update(holder=row.holder if expires_in > 0 else None, epoch=row.epoch,
                          expires_in=round(expires_in, 3) if expires_in > 0 else 0.0)
        return report


class FileLockLeadership(Leadership):
    """An exclusive flock on `<data_dir>/scheduler.lock` (SQLite); see the module doc."""

    kind = "file-lock"

    def __init__(self, path: Path, interval: float, identity: str | None = None):
        super().__init__(interval, identity)
        self.path = path
        self._fd: int | None = None

    def leading(self) -> bool:
        return self._fd is not None

    def _acquire_or_renew(self) -> None:
        if self._fd is not None:
            return  # held until this process closes it or dies
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return
        os.ftruncate(fd, 0)
        os.write(fd, self.identity.encode())
        self._fd = fd

    def _release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases the lock
            self._fd = None

    def holder(self) -> str | None:
        """Who holds the lock, as its holder wrote it (None if nobody does)."""
        if self._fd is not None:
            return self.identity
        try:
            fd = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            return None
        try:
            try:  # a shared lock we can get means nobody holds the exclusive one
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return os.read(fd, 400).decode(errors="replace") or "unknown"
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    def status(self) -> dict:
        return {"role": "leader" if self.leading() else "standby", "replica": self.identity,
                "lease": "file-lock", "holder": self.holder()}


def open_leadership(settings: Settings, engine: Engine) -> Leadership:
    """The lease row on PostgreSQL; the data dir's lock file on SQLite."""
    if engine.dialect.name == "sqlite":
        return FileLockLeadership(settings.data_dir / "scheduler.lock",
                                  interval=min(settings.leader_lease_seconds / 5, 1.0))
    if engine.dialect.name != "postgresql":
        raise ValueError(f"no scheduler lease on {engine.dialect.name}; "
                         "use SQLite or PostgreSQL for the ledger")
    return LeaseLeadership(engine, settings.leader_lease_seconds)
