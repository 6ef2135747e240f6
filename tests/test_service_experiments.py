"""The estimator lab through the API (service.experiments): an experiment's
jobs run on the farm as ordinary jobs; when they are done its report says,
from the renders themselves, that path tracing is unbiased and consistent
and rasterization (no indirect light) is neither; CSV and figures follow;
bad experiments are 422s naming the field."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from conftest import wait_for

SMALL = {"scene": "cornell-box", "width": 16, "height": 16, "depth": 3, "repeats": 3,
         "spp": [2, 8], "block": 8, "configs": [{"method": "path-mis"}, {"method": "raster"}]}
# long enough to be running still when a test cancels it
LONG = {**SMALL, "spp": [4096], "repeats": 2, "configs": [{"method": "path-mis"}]}


def finished(client, experiment_id: str, timeout: float = 300) -> dict:
    def done():
        body = client.get(f"/experiments/{experiment_id}").json()
        return body if body["status"] != "running" else None
    return wait_for(done, timeout, "the experiment to finish", interval=0.2)


@pytest.fixture(scope="module")
def small(local_client):
    response = local_client.post("/experiments", json=SMALL)
    assert response.status_code == 201, response.text
    created = response.json()
    assert response.headers["location"] == f"/experiments/{created['id']}"
    return created, finished(local_client, created["id"])


def test01_an_experiment_runs_as_jobs_and_measures_bias_and_consistency(local_client, small):
    created, body = small
    assert created["status"] == "running" and created["jobs_total"] == 2 * 2 * 3 + 1
    assert body["status"] == "done", body["error"]
    assert body["jobs_done"] == body["jobs_total"] == 13
    seeds = set()
    for run in body["runs"]:  # ordinary jobs, each with its own derived seed
        job = local_client.get(f"/jobs/{run['job']}").json()
        assert job["status"] == "done" and job["spp"] == run["spp"] and job["width"] == 16
        seeds.add(job["seed"])
    assert len(seeds) == 12
    path, raster = body["report"]
    assert path["label"] == "path-mis" and raster["label"] == "raster"
    assert path["unbiased"] and path["consistent"]
    assert -0.8 < path["slope"] < -0.25  # 1/sqrt(spp), within what 3 repeats can show
    assert not raster["unbiased"] and raster["levels"][-1]["relative_bias"] < -0.1
    assert not raster["consistent"]
    blocks = raster["levels"][-1]["block_t"]  # 16 x 16 pixels: 2 x 2 blocks of 8
    assert len(blocks) == 2 and all(len(row) == 2 for row in blocks)
    assert sum(t is None or abs(t) > 4 for row in blocks for t in row) >= 3
    for level in path["levels"]:
        assert level["efficiency"] == pytest.approx(1 / (level["mse"] * level["seconds"]))
        assert level["rmse"] == pytest.approx(np.sqrt(level["mse"]))


def test02_csv_and_figures(local_client, small):
    _, body = small
    text = local_client.get(body["csv_url"])
    assert text.status_code == 200 and text.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(text.text)))
    assert [(r["label"], int(r["spp"])) for r in rows] == [
        ("path-mis", 2), ("path-mis", 8), ("raster", 2), ("raster", 8)]
    assert float(rows[1]["rmse"]) == pytest.approx(body["report"][0]["levels"][1]["rmse"])
    for url in (body["plot_url"], body["maps_url"]):
        png = local_client.get(url)
        assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert local_client.get(f"/experiments/{body['id']}/other.png").status_code == 404
    listed = local_client.get("/experiments").json()
    assert body["id"] in [e["id"] for e in listed]


def test03_bad_experiments_are_422s_naming_the_field(local_client):
    cases = [
        ({"spp": [8, 2]}, "spp"),
        ({"configs": [{"method": "nope"}]}, "configs"),
        ({"configs": [{"method": "path-mis"}, {"method": "path"}]}, "configs"),  # one label twice
        ({"repeats": 1}, "repeats"),
        ({"repeats": 64, "spp": [1, 2, 4, 8, 16, 32, 64, 128]}, "repeats"),  # above the job limit
        ({"block": 32}, "block"),
        ({"reference": {"job": "0123456789ab"}}, "reference"),
        ({"configs": [{"method": "path-mis", "options": {"bogus": 1}}]}, "configs"),
    ]
    for change, field in cases:
        response = local_client.post("/experiments", json={**SMALL, **change})
        assert response.status_code == 422, (change, response.text)
        assert field in str(response.json()["detail"]), (change, response.text)


def test04_a_canceled_experiment_cancels_its_jobs(local_client):
    body = local_client.post("/experiments", json=LONG).json()
    canceled = local_client.post(f"/experiments/{body['id']}/cancel")
    assert canceled.status_code == 200 and canceled.json()["status"] == "canceled"
    for run in canceled.json()["runs"]:
        assert local_client.get(f"/jobs/{run['job']}").json()["status"] in ("canceled", "done")
    assert local_client.post(f"/experiments/{body['id']}/cancel").status_code == 409


def cancels(session) -> bool:
    """Whether a flush is the cancel's (a job marked canceled), not one of
    the scheduler's, whose thread shares the sessionmaker."""
    from service.models import Job

    return any(isinstance(row, Job) and row.status == "canceled" for row in session.dirty)


