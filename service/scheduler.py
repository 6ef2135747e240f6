"""The scheduler: one background thread that moves jobs forward.

Each tick:
1. take a census: the scheduled (queued, running, paused) jobs and, in one
   small query, their units in flight (queued or running) by job;
2. for every job that needs it (queued, units in flight, complete, or a
   running preview to flush; a job that only waits is not touched):
   plan a queued job into unit rows (its method's plan: tiles x passes,
   progressive or not, or a small DAG of prepass -> units, renderer/plan.py)
   and mark it running; observe its units in flight: store a finished
   unit's film (atomically) *before* marking the unit done, exactly once;
   re-enqueue lost units; retry failed ones and ones whose render process
   crashed (each spends an attempt) up to `max_attempts`, then fail the job;
   stop a unit rendering longer than its time budget (`service.budget`: the
   measured rate, a generous margin, a floor), which is a failed attempt
   too; refresh its `preview.png` and `noise.png` from the units landed
   so far and publish a `preview` event; when every unit is done, merge the
   stored films in unit order into `result.exr` + `preview.png` +
   `noise.png`, then mark the job done;
3. dispatch: with the census as the tick left it, fill the executor's free slots
   (`capacity`, which every executor bounds) by fair share
   (`service.fairshare`): each slot goes to the owner with the fewest units
   in flight relative to its share, within an owner to its highest priority,
   then to the job with the fewest units in flight, then the oldest. Only
   pending units whose needs are done go (a DAG unit travels with the
   digests of the stored films it needs, `service.artefacts`; the executor
   finds the bytes); paused jobs collect but never enqueue. The
   units are enqueued in the order they were chosen, so different jobs'
   units interleave in the executor's queue too, and no job can hold it:
   a small job submitted behind a huge one starts within a few ticks.
   Before that, fair share over the render processes (`_rebalance`,
   `service.fairshare.rebalance`): while an owner waits for a process, the
   owners holding their share or more get no new units, their units waiting
   in the executor's queue are withdrawn, and a unit of one holding more
   than its share may be preempted; both go back to pending without
   spending an attempt, and their tasks are stopped (`Executor.stop`).
Units whose job was canceled (by the API) leave flight; their tasks are
canceled, and a running one's process is stopped. The ledger is the truth: after a restart the scheduler picks up
where the rows say it was.

The tick stays cheap with many jobs waiting: its queries count units in
flight (a number the executors bound), not pending ones. A running job's
pending units are its planned units minus those done and in flight (its
counters change in the same transactions as its units'), an upper bound
that `_ready_units` makes exact for the few jobs fair share asks about.

Only the replica that leads ticks (`service.leader`): the thread checks the
leadership before each tick and runs the tick fenced, so a replica that lost
its lease mid-tick cannot commit. On becoming the leader it forgets what it
tracked before: the ledger says what is in flight.

Every committed status change and progress step is published to the event
streams (`service.events`). The scheduler only schedules: the running
previews of the jobs in flight are `service.previews`' (fed the films that
land), the final merge and its images `service.results`'.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import logging
import threading
import time
from collections import Counter, deque
from datetime import datetime
from typing import Callable, NamedTuple

from sqlalchemy import select
from sqlalchemy.orm import Session, object_session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError


from renderer import PartialFilm, RenderSpec
from renderer.target import supports_target

from . import blocklist, events, states
from .admission import job_plan
from .artefacts import Artefacts
from .budget import UnitRates
from .events import EventHub
from .executors import Executor, Flight, Observation, Ticket
from .fairshare import Contender, Holding, fair_share, rebalance, starved
from .leader import Leadership, LeadershipLost
from .metrics import FarmMetrics
from .models import Job, User, WorkUnit, utcnow
from .previews import RunningPreviews
from .results import write_result
from .targets import TargetJobs, at_barrier, job_target
from .settings import Settings
from .store import Store

__all__ = ["Scheduler"]


@contextlib.contextmanager
def _unfenced():
    yield

log = logging.getLogger(__name__)

STORE_FAILED = "storing the unit's film failed"  # a unit's and its job's error meanwhile
RESULT_STORE_FAILED = "writing the result failed"  # a complete job's error while the disk is full


class _JobRow(NamedTuple):
    """A scheduled job as the tick's census reads it (no unit rows)."""

    id: str
    owner: str
    status: str
    priority: int | None
    created: datetime
    units_total: int
    units_done: int
    units_open: int | None  # a target job's units that may run (service.targets)

    @property
    def open_pending(self) -> int:
        """Open units not finished (upper bound of those pending: minus those in flight)."""
        return (self.units_total if self.units_open is None else self.units_open) - self.units_done


class _Advanced(NamedTuple):
    """A job as `_advance` left it (committed): what the dispatch needs."""

    status: str
    units_total: int
    units_done: int
    units_open: int | None
    in_flight: int
    started: dict[int, datetime | None]  # its units in flight: when each began rendering

    @property
    def complete(self) -> bool:
        return self.status == "running" and self.units_done == self.units_total


