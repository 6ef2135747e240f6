"""A DAG job's artefacts: the unit films that later units of the job read
(photon maps, an MLT bootstrap, a radiosity solution, a gather tile's state
for the next round), named by the SHA-256 the ledger records for each done
unit (`WorkUnit.film_digest`).

The scheduler hands executors digests, never bytes: the bytes are where the
unit that made them left them (Redis on the farm) or in the store, and the
executor fetches them from there (service/executors). This module answers the
scheduler's two questions about them:
- `is_input(job, index)`: does any later unit read this unit's film? Then
  the executor keeps it at hand until the job is over; otherwise it may drop
  its copy as soon as the film is stored. Answered from the job's plan (a pure
  function of its spec), computed once per job.
- `digests(session, job, needs)`: the digests of the films a unit needs, read
  from the ledger once per tick (every gather tile of a photon round needs the
  same photon units).
- `departed(scheduled)`: the digests of input films stored for jobs that left
  the scheduler's view behind its back (canceled or deleted through the API),
  which the executor may drop at once rather than when they expire (a day).
  A job that finishes or fails here drops its own (`stored_digests`).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import Callable, Iterable

from sqlalchemy import select
from sqlalchemy.orm import Session

from renderer import METHODS, RenderSpec

from .models import Job, WorkUnit

__all__ = ["Artefacts", "inputs_of_plan"]


def inputs_of_plan(spec: dict, progressive: bool) -> frozenset[int]:
    """The indices of the units whose films some other unit of the plan needs."""
    plan_spec = RenderSpec.from_dict(spec)
    units = METHODS[plan_spec.method].make_plan(plan_spec, progressive)
    return frozenset(i for unit in units for i in unit.needs)


class Artefacts:
    """Which films of a job are inputs, and their digests (see the module doc).
    Used by the scheduler thread only."""

    JOBS_KEPT = 256  # plans' input sets remembered (jobs in flight are few)

    def __init__(self, load_unit_film: Callable[[str, int], bytes]):
        self._load_unit_film = load_unit_film
        self._inputs: OrderedDict[str, frozenset[int]] = OrderedDict()
        self._digests: dict[tuple[str, int], str] = {}  # this tick's reads
        self._kept: dict[str, set[str]] = {}  # job -> digests of its stored input films

    def new_tick(self) -> None:
        """Forget the digests read so far (they are re-read from the ledger)."""
        self._digests = {}

    def inputs(self, job: Job) -> frozenset[int]:
        """The units of `job` whose films later units read."""
        found = self._inputs.get(job.id)
        if found is None:
            found = inputs_of_plan(job.spec, bool(job.progressive))
            self._inputs[job.id] = found
            while len(self._inputs) > self.JOBS_KEPT:
                self._inputs.popitem(last=False)
        else:
            self._inputs.move_to_end(job.id)
        return found

    def is_input(self, job: Job, index: int) -> bool:
        return index in self.inputs(job)

    def forget(self, job_id: str) -> None:
        """The job was planned anew or is over."""
        self._inputs.pop(job_id, None)
        self._kept.pop(job_id, None)

    def keep(self, job_id: str, digest: str) -> None:
        """An input film of the job was stored; the executor keeps a copy."""
        self._kept.setdefault(job_id, set()).add(digest)

    def departed(self, scheduled: Iterable[str]) -> list[str]:
        """The kept digests of jobs not among `scheduled` (the jobs the
        scheduler still looks at), forgotten as they are returned."""
        gone = set(self._kept) - set(scheduled)
        digests = sorted({d for job_id in gone for d in self._kept.pop(job_id)})
        for job_id in gone:
            self._inputs.pop(job_id, None)
        return digests

    def digests(self, session: Session, job: Job, needs: Iterable[int]) -> dict[int, str]:
        """index -> SHA-256 of the stored film, for the done units `needs`."""
        needs = [int(i) for i in needs]
        missing = [i for i in needs if (job.id, i) not in self._digests]
        if missing:
            rows = session.execute(select(WorkUnit.index, WorkUnit.film_digest).where(
                WorkUnit.job_id == job.id, WorkUnit.index.in_(missing)))
            for index, digest in rows:
                if digest is None:  # done before the ledger recorded digests
                    digest = hashlib.sha256(self._load_unit_film(job.id, index)).hexdigest()
                self._digests[(job.id, index)] = digest
        return {i: self._digests[(job.id, i)] for i in needs}

    def stored_digests(self, session: Session, job: Job) -> list[str]:
        """The digests of the job's done units that are inputs (to drop once
        the job is over)."""
        inputs = self.inputs(job)
        if not inputs:
            return []
        return sorted({digest for index, digest in session.execute(
            select(WorkUnit.index, WorkUnit.film_digest).where(
                WorkUnit.job_id == job.id, WorkUnit.film_digest.is_not(None)))
            if index in inputs})
