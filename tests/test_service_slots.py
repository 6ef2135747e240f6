"""A running unit can be stopped, and no owner holds the render processes.

test01 stops a rendering unit of the local pool; test02/test03 cancel a
running job on the embedded service and on a Celery worker, and the freed
process takes the next job's unit; test04 stops a unit over its time budget
(an attempt spent each time, then the job fails); test05-07 drive fair share
over the render processes on a fake executor (who is withdrawn, who is
preempted, and when nobody is); test08/test09 let a newcomer's unit run
while another owner's long units hold every process, on the embedded pool
and on Celery, with both images bit-identical to undisturbed renders.

The long units would take minutes if nothing stopped them (about 3.5 us a
sample on the 2-core machine, where 64 x 64 pixels at 32,768 spp took 465 s),
so on code that cannot stop a unit each test times out; the waits are
generous, and no test asserts how fast anything was (bench/preemption.py
measures that).
"""

from __future__ import annotations

import pytest

from conftest import wait_for

# One unit of 64 x 64 pixels at 16,384 spp: minutes on one core.
LONG = {"scene": "cornell-box", "method": "path", "spp": 16384, "depth": 3, "width": 64,
        "height": 64, "tile_size": 64, "progressive": False}


# -- the local pool ----------------------------------------------------------------------

def test01_the_local_pool_stops_a_rendering_unit_and_the_slot_takes_the_next():
    from renderer import (METHODS, LocalPool, PartialFilm, RenderSpec, UnitStopped,
                          resolve_document, scene_text)

    key, text = scene_text(resolve_document("cornell-box"))
    long_spec = RenderSpec(spp=16384, depth=3, width=64, height=64, tile_size=64)
    long_unit = METHODS["path"].make_plan(long_spec, False)[0].to_dict()
    small = RenderSpec(spp=4, depth=1, width=8, height=8, tile_size=8)
    small_unit = METHODS["path"].make_plan(small, False)[0].to_dict()
    with LocalPool(1) as pool:
        victim = pool.submit(key, text, long_spec.to_dict(), long_unit, tag=1)
        waiting = pool.submit(key, text, long_spec.to_dict(), long_unit, tag=2)
        after = pool.submit(key, text, small.to_dict(), small_unit, tag=3)
        wait_for(lambda: pool.rendering() == [1], 120, "the long unit rendering")
        assert pool.stop(2)  # still waiting: dropped
        assert waiting.cancelled()
        assert pool.stop(1)  # rendering: its process is killed
        with pytest.raises(UnitStopped):
            victim.result(30)
        # The slot starts a new process and renders the next unit (minutes
        # behind the long unit if it had not been stopped).
        assert PartialFilm.from_bytes(after.result(60)).stats["samples"] == 8 * 8 * 4
        assert not pool.stop(1) and not pool.stop(99)  # nothing has those tags now


# -- fair share over the render processes, on a fake executor --------------------------------

# 64 units of an 8x8-pixel tile (nothing renders them here), and one unit.
WIDE = {"scene": "cornell-box", "method": "path", "spp": 4, "depth": 1, "width": 64,
        "height": 64, "tile_size": 8, "progressive": False}
ONE = dict(WIDE, width=8, height=8)


class Farm:
    """A ledger and a scheduler on a fake executor (tests/fake_executor.py) of
    `slots` units in flight and `processes` render processes, on a clock the
    test moves (`later`)."""

    def __init__(self, tmp_path, slots: int, processes: int, **settings):
        from datetime import timedelta

        from fake_executor import FakeExecutor
        from service.db import open_ledger
        from service.models import utcnow
        from service.scheduler import Scheduler
        from service.settings import Settings
        from service.store import Store

        self.settings = Settings(data_dir=tmp_path / "data", broker_url="", database_url="",
                                 **settings)
        self.engine, self.sessions = open_ledger(self.settings)
        self.store = Store(self.settings.data_dir)
        self.executor = FakeExecutor(slots)
        self.executor.processes = processes
        self.now = utcnow()
        self.scheduler = Scheduler(self.settings, self.sessions, self.store, self.executor,
                                   clock=lambda: self.now)
        self.timedelta = timedelta

    def later(self, seconds: float) -> None:
        self.now += self.timedelta(seconds=seconds)

    def job(self, owner: str, body: dict) -> str:
        from service import jobs
        from service.access import Principal
        from service.schemas import JobCreate

        with self.sessions.begin() as session:
            return jobs.create_job(session, self.store, self.settings, Principal(owner, "admin"),
                                   JobCreate(**body), self.now).id

    def units(self, job_id: str):
        from sqlalchemy import select

        from service.models import WorkUnit

        with self.sessions() as session:
            return list(session.scalars(select(WorkUnit).where(WorkUnit.job_id == job_id)
                                        .order_by(WorkUnit.index)))

    def states(self, job_id: str) -> dict[str, int]:
        from collections import Counter

        return dict(Counter(u.state for u in self.units(job_id)))

    def tick(self) -> None:
        self.scheduler.tick()


@pytest.fixture
def fake_farm(tmp_path):
    made = []

    def make(slots: int = 6, processes: int = 2, **settings) -> Farm:
        made.append(Farm(tmp_path / str(len(made)), slots, processes, **settings))
        return made[-1]
    yield make
    for farm in made:
        farm.engine.dispose()


