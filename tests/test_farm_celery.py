"""The real farm: a Redis of this test run (conftest's `redis_server`), `rayfarm worker` and
`rayfarm serve` as processes. Same plan, same units, same merge, same bytes."""

from __future__ import annotations

import signal
import time

import httpx
import pytest
from fastapi.testclient import TestClient

from service.executors.celery_farm import CeleryExecutor
from service.main import create_app
from service.settings import Settings

from conftest import (ADMIN_HEADERS, TINY, assert_bit_identical, assert_denoised_beside_raw,
                      channels_of, get_json,
                      planned_units, poll_job, submit, wait_for)

from test_service_target import TARGET_JOB, assert_target_job, target_reference

pytestmark = pytest.mark.farm



def run_job(client, body: dict, exr_path, timeout: float = 300.0) -> dict:
    response = client.post("/jobs", json=body)
    assert response.status_code == 201, response.text
    job = poll_job(get_json(client), response.json()["id"], timeout)
    assert job["status"] == "done", job
    exr = client.get(job["result_url"])
    assert exr.status_code == 200
    exr_path.write_bytes(exr.content)
    return job


# One job per kernel family (the path tracers, the rasterizer) and a
# low-discrepancy sampler, and every method that plans a DAG (their units
# carry other units' films: photon maps, a bootstrap, a radiosity solution):
# each must come out of both executors bit for bit.
FAMILIES = [dict(TINY, spp=8, tile_size=16),
            dict(TINY, method="raster", spp=4, tile_size=16),
            dict(TINY, method="path-onesample", sampler="sobol", spp=8, tile_size=16),
            dict(TINY, method="light", spp=4, progressive=False),
            dict(TINY, method="bdpt", spp=4, tile_size=16, progressive=False),
            dict(TINY, method="mlt", spp=4, progressive=False),
            dict(TINY, method="photon", spp=3, tile_size=16, progressive=False),
            dict(TINY, method="radiosity", spp=2, tile_size=16, progressive=False)]


def _mesh_scene() -> dict:
    """cornell-box with an inline mesh (normals, UVs): it becomes an asset,
    which the local pool reads from the store and Celery workers from Redis."""
    import json

    from renderer import resolve_document

    doc = json.loads(json.dumps(resolve_document("cornell-box")))
    doc["shapes"].append({"type": "mesh", "material": doc["shapes"][0]["material"],
                          "vertices": [[-0.5, -1, 0.3], [0.1, -1, 0.6], [-0.2, -0.2, 0.4],
                                       [-0.6, -0.7, 0.7]],
                          "faces": [[0, 1, 2], [0, 2, 3], [1, 3, 2]],
                          "normals": [[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]],
                          "uvs": [[0, 0], [1, 0], [1, 1], [0, 1]]})
    return doc


FAMILIES.append(dict(TINY, scene=_mesh_scene(), spp=4, tile_size=16))


def test01_local_pool_and_celery_render_bit_identical_images(local_client, redis_url,
                                                             spawn_worker, tmp_path):
    local = [run_job(local_client, body, tmp_path / f"local{i}.exr")
             for i, body in enumerate(FAMILIES)]
    worker = spawn_worker(concurrency=2)
    settings = Settings(data_dir=tmp_path / "celery-data", broker_url=redis_url,
                        poll_interval=0.05, unit_lease_seconds=30)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        assert client.get("/healthz").json()["executor"] == "celery"
        farm = [run_job(client, body, tmp_path / f"celery{i}.exr")
                for i, body in enumerate(FAMILIES)]
        units = client.get(f"/jobs/{farm[0]['id']}/units").json()
    assert {u["worker"] for u in units} == {f"rayfarm-{worker.pid}@{_nodehost(units)}"}
    assert farm[0]["samples"] == local[0]["samples"] == 32 * 32 * 8
    for i, body in enumerate(FAMILIES):
        assert farm[i]["samples"] == local[i]["samples"] == 32 * 32 * body["spp"], body
        assert farm[i]["scene_hash"] == local[i]["scene_hash"]  # the same scene everywhere
        assert_bit_identical(channels_of(tmp_path / f"local{i}.exr"),
                             channels_of(tmp_path / f"celery{i}.exr"))


