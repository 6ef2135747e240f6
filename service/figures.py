"""A job's derived figures: what every view of a job computes from its counters
and the clock (seconds it ran, fraction done, ETA, rates), in one place.

    figures = job_figures(job, now)   # {"elapsed": 12.5, "eta": 3.1, "fraction": 0.4, ...}

Each figure is computed on its own, and one whose computation raises, or
whose value is not a finite number (which no JSON writer may send), is None:
its failure is logged once per job and figure. A job list, a job's page and
the event streams serialise every job through `JobPublic.from_job`, so an odd
value in one job (a ledger row of an older version, a corner a formula did not
foresee: a noise target of 1e-300 made the ETA raise OverflowError) costs that
one figure, not every caller's list nor the job's events.
"""

from __future__ import annotations

import logging
import math
import threading
from datetime import datetime
from typing import Callable

from .models import Job
from .targets import error_eta

__all__ = ["FIGURES", "job_figures"]

log = logging.getLogger(__name__)


def _elapsed(job: Job, now: datetime) -> float | None:
    return job.active_seconds(now)


def _fraction(job: Job, now: datetime) -> float:
    total = job.samples_total
    return min(job.samples / total, 1.0) if total else 0.0


def _eta(job: Job, now: datetime) -> float | None:
    if job.status == "done":
        return 0.0
    if job.status != "running":
        return None
    if job.target:
        return error_eta(job)
    if not job.recent_rate:
        return None
    # Only a rate measured between landings (Job.note_samples): the mean since
    # the start counts the wait for the first unit.
    eta = max(job.samples_total - job.samples, 0) / job.recent_rate
    if job.units_done < job.units_total and job.unit_seconds and job.units_done:
        # Units left (say one lost and enqueued again) take at least a mean
        # unit's render time, whatever few samples they hold.
        eta = max(eta, job.unit_seconds / job.units_done)
    return eta


def _samples_per_second(job: Job, now: datetime) -> float | None:
    elapsed = job.active_seconds(now)
    return job.samples / elapsed if elapsed and job.samples else None


def _recent_samples_per_second(job: Job, now: datetime) -> float | None:
    return job.recent_rate if job.status == "running" else None


def _rays_per_second(job: Job, now: datetime) -> float | None:
    elapsed = job.active_seconds(now)
    return job.rays / elapsed if elapsed and job.rays else None


def _seconds_per_unit(job: Job, now: datetime) -> float | None:
    return (job.unit_seconds or 0.0) / job.units_done if job.units_done else None


def _rel_error(job: Job, now: datetime) -> float | None:
    return job.rel_error


# name -> how it is computed from a job and the time now
FIGURES: dict[str, Callable[[Job, datetime], float | None]] = {
    "elapsed": _elapsed,
    "fraction": _fraction,
    "eta": _eta,
    "rel_error": _rel_error,
    "samples_per_second": _samples_per_second,
    "recent_samples_per_second": _recent_samples_per_second,
    "rays_per_second": _rays_per_second,
    "seconds_per_unit": _seconds_per_unit,
}

_MAX_LOGGED = 10000  # (job, figure) failures remembered so as to log each once
_logged: set[tuple[str, str]] = set()
_logged_lock = threading.Lock()


def _log_once(job: Job, name: str, problem: str) -> None:
    key = (str(job.id), name)
    with _logged_lock:
        if key in _logged:
            return
        if len(_logged) >= _MAX_LOGGED:
            _logged.clear()
        _logged.add(key)
    log.warning("job %s: its %s is shown as null: %s", job.id, name, problem)


def job_figures(job: Job, now: datetime) -> dict[str, float | None]:
    """Every figure of `FIGURES` for `job` at `now`: a number, or None when it
    is unknown or could not be computed (module doc)."""
    out: dict[str, float | None] = {}
    for name, compute in FIGURES.items():
        try:
            value = compute(job, now)
            if value is not None and not math.isfinite(value):
                raise ValueError(f"{value!r} is not a finite number")
        except Exception as exc:  # one figure's failure is that figure's null
            _log_once(job, name, f"{type(exc).__name__}: {exc}")
            value = None
        out[name] = value
    return out
