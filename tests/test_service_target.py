"""Jobs rendered to a noise target through the service (service/targets.py):
the pass barrier and its decisions give the same bytes as `render_to_target`
in this process; the job reports its error, its passes and why it stopped;
bad targets and methods that cannot take one are 422s naming the field.
(The Celery executor's run of the same job: test_farm_celery.)"""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import assert_bit_identical, channels_of, get_json, poll_job, submit
from test_service_events import read_events

# Small enough for seconds, noisy enough that tiles stop at different passes.
TARGET_JOB = {"scene": "cornell-box", "method": "path-mis", "depth": 5, "width": 32,
              "height": 32, "tile_size": 8, "seed": 3,
              "target": {"rel_error": 0.25, "max_spp": 1024}}


def target_reference(body: dict, path) -> dict[str, np.ndarray]:
    """The job rendered to its target by the renderer alone, as EXR channels."""
    from renderer import LocalPool, RenderSpec
    from renderer.target import Target, render_to_target

    spec = RenderSpec(**{k: body[k] for k in ("method", "depth", "width", "height", "tile_size",
                                              "seed")})
    with LocalPool(1) as pool:
        film, _ = render_to_target(body["scene"], spec, Target(**body["target"]), pool=pool)
    film.write_exr(path)
    return channels_of(path)


def assert_target_job(job: dict, body: dict) -> None:
    """A done target job's report: within its target, tiles skipped, passes logged."""
    target = body["target"]
    progress = job["progress"]
    assert job["status"] == "done" and job["target_stop"] == "target", job
    assert job["target"]["rel_error"] == target["rel_error"] and job["spp"] == target["max_spp"]
    assert progress["rel_error"] <= target["rel_error"] == progress["target_rel_error"]
    assert 0 < progress["units_skipped"] < progress["units_total"], progress
    assert progress["units_done"] == progress["units_total"]
    passes = job["passes"]
    assert [p["pass"] for p in passes] == list(range(len(passes)))
    assert all(a["spp"] < b["spp"] for a, b in zip(passes, passes[1:]))
    assert passes[-1]["rel_error"] == pytest.approx(progress["rel_error"])
    assert progress["samples_done"] < 32 * 32 * target["max_spp"]


def test01_a_target_job_stops_at_its_target_with_the_renderers_bytes(local_client, tmp_path):
    job = poll_job(get_json(local_client), submit(local_client, TARGET_JOB)["id"])
    assert_target_job(job, TARGET_JOB)
    exr = local_client.get(job["result_url"])
    assert exr.status_code == 200
    (tmp_path / "job.exr").write_bytes(exr.content)
    got = channels_of(tmp_path / "job.exr")
    assert_bit_identical(got, target_reference(TARGET_JOB, tmp_path / "ref.exr"))
    # Skipped tiles stopped early: the samples channel differs between tiles.
    assert len(np.unique(got["samples.Y"])) > 1

    from renderer import read_exr

    _, header = read_exr(tmp_path / "job.exr")
    assert json.loads(header["rayfarm.target"]) == {**TARGET_JOB["target"], "max_seconds": None}
    assert header["rayfarm.rel_error"] == pytest.approx(job["progress"]["rel_error"], rel=1e-6)
    units = local_client.get(f"/jobs/{job['id']}/units").json()
    assert sum(u["state"] == "skipped" for u in units) == job["progress"]["units_skipped"]
    assert {u["state"] for u in units} == {"done", "skipped"}


def test02_a_time_budget_stops_a_job_between_passes(local_client):
    body = dict(TARGET_JOB, target={"rel_error": 0.001, "max_spp": 4096, "max_seconds": 0.01})
    job = poll_job(get_json(local_client), submit(local_client, body)["id"])
    assert job["status"] == "done" and job["target_stop"] == "max_seconds", job
    error = job["progress"]["rel_error"]  # null: one pass of 1 spp has no variance yet
    assert error is None or error > 0.001
    assert len(job["passes"]) >= 1 and job["progress"]["units_skipped"] > 0


def test03_a_ceiling_that_comes_first_says_so(local_client):
    body = dict(TARGET_JOB, target={"rel_error": 0.001, "max_spp": 4})
    job = poll_job(get_json(local_client), submit(local_client, body)["id"])
    assert job["status"] == "done" and job["target_stop"] == "max_spp", job
    assert job["progress"]["units_skipped"] == 0 and job["samples"] == 32 * 32 * 4