def _nodehost(units: list[dict]) -> str:
    return units[0]["worker"].split("@", 1)[1]


def test02_end_to_end_serve_and_worker_processes_over_http(spawn_serve, spawn_worker,
                                                         tmp_path, reference_channels):
    spawn_worker(concurrency=2)
    _serve, base = spawn_serve(RAYFARM_POLL_INTERVAL="0.05")
    with httpx.Client(base_url=base, timeout=30, headers=ADMIN_HEADERS) as client:
        health = client.get("/healthz").json()
        assert health["executor"] == "celery" and health["broker"] == "ok"
        job = run_job(client, TINY, tmp_path / "e2e.exr")
        assert job["progress"]["units_done"] == planned_units(TINY)  # progressive: 3 passes
        import OpenEXR

        with OpenEXR.File(str(tmp_path / "e2e.exr")) as exr:
            header = exr.header()
            assert header["rayfarm.job_id"] == job["id"]
            assert exr.channels()["RGB"].pixels.shape == (32, 32, 3)
        assert client.get(job["preview_url"]).headers["content-type"] == "image/png"
        assert job["denoise"] is False and job["denoised_url"] is None
        # denoise: once, in the service, over the frame the Celery workers' units merge to
        denoised = run_job(client, dict(TINY, denoise=True), tmp_path / "denoised.exr")
        assert denoised["denoised_url"] == f"/jobs/{denoised['id']}/denoised.png"
        assert client.get(denoised["denoised_url"]).headers["content-type"] == "image/png"
        # a noise target: the pass barrier's decisions over Celery workers' units
        targeted = run_job(client, TARGET_JOB, tmp_path / "target.exr")
        assert_target_job(targeted, TARGET_JOB)
    assert_bit_identical(channels_of(tmp_path / "e2e.exr"), reference_channels(TINY))
    assert_denoised_beside_raw(tmp_path / "denoised.exr", reference_channels(TINY))
    assert_bit_identical(channels_of(tmp_path / "target.exr"),
                         target_reference(TARGET_JOB, tmp_path / "target-ref.exr"))


def test03_sigkilled_worker_mid_job_the_job_still_finishes_bit_identical(
        redis_url, spawn_worker, tmp_path, reference_channels):
    import redis

    # 36 units on one process, so the kill lands mid-job: at 512 spp a unit
    # took about 70 ms on the machine this was written on and 10 ms on an AMD
    # EPYC Zen 5 (half a second for the job); at 2048 spp 40 ms there.
    body = dict(TINY, width=48, height=48, spp=2048, tile_size=8, progressive=False)
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05,
                        unit_lease_seconds=5)
    broker = redis.Redis.from_url(redis_url)
    first = spawn_worker(concurrency=1)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        job_id = client.post("/jobs", json=body).json()["id"]

        def rendering() -> list[int]:
            # A heartbeat exists only while a unit renders: kill in the middle of
            # one (killing right after a result would land between two units).
            if get(f"/jobs/{job_id}")["progress"]["units_done"] < 2:
                return []
            return [int(k.rsplit(b":", 1)[1]) for k in broker.keys(f"rayfarm:hb:{job_id}:*")]
        victims = wait_for(rendering, 300, "a unit rendering after the first two", interval=0.01)
        first.kill_group(signal.SIGKILL)
        first.proc.wait(10)
        wait_for(lambda: not first.group_alive(), 10, "the worker's whole process group to die")
        at_kill = get(f"/jobs/{job_id}")
        assert at_kill["status"] == "running"
        assert at_kill["progress"]["units_done"] < at_kill["progress"]["units_total"] == 36
        second = spawn_worker(concurrency=2)
        job = poll_job(get, job_id)
        assert job["status"] == "done", job
        assert job["samples"] == 48 * 48 * body["spp"], "a unit was counted twice or lost"
        units = get(f"/jobs/{job_id}/units")
        # The unit the dead worker was rendering came back as a new task, not as
        # a failed attempt (unless it stored its result in the instant before the kill).
        assert any(units[i]["tasks"] > 1 for i in victims) or \
            all(units[i]["worker"].startswith(f"rayfarm-{first.pid}@") for i in victims)
        assert all(u["attempts"] == 1 and u["state"] == "done" for u in units)
        assert any(u["worker"].startswith(f"rayfarm-{second.pid}@") for u in units)
        (tmp_path / "killed.exr").write_bytes(client.get(job["result_url"]).content)
    broker.close()
    assert_bit_identical(channels_of(tmp_path / "killed.exr"), reference_channels(body))


