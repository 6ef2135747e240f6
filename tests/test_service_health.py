"""/healthz when parts are missing: the service degrades, it does not fall over.
A full disk too: what is stored is served, new work is refused (507) until
there is room, and authentication only reads."""

from __future__ import annotations

import shutil
from collections import namedtuple

from fastapi.testclient import TestClient
from sqlalchemy import event

from service.main import create_app
from service.settings import Settings

from conftest import ADMIN_HEADERS, TINY, free_port, get_json, poll_job, submit, wait_for


def test01_unreachable_broker_is_degraded_and_jobs_wait(tmp_path):
    dead_broker = f"redis://127.0.0.1:{free_port()}/0"  # nothing listens there
    settings = Settings(data_dir=tmp_path / "data", broker_url=dead_broker, poll_interval=0.05)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        health = client.get("/healthz")
        assert health.status_code == 200
        assert health.json()["status"] == "degraded"
        assert health.json()["broker"].startswith("unreachable")
        response = client.post("/jobs", json=TINY)
        assert response.status_code == 201
        job_id = response.json()["id"]
        wait_for(lambda: "scheduler_error" in client.get("/healthz").json(), 30,
                 "the scheduler to report the broker error")
        health = client.get("/healthz").json()
        assert health["scheduler"] == "running", "a failing tick must not kill the scheduler"
        # Planned, but nothing could be enqueued: the units wait as pending.
        units = client.get(f"/jobs/{job_id}/units").json()
        assert units and all(u["state"] == "pending" and u["tasks"] == 0 for u in units)
        assert client.post(f"/jobs/{job_id}/cancel").json()["status"] == "canceled"


def test02_stopped_scheduler_is_unhealthy(local_client):
    farm = local_client.app.state.farm
    farm.scheduler.stop()
    try:
        health = local_client.get("/healthz")
        assert health.status_code == 503 and health.json()["status"] == "unhealthy"
        assert health.json()["scheduler"] == "stopped"
    finally:
        farm.scheduler.start()
    assert local_client.get("/healthz").status_code == 200


# -- a full disk degrades the farm, it does not fail it -----------------------------------------

def _low_space(monkeypatch, free: int) -> None:
    """The data dir's file system has `free` bytes free, as statvfs would say."""
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 << 30, 10 << 30, free))


def _refused_for_room(response) -> str:
    assert response.status_code == 507, response.text
    assert int(response.headers["retry-after"]) >= 1
    return response.json()["detail"]


def test03_a_full_data_dir_refuses_new_work_with_507_and_serves_what_is_stored(tmp_path,
                                                                              monkeypatch):
    settings = Settings(data_dir=tmp_path / "data", local_workers=1, poll_interval=0.05,
                        min_free_bytes=1 << 20)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        job = poll_job(get_json(client), submit(client, TINY)["id"])
        image = client.get(job["result_url"]).content
        _low_space(monkeypatch, 4096)
        detail = _refused_for_room(client.post("/jobs", json=TINY))
        assert "4096 bytes free" in detail and "RAYFARM_MIN_FREE_BYTES" in detail
        _refused_for_room(client.post("/experiments", json={
            "scene": "cornell-box", "width": 8, "height": 8, "spp": [1, 2], "repeats": 2,
            "configs": [{"method": "path"}]}))
        _refused_for_room(client.post("/scenes", files={"scene": ("room.json", b"{}")}))
        health = client.get("/healthz")
        assert health.status_code == 200 and health.json()["status"] == "degraded"
        assert any(r.startswith("disk:") and "4096 bytes free" in r
                   for r in health.json()["reasons"]), health.json()
        # What is stored is served: the job, its image.
        assert client.get(f"/jobs/{job['id']}").json()["status"] == "done"
        assert client.get(job["result_url"]).content == image
        monkeypatch.undo()  # room again
        assert client.post("/jobs", json=TINY).status_code == 201
        assert "reasons" not in client.get("/healthz").json()
    uploads = tmp_path / "data" / "uploads"  # the upload was not read
    assert not uploads.exists() or list(uploads.iterdir()) == []


def test04_a_ledger_that_cannot_write_authenticates_reads_and_refuses_new_work(tmp_path):
    """A read-only ledger (SQLite's query_only), then a full one (max_page_count
    at its page count: SQLITE_FULL, what a full disk gives): a token never used
    before still works, what is stored is read, new work is a 507, /healthz
    says why; once there is room, all is as before."""
    from service import auth
    from service.models import utcnow

    ledger = {"state": "ok"}

    def on_checkout(dbapi_conn, _record, _proxy):  # every connection the farm takes
        cursor = dbapi_conn.cursor()
        cursor.execute(f"PRAGMA query_only = {'ON' if ledger['state'] == 'read-only' else 'OFF'}")
        pages = cursor.execute("PRAGMA page_count").fetchone()[0]
        cursor.execute(f"PRAGMA max_page_count = {pages if ledger['state'] == 'full' else 1 << 30}")
        cursor.close()

    settings = Settings(data_dir=tmp_path / "data", local_workers=1, poll_interval=0.05)
    app = create_app(settings)
    with TestClient(app, headers=ADMIN_HEADERS) as client:
        farm = app.state.farm
        event.listen(farm.engine, "checkout", on_checkout)
        job = poll_job(get_json(client), submit(client, TINY)["id"])
        with farm.sessions.begin() as session:
            auth.add_user(session, "nia", "artist", utcnow())
            _, secret = auth.create_token(session, "nia", utcnow())
        nia = TestClient(app, headers={"Authorization": f"Bearer {secret}"})

        ledger["state"] = "read-only"
        assert nia.get("/auth/me").json()["user"] == "nia"  # its last_used could not be written
        assert nia.get("/jobs").status_code == 200
        assert client.get(f"/jobs/{job['id']}").json()["status"] == "done"
        assert client.get(job["result_url"]).status_code == 200
        assert "read-only" in _refused_for_room(nia.post("/jobs", json=TINY))
        health = client.get("/healthz").json()
        assert health["status"] == "degraded" and health["ledger_writes"] == "failing", health
        assert any(r.startswith("disk:") and "read-only" in r for r in health["reasons"])

        ledger["state"] = "ok"
        assert client.post("/jobs", json=TINY).status_code == 201  # room again at once
        ledger["state"] = "full"
        refused = None
        for _ in range(50):  # jobs (and their units) fill the pages left
            response = client.post("/jobs", json=TINY)
            if response.status_code != 201:
                refused = response
                break
        assert refused is not None, "the ledger never filled"
        assert "the ledger is full" in _refused_for_room(refused)
        # Health reports the last write's outcome: an update in place that fits
        # the full file (a unit of the jobs above landing) may succeed in
        # between, and the scheduler's next insert fails again.
        wait_for(lambda: any("the ledger is full" in r
                             for r in client.get("/healthz").json().get("reasons", ())),
                 30, "/healthz to say the ledger is full")
        assert client.get("/jobs").status_code == 200

        ledger["state"] = "ok"
        assert nia.post("/jobs", json=TINY).status_code == 201
        assert client.get("/healthz").json()["ledger_writes"] == "ok"
        assert client.get(f"/jobs/{job['id']}").json()["status"] == "done"
