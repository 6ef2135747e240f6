"""Who runs the scheduler: exactly one service replica per ledger.

    leadership = open_leadership(settings, engine)
    leadership.join(settings.data_dir)       # refuse another data dir; record this replica
    leadership.start()                       # a thread acquires, renews, takes over
    if leadership.leading():
        with leadership.fenced():            # the scheduler's commits check the lease
            scheduler.tick()
    leadership.status()                      # for /healthz: role, holder, epoch

Every replica serves HTTP; only the leader schedules. The lease is one row of
`scheduler_lease` (name, holder, epoch, expires_at) in the ledger, whatever
the ledger: the services that share a ledger share its lease, wherever their
data dirs are. A replica takes the row only once it has expired, bumping
`epoch`; the holder renews it every `lease/5` seconds. The holder stops
scheduling (`leading()` turns false) once `lease/2` seconds passed on its own
monotonic clock since the *start* of its last successful renewal; the row
expires `lease` seconds after the ledger's clock read at that renewal, which
is later. So a leader cut off from the database stops before anyone may
start. As a fence for a tick that was already under way, each commit the
scheduler makes checks the row inside its own transaction: still ours, same
epoch, not expired; a commit after a takeover fails (`LeadershipLost`) and
rolls back. A clean stop releases the row at once.

**PostgreSQL** (`LeaseLeadership`): times are the database's
(`clock_timestamp()`), never a machine's. The fence share-locks the row, so a
takeover's UPDATE waits for the fenced commit.

**SQLite** (`SqliteLeadership`): every process that opens a SQLite file runs
on the file's host (SQLite's locking needs it), so the host's clock is the
one clock, read inside the write transaction. Writers serialise on the
database's write lock, and that is the fence: a fenced commit that writes
takes the write lock (`BEGIN IMMEDIATE`) before it checks the row, so no
takeover comes between the check and the commit. Safety rests on the epoch
and the write lock, not on the clock: a step of the clock can only hasten or
delay a takeover. A takeover after a crash need not wait for the expiry: the
leader also holds an exclusive `flock` on `<ledger file>-scheduler.lock`
(the kernel drops it when the process dies, however it dies) and writes its
holder and epoch in it; a standby that gets the lock and reads there the
row's own holder and epoch knows that holder is gone and takes over at once.
A replica lets go of the lock as soon as it stops leading.

**Data dirs**: the ledger's jobs name files in the data dir, so the services
on one ledger must share it. Each replica records itself in
`service_replicas` with its data dir (by the directory's own id, so a shared
volume mounted at other paths is still the same) and beats that record while
it lives; `join` refuses (`DataDirConflict`, naming both paths) to start a
service whose data dir differs from that of another live one.
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

from sqlalchemy import (Connection, DateTime, Engine, and_, delete, event, func, or_, select,
                        text, update)
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.orm import Session, sessionmaker

from .models import SchedulerLease, ServiceReplica, utcnow
from .settings import Settings
from .store import data_dir_identity

__all__ = ["DataDirConflict", "Leadership", "LeadershipLost", "LeaseLeadership",
           "SqliteLeadership", "open_leadership", "replica_identity"]

log = logging.getLogger(__name__)

LEASE_NAME = "scheduler"
_NEVER = datetime(1970, 1, 1, tzinfo=timezone.utc)


def _db_now():
    """The database's clock now (not the transaction's start, as `now()` is)."""
    return func.clock_timestamp(type_=DateTime(timezone=True))


class LeadershipLost(RuntimeError):
    """The scheduler's commit found that this replica no longer holds the lease."""


class DataDirConflict(RuntimeError):
    """Another live service on the ledger uses another data dir (the message names both)."""


def replica_identity() -> str:
    """This process among the replicas: host, pid and a random tag (a pid is reused)."""
    return f"{socket.gethostname()}/{os.getpid()}/{secrets.token_hex(3)}"