def test04_messages_lost_by_the_broker_are_enqueued_again(redis_url, spawn_worker, tmp_path,
                                                         reference_channels):
    import redis

    from service.executors.celery_farm import PRIORITY_SEP, PRIORITY_STEPS
    from worker.keys import QUEUE

    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05,
                        unit_lease_seconds=2)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        job_id = client.post("/jobs", json=dict(TINY, progressive=False)).json()["id"]
        # No worker has reported yet: the executor sends only a few units.
        sent = CeleryExecutor.NO_WORKER_SLOTS

        def states() -> list[str]:
            return [u["state"] for u in get(f"/jobs/{job_id}/units")]
        wait_for(lambda: sorted(states()) == ["pending"] * (16 - sent) + ["queued"] * sent,
                 30, f"{sent} units to be queued, the rest pending")
        lost = [i for i, state in enumerate(states()) if state == "queued"]
        broker = redis.Redis.from_url(redis_url)
        # Priority 0 goes to one of kombu's priority lists of the queue.
        lists = [QUEUE, *(f"{QUEUE}{PRIORITY_SEP}{p}" for p in PRIORITY_STEPS[1:])]
        assert sum(broker.llen(name) for name in lists) == sent
        broker.delete(*lists)  # as if Redis restarted without persistence
        broker.close()
        spawn_worker(concurrency=2)
        job = poll_job(get, job_id)
        assert job["status"] == "done", job
        units = get(f"/jobs/{job_id}/units")
        assert all(units[i]["tasks"] >= 2 for i in lost)
        assert all(u["attempts"] == 1 for u in units)
        (tmp_path / "lost.exr").write_bytes(client.get(job["result_url"]).content)
    assert_bit_identical(channels_of(tmp_path / "lost.exr"), reference_channels(TINY))


def test05_workers_are_shown_busy_idle_lost_and_offline(redis_url, spawn_worker, tmp_path):
    beat = {"RAYFARM_WORKER_HEARTBEAT_SECONDS": "0.3"}
    doomed, leaving = spawn_worker(concurrency=1, **beat), spawn_worker(concurrency=2, **beat)
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05,
                        worker_lost_seconds=2.0)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        get = get_json(client)

        def by_pid() -> dict[int, dict]:
            return {int(w["name"].split("-", 1)[1].split("@")[0]): w for w in get("/workers")}
        workers = wait_for(lambda: (w := by_pid()).keys() >= {doomed.pid, leaving.pid} and w,
                           60, "both workers to report")
        assert workers[doomed.pid]["concurrency"] == 1 and workers[leaving.pid]["concurrency"] == 2
        assert all(w["kind"] == "celery" and w["state"] == "idle" for w in workers.values())
        # A job in flight: some worker shows the units it renders, then counts them.
        job_id = client.post("/jobs", json=dict(TINY, width=64, height=64, spp=128)).json()["id"]
        busy = wait_for(lambda: [w for w in get("/workers") if w["state"] == "busy"], 120,
                        "a worker to be busy")
        assert all(r["job_id"] == job_id for w in busy for r in w["running"]), (job_id, busy)
        job = poll_job(get, job_id)
        workers = by_pid()
        units = get(f"/jobs/{job_id}/units")
        for pid, worker in workers.items():
            mine = [u for u in units if u["worker"] == worker["name"]]
            assert worker["units_done"] == len(mine), worker  # fresh workers: only this job
        assert sum(w["samples"] for w in workers.values()) == job["samples"]
        # SIGKILL: no goodbye, the heartbeats stop -> lost. SIGTERM: a clean exit -> offline.
        doomed.kill_group()
        leaving.stop()
        wait_for(lambda: by_pid()[doomed.pid]["state"] == "lost", 30, "the killed worker lost")
        workers = by_pid()
        assert workers[leaving.pid]["state"] == "offline", workers[leaving.pid]
        assert workers[doomed.pid]["silent_seconds"] > 2.0