class _Census:
    """The tick's view of the scheduled jobs: read once at its start, then
    kept current with what the tick itself did (`update`), so the dispatch
    needs no second census. A change the API made meanwhile (a pause, a
    cancel, a new job) the dispatch either re-reads (the job's row) or leaves
    to the next tick."""

    def __init__(self, jobs: dict[str, _JobRow], flying: Counter[str],
                 live: set[tuple[str, int]], started: dict[str, dict[int, datetime | None]]):
        self.jobs, self.flying, self.live = jobs, flying, live
        # Per job, its units in flight: when each began rendering (None: queued).
        self.started = started

    def update(self, job_id: str, after: _Advanced | None) -> None:
        """The job as the tick left it; None: no longer scheduled (or gone)."""
        if after is None or after.status not in states.SCHEDULED_JOB:
            self.jobs.pop(job_id, None)
            self.flying.pop(job_id, None)
            self.started.pop(job_id, None)
            return
        self.jobs[job_id] = self.jobs[job_id]._replace(
            status=after.status, units_total=after.units_total, units_done=after.units_done,
            units_open=after.units_open)
        self.flying[job_id] = after.in_flight
        self.started[job_id] = after.started

    def left_flight(self, job_id: str, index: int) -> None:
        """A unit of the job went back to pending (withdrawn or preempted)."""
        if self.started.get(job_id, {}).pop(index, False) is not False:
            self.flying[job_id] -= 1


def _attempts_error(unit: WorkUnit, obs: Observation) -> str:
    """A unit's last attempt failed: its job's error. A crash reads as what
    happened, `unit 5: render process died with SIGSEGV on 3 attempts`."""
    if obs.state == "crashed":
        return f"unit {unit.index}: {obs.error} on {unit.attempts} attempts"
    return f"unit {unit.index} failed after {unit.attempts} attempts: {obs.error}"


