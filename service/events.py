"""Job events: every committed change, fanned out to the event streams.

    hub = EventHub()
    publish_commits(sessions, hub)      # committed job/unit changes become events
    sub = hub.subscribe(job_id, loop)   # one job's events (None: every job's)
    event = await sub.next(timeout=15)

`service.states` notes every status change on its session (`note`); the
scheduler notes a job whose progress moved. When the transaction commits,
the noted objects are published as they stand then, units before their job,
so a stream never shows a change that was rolled back. The preview and
deletion events are published directly (`EventHub.publish`).

Event kinds (the SSE `event:` names) and their data:

    job       the job as `GET /jobs/{id}` shows it (status, progress, ETA, stats)
    unit      a unit as `GET /jobs/{id}/units` shows it, plus `job_id`: queued,
              running (started, with its worker), done (worker, seconds), ...
    preview   {"job_id", "version", "url", "noise_url", "units"}: the running
              preview and noise map were rewritten
    deleted   {"job_id"}

Streams are in-process on SQLite: the service that runs the scheduler
publishes, its HTTP handlers subscribe; a second service on the same file (a
standby) polls the ledger for changes and publishes them to its own streams
(`service.ledger_watch`). On PostgreSQL, with several service replicas,
the hub's `relay` (`service.event_relay`) carries every event to every
replica, which delivers it to its own streams. Every job and deletion event carries its job's `owner`; a
subscription made for someone who may see only their own jobs names that
owner and receives only events that carry it (an event without an owner
reaches only subscriptions without that filter: those of one job, opened
after the caller was shown to see it). A subscriber that falls more than `QUEUE_LIMIT` events
behind is told so (`overflowed`) and resynchronises from a snapshot.

When a login may have ended (a token revoked, a logout, a user disabled or
given another role: `service.revocations` sees the ledger change),
`logins_changed` bumps the hub's `logins` count and wakes every idle
subscriber: each stream checks its caller once, busy or idle, and ends if
that login is over.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import threading
from dataclasses import dataclass

from sqlalchemy import event as sa_event
from sqlalchemy import inspect as sa_inspect
from sqlalchemy.orm import Session, object_session, sessionmaker

__all__ = ["Event", "EventHub", "Subscription", "note", "publish_commits", "sse_frame", "JOB_KINDS"]

log = logging.getLogger(__name__)

_PENDING = "rayfarm.events.pending"
_SNAPSHOT = "rayfarm.events.snapshot"  # (keys, events) read at the last flush
QUEUE_LIMIT = 2000
JOB_KINDS = frozenset({"job", "deleted"})  # what a stream of every job carries


@dataclass(frozen=True)
class Event:
    id: int
    kind: str
    job_id: str
    data: dict
    owner: str | None = None

    def sse(self) -> str:
        """The event in `text/event-stream` framing."""
        return sse_frame(self.kind, self.data, self.id)


def sse_frame(kind: str, data, event_id: int | None = None) -> str:
    """One server-sent event: `id:` (if given), `event:` and one JSON `data:` line."""
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {kind}\ndata: {json.dumps(data)}\n\n"


class Subscription:
    """One stream's queue, fed from any thread, read in its event loop."""

    def __init__(self, hub: "EventHub", job_id: str | None, kinds: frozenset[str] | None,
                 loop: asyncio.AbstractEventLoop, owner: str | None = None):
        self.hub, self.job_id, self.kinds, self.loop = hub, job_id, kinds, loop
        self.owner = owner  # only events of this owner's jobs (None: no such filter)
        self.queue: asyncio.Queue[Event] = asyncio.Queue()
        self.overflowed = False

    def wants(self, event: Event) -> bool:
        return ((self.job_id is None or self.job_id == event.job_id)
                and (self.kinds is None or event.kind in self.kinds)
                and (self.owner is None or event.owner == self.owner))

    def _put(self, events: list[Event]) -> None:  # runs in the subscriber's loop
        for event in events:
            if self.queue.qsize() >= QUEUE_LIMIT:
                self.overflowed = True
                return
            self.queue.put_nowait(event)

    def _wake(self) -> None:  # runs in the subscriber's loop
        if self.queue.empty():  # a busy stream looks at the hub between its events anyway
            self.queue.put_nowait(None)

    async def next(self, timeout: float) -> Event | None:
        """The next event, or None after `timeout` seconds of silence (or when
        the hub wakes its idle subscribers: `EventHub.logins_changed`)."""
        try:
            return await asyncio.wait_for(self.queue.get(), timeout)
        except asyncio.TimeoutError:
            return None

    def close(self) -> None:
        self.hub.unsubscribe(self)


