"""Crashes count: a unit whose render process dies spends an attempt and fails
its job after `max_attempts`, on both executors, without disturbing other
jobs; and render processes die with the service that started them.

The poison unit is deliberate: a render process whose environment holds
`RAYFARM_TEST_CRASH_SEED` kills itself with SIGSEGV on every unit of a job
with that seed (renderer/runtime.py). Only the processes these tests start
get it; no request can set it.
"""

from __future__ import annotations

import os
import re
import signal
import time
from collections import Counter
from pathlib import Path

import pytest
from sqlalchemy import select

from renderer.runtime import CRASH_SEED_ENV
from service import jobs
from service.access import SYSTEM
from service.executors import Observation
from service.farm import Farm
from service.models import Job, WorkUnit, utcnow
from service.schemas import JobCreate
from service.settings import Settings

from conftest import (ADMIN_HEADERS, TINY, assert_bit_identical, channels_of, embedded_env,
                      get_json, poll_job, start_serve, wait_for)
from fake_executor import FakeExecutor

CRASH_SEED = 660013  # no other test renders with this seed
SEGFAULT = "render process died with SIGSEGV"
POISON = dict(TINY, seed=CRASH_SEED, tile_size=32, progressive=False)  # one unit
HEALTHY = dict(TINY, progressive=False)  # 16 units


def create(sessions, store, settings, body: dict) -> str:
    with sessions.begin() as session:
        return jobs.create_job(session, store, settings, SYSTEM, JobCreate(**body), utcnow()).id


def rows(sessions, job_id: str) -> tuple[Job, list[WorkUnit]]:
    with sessions() as session:
        return session.get(Job, job_id), list(session.scalars(
            select(WorkUnit).where(WorkUnit.job_id == job_id).order_by(WorkUnit.index)))


# -- the scheduler's rule, on a fake executor ----------------------------------------------

class CrashingExecutor(FakeExecutor):
    """Every task of the units in `crash` dies under them; the first task of
    the units in `lose` is lost (as when the service restarted)."""

    def __init__(self, slots: int, crash: set[int], lose: set[int]):
        super().__init__(slots)
        self.crash, self.lose = crash, lose
        self._reported: set[str] = set()

    def observe(self, flights, now):
        out = super().observe(flights, now)
        for i, flight in enumerate(flights):
            latest = flight.task_ids[-1]
            if latest in self._reported:
                continue
            if flight.index in self.crash:
                out[i] = Observation("crashed", error=SEGFAULT, worker="fake")
            elif flight.index in self.lose:
                self.lose.discard(flight.index)
                out[i] = Observation("lost")
            else:
                continue
            self._reported.add(latest)
        return out


def test01_a_crash_spends_an_attempt_and_a_lost_unit_does_not(tmp_path):
    from service.db import open_ledger
    from service.metrics import PrometheusMetrics
    from service.scheduler import Scheduler
    from service.store import Store

    settings = Settings(data_dir=tmp_path / "data", broker_url="", database_url="",
                        max_attempts=3)
    engine, sessions = open_ledger(settings)
    store = Store(settings.data_dir)
    executor = CrashingExecutor(slots=4, crash={0}, lose={1})
    metrics = PrometheusMetrics()
    scheduler = Scheduler(settings, sessions, store, executor, metrics=metrics)
    try:
        job_id = create(sessions, store, settings, HEALTHY)
        for _ in range(10):
            scheduler.tick()
            if rows(sessions, job_id)[0].status == "failed":
                break
        job, units = rows(sessions, job_id)
        assert job.status == "failed"
        assert job.error == f"unit 0: {SEGFAULT} on 3 attempts"
        assert units[0].state == "failed" and units[0].error == SEGFAULT
        assert units[0].attempts == 3 and len(units[0].task_ids) == 3
        # The lost unit was enqueued again without spending an attempt.
        assert units[1].attempts == 1 and len(units[1].task_ids) == 2
        get = metrics.registry.get_sample_value
        assert get("rayfarm_units_requeued_total", {"reason": "crash"}) == 2
        assert get("rayfarm_units_requeued_total", {"reason": "lost"}) == 1
        assert get("rayfarm_units_requeued_total", {"reason": "failed"}) == 0
    finally:
        engine.dispose()


# -- the embedded pool ---------------------------------------------------------------------

def test02_a_killed_render_process_fails_only_its_unit_and_is_replaced():
    from renderer import (METHODS, LocalPool, PartialFilm, RenderProcessDied, RenderSpec,
                          resolve_document, scene_text)

    key, text = scene_text(resolve_document("cornell-box"))
    spec = RenderSpec(spp=2048, depth=3, width=32, height=32, tile_size=32)  # ~seconds a unit
    unit = METHODS["path"].make_plan(spec, False)[0].to_dict()
    with LocalPool(2) as pool:
        victim = pool.submit(key, text, spec.to_dict(), unit, tag=1)
        bystander = pool.submit(key, text, spec.to_dict(), unit, tag=2)
        wait_for(lambda: sorted(pool.rendering()) == [1, 2], 120, "both units rendering")
        before = pool.pids()
        victim_pid = pool._processes[pool._rendering.index(1)].process.pid
        os.kill(victim_pid, signal.SIGKILL)
        with pytest.raises(RenderProcessDied, match="render process died with SIGKILL") as died:
            victim.result(60)
        assert died.value.exitcode == -signal.SIGKILL
        assert len(bystander.result(120)) > 0  # its process rendered on, undisturbed
        assert PartialFilm.from_bytes(bystander.result()).stats["samples"] == 32 * 32 * 2048
        small = RenderSpec(spp=1, depth=1, width=8, height=8, tile_size=8)
        again = pool.submit(key, text, small.to_dict(),
                            METHODS["path"].make_plan(small, False)[0].to_dict())
        assert PartialFilm.from_bytes(again.result(120)).stats["samples"] == 8 * 8
        # The replacement shows in pids() once warmed up (it loads every kernel),
        # which `again`, rendered by the other process, need not wait for.
        wait_for(lambda: victim_pid not in pool.pids() and len(pool.pids()) == 2, 120,
                 "the killed process's replacement to be ready")
        assert set(before) - {victim_pid} <= set(pool.pids())


