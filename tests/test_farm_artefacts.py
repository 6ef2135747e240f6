"""Unit films travel by digest on the real farm (a Redis of this run, `rayfarm
worker` processes): the worker publishes each film under its SHA-256, the
service copies it into the store from there, later DAG units receive the
digest, and Redis keeps only what later units still read. A film that
vanished before the service read it is rendered again; one that does not
match its digest is a failed attempt."""

from __future__ import annotations

import hashlib
import threading
from collections import Counter

import pytest
import redis
from fastapi.testclient import TestClient

from service.farm import Farm
from service.main import create_app
from service.settings import Settings
from worker.keys import input_key

from conftest import ADMIN_HEADERS, TINY, assert_bit_identical, assert_equals_renderer, \
    channels_of, poll_job, get_json, wait_for
from test_service_scheduler import create, finished, job_row, tick_until, unit_rows

pytestmark = pytest.mark.farm

INPUT_PREFIX = input_key("")


class InputSets:
    """Every SET of an input key on the test's Redis, by key (keyspace
    notifications: no MONITOR, and every client's SETs are seen)."""

    def __init__(self, url: str):
        self.client = redis.Redis.from_url(url)
        self.client.config_set("notify-keyspace-events", "E$")
        self.keys: Counter[str] = Counter()
        self._pubsub = self.client.pubsub()
        self._pubsub.subscribe(**{"__keyevent@0__:set": self._on_set})
        self._thread = self._pubsub.run_in_thread(sleep_time=0.01, daemon=True)
        self._lock = threading.Lock()

    def _on_set(self, message) -> None:
        key = message["data"].decode()
        if key.startswith(INPUT_PREFIX):
            with self._lock:
                self.keys[key] += 1

    def close(self) -> None:
        self._thread.stop()
        self._thread.join(5)  # before its connection is closed under it
        self._pubsub.close()
        self.client.config_set("notify-keyspace-events", "")
        self.client.close()


PHOTON = dict(TINY, method="photon", spp=3, tile_size=16, progressive=False)


def test01_a_photon_job_moves_each_film_once_and_redis_keeps_none_after(
        redis_url, spawn_worker, tmp_path):
    spawn_worker(concurrency=2)
    sets = InputSets(redis_url)
    broker = redis.Redis.from_url(redis_url)
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05)
    try:
        with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
            farm = client.app.state.farm
            job = poll_job(get_json(client), client.post("/jobs", json=PHOTON).json()["id"])
            assert job["status"] == "done", job
            (tmp_path / "photon.exr").write_bytes(client.get(job["result_url"]).content)
            units = unit_rows(farm, job["id"])
            # The API names each unit's film by the digest the ledger holds.
            shown = client.get(f"/jobs/{job['id']}/units").json()
            assert [u["film_digest"] for u in shown] == [u.film_digest for u in units]
            # The service sent no input from its store: every one was in Redis already.
            assert farm.executor.inputs_uploaded == 0
            # Nothing is left in Redis for the finished job: films no later unit
            # read went when they were stored, the inputs when the job finished.
            assert broker.keys(f"{INPUT_PREFIX}*") == []
        wait_for(lambda: sum(sets.keys.values()) >= len(units), 10, "the last notifications")
    finally:
        sets.close()
        broker.close()
    assert len(units) == 15 and any(u.unit["needs"] for u in units)
    for u in units:
        # The ledger names each stored film by its digest...
        assert u.film_digest == hashlib.sha256(farm.store.unit_film(u.job_id, u.index)).hexdigest()
    # ... and each was SET in Redis exactly once: by the worker that rendered
    # it, never again by the service for the units that read it.
    assert sets.keys == Counter({input_key(u.film_digest): 1 for u in units})
    assert_equals_renderer(tmp_path / "photon.exr", PHOTON)


def _landed(farm: Farm, job_id: str) -> dict[int, str]:
    """Units whose latest task succeeded (not yet collected): index -> film digest."""
    out = {}
    for u in unit_rows(farm, job_id):
        if u.state in ("queued", "running") and u.task_ids:
            result = farm.executor.app.AsyncResult(u.task_ids[-1])
            if result.state == "SUCCESS":
                out[u.index] = result.result["digest"]
    return out


def test02_a_film_gone_from_redis_is_rendered_again_a_corrupt_one_is_a_failed_attempt(
        redis_url, spawn_worker, tmp_path, reference_channels):
    body = dict(TINY, progressive=False)
    spawn_worker(concurrency=1)
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05)
    broker = redis.Redis.from_url(redis_url)
    with Farm.open(settings) as farm:  # ticked by hand: nothing is collected meanwhile
        job_id = create(farm, body)
        farm.scheduler.tick()
        landed = wait_for(lambda: (lambda d: d if len(d) >= 2 else None)(_landed(farm, job_id)),
                          120, "two units to finish")
        gone, corrupt = sorted(landed)[:2]
        broker.delete(input_key(landed[gone]))
        broker.set(input_key(landed[corrupt]), b"not the film")
        farm.scheduler.tick()
        rows = unit_rows(farm, job_id)
        # Gone: enqueued again as a lost unit, no attempt spent.
        assert rows[gone].state in ("queued", "running") and len(rows[gone].task_ids) == 2
        assert rows[gone].attempts == 1 and rows[gone].error is None
        # Corrupt: a failed attempt that says why, and tried again.
        assert rows[corrupt].state in ("queued", "running") and rows[corrupt].attempts == 2
        assert "does not match its digest" in rows[corrupt].error
        tick_until(farm, finished(farm, job_id))
        assert job_row(farm, job_id).status == "done"
        rows = unit_rows(farm, job_id)
        assert rows[gone].state == rows[corrupt].state == "done"
        assert_bit_identical(channels_of(farm.store.result_path(job_id)), reference_channels(body))
    broker.close()


