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
    ({"target": {"rel_error": 0.0, "max_spp": 64}}, "target.rel_error", "must be in (0, 1]"),
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
