"""Lost workers and worker control, without a broker: the scheduler on a fake
executor (tests/fake_executor.py) for requeue reasons and per-job blocklists,
the embedded service for the /workers and /jobs/{id}/blocklist routes. The
real Celery worker cases (a SIGKILLed worker's unit re-enqueued within a few
heartbeats, a long unit never re-run by lease, a drained worker) are in
tests/test_farm_workers.py."""

from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy import select

from service import blocklist, jobs
from service.access import Principal
from service.db import open_ledger
from service.metrics import PrometheusMetrics
from service.models import Job, WorkerBlock, WorkUnit, utcnow
from service.scheduler import Scheduler
from service.schemas import JobCreate, JobPublic
from service.settings import Settings
from service.store import Store

from conftest import TINY, get_json, poll_job, submit, wait_for
from fake_executor import FakeExecutor

FOUR = dict(TINY, tile_size=16, progressive=False)  # 4 units


@pytest.fixture
def fake_farm(tmp_path):
    """(settings, sessions, executor, scheduler, metrics) on a fake executor of 8 slots."""
    settings = Settings(data_dir=tmp_path / "data", broker_url="", database_url="",
                        worker_failures_per_job=2, max_attempts=5)
    engine, sessions = open_ledger(settings)
    executor = FakeExecutor(slots=8)
    metrics = PrometheusMetrics()
    scheduler = Scheduler(settings, sessions, Store(settings.data_dir), executor, metrics=metrics)
    yield settings, sessions, executor, scheduler, metrics
    engine.dispose()


def _job(settings, sessions) -> str:
    with sessions.begin() as session:
        return jobs.create_job(session, Store(settings.data_dir), settings,
                               Principal("admin", "admin"), JobCreate(**FOUR), utcnow()).id


def _unit(sessions, job_id: str, index: int) -> WorkUnit:
    with sessions() as session:
        return session.scalars(select(WorkUnit).where(WorkUnit.job_id == job_id,
                                                      WorkUnit.index == index)).one()


def _requeued(metrics, reason: str) -> float:
    return metrics.registry.get_sample_value("rayfarm_units_requeued_total", {"reason": reason})


def test01_a_lost_unit_is_enqueued_again_with_its_reason_and_no_attempt_spent(fake_farm):
    settings, sessions, executor, scheduler, metrics = fake_farm
    job_id = _job(settings, sessions)
    scheduler.tick()
    executor.lose(job_id, 1, cause="worker", error="worker w1 lost (no presence heartbeat)")
    executor.lose(job_id, 2, cause="lease", error="no heartbeat for 60 s")
    scheduler.tick()
    one, two = _unit(sessions, job_id, 1), _unit(sessions, job_id, 2)
    assert one.state == "queued" and len(one.task_ids) == 2 and one.attempts == 1
    assert one.requeue_reason == "worker w1 lost (no presence heartbeat)"
    assert two.requeue_reason == "no heartbeat for 60 s" and two.attempts == 1
    assert _unit(sessions, job_id, 0).requeue_reason is None
    # The metrics tell a lost worker from a lapsed lease.
    assert _requeued(metrics, "lost") == 1 and _requeued(metrics, "lease") == 1


def test02_a_worker_failing_n_units_of_a_job_is_blocklisted_for_it(fake_farm):
    settings, sessions, executor, scheduler, _ = fake_farm
    executor.live = ["w1", "w2"]
    job_id = _job(settings, sessions)
    scheduler.tick()
    executor.fail(job_id, 0, "ValueError: bad", worker="w1")
    scheduler.tick()
    assert executor.tickets_of(job_id, 0)[-1].blocked == ()  # one failure: not yet
    executor.fail(job_id, 1, "ValueError: bad", worker="w1")
    scheduler.tick()
    # The second failure (worker_failures_per_job=2) blocklists w1: the retried
    # unit's ticket tells workers so (w1 declines it, another takes it).
    assert executor.tickets_of(job_id, 1)[-1].blocked == ("w1",)
    with sessions() as session:
        assert blocklist.blocked_workers(session, job_id) == ("w1",)
        rows = blocklist.list_blocks(session, job_id)
        assert [(r.worker, r.failures) for r in rows] == [("w1", 2)]
        assert session.get(Job, job_id).status == "running"
    # A decline by the blocklisted worker costs no attempt.
    executor.lose(job_id, 1, cause="declined", error="declined by w1: blocklisted for the job")
    attempts = _unit(sessions, job_id, 1).attempts
    scheduler.tick()
    assert _unit(sessions, job_id, 1).attempts == attempts
    assert _unit(sessions, job_id, 1).requeue_reason.startswith("declined by w1")
    # Cleared by the owner: the next tickets carry no blocklist.
    with sessions.begin() as session:
        blocklist.clear(session, Principal("admin", "admin"), session.get(Job, job_id), "w1")
    executor.lose(job_id, 2, cause="worker", error="worker w9 lost")
    scheduler.tick()
    assert executor.tickets_of(job_id, 2)[-1].blocked == ()


def test03_when_every_live_worker_is_blocklisted_the_job_fails_saying_so(fake_farm):
    settings, sessions, executor, scheduler, _ = fake_farm
    executor.live = ["w1", "w2"]
    executor.disabled = {"w2"}  # a drained worker cannot run it either
    job_id = _job(settings, sessions)
    scheduler.tick()
    executor.fail(job_id, 0, "ValueError: bad", worker="w1")
    executor.fail(job_id, 1, "ValueError: bad", worker="w1")
    scheduler.tick()
    with sessions() as session:
        job = session.get(Job, job_id)
        assert job.status == "failed", job.error
        assert "every live worker is blocklisted for this job (w1)" in job.error


