"""The scheduler: one background thread that moves jobs forward.

Each tick, for every queued, running or paused job (higher priority first,
then oldest):
1. plan a queued job into unit rows (its method's plan: tiles x passes,
   progressive or not, or a small DAG of prepass -> units, renderer/plan.py)
   and mark it running;
2. observe its units in flight: store a finished unit's film (atomically)
   *before* marking the unit done, exactly once; re-enqueue lost units;
   retry failed ones up to `max_attempts`, then fail the job;
3. enqueue pending units whose needs are done (a DAG unit travels with the
   stored films of the units it needs) while the executor has capacity,
   unless the job is paused or a job before it in the order still has
   pending units ready to go (so priority holds on both executors: the
   Celery executor also passes it to the broker as the message priority);
4. refresh the job's `preview.png` and `noise.png` from the units landed so
   far, and publish a `preview` event;
5. when every unit is done, merge the stored films in unit order into
   `result.exr` + `preview.png` + `noise.png`, then mark the job done.
Units whose job was canceled (by the API) leave flight; their tasks are
canceled. The ledger is the truth: after a restart the scheduler picks up
where the rows say it was.

Every committed status change and progress step is published to the event
streams (`service.events`). The running preview is cheap by design: each
landed unit's film is added (float32 sums and weight) into an in-memory frame
per job, and the PNGs are written at most every `PREVIEW_INTERVAL` seconds per
job (the first unit's at once). A frame missing after a restart (or evicted: at most `PREVIEW_JOBS`
are kept) is rebuilt once from the stored films of the done units. The
preview's order of addition does not matter; the final EXR is merged from
the stored films in unit order, as without previews.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from datetime import datetime
from typing import Callable

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError

import numpy as np

from renderer import METHODS, Film, PartialFilm, RenderSpec, merge

from . import events, states
from .events import EventHub
from .executors import Executor, Flight, Observation, Ticket
from .models import Job, WorkUnit, utcnow
from .settings import Settings
from .store import Store

__all__ = ["Scheduler", "EXR_METADATA_KEYS", "PREVIEW_INTERVAL", "PREVIEW_JOBS"]

log = logging.getLogger(__name__)

EXR_METADATA_KEYS = ("job_id", "scene", "scene_hash", "method", "spp", "depth", "seed",
                     "sampler", "tile_size", "width", "height")
PREVIEW_INTERVAL = 1.0  # seconds between two writes of a job's running preview
PREVIEW_JOBS = 4  # running previews kept in memory (float32: 28 bytes per pixel)


class _Preview:
    """A job's running preview: the sums and weight of the units added so far."""

    def __init__(self, width: int, height: int):
        self.sum = np.zeros((height, width, 3), np.float32)
        self.sum_sq = np.zeros((height, width, 3), np.float32)
        self.weight = np.zeros((height, width), np.float32)
        self.splat: np.ndarray | None = None  # splat batches (film.py), when the method splats
        self.splat_sq: np.ndarray | None = None
        self.splat_paths, self.splat_batches = 0.0, 0
        self.added: set[int] = set()
        self.written = -1e9  # time.monotonic() of the last PNG
        self.dirty = False

    def add(self, index: int, part: PartialFilm) -> None:
        if index in self.added:
            return
        ys = slice(part.y0, part.y0 + part.height)
        xs = slice(part.x0, part.x0 + part.width)
        self.sum[ys, xs] += part.sum
        self.sum_sq[ys, xs] += part.sum_sq
        self.weight[ys, xs] += part.weight
        if part.splat is not None:
            if self.splat is None:
                self.splat, self.splat_sq = np.zeros_like(self.sum), np.zeros_like(self.sum)
            self.splat += part.splat
            self.splat_sq += part.splat_sq
            self.splat_paths += part.splat_paths
            self.splat_batches += part.splat_batches
        self.added.add(index)
        self.dirty = True

    def write(self, preview_path, noise_path) -> None:
        film = Film(0, 0, self.sum, self.sum_sq, self.weight, splat=self.splat,
                    splat_sq=self.splat_sq, splat_paths=self.splat_paths,
                    splat_batches=self.splat_batches)
        film.write_png(preview_path)
        film.write_noise_png(noise_path)
        self.written, self.dirty = time.monotonic(), False


