"""Rendering to a noise target: sample passes are added until the image's error
statistic meets a target, region by region, or a budget runs out.

    film, report = render_to_target("cornell-box", spec, Target(rel_error=0.05, max_spp=1024))

The statistic is `film.image_error`: the 95th percentile, over the pixels
brighter than 1 % of the mean, of the relative standard error the var
channels give (why that one: its docstring). The job is the progressive plan
of `max_spp` samples per pixel. Before each pass after the first, every
unit of the pass looks at its own region of the frame merged so far: if the
statistic over that region meets the target, the unit is skipped, so a clean
region stops receiving samples while a noisy one goes on. The units are the
plain tiles and the passes the canonical sample blocks (1, 1, 2, 4, ..., 64,
64, ... spp: `plan(small_passes=True)`), not the grouped passes of a
progressive job: a unit holding many tiles could only stop them all at once.

Determinism. A decision reads only complete passes, merged in unit order, so
which units run is a function of the job alone, and so is the image: the same
bytes on one process or many (tests/test_renderer_target.py). `max_seconds`
is the one exception: it is checked between passes, against wall time, so a
slower machine may stop a pass earlier. `max_spp` is the plan itself.

Which methods: those whose plan is the plain tile plan (the path family,
`direct`, `raster`). A DAG method (photon maps, a radiosity solution, MLT's
bootstrap) or one that splats across the frame (light tracing, BDPT's t = 1)
has no per-region estimate that a later pass only refines, and is refused.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from .errors import SpecError
from .film import Film, PartialFilm, image_error, merge
from .plan import Unit, plan
from .registry import METHODS
from .spec import BOUNDS, RenderSpec

__all__ = ["Target", "TargetReport", "REL_ERROR_BOUNDS", "MAX_SECONDS", "passes",
           "render_to_target", "require_target_support", "stop_reason", "supports_target",
           "target_plan", "units_to_run"]

# The relative error a target may ask for. A render of max_spp <= 2^20 samples
# per pixel divides a pixel's relative deviation by at most 1024, so a noisy
# image cannot go below about 1e-4 and a noiseless one meets any target:
# 1e-6 refuses nothing reachable. Far below it the ETA's (error / target)^2
# overflowed (1e-300 raised OverflowError in every view of the job).
REL_ERROR_BOUNDS = (1e-6, 1.0)
MAX_SECONDS = 366 * 24 * 3600.0  # a time budget of a year at most


@dataclass(frozen=True)
class Target:
    """Stop at `rel_error` (the statistic above, e.g. 0.01 for 1 %), or at
    `max_spp` samples per pixel, or after `max_seconds` (checked between passes)."""

    rel_error: float
    max_spp: int
    max_seconds: float | None = None

    def validate(self) -> "Target":
        lo, hi = REL_ERROR_BOUNDS
        if isinstance(self.rel_error, bool) or not (
                isinstance(self.rel_error, (int, float)) and lo <= self.rel_error <= hi):
            raise SpecError("target.rel_error", f"must be between {lo:g} and {hi:g} (a "
                                                f"relative error), got {self.rel_error!r}")
        lo, hi = BOUNDS["spp"]
        if isinstance(self.max_spp, bool) or not isinstance(self.max_spp, int) \
                or not lo <= self.max_spp <= hi:
            raise SpecError("target.max_spp", f"must be an integer between {lo} and {hi}, "
                                              f"got {self.max_spp!r}")
        if self.max_seconds is not None and (isinstance(self.max_seconds, bool) or not (
                isinstance(self.max_seconds, (int, float))
                and 0 < self.max_seconds <= MAX_SECONDS)):
            raise SpecError("target.max_seconds", f"must be a positive number of seconds, at "
                                                  f"most {MAX_SECONDS:.0f} (366 days), got "
                                                  f"{self.max_seconds!r}")
        return self


    def to_dict(self) -> dict:
        return {"rel_error": self.rel_error, "max_spp": self.max_spp,
                "max_seconds": self.max_seconds}


@dataclass
class TargetReport:
    """How a render to a target went: passes run, units run and skipped, what
    stopped it ("target", "max_spp" or "max_seconds"), the statistic after
    each pass."""

    passes: int = 0
    units_run: int = 0
    units_skipped: int = 0
    stopped: str = "max_spp"
    errors: list[float] = field(default_factory=list)


def supports_target(method: str) -> bool:
    """True for methods planned as plain tiles x passes (module doc)."""
    from .integrators.tile import tile_plan

    m = METHODS.get(method)
    return m is not None and m.plan is tile_plan


def require_target_support(method: str) -> None:
    """Raise SpecError naming 'target' if `method` cannot render to a noise
    target, listing those that can."""
    if not supports_target(method):
        allowed = ", ".join(sorted(n for n in METHODS if supports_target(n)))
        raise SpecError("target", f"method '{method}' cannot render to a noise target "
                                  f"(its plan is not tiles x passes); use one of: {allowed}")


def target_plan(spec: RenderSpec, target: Target) -> tuple[RenderSpec, list[Unit]]:
    """The spec a render to `target` runs (its spp is target.max_spp) and its
    units: plain tiles x canonical-block passes, pass-major. Raises SpecError
    naming 'target' for a bad target or a method that cannot render to one."""
    target.validate()
    require_target_support(spec.method)
    spec = replace(spec, spp=target.max_spp)
    return spec, plan(spec, progressive=True, small_passes=True)


def passes(units: list[Unit]) -> list[list[Unit]]:
    """A plan's units grouped by pass, in pass order (unit order within)."""
    by_pass: dict[int, list[Unit]] = defaultdict(list)
    for u in units:
        by_pass[u.pass_index].append(u)
    return [by_pass[p] for p in sorted(by_pass)]