def test04_the_eta_counts_a_unit_left_to_render_however_few_its_samples(tmp_path):
    now = utcnow()
    job = Job(id="j", version=1, created=now, started=now - timedelta(seconds=10),
              status="running", owner="admin", scene="s", scene_hash="h",
              spec={"method": "path", "spp": 4, "depth": 1, "tile_size": 8, "seed": 0,
                    "sampler": "random"}, width=10, height=10, units_total=100, units_done=99,
              samples=396, rays=0, unit_seconds=99 * 5.0, paused_seconds=0.0,
              recent_rate=1000.0, units_retried=0)
    # 4 samples left at 1000 samples/s would say 0.004 s; a unit takes 5 s.
    assert JobPublic.from_job(job, now).progress.eta == pytest.approx(5.0)


def test04b_no_eta_until_a_rate_is_measured_between_two_landings(tmp_path):
    # The first job after a start: its first unit lands after the render
    # processes loaded their kernels (40 s here), then units land every 0.5 s.
    # Counting the first wait said 45 minutes for a job of under a minute.
    start = utcnow()
    job = Job(id="j", version=1, created=start, started=start, status="queued", owner="admin",
              scene="s", scene_hash="h", spec={"method": "path", "spp": 64, "depth": 1,
                                               "tile_size": 8, "seed": 0, "sampler": "random"},
              width=64, height=64, units_total=64, units_done=0, samples=0, rays=0,
              unit_seconds=0.0, paused_seconds=0.0, units_retried=0)
    from service import states

    states.change_job(job, "running", start)
    per_unit = 64 * 64  # samples in a unit
    now = start + timedelta(seconds=40)
    job.units_done, job.samples = 1, per_unit
    job.note_samples(per_unit, now)
    assert job.recent_rate is None and JobPublic.from_job(job, now).progress.eta is None
    for _ in range(3):
        now += timedelta(seconds=0.5)
        job.units_done += 1
        job.samples += per_unit
        job.note_samples(per_unit, now)
    assert job.recent_rate == pytest.approx(per_unit / 0.5)
    eta = JobPublic.from_job(job, now).progress.eta
    assert eta == pytest.approx((64 - 4) * 0.5, rel=1e-6)  # 30 s, not 60 units x 10 s


# -- the HTTP API (embedded service: one local worker) ----------------------------------------

def test05_worker_control_is_for_admins_and_names_a_known_worker(local_client, make_user):
    artist = make_user("wendy")
    name = wait_for(lambda: [w["name"] for w in local_client.get("/workers").json()], 10,
                    "the local worker")[0]
    assert artist.post(f"/workers/{name}/disable").status_code == 403
    assert artist.delete(f"/workers/{name}").status_code == 403
    missing = local_client.post("/workers/nobody@nowhere/disable")
    assert missing.status_code == 404 and "nobody@nowhere" in missing.json()["detail"]
    assert local_client.delete("/workers/nobody@nowhere").status_code == 404
    live = local_client.delete(f"/workers/{name}")  # the embedded pool is live
    assert live.status_code == 409 and "only lost or offline" in live.json()["detail"]
    try:
        disabled = local_client.post(f"/workers/{name}/disable")
        assert disabled.status_code == 200 and disabled.json()["disabled"] is True
        # Drained: a new job's units stay pending, none is sent to the pool.
        job = submit(artist, dict(TINY, progressive=False, tile_size=16))
        get = get_json(local_client)
        wait_for(lambda: get(f"/jobs/{job['id']}")["status"] == "running", 30, "planned")
        for _ in range(5):
            assert {u["state"] for u in get(f"/jobs/{job['id']}/units")} == {"pending"}
            local_client.get("/healthz")  # a few scheduler ticks pass meanwhile
        assert [w["disabled"] for w in get("/workers")] == [True]
    finally:
        enabled = local_client.post(f"/workers/{name}/enable")
    assert enabled.status_code == 200 and enabled.json()["disabled"] is False
    assert poll_job(get, job["id"], 120)["status"] == "done"


def test06_a_jobs_blocklist_is_shown_to_who_sees_it_and_cleared_by_its_owner(
        local_client, local_app, make_user):
    owner, other = make_user("bella"), make_user("bruno")
    job = submit(owner, dict(TINY, progressive=False, tile_size=16))
    with local_app.state.farm.sessions.begin() as session:
        session.add(WorkerBlock(job_id=job["id"], worker="rayfarm-1@node", failures=3,
                                last_error="ValueError: bad", blocked=utcnow()))
    shown = owner.get(f"/jobs/{job['id']}/blocklist")
    assert shown.status_code == 200
    assert [(b["worker"], b["failures"], b["blocked"] is not None) for b in shown.json()] == \
        [("rayfarm-1@node", 3, True)]
    assert local_client.get(f"/jobs/{job['id']}/blocklist").status_code == 200  # an admin
    assert other.get(f"/jobs/{job['id']}/blocklist").status_code == 404  # not theirs
    assert other.delete(f"/jobs/{job['id']}/blocklist/rayfarm-1@node").status_code == 404
    gone = owner.delete(f"/jobs/{job['id']}/blocklist/nobody@x")
    assert gone.status_code == 404 and "nobody@x" in gone.json()["detail"]
    assert owner.delete(f"/jobs/{job['id']}/blocklist/rayfarm-1@node").status_code == 204
    assert owner.get(f"/jobs/{job['id']}/blocklist").json() == []
