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

Fair share over the render processes (`rebalance`). Choosing the next unit
is not enough when units are long: an owner whose units fill every process
holds the farm for as long as they run, and the executor's queue (a few
units per process, first in, first out) holds more of them ahead of anyone
else's. So each owner active on the farm (rendering, or with a unit it
could start) is entitled to `processes x share / sum of the active owners'
shares` render processes. An owner that wants a unit started and renders
none, or renders at least one fewer than it is entitled to, is *starved*.
While an owner has been starved for a moment (the scheduler's grace: the
ledger notices a unit start a tick late), every other owner that renders at
least its entitlement is *held back*: it gets no new units, and its units
waiting in the executor's queue are withdrawn (back to pending, no attempt
spent), so the starved owner's unit is next in line. If no process is idle,
a unit of an owner that would still render at least its entitlement without
it is *preempted*: stopped and put back to pending, no attempt spent (units
are deterministic: the image stays bit-identical). No thrash: the starved
owner ends at or below its entitlement and the preempted one at or above
its own, so neither can claim from the other again; a unit that has rendered
less than `min_run` seconds is not preempted (short units free their process
on their own); and an owner with nothing to start claims nothing. With one
process and two owners nobody is entitled to a whole process: nothing is
preempted (a unit stopped is rendered again from its start, so taking turns
would finish nothing).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from datetime import datetime
from typing import Callable, Iterable, Mapping

__all__ = ["Contender", "fair_share", "DEFAULT_SHARE", "Holding", "Rebalance", "entitlements",
           "starved", "rebalance"]

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


# -- fair share over the render processes ------------------------------------------------

@dataclass(frozen=True)
class Holding:
    """A unit in flight: rendering for `running_for` seconds, or waiting in the
    executor's queue (`running_for` None)."""

    owner: str
    key: tuple[str, int]  # (job id, unit index)
    running_for: float | None


@dataclass(frozen=True)
class Rebalance:
    """What `rebalance` decided: owners that get no new units this tick, the
    units to put back to pending (withdrawn from the queue, or preempted), and
    for each claimant still starved how many processes it is to get now (an
    idle one, or one preempted for it; 0 if none can be had yet)."""

    held_back: frozenset[str] = frozenset()
    withdraw: tuple[tuple[str, int], ...] = ()
    preempt: tuple[tuple[str, int], ...] = ()
    claimed: Mapping[str, int] = field(default_factory=dict)


def _running(holdings: Iterable[Holding]) -> dict[str, int]:
    running: dict[str, int] = {}
    for h in holdings:
        if h.running_for is not None:
            running[h.owner] = running.get(h.owner, 0) + 1
    return running


def entitlements(running: Mapping[str, int], wanting: Mapping[str, int],
                 shares: Mapping[str, float], processes: int) -> dict[str, float]:
    """The render processes each active owner (rendering, or wanting a unit
    started) is entitled to: `processes` split by share (module doc)."""
    active = {o for o, n in running.items() if n > 0} | {o for o, n in wanting.items() if n > 0}
    weight = {o: max(shares.get(o, DEFAULT_SHARE), 0.0) for o in active}
    total = sum(weight.values())
    if total <= 0:
        return {o: 0.0 for o in active}
    return {o: processes * w / total for o, w in weight.items()}


def _is_starved(running: int, wanting: int, entitled: float) -> bool:
    return wanting > 0 and entitled > 0 and (running == 0 or running + 1 <= entitled)


def starved(holdings: Iterable[Holding], wanting: Mapping[str, int],
            shares: Mapping[str, float], processes: int) -> set[str]:
    """The owners that want a unit started (`wanting`: ready units plus
    their units waiting in the queue) and render none, or at least one fewer
    than they are entitled to."""
    running = _running(holdings)
    entitled = entitlements(running, wanting, shares, processes)
    return {o for o in entitled
            if _is_starved(running.get(o, 0), wanting.get(o, 0), entitled[o])}


def rebalance(holdings: Iterable[Holding], wanting: Mapping[str, int],
              shares: Mapping[str, float], processes: int, claimants: Iterable[str],
              min_run: float) -> Rebalance:
    """Make room for the `claimants` (starved owners whose grace is over):
    hold back every other owner rendering at least its entitlement and
    withdraw its queued units; then, for each claimant (most starved first)
    and each unit it wants started, take an idle process, or else preempt the
    unit that rendered least (but at least `min_run` seconds) of the owner
    most over its share that would stay at or above its entitlement.

        rebalance([Holding("a", ("j1", 0), 30.0), Holding("a", ("j2", 0), 30.0)],
                  {"b": 1}, {}, processes=2, claimants={"b"}, min_run=2.0)
        # -> held_back {"a"}, preempt (("j1", 0),) or (("j2", 0),): one process each
    """
    holdings = list(holdings)
    running = _running(holdings)
    entitled = entitlements(running, wanting, shares, processes)
    claimants = [o for o in claimants
                 if _is_starved(running.get(o, 0), wanting.get(o, 0), entitled.get(o, 0.0))]
    if not claimants:
        return Rebalance()
    held_back = frozenset(o for o, n in running.items()
                          if o not in claimants and n >= entitled.get(o, 0.0))
    withdraw = tuple(h.key for h in holdings if h.owner in held_back and h.running_for is None)
    # Preemptable units per owner, the one that rendered least first.
    victims: dict[str, list[Holding]] = {}
    for h in sorted((h for h in holdings if h.running_for is not None
                     and h.running_for >= min_run), key=lambda h: (h.running_for, h.key)):
        victims.setdefault(h.owner, []).append(h)
    idle = max(processes - sum(running.values()), 0)
    preempt: list[tuple[str, int]] = []
    claimed = dict.fromkeys(claimants, 0)

    def load(owner: str) -> tuple:
        share = shares.get(owner, DEFAULT_SHARE)
        return (running.get(owner, 0) / share if share > 0 else math.inf,
                running.get(owner, 0), owner)

    for claimant in sorted(claimants, key=load):
        want = wanting.get(claimant, 0)
        while want > 0 and _is_starved(running.get(claimant, 0), want, entitled[claimant]):
            if idle > 0:
                idle -= 1
            else:
                over = [o for o, units in victims.items() if units and o != claimant
                        and running.get(o, 0) - 1 >= entitled.get(o, 0.0)]
                if not over:
                    break
                victim = max(over, key=load)
                preempt.append(victims[victim].pop(0).key)
                running[victim] -= 1
            running[claimant] = running.get(claimant, 0) + 1
            claimed[claimant] += 1
            want -= 1
    return Rebalance(held_back, withdraw, tuple(preempt), claimed)
