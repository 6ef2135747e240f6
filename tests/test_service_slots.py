"""A running unit can be stopped, and no owner holds the render processes.

test01 stops a rendering unit of the local pool; test02/test03 cancel (and
delete) a running job on the embedded service and on a Celery worker, and
the freed process takes the next job's unit; test04 stops a unit over its
time budget (an attempt spent each time, then the job fails), and test08
derives budgets from measured rates; test05-07 drive fair share over the
render processes on a fake executor (who is withdrawn, who is preempted, and
when nobody is); test09/test10 let a newcomer's unit run while another
owner's long units hold every process, on the embedded pool and on Celery,
with the long jobs' images bit-identical to undisturbed renders.

The long units would take minutes if nothing stopped them (the path tracer
takes about 0.42 us a sample at depth 5 on one core of the 2-core machine),
so on code that cannot stop a unit each test times out or sees the other
job finish first; the waits are generous, and no test asserts how fast
anything was (bench/preemption.py measures that).
"""

from __future__ import annotations

import pytest

from conftest import (ADMIN_HEADERS, TINY, assert_bit_identical, channels_of, get_json, poll_job,
                      submit, wait_for)

# One unit of 64 x 64 pixels at 262,144 spp (2^30 samples): about 7 minutes on one core.
LONG = {"scene": "cornell-box", "method": "path", "spp": 262144, "depth": 5, "width": 64,
        "height": 64, "tile_size": 64, "progressive": False}
QUICK = dict(TINY, spp=16, tile_size=32, progressive=False)  # one unit of milliseconds


def rendering(get, job_id: str) -> bool:
    return any(u["state"] == "running" for u in get(f"/jobs/{job_id}/units"))


def embedded(tmp_path, **settings):
    """A TestClient of an embedded service of its own (its pool, its ledger)."""
    from fastapi.testclient import TestClient

    from service.main import create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", broker_url="", database_url="",
                        poll_interval=0.05, **{"local_workers": 1, **settings})
    return TestClient(create_app(settings), headers=ADMIN_HEADERS)


def on_celery(tmp_path, redis_url, **settings):
    """A TestClient of a service on this run's Redis (its workers spawned by the test)."""
    from fastapi.testclient import TestClient

    from service.main import create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05,
                        **settings)
    return TestClient(create_app(settings), headers=ADMIN_HEADERS)


def cancel_frees_the_process(client, delete: bool = False) -> None:
    """A long job renders on the only process; canceling (or deleting) it lets
    the next job (the same owner's: no fair share involved) render within
    seconds, where the long unit would have held the process for minutes."""
    get = get_json(client)
    long_job = submit(client, LONG)["id"]
    wait_for(lambda: rendering(get, long_job), 120, "the long unit rendering")
    quick = submit(client, QUICK)["id"]
    if delete:
        assert client.delete(f"/jobs/{long_job}").status_code == 204
    else:
        assert client.post(f"/jobs/{long_job}/cancel").status_code == 200
    done = poll_job(get, quick, timeout=60)
    assert done["status"] == "done", done
    assert [u["attempts"] for u in get(f"/jobs/{quick}/units")] == [1]


# -- the local pool ----------------------------------------------------------------------

def test01_the_local_pool_stops_a_rendering_unit_and_the_slot_takes_the_next():
    from renderer import (METHODS, LocalPool, PartialFilm, RenderSpec, UnitStopped,
                          resolve_document, scene_text)

    key, text = scene_text(resolve_document("cornell-box"))
    long_spec = RenderSpec(spp=262144, depth=5, width=64, height=64, tile_size=64)
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


def test02_cancel_or_delete_of_a_running_job_frees_the_embedded_process(tmp_path):
    with embedded(tmp_path, local_workers=1) as client:
        cancel_frees_the_process(client)
        cancel_frees_the_process(client, delete=True)
        assert client.get("/workers").json()[0]["running"] == []


@pytest.mark.farm
def test03_cancel_of_a_running_job_frees_the_celery_process(redis_url, spawn_worker, tmp_path):
    import redis

    worker = spawn_worker(concurrency=1)
    with on_celery(tmp_path, redis_url) as client:
        get = get_json(client)
        wait_for(lambda: any(w["state"] == "idle" for w in get("/workers")), 30, "the worker")
        cancel_frees_the_process(client)
        # The killed render process was revoked, not lost: no FAILURE stored, no
        # crash counted, and the worker shows nothing running.
        wait_for(lambda: all(not w["running"] for w in get("/workers")), 30,
                 "the worker's running list to clear")
    broker = redis.Redis.from_url(redis_url)
    log = worker.log()
    assert "WorkerLostError" not in log, log
    assert "Terminating" in log, log
    broker.close()


