"""Events across service replicas: PostgreSQL LISTEN/NOTIFY.

    relay = PostgresRelay(engine, sessions, hub)
    hub.relay = relay          # hub.publish() now NOTIFYs instead of delivering
    relay.start()              # a thread LISTENs and delivers to this replica's streams

With several replicas on one PostgreSQL ledger, a job changed by the leader
(which runs the scheduler) must reach a stream opened on any replica. Every
event is sent with `pg_notify` on the channel `rayfarm_events`, and every
replica, the sender too, delivers what it hears to its own hub: one path, one
order. A NOTIFY payload holds at most 8000 bytes; a larger job or unit event
travels as its reference and each replica reads the row itself. Events missed
while the listening connection was away are not replayed: every stream is told
to resynchronise from a snapshot (`Subscription.overflowed`).

On SQLite the hub delivers in-process: the service that runs the scheduler
publishes what it commits, and a standby on the same file reads the changes
from the ledger (`service.ledger_watch`).
"""

from __future__ import annotations

import json
import logging
import threading

from sqlalchemy import Engine, select, text
from sqlalchemy.orm import Session, sessionmaker

from .events import EventHub

__all__ = ["CHANNEL", "PostgresRelay"]

log = logging.getLogger(__name__)

CHANNEL = "rayfarm_events"
PAYLOAD_LIMIT = 7900  # bytes; PostgreSQL refuses a NOTIFY payload of 8000 or more


class PostgresRelay:
    """Sends hub events with NOTIFY; a thread LISTENs and delivers them locally."""

    def __init__(self, engine: Engine, sessions: sessionmaker[Session], hub: EventHub):
        self.engine, self.sessions, self.hub = engine, sessions, hub
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._listening = threading.Event()
        self.delivered = 0

    # -- sending ------------------------------------------------------------------
    def send(self, kind: str, job_id: str, data: dict, owner: str | None) -> bool:
        """NOTIFY the event to every replica; False if it could not be sent (the
        caller then delivers it here only)."""
        payload = json.dumps({"k": kind, "j": job_id, "o": owner, "d": data})
        if len(payload.encode()) > PAYLOAD_LIMIT:
            if kind not in ("job", "unit"):
                log.warning("a %s event of job %s is too large to relay", kind, job_id)
                return False
            payload = json.dumps({"k": kind, "j": job_id, "o": owner,
                                  "i": data.get("index"), "reload": True})
        try:
            with self.engine.begin() as conn:
                conn.execute(text("SELECT pg_notify(:channel, :payload)"),
                             {"channel": CHANNEL, "payload": payload})
        except Exception as exc:
            log.warning("relaying a %s event failed: %s", kind, exc)
            return False
        return True

    # -- listening ----------------------------------------------------------------
    def start(self, timeout: float = 10.0) -> None:
        """Start listening; returns once LISTEN is in place (or after `timeout`)."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="rayfarm-events", daemon=True)
        self._thread.start()
        self._listening.wait(timeout)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None

    def _run(self) -> None:
        first = True
        while not self._stop.is_set():
            try:
                self._listen(resync=not first)
            except Exception as exc:
                log.warning("event relay: %s: %s; listening again", type(exc).__name__, exc)
            first = False
            self._listening.clear()
            self._stop.wait(1.0)

    def _listen(self, resync: bool) -> None:
        raw = self.engine.raw_connection()  # the engine's URL and connect arguments
        conn = raw.driver_connection
        raw.detach()  # ours alone, closed here, never back in the pool
        try:
            conn.autocommit = True
            conn.execute(f"LISTEN {CHANNEL}")
            self._listening.set()
            if resync:  # what was sent while we were away is gone: streams reload
                self.hub.resync_all()
            while not self._stop.is_set():
                for note in conn.notifies(timeout=0.5):
                    self._deliver(note.payload)
        finally:
            conn.close()

    def _deliver(self, payload: str) -> None:
        try:
            message = json.loads(payload)
            data = self._reload(message) if message.get("reload") else message["d"]
            if data is not None:
                self.hub.deliver(message["k"], message["j"], data, message.get("o"))
                self.delivered += 1
        except Exception:  # one bad event never stops the relay
            log.exception("delivering a relayed event failed")

    def _reload(self, message: dict) -> dict | None:
        """A job or unit event too large for NOTIFY, read back from the ledger."""
        from .models import Job, WorkUnit, utcnow
        from .schemas import JobPublic, UnitPublic

        with self.sessions() as session:
            if message["k"] == "job":
                job = session.get(Job, message["j"])
                return None if job is None else (
                    JobPublic.from_job(job, utcnow()).model_dump(mode="json"))
            unit = session.scalars(select(WorkUnit).where(
                WorkUnit.job_id == message["j"], WorkUnit.index == message["i"])).first()
            return None if unit is None else {
                "job_id": unit.job_id, **UnitPublic.from_unit(unit).model_dump(mode="json")}
