"""Per-unit logs: what a unit's render process logged, and its traceback if it
failed, kept by the service per task (GET /jobs/{id}/units/{i}/log, `rayfarm
logs`), on the embedded pool and on a real Celery worker; and JSON logs.

A unit that fails for real: the scene's text in the store is replaced before
the job is submitted (the store keeps an existing content-addressed file), so
every render process that loads it raises "does not match its hash".
"""

from __future__ import annotations

import json
import logging
import secrets
import subprocess

import httpx
import pytest
from fastapi.testclient import TestClient

from conftest import (ADMIN_HEADERS, TINY, get_json, poll_job, rayfarm_command, submit,
                      wait_for)

UNIT_LINE = "unit 0 (tile, stage 0) of path"  # renderer.runtime logs one per unit
HASH_ERROR = "does not match its hash"


def poisoned_scene(scene_path) -> dict:
    """An inline scene of a new hash whose stored text is tampered with (see the
    module doc); `scene_path(hash)` is where the service's store keeps it."""
    from renderer import resolve_document, scene_text

    doc = resolve_document("cornell-box")
    doc["name"] = f"poison-{secrets.token_hex(6)}"
    key, text = scene_text(resolve_document(doc, allow_files=False))
    path = scene_path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text.replace(doc["name"], "tampered"))
    return doc


def assert_failed_three_times(log: dict) -> None:
    assert log["state"] == "failed" and HASH_ERROR in log["error"], log
    attempts = log["attempts"]
    assert [a["task"] for a in attempts] == [1, 2, 3], attempts
    for attempt in attempts:
        assert attempt["outcome"] == "failed"
        assert "Traceback (most recent call last)" in attempt["traceback"]
        assert HASH_ERROR in attempt["traceback"] and "renderer/runtime.py" in attempt["traceback"]


# -- the capture itself ------------------------------------------------------------------

def test01_the_capture_keeps_a_bounded_tail_and_the_traceback():
    from renderer.unitlog import capture_unit_log, unit_context

    logger = logging.getLogger("renderer.test-unitlog")
    with pytest.raises(ZeroDivisionError):
        with capture_unit_log("job1", 4, max_lines=5) as captured:
            assert unit_context.get() == ("job1", 4)
            for i in range(12):
                logger.info("line %d", i)
            1 / 0
    assert unit_context.get() is None
    data = captured.to_dict()
    assert [line.rsplit(" ", 1)[1] for line in data["lines"]] == ["7", "8", "9", "10", "11"]
    assert data["dropped"] == 7
    assert "ZeroDivisionError" in data["traceback"] and "1 / 0" in data["traceback"]
    assert captured not in logging.getLogger().handlers  # removed after the block


def test02_json_lines_carry_the_unit_ids_while_it_renders():
    from renderer.unitlog import JsonLogFormatter, unit_context

    record = logging.LogRecord("renderer.x", logging.WARNING, __file__, 1, "half %s", ("done",),
                               None)
    plain = json.loads(JsonLogFormatter().format(record))
    assert plain["message"] == "half done" and plain["level"] == "WARNING"
    assert plain["logger"] == "renderer.x" and "job_id" not in plain and plain["time"]
    token = unit_context.set(("abc123", 7))
    try:
        inside = json.loads(JsonLogFormatter().format(record))
    finally:
        unit_context.reset(token)
    assert (inside["job_id"], inside["unit"]) == ("abc123", 7)


# -- the embedded pool -------------------------------------------------------------------

def test03_embedded_a_done_units_lines_and_a_failed_units_tracebacks(local_app, local_client,
                                                                      make_user):
    get = get_json(local_client)
    done = poll_job(get, submit(local_client, dict(TINY, seed=1201))["id"])
    assert done["status"] == "done", done
    log = get(f"/jobs/{done['id']}/units/0/log")
    assert log["state"] == "done" and log["error"] is None
    [attempt] = log["attempts"]
    assert attempt["outcome"] == "done" and attempt["traceback"] is None
    assert attempt["worker"].startswith("local@")
    assert any(UNIT_LINE in line for line in attempt["lines"]), attempt["lines"]

    store = local_app.state.farm.store
    body = dict(TINY, scene=poisoned_scene(store.scene_path), progressive=False)
    failed = poll_job(get, submit(local_client, body)["id"])
    assert failed["status"] == "failed" and "failed after 3 attempts" in failed["error"], failed
    units = get(f"/jobs/{failed['id']}/units")
    [bad] = [u["index"] for u in units if u["state"] == "failed"]
    assert_failed_three_times(get(f"/jobs/{failed['id']}/units/{bad}/log"))

    # Access as for the job itself: a stranger sees no such job; bad indices are named.
    stranger = make_user("unitlog-stranger")
    response = stranger.get(f"/jobs/{done['id']}/units/0/log")
    assert response.status_code == 404 and done["id"] in response.text
    missing = local_client.get(f"/jobs/{done['id']}/units/999/log")
    assert missing.status_code == 404 and "no unit 999" in missing.text
    assert local_client.get(f"/jobs/{done['id']}/units/-1/log").status_code == 422
    assert local_client.get(f"/jobs/{done['id']}/units/x/log").status_code == 422
    anonymous = TestClient(local_app)  # no token at all
    assert anonymous.get(f"/jobs/{done['id']}/units/0/log").status_code == 401


