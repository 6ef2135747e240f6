"""/healthz when parts are missing: the service degrades, it does not fall over."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.main import create_app
from service.settings import Settings

from conftest import ADMIN_HEADERS, TINY, free_port, wait_for


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
