"""Jobs rendered to a noise target on the farm: the pass barrier and its
decisions (renderer/target.py says what the statistic is and why).

A target job is planned as `renderer.target.target_plan`: plain tiles x
canonical-block passes (1, 1, 2, 4, ..., 64, 64, ... spp), pass-major, up to
the target's max_spp. Only a prefix of the plan may run: `Job.units_open`,
the passes decided so far (the scheduler's dispatch reads no unit beyond it).
When every open unit is finished and none is in flight, the scheduler calls
`TargetJobs.decide` in the transaction that collected the pass's last unit:

1. the complete passes are merged in unit order (`frame`: the same bytes as
   `render_to_target`'s frame, whichever units landed first);
2. the frame's statistic and the pass go into `Job.rel_error` and `Job.pass_log`;
3. the next pass's units whose own region meets the target are `skipped`
   (a state of their own, counted in `units_done`: finished, without a film),
   the others are opened; if none is left, or the job has run `max_seconds`,
   every unit not yet run is skipped and the job is complete.

Decisions read only complete passes, merged in unit order, so which units
run, and so the merged image, is a function of the job alone: the same bytes
on the local pool, on Celery, after a restart, as `rayfarm render --target`
(tests/test_service_target.py). `max_seconds` alone reads the clock (the
job's active seconds, pauses excluded), between passes.

Every other progressive tile job logs its convergence with the same frames
(`TargetJobs.note_passes`): once a pass and every pass before it are done,
the passes so far merged in unit order give the error statistic that goes
into `Job.pass_log` (the API's `passes`, the job page's plot).

The frames are kept in memory (camera sums only: 56 bytes a pixel) up to
`FRAME_BYTES` in all; one missing after a restart, a leadership change or an
eviction is merged again from the stored unit films.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from renderer import Film, PartialFilm, RenderSpec, Unit, merge
from renderer.target import Target, stop_reason, units_to_run

from . import events, states
from .admission import job_plan
from .models import Job, WorkUnit
from .store import Store

__all__ = ["FRAME_BYTES", "TargetJobs", "job_target", "at_barrier", "error_eta"]

FRAME_BYTES = 512 << 20


def job_target(job: Job) -> Target | None:
    """The job's noise target, or None for a fixed-spp job."""
    t = job.target
    if not t:
        return None
    return Target(rel_error=float(t["rel_error"]), max_spp=int(t["max_spp"]),
                  max_seconds=None if t.get("max_seconds") is None else float(t["max_seconds"]))


def at_barrier(status: str, units_open: int | None, units_done: int, units_total: int) -> bool:
    """A running target job whose open units are all finished while more are
    planned: its next pass waits for `TargetJobs.decide`."""
    return (status == "running" and units_open is not None
            and units_done >= units_open and units_open < units_total)


def error_eta(job: Job) -> float | None:
    """Seconds until a running target job meets its target, by the error's
    1/sqrt(samples) law: the regions still refined (`active` pixels of the
    last decision) need (error / target)^2 times the samples per pixel they
    have, capped at max_spp, at the job's recent samples/s. None before the
    first decision (no error yet) or without a rate."""
    target, log = job_target(job), job.pass_log or []
    rate = job.recent_rate
    if target is None or not log or not rate or job.rel_error is None \
            or not math.isfinite(job.rel_error):
        return None
    last = log[-1]
    spp = float(last["spp"])
    # The growth is capped before it is squared: a large error over a small
    # target would overflow (max_spp caps the result anyway).
    growth = min(job.rel_error / target.rel_error, math.sqrt(target.max_spp / spp))
    needed = min(spp * growth * growth, float(target.max_spp))
    return max(needed - spp, 0.0) * float(last["active"]) / rate


def _log_pass(job: Job, film: Film, pass_index: int, spp: int, seconds: float,
              active: int) -> None:
    """Append a complete pass to the job's pass log (and its error to the job):
    the spp it reached, the samples in the passes so far (`film`, merged) and
    the job's active seconds when it was seen complete, the image's error
    statistic then (null while unknown), the pixels still refined after it
    (all of them but for a target's skipped tiles)."""
    error = film.image_error()
    job.rel_error = error if math.isfinite(error) else None  # inf: a pixel of 1 sample
    job.pass_log = [*(job.pass_log or []), {
        "pass": pass_index, "spp": spp, "samples": int(film.stats.get("samples", 0)),
        "seconds": round(seconds, 3), "rel_error": job.rel_error, "active": active}]
    events.note(job)


def _pass_bounds(job: Job) -> list[tuple[int, int, int, int]]:
    """(end unit index, pass, its sample_end, pixels) of each pass of the job's
    plan (a pure function of the job: renderer.plan), pass-major."""
    units = job_plan(RenderSpec.from_dict(job.spec), bool(job.progressive), job_target(job))
    out: list[tuple[int, int, int, int]] = []
    for u in units:
        if out and out[-1][1] == u.pass_index:
            out[-1] = (u.index + 1, u.pass_index, u.sample_end, out[-1][3] + u.pixels)
        else:
            out.append((u.index + 1, u.pass_index, u.sample_end, u.pixels))
    return out


def _camera_sums(part: PartialFilm) -> PartialFilm:
    """What a decision reads of a unit film: its camera sums (no AOVs)."""
    return PartialFilm(part.x0, part.y0, part.sum, part.sum_sq, part.weight, part.stats)


class _Frame:
    def __init__(self, film: Film, merged: int):
        self.film, self.merged = film, merged  # units [0, merged) are in the film