class Scheduler:
    """Drives jobs through plan -> enqueue -> collect -> merge (see module doc)."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session], store: Store,
                 executor: Executor, clock: Callable[[], datetime] = utcnow,
                 hub: EventHub | None = None, metrics: FarmMetrics | None = None,
                 leadership: Leadership | None = None):
        self.settings, self.sessions, self.store, self.executor = settings, sessions, store, executor
        # None: this scheduler alone drives the ledger (tests that call tick()).
        self.leadership = leadership
        self.leading = leadership is None
        self.clock = clock
        self.events = hub if hub is not None else EventHub()
        self.metrics = metrics if metrics is not None else FarmMetrics()  # service.metrics
        self._tracked: dict[tuple[str, int], tuple[str, ...]] = {}  # units we put in flight
        self.previews = RunningPreviews(store, self.events, self._done_units)
        self.targets = TargetJobs(store)  # the pass decisions of target jobs
        # Measured render rates, for the units' time budgets (service.budget).
        self.rates = UnitRates(settings.unit_budget_factor, settings.unit_budget_floor)
        self._budget_looked: dict[str, float] = {}  # job -> when a budget last sent a visit
        # Owners starved of render processes -> since when (service.fairshare).
        self._starved_since: dict[str, datetime] = {}
        self._stop = threading.Event()
        # Set when the executor reports a unit finished: the next tick starts
        # before poll_interval, so short units don't leave the pool idle
        # between ticks (paced while the executor has work ahead: `_pause`).
        self._wake = threading.Event()
        executor.on_progress(self._wake.set)
        self._urgent = threading.Event()  # wake(): tick at once, unpaced
        self._thread: threading.Thread | None = None
        # Which unit films later units read, and their digests (read once a tick).
        self.artefacts = Artefacts(store.unit_film)
        # The workers blocklisted per job, read once per tick (service.blocklist).
        self._blocked: dict[str, tuple[str, ...]] = {}
        self.ticks = 0  # a standby's stay 0
        self._visits_missed = True  # look at every job in flight (see _tick)
        # Jobs with a landed unit whose film could not be stored: the executor
        # has no more news of it, and the next tick stores it again.
        self._revisit: set[str] = set()
        self.last_error: str | None = None

    # -- the thread --------------------------------------------------------------
    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="rayfarm-scheduler", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 60.0) -> None:
        self._stop.set()
        self._urgent.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def wake(self) -> None:
        """Tick now rather than at the next poll (a job was submitted or changed
        here): a short job does not wait up to poll_interval to start. Safe from
        any thread; a standby's wake only re-checks that it does not lead."""
        self._urgent.set()
        self._wake.set()

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        while not self._stop.is_set():
            cpu = time.thread_time()
            try:
                if self._lead():
                    with self.leadership.fenced() if self.leadership else _unfenced():
                        self.tick()
                self.last_error = None
            except LeadershipLost as exc:  # another replica leads now; stand by
                log.warning("scheduler stopped mid-tick: %s", exc)
                self._lead()
            except Exception as exc:  # keep scheduling; the next tick retries
                error = f"{type(exc).__name__}: {exc}"
                if error != self.last_error:  # once per distinct error, not every tick
                    log.exception("scheduler tick failed")
                self.last_error = error
            self._pause(time.thread_time() - cpu)

    # A tick costs the scheduler milliseconds of CPU, and on a machine whose
    # cores the render processes use, that CPU is taken from them. While every
    # render process has a unit waiting (`Executor.work_ahead`), the next tick
    # waits PACE times the CPU the last one took (up to PACE_SPAN poll
    # intervals): the scheduler then uses at most about 1/PACE of a core, and
    # each tick collects what landed meanwhile, several units at once. The
    # wait ends early when a landing leaves a process without a unit waiting,
    # so no process runs dry for it. Measured on the 2-core machine (a
    # progressive 302-spp job, 96 units): a tick per unit landed and 13 ms of
    # CPU each before; PACE 8 took the service's CPU from about 1.6 s to 1.1 s
    # a job, PACE 16 (ticks 291 -> 207 for 3 jobs) a further 20 %. There the
    # cap was one poll interval, and on an AMD EPYC Zen 5 (507-spp progressive
    # jobs, 64 units of about 0.27 s, 11 ms of CPU a tick) it bound: a tick per
    # unit landed again, 60 a job. PACE 32 with a cap of 4 intervals: 22 to 27
    # ticks and 0.64 s of service CPU a job instead of 0.79 s (four jobs each,
    # alternated twice); PACE 48 or 64 tick no less, the work-ahead check ends
    # the wait first.
    PACE = 32.0
    PACE_SPAN = 4.0

    def _pause(self, tick_cpu: float) -> None:
        """Between two ticks: until woken (a unit landed, a job changed) or the
        poll interval passed; then, if the wake came from a landed unit while
        every render process has work waiting, until the pace allows (above)."""
        resume = time.monotonic() + min(self.PACE * tick_cpu,
                                        self.PACE_SPAN * self.settings.poll_interval)
        self._wake.wait(self.settings.poll_interval)
        self._wake.clear()
        while not self._urgent.is_set():
            remaining = resume - time.monotonic()
            if remaining <= 0 or not self.executor.work_ahead():
                break
            self._wake.wait(remaining)
            self._wake.clear()
        self._urgent.clear()

    def _lead(self) -> bool:
        """Does this replica lead now? On a change, forget what it tracked: the
        ledger has the units in flight, and the executor reports those it does
        not run (another leader's) as lost, so they are enqueued again."""
        leading = self.leadership is None or self.leadership.leading()
        if leading != self.leading:
            if not leading:  # the new leader enqueues them again; free our slots
                for (job_id, _index), task_ids in self._tracked.items():
                    self.executor.cancel(job_id, task_ids)
            self._tracked = {}
            self.previews = RunningPreviews(self.store, self.events, self._done_units)
            self.targets = TargetJobs(self.store)
            self.leading = leading
        return leading

    # -- one tick ------------------------------------------------------------------
    def tick(self) -> None:
        """Collect and advance the jobs that need it, then fill free slots by fair share."""
        started = time.perf_counter()
        try:
            self._tick()
        finally:
            self.metrics.tick(time.perf_counter() - started)

    def _tick(self) -> None:
        census = self._census()
        # What the executor has news of (None: it cannot tell, look at every job).
        # A tick that did not finish its visits looks at every job next time:
        # the news it took would be lost.
        news = None if self._visits_missed else self.executor.news()
        self._visits_missed = True
        untracked = {job_id for job_id, index in census.live if (job_id, index) not in self._tracked}
        revisit, self._revisit = self._revisit, set()
        self._cancel_departed(census.live)
        self._drop_departed_artefacts(census.jobs)
        self.previews.keep_only(census.jobs)
        self.targets.keep_only(census.jobs)
        self.rates.keep_only(census.jobs)
        overdue = self._overdue(census)
        self.artefacts.new_tick()
        self._blocked = {}
        try:
            for job in list(census.jobs.values()):
                if self._stop.is_set():
                    return
                news_of = (news is None or job.id in news or job.id in untracked
                           or job.id in revisit or job.id in overdue)
                if not self._needs_visit(job, census.flying[job.id] if news_of else 0):
                    continue
                try:
                    after = self._advance(job.id, plan=job.status == "queued")
                    census.update(job.id, after)
                    if after is not None and after.complete:
                        self._finish(job.id)
                        census.update(job.id, None)
                except StaleDataError:
                    log.info("job %s changed meanwhile (canceled?); next tick", job.id)
                    self._forget_if_deleted(job.id)
                    census.update(job.id, None)
            self._visits_missed = False
            try:
                self._dispatch(census)
            except StaleDataError:
                # A job changed (canceled, deleted) while its units were enqueued: the
                # whole batch is rolled back; its tasks are no longer in flight in the
                # ledger, so the next tick cancels them and chooses again.
                log.info("a job changed while units were enqueued; next tick chooses again")
        finally:
            self.artefacts.new_tick()
            self.ticks += 1

    def _census(self) -> _Census:
        """The scheduled jobs (higher priority first, then oldest) and their
        units in flight: two small queries, whatever the pending units (the
        units in flight are few: every executor bounds them)."""
        with self.sessions() as session:
            jobs = {row.id: _JobRow(*row) for row in session.execute(
                select(Job.id, Job.owner, Job.status, Job.priority, Job.created,
                       Job.units_total, Job.units_done, Job.units_open)
                .where(Job.status.in_(states.SCHEDULED_JOB))
                .order_by(Job.priority.desc(), Job.created, Job.id))}
            flights = session.execute(
                select(WorkUnit.job_id, WorkUnit.index, WorkUnit.state, WorkUnit.started_at)
                .join(Job, Job.id == WorkUnit.job_id)
                .where(WorkUnit.state.in_(states.IN_FLIGHT),
                       Job.status.in_(states.SCHEDULED_JOB))).all()
        live = {(job_id, index) for job_id, index, _, _ in flights}
        started: dict[str, dict[int, datetime | None]] = {}
        for job_id, index, state, started_at in flights:
            started.setdefault(job_id, {})[index] = started_at if state == "running" else None
        return _Census(jobs, Counter(job_id for job_id, _ in live), live, started)

    # How often a job whose unit has rendered longer than the budget floor is
    # looked at (its budget checked) when the executor has no news of it.
    BUDGET_LOOK_SECONDS = 1.0

    def _overdue(self, census: _Census) -> set[str]:
        """Jobs with a unit rendering for longer than the budget floor, each at
        most once per BUDGET_LOOK_SECONDS: `_collect` checks its budget."""
        now, clock = self.clock(), time.monotonic()
        for job_id in [j for j in self._budget_looked if j not in census.jobs]:
            del self._budget_looked[job_id]
        out = set()
        for job_id, units in census.started.items():
            if any(t is not None and (now - t).total_seconds() >= self.rates.floor
                   for t in units.values()) \
                    and clock - self._budget_looked.get(job_id, -1e9) >= self.BUDGET_LOOK_SECONDS:
                self._budget_looked[job_id] = clock
                out.add(job_id)
        return out

    def _needs_visit(self, job: _JobRow, in_flight: int) -> bool:
        """Does the job need its own transaction this tick? A running job that
        only waits for a slot does not (the dispatch reads its units), nor one
        whose units in flight the executor has no news of (`in_flight` 0:
        `Executor.news`; units in flight this scheduler did not put there, as
        after a restart, are always looked at)."""
        if job.status == "queued" or in_flight:
            return True
        if job.status == "running" and job.units_done == job.units_total:
            return True  # complete: merge (e.g. the service stopped before it could)
        if at_barrier(job.status, job.units_open, job.units_done, job.units_total):
            return True  # a target job's next pass to decide (e.g. after a restart)
        return self.previews.dirty(job.id)  # a throttled preview to write

    def _cancel_departed(self, live: set[tuple[str, int]]) -> None:
        """Cancel the tasks of units that left flight behind our back (job
        canceled): tracked here, not in flight in the census (`live`)."""
        for key in [k for k in self._tracked if k not in live]:
            self.executor.cancel(key[0], self._tracked.pop(key))

    def _drop_departed_artefacts(self, jobs: dict[str, _JobRow]) -> None:
        """Let the executor drop the input films kept for jobs canceled or
        deleted behind our back (see service.artefacts)."""
        digests = self.artefacts.departed(jobs)
        if digests:
            try:
                self.executor.drop_films(digests)
            except Exception as exc:  # they expire anyway
                log.warning("dropping %d films of departed jobs failed: %s", len(digests), exc)

    def _advance(self, job_id: str, plan: bool = True) -> _Advanced | None:
        """Plan a queued job (`plan`: the census saw it queued; a job queued
        since waits for the next tick), collect a job's units in flight and
        refresh its preview; returns the job as committed (None: it is gone
        or no longer running or paused)."""
        released: list[tuple[str, ...]] = []
        landed: list[tuple[int, PartialFilm]] = []
        if plan:  # a transaction of its own: the plan stands even if collecting fails
            with self.sessions.begin() as session:
                job = session.get(Job, job_id)
                if job is None or job.status not in states.SCHEDULED_JOB:
                    return None
                if job.status == "queued":
                    self._plan(session, job, self.clock())
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None or job.status not in ("running", "paused"):
                return None
            now = self.clock()
            flying = list(session.scalars(
                select(WorkUnit).where(WorkUnit.job_id == job.id,
                                       WorkUnit.state.in_(states.IN_FLIGHT))
                .order_by(WorkUnit.index)))
            observations = self.executor.observe(
                [Flight(u.job_id, u.index, u.state, tuple(u.task_ids), u.enqueued_at, u.started_at)
                 for u in flying], now)
            for unit, obs in zip(flying, observations):
                self._tracked.setdefault((job.id, unit.index), tuple(unit.task_ids))
                if self._collect(session, job, unit, obs, now, released, landed):
                    break  # the job failed
            if landed:
                job.note_samples(sum(int(f.stats.get("samples", 0)) for _, f in landed), now)
            in_flight = sum(u.state in states.IN_FLIGHT for u in flying)
            started = {u.index: u.started_at if u.state == "running" else None
                       for u in flying if u.state in states.IN_FLIGHT}
            if landed and job.progressive and job.target is None \
                    and supports_target(job.spec.get("method", "")):
                self.targets.note_passes(session, job, now)  # the convergence, pass by pass
            if not in_flight and at_barrier(job.status, job.units_open, job.units_done,
                                            job.units_total):
                # In the transaction that collected the pass's last unit: a
                # landed pass and its decision commit together.
                self.targets.decide(session, job, now)
            after = _Advanced(job.status, job.units_total, job.units_done, job.units_open,
                              in_flight, started)
            width, height, method = job.width, job.height, job.spec.get("method", "")
            written = None
            if landed and not self.previews.ever_written(job_id):
                # The API shows preview_url from the first landed unit on: its
                # image is written before the commit that lands it, also when
                # that commit completes the job (whose final images come later,
                # from the merge). Later previews are written after the commit.
                written = self._refresh_preview(job_id, width, height, landed)
        for _, film in landed:  # committed: each unit counts once
            self.metrics.unit_done(method, float(film.stats.get("seconds", 0.0)),
                                   int(film.stats.get("samples", 0)), int(film.stats.get("rays", 0)))
        for task_ids in released:  # only once the ledger says done (or failed)
            self.executor.release(task_ids)
        if written is None and not after.complete:  # a complete job's comes from the merge
            written = self._refresh_preview(job_id, width, height, landed)
        if written is not None:
            # Written around the tick's commit: a job deleted meanwhile would
            # get its directory back (with the PNGs in it) for good.
            self._forget_if_deleted(job_id)
            self.previews.publish(job_id, written)
        return after

    def _refresh_preview(self, job_id: str, width: int, height: int,
                         landed: list[tuple[int, PartialFilm]]) -> int | None:
        """`RunningPreviews.refresh`, never raising: a preview is a courtesy,
        it never stops a job."""
        try:
            return self.previews.refresh(job_id, width, height, landed)
        except Exception:
            log.exception("preview of job %s failed", job_id)
            self.previews.drop(job_id)
            return None

    def _dispatch(self, census: _Census) -> None:
        """Fill the executor's free slots by fair share (module doc, step 3).
        Asked after collecting (the census as the tick left it), so finished
        units have freed their slots. First, fair share over the render
        processes (`_rebalance`): owners holding more than their share while
        another waits get nothing new, and may give up queued or running units."""
        jobs, flying = census.jobs, census.flying
        contenders = [Contender(j.id, j.owner, j.priority or 0, j.created, flying[j.id])
                      for j in jobs.values() if j.status == "running"
                      and j.open_pending - flying[j.id] > 0]
        held_back, cap = self._rebalance(census, contenders)
        contenders = [Contender(c.job_id, c.owner, c.priority, c.created, flying[c.job_id])
                      for c in contenders if c.owner not in held_back]
        if not contenders:
            return
        slots = max(self.executor.capacity(sum(flying.values())), 0)
        if cap is not None:
            slots = min(slots, cap)
        if not slots:
            return
        owner_in_flight: Counter[str] = Counter()
        for job in jobs.values():
            owner_in_flight[job.owner] += flying[job.id]
        enqueue_error: Exception | None = None
        with self.sessions.begin() as session:
            now = self.clock()
            shares = {name: share for name, share in session.execute(
                select(User.name, User.share).where(User.name.in_({c.owner for c in contenders})))}
            ready: dict[str, deque[WorkUnit]] = {}
            # Held here: the session's identity map keeps an unchanged row only
            # weakly, and a second Session.get would load it again per unit.
            rows: dict[str, Job] = {}

            def count_ready(job_id: str) -> int:
                job = session.get(Job, job_id)  # paused or deleted since the census: none
                running = job is not None and job.status == "running"
                units = self._ready_units(session, job, slots) if running else []
                ready[job_id] = deque(units)
                rows[job_id] = job
                return len(units)

            for job_id in fair_share(contenders, owner_in_flight, shares, slots, count_ready):
                unit = ready[job_id].popleft()
                try:
                    self._enqueue(rows[job_id], unit, now)
                except Exception as exc:  # broker down: keep what was sent, retry later
                    enqueue_error = exc
                    break
                unit.attempts = max(unit.attempts or 0, 1)  # a preempted unit keeps its count
        if enqueue_error is not None:
            raise enqueue_error

    # How long an owner must have been starved of render processes before
    # others are held back or preempted for it: the ledger sees a unit begin
    # rendering a tick or so late, and a short unit's process frees itself.
    STARVED_GRACE = 1.0

    def _rebalance(self, census: _Census,
                   contenders: list[Contender]) -> tuple[frozenset[str], int | None]:
        """Fair share over the render processes (service.fairshare.rebalance):
        withdraw and preempt what it says (back to pending, no attempt spent;
        their tasks stopped); returns the owners held back this tick and, while
        some are, how many units the dispatch may enqueue (the claimants'
        processes, less their units already queued), else None."""
        processes = self.executor.render_processes() if self.settings.preemption else None
        if not processes:
            self._starved_since.clear()
            return frozenset(), None
        now = self.clock()
        holdings = [Holding(census.jobs[job_id].owner, (job_id, index),
                            None if began is None else max((now - began).total_seconds(), 0.0))
                    for job_id, units in census.started.items() if job_id in census.jobs
                    for index, began in units.items()]
        queued = Counter(h.owner for h in holdings if h.running_for is None)
        wanting = Counter(queued)  # an upper bound: pending units may wait for their needs
        for c in contenders:
            wanting[c.owner] += census.jobs[c.job_id].open_pending - census.flying[c.job_id]
        owners = {h.owner for h in holdings} | {o for o, n in wanting.items() if n > 0}
        hungry: set[str] = set()
        shares: dict[str, float] = {}
        if len(owners) > 1:  # one owner alone starves nobody
            with self.sessions() as session:
                shares = dict(session.execute(select(User.name, User.share)
                                              .where(User.name.in_(owners))).all())
            hungry = starved(holdings, wanting, shares, processes)
        for owner in [o for o in self._starved_since if o not in hungry]:
            del self._starved_since[owner]
        claimants = {o for o in hungry if (now - self._starved_since.setdefault(o, now))
                     .total_seconds() >= self.STARVED_GRACE}
        if not claimants:
            return frozenset(), None
        stopped: list[str] = []
        left: list[tuple[str, int]] = []
        with self.sessions.begin() as session:
            # What the claimants can start now, exactly (a DAG stage may wait).
            for owner in claimants:
                wanting[owner] = queued[owner]
            for c in contenders:
                if c.owner in claimants:
                    job = session.get(Job, c.job_id)
                    if job is not None and job.status == "running":
                        wanting[c.owner] += len(self._ready_units(session, job, processes))
            plan = rebalance(holdings, wanting, shares, processes, claimants,
                             self.settings.preempt_after_seconds)
            for key, was, reason in (
                    [(k, "queued", "withdrawn from the executor's queue") for k in plan.withdraw]
                    + [(k, "running", "preempted") for k in plan.preempt]):
                unit = session.get(WorkUnit, key)
                if unit is None or unit.state != was:
                    continue  # it moved on meanwhile (landed, failed, canceled)
                states.change_unit(unit, "pending", self.clock())
                unit.requeue_reason = f"{reason}: another owner waited for a render process"
                stopped.extend(unit.task_ids)
                left.append(key)
        for key in left:  # committed: their tasks go, their slots free
            census.left_flight(*key)
            self._tracked.pop(key, None)
            self.metrics.requeued("preempted" if key in plan.preempt else "withdrawn")
        if left:
            log.info("fair share over %d render processes: %d units withdrawn, %d preempted "
                     "for %s", processes, len(left) - sum(k in plan.preempt for k in left),
                     sum(k in plan.preempt for k in left), ", ".join(sorted(claimants)))
            self.executor.stop(stopped)
        if not plan.held_back:
            return frozenset(), None
        # While others are held back, a claimant gets the units its processes
        # need (at least one waiting, first in line for the next free process),
        # and no more: a deep queue of its own would hold the farm in its turn.
        return plan.held_back, sum(max(max(n, 1) - queued[o], 0)
                                   for o, n in plan.claimed.items())

    def _ready_units(self, session: Session, job: Job, limit: int) -> list[WorkUnit]:
        """Up to `limit` pending units of the job whose needs are all done, in
        unit order. Tile jobs need nothing; a DAG's later stages wait here, and
        a target job's passes not yet decided (`Job.units_open`).
        Read in batches: a huge job's pending units are never all loaded, and a
        tile job's dispatch of one slot loads a few rows, not 64 (each a JSON
        document to decode: that was most of a busy scheduler's CPU)."""
        ready: list[WorkUnit] = []
        done: set[int] | None = None
        after, batch_size = -1, max(2 * limit, 16)
        bound = job.units_total if job.units_open is None else job.units_open
        while len(ready) < limit:
            batch = list(session.scalars(
                select(WorkUnit).where(WorkUnit.job_id == job.id, WorkUnit.state == "pending",
                                       WorkUnit.index > after, WorkUnit.index < bound)
                .order_by(WorkUnit.index).limit(batch_size)))
            if not batch:
                break
            after = batch[-1].index
            for unit in batch:
                needs = unit.unit.get("needs") or ()
                if needs:
                    if done is None:
                        done = set(session.scalars(select(WorkUnit.index).where(
                            WorkUnit.job_id == job.id, WorkUnit.state == "done")))
                    if not done.issuperset(needs):
                        continue
                ready.append(unit)
                if len(ready) >= limit:
                    break
            if len(batch) < batch_size:  # that was the last of them
                break
        return ready

    def _plan(self, session: Session, job: Job, now: datetime) -> None:
        spec, target = RenderSpec.from_dict(job.spec), job_target(job)
        units = job_plan(spec, bool(job.progressive), target)
        self.previews.drop(job.id)  # planned anew (e.g. requeued): a fresh preview
        self.artefacts.forget(job.id)
        self.targets.forget(job.id)
        if target is not None:  # its first pass (service.targets)
            job.units_open = sum(u.pass_index == 0 for u in units)
        for unit in units:
            session.add(WorkUnit(job_id=job.id, index=unit.index, state="pending",
                                 unit=unit.to_dict(), attempts=0, task_ids=[]))
        job.units_total = len(units)
        states.change_job(job, "running", now)
        session.flush()

    def _enqueue(self, job: Job, unit: WorkUnit, now: datetime) -> None:
        needs = unit.unit.get("needs") or ()
        inputs = self.artefacts.digests(object_session(unit), job, needs) if needs else {}
        if job.id not in self._blocked:  # a pool that never blocklists needs no query
            self._blocked[job.id] = (blocklist.blocked_workers(object_session(job), job.id)
                                     if self.executor.blocklists_workers else ())
        task_id = self.executor.submit(Ticket(job.id, unit.index, job.scene_hash, job.spec,
                                              unit.unit, priority=job.priority or 0,
                                              inputs=inputs,
                                              is_input=self.artefacts.is_input(job, unit.index),
                                              blocked=self._blocked[job.id]))
        unit.task_ids = [*unit.task_ids, task_id]
        states.change_unit(unit, "queued", now)
        self._tracked[(job.id, unit.index)] = tuple(unit.task_ids)

    def _collect(self, session: Session, job: Job, unit: WorkUnit, obs: Observation,
                 now: datetime, released: list, landed: list) -> bool:
        """Apply one observation to a unit; returns True if the job failed."""
        if obs.state == "done":
            try:
                film = PartialFilm.from_bytes(obs.film, copy=False)  # read only: views
            except Exception as exc:  # a corrupt result is a failed attempt
                obs = Observation("failed", error=f"unreadable partial film: {exc}")
            else:
                # Stored before the unit is marked done; a crash in between only
                # means the same bytes are written again.
                try:
                    self.store.put_unit_film(job.id, unit.index, obs.film)
                except OSError as exc:  # e.g. a full disk: keep the result, try next tick
                    self._store_failed(job, unit, exc)
                    return False
                if unit.error and unit.error.startswith(STORE_FAILED):
                    unit.error = None
                if job.error and job.error.startswith(f"unit {unit.index}: {STORE_FAILED}"):
                    job.error = None  # space is back (another unit still failing says so)
                    events.note(job)
                states.change_unit(unit, "done", now)
                unit.film_digest = obs.digest or hashlib.sha256(obs.film).hexdigest()
                if self.artefacts.is_input(job, unit.index):
                    self.artefacts.keep(job.id, unit.film_digest)
                unit.worker = obs.worker or unit.worker
                self._keep_log(job, unit, obs, now)
                unit.seconds = float(film.stats.get("seconds", 0.0))
                self.rates.note(job.id, job.spec.get("method", ""), int(job.spec.get("depth", 0)),
                                unit.unit, unit.seconds)
                job.units_done += 1
                job.samples += int(film.stats.get("samples", 0))
                job.rays += int(film.stats.get("rays", 0))
                job.unit_seconds = (job.unit_seconds or 0.0) + unit.seconds
                if len(unit.task_ids) > 1:  # lost or failed before this task landed
                    job.units_retried = (job.units_retried or 0) + 1
                events.note(job)  # its progress moved
                released.append(tuple(unit.task_ids))
                landed.append((unit.index, film))
                self._tracked.pop((job.id, unit.index), None)
                return False
        if obs.state == "running" and unit.state == "running":
            over = self._over_budget(session, job, unit, now)
            if over is not None:  # stopped; a failed attempt (below)
                self.executor.stop(unit.task_ids)
                obs = Observation("failed", error=over, worker=obs.worker or unit.worker)
        if obs.state == "running":
            if unit.state == "queued":
                states.change_unit(unit, "running", now)
            unit.worker = obs.worker or unit.worker
        elif obs.state == "lost":
            return self._requeue_lost(session, job, unit, obs, now)
        elif obs.state in ("failed", "crashed"):  # an attempt spent (a crash too)
            newly_blocked = self._note_failure(session, job, unit, obs, now)
            unit.error = obs.error
            self._keep_log(job, unit, obs, now)
            if unit.attempts >= self.settings.max_attempts:
                states.change_unit(unit, "failed", now)
                self._fail_job(session, job, now, _attempts_error(unit, obs))
                released.append(tuple(unit.task_ids))
                self._tracked.pop((job.id, unit.index), None)
                return True
            if newly_blocked and self._all_blocked(session, job, unit, now):
                return True
            log.warning("unit %s/%d attempt %d %s: %s", job.id, unit.index, unit.attempts,
                        obs.state, obs.error)
            unit.attempts += 1
            self._enqueue(job, unit, now)
            self.metrics.requeued("crash" if obs.state == "crashed" else "failed")
        return False

    def _over_budget(self, session: Session, job: Job, unit: WorkUnit,
                     now: datetime) -> str | None:
        """The error of a unit rendering for longer than its time budget
        (service.budget), or None. A job's rates are read back from its done
        units once after a restart (the scheduler keeps them in memory)."""
        if unit.started_at is None:
            return None
        elapsed = (now - unit.started_at).total_seconds()
        if elapsed < self.rates.floor:
            return None
        method, depth = job.spec.get("method", ""), int(job.spec.get("depth", 0))
        if job.units_done and not self.rates.knows(job.id):
            for done, seconds in session.execute(
                    select(WorkUnit.unit, WorkUnit.seconds).where(
                        WorkUnit.job_id == job.id, WorkUnit.state == "done",
                        WorkUnit.seconds.is_not(None)).limit(64)):
                self.rates.note(job.id, method, depth, done, seconds)
        budget = self.rates.budget(job.id, method, depth, unit.unit)
        if budget is None or elapsed <= budget.seconds:
            return None
        log.warning("unit %s/%d: %s", job.id, unit.index, budget.exceeded(elapsed))
        return budget.exceeded(elapsed)

    def _keep_log(self, job: Job, unit: WorkUnit, obs: Observation, now: datetime) -> None:
        """Keep what the unit's latest task logged (GET /jobs/{id}/units/{i}/log).
        A log is a courtesy: a full disk loses it, never the unit."""
        entry = {"task": len(unit.task_ids), "attempt": unit.attempts, "outcome": obs.state,
                 "worker": obs.worker, "error": obs.error if obs.state == "failed" else None,
                 "at": now.isoformat(), **(obs.log or {"lines": [], "traceback": None})}
        try:
            self.store.put_unit_log(job.id, unit.index, len(unit.task_ids), entry)
        except OSError as exc:
            log.warning("the log of unit %s/%d was not kept: %s", job.id, unit.index, exc)

    # Observation.cause -> the metrics' requeue reason (service.metrics)
    _REQUEUE_METRIC = {"worker": "lost", "lease": "lease", "message": "message",
                       "declined": "declined"}

    def _requeue_lost(self, session: Session, job: Job, unit: WorkUnit, obs: Observation,
                      now: datetime) -> bool:
        """Enqueue a lost unit again (no attempt spent), saying why on the unit;
        returns True if the job failed instead (declined by a blocklisted
        worker when no live worker may run it)."""
        reason = obs.error or "lost (no task of it will report)"
        log.warning("unit %s/%d lost (task %s): %s; enqueuing it again", job.id, unit.index,
                    unit.task_ids[-1] if unit.task_ids else None, reason)
        if obs.cause == "declined" and self._all_blocked(session, job, unit, now):
            return True
        unit.requeue_reason = reason
        self._enqueue(job, unit, now)
        self.metrics.requeued(self._REQUEUE_METRIC.get(obs.cause or "", "lost"))
        return False

    def _note_failure(self, session: Session, job: Job, unit: WorkUnit, obs: Observation,
                      now: datetime) -> bool:
        """Count a failed attempt against its worker (service.blocklist); returns
        whether that blocklisted the worker for the job."""
        # Only where workers are interchangeable: the embedded pool names its one
        # worker (for the unit's log) but never blocklists it; max_attempts decides.
        worker = obs.worker if self.executor.blocklists_workers else None
        limit = self.settings.worker_failures_per_job
        if not worker or not limit:
            return False
        if not blocklist.note_failure(session, job.id, worker, obs.error, now, limit):
            return False
        log.warning("worker %s blocklisted for job %s after %d failed units", worker, job.id,
                    limit)
        self._blocked.pop(job.id, None)  # the next tickets carry it
        events.note(job)
        return True

    def _all_blocked(self, session: Session, job: Job, unit: WorkUnit, now: datetime) -> bool:
        """Fail the job if every live worker is blocklisted for it (nothing could run it)."""
        session.flush()
        error = blocklist.all_blocked(blocklist.blocked_workers(session, job.id),
                                      self.executor.workers())
        if error is None:
            return False
        states.change_unit(unit, "failed", now)
        # Its tasks stay tracked: the next tick cancels (and forgets) them.
        self._fail_job(session, job, now, f"unit {unit.index}: {error}")
        return True

    def _store_failed(self, job: Job, unit: WorkUnit, exc: OSError) -> None:
        """A finished unit whose film could not be stored (ENOSPC, EIO, ...): it is
        not done, and its result is not released, so the executor still holds it
        and the next tick stores it again. The unit's and the job's error say why
        while it waits; the first successful store clears them."""
        self._revisit.add(job.id)
        error = f"{STORE_FAILED}: {exc.strerror or exc}"
        if unit.error != error:
            log.error("unit %s/%d: %s (the result is kept; retried every tick)",
                      job.id, unit.index, error)
            unit.error = error
        job_error = f"unit {unit.index}: {error}"
        if job.error != job_error and not (job.error and STORE_FAILED in job.error):
            job.error = job_error
            events.note(job)

    def _fail_job(self, session: Session, job: Job, now: datetime, error: str) -> None:
        states.change_job(job, "failed", now, error=error)
        for other in session.scalars(select(WorkUnit).where(
                WorkUnit.job_id == job.id, WorkUnit.state.not_in(states.FINAL_UNIT))):
            states.change_unit(other, "canceled", now)  # their tasks are canceled next tick
        self._drop_artefacts(session, job)

    def _drop_artefacts(self, session: Session, job: Job) -> None:
        """The job is over: the executor may let go of the films kept for its
        later units (a retry plans and renders the job anew)."""
        try:
            self.executor.drop_films(self.artefacts.stored_digests(session, job))
        except Exception as exc:  # they expire anyway; never keep a job from finishing
            log.warning("job %s: dropping its artefacts failed: %s", job.id, exc)
        self.artefacts.forget(job.id)

    def _done_units(self, job_id: str) -> list[int]:
        """The indices of a job's done units (a preview rebuilt after a restart)."""
        with self.sessions() as session:
            return list(session.scalars(select(WorkUnit.index).where(
                WorkUnit.job_id == job_id, WorkUnit.state == "done")))

    def _forget_if_deleted(self, job_id: str) -> None:
        """A job deleted while a tick worked on it: drop what the tick may have
        written for it meanwhile (a unit film, a preview)."""
        with self.sessions() as session:
            if session.get(Job, job_id) is not None:
                return
        self.previews.drop(job_id)
        self.store.delete_job(job_id)

    # -- finishing -------------------------------------------------------------------
    def _finish(self, job_id: str) -> None:
        """Merge the stored unit films in unit order, write the images, mark done."""
        with self.sessions() as session:
            job = session.get(Job, job_id)
            if job is None or job.status != "running" or job.units_done != job.units_total:
                return
            spec, n_units = RenderSpec.from_dict(job.spec), job.units_total
            scene, scene_hash, denoise = job.scene, job.scene_hash, bool(job.denoise)
            target = job_target(job)
            # A target job's skipped units have no film (service.targets).
            indices = (list(session.scalars(select(WorkUnit.index).where(
                WorkUnit.job_id == job_id, WorkUnit.state == "done").order_by(WorkUnit.index)))
                if job.units_skipped else range(n_units))
        error = waiting = None
        rel_error = float("nan")
        # The running frames are not what the result is made of: freed before
        # the merge makes the frame's channels.
        self.previews.drop(job_id)
        self.targets.forget(job_id)
        try:
            try:
                rel_error = write_result(self.store, job_id, spec, indices, scene=scene,
                                         scene_hash=scene_hash, denoise=denoise, target=target)
            except OSError as exc:
                if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                    raise
                # A full disk: the unit films are all stored; merge again next tick.
                waiting = f"{RESULT_STORE_FAILED}: {exc.strerror or exc}"
            else:
                self.previews.publish(job_id, n_units)
        except Exception as exc:
            log.exception("merging job %s failed", job_id)
            error = f"merge failed: {type(exc).__name__}: {exc}"
        if waiting is None:
            self.previews.drop(job_id)
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None:  # deleted while it was merged
                self.store.delete_job(job_id)
                return
            if job.status != "running":
                return
            if waiting is not None:
                if job.error != waiting:
                    log.error("job %s: %s (retried every tick)", job_id, waiting)
                    job.error = waiting
                    events.note(job)
                return
            if job.error and job.error.startswith(RESULT_STORE_FAILED):
                job.error = None
            self.targets.forget(job_id)
            if error is None:
                self.targets.finished(job, rel_error)
                states.change_job(job, "done", self.clock())
                self._drop_artefacts(session, job)
            else:
                self._fail_job(session, job, self.clock(), error)
