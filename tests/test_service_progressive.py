"""Progressive jobs, priorities, pause/resume, retry and requeue: over the API
(embedded service) and, where order must be deterministic, tick by tick."""

from __future__ import annotations

import io
import time

import pytest
from PIL import Image
from sqlalchemy import select

from service.access import SYSTEM
from service import jobs
from service.farm import Farm
from service.models import Job, WorkUnit, utcnow
from service.schemas import JobCreate
from service.settings import Settings

from conftest import (TINY, assert_bit_identical, assert_complete_progress, channels_of, get_json,
                      planned_units, poll_job, submit, wait_for)




def post(client, path: str, expect: int = 200) -> dict:
    response = client.post(path)
    assert response.status_code == expect, response.text
    return response.json()


def download(client, job: dict, path):
    response = client.get(job["result_url"])
    assert response.status_code == 200
    path.write_bytes(response.content)
    return channels_of(path)


@pytest.mark.parametrize("body", [dict(TINY, spp=8),
                                  dict(TINY, method="path-onesample", sampler="sobol", spp=16,
                                       tile_size=16)])
def test01_progressive_exr_is_bit_identical_to_the_single_pass_one(local_client, tmp_path, body,
                                                                   reference_channels):
    get = get_json(local_client)
    progressive = submit(local_client, body)  # the default
    single = submit(local_client, dict(body, progressive=False))
    assert progressive["progressive"] is True and single["progressive"] is False
    progressive, single = poll_job(get, progressive["id"]), poll_job(get, single["id"])
    assert progressive["status"] == single["status"] == "done"
    # passes of 2, 2, 4 (or 4, 4, 8) spp, each one unit: their tiles hold few samples
    assert progressive["progress"]["units_total"] == planned_units(body) == 3
    assert single["progress"]["units_total"] == planned_units(dict(body, progressive=False)) > 3
    passes = [u["region"]["pass"] for u in get(f"/jobs/{progressive['id']}/units")]
    assert passes == [0, 1, 2]
    assert progressive["samples"] == single["samples"]
    a = download(local_client, progressive, tmp_path / "progressive.exr")
    b = download(local_client, single, tmp_path / "single.exr")
    assert_bit_identical(a, b)
    assert_bit_identical(a, reference_channels(body))


def test01b_a_progressive_job_logs_its_convergence_pass_by_pass(local_client, tmp_path):
    """Each complete pass goes into the job's `passes`: the spp it reached, the
    samples so far, and the error statistic of the passes so far merged in
    unit order, which falls as the passes add samples; the last is the
    result's (its EXR header's rel_error). A one-pass job logs nothing."""
    from renderer import read_exr

    body = dict(TINY, width=64, height=64, spp=64, tile_size=16)
    job = poll_job(get_json(local_client), submit(local_client, body)["id"])
    passes = job["passes"]
    spps = [u["region"]["sample_end"] for u in local_client.get(f"/jobs/{job['id']}/units").json()]
    assert [p["spp"] for p in passes] == sorted(set(spps)) and passes[-1]["spp"] == 64
    assert [p["pass"] for p in passes] == list(range(len(passes))) and len(passes) >= 3
    assert all(a["samples"] < b["samples"] for a, b in zip(passes, passes[1:]))
    assert passes[-1]["samples"] == job["samples"] == 64 * 64 * 64
    errors = [p["rel_error"] for p in passes if p["rel_error"] is not None]
    assert len(errors) >= 2 and errors[-1] < errors[0]
    (tmp_path / "job.exr").write_bytes(local_client.get(job["result_url"]).content)
    header = read_exr(tmp_path / "job.exr")[1]
    assert header["rayfarm.rel_error"] == pytest.approx(errors[-1], rel=1e-6)
    assert job["progress"]["rel_error"] == pytest.approx(errors[-1])
    single = poll_job(get_json(local_client),
                      submit(local_client, dict(body, progressive=False))["id"])
    assert single["passes"] == [] and single["progress"]["rel_error"] == pytest.approx(errors[-1])