def test03_embedded_poison_unit_fails_its_job_and_disturbs_no_other(
        tmp_path, monkeypatch, reference_channels):
    # Set before the pool starts: its render processes inherit it.
    monkeypatch.setenv(CRASH_SEED_ENV, str(CRASH_SEED))
    settings = Settings(data_dir=tmp_path / "data", broker_url="", database_url="",
                        local_workers=2, poll_interval=0.05, max_attempts=3)
    started = time.monotonic()
    with Farm.open(settings) as farm:
        poison = create(farm.sessions, farm.store, settings, POISON)
        healthy = create(farm.sessions, farm.store, settings, HEALTHY)

        def both_final():
            farm.scheduler.tick()
            return all(rows(farm.sessions, j)[0].status in ("done", "failed", "canceled")
                       for j in (poison, healthy))
        wait_for(both_final, 240, "both jobs to finish", interval=0.02)
        job, units = rows(farm.sessions, poison)
        assert job.status == "failed", job.error
        assert job.error == f"unit 0: {SEGFAULT} on 3 attempts"
        assert len(units) == 1 and units[0].attempts == 3 and len(units[0].task_ids) == 3
        job, units = rows(farm.sessions, healthy)
        assert job.status == "done" and job.units_done == 16
        assert (job.units_retried or 0) == 0  # no unit of it rendered twice
        assert all(len(u.task_ids) == 1 and u.attempts == 1 for u in units)
        assert_bit_identical(channels_of(farm.store.result_path(healthy)),
                             reference_channels(HEALTHY))
    assert time.monotonic() - started < 240


# -- the real farm ---------------------------------------------------------------------------

@pytest.mark.farm
def test04_celery_poison_unit_fails_its_job_without_redelivery(
        redis_url, spawn_worker, tmp_path, reference_channels):
    from fastapi.testclient import TestClient

    from service.main import create_app

    worker = spawn_worker(concurrency=2, **{CRASH_SEED_ENV: str(CRASH_SEED)})
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05,
                        unit_lease_seconds=30, max_attempts=3)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        poison = client.post("/jobs", json=POISON).json()["id"]
        healthy = client.post("/jobs", json=HEALTHY).json()["id"]
        job = poll_job(get, poison, timeout=240)
        assert job["status"] == "failed", job
        assert job["error"] == f"unit 0: {SEGFAULT} on 3 attempts"
        [unit] = get(f"/jobs/{poison}/units")
        assert unit["attempts"] == 3 and unit["tasks"] == 3 and unit["error"] == SEGFAULT
        done = poll_job(get, healthy, timeout=240)
        assert done["status"] == "done", done
        assert all(u["attempts"] == 1 and u["tasks"] == 1 for u in get(f"/jobs/{healthy}/units"))
        (tmp_path / "healthy.exr").write_bytes(client.get(done["result_url"]).content)
        # Three render processes died, and the broker redelivered none of their
        # messages (a redelivery is received again under the same task id).
        log = worker.log()
        assert log.count("exited with 'signal 11 (SIGSEGV)'") == 3, log
        received = Counter(re.findall(r"Task rayfarm\.render_unit\[([0-9a-f]{32})\] received", log))
        assert received and max(received.values()) == 1, received
        # The worker's page does not show the dead processes' unit as running.
        workers = client.get("/workers").json()
        mine = [w for w in workers if w["name"].startswith(f"rayfarm-{worker.pid}@")]
        assert mine and not [r for w in mine for r in w["running"] if r["job_id"] == poison]
    assert_bit_identical(channels_of(tmp_path / "healthy.exr"), reference_channels(HEALTHY))


# -- render processes die with their service -------------------------------------------------

def descendants(pid: int) -> set[int]:
    """Every process below `pid`, read from /proc (children of children too)."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has died; only its parent's wait is missing


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads processes from /proc")
def test05_a_sigkilled_embedded_service_leaves_no_render_process(tmp_path):
    child, base = start_serve(embedded_env(tmp_path / "data"), tmp_path / "serve.log")
    try:
        import httpx

        with httpx.Client(base_url=base, headers=ADMIN_HEADERS, timeout=10) as client:
            # Long units: the render processes are inside a kernel when the service dies.
            body = dict(TINY, spp=4096, tile_size=16, progressive=False)
            job_id = client.post("/jobs", json=body).json()["id"]
            wait_for(lambda: any(u["state"] == "running"
                                 for u in client.get(f"/jobs/{job_id}/units").json()),
                     120, "a unit rendering")
        below = descendants(child.pid)
        assert len(below) >= 2, below  # two render processes (and a resource tracker)
        os.kill(child.pid, signal.SIGKILL)  # the service alone, not its process group
        child.proc.wait(10)
        wait_for(lambda: not [p for p in below if alive(p)], 10,
                 f"the service's processes {sorted(below)} to die with it")
    finally:
        child.stop()