class EventHub:
    """Publishes events to every matching subscription; thread-safe."""

    def __init__(self):
        self._lock = threading.Lock()
        self._subscriptions: set[Subscription] = set()
        self._ids = itertools.count(1)
        # Carries events to every replica, whose relays `deliver` them (this
        # one's too); None: delivered here only.
        self.relay = None
        self.logins = 0  # bumped when a login may have ended (module doc)

    def subscribe(self, job_id: str | None, loop: asyncio.AbstractEventLoop,
                  kinds: frozenset[str] | None = None, owner: str | None = None) -> Subscription:
        sub = Subscription(self, job_id, kinds, loop, owner)
        with self._lock:
            self._subscriptions.add(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            self._subscriptions.discard(sub)

    @property
    def subscribers(self) -> int:
        with self._lock:
            return len(self._subscriptions)

    def publish(self, kind: str, job_id: str, data: dict, owner: str | None = None) -> None:
        """Send an event to the streams of every replica (of this one, without a relay)."""
        self.publish_many([(kind, job_id, data, owner)])

    def publish_many(self, events: list[tuple[str, str, dict, str | None]]) -> None:
        """`publish` each of (kind, job_id, data, owner), in order."""
        if self.relay is not None:
            events = [e for e in events if not self.relay.send(*e)]
        self.deliver_many(events)

    def deliver(self, kind: str, job_id: str, data: dict, owner: str | None = None) -> Event:
        """Put an event on this replica's matching subscriptions."""
        return self.deliver_many([(kind, job_id, data, owner)])[0]

    def deliver_many(self, items: list[tuple[str, str, dict, str | None]]) -> list[Event]:
        """`deliver` each of (kind, job_id, data, owner), in order, with one wake-up
        of each subscriber's loop: a commit that lands a unit changes a unit and
        its job, and a wake-up (a write to the loop's self-pipe, and the GIL
        handed to the loop's thread) per event cost the scheduler's thread more
        than the events themselves."""
        if not items:
            return []
        by_sub: dict[Subscription, list[Event]] = {}
        with self._lock:
            events = [Event(next(self._ids), kind, job_id, data, owner)
                      for kind, job_id, data, owner in items]
            for sub in self._subscriptions:
                wanted = [e for e in events if sub.wants(e)]
                if wanted:
                    by_sub[sub] = wanted
        for sub, wanted in by_sub.items():
            try:
                sub.loop.call_soon_threadsafe(sub._put, wanted)
            except RuntimeError:  # its loop is closed: the stream is gone
                self.unsubscribe(sub)
        return events


    def logins_changed(self) -> None:
        """A login may have ended: bump `logins` and wake every idle stream."""
        with self._lock:
            self.logins += 1
            targets = list(self._subscriptions)
        for sub in targets:
            try:
                sub.loop.call_soon_threadsafe(sub._wake)
            except RuntimeError:  # its loop is closed: the stream is gone
                self.unsubscribe(sub)

    def resync_all(self) -> None:
        """Events may have been missed: every stream reloads from a snapshot."""
        with self._lock:
            targets = list(self._subscriptions)
        for sub in targets:
            sub.overflowed = True


def note(obj) -> None:
    """Remember a changed Job or WorkUnit on its session, to publish at commit.
    Objects outside a session (plain tests of the state table) are ignored."""
    session = object_session(obj)
    if session is None:
        return
    pending: dict = session.info.setdefault(_PENDING, {})
    key = (type(obj).__name__, obj.job_id, obj.index) if hasattr(obj, "index") else ("Job", obj.id)
    pending.pop(key, None)
    pending[key] = obj  # latest change last; the state published is the committed one


def publish_commits(sessions: sessionmaker[Session], hub: EventHub) -> None:
    """Publish what `note` recorded on sessions of `sessions` when they commit."""
    from .models import utcnow
    from .schemas import JobPublic, UnitPublic

    def events_of(pending: dict) -> list[tuple[str, str, dict, str | None]]:
        now = utcnow()
        # A job deleted in this transaction (canceled on the way) is announced
        # by its `deleted` event alone.
        objects = [o for o in pending.values() if not sa_inspect(o).was_deleted]
        out = [("unit", unit.job_id, {"job_id": unit.job_id,
                                      **UnitPublic.from_unit(unit).model_dump(mode="json")}, None)
               for unit in objects if hasattr(unit, "index")]
        out += [("job", job.id, JobPublic.from_job(job, now).model_dump(mode="json"), job.owner)
                for job in objects if not hasattr(job, "index")]
        return out

    def after_flush(session: Session, _context) -> None:
        # The state to publish is read here, inside the transaction: read after
        # the commit, an expired attribute is loaded again and may already show
        # another thread's later commit (a new job announced as `running`
        # because the scheduler planned it in between).
        pending = session.info.get(_PENDING)
        if pending:
            try:
                session.info[_SNAPSHOT] = (set(pending), events_of(pending))
            except Exception:  # read again after the commit instead
                log.exception("reading events at flush failed")
                session.info.pop(_SNAPSHOT, None)

    def after_commit(session: Session) -> None:
        pending = session.info.pop(_PENDING, None)
        keys, events = session.info.pop(_SNAPSHOT, None) or (set(), [])
        if not pending:
            return
        try:
            late = {k: o for k, o in pending.items() if k not in keys}  # noted after it
            hub.publish_many(events + (events_of(late) if late else []))
        except Exception:  # an event is a courtesy; the commit stands
            log.exception("publishing events failed")

    def forget(session: Session, *_args) -> None:
        session.info.pop(_PENDING, None)
        session.info.pop(_SNAPSHOT, None)

    sa_event.listen(sessions, "after_flush_postexec", after_flush)
    sa_event.listen(sessions, "after_commit", after_commit)
    sa_event.listen(sessions, "after_soft_rollback", forget)