def test04_a_unit_over_its_time_budget_is_stopped_and_spends_an_attempt(tmp_path):
    # A quick job measures the farm's rate; the long job's unit then has a
    # budget of one second, the floor (with a factor of 1e-4 a rate measured
    # on a loaded machine gave 2 s), and is stopped on each of its two
    # attempts, where it would otherwise render for minutes.
    with embedded(tmp_path, local_workers=1, unit_budget_floor=1.0, unit_budget_factor=1e-5,
                  max_attempts=2) as client:
        get = get_json(client)
        assert poll_job(get, submit(client, QUICK)["id"], timeout=60)["status"] == "done"
        long_job = submit(client, LONG)["id"]
        job = poll_job(get, long_job, timeout=90)
        assert job["status"] == "failed", job
        assert job["error"].startswith("unit 0 failed after 2 attempts: stopped after ")
        assert "over its time budget of 1 s" in job["error"]
        [unit] = get(f"/jobs/{long_job}/units")
        assert unit["attempts"] == 2 and unit["tasks"] == 2
        assert "time budget" in unit["error"]
        # The process it held renders the next job.
        assert poll_job(get, submit(client, QUICK)["id"], timeout=60)["status"] == "done"


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


def test08_budget_rates_come_from_the_job_then_from_the_farm():
    from service.budget import UnitRates, unit_work

    tile = {"kind": "tile", "x0": 0, "y0": 0, "x1": 16, "y1": 16, "sample_start": 0,
            "sample_end": 64}
    assert unit_work(tile) == 16 * 16 * 64
    rates = UnitRates(factor=10.0, floor=30.0)
    assert rates.budget("j", "path", 3, tile) is None  # nothing measured
    rates.note("other", "path", 7, tile, seconds=8.0)  # 1 s per sample and vertex... scaled
    # The farm's rate for path tiles, per vertex: depth 3 expects half of depth 7's time,
    # with four times the margin.
    fallback = rates.budget("j", "path", 3, tile)
    assert fallback.seconds == pytest.approx(40 * 4.0) and "farm" in fallback.basis
    rates.note("j", "path", 3, tile, seconds=2.0)
    own = rates.budget("j", "path", 3, dict(tile, sample_end=256))  # four times the samples
    assert own.seconds == pytest.approx(10 * 8.0) and "job's measured rate" in own.basis
    assert rates.budget("j", "path", 3, dict(tile, sample_end=1)).seconds == 30.0  # the floor
    assert "over its time budget of 80 s" in own.exceeded(95.0)
    rates.keep_only({"other"})
    assert "farm" in rates.budget("j", "path", 3, tile).basis


# -- fair share over the render processes, on the real executors ----------------------------

# Owner a's jobs: one unit each of 32 x 32 pixels at 16,384 spp (about 7 s on
# one core); owner b's: one unit of milliseconds. b's unit takes a process
# within the starved grace (1 s), a's units' half second of `preempt_after`,
# and a new process's warm-up.
HELD = dict(LONG, width=32, height=32, tile_size=32, spp=16384)
NEWCOMER = dict(QUICK, width=16, height=16, tile_size=16)


def newcomer_runs_beside_long_units(client) -> None:
    """Owner a's two one-unit jobs hold both render processes; owner b's job
    renders while they still render (one of a's units preempted: on code that
    cannot preempt, b's unit waits for one of a's to finish), and the preempted
    job's image comes out bit-identical to its undisturbed twin's all the same."""
    from test_service_fairness import submit_as

    get = get_json(client)
    held = [submit_as(client, "a", HELD) for _ in range(2)]
    wait_for(lambda: all(rendering(get, j) for j in held), 120, "a's units rendering")
    newcomer = submit_as(client, "b", NEWCOMER)
    done = poll_job(get, newcomer, timeout=120)
    assert done["status"] == "done", done
    assert [get(f"/jobs/{j}")["status"] for j in held] == ["running", "running"], \
        "the newcomer waited for one of a's units to finish"
    for job_id in held:
        job = poll_job(get, job_id, timeout=240)
        assert job["status"] == "done", job
    units = {j: get(f"/jobs/{j}/units")[0] for j in held}
    assert [u["attempts"] for u in units.values()] == [1, 1]  # preemption spends no attempt
    assert sorted(u["tasks"] for u in units.values()) == [1, 2]  # one of them ran twice
    # The two jobs are one body: the one whose unit ran once is the undisturbed
    # render (the pool's images are the renderer's: test_service_pixels and others).
    preempted, undisturbed = sorted(held, key=lambda j: -units[j]["tasks"])
    store = client.app.state.farm.store
    assert_bit_identical(channels_of(store.result_path(preempted)),
                         channels_of(store.result_path(undisturbed)))


def test09_a_newcomer_renders_beside_long_units_on_the_embedded_pool(tmp_path):
    with embedded(tmp_path, local_workers=2, preempt_after_seconds=0.5) as client:
        newcomer_runs_beside_long_units(client)


@pytest.mark.farm
def test10_a_newcomer_renders_beside_long_units_on_celery(redis_url, spawn_worker, tmp_path):
    worker = spawn_worker(concurrency=2)
    with on_celery(tmp_path, redis_url, preempt_after_seconds=0.5) as client:
        get = get_json(client)
        wait_for(lambda: any(w["state"] == "idle" for w in get("/workers")), 30, "the worker")
        newcomer_runs_beside_long_units(client)
    assert "WorkerLostError" not in worker.log()
