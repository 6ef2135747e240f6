"""The scheduler: one background thread that moves jobs forward.

Each tick, for every active job (oldest first):
1. plan a queued job into unit rows (`renderer.plan`) and mark it running;
2. observe its units in flight: store a finished unit's film (atomically)
   *before* marking the unit done, exactly once; re-enqueue lost units;
   retry failed ones up to `max_attempts`, then fail the job;
3. enqueue pending units while the executor has capacity;
4. when every unit is done, merge the stored films in unit order into
   `result.exr` + `preview.png`, then mark the job done.
Units whose job was canceled (by the API) leave flight; their tasks are
canceled. The ledger is the truth: after a restart the scheduler picks up
where the rows say it was.
"""

from __future__ import annotations

import logging
import threading
from datetime import datetime
from typing import Callable

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError

from renderer import PartialFilm, RenderSpec, merge, plan

from . import states
from .executors import Executor, Flight, Observation, Ticket
from .models import Job, WorkUnit, utcnow
from .settings import Settings
from .store import Store

__all__ = ["Scheduler", "EXR_METADATA_KEYS"]

log = logging.getLogger(__name__)

EXR_METADATA_KEYS = ("job_id", "scene", "scene_hash", "method", "spp", "depth", "seed",
                     "sampler", "tile_size", "width", "height")


class Scheduler:
    """Drives jobs through plan -> enqueue -> collect -> merge (see module doc)."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session], store: Store,
                 executor: Executor, clock: Callable[[], datetime] = utcnow):
        self.settings, self.sessions, self.store, self.executor = settings, sessions, store, executor
        self.clock = clock
        self._tracked: dict[tuple[str, int], tuple[str, ...]] = {}  # units we put in flight
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.ticks = 0
        self.last_error: str | None = None

    # -- the thread --------------------------------------------------------------
    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="rayfarm-scheduler", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 60.0) -> None:
        self._stop.set()
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
            self._stop.wait(self.settings.poll_interval)

    # -- one tick ------------------------------------------------------------------
    def tick(self) -> None:
        """Advance every active job once."""
        with self.sessions() as session:
            job_ids = list(session.scalars(select(Job.id).where(Job.status.in_(states.ACTIVE_JOB))
                                           .order_by(Job.created, Job.id)))
        self._cancel_departed()
        for job_id in job_ids:
            if self._stop.is_set():
                break
            try:
                complete = self._advance(job_id)
                if complete:
                    self._finish(job_id)
            except StaleDataError:
                log.info("job %s changed meanwhile (canceled?); next tick", job_id)
        self.ticks += 1

    def _cancel_departed(self) -> None:
        """Cancel the tasks of units that left flight behind our back (job canceled)."""
        if not self._tracked:
            return
        with self.sessions() as session:
            live = {(job_id, index) for job_id, index in session.execute(
                select(WorkUnit.job_id, WorkUnit.index).join(Job, Job.id == WorkUnit.job_id)
                .where(WorkUnit.state.in_(states.IN_FLIGHT), Job.status.in_(states.ACTIVE_JOB)))}
        for key in [k for k in self._tracked if k not in live]:
            self.executor.cancel(key[0], self._tracked.pop(key))

    def _advance(self, job_id: str) -> bool:
        """Plan, collect and enqueue for one job; returns whether all its units are done."""
        released: list[tuple[str, ...]] = []
        enqueue_error: Exception | None = None
        with self.sessions.begin() as session:  # the plan stands even if enqueuing fails
            job = session.get(Job, job_id)
            if job is None or job.status not in states.ACTIVE_JOB:
                return False
            if job.status == "queued":
                self._plan(session, job, self.clock())
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None or job.status != "running":
                return False
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
                if self._collect(session, job, unit, obs, now, released):
                    break  # the job failed
            if job.status == "running":
                # Asked after collecting: finished units free their slots at once.
                pending = session.scalars(
                    select(WorkUnit).where(WorkUnit.job_id == job.id, WorkUnit.state == "pending")
                    .order_by(WorkUnit.index).limit(max(self.executor.capacity(), 0)))
                for unit in pending:
                    try:
                        self._enqueue(job, unit, now)
                    except Exception as exc:  # broker down: keep what was sent, retry later
                        enqueue_error = exc
                        break
                    unit.attempts = 1
            complete = job.status == "running" and job.units_done == job.units_total
        for task_ids in released:  # only once the ledger says done (or failed)
            self.executor.release(task_ids)
        if enqueue_error is not None:
            raise enqueue_error
        return complete

    def _plan(self, session: Session, job: Job, now: datetime) -> None:
        units = plan(RenderSpec.from_dict(job.spec))
        for unit in units:
            session.add(WorkUnit(job_id=job.id, index=unit.index, state="pending",
                                 unit=unit.to_dict(), attempts=0, task_ids=[]))
        job.units_total = len(units)
        states.change_job(job, "running", now)
        session.flush()

    def _enqueue(self, job: Job, unit: WorkUnit, now: datetime) -> None:
        task_id = self.executor.submit(Ticket(job.id, unit.index, job.scene_hash, job.spec,
                                              unit.unit))
        unit.task_ids = [*unit.task_ids, task_id]
        states.change_unit(unit, "queued", now)
        self._tracked[(job.id, unit.index)] = tuple(unit.task_ids)

    def _collect(self, session: Session, job: Job, unit: WorkUnit, obs: Observation,
                 now: datetime, released: list) -> bool:
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
                released.append(tuple(unit.task_ids))
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
        except Exception as exc:
            log.exception("merging job %s failed", job_id)
            error = f"merge failed: {type(exc).__name__}: {exc}"
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job.status != "running":
                return
            if error is None:
                states.change_job(job, "done", self.clock())
            else:
                self._fail_job(session, job, self.clock(), error)
