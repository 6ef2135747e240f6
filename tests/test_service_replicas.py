"""Several service replicas on one ledger: exactly one schedules.

The lease on the test run's own PostgreSQL (service.leader) and on SQLite
(whatever the services' data dirs), events relayed between replicas, and the
leader SIGKILLed mid-job with real `rayfarm serve` processes. The failover
time (the kill -> the standby's first tick) is printed (`pytest -s`) for the
record.
"""

from __future__ import annotations

import json
import os
from collections import Counter
import signal
import sys
import threading
import time

import httpx
import pytest
from sqlalchemy import update

from service.db import open_ledger
from service.leader import LeadershipLost, LeaseLeadership, open_leadership
from service.models import SchedulerLease, User, utcnow
from service.settings import Settings

from conftest import (ADMIN_HEADERS, TINY, Child, assert_bit_identical, channels_of,
                      embedded_env, free_port, rayfarm_command, start_serve, wait_for)


@pytest.fixture
def pg_engine(postgres_url, tmp_path):
    engine, sessions = open_ledger(Settings(database_url=postgres_url, data_dir=tmp_path))
    yield engine, sessions
    engine.dispose()


def test01_one_holder_and_the_leader_stops_before_a_standby_may_start(pg_engine):
    engine, _ = pg_engine
    a, b = LeaseLeadership(engine, 3.0, "a"), LeaseLeadership(engine, 3.0, "b")
    a._attempt()
    b._attempt()
    assert a.leading() and not b.leading()
    assert a.status()["holder"] == "a" and b.status()["role"] == "standby"
    # a stops renewing (cut off, hung): it stops leading after half the lease ...
    wait_for(lambda: not a.leading(), 2.5, "the leader to stop leading")
    b._attempt()
    assert not b.leading(), "the standby took the lease before it expired"
    # ... and b may take it only once it expired, by the database's clock.
    wait_for(lambda: b._attempt() or b.leading(), 5.0, "the standby to take over",
             interval=0.1)
    assert b.epoch == a.epoch + 1
    a._attempt()  # a renewal of a lease someone else took fails
    assert a.epoch is None and not a.leading()
    b.stop()  # a clean stop releases it at once
    a._attempt()
    assert a.leading() and a.epoch == 3


def test02_a_commit_fenced_by_a_lost_lease_rolls_back(pg_engine):
    engine, sessions = pg_engine
    a, b = LeaseLeadership(engine, 5.0, "a"), LeaseLeadership(engine, 5.0, "b")
    a.guard(sessions)
    a._attempt()
    assert a.leading()
    with sessions.begin() as session:
        session.add(User(name="probe", role="artist", share=1.0, created=utcnow()))
    with a.fenced(), pytest.raises(LeadershipLost):
        with sessions.begin() as session:
            session.get(User, "probe").share = 2.0  # written by a leader about to be deposed
            # meanwhile the lease expired (as after a long pause) and b took it
            with engine.begin() as conn:
                conn.execute(update(SchedulerLease.__table__)
                             .where(SchedulerLease.name == "scheduler")
                             .values(expires_at=_utc(0)))
            b._attempt()
            assert b.leading()
    with sessions() as session:
        assert session.get(User, "probe").share == 1.0, "the fenced write stood"
    # Outside a fenced block (the API's commits) nothing is checked.
    with sessions.begin() as session:
        session.get(User, "probe").share = 3.0
    with a.fenced(), sessions.begin() as session:  # nor while this replica leads
        b.stop()
        a._attempt()
        session.get(User, "probe").share = 4.0
    with sessions() as session:
        assert session.get(User, "probe").share == 4.0


def _utc(seconds: float):
    from datetime import datetime, timezone

    return datetime.fromtimestamp(seconds, timezone.utc)


def _sqlite_leaderships(tmp_path, *data_dirs: str, lease: float = 60.0):
    """One SQLite ledger, and the leadership of a service for each of `data_dirs`
    (as `rayfarm serve` opens it); the engines are disposed of by the caller."""
    ledger = f"sqlite:///{tmp_path / 'ledger.sqlite3'}"
    out = []
    for name in data_dirs:
        settings = Settings(data_dir=tmp_path / name, database_url=ledger,
                            leader_lease_seconds=lease)
        engine, sessions = open_ledger(settings)
        out.append((open_leadership(settings, engine), engine, sessions))
    return out