class Leadership:
    """The common part: a thread that tries to become (and stay) the leader
    every `interval` seconds once started (and beats the replica's record from
    `join` on), and a thread-local fence for the scheduler."""

    kind = "none"

    def __init__(self, interval: float, identity: str | None = None):
        self.identity = identity or replica_identity()
        self.interval = interval
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fencing = threading.local()
        self._campaigning = False  # start() was called: the thread tries to lead

    # -- the thread -----------------------------------------------------------------
    def start(self) -> None:
        self._campaigning = True
        self._attempt()  # the first replica leads from its first tick
        self._run_thread()

    def _run_thread(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="rayfarm-leader", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the thread, give the leadership up (call after the scheduler
        stopped) and remove the replica's record."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)
            self._thread = None
        self._campaigning = False
        try:
            self._release()
        except Exception:  # the lease then lapses by itself
            log.exception("releasing the scheduler lease failed")
        try:
            self._leave()
        except Exception:  # the record then lapses by itself
            log.exception("removing this replica's record failed")

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            if self._campaigning:
                self._attempt()
            try:
                self._beat()
            except Exception as exc:  # the database is away: the record lapses meanwhile
                log.warning("replica record: %s: %s", type(exc).__name__, exc)

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

    def _beat(self) -> None:
        """Refresh this replica's record (after `join`)."""

    def _leave(self) -> None:
        """Remove this replica's record."""


class LeaseLeadership(Leadership):
    """The lease row on a PostgreSQL ledger, and the replicas' records; see the
    module doc. `SqliteLeadership` changes the clock and the fence."""

    kind = "lease"

    def __init__(self, engine: Engine, lease_seconds: float, identity: str | None = None):
        super().__init__(lease_seconds / 5, identity)
        self.engine = engine
        self.lease = timedelta(seconds=lease_seconds)
        self.epoch: int | None = None
        self._renewed_at = 0.0  # monotonic start of the last successful acquire/renew
        self._lock = threading.Lock()
        self._data_dir: tuple[str, str] | None = None  # (path, id) once joined

    # -- what the two ledgers do differently ---------------------------------------
    def _now(self):
        """The ledger's clock now, for a statement of the current write transaction."""
        return _db_now()

    @contextlib.contextmanager
    def _writing(self) -> Iterator[Connection]:
        with self.engine.begin() as conn:
            yield conn

    def _insert(self, table):
        return pg_insert(table)

    def _lock_replicas(self, conn: Connection) -> None:
        # Two services that start at once must not both find the other absent.
        conn.execute(text(f"LOCK TABLE {ServiceReplica.__tablename__} "
                          "IN SHARE ROW EXCLUSIVE MODE"))

    # -- the lease -----------------------------------------------------------------
    def leading(self) -> bool:
        with self._lock:
            return (self.epoch is not None
                    and time.monotonic() - self._renewed_at < self.lease.total_seconds() / 2)

    def _set_epoch(self, epoch: int | None, renewed_at: float | None = None) -> None:
        with self._lock:
            self.epoch = epoch
            if epoch is not None and renewed_at is not None:
                self._renewed_at = renewed_at

    def _renew(self, conn: Connection, now) -> int | None:
        """Extend the lease, unless someone took it (then its epoch differs): the epoch or None."""
        table = SchedulerLease.__table__
        return conn.execute(
            update(table).where(table.c.name == LEASE_NAME, table.c.holder == self.identity,
                                table.c.epoch == self.epoch)
            .values(expires_at=now + self.lease, renewed_at=now)
            .returning(table.c.epoch)).scalar()

    def _take(self, conn: Connection, now, takeable) -> int | None:
        """Take the row where `takeable` holds (made first if missing): the new epoch or None."""
        table = SchedulerLease.__table__
        conn.execute(self._insert(table).values(name=LEASE_NAME, holder="", epoch=0,
                                                expires_at=_NEVER).on_conflict_do_nothing())
        return conn.execute(
            update(table).where(table.c.name == LEASE_NAME, takeable)
            .values(holder=self.identity, epoch=table.c.epoch + 1,
                    expires_at=now + self.lease, acquired_at=now, renewed_at=now)
            .returning(table.c.epoch)).scalar()

    def _acquire_or_renew(self) -> None:
        sent = time.monotonic()
        with self._writing() as conn:
            now = self._now()
            if self.epoch is not None:
                epoch = self._renew(conn, now)
            else:
                epoch = self._take(conn, now, SchedulerLease.__table__.c.expires_at < now)
        self._set_epoch(epoch, sent)

    def verify(self, session: Session) -> None:
        table = SchedulerLease.__table__
        held = self.epoch is not None and session.execute(
            select(table.c.epoch).where(table.c.name == LEASE_NAME,
                                        table.c.holder == self.identity,
                                        table.c.epoch == self.epoch,
                                        table.c.expires_at > _db_now())
            .with_for_update(read=True)).first() is not None
        if not held:
            self._set_epoch(None)
            raise LeadershipLost(f"{self.identity} no longer holds the scheduler lease")

    def _release(self) -> None:
        if self.epoch is None:
            return
        table = SchedulerLease.__table__
        with self._writing() as conn:
            conn.execute(update(table).where(table.c.name == LEASE_NAME,
                                             table.c.holder == self.identity,
                                             table.c.epoch == self.epoch)
                         .values(expires_at=_NEVER))
        self._set_epoch(None)

    def _read_lease(self, conn: Connection):
        """(the lease row or None, the ledger's clock now)."""
        row = conn.execute(select(SchedulerLease.__table__, _db_now().label("db_now"))
                           .where(SchedulerLease.name == LEASE_NAME)).first()
        return row, (row.db_now if row is not None else None)

    def status(self) -> dict:
        role = "leader" if self.leading() else "standby"
        report = {"role": role, "replica": self.identity, "lease": "ledger"}
        try:
            with self.engine.connect() as conn:
                row, now = self._read_lease(conn)
        except Exception as exc:
            report["holder"] = f"unknown ({type(exc).__name__})"
            return report
        if row is not None:
            expires_in = (row.expires_at - now).total_seconds()
            report.update(holder=row.holder if expires_in > 0 else None, epoch=row.epoch,
                          expires_in=round(expires_in, 3) if expires_in > 0 else 0.0)
        return report

    # -- the replicas and their data dirs ---------------------------------------
    def _conflict(self, conn: Connection, now, path: str, ident: str) -> str | None:
        """Why a service with this data dir may not serve on the ledger: another
        live replica uses another data dir (None if none does)."""
        table = ServiceReplica.__table__
        others = conn.execute(select(table).where(table.c.identity != self.identity,
                                                  table.c.seen_at > now - self.lease)
                              .order_by(table.c.started)).all()
        for other in others:
            if other.data_dir_id == ident:
                continue
            ledger = self.engine.url.render_as_string(hide_password=True)
            same_path = (f"; the path is the same, but it names another directory there "
                         f"(data dir id {other.data_dir_id}, here {ident})"
                         if other.data_dir == path else "")
            return (f"another rayfarm service ({other.identity}) runs on this ledger "
                    f"({ledger}) with the data dir {other.data_dir}, and this one's data dir "
                    f"is {path}{same_path}. The services on one ledger must share one data "
                    f"dir (its jobs' files are there): start this one with "
                    f"RAYFARM_DATA_DIR={other.data_dir}, or give it a ledger of its own "
                    f"(RAYFARM_DATABASE_URL). A service that died is forgotten "
                    f"{self.lease.total_seconds():g} s after its last beat.")
        return None

    def check(self, data_dir: Path) -> None:
        """Raise DataDirConflict if another live replica uses another data dir (records nothing)."""
        path = str(Path(data_dir).resolve())
        with self.engine.connect() as conn:
            problem = self._conflict(conn, self._now(), path, data_dir_identity(Path(path)))
        if problem:
            raise DataDirConflict(problem)

    def join(self, data_dir: Path) -> None:
        """Record this replica and its data dir in the ledger (refusing with
        DataDirConflict as `check` does), in one transaction with the check,
        and beat the record from the leadership's thread until `stop`."""
        path = str(Path(data_dir).resolve())
        ident = data_dir_identity(Path(path))
        table = ServiceReplica.__table__
        with self._writing() as conn:
            self._lock_replicas(conn)
            now = self._now()
            conn.execute(delete(table).where(table.c.seen_at < now - self.lease))  # dead
            problem = self._conflict(conn, now, path, ident)
            if problem:
                raise DataDirConflict(problem)
            conn.execute(self._insert(table).values(identity=self.identity, data_dir=path,
                                                    data_dir_id=ident, started=now,
                                                    seen_at=now)
                         .on_conflict_do_update(index_elements=[table.c.identity],
                                                set_={"seen_at": now}))
        self._data_dir = (path, ident)
        self._run_thread()

    def _beat(self) -> None:
        if self._data_dir is None:
            return
        path, ident = self._data_dir
        table = ServiceReplica.__table__
        with self._writing() as conn:
            now = self._now()
            # Back if it was taken for dead (this replica stalled for a lease).
            conn.execute(self._insert(table).values(identity=self.identity, data_dir=path,
                                                    data_dir_id=ident, started=now,
                                                    seen_at=now)
                         .on_conflict_do_update(index_elements=[table.c.identity],
                                                set_={"seen_at": now}))

    def _leave(self) -> None:
        if self._data_dir is None:
            return
        table = ServiceReplica.__table__
        with self._writing() as conn:
            conn.execute(delete(table).where(table.c.identity == self.identity))
        self._data_dir = None


class SqliteLeadership(LeaseLeadership):
    """The lease row on a SQLite ledger: the host's clock, the write lock as the
    fence, and the lock file beside the ledger for a takeover at once after a
    crash; see the module doc. `lock_path` None (an in-memory ledger): expiry only."""

    def __init__(self, engine: Engine, lease_seconds: float, lock_path: Path | None,
                 identity: str | None = None):
        super().__init__(engine, lease_seconds, identity)
        self.lock_path = lock_path
        self._fd: int | None = None  # the lock file, exclusively locked, while leading

    def _now(self):
        return utcnow()

    @contextlib.contextmanager
    def _writing(self) -> Iterator[Connection]:
        with self.engine.connect() as conn:
            # The write lock before anything is read, so what is read (and the
            # clock read after it) is not older than the lock.
            conn.exec_driver_sql("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.rollback()
                raise
            conn.commit()

    def _insert(self, table):
        return sqlite_insert(table)

    def _lock_replicas(self, conn: Connection) -> None:
        pass  # BEGIN IMMEDIATE has the database's write lock already

    # -- the lock file ---------------------------------------------------------
    def _try_lock(self) -> int | None:
        """The lock file, exclusively locked, or None while another process holds it."""
        if self.lock_path is None:
            return None
        fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        return fd

    @staticmethod
    def _last_holder(fd: int) -> tuple[str, int] | None:
        """The holder and epoch the lock's last holder wrote in it."""
        try:
            holder, epoch = os.pread(fd, 1024, 0).decode().split("\n")[:2]
            return holder, int(epoch)
        except (ValueError, UnicodeDecodeError):
            return None

    def _keep_lock(self, fd: int, epoch: int) -> None:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{self.identity}\n{epoch}\n".encode(), 0)
        with self._lock:
            self._fd = fd

    def _set_epoch(self, epoch: int | None, renewed_at: float | None = None) -> None:
        with self._lock:
            self.epoch = epoch
            if epoch is not None and renewed_at is not None:
                self._renewed_at = renewed_at
            if epoch is None and self._fd is not None:
                os.close(self._fd)  # not leading: a standby may take over at once
                self._fd = None

    def _acquire_or_renew(self) -> None:
        sent = time.monotonic()
        table = SchedulerLease.__table__
        if self.epoch is not None:
            with self._writing() as conn:
                epoch = self._renew(conn, self._now())
            if epoch is not None and self._fd is None:
                # Led since an expiry, without the lock: hold it from now on, so a
                # crash of this process is seen at once too.
                fd = self._try_lock()
                if fd is not None:
                    self._keep_lock(fd, epoch)
            self._set_epoch(epoch, sent)
            return
        fd = self._try_lock()
        try:
            last = self._last_holder(fd) if fd is not None else None
            with self._writing() as conn:
                now = self._now()
                takeable = table.c.expires_at < now
                if last is not None:  # its holder let the lock go: it is gone
                    takeable = or_(takeable, and_(table.c.holder == last[0],
                                                  table.c.epoch == last[1]))
                epoch = self._take(conn, now, takeable)
            if epoch is not None and fd is not None:
                self._keep_lock(fd, epoch)
                fd = None
        finally:
            if fd is not None:
                os.close(fd)
        self._set_epoch(epoch, sent)

    def verify(self, session: Session) -> None:
        table = SchedulerLease.__table__
        held = False
        if self.epoch is not None:
            conn = session.connection()
            if (not conn.connection.dbapi_connection.in_transaction
                    and (session.new or session.dirty or session.deleted)):
                # The commit will write: the write lock now, held to the commit.
                # (A transaction that wrote already holds it.)
                conn.exec_driver_sql("BEGIN IMMEDIATE")
            held = conn.execute(
                select(table.c.epoch).where(table.c.name == LEASE_NAME,
                                            table.c.holder == self.identity,
                                            table.c.epoch == self.epoch,
                                            table.c.expires_at > utcnow())).first() is not None
        if not held:
            self._set_epoch(None)
            raise LeadershipLost(f"{self.identity} no longer holds the scheduler lease")

    def _read_lease(self, conn: Connection):
        row = conn.execute(select(SchedulerLease.__table__)
                           .where(SchedulerLease.name == LEASE_NAME)).first()
        return row, utcnow()


def _sqlite_lock_path(engine: Engine) -> Path | None:
    """`<ledger file>-scheduler.lock`, or None for an in-memory ledger."""
    database = engine.url.database
    if not database or database == ":memory:" or engine.url.query.get("mode") == "memory":
        return None
    if database.startswith("file:"):  # a URI filename
        database = database[5:].split("?", 1)[0]
    return Path(database).resolve().with_name(Path(database).name + "-scheduler.lock")


def open_leadership(settings: Settings, engine: Engine) -> LeaseLeadership:
    """The lease row in the ledger, on SQLite or PostgreSQL."""
    if engine.dialect.name == "sqlite":
        return SqliteLeadership(engine, settings.leader_lease_seconds, _sqlite_lock_path(engine))
    if engine.dialect.name != "postgresql":
        raise ValueError(f"no scheduler lease on {engine.dialect.name}; "
                         "use SQLite or PostgreSQL for the ledger")
    return LeaseLeadership(engine, settings.leader_lease_seconds)