def test03_an_input_that_expired_is_sent_again_from_the_store(redis_url, spawn_worker, tmp_path):
    spawn_worker(concurrency=1)
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05)
    broker = redis.Redis.from_url(redis_url)
    with Farm.open(settings) as farm:
        submit = farm.executor.submit
        expired: list[str] = []

        def submit_after_expiry(ticket):
            if ticket.inputs and not expired:  # the first unit with inputs: they expired
                expired.extend(ticket.inputs.values())
                assert broker.delete(*(input_key(d) for d in expired)) == len(expired)
            return submit(ticket)
        farm.executor.submit = submit_after_expiry
        job_id = create(farm, PHOTON)
        tick_until(farm, finished(farm, job_id))
        assert job_row(farm, job_id).status == "done", job_row(farm, job_id).error
        assert expired and farm.executor.inputs_uploaded == len(expired)
        assert all(u.attempts == 1 for u in unit_rows(farm, job_id))
        (tmp_path / "expired.exr").write_bytes(farm.store.result_path(job_id).read_bytes())
    broker.close()
    assert_equals_renderer(tmp_path / "expired.exr", PHOTON)



def test04_a_canceled_jobs_films_leave_redis_at_once(redis_url, spawn_worker, tmp_path):
    # A photon job canceled mid-way: the photon maps kept for its gather
    # tiles, the films of tasks that landed but were never stored, and those
    # of units still rendering at the cancel all leave Redis within moments,
    # not when they would expire (a day).
    spawn_worker(concurrency=2)
    broker = redis.Redis.from_url(redis_url)
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url, poll_interval=0.05)
    body = dict(PHOTON, spp=64)  # 128 units: 32 rounds of 4 photon units and 4 gather tiles
    try:
        with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
            farm = client.app.state.farm
            get = get_json(client)
            job_id = client.post("/jobs", json=body).json()["id"]
            # Some input film stored and kept in Redis for later units.
            wait_for(lambda: get(f"/jobs/{job_id}")["progress"]["units_done"] >= 6
                     and broker.keys(f"{INPUT_PREFIX}*"), 120, "photon maps kept in Redis")
            assert client.post(f"/jobs/{job_id}/cancel").status_code == 200
            wait_for(lambda: not broker.keys(f"{INPUT_PREFIX}*"), 30,
                     "the canceled job's films to leave Redis", interval=0.1)
            assert get(f"/jobs/{job_id}")["status"] == "canceled"
            assert farm.executor.inputs_uploaded == 0
            # Nothing comes back: the units in flight at the cancel have finished
            # (their films taken back by their workers) or were skipped.
            wait_for(lambda: not broker.keys("rayfarm:hb:*"), 30, "the units in flight to end")
            assert broker.keys(f"{INPUT_PREFIX}*") == []
    finally:
        broker.close()


def test05_a_film_published_just_before_the_cancel_is_dropped_and_none_after(
        redis_url, tmp_path):
    # The window test04 once lost: a worker publishes its film, the cancel
    # comes before Celery has written the task's SUCCESS, so the service
    # cannot learn the film's digest from the task. Publishing notes the film
    # in the job's film set in the same atomic step that checks the cancel
    # marker, so the cancel finds it; after the marker, nothing is published.
    from service.executors.celery_farm import CeleryExecutor
    from worker.keys import cancel_key, job_films_key
    from worker.tasks import publish_film

    broker = redis.Redis.from_url(redis_url)
    settings = Settings(data_dir=tmp_path / "data", broker_url=redis_url)
    executor = CeleryExecutor(settings, lambda scene_hash: "")
    try:
        film = b"a film of job-race " + tmp_path.name.encode()
        digest = publish_film(broker, "job-race", film)
        assert digest == hashlib.sha256(film).hexdigest()
        assert broker.get(input_key(digest)) == film
        assert broker.smembers(job_films_key("job-race")) == {digest.encode()}
        executor.cancel("job-race", ["no-such-task"])  # no task result says the digest
        assert broker.exists(input_key(digest)) == 0
        assert broker.exists(job_films_key("job-race")) == 0
        assert publish_film(broker, "job-race", film) is None  # canceled: refused
        assert broker.exists(input_key(digest)) == 0
        assert broker.exists(job_films_key("job-race")) == 0
        # A job that runs again (retried) publishes once the service lifts the marker.
        broker.delete(cancel_key("job-race"))
        assert publish_film(broker, "job-race", film) == digest
        assert publish_film(broker, "job-race", film) == digest  # already there: TTL only
        assert broker.ttl(input_key(digest)) > 0
    finally:
        executor.close()
        broker.delete(input_key(hashlib.sha256(film).hexdigest()), job_films_key("job-race"),
                      cancel_key("job-race"))
        broker.close()
