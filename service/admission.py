"""Admission control: what one caller may ask of the farm, checked before a job
or an upload is accepted. Plain Python, no HTTP; the job and upload use cases
call it with the caller (`service.access.Principal`), and the error tree maps
the refusals (`InvalidRequest` 422, `Forbidden` 403, `RateLimited` 429 with
Retry-After).

    limits = limits_for(settings, actor)            # the role's RoleLimits
    check_memory(settings, actor, spec, progressive=True) # pixels, a unit's and the job's bytes
    check_job(settings, actor, spec, units=planned_units(spec, progressive=True),
              active_jobs=count_active_jobs(session, actor.user))
    check_submission_rate(limiter, settings, actor) # POST /jobs per token and minute
    check_submission_rate(limiter, settings, actor, jobs=13)  # an experiment of 13 jobs
    check_upload_rate(limiter, settings, actor)     # POST /scenes per owner and hour

Limits are per role (`Settings.limits_admin`, `Settings.limits_artist`;
`RAYFARM_LIMITS_ARTIST__MAX_ACTIVE_JOBS=5` sets one); a viewer submits
nothing. They refuse what the farm cannot serve fairly: a job too big to
finish (samples), one too big to hold (pixels; the bytes a unit's render
process and the job as a whole would hold, renderer/memory.py), one whose
plan would swamp the ledger (units), an owner queueing more than its share
of jobs, a script submitting in a loop.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import replace

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from renderer import BOUNDS, METHODS, RenderSpec, Unit
from renderer.memory import JobMemory, job_memory
from renderer.plan_size import plan_size
from renderer.target import Target, target_plan
from worker.settings import RoleLimits

from . import states
from .access import Principal, require_submit
from .errors import InvalidRequest, RateLimited
from .models import Job
from .settings import Settings

__all__ = ["limits_for", "check_job", "check_memory", "job_plan", "planned_units", "unit_floor", "admit_job", "count_active_jobs", "RateLimiter",
           "check_submission_rate", "check_upload_rate", "ACTIVE_JOBS_RETRY_AFTER"]

# Finished units whose films may wait in the service to be collected, per
# render process: what the local executor keeps in flight for short units
# (LocalExecutor.MAX_AHEAD; Celery's prefetch keeps fewer).
IN_FLIGHT_PER_PROCESS = 16

# Retry-After of a refusal for too many active jobs: a hint, since nobody knows
# when one of them finishes (or is canceled).
ACTIVE_JOBS_RETRY_AFTER = 30.0


def limits_for(settings: Settings, actor: Principal) -> RoleLimits:
    """The limits of the actor's role; a viewer may submit nothing (`Forbidden`)."""
    require_submit(actor)
    return settings.limits_admin if actor.is_admin else settings.limits_artist


def _setting(actor: Principal, field: str) -> str:
    """The environment variable that sets `field` of the actor's role."""
    return f"RAYFARM_LIMITS_{actor.role.upper()}__{field.upper()}"


def unit_floor(spec: RenderSpec, progressive: bool, target: Target | None = None) -> int:
    """A lower bound of the job's planned units, computed without planning:
    the tile plan's count for tile and radiosity plans (exact for tile
    plans and for a noise target's tiles x canonical-block passes), tiles x
    passes for BDPT, an iteration's photon unit for SPPM. A request for
    millions of units is refused on this, before `planned_units` counts them."""
    from renderer.plan import count_units, sample_passes, tile_pixels

    if target is not None:
        return count_units(spec, True, small_passes=True)
    method = METHODS[spec.method]
    if method.family in ("tile", "radiosity"):  # the tile plan's units (radiosity's display)
        return count_units(spec, progressive)
    if method.name == "bdpt":  # tiles x passes (it keeps every small pass: at least this)
        tiles = math.ceil(spec.width / spec.tile_size) * math.ceil(spec.height / spec.tile_size)
        return tiles * len(sample_passes(spec.spp, progressive, tile_pixels(spec)))
    if method.family == "photons":
        return spec.spp
    return 1  # light tracing and MLT: a few dozen units whatever the job