def test03_one_scheduler_per_sqlite_ledger_whatever_the_data_dirs(tmp_path):
    (a, ea, _), (b, eb, _) = _sqlite_leaderships(tmp_path, "data-a", "data-b")
    try:
        a._attempt()
        b._attempt()
        assert a.leading() and not b.leading(), "two services on one ledger both lead"
        assert b.status()["holder"] == a.identity and b.status()["epoch"] == 1
        a.stop()  # a clean stop releases the lease at once
        b._attempt()
        assert b.leading() and b.epoch == 2
    finally:
        a.stop()
        b.stop()
        ea.dispose()
        eb.dispose()


def test03b_on_sqlite_a_fenced_commit_after_a_takeover_rolls_back(tmp_path):
    (a, ea, sessions), (b, eb, _) = _sqlite_leaderships(tmp_path, "data", "data")
    try:
        a.guard(sessions)
        a._attempt()
        assert a.leading()
        with sessions.begin() as session:
            session.add(User(name="probe", role="artist", share=1.0, created=utcnow()))
        with a.fenced(), pytest.raises(LeadershipLost):
            with sessions.begin() as session:
                session.get(User, "probe").share = 2.0  # written by a leader about to be deposed
                # Meanwhile the lease expired (a stalled a while still holding
                # its lock file) and b took it.
                with eb.begin() as conn:
                    conn.execute(update(SchedulerLease.__table__).values(expires_at=_utc(0)))
                b._attempt()
                assert b.leading()
        with sessions() as session:
            assert session.get(User, "probe").share == 1.0, "the fenced write stood"
        a._attempt()  # the deposed leader's lock file proves nothing: it stays a standby
        assert not a.leading() and b.leading()
        with a.fenced(), sessions.begin() as session:  # while a leads again, it commits
            b.stop()
            a._attempt()
            session.get(User, "probe").share = 4.0
        with sessions() as session:
            assert session.get(User, "probe").share == 4.0
    finally:
        a.stop()
        b.stop()
        ea.dispose()
        eb.dispose()


_LEADER = """
import sys, time
from service.db import open_ledger
from service.leader import open_leadership
from service.settings import Settings
settings = Settings(data_dir=sys.argv[1], database_url=sys.argv[2], leader_lease_seconds=60)
leadership = open_leadership(settings, open_ledger(settings)[0])
leadership._attempt()
print("leading" if leadership.leading() else "standby", flush=True)
time.sleep(600)
"""


def test03c_on_sqlite_a_killed_leader_is_replaced_at_once_not_after_its_lease(tmp_path):
    """The lease lasts a minute; the leader's lock file beside the ledger,
    dropped by the kernel when the process dies, lets a standby take over at once."""
    [(b, eb, _)] = _sqlite_leaderships(tmp_path, "data-b")
    log = tmp_path / "leader.log"
    leader = Child([sys.executable, "-c", _LEADER, str(tmp_path / "data-a"),
                    f"sqlite:///{tmp_path / 'ledger.sqlite3'}"], dict(os.environ), log)
    try:
        wait_for(lambda: "leading" in leader.log() or leader.proc.poll() is not None, 60,
                 "the other process to lead")
        assert "leading" in leader.log(), leader.log()
        b._attempt()
        assert not b.leading(), "a standby led beside a live leader"
        leader.kill_group(signal.SIGKILL)
        leader.proc.wait(10)
        b._attempt()
        assert b.leading() and b.epoch == 2, b.status()
        assert b.status()["expires_in"] > 50
    finally:
        leader.stop()
        b.stop()
        eb.dispose()


# -- real `rayfarm serve` replicas ------------------------------------------------------