@pytest.mark.parametrize("change,field,words", [
    ({"method": "photon"}, "target", "cannot render to a noise target"),
    ({"method": "bdpt"}, "target", "cannot render to a noise target"),
    ({"target": {"rel_error": 0.0, "max_spp": 64}}, "target.rel_error",
     "must be between 1e-06 and 1"),
    # (error / target)^2 overflowed in the ETA: every GET /jobs was a 500
    ({"target": {"rel_error": 1e-300, "max_spp": 64}}, "target.rel_error",
     "must be between 1e-06 and 1"),
    ({"target": {"rel_error": 0.1, "max_spp": 64, "max_seconds": 1e308}},
     "target.max_seconds", "at most 31622400"),
    ({"target": {"rel_error": 0.1, "max_spp": 0}}, "target.max_spp", "between"),
    ({"target": {"rel_error": 0.1, "max_spp": 64, "max_seconds": -1.0}},
     "target.max_seconds", "positive"),
    ({"target": {"rel_error": 0.1}}, "target.max_spp", "is required"),
    ({"spp": 16}, "spp", "target.max_spp is 1024"),
    ({"target": None}, "spp", "is required"),
    ({"target": {"rel_error": 0.1, "max_spp": 64, "tolerance": 2}}, "tolerance", "Extra inputs"),
])
def test04_bad_targets_are_422s_naming_the_field(local_client, change, field, words):
    body = {k: v for k, v in {**TARGET_JOB, **change}.items() if v is not None}
    response = local_client.post("/jobs", json=body)
    assert response.status_code == 422, response.text
    detail = response.json()["detail"][0]
    assert field in ".".join(map(str, detail["loc"])) and words in detail["msg"], detail


def test05_methods_say_whether_they_take_a_target(local_client):
    methods = {m["name"]: m for m in local_client.get("/methods").json()}
    assert methods["path-mis"]["noise_target"] and methods["raster"]["noise_target"]
    assert not any(methods[name]["noise_target"] for name in ("photon", "bdpt", "mlt", "light",
                                                              "radiosity"))


def _running_target_job(target: dict):
    """A running target job after its first pass (error 0.5 over 1024 pixels,
    1000 samples/s), as the ledger holds it; not added to any session."""
    from service.models import Job, utcnow

    now = utcnow()
    return Job(id="0123456789ab", status="running", owner="admin", scene="cornell-box",
               scene_hash="0" * 64, spec={"method": "path-mis", "spp": target["max_spp"],
                                          "depth": 5, "tile_size": 8, "seed": 3,
                                          "sampler": "sobol", "options": {}},
               width=32, height=32, units_total=64, units_done=16, samples=1024, rays=4096,
               priority=0, progressive=True, denoise=False, target=target, units_open=16,
               pass_log=[{"pass": 0, "spp": 1, "samples": 1024, "seconds": 0.5,
                          "rel_error": 0.5, "active": 1024}],
               rel_error=0.5, recent_rate=1000.0, created=now, started=now,
               paused_seconds=0.0, unit_seconds=0.5, units_retried=0, units_skipped=0), now


def test06_the_eta_of_a_target_far_below_the_error_is_the_ceilings(local_client):
    """A ledger may hold a target the API now refuses (1e-300: its ETA raised
    OverflowError, and every GET /jobs answered 500): the growth is capped at
    max_spp before it is squared."""
    from service.schemas import JobPublic

    job, now = _running_target_job({"rel_error": 1e-300, "max_spp": 1024, "max_seconds": None})
    assert JobPublic.from_job(job, now).progress.eta == pytest.approx((1024 - 1) * 1024 / 1000)


def test07_a_figure_that_cannot_be_computed_is_null_and_the_views_go_on(local_client,
                                                                        monkeypatch, caplog):
    """A job's derived figures are computed in one guarded place
    (service.figures): one that raises is that figure's null, logged once per
    job, and the job list, the job and its event stream carry on."""
    from service import figures

    def overflow(job, now):
        raise OverflowError("(34, 'Numerical result out of range')")

    monkeypatch.setitem(figures.FIGURES, "eta", overflow)
    job = submit(local_client, dict(TARGET_JOB, target={"rel_error": 0.5, "max_spp": 16}))
    with local_client.stream("GET", f"/jobs/{job['id']}/events") as response:
        events = read_events(response)
    assert events[-1] == ("end", {"job_id": job["id"], "status": "done"})
    published = [data for kind, data in events if kind == "job"]
    assert published and all(j["progress"]["eta"] is None for j in published)
    listed = local_client.get("/jobs")
    assert listed.status_code == 200, listed.text
    mine = next(j for j in listed.json() if j["id"] == job["id"])
    assert mine["progress"]["eta"] is None and mine["progress"]["elapsed"] is not None
    assert mine["progress"]["fraction"] > 0 and mine["stats"]["seconds_per_unit"] is not None
    logged = [r for r in caplog.records if f"job {job['id']}: its eta" in r.getMessage()]
    assert len(logged) == 1 and "OverflowError" in logged[0].getMessage()
