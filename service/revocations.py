"""Logins that end, ending their event streams within a second, on every replica.

    watch = RevocationWatch(sessions, hub)
    watch.start()      # a thread reads the ledger's logins mark while streams are open
    watch.stop()

A revoked token, a logout, a disabled user or a new role must end that
caller's event streams at once, however busy they are. Asking the ledger at
every event would cost a query per event per stream; instead one thread per
service reads `auth.logins_mark` (the count of revoked tokens, the users'
roles and flags: two small queries) every `interval` seconds while any stream
is open, and when it moved calls `EventHub.logins_changed`: each stream then
checks its own caller once (service.api.routes.events). A stream checks once
when it starts too, and the first read after a time without streams counts
as a change: a login that ended between a stream's authentication and the
watch's reading is not missed. It reads the ledger
itself, so a change made by another replica, or by `rayfarm tokens revoke` on
the ledger, is seen the same way on SQLite and PostgreSQL.
"""

from __future__ import annotations

from sqlalchemy.orm import Session, sessionmaker

from . import auth
from .events import EventHub
from .poller import Poller

__all__ = ["RevocationWatch", "INTERVAL"]

INTERVAL = 0.5  # seconds between two reads of the mark while streams are open


class RevocationWatch(Poller):
    """Polls `auth.logins_mark` while `hub` has subscribers (module doc)."""

    what = "revocation watch"

    def __init__(self, sessions: sessionmaker[Session], hub: EventHub,
                 interval: float = INTERVAL):
        super().__init__(interval)
        self.sessions, self.hub = sessions, hub
        self._mark: tuple | None = None

    def wanted(self) -> bool:
        return bool(self.hub.subscribers)

    def idle(self) -> None:
        self._mark = None  # unknown from here on: the next read wakes the streams

    def poll(self) -> None:
        """Read the mark; wake the streams if it moved since the last read, or
        if there was none (a stream opened while nothing was read may have
        missed a change)."""
        with self.sessions() as session:
            mark = auth.logins_mark(session)
        self.polls += 1
        if mark != self._mark:
            self.hub.logins_changed()
        self._mark = mark