@pytest.fixture
def spawn_replica(tmp_path):
    """spawn_replica(**env) -> (child, base URL): `rayfarm serve` (embedded
    executor, one render process) on a free port and the shared data dir."""
    children: list[Child] = []

    def spawn(**env: str) -> tuple[Child, str]:
        child, base = start_serve(
            embedded_env(tmp_path / "data", RAYFARM_LOCAL_WORKERS="1",
                         RAYFARM_LEADER_LEASE_SECONDS="2", **env),
            tmp_path / f"replica-{len(children)}.log")
        children.append(child)
        return child, base

    yield spawn
    for child in children:
        child.stop()


def health(base: str) -> dict:
    return httpx.get(f"{base}/healthz", timeout=5).json()


def api(base: str, method: str, path: str, **kwargs):
    response = httpx.request(method, f"{base}{path}", headers=ADMIN_HEADERS, timeout=10, **kwargs)
    assert response.status_code < 300, response.text
    return response.json()


class EventReader(threading.Thread):
    """Reads a job's event stream (`GET /jobs/{id}/events`) into `seen`."""

    def __init__(self, url: str):
        super().__init__(daemon=True)
        self.url, self.seen = url, []

    def run(self) -> None:
        with httpx.stream("GET", self.url, headers=ADMIN_HEADERS, timeout=240) as response:
            kind = None
            for line in response.iter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: ") and kind:
                    self.seen.append((kind, json.loads(line[6:])))
                    if kind == "end":
                        return

    def kinds(self) -> list[str]:
        return [kind for kind, _ in self.seen]


def test04_two_services_on_one_sqlite_file_never_both_schedule(spawn_replica):
    first, a = spawn_replica()
    second, b = spawn_replica()
    assert health(a)["leadership"]["role"] == "leader"
    standby = health(b)
    assert standby["leadership"]["role"] == "standby" and standby["scheduler"] == "standby"
    assert standby["leadership"]["holder"] == health(a)["leadership"]["replica"]
    assert "another service runs the scheduler" in second.log()
    # Submitted to the standby, run by the leader.
    # Paused until the stream below has subscribed: on a loaded machine a
    # stream opened after the submit found the job done, with no live event.
    # 4096 spp (a few seconds of units) so the pause comes before the end.
    job = api(b, "POST", "/jobs", json=dict(TINY, spp=4096))
    api(b, "POST", f"/jobs/{job['id']}/pause")
    # A stream on the standby follows the job the leader renders (the standby
    # reads the changes from the ledger: service.ledger_watch) to its end.
    stream = EventReader(f"{b}/jobs/{job['id']}/events")
    stream.start()
    wait_for(lambda: stream.seen, 30, "the stream's first event")
    api(b, "POST", f"/jobs/{job['id']}/resume")
    wait_for(lambda: api(b, "GET", f"/jobs/{job['id']}")["status"] == "done", 120,
             "the job to be done")
    stream.join(30)
    assert not stream.is_alive(), f"the standby's stream did not end: {stream.kinds()}"
    assert stream.seen[-1] == ("end", {"job_id": job["id"], "status": "done"})
    assert {"unit", "preview"} <= set(stream.kinds()), stream.kinds()
    # Each unit is seen done: in a unit event, or in the snapshot the stream
    # opened with (a unit may finish before the stream subscribes).
    done_units = {d["index"] for k, d in stream.seen if k == "unit" and d["state"] == "done"}
    done_units |= {u["index"] for k, d in stream.seen if k == "units" for u in d
                   if u["state"] == "done"}
    assert done_units == set(range(len(api(b, "GET", f"/jobs/{job['id']}/units"))))
    assert health(b)["scheduler_ticks"] == 0, "the standby scheduled"
    first.kill_group(signal.SIGKILL)  # the kernel drops its lock: the standby takes over
    wait_for(lambda: health(b)["leadership"]["role"] == "leader", 10, "the standby to lead")
    wait_for(lambda: health(b)["scheduler_ticks"] > 0, 10, "the new leader to tick")