def test02_pause_stops_enqueuing_the_preview_is_there_and_resume_finishes(local_client, tmp_path,
                                                                         reference_channels):
    get = get_json(local_client)
    # one pass of 256 tiles (a progressive one would be 3 units: renderer.plan groups
    # tiles that hold few samples), more than the pool keeps in flight
    body = dict(TINY, width=128, height=128, spp=16, tile_size=8, progressive=False)
    job = submit(local_client, body)
    wait_for(lambda: get(f"/jobs/{job['id']}")["progress"]["units_done"] >= 1, 300,
             "the first unit")
    paused = post(local_client, f"/jobs/{job['id']}/pause")
    assert paused["status"] == "paused"

    def settled():  # units in flight finish and are collected
        units = get(f"/jobs/{job['id']}/units")
        return units if not any(u["state"] in ("queued", "running") for u in units) else None
    units = wait_for(settled, 120, "the units in flight to land")
    time.sleep(0.5)  # ten scheduler ticks: none may enqueue anything
    assert get(f"/jobs/{job['id']}/units") == units
    assert sum(u["state"] == "pending" for u in units) > 0
    job = get(f"/jobs/{job['id']}")
    assert job["status"] == "paused" and job["finished"] is None
    # The running preview: written as units land, available before the job is done.
    assert job["preview_url"] == f"/jobs/{job['id']}/preview.png"
    png = wait_for(lambda: (r := local_client.get(job["preview_url"])).status_code == 200 and r,
                   30, "the running preview")
    assert png.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(png.content)).size == (128, 128)
    assert local_client.get(f"/jobs/{job['id']}/result.exr").status_code == 404
    # Illegal transitions are 409 with the state table's words.
    again = local_client.post(f"/jobs/{job['id']}/pause")
    assert again.status_code == 409 and "'paused'" in again.json()["detail"]
    resumed = post(local_client, f"/jobs/{job['id']}/resume")
    assert resumed["status"] == "running" and resumed["started"] == job["started"]
    job = poll_job(get, job["id"])
    assert job["status"] == "done" and job["progress"]["units_done"] == 256
    assert_bit_identical(download(local_client, job, tmp_path / "resumed.exr"),
                         reference_channels(body))


def test03_requeue_starts_again_from_nothing_and_renders_the_same(local_client, tmp_path,
                                                                  reference_channels):
    get = get_json(local_client)
    job = poll_job(get, submit(local_client, TINY)["id"])
    assert job["status"] == "done"
    requeued = post(local_client, f"/jobs/{job['id']}/requeue")
    assert requeued["status"] == "queued" and requeued["finished"] is None
    assert requeued["progress"]["units_done"] == 0 and requeued["samples"] == 0
    assert requeued["result_url"] is None
    job = poll_job(get, job["id"])
    assert job["status"] == "done" and job["samples"] == 32 * 32 * 4
    assert_complete_progress(job["progress"], units=planned_units(TINY), samples=32 * 32 * 4)
    assert_bit_identical(download(local_client, job, tmp_path / "again.exr"),
                         reference_channels(TINY))


def test04_illegal_transitions_are_409(local_client):
    get = get_json(local_client)
    job = poll_job(get, submit(local_client, TINY)["id"])
    for action, words in (("pause", "cannot go from 'done' to 'paused'"),
                          ("resume", "not paused"), ("retry", "no failed units")):
        response = local_client.post(f"/jobs/{job['id']}/{action}")
        assert response.status_code == 409 and words in response.json()["detail"], response.text
    big = submit(local_client, dict(TINY, width=256, height=256, spp=64, tile_size=16))
    assert local_client.post(f"/jobs/{big['id']}/cancel").status_code == 200
    for action in ("pause", "resume", "retry"):
        assert local_client.post(f"/jobs/{big['id']}/{action}").status_code == 409
    # A canceled job can be requeued (and canceled again).
    assert post(local_client, f"/jobs/{big['id']}/requeue")["status"] == "queued"
    assert local_client.post(f"/jobs/{big['id']}/cancel").json()["status"] == "canceled"
    for action in ("pause", "resume", "retry", "requeue"):
        assert local_client.post(f"/jobs/0123456789ab/{action}").status_code == 404
    assert local_client.patch("/jobs/0123456789ab", json={"priority": 1}).status_code == 404


@pytest.mark.parametrize("priority", [101, -101, "high", 1.5, None])
def test05_bad_priority_is_422(local_client, priority):
    response = local_client.post("/jobs", json=dict(TINY, priority=priority))
    assert response.status_code == 422 and "priority" in response.json()["detail"][0]["loc"]


def test06_patch_changes_the_priority_only(local_client):
    job = submit(local_client, dict(TINY, priority=-3, progressive=False))
    assert job["priority"] == -3
    response = local_client.patch(f"/jobs/{job['id']}", json={"priority": 42})
    assert response.status_code == 200 and response.json()["priority"] == 42
    assert local_client.get(f"/jobs/{job['id']}").json()["priority"] == 42
    for body in ({"priority": 1000}, {}, {"priority": 1, "status": "done"}):
        response = local_client.patch(f"/jobs/{job['id']}", json=body)
        assert response.status_code == 422, (body, response.text)
    poll_job(get_json(local_client), job["id"])