def cancel_raced(farm, client, experiment_id: str, job_id: str, race) -> tuple:
    """POST the experiment's cancel while `race(session)` says, at each of
    its flushes, whether the scheduler changes job `job_id` first (its
    version bumped from another connection, as the scheduler's write would).
    Returns the response and the number of races run."""
    from sqlalchemy import event, update

    from service.models import Job

    raced = []

    def scheduler_meanwhile(session, flush_context, instances):
        if cancels(session) and race(session, raced):
            raced.append(session)
            with farm.engine.begin() as other:
                other.execute(update(Job).where(Job.id == job_id)
                              .values(version=Job.version + 1))

    event.listen(farm.sessions, "before_flush", scheduler_meanwhile)
    try:
        return client.post(f"/experiments/{experiment_id}/cancel"), len(raced)
    finally:
        event.remove(farm.sessions, "before_flush", scheduler_meanwhile)


def test04b_a_cancel_whose_read_went_stale_is_tried_again_not_a_500(local_app, local_client):
    """The scheduler changes an experiment's jobs while the API cancels them
    (it plans them, units land): the cancel's write then matches no row
    (optimistic locking). The route must try again on the new state: a 200,
    never a 500 (CI once failed on exactly this race)."""
    body = local_client.post("/experiments", json=LONG).json()
    job = body["runs"][0]["job"]
    canceled, races = cancel_raced(local_app.state.farm, local_client, body["id"], job,
                                   lambda session, raced: not raced)  # once, before a write
    assert races == 1, "the hook never ran: the test no longer tests the race"
    assert canceled.status_code == 200, canceled.text
    assert canceled.json()["status"] == "canceled"
    assert local_client.get(f"/jobs/{job}").json()["status"] in ("canceled", "done")


def test04c_a_cancel_that_keeps_going_stale_is_a_409(local_app, local_client):
    """If the jobs change before every try, the cancel gives up with a 409
    that says to try again; the experiment is left running, not half done."""
    body = local_client.post("/experiments", json=LONG).json()
    # Before each try's first write: once a try has written, SQLite's lock
    # is the try's until it ends, and another writer would wait.
    refused, races = cancel_raced(local_app.state.farm, local_client, body["id"],
                                  body["runs"][0]["job"],
                                  lambda session, raced: not any(s is session for s in raced))
    assert refused.status_code == 409 and "keeps changing" in refused.json()["detail"]
    assert races == 5  # jobs.retrying's tries, each raced before its first write
    assert local_client.get(f"/experiments/{body['id']}").json()["status"] == "running"
    assert local_client.post(f"/experiments/{body['id']}/cancel").status_code == 200


def test05_an_experiments_jobs_count_against_the_submission_rate(local_client, local_settings,
                                                                make_user, monkeypatch):
    """An experiment creates as many jobs as a script posting them one by
    one, so it spends as many submissions of its token's minute: before, it
    bypassed the limit (294 jobs in 18 s against 60 a minute)."""
    monkeypatch.setattr(local_settings.limits_artist, "submissions_per_minute", 4)
    eve = make_user("eve-rates")
    three = {**SMALL, "spp": [2], "repeats": 2, "configs": [{"method": "raster"}],
             "reference": {"spp": 4}}  # 2 runs and a reference: 3 jobs
    first = eve.post("/experiments", json=three)
    assert first.status_code == 201, first.text
    second = eve.post("/experiments", json=three)
    assert second.status_code == 429, second.text
    assert 0 < int(second.headers["retry-after"]) <= 60
    job = eve.post("/jobs", json={"scene": "cornell-box", "method": "raster", "spp": 1,
                                  "depth": 1, "width": 8, "height": 8, "tile_size": 8})
    assert job.status_code == 201, job.text  # the minute's fourth
    too_big = eve.post("/experiments", json={**three, "repeats": 4})  # 5 jobs
    assert too_big.status_code == 422 and "repeats" in str(too_big.json()["detail"])
    assert "creates 5 jobs" in too_big.text
    cancel = eve.post(f"/experiments/{first.json()['id']}/cancel")
    assert cancel.status_code in (200, 409)  # 409: done already