def test04b_a_service_with_another_data_dir_on_the_same_sqlite_ledger_refuses_to_start(
        tmp_path):
    """Two `rayfarm serve` named one SQLite ledger by RAYFARM_DATABASE_URL and
    given different data dirs: the second refuses to start, naming both data
    dirs, and every unit of the first one's jobs runs once."""
    ledger = f"sqlite:///{tmp_path / 'ledger.sqlite3'}"
    mine, other = tmp_path / "data-a", tmp_path / "data-b"
    first, a = start_serve(embedded_env(mine, RAYFARM_DATABASE_URL=ledger,
                                        RAYFARM_LOCAL_WORKERS="1"), tmp_path / "a.log")
    second = None
    try:
        jobs = [api(a, "POST", "/jobs", json=dict(TINY, spp=64, seed=seed)) for seed in (1, 2, 3)]
        second = Child([*rayfarm_command(), "serve", "--host", "127.0.0.1", "--port",
                        str(free_port())],
                       embedded_env(other, RAYFARM_DATABASE_URL=ledger), tmp_path / "b.log")
        wait_for(lambda: second.proc.poll() is not None, 120,
                 "the service with another data dir to refuse to start")
        assert second.proc.returncode == 2, second.log()
        assert str(mine.resolve()) in second.log() and str(other.resolve()) in second.log()
        for job in jobs:
            wait_for(lambda: api(a, "GET", f"/jobs/{job['id']}")["status"] in ("done", "failed"),
                     120, "the job to end")
            assert api(a, "GET", f"/jobs/{job['id']}")["status"] == "done"
            units = api(a, "GET", f"/jobs/{job['id']}/units")
            assert all(u["tasks"] == 1 for u in units), [u["tasks"] for u in units]
        assert health(a)["leadership"]["role"] == "leader"
    finally:
        if second is not None:
            second.stop()
        first.stop()


def _replica_pair(spawn_replica, postgres_url: str, **env: str):
    """Two replicas on one PostgreSQL ledger and one data dir; the first leads."""
    env.setdefault("RAYFARM_DATABASE_URL", postgres_url)
    leader, a = spawn_replica(**env)
    standby, b = spawn_replica(**env)
    first, second = health(a)["leadership"], health(b)["leadership"]
    assert first["role"] == "leader" and second["role"] == "standby", (first, second)
    assert second["holder"] == first["replica"] and second["epoch"] == 1
    return (leader, a), (standby, b)


def test05_the_leader_killed_mid_job_the_standby_finishes_it_bit_identical(
        postgres_url, spawn_replica, reference_channels, tmp_path):
    """Two replicas on PostgreSQL: a stream on B follows a job submitted to A
    and run by A's scheduler (events relayed); A is SIGKILLed mid-job; B takes
    over, renders again only the units A had in flight, and the result is
    bit-identical to an undisturbed render."""
    (leader, a), (_, b) = _replica_pair(spawn_replica, postgres_url)
    # 64 units, long enough (32768 samples each: about a second in all) that
    # some are in flight at the kill. At 8192 samples a unit the first 16 were
    # done in a few tens of milliseconds, sooner than the stream below had
    # connected when another test process kept the cores busy.
    body = dict(TINY, width=64, height=64, tile_size=8, spp=512, progressive=False)
    job = api(a, "POST", "/jobs", json=body)
    stream = EventReader(f"{b}/jobs/{job['id']}/events")
    stream.start()
    wait_for(lambda: stream.seen, 60, "the standby's stream to open with the job's snapshot")
    assert stream.seen[0][0] == "job" and stream.seen[0][1]["status"] != "done", stream.seen[:1]

    def relayed() -> list[dict]:
        """What B's stream had from A's scheduler: it came through the relay."""
        return [data for kind, data in stream.seen if kind == "unit" and data["state"] == "done"]

    wait_for(lambda: api(b, "GET", f"/jobs/{job['id']}")["progress"]["units_done"] >= 16
             and relayed(), 120, "a quarter of the units to be done, and a unit event from the "
             "leader on the standby's stream")
    leader.kill_group(signal.SIGKILL)  # the service and its render process
    killed = time.monotonic()
    # The ledger at the kill (the dead leader writes nothing more): what was
    # done must never be rendered again; what was in flight may be, once.
    at_kill = {u["index"]: u for u in api(b, "GET", f"/jobs/{job['id']}/units")}
    assert health(b)["scheduler_ticks"] == 0, "the standby scheduled while the leader lived"
    wait_for(lambda: health(b)["scheduler_ticks"] > 0, 15, "the standby's first tick",
             interval=0.02)
    failover = time.monotonic() - killed
    assert health(b)["leadership"]["epoch"] == 2
    stream.join(180)
    assert stream.seen[-1] == ("end", {"job_id": job["id"], "status": "done"}), stream.seen[-3:]
    done = api(b, "GET", f"/jobs/{job['id']}")
    assert done["status"] == "done", done["error"]
    units = {u["index"]: u for u in api(b, "GET", f"/jobs/{job['id']}/units")}
    finished_before = [i for i, u in at_kill.items() if u["state"] == "done"]
    in_flight = [i for i, u in at_kill.items() if u["state"] in ("queued", "running")]
    rendered_again = [i for i in finished_before if units[i]["tasks"] != at_kill[i]["tasks"]]
    assert not rendered_again, f"units done before the kill ran again: {rendered_again}"
    retried = [i for i, u in units.items() if u["tasks"] > 1]
    assert set(retried) <= set(in_flight), (retried, in_flight)
    assert done["progress"]["samples_done"] == 64 * 64 * body["spp"], "a unit was counted twice"
    print(f"\nfailover (SIGKILL of the leader -> the standby's first tick): {failover:.2f} s "
          f"with a 2 s lease; {len(finished_before)} units done before the kill, "
          f"{len(in_flight)} in flight, {len(retried)} rendered again; states at the kill: "
          f"{dict(Counter(u['state'] for u in at_kill.values()))}")
    exr = tmp_path / "result.exr"
    exr.write_bytes(httpx.get(f"{b}/jobs/{job['id']}/result.exr", headers=ADMIN_HEADERS,
                              timeout=30).content)
    assert_bit_identical(channels_of(exr), reference_channels(body))