def test05_a_starved_owner_gets_a_process_by_withdrawal_and_preemption(fake_farm):
    farm = fake_farm(slots=6, processes=2)
    big = farm.job("a", WIDE)
    farm.tick()  # 6 of a's units in flight, two of them rendering
    farm.executor.start(big, 0)
    farm.executor.start(big, 1)
    farm.tick()
    assert farm.states(big) == {"running": 2, "queued": 4, "pending": 58}
    farm.later(10)
    small = farm.job("b", ONE)
    farm.tick()  # b starved, but only just: nothing happens yet
    assert farm.states(small) == {"pending": 1} and farm.executor.stopped == []
    farm.later(2)
    farm.tick()
    # a is held back: its queued units withdrawn, one of its two rendering units
    # preempted (back to pending, no attempt spent), b's unit enqueued.
    units = farm.units(big)
    assert farm.states(big) == {"running": 1, "pending": 63}
    preempted = [u for u in units[:2] if u.state == "pending"]
    assert len(preempted) == 1 and preempted[0].attempts == 1
    assert preempted[0].requeue_reason.startswith("preempted")
    assert all(u.requeue_reason.startswith("withdrawn") for u in units[2:6])
    assert len(farm.executor.stopped) == 5
    assert farm.states(small) == {"queued": 1}
    # While b's unit waits for the freed process, nothing more is stopped and
    # a gets nothing new; once it renders, a fills the queue again.
    farm.later(1)
    farm.tick()
    assert len(farm.executor.stopped) == 5 and farm.states(big) == {"running": 1, "pending": 63}
    farm.executor.start(small, 0)
    farm.later(1)
    farm.tick()
    assert farm.states(big) == {"running": 1, "queued": 4, "pending": 59}
    # No thrash: b holds its one process, a the other, however long they render.
    for _ in range(5):
        farm.later(30)
        farm.tick()
    assert len(farm.executor.stopped) == 5
    # The preempted unit runs again later, as the same attempt.
    for _ in range(20):
        for job_id in (big, small):
            for unit in farm.units(job_id):
                if unit.state in ("queued", "running"):
                    farm.executor.finish(job_id, unit.index)
        farm.tick()
    assert farm.states(big) == {"done": 64} and farm.states(small) == {"done": 1}
    again = farm.units(big)[preempted[0].index]
    assert again.attempts == 1 and len(again.task_ids) == 2


def test06_nothing_is_preempted_for_nothing_ready_from_short_units_or_on_one_process(fake_farm):
    # b's only job is paused: b wants nothing started, so a keeps everything.
    farm = fake_farm(slots=6, processes=2)
    big = farm.job("a", WIDE)
    paused = farm.job("b", ONE)
    from service import jobs
    from service.access import SYSTEM

    with farm.sessions.begin() as session:
        jobs.pause_job(session, SYSTEM, paused, farm.now)
    farm.tick()
    farm.executor.start(big, 0)
    farm.executor.start(big, 1)
    for _ in range(3):
        farm.later(10)
        farm.tick()
    assert farm.executor.stopped == [] and farm.states(big)["queued"] == 4

    # a's units have rendered for less than preempt_after_seconds: withdrawn
    # from the queue, but not preempted until they have.
    farm = fake_farm(slots=6, processes=2, preempt_after_seconds=5.0)
    big = farm.job("a", WIDE)
    farm.tick()
    farm.executor.start(big, 0)
    farm.executor.start(big, 1)
    farm.tick()
    small = farm.job("b", ONE)
    farm.later(1.5)
    farm.tick()
    farm.later(1.5)
    farm.tick()
    assert farm.states(big) == {"running": 2, "pending": 62} and len(farm.executor.stopped) == 4
    farm.later(2.5)
    farm.tick()
    assert farm.states(big) == {"running": 1, "pending": 63} and len(farm.executor.stopped) == 5

    # One process and two owners: nobody is entitled to a whole process, so
    # nothing is preempted (taking turns from the start would finish nothing).
    farm = fake_farm(slots=3, processes=1)
    big = farm.job("a", WIDE)
    farm.tick()
    farm.executor.start(big, 0)
    farm.tick()
    small = farm.job("b", ONE)
    for _ in range(4):
        farm.later(10)
        farm.tick()
    assert farm.states(big)["running"] == 1
    assert farm.units(big)[0].state == "running"


def test07_rebalance_splits_processes_by_share():
    from service.fairshare import Holding, rebalance, starved

    held = [Holding("a", ("ja", i), 60.0 + i) for i in range(4)]
    # b (share 3) is entitled to 3 of 4 processes: three of a's units go, the
    # ones that rendered least first; a keeps its one.
    assert starved(held, {"b": 5}, {"b": 3.0}, 4) == {"b"}
    plan = rebalance(held, {"b": 5}, {"b": 3.0}, 4, {"b"}, min_run=2.0)
    assert plan.held_back == {"a"} and plan.preempt == (("ja", 0), ("ja", 1), ("ja", 2))
    assert plan.claimed == {"b": 3}
    # b wants only one unit: one process, not three.
    assert rebalance(held, {"b": 1}, {"b": 3.0}, 4, {"b"}, 2.0).preempt == (("ja", 0),)
    # Equal shares, three owners on two processes: c gets one of a's; b (at its
    # share already) gives nothing, and c cannot take b's either.
    held = [Holding("a", ("ja", 0), 9.0), Holding("a", ("ja", 1), 8.0),
            Holding("a", ("ja", 2), None)]
    plan = rebalance(held, {"a": 1, "c": 1}, {}, 2, {"c"}, 2.0)
    assert plan.preempt == (("ja", 1),) and plan.withdraw == (("ja", 2),)
    held = [Holding("a", ("ja", 0), 9.0), Holding("b", ("jb", 0), 9.0)]
    assert rebalance(held, {"c": 1}, {}, 2, {"c"}, 2.0).preempt == ()