class Scheduler:
    """Drives jobs through plan -> enqueue -> collect -> merge (see module doc)."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session], store: Store,
                 executor: Executor, clock: Callable[[], datetime] = utcnow,
                 hub: EventHub | None = None):
        self.settings, self.sessions, self.store, self.executor = settings, sessions, store, executor
        self.clock = clock
        self.events = hub if hub is not None else EventHub()
        self._preview_versions = itertools.count(1)
        self._tracked: dict[tuple[str, int], tuple[str, ...]] = {}  # units we put in flight
        self._previews: dict[str, _Preview] = {}  # running previews, least recently used first
        self._stop = threading.Event()
        # Set when the executor reports a unit finished: the next tick starts at
        # once instead of after poll_interval, so short units don't leave the
        # pool idle between ticks.
        self._wake = threading.Event()
        executor.on_progress(self._wake.set)
        self._thread: threading.Thread | None = None
        # Stored films read as inputs during one tick, by (job, unit): every
        # gather tile of a photon round needs the same photon maps, so they are
        # read once and the tickets share one bytes object each.
        self._inputs: dict[tuple[str, int], bytes] = {}
        self.ticks = 0
        self.last_error: str | None = None

    # -- the thread --------------------------------------------------------------
    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="rayfarm-scheduler", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 60.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.tick()
                self.last_error = None
            except Exception as exc:  # keep scheduling; the next tick retries
                error = f"{type(exc).__name__}: {exc}"
                if error != self.last_error:  # once per distinct error, not every tick
                    log.exception("scheduler tick failed")
                self.last_error = error
            self._wake.wait(self.settings.poll_interval)
            self._wake.clear()

    # -- one tick ------------------------------------------------------------------
    def tick(self) -> None:
        """Advance every scheduled job once, in priority order."""
        with self.sessions() as session:
            job_ids = list(session.scalars(
                select(Job.id).where(Job.status.in_(states.SCHEDULED_JOB))
                .order_by(Job.priority.desc(), Job.created, Job.id)))
        self._cancel_departed()
        for job_id in [j for j in self._previews if j not in job_ids]:
            del self._previews[job_id]
        may_enqueue = True
        self._inputs = {}
        for job_id in job_ids:
            if self._stop.is_set():
                break
            try:
                complete, waiting = self._advance(job_id, may_enqueue)
                if waiting:  # jobs after it wait until its pending units are enqueued
                    may_enqueue = False
                if complete:
                    self._finish(job_id)
            except StaleDataError:
                log.info("job %s changed meanwhile (canceled?); next tick", job_id)
                self._forget_if_deleted(job_id)
        self._inputs = {}
        self.ticks += 1

    def _cancel_departed(self) -> None:
        """Cancel the tasks of units that left flight behind our back (job canceled)."""
        if not self._tracked:
            return
        with self.sessions() as session:
            live = {(job_id, index) for job_id, index in session.execute(
                select(WorkUnit.job_id, WorkUnit.index).join(Job, Job.id == WorkUnit.job_id)
                .where(WorkUnit.state.in_(states.IN_FLIGHT),
                       Job.status.in_(states.SCHEDULED_JOB)))}
        for key in [k for k in self._tracked if k not in live]:
            self.executor.cancel(key[0], self._tracked.pop(key))

    def _advance(self, job_id: str, may_enqueue: bool = True) -> tuple[bool, bool]:
        """Plan, collect and enqueue (if `may_enqueue`) for one job; returns
        (all its units are done, it still has pending units to enqueue)."""
        released: list[tuple[str, ...]] = []
        landed: list[tuple[int, PartialFilm]] = []
        enqueue_error: Exception | None = None
        with self.sessions.begin() as session:  # the plan stands even if enqueuing fails
            job = session.get(Job, job_id)
            if job is None or job.status not in states.SCHEDULED_JOB:
                return False, False
            if job.status == "queued":
                self._plan(session, job, self.clock())
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None or job.status not in ("running", "paused"):
                return False, False
            waiting = False
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
            if job.status == "running":
                # Asked after collecting: finished units free their slots at once.
                slots = max(self.executor.capacity(), 0) if may_enqueue else 0
                pending = self._ready_units(session, job, slots + 1)
                waiting = len(pending) > slots
                for unit in pending[:slots]:
                    try:
                        self._enqueue(job, unit, now)
                    except Exception as exc:  # broker down: keep what was sent, retry later
                        enqueue_error = exc
                        waiting = True
                        break
                    unit.attempts = 1
            complete = job.status == "running" and job.units_done == job.units_total
            width, height = job.width, job.height
        for task_ids in released:  # only once the ledger says done (or failed)
            self.executor.release(task_ids)
        if not complete:  # a complete job's preview comes from the final merge
            try:
                self._refresh_preview(job_id, width, height, landed)
            except Exception:  # a preview is a courtesy; never stop the job for it
                log.exception("preview of job %s failed", job_id)
                self._previews.pop(job_id, None)
        if enqueue_error is not None:
            raise enqueue_error
        return complete, waiting

    def _ready_units(self, session: Session, job: Job, limit: int) -> list[WorkUnit]:
        """Up to `limit` pending units of the job whose needs are all done, in
        unit order. Tile jobs need nothing; a DAG's later stages wait here."""
        pending = session.scalars(
            select(WorkUnit).where(WorkUnit.job_id == job.id, WorkUnit.state == "pending")
            .order_by(WorkUnit.index))
        ready: list[WorkUnit] = []
        done: set[int] | None = None
        for unit in pending:
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
        return ready

    def _plan(self, session: Session, job: Job, now: datetime) -> None:
        spec = RenderSpec.from_dict(job.spec)
        units = METHODS[spec.method].make_plan(spec, bool(job.progressive))
        self._previews.pop(job.id, None)  # planned anew (e.g. requeued): a fresh preview
        for unit in units:
            session.add(WorkUnit(job_id=job.id, index=unit.index, state="pending",
                                 unit=unit.to_dict(), attempts=0, task_ids=[]))
        job.units_total = len(units)
        states.change_job(job, "running", now)
        session.flush()

    def _enqueue(self, job: Job, unit: WorkUnit, now: datetime) -> None:
        inputs = {}
        for i in unit.unit.get("needs") or ():
            key = (job.id, int(i))
            if key not in self._inputs:
                self._inputs[key] = self.store.unit_film(job.id, int(i))
            inputs[int(i)] = self._inputs[key]
        task_id = self.executor.submit(Ticket(job.id, unit.index, job.scene_hash, job.spec,
                                              unit.unit, priority=job.priority or 0,
                                              inputs=inputs))
        unit.task_ids = [*unit.task_ids, task_id]
        states.change_unit(unit, "queued", now)
        self._tracked[(job.id, unit.index)] = tuple(unit.task_ids)

    def _collect(self, session: Session, job: Job, unit: WorkUnit, obs: Observation,
                 now: datetime, released: list, landed: list) -> bool:
        """Apply one observation to a unit; returns True if the job failed."""
        if obs.state == "done":
            try:
                film = PartialFilm.from_bytes(obs.film)
            except Exception as exc:  # a corrupt result is a failed attempt
                obs = Observation("failed", error=f"unreadable partial film: {exc}")
            else:
                # Stored before the unit is marked done; a crash in between only
                # means the same bytes are written again.
                self.store.put_unit_film(job.id, unit.index, obs.film)
                states.change_unit(unit, "done", now)
                unit.worker = obs.worker or unit.worker
                unit.seconds = float(film.stats.get("seconds", 0.0))
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
        if obs.state == "running":
            if unit.state == "queued":
                states.change_unit(unit, "running", now)
            unit.worker = obs.worker or unit.worker
        elif obs.state == "lost":
            log.warning("unit %s/%d lost (task %s); enqueuing it again",
                        job.id, unit.index, unit.task_ids[-1] if unit.task_ids else None)
            self._enqueue(job, unit, now)
        elif obs.state == "failed":
            unit.error = obs.error
            if unit.attempts >= self.settings.max_attempts:
                states.change_unit(unit, "failed", now)
                self._fail_job(session, job, now, f"unit {unit.index} failed after "
                                                  f"{unit.attempts} attempts: {obs.error}")
                released.append(tuple(unit.task_ids))
                self._tracked.pop((job.id, unit.index), None)
                return True
            log.warning("unit %s/%d attempt %d failed: %s", job.id, unit.index, unit.attempts,
                        obs.error)
            unit.attempts += 1
            self._enqueue(job, unit, now)
        return False

    def _fail_job(self, session: Session, job: Job, now: datetime, error: str) -> None:
        states.change_job(job, "failed", now, error=error)
        for other in session.scalars(select(WorkUnit).where(
                WorkUnit.job_id == job.id, WorkUnit.state.not_in(states.FINAL_UNIT))):
            states.change_unit(other, "canceled", now)  # their tasks are canceled next tick

    # -- the running preview ----------------------------------------------------------
    def _refresh_preview(self, job_id: str, width: int, height: int,
                         landed: list[tuple[int, PartialFilm]]) -> None:
        """Add the units that just landed (committed as done) to the job's running
        preview; write its PNG if it changed and the last write is old enough."""
        preview = self._previews.pop(job_id, None)
        if preview is None:
            if not landed:
                return
            preview = _Preview(width, height)
            with self.sessions() as session:  # after a restart or eviction: the done units
                done = list(session.scalars(select(WorkUnit.index).where(
                    WorkUnit.job_id == job_id, WorkUnit.state == "done")))
            fresh = {index for index, _ in landed}
            for index in done:
                if index not in fresh:
                    preview.add(index, PartialFilm.from_bytes(self.store.unit_film(job_id, index)))
        for index, film in landed:
            preview.add(index, film)
        self._previews[job_id] = preview  # most recently used last
        while len(self._previews) > PREVIEW_JOBS:
            self._previews.pop(next(iter(self._previews)))
        if preview.dirty and time.monotonic() - preview.written >= PREVIEW_INTERVAL:
            preview.write(self.store.preview_path(job_id), self.store.noise_path(job_id))
            self._publish_preview(job_id, len(preview.added))

    def _publish_preview(self, job_id: str, units: int) -> None:
        version = next(self._preview_versions)
        self.events.publish("preview", job_id, {
            "job_id": job_id, "version": version, "units": units,
            "url": f"/jobs/{job_id}/preview.png?v={version}",
            "noise_url": f"/jobs/{job_id}/noise.png?v={version}"})

    def _forget_if_deleted(self, job_id: str) -> None:
        """A job deleted while a tick worked on it: drop what the tick may have
        written for it meanwhile (a unit film, a preview)."""
        with self.sessions() as session:
            if session.get(Job, job_id) is not None:
                return
        self._previews.pop(job_id, None)
        self.store.delete_job(job_id)

    # -- finishing -------------------------------------------------------------------
    def _finish(self, job_id: str) -> None:
        """Merge the stored unit films in unit order, write the images, mark done."""
        with self.sessions() as session:
            job = session.get(Job, job_id)
            if job is None or job.status != "running" or job.units_done != job.units_total:
                return
            spec, n_units = dict(job.spec), job.units_total
            metadata = {"job_id": job.id, "scene": job.scene, "scene_hash": job.scene_hash,
                        **{k: spec[k] for k in EXR_METADATA_KEYS if k in spec}}
            width, height = job.width, job.height
        error = None
        try:
            film = merge(width, height, (PartialFilm.from_bytes(self.store.unit_film(job_id, i))
                                         for i in range(n_units)))
            film.write_exr(self.store.result_path(job_id),
                           {k: str(metadata[k]) for k in EXR_METADATA_KEYS})
            film.write_png(self.store.preview_path(job_id))
            film.write_noise_png(self.store.noise_path(job_id))
            self._publish_preview(job_id, n_units)
        except Exception as exc:
            log.exception("merging job %s failed", job_id)
            error = f"merge failed: {type(exc).__name__}: {exc}"
        self._previews.pop(job_id, None)
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None:  # deleted while it was merged
                self.store.delete_job(job_id)
                return
            if job.status != "running":
                return
            if error is None:
                states.change_job(job, "done", self.clock())
            else:
                self._fail_job(session, job, self.clock(), error)