def units_to_run(film: Film, units: list[Unit], target: Target) -> list[Unit]:
    """Of a pass's units, those whose own region of `film` (every complete
    pass before it, merged in unit order) does not meet the target yet: the
    statistic over the region's pixels that the frame's statistic counts
    (brighter than 1 % of the frame's mean, not the region's: a dark region
    would otherwise refine pixels the frame's statistic ignores; measured on
    veach-mis, that made the adaptive render dearer than a fixed one). A
    region with no such pixel meets it."""
    floor = film.error_floor()
    todo = []
    for u in units:  # a region at a time: no whole-frame mean and variance
        region = film.region(u.x0, u.y0, u.x1, u.y1)
        e = image_error(region.mean(), region.variance_of_mean(), floor)
        if not (math.isnan(e) or e <= target.rel_error):
            todo.append(u)
    return todo


def stop_reason(rel_error: float, target: Target) -> str:
    """Why a render that ran its last planned pass stopped: "target" if its
    statistic meets the target, else "max_spp"."""
    return "target" if rel_error <= target.rel_error else "max_spp"


def render_to_target(scene_source, spec: RenderSpec, target: Target, *, pool=None,
                     workers: int | None = None,
                     progress: Callable[[int, float], None] | None = None
                     ) -> tuple[Film, TargetReport]:
    """Render `spec` (its spp replaced by target.max_spp) pass by pass on a
    local pool until every region meets `target` (module doc). `progress`
    is called after each pass with (pass index, the frame's statistic)."""
    from .local import LocalPool
    from .runtime import scene_text
    from .scene_format import resolve_document

    doc = resolve_document(scene_source)
    target.validate()
    spec, units = target_plan(replace(spec, spp=target.max_spp).validate(scene=doc), target)
    key, text = scene_text(doc)
    film = merge(spec.width, spec.height, [])
    report = TargetReport()
    own_pool = pool is None
    pool = pool or LocalPool(workers)
    t0 = time.perf_counter()
    try:
        for p, units in enumerate(passes(units)):
            if p > 0:
                if target.max_seconds is not None and time.perf_counter() - t0 >= target.max_seconds:
                    report.stopped = "max_seconds"
                    break
                todo = units_to_run(film, units, target)
                report.units_skipped += len(units) - len(todo)
                if not todo:
                    report.stopped = "target"
                    break
                units = todo
            futures = {pool.submit(key, text, spec.to_dict(), u.to_dict(), inputs={}): u
                       for u in units}
            parts: dict[int, PartialFilm] = {}
            pending = set(futures)
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    parts[futures[fut].index] = PartialFilm.from_bytes(fut.result())
            for index in sorted(parts):  # unit order: the same bytes however they landed
                film.add(parts[index])
            report.passes += 1
            report.units_run += len(units)
            report.errors.append(film.image_error())
            if progress is not None:
                progress(p, report.errors[-1])
        if report.stopped == "max_spp" and report.errors:
            report.stopped = stop_reason(report.errors[-1], target)
    finally:
        if own_pool:
            pool.shutdown()
    return film, report
