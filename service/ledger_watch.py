"""Events on a standby replica of a SQLite ledger: read from the ledger itself.

    watch = LedgerWatch(sessions, hub, leading=leadership.leading)
    watch.start()     # a thread polls the ledger while this replica does not lead
    watch.stop()

On SQLite the hub delivers in-process (service.events): the replica that
runs the scheduler publishes what it commits to its own streams, and a second
service on the same file (a standby, service.leader) would hear nothing of the
jobs it renders. PostgreSQL relays events between replicas (LISTEN/NOTIFY,
service.event_relay); SQLite has no such channel, so a standby polls: every
`interval` seconds it reads the version of every job and of every unit of the
jobs in flight or changed since the last poll (both rows carry an optimistic-locking `version` that every
update bumps) and publishes, for what changed since the last poll, the `unit`
and `job` events the leader's streams carried, a `preview` event when a job's
units done moved (the preview files are in the shared data dir), and `deleted`
for a job that is gone. Its first poll, and the first after it stopped
leading, only records what is there and asks every stream to resynchronise
from a snapshot (`EventHub.resync_all`): what happened meanwhile is not
replayed. While this replica leads, it polls nothing: its scheduler's own
commits are its events.

Two small queries per poll, whatever the number of finished jobs' units; a
change made by this replica's own HTTP handlers is published twice (once at its
commit, once here), which a stream shows as the same state again.
"""

from __future__ import annotations

import itertools
from typing import Callable

from sqlalchemy import or_, select
from sqlalchemy.orm import Session, sessionmaker

from . import states
from .events import EventHub
from .models import Job, WorkUnit, utcnow
from .poller import Poller
from .previews import preview_event

__all__ = ["LedgerWatch"]


class LedgerWatch(Poller):
    """Polls the ledger for changes while `leading()` is false (module doc)."""

    what = "ledger watch"

    def __init__(self, sessions: sessionmaker[Session], hub: EventHub,
                 leading: Callable[[], bool], interval: float = 0.5):
        super().__init__(interval)
        self.sessions, self.hub, self.leading = sessions, hub, leading
        # id -> (version, owner, units done, status), as of the last poll
        self._jobs: dict[str, tuple[int, str, int, str]] | None = None
        self._units: dict[tuple[str, int], int] = {}  # (job, index) -> version
        self._previews = itertools.count(1)

    def start(self) -> None:
        """Take the first reading now (the service starts before it serves a
        stream: none misses what happens between its snapshot and this
        reading), then poll from a thread."""
        if self.wanted():
            self.try_poll()
        super().start()

    def wanted(self) -> bool:
        return not self.leading()

    def idle(self) -> None:
        self._jobs = None  # polled afresh (and streams resynced) if it stands by again

    def poll(self) -> None:
        """Publish what changed since the last poll (the first only records)."""
        from .schemas import JobPublic, UnitPublic

        with self.sessions() as session:
            jobs = {job_id: (version, owner, done, status)
                    for job_id, version, owner, done, status in session.execute(
                        select(Job.id, Job.version, Job.owner, Job.units_done, Job.status))}
            # The units of the jobs in flight, and of those that were at the last
            # poll or changed since (a job that just finished, perhaps planned
            # and rendered between two polls: its units' last changes).
            first, before = self._jobs is None, self._jobs or {}
            changed_jobs = {job_id for job_id, row in jobs.items() if not first and (
                job_id not in before or (before[job_id][0] != row[0]
                                         and before[job_id][3] in states.SCHEDULED_JOB))}
            also = sorted({job_id for job_id, _ in self._units} | changed_jobs)
            rows = session.execute(
                select(WorkUnit.job_id, WorkUnit.index, WorkUnit.version, Job.status)
                .join(Job, Job.id == WorkUnit.job_id)
                .where(or_(Job.status.in_(states.SCHEDULED_JOB),
                           WorkUnit.job_id.in_(also)))).all()
            versions = {(job_id, index): version for job_id, index, version, _ in rows}
            watched = self._units
            self._jobs = jobs
            self._units = {(job_id, index): version for job_id, index, version, status in rows
                           if status in states.SCHEDULED_JOB}
            self.polls += 1
            if first:
                self.hub.resync_all()
                return
            changed_units = [k for k, v in versions.items() if watched.get(k) != v]
            if changed_units:
                by_job: dict[str, set[int]] = {}
                for job_id, index in changed_units:
                    by_job.setdefault(job_id, set()).add(index)
                for job_id, indices in by_job.items():
                    for unit in session.scalars(select(WorkUnit).where(
                            WorkUnit.job_id == job_id, WorkUnit.index.in_(sorted(indices)))):
                        self.hub.publish("unit", job_id, {
                            "job_id": job_id,
                            **UnitPublic.from_unit(unit).model_dump(mode="json")})
            now = utcnow()
            for job_id, (version, owner, done, _) in jobs.items():
                old = before.get(job_id)
                if old is not None and old[0] == version:
                    continue
                job = session.get(Job, job_id)
                if job is None:  # deleted since the first query
                    continue
                if done and (old is None or old[2] != done):  # the leader rewrote the preview
                    self.hub.publish("preview", job_id,
                                     preview_event(job_id, f"w{next(self._previews)}", done))
                self.hub.publish("job", job_id,
                                 JobPublic.from_job(job, now).model_dump(mode="json"), owner=owner)
            for job_id in before.keys() - jobs.keys():
                self.hub.publish("deleted", job_id, {"job_id": job_id}, owner=before[job_id][1])