# -- a real Celery worker, `rayfarm logs`, JSON logs ---------------------------------------

@pytest.mark.farm
def test04_celery_logs_reach_the_service_the_cli_prints_them_json_logs(
        spawn_serve, spawn_worker, tmp_path):
    # No blocklisting: with one worker, the poisoned job's third failed unit would
    # blocklist it and fail the job before any unit spends its three attempts.
    child, base = spawn_serve(RAYFARM_LOG_FORMAT="json", RAYFARM_POLL_INTERVAL="0.05",
                              RAYFARM_WORKER_FAILURES_PER_JOB="0")
    worker = spawn_worker(concurrency=1, RAYFARM_LOG_FORMAT="JSON")
    scenes = tmp_path / "serve-data" / "store" / "scenes"  # spawn_serve's data dir
    with httpx.Client(base_url=base, headers=ADMIN_HEADERS, timeout=30) as client:
        get = get_json(client)
        done = poll_job(get, client.post("/jobs", json=dict(TINY, seed=1202)).json()["id"])
        assert done["status"] == "done", done
        poison = poisoned_scene(lambda key: scenes / f"{key}.json")
        failed = poll_job(get, client.post("/jobs", json=dict(
            TINY, scene=poison, progressive=False)).json()["id"])
        assert failed["status"] == "failed", failed
        log = get(f"/jobs/{done['id']}/units/0/log")
        [attempt] = log["attempts"]
        assert attempt["worker"] == f"rayfarm-{worker.pid}@{attempt['worker'].split('@')[1]}"
        assert any(UNIT_LINE in line for line in attempt["lines"]), attempt
        [bad] = [u["index"] for u in get(f"/jobs/{failed['id']}/units") if u["state"] == "failed"]
        assert_failed_three_times(get(f"/jobs/{failed['id']}/units/{bad}/log"))

    def logs(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([*rayfarm_command(), "logs", "--server", base, *args],
                              capture_output=True, text=True, timeout=60)

    # The units worth reading: the failed one, and those that failed an attempt too.
    printed = logs(failed["id"])
    assert printed.returncode == 0, printed.stderr
    section = printed.stdout.split(f"== unit {bad} (failed)", 1)[1].split("\n== unit", 1)[0]
    assert section.count("Traceback (most recent call last)") == 3, printed.stdout
    assert "-- task 3, attempt 3: failed" in section and HASH_ERROR in section
    one = logs(done["id"], "0")
    assert one.returncode == 0 and UNIT_LINE in one.stdout and "Traceback" not in one.stdout
    quiet = logs(done["id"])
    assert quiet.returncode == 0 and "no unit" in quiet.stderr and quiet.stdout == ""
    assert logs(done["id"], "999").returncode == 1

    # RAYFARM_LOG_FORMAT=json: the worker's unit lines are JSON with the unit's ids,
    # and so are the service's own log lines.
    def json_lines(text: str) -> list[dict]:
        out = []
        for line in text.splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if isinstance(entry, dict):
                out.append(entry)
        return out

    wait_for(lambda: any(e.get("job_id") == done["id"] for e in json_lines(worker.log())), 10,
             "the worker's JSON lines of the job")
    unit_lines = [e for e in json_lines(worker.log()) if e.get("job_id") == done["id"]]
    assert {"time", "level", "logger", "message", "unit"} <= set(unit_lines[0])
    assert any(e["logger"] == "renderer.runtime" and e["unit"] == 0 for e in unit_lines)
    served = json_lines(child.log())
    assert any(e["logger"].startswith("uvicorn") for e in served), child.log()[-2000:]
    assert not any(line.startswith("INFO:") for line in child.log().splitlines())