def test06_a_higher_priority_job_overtakes_the_units_already_in_the_broker(
        redis_url, spawn_worker, tmp_path):
    # The low job's units in flight (a few per worker process: the executor keeps
    # no deep queue) are in Redis when the high job arrives; the scheduler sends the
    # high job's units next (strict priority within an owner) and the broker's
    # priority lists serve them before the low ones already there, so it finishes
    # while most of the low job still waits.
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05)
    spawn_worker(concurrency=1)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        # 64 units of 16 x 16 pixels at 4096 spp, 0.38 s each on an AMD EPYC Zen
        # 5. Units that land faster (the scheduler now wakes on each result) left
        # 18 of them done before the high job was sent; and the count below is
        # the ledger's, which trails the worker by the units its scheduler has
        # not collected yet: with 8 x 8-pixel units (0.1 s there) and a third
        # process keeping the cores busy, 12 low units finished first against
        # 9 + 2 counted.
        low = submit(client, dict(TINY, width=128, height=128, spp=4096, tile_size=16,
                                  progressive=False, priority=-10))  # 64 units
        wait_for(lambda: get(f"/jobs/{low['id']}")["progress"]["units_done"] >= 2, 120,
                 "the low job to be under way")
        # Bounded, not all 64. Sampled a few times: a tick commits what it collected
        # before it dispatches, so a single read can fall between the two, when the
        # unit that just started has not been replaced in the broker yet.
        samples = []
        for _ in range(20):
            samples.append(sum(u["state"] == "queued" for u in get(f"/jobs/{low['id']}/units")))
            time.sleep(0.05)
        assert 0 < max(samples) <= CeleryExecutor.MAX_AHEAD * 1, samples
        high = submit(client, dict(TINY, progressive=False, tile_size=16, priority=60))  # 4 units
        # Counted once the high job's units are all in the broker: each waits
        # for a slot a low unit frees, so low units keep finishing until then
        # (read at the submit, this raced: 15 finished first against 12 + 2).
        wait_for(lambda: all(u["state"] != "pending" for u in get(f"/jobs/{high['id']}/units")),
                 60, "the high job's units to be sent", interval=0.01)
        done_before = get(f"/jobs/{low['id']}")["progress"]["units_done"]
        high = poll_job(get, high["id"])
        assert high["status"] == "done"
        finished_high = max(u["finished_at"] for u in get(f"/jobs/{high['id']}/units"))
        low_first = sum(u["finished_at"] is not None and u["finished_at"] < finished_high
                        for u in get(f"/jobs/{low['id']}/units"))
        # Only the low unit rendering when the high job came (and one the ledger had not
        # yet seen land) finish first: the high job's four units jumped the queue.
        assert low_first <= done_before + 2 < 20, (low_first, done_before)
        assert client.post(f"/jobs/{low['id']}/cancel").status_code == 200


def test07_the_scheduler_collects_landed_units_without_waiting_for_its_poll(
        spawn_serve, spawn_worker, tmp_path, reference_channels):
    """With a 600 s poll interval a job of 64 units still finishes:
    the scheduler ticks when the job is submitted and whenever Celery's result
    backend publishes a task's state (the executor listens on those channels).
    Without the wakes it would wait 600 s after the first tick."""
    spawn_worker(concurrency=2)
    _serve, base = spawn_serve(RAYFARM_POLL_INTERVAL="600")
    with httpx.Client(base_url=base, timeout=30, headers=ADMIN_HEADERS) as client:
        body = dict(TINY, tile_size=4, progressive=False)
        job = run_job(client, body, tmp_path / "woken.exr", timeout=240)
        assert job["progress"]["units_done"] == 64
    assert_bit_identical(channels_of(tmp_path / "woken.exr"), reference_channels(body))
