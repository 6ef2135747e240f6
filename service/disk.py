"""Room to write: the data dir's free space and the ledger's writes.

    disk = DiskWatch(settings.data_dir, settings.min_free_bytes)
    disk.watch_ledger(engine, sessions)   # hears the ledger's failed writes, and the next good one
    disk.space_problem(), disk.ledger_problem()   # why there is no room now, or None
    disk.check_room()                      # InsufficientStorage (507, Retry-After) while the
                                           # data dir is short of space

A full disk degrades the farm; it does not fail it. What is stored stays
stored and readable, authentication only reads (service.api.auth), and new
work, which would need room (a job's units and films, an upload, an
experiment's jobs), is refused with the reason and a Retry-After until there
is room again. "No room" is either of:
- the data dir's file system has less than `min_free_bytes` free (unit films,
  results and uploads go there): submissions are refused before they start;
- the ledger failed a write for want of room (SQLite's SQLITE_FULL, which is
  also what its `max_page_count` gives; PostgreSQL's disk_full) or because it
  is read-only: that write's request is a 507 (service.api.errors), and
  /healthz says so for `LEDGER_MEMORY` seconds unless a write succeeds
  meanwhile. A submission still tries its write, so the farm takes work again
  as soon as the ledger does.
"""

from __future__ import annotations

import shutil
import sqlite3
import threading
import time
from pathlib import Path

from sqlalchemy import Engine, event
from sqlalchemy.orm import Session, sessionmaker

from .errors import InsufficientStorage

__all__ = ["DiskWatch", "ledger_cannot_write", "RETRY_AFTER", "LEDGER_MEMORY"]

RETRY_AFTER = 60.0  # seconds a refused submission is told to wait
LEDGER_MEMORY = 60.0  # seconds a failed ledger write counts without a later good one
_WROTE = "rayfarm.disk.wrote"
_PG_DISK_FULL = "53100"


def ledger_cannot_write(exc: BaseException) -> str | None:
    """Why the ledger refused a write for want of room (or of write access),
    from a database error or its driver's; None for any other error."""
    orig = getattr(exc, "orig", None) or exc
    if isinstance(orig, sqlite3.Error):
        code = getattr(orig, "sqlite_errorcode", None)
        if code == sqlite3.SQLITE_FULL:
            return f"the ledger is full ({orig})"
        if code == sqlite3.SQLITE_READONLY:
            return f"the ledger is read-only ({orig})"
    if getattr(orig, "sqlstate", None) == _PG_DISK_FULL:
        return f"the ledger's disk is full ({str(orig).splitlines()[0]})"
    return None


class DiskWatch:
    """The data dir's free space, asked when needed, and what the ledger's
    writes said last (module doc)."""

    def __init__(self, data_dir: Path, min_free_bytes: int):
        self.data_dir, self.min_free_bytes = Path(data_dir), min_free_bytes
        self._lock = threading.Lock()
        self._ledger_failed: tuple[float, str] | None = None  # (monotonic time, reason)

    # -- the ledger -----------------------------------------------------------------
    def watch_ledger(self, engine: Engine, sessions: sessionmaker[Session]) -> None:
        """Hear every failed write of `engine` and every committed write of `sessions`."""
        event.listen(engine, "handle_error", self._on_error)
        event.listen(sessions, "after_flush", self._on_flush)
        event.listen(sessions, "after_commit", self._on_commit)
        event.listen(sessions, "after_soft_rollback",
                     lambda session, _previous: session.info.pop(_WROTE, None))

    def _on_error(self, context) -> None:
        reason = ledger_cannot_write(context.original_exception)
        if reason is not None:
            self.ledger_failed(reason)

    def ledger_failed(self, reason: str) -> None:
        with self._lock:
            self._ledger_failed = (time.monotonic(), reason)

    @staticmethod
    def _on_flush(session: Session, _context) -> None:
        session.info[_WROTE] = True

    def _on_commit(self, session: Session) -> None:
        if session.info.pop(_WROTE, False):  # a write went through: there is room again
            with self._lock:
                self._ledger_failed = None

    # -- the answer -------------------------------------------------------------------
    def free_bytes(self) -> int:
        return shutil.disk_usage(self.data_dir).free

    def ledger_problem(self) -> str | None:
        with self._lock:
            failed = self._ledger_failed
        if failed is None or time.monotonic() - failed[0] > LEDGER_MEMORY:
            return None
        return f"{failed[1]}, {time.monotonic() - failed[0]:.0f} s ago"

    def space_problem(self, free: int | None = None) -> str | None:
        free = self.free_bytes() if free is None else free
        if free >= self.min_free_bytes:
            return None
        return (f"the data dir's file system has {free} bytes free, less than min_free_bytes "
                f"({self.min_free_bytes}, RAYFARM_MIN_FREE_BYTES)")

    def check_room(self) -> None:
        """`InsufficientStorage` (507 with Retry-After) while the data dir's file
        system is short of space (an unknown free space is not refused)."""
        try:
            problem = self.space_problem()
        except OSError:
            return
        if problem is not None:
            raise InsufficientStorage(f"no room for new work: {problem}; what is stored is "
                                      "kept and served, try again when there is room",
                                      retry_after=RETRY_AFTER)
