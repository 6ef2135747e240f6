"""Time budgets of rendering units: a unit that renders far longer than its
work should take is stopped, and that spends an attempt.

    rates = UnitRates(factor=10.0, floor=120.0)
    rates.note("job-1", "path", 3, unit, seconds=2.1)     # a landed unit
    rates.budget("job-1", "path", 3, other_unit)          # -> Budget(seconds=..., basis=...)

    budget = max(floor, factor x work x rate)

A unit's *work* is what its plan says it renders: a tile's camera samples
(pixels x samples per pixel), or for the other kinds (light paths, photons,
chains: renderer/plan.py) the length of its range. The *rate* is seconds per
unit of work, measured on the job's own landed units of the same kind (a
job's tiles cost about the same per sample; kinds differ). Before any of its
kind has landed (a job's first units), the farm's recent rate for the same
method and kind stands in, per unit of work and path vertex (depth + 1, so a
deep job is not measured by a shallow one), with `FALLBACK_MARGIN` times the
margin: scenes differ more than a job's tiles do. With neither, a unit has no
budget (nothing measured yet: nothing to judge it by).

The floor keeps short units from ever being stopped by a noisy estimate; the
factor leaves a generous margin for tiles that cost more than the job's
average (a glass sphere, a light in view). A stopped unit is a failed
attempt whose error names the budget; after `max_attempts` its job fails,
as for any failing unit.

Pure bookkeeping: no database, no executor. The scheduler notes every unit
it stores and asks for a budget only for units that have rendered longer
than the floor, so it costs nothing for units shorter than that.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Budget", "UnitRates", "unit_work", "FALLBACK_MARGIN"]

FALLBACK_MARGIN = 4.0  # times the factor, where the rate is not the job's own
_EWMA = 0.2  # weight of the newest unit in the farm's rate per method and kind


def unit_work(unit: dict) -> int:
    """A unit's work (module doc): at least 1."""
    span = max(int(unit.get("sample_end", 0)) - int(unit.get("sample_start", 0)), 0)
    if unit.get("kind", "tile") == "tile":
        pixels = max(int(unit.get("x1", 0)) - int(unit.get("x0", 0)), 0) * \
            max(int(unit.get("y1", 0)) - int(unit.get("y0", 0)), 0)
        span *= pixels
    return max(span, 1)


@dataclass(frozen=True)
class Budget:
    """How long a unit may render, and what that was derived from (for its error)."""

    seconds: float
    basis: str

    def exceeded(self, elapsed: float) -> str:
        """The error of a unit stopped after `elapsed` seconds."""
        return (f"stopped after {elapsed:.0f} s: over its time budget of {self.seconds:.0f} s "
                f"({self.basis})")


class UnitRates:
    """Measured render rates (module doc) and the budgets they give."""

    def __init__(self, factor: float, floor: float):
        self.factor, self.floor = factor, floor
        self._jobs: dict[tuple[str, str], tuple[float, float]] = {}  # (job, kind) -> seconds, work
        self._farm: dict[tuple[str, str], float] = {}  # (method, kind) -> s per work and vertex

    def note(self, job_id: str, method: str, depth: int, unit: dict, seconds: float) -> None:
        """A unit of the job rendered in `seconds`."""
        if not seconds or seconds <= 0:
            return
        kind, work = unit.get("kind", "tile"), unit_work(unit)
        total_seconds, total_work = self._jobs.get((job_id, kind), (0.0, 0.0))
        self._jobs[(job_id, kind)] = (total_seconds + seconds, total_work + work)
        per_vertex = seconds / (work * (max(depth, 0) + 1))
        old = self._farm.get((method, kind))
        self._farm[(method, kind)] = per_vertex if old is None else old + _EWMA * (per_vertex - old)

    def knows(self, job_id: str) -> bool:
        return any(key[0] == job_id for key in self._jobs)

    def budget(self, job_id: str, method: str, depth: int, unit: dict) -> Budget | None:
        """The unit's budget, or None if nothing measured says what it should take."""
        kind, work = unit.get("kind", "tile"), unit_work(unit)
        measured = self._jobs.get((job_id, kind))
        if measured is not None and measured[1] > 0:
            expected = work * measured[0] / measured[1]
            factor, basis = self.factor, "the job's measured rate"
        elif (method, kind) in self._farm:
            expected = work * (max(depth, 0) + 1) * self._farm[(method, kind)]
            factor = self.factor * FALLBACK_MARGIN
            basis = f"the farm's recent rate for {method}"
        else:
            return None
        seconds = max(self.floor, factor * expected)
        return Budget(seconds, f"{factor:g} x the {expected:.3g} s its {work} samples take at "
                               f"{basis}, at least {self.floor:g} s")

    def keep_only(self, job_ids) -> None:
        """Forget the jobs no longer scheduled."""
        job_ids = set(job_ids)
        for key in [k for k in self._jobs if k[0] not in job_ids]:
            del self._jobs[key]