def job_plan(spec: RenderSpec, progressive: bool, target: Target | None = None) -> list[Unit]:
    """The job's work units: its method's plan, or with a noise target the
    target's plan (renderer.target.target_plan; `spec.spp` is its max_spp)."""
    if target is not None:
        return target_plan(spec, target)[1]
    return METHODS[spec.method].make_plan(spec, progressive)


def planned_units(spec: RenderSpec, progressive: bool, target: Target | None = None) -> int:
    """How many work units the job would be planned into (the planner is pure,
    so this is exact, also for DAG methods), counted without building them
    (`renderer.plan_size`): a plan is built by the scheduler, not in a request."""
    if target is not None:
        return unit_floor(spec, progressive, target)
    return plan_size(spec, progressive)


def check_job(settings: Settings, actor: Principal, spec: RenderSpec, units: int,
              active_jobs: int) -> None:
    """Refuse a job the actor's role may not submit: too many samples
    (`InvalidRequest` on `spp`), too many units (on `tile_size`), or too many
    of the owner's jobs already queued, running or paused (`RateLimited`).

    `units` is the job's planned units (`planned_units`), `active_jobs` the
    owner's (`count_active_jobs`)."""
    limits = limits_for(settings, actor)
    pixels = spec.width * spec.height
    samples = pixels * spec.spp
    if samples > limits.max_samples_per_job:
        most = max(limits.max_samples_per_job // pixels, 0)
        raise InvalidRequest("spp", f"{spec.width}x{spec.height} pixels x {spec.spp} spp = "
                                    f"{samples} samples exceed the {actor.role} limit of "
                                    f"{limits.max_samples_per_job} samples per job "
                                    f"({_setting(actor, 'max_samples_per_job')}); "
                                    f"use spp <= {most} at this size")
    if units > limits.max_units_per_job:
        raise InvalidRequest("tile_size", f"the job plans {units} work units, above the "
                                          f"{actor.role} limit of {limits.max_units_per_job} "
                                          f"({_setting(actor, 'max_units_per_job')}); use a "
                                          "larger tile_size, fewer spp or progressive=false")
    if active_jobs >= limits.max_active_jobs:
        raise RateLimited(f"user '{actor.user}' has {active_jobs} jobs queued, running or "
                          f"paused; the {actor.role} limit is {limits.max_active_jobs} "
                          f"({_setting(actor, 'max_active_jobs')}): wait for one to finish "
                          "or cancel one", retry_after=ACTIVE_JOBS_RETRY_AFTER)


def _mb(n: int) -> str:
    return f"{n / 1e6:,.0f} MB"


def _frame_field(spec: RenderSpec) -> str:
    """The dimension to name when the frame is too big: the larger one."""
    return "width" if spec.width >= spec.height else "height"


def check_memory(settings: Settings, actor: Principal, spec: RenderSpec, progressive: bool,
                 target: Target | None = None, denoise: bool = False,
                 units: int | None = None, scene: int = 0) -> JobMemory:
    """Refuse a job too big to hold for the actor's role (`InvalidRequest`):
    more pixels than `max_pixels_per_job` (on `width` or `height`); a work
    unit whose render process would hold more than `max_unit_bytes` (on
    `tile_size` with the largest tile that fits, or on the frame when
    whole-frame layers alone exceed it: splats, photon maps); a job that
    would hold more than `max_job_bytes` with a unit in every render process
    (`local_workers`) and the service's share, with as many of its `units`
    (its planned units, or a lower bound; default: one a process) finished
    and waiting to be collected as the executor keeps in flight; unit films
    that would take more than `max_job_store_bytes` of the store (on
    `tile_size` for BDPT, whose every tile stores the frame's splats, else on
    the frame). `scene`: what each render process holds for the scene
    (renderer.memory.scene_memory: its triangles and textures), counted in
    the job's bytes. The bytes are renderer.memory's; returns them."""
    limits = limits_for(settings, actor)
    pixels = spec.width * spec.height
    if pixels > limits.max_pixels_per_job:
        raise InvalidRequest(_frame_field(spec), f"{spec.width}x{spec.height} = {pixels} pixels "
                             f"exceed the {actor.role} limit of {limits.max_pixels_per_job} "
                             f"pixels per job ({_setting(actor, 'max_pixels_per_job')})")

    def memory(tile: int) -> JobMemory:
        return job_memory(replace(spec, tile_size=tile), progressive=progressive,
                          target=target is not None, denoise=denoise, scene=scene)

    def largest_tile(fits) -> int | None:
        """The largest tile size below spec.tile_size for which `fits`, if any."""
        lo, hi = BOUNDS["tile_size"][0], spec.tile_size - 1
        if hi < lo or not fits(memory(lo)):
            return None
        while lo < hi:  # the bytes grow with the tile
            mid = (lo + hi + 1) // 2
            lo, hi = (mid, hi) if fits(memory(mid)) else (lo, mid - 1)
        return lo

    mem = memory(spec.tile_size)
    if mem.unit > limits.max_unit_bytes:
        setting = _setting(actor, "max_unit_bytes")
        what = (f"a work unit of this {spec.method} job would hold about {_mb(mem.unit)} in its "
                f"render process, above the {actor.role} limit of "
                f"{_mb(limits.max_unit_bytes)} ({setting})")
        tile = largest_tile(lambda m: m.unit <= limits.max_unit_bytes)
        if tile is None:
            raise InvalidRequest(_frame_field(spec), f"{what}; {_mb(mem.unit_frame)} of it "
                                 "does not shrink with the tile (layers over the whole frame: "
                                 "splats, photon maps): render fewer pixels")
        raise InvalidRequest("tile_size", f"{what}; use tile_size <= {tile}")
    processes = settings.local_workers
    waiting = processes if units is None else min(units, processes * IN_FLIGHT_PER_PROCESS)
    total = mem.total(processes, waiting)
    if total > limits.max_job_bytes:
        setting = _setting(actor, "max_job_bytes")
        scene_part = f" and the scene's {_mb(mem.scene)}" if mem.scene else ""
        what = (f"this job would hold about {_mb(total)} at once (the service "
                f"{_mb(mem.service(processes, waiting))}, {processes} render processes "
                f"{_mb(mem.unit)} each{scene_part}), above the {actor.role} limit of "
                f"{_mb(limits.max_job_bytes)} per job ({setting})")
        tile = largest_tile(lambda m: m.total(processes, waiting) <= limits.max_job_bytes)
        if tile is None:
            if mem.scene and processes * mem.scene >= limits.max_job_bytes:
                raise InvalidRequest("scene", f"{what}: the scene alone is too large")
            raise InvalidRequest(_frame_field(spec), f"{what}: render fewer pixels")
        raise InvalidRequest("tile_size", f"{what}; use tile_size <= {tile}")
    if mem.stored > limits.max_job_store_bytes:
        what = (f"this job's unit films would take about {_mb(mem.stored)} of the store, above "
                f"the {actor.role} limit of {_mb(limits.max_job_store_bytes)} per job "
                f"({_setting(actor, 'max_job_store_bytes')})")
        if METHODS[spec.method].name == "bdpt":  # each tile unit stores the frame's splats
            tile = _smallest_tile(spec, lambda t: memory(t).stored <= limits.max_job_store_bytes)
            if tile is not None:
                raise InvalidRequest("tile_size", f"{what}; every tile of every pass stores "
                                                  f"the frame's splats: use tile_size >= {tile}")
        raise InvalidRequest(_frame_field(spec), f"{what}: render fewer pixels or samples")
    return mem


def _smallest_tile(spec: RenderSpec, fits) -> int | None:
    """The smallest tile size above spec.tile_size for which `fits` (fewer,
    larger tiles), if any."""
    lo, hi = spec.tile_size + 1, max(spec.width, spec.height, spec.tile_size + 1)
    hi = min(hi, BOUNDS["tile_size"][1])
    if lo > hi or not fits(hi):
        return None
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if fits(mid) else (mid + 1, hi)
    return lo


def admit_job(session: Session, settings: Settings, actor: Principal, spec: RenderSpec,
              progressive: bool, target: Target | None = None, denoise: bool = False,
              scene: int = 0) -> int:
    """Every admission check of a job, cheapest first; returns its planned
    units. A target job is checked at its budget (spp = max_spp); `scene` as
    for `check_memory`."""
    floor = unit_floor(spec, progressive, target)
    check_memory(settings, actor, spec, progressive, target, denoise, units=floor, scene=scene)
    check_job(settings, actor, spec, units=floor, active_jobs=0)
    units = planned_units(spec, progressive, target)
    check_memory(settings, actor, spec, progressive, target, denoise, units=units, scene=scene)
    check_job(settings, actor, spec, units=units,
              active_jobs=count_active_jobs(session, actor.user))
    return units


def count_active_jobs(session: Session, owner: str) -> int:
    """The owner's jobs that hold a place in the farm: queued, running or paused."""
    return session.scalar(select(func.count()).select_from(Job).where(
        Job.owner == owner, Job.status.in_(states.SCHEDULED_JOB))) or 0


class RateLimiter:
    """At most `limit` hits per key within any `window_seconds` (a sliding
    window of the hits' times), in this process, thread-safe.

        limiter = RateLimiter()
        limiter.hit("submit:3f9c0a1b", limit=60, window_seconds=60)  # or RateLimited

    The windows live in this process's memory: with several service replicas,
    each enforces its own window, so a client spread over N replicas may make
    up to N x `limit` requests per window (and a restart forgets the hits).
    Refused hits are not recorded: a client retrying too early does not push
    its own retry further away.
    """

    MAX_KEYS = 10000  # beyond this, keys whose hits all left their window are dropped

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._hits: dict[str, tuple[float, deque[float]]] = {}  # key -> (window, hit times)

    def hit(self, key: str, limit: int, window_seconds: float, now: float | None = None,
            count: int = 1) -> None:
        """Record `count` hits of `key` at `now` (default: `time.monotonic()`),
        or none and raise `RateLimited` with the seconds until enough hits
        leave the window, when fewer than `count` places are left in it. A
        limit of 0 refuses all; a `count` above the limit never fits (the
        caller refuses it first: `check_submission_rate`)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            _, hits = self._hits.get(key, (window_seconds, None))
            hits = hits if hits is not None else deque()
            while hits and hits[0] <= now - window_seconds:
                hits.popleft()
            if len(hits) + count > limit:
                # the hit whose leaving makes room for `count`
                leaving = len(hits) + count - limit - 1
                retry_after = (hits[leaving] + window_seconds - now if leaving < len(hits)
                               else window_seconds)
                self._hits[key] = (window_seconds, hits)
                what = "requests" if count == 1 else f"requests ({count} asked at once)"
                raise RateLimited(f"more than {limit} {what} in {_span(window_seconds)}; "
                                  f"retry in {math.ceil(retry_after)} s",
                                  retry_after=retry_after)
            hits.extend([now] * count)
            self._hits[key] = (window_seconds, hits)
            if len(self._hits) > self.MAX_KEYS:
                self._sweep(now)

    def _sweep(self, now: float) -> None:
        for key in [k for k, (window, hits) in self._hits.items()
                    if not hits or hits[-1] <= now - window]:
            del self._hits[key]


def _span(seconds: float) -> str:
    if seconds == 60:
        return "a minute"
    if seconds == 3600:
        return "an hour"
    return f"{seconds:g} s"


def check_submission_rate(limiter: RateLimiter, settings: Settings, actor: Principal,
                          now: float | None = None, jobs: int = 1, field: str = "jobs") -> None:
    """`jobs` job submissions by the actor's token (per token: a script and
    its owner's dashboard count apart), at most `submissions_per_minute`: a
    `POST /jobs` is one, an experiment as many as the jobs it creates. More
    than a minute's worth at once could never pass: `InvalidRequest` on
    `field`, not a 429 that no wait would cure."""
    limits = limits_for(settings, actor)
    if jobs > 1 and jobs > limits.submissions_per_minute:
        raise InvalidRequest(field, f"creates {jobs} jobs at once; the {actor.role} limit is "
                                    f"{limits.submissions_per_minute} job submissions per "
                                    f"minute ({_setting(actor, 'submissions_per_minute')})")
    key = f"submit:{actor.token_id or 'user:' + actor.user}"
    limiter.hit(key, limits.submissions_per_minute, 60.0, now, count=jobs)


def check_upload_rate(limiter: RateLimiter, settings: Settings, actor: Principal,
                      now: float | None = None) -> None:
    """One scene upload by the actor (per owner), at most `uploads_per_hour`."""
    limits = limits_for(settings, actor)
    limiter.hit(f"upload:{actor.user}", limits.uploads_per_hour, 3600.0, now)