@pytest.mark.farm
def test06_on_celery_the_leader_killed_mid_job_leaves_no_unit_rendered_twice(
        postgres_url, redis_url, spawn_worker, spawn_replica, reference_channels, tmp_path):
    """The same on the Celery farm: the units in flight at the kill go on
    rendering on the workers, and the new leader collects their results from
    the broker; nothing is rendered again and the EXR is bit-identical."""
    spawn_worker(concurrency=2)
    farm = dict(RAYFARM_DATABASE_URL=postgres_url, RAYFARM_BROKER_URL=redis_url)
    (leader, a), (_, b) = _replica_pair(spawn_replica, postgres_url, **farm)
    body = dict(TINY, width=64, height=64, tile_size=8, spp=128, progressive=False)
    job = api(a, "POST", "/jobs", json=body)
    wait_for(lambda: api(b, "GET", f"/jobs/{job['id']}")["progress"]["units_done"] >= 16, 120,
             "a quarter of the units to be done")
    leader.kill_group(signal.SIGKILL)
    at_kill = {u["index"]: u for u in api(b, "GET", f"/jobs/{job['id']}/units")}
    wait_for(lambda: api(b, "GET", f"/jobs/{job['id']}")["status"] == "done", 120,
             "the standby to finish the job")
    units = {u["index"]: u for u in api(b, "GET", f"/jobs/{job['id']}/units")}
    assert all(u["tasks"] == 1 for u in units.values()), \
        {i: (u["tasks"], u["requeue_reason"]) for i, u in units.items() if u["tasks"] > 1}
    assert api(b, "GET", f"/jobs/{job['id']}")["progress"]["samples_done"] == 64 * 64 * 128
    print(f"\ncelery failover: {sum(u['state'] == 'done' for u in at_kill.values())} units done "
          f"at the kill, {sum(u['state'] in ('queued', 'running') for u in at_kill.values())} "
          "in flight, 0 rendered again")
    exr = tmp_path / "result.exr"
    exr.write_bytes(httpx.get(f"{b}/jobs/{job['id']}/result.exr", headers=ADMIN_HEADERS,
                              timeout=30).content)
    assert_bit_identical(channels_of(exr), reference_channels(body))
