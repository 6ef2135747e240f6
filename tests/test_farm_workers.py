"""Lost workers and worker control on the real farm: this run's Redis,
`rayfarm worker` processes, the service in this process (a TestClient).

- a SIGKILLed worker's unit is enqueued again within a few heartbeat
  intervals of the kill, with a lease of 120 s that plays no part;
- a unit rendering longer than the lease is never re-run: its heartbeat
  keeps it alive;
- a drained (disabled) worker takes no new unit while another does;
- a worker declines, without rendering, a unit of a job it is blocklisted
  for, or any unit while it is disabled;
- a worker SIGKILLed mid-unit and started again under its name gives that
  unit back at once, although the name never looks lost.
"""

from __future__ import annotations

import signal
import time

import pytest
from fastapi.testclient import TestClient

from service.main import create_app
from service.settings import Settings

from conftest import (ADMIN_HEADERS, TINY, assert_bit_identical, channels_of, get_json, poll_job,
                      submit, wait_for)

pytestmark = pytest.mark.farm

BEAT = {"RAYFARM_WORKER_HEARTBEAT_SECONDS": "0.3"}
# Four units of about half a second each on an AMD EPYC Zen 5 (16 x 16 pixels
# x 4096 samples, depth 7: 0.53 s on one thread; at 2048 spp and depth 3 they
# took 0.17 s, short enough for a unit to finish between the test seeing it
# start and its kill).
SLOW = dict(TINY, spp=4096, depth=7, tile_size=16, progressive=False)


def _settings(tmp_path, redis_url, **extra) -> Settings:
    return Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05,
                    worker_heartbeat_seconds=0.3, worker_lost_seconds=1.5, **extra)


def _name(child, workers: list[dict]) -> str | None:
    return next((w["name"] for w in workers if w["name"].startswith(f"rayfarm-{child.pid}@")),
                None)