# -- tick by tick: ordering and retry ---------------------------------------------

@pytest.fixture
def settings(tmp_path):
    return Settings(data_dir=tmp_path / "data", broker_url="", database_url="", local_workers=1,
                    poll_interval=0.05)


def create(farm: Farm, body: dict) -> str:
    with farm.sessions.begin() as session:
        return jobs.create_job(session, farm.store, farm.settings, SYSTEM, JobCreate(**body), utcnow()).id


def rows(farm: Farm, job_id: str) -> tuple[Job, list[WorkUnit]]:
    with farm.sessions() as session:
        return session.get(Job, job_id), list(session.scalars(
            select(WorkUnit).where(WorkUnit.job_id == job_id).order_by(WorkUnit.index)))


def tick_until(farm: Farm, predicate, what: str, timeout: float = 300.0):
    def step():
        farm.scheduler.tick()
        return predicate()
    return wait_for(step, timeout, what, interval=0.02)


def test07_higher_priority_jobs_run_first(settings):
    with Farm.open(settings) as farm:
        low = create(farm, dict(TINY, tile_size=4, progressive=False, priority=-5))  # 64 units
        high = create(farm, dict(TINY, progressive=False, priority=5))  # 16 units, newer
        tick_until(farm, lambda: rows(farm, high)[0].status == "done", "the high job")
        low_job, low_units = rows(farm, low)
        assert low_job.status == "running" and low_job.units_done < 64
        _, high_units = rows(farm, high)
        last_high = max(u.enqueued_at for u in high_units)
        # No unit of the low job was enqueued before the high one's last unit.
        assert all(u.enqueued_at >= last_high for u in low_units if u.enqueued_at)
        # Reprioritized: the low job now goes before an even newer default job.
        with farm.sessions.begin() as session:
            jobs.set_priority(session, SYSTEM, low, 50, utcnow())
        newer = create(farm, dict(TINY, progressive=False))
        everything = lambda: all(rows(farm, j)[0].status == "done" for j in (low, newer))
        tick_until(farm, everything, "both jobs")
        last_low = max(u.enqueued_at for u in rows(farm, low)[1])
        assert min(u.enqueued_at for u in rows(farm, newer)[1]) >= last_low


def test08_retry_runs_the_failed_units_again(settings, reference_channels):
    with Farm.open(settings) as farm:
        job_id = create(farm, TINY)
        scene_file = farm.store.scene_path(rows(farm, job_id)[0].scene_hash)
        good = scene_file.read_text()
        scene_file.write_text(good.replace("cornell-box", "tampered", 1))
        tick_until(farm, lambda: rows(farm, job_id)[0].status == "failed", "the job to fail")
    scene_file.write_text(good)
    with Farm.open(settings) as farm:  # a fresh pool: no cached tampered scene
        with farm.sessions.begin() as session:
            job = jobs.retry_job(session, SYSTEM, job_id, utcnow())
            assert job.status == "running" and job.error is None and job.finished is None
        job, units = rows(farm, job_id)
        assert job.status == "running"
        assert all(u.state in ("pending", "done") for u in units)
        assert any(u.state == "pending" for u in units)
        tick_until(farm, lambda: rows(farm, job_id)[0].status == "done", "the retried job")
        job, units = rows(farm, job_id)
        assert job.units_done == job.units_total == planned_units(TINY)
        assert job.samples == 32 * 32 * 4
        assert_bit_identical(channels_of(farm.store.result_path(job_id)), reference_channels(TINY))


def test09_a_submitted_job_starts_without_waiting_for_the_poll(tmp_path, reference_channels):
    """With a 600 s poll interval a job submitted after the scheduler's first
    tick still runs at once: the submit wakes the scheduler, and each unit the
    local pool finishes wakes it again (until the submit woke it, a job waited
    up to poll_interval to start: a fifth of a 1-s job at the default 0.2 s)."""
    import httpx

    from conftest import ADMIN_HEADERS, embedded_env, start_serve

    child, base = start_serve(embedded_env(tmp_path / "data", RAYFARM_POLL_INTERVAL="600"),
                              tmp_path / "serve.log")
    try:
        with httpx.Client(base_url=base, timeout=30, headers=ADMIN_HEADERS) as client:
            job = poll_job(get_json(client), submit(client, TINY)["id"], timeout=240)
            assert job["status"] == "done", job
            (tmp_path / "woken.exr").write_bytes(client.get(job["result_url"]).content)
    finally:
        child.stop()
    assert_bit_identical(channels_of(tmp_path / "woken.exr"), reference_channels(TINY))
