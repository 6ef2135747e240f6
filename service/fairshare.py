"""Fair share: which job gets each free slot of the farm, one slot at a time.

    order = fair_share(contenders, owner_in_flight={"ana": 6, "ben": 0},
                       shares={"ana": 3.0}, slots=4, ready=ready_units_of)
    # -> ["ben-job", "ben-job", "ana-job-1", "ben-job"]: one job id per unit to enqueue

Between owners, weighted fair share (OpenCue's shares, Deadline's weights):
the next slot goes to the owner with the fewest units in flight relative to
its share (`in_flight / share`; an owner without a row in `users` has share
1.0), among the owners with a ready unit. So owners with shares 1 and 3 and
plenty of work split 8 slots 2:6, and a newcomer gets every freed slot until
it holds its share: a small job submitted behind a huge one starts as soon as
a slot frees, however many units the huge one has left.

Within an owner, a higher priority goes first, strictly; among its jobs of
equal priority, the job with the fewest units in flight, then the oldest: its
jobs' units interleave, so none of them holds the owner's slots.

Units in flight are what we count (not CPU seconds, as OpenCue's cores do):
one unit occupies one render process, and the ledger knows the count exactly
each tick. An owner's in-flight count includes its paused jobs' units still
rendering: they occupy slots too. A share of 0 (or less) only gets slots that
no other owner wants.

Pure: no database, no executor. The scheduler calls it once per tick with the
in-flight counts of one small query and reads ready units lazily (`ready`).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from datetime import datetime
from typing import Callable, Iterable, Mapping

__all__ = ["Contender", "fair_share", "DEFAULT_SHARE"]

DEFAULT_SHARE = 1.0  # of an owner without a row in `users`


@dataclass(frozen=True)
class Contender:
    """A running job that may have pending units, as the scheduler sees it this tick."""

    job_id: str
    owner: str
    priority: int
    created: datetime
    in_flight: int  # its units queued or running now


def fair_share(contenders: Iterable[Contender], owner_in_flight: Mapping[str, int],
               shares: Mapping[str, float], slots: int,
               ready: Callable[[str], int]) -> list[str]:
    """Give up to `slots` units to `contenders`, one at a time (module doc);
    returns the job id of each unit in the order they should be enqueued.

    `owner_in_flight` counts every unit in flight per owner, also those of
    jobs that are not contenders (paused, or with nothing left to enqueue).
    `ready(job_id)` is how many units the job can enqueue now (its pending
    units whose needs are done); it is asked once, when the job comes first
    in its owner's order, so jobs that never come up cost nothing.
    """
    # Per owner, a heap of its jobs: (-priority, in flight, created, id).
    queues: dict[str, list[tuple[int, int, datetime, str]]] = {}
    for c in contenders:
        queues.setdefault(c.owner, []).append((-c.priority, c.in_flight, c.created, c.job_id))
    for queue in queues.values():
        heapq.heapify(queue)
    flight = {owner: owner_in_flight.get(owner, 0) for owner in queues}
    left: dict[str, int] = {}  # ready units not yet given, per job asked
    order: list[str] = []
    while len(order) < slots and queues:
        owner = min(queues, key=lambda o: _owner_key(o, flight[o], shares, queues[o][0]))
        queue = queues[owner]
        neg_priority, in_flight, created, job_id = queue[0]
        if job_id not in left:
            left[job_id] = ready(job_id)
        if left[job_id] <= 0:  # nothing ready (a DAG stage waits): out for this tick
            heapq.heappop(queue)
        else:
            left[job_id] -= 1
            order.append(job_id)
            flight[owner] += 1
            heapq.heapreplace(queue, (neg_priority, in_flight + 1, created, job_id))
        if not queue:
            del queues[owner]
    return order


def _owner_key(owner: str, in_flight: int, shares: Mapping[str, float],
               head: tuple[int, int, datetime, str]) -> tuple:
    share = shares.get(owner, DEFAULT_SHARE)
    load = in_flight / share if share > 0 else math.inf
    # Ties (e.g. two idle owners): fewer units first, then the owner whose next
    # job is older, then the name, so the order is deterministic.
    return (load, in_flight, head[2], owner)