def test01_a_killed_workers_unit_is_enqueued_again_within_heartbeats_not_the_lease(
        redis_url, spawn_worker, tmp_path, reference_channels):
    import redis

    doomed = spawn_worker(concurrency=1, **BEAT)
    rescuer = spawn_worker(concurrency=1, **BEAT)
    broker = redis.Redis.from_url(redis_url)
    with TestClient(create_app(_settings(tmp_path, redis_url, unit_lease_seconds=120)),
                    headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        name = wait_for(lambda: _name(doomed, get("/workers")), 30, "the doomed worker")
        job_id = submit(client, SLOW)["id"]

        def doomed_renders() -> list[int]:
            return [int(k.rsplit(b":", 1)[1]) for k in broker.keys(f"rayfarm:hb:{job_id}:*")
                    if broker.get(k) == name.encode()]
        victims = wait_for(doomed_renders, 120, "the doomed worker to render a unit",
                           interval=0.01)
        doomed.kill_group(signal.SIGKILL)  # the main process and its render process
        killed = time.monotonic()

        def requeued() -> dict | None:
            unit = get(f"/jobs/{job_id}/units")[victims[0]]
            return unit if unit["tasks"] > 1 or unit["state"] == "done" else None
        unit = wait_for(requeued, 60, "the killed worker's unit to be enqueued again",
                        interval=0.02)
        delay = time.monotonic() - killed
        print(f"\nre-enqueue delay after the kill: {delay:.2f} s "
              f"(worker heartbeat 0.3 s, lost after 1.5 s, lease 120 s)")
        assert unit["tasks"] == 2, unit  # not done by the dead worker in its last instant
        assert delay < 30, delay  # a few heartbeats and ticks; the lease is 120 s
        job = poll_job(get, job_id)
        assert job["status"] == "done", job
        units = get(f"/jobs/{job_id}/units")
        again = units[victims[0]]
        assert again["requeue_reason"].startswith(f"worker {name} lost"), again
        assert again["attempts"] == 1 and again["worker"] != name
        assert job["stats"]["units_retried"] >= 1
        assert job["samples"] == 32 * 32 * SLOW["spp"], "a unit was counted twice or lost"
        workers = {w["name"]: w for w in get("/workers")}
        assert workers[name]["state"] == "lost"
        # A lost worker can be removed from the list; a live one cannot.
        live = _name(rescuer, list(workers.values()))
        assert client.delete(f"/workers/{live}").status_code == 409
        assert client.delete(f"/workers/{name}").status_code == 204
        assert name not in {w["name"] for w in get("/workers")}
        (tmp_path / "killed.exr").write_bytes(client.get(job["result_url"]).content)
    broker.close()
    assert_bit_identical(channels_of(tmp_path / "killed.exr"), reference_channels(SLOW))


def test02_a_unit_longer_than_the_lease_is_never_rendered_again(redis_url, spawn_worker,
                                                                tmp_path):
    spawn_worker(concurrency=1, **BEAT)
    # One unit of about three seconds or more against a lease of 1.5 s (a Numba
    # kernel holds the render process's GIL: its own heartbeat thread cannot
    # beat). 2048 spp on 32 x 32 pixels took 1.36 s on a fast machine, and
    # 4096 spp 1.45 s on an AMD EPYC Zen 5 once the sampler's memo kept its
    # pair tables for such a unit (integrators/tile.py): too close to the
    # lease. 48 x 48 pixels at 4096 spp are 2.25 times that.
    body = dict(TINY, width=48, height=48, spp=4096, tile_size=48, progressive=False)
    with TestClient(create_app(_settings(tmp_path, redis_url, unit_lease_seconds=1.5)),
                    headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        # First a one-unit job, so the render process is warm: a message it
        # reserved while it still loaded its kernels would be taken for lost
        # (queued past this short lease), which is not what this test is about.
        assert poll_job(get, submit(client, dict(TINY, spp=1, tile_size=32,
                                                 progressive=False))["id"])["status"] == "done"
        job = poll_job(get, submit(client, body)["id"])
        assert job["status"] == "done", job
        (unit,) = get(f"/jobs/{job['id']}/units")
        assert unit["seconds"] > 1.5, unit  # it did outlive the lease
        assert unit["tasks"] == 1 and unit["requeue_reason"] is None, unit


def test03_a_disabled_worker_takes_no_new_unit_while_another_does(redis_url, spawn_worker,
                                                                 tmp_path):
    drained, busy = spawn_worker(concurrency=1, **BEAT), spawn_worker(concurrency=1, **BEAT)
    with TestClient(create_app(_settings(tmp_path, redis_url)), headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        def both() -> list[dict] | None:
            found = get("/workers")
            return found if _name(drained, found) and _name(busy, found) else None
        workers = wait_for(both, 30, "both workers")
        name = _name(drained, workers)
        answer = client.post(f"/workers/{name}/disable")
        assert answer.status_code == 200 and answer.json()["disabled"] is True
        job = poll_job(get, submit(client, dict(TINY, progressive=False, tile_size=8))["id"])
        assert job["status"] == "done", job
        units = get(f"/jobs/{job['id']}/units")
        assert {u["worker"] for u in units} == {_name(busy, workers)}
        shown = {w["name"]: w for w in get("/workers")}
        assert shown[name]["disabled"] and shown[name]["units_done"] == 0
        # Enabled again, it takes units again. The other worker is disabled in
        # turn, so the job can only finish on the enabled one: a race between
        # the two for a job's units proves nothing (16 units of 8 x 8 pixels
        # at 2048 spp took about 30 ms each on an AMD EPYC Zen 5, and the busy
        # worker had done them all before the enabled one's consumer polled
        # the queue again, with the other test process keeping both cores busy).
        assert client.post(f"/workers/{name}/enable").json()["disabled"] is False
        other = _name(busy, workers)
        assert client.post(f"/workers/{other}/disable").json()["disabled"] is True
        job = poll_job(get, submit(client, dict(TINY, progressive=False, tile_size=8,
                                                seed=8))["id"])
        assert job["status"] == "done", (job, drained.log()[-3000:])
        takers = {u["worker"] for u in get(f"/jobs/{job['id']}/units")}
        assert takers == {name}, (takers, drained.log()[-3000:])
        # (its presence thread logs the flag on its next beat, which a job of
        # a few milliseconds may beat to the finish)
        wait_for(lambda: "enabled: consuming again" in drained.log(), 30,
                 "the worker to log that it consumes again")


def test04_a_worker_declines_units_of_a_job_it_is_blocklisted_for_or_while_disabled(
        redis_url):
    import redis

    from worker.presence import set_disabled
    from worker.tasks import render_unit

    client = redis.Redis.from_url(redis_url)
    # Neither the scene nor anything else is needed: it declines before reading them.
    payload = {"job_id": "j1", "index": 0, "scene_hash": "0" * 64, "spec": {}, "unit": {},
               "lease_seconds": 60, "heartbeat_seconds": 1, "blocked": ["w1"], "inputs": {}}
    assert render_unit(client, "w1", payload, "t1") == {"declined": "blocklisted for the job",
                                                       "worker": "w1"}
    set_disabled(client, "w2", True)
    assert render_unit(client, "w2", payload, "t2") == {"declined": "disabled", "worker": "w2"}
    set_disabled(client, "w2", False)
    with pytest.raises(Exception):  # enabled and not blocklisted: it does try to render
        render_unit(client, "w2", payload, "t3")
    client.close()


def test05_a_unit_whose_message_a_live_worker_holds_stays_queued_past_the_lease(
        redis_url, tmp_path):
    # A cold worker's render processes compile kernels for minutes while its
    # main process holds prefetched messages: not in the broker's queue, yet
    # not lost. Taking them for lost ("queued over a lease, not in the queue")
    # rendered them twice. The presence record lists what a worker holds; the
    # messages a *lost* worker held are lost with it.
    from datetime import datetime, timedelta, timezone

    import redis

    from service.executors.base import Flight
    from service.executors.celery_farm import CeleryExecutor
    from worker.keys import worker_key
    from worker.presence import Presence

    client = redis.Redis.from_url(redis_url)
    executor = CeleryExecutor(_settings(tmp_path, redis_url, unit_lease_seconds=1.0),
                              load_scene_text=lambda h: "{}")
    now = datetime.now(timezone.utc)
    flight = Flight("job", 0, "queued", ("t-held",), now - timedelta(seconds=30), None)
    presence = Presence(client, "w-cold", 2, 0.1, reserved=lambda: ["t-held", "t-other"])
    presence.start()
    try:
        (worker,) = executor.workers()
        assert worker.reserved == ("t-held", "t-other") and worker.state == "idle"
        (obs,) = executor.observe([flight], now)
        assert obs.state == "queued", obs
        # Not held by anyone: the message is gone from the broker.
        (obs,) = executor.observe([Flight("job", 1, "queued", ("t-gone",),
                                          now - timedelta(seconds=30), None)], now)
        assert (obs.state, obs.cause) == ("lost", "message"), obs
        # The worker that holds it stops beating: the unit is lost with it.
        presence._stop.set()
        presence._thread.join()
        client.hset(worker_key("w-cold"), "last_seen", float(client.time()[0]) - 60)
        executor._lost_read = -1e9  # presence is read at most once a second
        (obs,) = executor.observe([flight], now)
        assert (obs.state, obs.cause, obs.worker) == ("lost", "worker", "w-cold"), obs
    finally:
        presence.stop()
        executor.close()
        client.close()


def test06_a_blocklisted_worker_is_never_offered_the_jobs_units(redis_url, spawn_worker,
                                                                 tmp_path):
    # From the shared queue, an idle worker blocklisted for a job took each of
    # its units and declined it, again and again, while the other worker was
    # busy. The job's units now go to the own queue of a worker that may run
    # them: each is sent once, and the blocklisted one sees none.
    from service.farm import Farm
    from service.models import WorkerBlock, utcnow

    from test_service_scheduler import create, finished, job_row, tick_until, unit_rows

    blocked, allowed = spawn_worker(concurrency=1, **BEAT), spawn_worker(concurrency=1, **BEAT)
    with Farm.open(_settings(tmp_path, redis_url)) as farm:
        def both() -> list | None:
            found = [{"name": w.name} for w in farm.executor.workers() if w.state == "idle"]
            return found if _name(blocked, found) and _name(allowed, found) else None
        names = wait_for(both, 30, "both workers")
        bad, good = _name(blocked, names), _name(allowed, names)
        body = dict(TINY, spp=64, tile_size=8, progressive=False)  # 16 short units
        job_id = create(farm, body)
        with farm.sessions.begin() as session:
            session.add(WorkerBlock(job_id=job_id, worker=bad, failures=3,
                                    last_error="test", blocked=utcnow()))
        tick_until(farm, finished(farm, job_id), 120)
        assert job_row(farm, job_id).status == "done", job_row(farm, job_id).error
        units = unit_rows(farm, job_id)
        assert {u.worker for u in units} == {good}
        assert [len(u.task_ids) for u in units] == [1] * len(units), \
            [(u.index, u.requeue_reason) for u in units if len(u.task_ids) > 1]
        # Without a blocklisted live worker the job's units use the shared queue.
        assert farm.executor._direct_target([]) is None
        assert farm.executor._direct_target(["rayfarm-gone@nowhere"]) is None
        assert farm.executor._direct_target([bad]) == good
        assert farm.executor._direct_target([bad, good]) is None


def test07_a_unit_in_a_stopped_workers_own_queue_is_enqueued_again(redis_url, tmp_path):
    # Presence records only (no worker consumes): a unit sent to w-good's own
    # queue waits there past the lease while w-good lives, and is enqueued
    # again as soon as w-good stops without having taken it.
    from datetime import datetime, timedelta, timezone

    import redis

    from service.executors.base import Flight, Ticket
    from service.executors.celery_farm import CeleryExecutor
    from worker.presence import Presence

    client = redis.Redis.from_url(redis_url)
    executor = CeleryExecutor(_settings(tmp_path, redis_url, unit_lease_seconds=1.0),
                              load_scene_text=lambda h: "{}")
    workers = [Presence(client, name, 1, 0.1) for name in ("w-bad", "w-good")]
    for presence in workers:
        presence.start()
    try:
        task_id = executor.submit(Ticket("job", 0, "0" * 64, {}, {}, blocked=("w-bad",)))
        # In w-good's own queue (kombu keeps a list per priority step), not the shared one.
        assert sum(client.llen(k) for k in client.keys("w-good.dq2*")) == 1
        assert executor.queue_length() == 0 and not client.keys("w-bad.dq2*")
        now = datetime.now(timezone.utc)
        flight = Flight("job", 0, "queued", (task_id,), now - timedelta(seconds=30), None)
        (obs,) = executor.observe([flight], now)
        assert obs.state == "queued", obs
        workers[1].stop()
        executor._lost_read = -1e9  # presence is read at most once a second
        (obs,) = executor.observe([flight], now)
        assert (obs.state, obs.cause, obs.worker) == ("lost", "worker", "w-good"), obs
        assert "stopped before taking it" in obs.error
    finally:
        for presence in workers:
            presence.stop()
        executor.close()
        client.close()


def test08_a_drained_worker_stays_drained_across_a_restart(redis_url, spawn_worker, tmp_path):
    # `rayfarm worker --name` keeps its name across restarts, and with it the
    # drain: restarted, it takes no unit until it is enabled again.
    first = spawn_worker(concurrency=1, name="steady", **BEAT)
    with TestClient(create_app(_settings(tmp_path, redis_url)), headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        name = wait_for(lambda: next((w["name"] for w in get("/workers")
                                      if w["name"].startswith("steady@")), None),
                        30, "the named worker")
        assert client.post(f"/workers/{name}/disable").json()["disabled"] is True
        first.stop()
        wait_for(lambda: {w["name"]: w for w in get("/workers")}[name]["state"] == "offline",
                 30, "the worker to be offline")
        second = spawn_worker(concurrency=1, name="steady", **BEAT)
        wait_for(lambda: {w["name"]: w for w in get("/workers")}[name]["state"] == "idle",
                 30, "the restarted worker")
        assert {w["name"]: w for w in get("/workers")}[name]["disabled"] is True
        # It never consumed the shared queue: it left it out before its consumer
        # started (a race when only its first heartbeat cancelled the consumer).
        assert "Canceling queue rayfarm.units" not in second.log()
        banner = second.log().split("[queues]", 1)[1].split("[tasks]", 1)[0]
        assert "rayfarm.units" not in banner and f"{name}.dq2" in banner, banner
        job_id = submit(client, dict(TINY, progressive=False, tile_size=16))["id"]
        time.sleep(3)  # many ticks and heartbeats: nothing may start meanwhile
        units = get(f"/jobs/{job_id}/units")
        assert all(u["started_at"] is None for u in units), units
        assert get(f"/jobs/{job_id}")["progress"]["units_done"] == 0
        assert client.post(f"/workers/{name}/enable").json()["disabled"] is False
        job = poll_job(get, job_id)
        assert job["status"] == "done", job
        assert {u["worker"] for u in get(f"/jobs/{job_id}/units")} == {name}


def test08b_a_worker_restarted_under_its_name_gives_back_at_once_the_unit_it_died_under(
        redis_url, spawn_worker, tmp_path, reference_channels):
    import redis

    first = spawn_worker(concurrency=1, name="phoenix", **BEAT)
    broker = redis.Redis.from_url(redis_url)
    # The unit lease and the silence that makes a worker lost both last ten
    # minutes: only the restart itself can tell the service the unit is gone.
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05,
                        worker_heartbeat_seconds=0.3, worker_lost_seconds=600,
                        unit_lease_seconds=600)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        get = get_json(client)
        name = wait_for(lambda: next((w["name"] for w in get("/workers")
                                      if w["name"].startswith("phoenix@")), None),
                        30, "the named worker")
        job_id = submit(client, SLOW)["id"]

        def rendering() -> list[int]:
            return [int(k.rsplit(b":", 1)[1]) for k in broker.keys(f"rayfarm:hb:{job_id}:*")
                    if broker.get(k) == name.encode()]
        victims = wait_for(rendering, 120, "the worker to render a unit", interval=0.01)
        first.kill_group(signal.SIGKILL)  # the main process and its render process
        first.proc.wait(10)
        killed = time.monotonic()
        spawn_worker(concurrency=1, name="phoenix", **BEAT)
        ready = time.monotonic()

        def requeued() -> dict | None:
            unit = get(f"/jobs/{job_id}/units")[victims[0]]
            return unit if unit["tasks"] > 1 or unit["state"] == "done" else None
        unit = wait_for(requeued, 90, "the dead process's unit to be enqueued again",
                        interval=0.05)
        print(f"\nthe unit enqueued again {time.monotonic() - killed:.2f} s after the kill, "
              f"{time.monotonic() - ready:.2f} s after the restarted worker was ready "
              "(lease and lost-worker silence 600 s)")
        assert unit["tasks"] == 2, unit  # not done by the dead process in its last instant
        assert unit["requeue_reason"].startswith(f"worker {name} was restarted"), unit
        assert {w["name"]: w for w in get("/workers")}[name]["state"] in ("busy", "idle")
        job = poll_job(get, job_id)
        assert job["status"] == "done", job
        assert get(f"/jobs/{job_id}/units")[victims[0]]["attempts"] == 1
        assert job["samples"] == 32 * 32 * SLOW["spp"], "a unit was counted twice or lost"
        (tmp_path / "restarted.exr").write_bytes(client.get(job["result_url"]).content)
    broker.close()
    assert_bit_identical(channels_of(tmp_path / "restarted.exr"), reference_channels(SLOW))


def test09_the_presence_asks_its_consumer_again_until_it_follows_the_flag(redis_url):
    # A remote-control message sent before the worker's event loop listens is
    # lost (pub/sub): the heartbeat compares the flag with what the consumer
    # does, not with what it asked, and asks again on every beat; never once
    # a shutdown began (consuming() says None). The consumer is a stand-in.
    import redis

    from worker.presence import Presence, set_disabled

    client = redis.Redis.from_url(redis_url)
    asked: list[bool] = []
    state = {"consuming": True}
    presence = Presence(client, "w-ask", 1, 60.0, consume=asked.append,
                        consuming=lambda: state["consuming"])
    set_disabled(client, "w-ask", True)
    for _ in range(3):  # the consumer does not follow: asked on every beat
        presence._follow_disabled()
    assert asked == [False, False, False]
    state["consuming"] = False  # it followed: nothing more to ask
    presence._follow_disabled()
    assert asked == [False, False, False]
    set_disabled(client, "w-ask", False)
    state["consuming"] = None  # shutting down: never asked to consume again
    presence._follow_disabled()
    presence._follow_disabled()
    assert asked == [False, False, False]
    client.close()