class TargetJobs:
    """The frames of the progressive jobs in flight: a target job's decisions,
    every such job's convergence log (module doc)."""

    def __init__(self, store: Store, frame_bytes: int = FRAME_BYTES):
        self.store, self.frame_bytes = store, frame_bytes
        self._frames: OrderedDict[str, _Frame] = OrderedDict()
        # A progressive job's passes: (end unit index, pass, sample_end, pixels) each
        self._passes: dict[str, list[tuple[int, int, int, int]]] = {}

    def forget(self, job_id: str) -> None:
        self._frames.pop(job_id, None)
        self._passes.pop(job_id, None)

    def keep_only(self, job_ids) -> None:
        for job_id in [j for j in self._frames if j not in job_ids]:
            del self._frames[job_id]
        for job_id in [j for j in self._passes if j not in job_ids]:
            del self._passes[job_id]

    def frame(self, session: Session, job: Job, bound: int | None = None) -> Film:
        """The job's units [0, bound) (default: units_open, its complete passes)
        merged in unit order, from the frame kept here plus the stored films of
        the units since; skipped units add nothing. Call with every unit below
        `bound` finished."""
        bound = job.units_open if bound is None else bound
        kept = self._frames.pop(job.id, None)
        if kept is None or kept.merged > bound:  # replanned meanwhile
            empty = merge(job.width, job.height, [])
            kept = _Frame(empty, 0)
        done = session.scalars(select(WorkUnit.index).where(
            WorkUnit.job_id == job.id, WorkUnit.state == "done",
            WorkUnit.index >= kept.merged, WorkUnit.index < bound)
            .order_by(WorkUnit.index))
        for index in done:
            kept.film.add(_camera_sums(PartialFilm.from_bytes(self.store.unit_film(job.id, index))))
        kept.merged = bound
        self._frames[job.id] = kept
        self._evict()
        return kept.film

    def note_passes(self, session: Session, job: Job, now: datetime) -> None:
        """A progressive job without a target: for each pass now complete
        (every unit of it and before it done), its error statistic goes into
        `Job.pass_log` (the convergence the API and the dashboard show),
        measured on the passes so far merged in unit order."""
        logged = {int(p["pass"]) for p in job.pass_log or []}
        for end, pass_index, spp, pixels in self._bounds(job):
            if pass_index in logged:
                continue
            if job.units_done < end:
                # Fewer units done in all than this pass ends at: it cannot be
                # complete, and the count below need not be asked. Most
                # landings stop here. Profiled 2026-11-29 (py-spy, 507-spp
                # progressive jobs): that query was about a third of this
                # method's samples; the service's CPU per job went from
                # 1.15 to 1.11 s (medians of five), within the noise.
                return
            done = session.scalar(select(func.count()).select_from(WorkUnit).where(
                WorkUnit.job_id == job.id, WorkUnit.state == "done", WorkUnit.index < end))
            if done < end:
                return
            _log_pass(job, self.frame(session, job, end), pass_index, spp,
                      job.active_seconds(now) or 0.0, pixels)

    def _bounds(self, job: Job) -> list[tuple[int, int, int, int]]:
        """`_pass_bounds` of the job, planned once."""
        if job.id not in self._passes:
            self._passes[job.id] = _pass_bounds(job)
        return self._passes[job.id]

    def _evict(self) -> None:
        pixel = 7 * 8  # sum, sum_sq (3 each) and weight, float64
        while len(self._frames) > 1 and sum(
                f.film.width * f.film.height * pixel for f in self._frames.values()) \
                > self.frame_bytes:
            self._frames.popitem(last=False)  # the least recently decided

    def decide(self, session: Session, job: Job, now: datetime) -> None:
        """The job's open passes are complete: note the statistic, then open the
        next pass's units that do not meet the target and skip the others, or
        stop (module doc). Call only `at_barrier`."""
        target = job_target(job)
        film = self.frame(session, job)
        bounds = self._bounds(job)
        p = next(i for i, b in enumerate(bounds) if b[0] == job.units_open)  # the last decided
        _, pass_index, spp, _ = bounds[p]
        next_pass = list(session.scalars(select(WorkUnit).where(
            WorkUnit.job_id == job.id, WorkUnit.index >= job.units_open,
            WorkUnit.index < bounds[p + 1][0]).order_by(WorkUnit.index)))
        stop = None
        elapsed = job.active_seconds(now) or 0.0
        if target.max_seconds is not None and elapsed >= target.max_seconds:
            stop = "max_seconds"
        else:
            todo = {u.index for u in units_to_run(
                film, [Unit.from_dict(u.unit) for u in next_pass], target)}
            if not todo:
                stop = "target"
        if stop:  # every unit not yet run
            run, skip = [], list(session.scalars(select(WorkUnit).where(
                WorkUnit.job_id == job.id, WorkUnit.index >= job.units_open)))
        else:
            run = [u for u in next_pass if u.index in todo]
            skip = [u for u in next_pass if u.index not in todo]
        for unit in skip:
            states.change_unit(unit, "skipped", now)
        job.units_done += len(skip)
        job.units_skipped = (job.units_skipped or 0) + len(skip)
        job.units_open = job.units_total if stop else job.units_open + len(next_pass)
        job.target_stop = stop
        active = sum((u.unit["x1"] - u.unit["x0"]) * (u.unit["y1"] - u.unit["y0"]) for u in run)
        _log_pass(job, film, pass_index, spp, elapsed, active)

    @staticmethod
    def finished(job: Job, error: float) -> None:
        """The merged result's statistic: the job's final error and, for a target
        job that ran its last planned pass, why it stopped."""
        job.rel_error = error if math.isfinite(error) else None
        target = job_target(job)
        if target is not None and job.target_stop is None:
            job.target_stop = stop_reason(error, target) if math.isfinite(error) else "max_spp"
