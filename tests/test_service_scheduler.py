"""The scheduler driven tick by tick on the embedded executor: retries,
exactly-once completion, restart recovery, cancel. Real pool, real ledger."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.orm.exc import StaleDataError

from service.access import SYSTEM
from service import jobs, states
from service.executors import Ticket
from service.farm import Farm
from service.models import Job, WorkUnit, utcnow
from service.schemas import JobCreate
from service.settings import Settings

from conftest import TINY, assert_bit_identical, channels_of, planned_units, wait_for


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request, tmp_path):
    """The ledger on SQLite (the default) and on PostgreSQL (a fresh database
    of the test run's own server, `postgres_url`)."""
    common = dict(data_dir=tmp_path / "data", broker_url="", local_workers=2,
                  poll_interval=0.05)
    if request.param == "sqlite":
        return Settings(database_url="", **common)
    return Settings(database_url=request.getfixturevalue("postgres_url"), **common)


def create(farm: Farm, body: dict) -> str:
    with farm.sessions.begin() as session:
        return jobs.create_job(session, farm.store, farm.settings, SYSTEM, JobCreate(**body), utcnow()).id


def job_row(farm: Farm, job_id: str) -> Job:
    with farm.sessions() as session:
        return session.get(Job, job_id)


def unit_rows(farm: Farm, job_id: str) -> list[WorkUnit]:
    with farm.sessions() as session:
        return list(session.scalars(select(WorkUnit).where(WorkUnit.job_id == job_id)
                                    .order_by(WorkUnit.index)))


def tick_until(farm: Farm, predicate, timeout: float = 300.0, what: str = "the job"):
    def step():
        farm.scheduler.tick()
        return predicate()
    return wait_for(step, timeout, what, interval=0.02)


def finished(farm: Farm, job_id: str):
    return lambda: job_row(farm, job_id).status in ("done", "failed", "canceled")


def test01_a_unit_that_raises_is_tried_three_times_then_the_job_fails(settings):
    with Farm.open(settings) as farm:
        job_id = create(farm, TINY)
        scene_file = farm.store.scene_path(job_row(farm, job_id).scene_hash)
        scene_file.write_text(scene_file.read_text().replace("cornell-box", "tampered", 1))
        tick_until(farm, finished(farm, job_id))
        job = job_row(farm, job_id)
        assert job.status == "failed"
        assert "failed after 3 attempts" in job.error
        assert "does not match its hash" in job.error  # the renderer's own words
        units = unit_rows(farm, job_id)
        failed = [u for u in units if u.state == "failed"]
        assert len(failed) == 1 and failed[0].attempts == 3 and len(failed[0].task_ids) == 3
        assert all(u.state in ("failed", "canceled") for u in units)
        assert not farm.store.result_path(job_id).exists()


def test02_a_unit_completing_twice_is_counted_once(settings, reference_channels):
    with Farm.open(settings) as farm:
        job_id = create(farm, TINY)
        farm.scheduler.tick()  # plans and enqueues the first units
        with farm.sessions.begin() as session:
            unit = session.scalars(select(WorkUnit).where(WorkUnit.job_id == job_id,
                                                          WorkUnit.state == "queued")).first()
            job = session.get(Job, job_id)
            # A second delivery of the same unit (as after a redelivered message).
            duplicate = farm.executor.submit(Ticket(job_id, unit.index, job.scene_hash,
                                                    job.spec, unit.unit))
            unit.task_ids = [*unit.task_ids, duplicate]
            index = unit.index
        tick_until(farm, finished(farm, job_id))
        job = job_row(farm, job_id)
        assert job.status == "done"
        assert job.units_done == job.units_total == planned_units(TINY)  # 3 passes, a unit each
        assert job.samples == 32 * 32 * 4, "a duplicate result was counted"
        assert unit_rows(farm, job_id)[index].state == "done"
        assert_bit_identical(channels_of(farm.store.result_path(job_id)),
                             reference_channels(TINY))


def test03_restarted_service_resumes_from_the_ledger(settings, reference_channels):
    body = dict(TINY, tile_size=4, progressive=False)  # 64 units
    with Farm.open(settings) as farm:
        job_id = create(farm, body)
        def mid_job():
            units = unit_rows(farm, job_id)
            return any(u.state == "done" for u in units) and \
                [u for u in units if u.state in ("queued", "running")]
        in_flight = tick_until(farm, mid_job, what="some units done, some in flight")
        assert job_row(farm, job_id).units_done < 64
    # A new service process: new pool, the same database and data directory.
    with Farm.open(settings) as farm:
        tick_until(farm, finished(farm, job_id))
        job = job_row(farm, job_id)
        assert job.status == "done" and job.units_done == 64
        assert job.samples == 32 * 32 * 4
        # Units in flight at the restart were enqueued again, attempts unchanged.
        again = {u.index: u for u in unit_rows(farm, job_id)}
        for unit in in_flight:
            assert len(again[unit.index].task_ids) > len(unit.task_ids)
            assert again[unit.index].attempts == unit.attempts
        assert_bit_identical(channels_of(farm.store.result_path(job_id)), reference_channels(body))


def test04_cancel_stops_enqueuing_and_cancels_the_units(settings):
    body = dict(TINY, width=128, height=128, spp=64, tile_size=4, progressive=False)  # 1024 units
    with Farm.open(settings) as farm:
        job_id = create(farm, body)
        farm.scheduler.tick()
        before = {u.index: list(u.task_ids) for u in unit_rows(farm, job_id)}
        enqueued = sum(1 for ids in before.values() if ids)
        assert 0 < enqueued <= farm.executor.limit()
        canceled = jobs.cancel_job_retrying(farm.sessions, SYSTEM, job_id, utcnow)
        assert canceled.status == "canceled"
        for _ in range(5):
            farm.scheduler.tick()
        units = unit_rows(farm, job_id)
        assert {u.index: list(u.task_ids) for u in units} == before, "enqueued after cancel"
        assert {u.state for u in units} <= {"canceled", "done"}
        assert sum(u.state == "canceled" for u in units) >= 1024 - enqueued
        assert farm.scheduler._tracked == {}  # every task of the job was canceled
        assert job_row(farm, job_id).status == "canceled"


def test05_data_stays_inside_data_dir(settings):
    with Farm.open(settings) as farm:
        job_id = create(farm, TINY)
        tick_until(farm, finished(farm, job_id))
        root = Path(settings.data_dir).resolve()
        files = {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}
        assert f"jobs/{job_id}/result.exr" in files and f"jobs/{job_id}/preview.png" in files
        assert {f"jobs/{job_id}/units/{i}.film" for i in range(planned_units(TINY))} <= files
        assert f"store/scenes/{job_row(farm, job_id).scene_hash}.json" in files
        assert not [f for f in files if f.endswith((".tmp", ".part"))]
        with pytest.raises(ValueError):
            farm.store.unit_path("../../etc", 0)


def test06_a_write_based_on_a_stale_read_fails_instead_of_overwriting(settings):
    with Farm.open(settings) as farm:
        job_id = create(farm, TINY)
        farm.scheduler.tick()
        session = farm.sessions()
        stale = session.get(Job, job_id)  # e.g. the scheduler, about to mark it done
        assert stale.status == "running"
        jobs.cancel_job_retrying(farm.sessions, SYSTEM, job_id, utcnow)  # the API, meanwhile
        states.change_job(stale, "done", utcnow())
        with pytest.raises(StaleDataError):
            session.commit()
        session.close()
        assert job_row(farm, job_id).status == "canceled"
