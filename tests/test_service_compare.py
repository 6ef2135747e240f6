"""GET /compare: several done jobs' convergence side by side — each pass's
error statistic, and with a reference job each pass's RMSE against it, from
the stored unit films merged pass by pass (service.compare)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import TINY, get_json, poll_job, submit

BODY = dict(TINY, width=16, height=16, spp=16, tile_size=8)  # progressive: several passes


@pytest.fixture(scope="module")
def three(local_client):
    get = get_json(local_client)
    a = submit(local_client, dict(BODY, seed=1))["id"]
    b = submit(local_client, dict(BODY, seed=2, sampler="random"))["id"]
    ref = submit(local_client, dict(BODY, spp=1024, seed=3, progressive=False))["id"]
    for job_id in (a, b, ref):
        assert poll_job(get, job_id)["status"] == "done"
    return a, b, ref


def _exr(client, job_id, tmp_path):
    from renderer import read_exr

    path = tmp_path / f"{job_id}.exr"
    path.write_bytes(client.get(f"/jobs/{job_id}/result.exr").content)
    channels = read_exr(path)[0]
    return (np.stack([channels[c] for c in "RGB"], -1).astype(np.float64),
            np.stack([channels[f"var.{c}"] for c in "RGB"], -1).astype(np.float64))


def test01_each_pass_is_a_point_and_the_last_is_the_final_image(local_client, three, tmp_path):
    a, b, ref = three
    response = local_client.get("/compare", params={"jobs": f"{a},{b}", "reference": ref})
    assert response.status_code == 200, response.text
    report = response.json()
    assert report["reference"] == ref and [j["id"] for j in report["jobs"]] == [a, b]
    job = local_client.get(f"/jobs/{a}").json()
    spps = [p["spp"] for p in job["passes"]]  # the plan's passes (small ones grouped)
    assert len(spps) >= 3 and spps[-1] == 16
    for curve in report["jobs"]:
        points = curve["points"]
        assert [p["spp"] for p in points] == spps
        assert [p["samples"] for p in points] == [16 * 16 * s for s in spps]
        assert points[-1]["rel_error"] < points[0]["rel_error"]
        assert all(p["seconds"] > 0 for p in points)
    # The pass-by-pass error statistic is the job's own convergence log.
    logged = [p["rel_error"] for p in job["passes"]]
    assert [p["rel_error"] for p in report["jobs"][0]["points"]] == pytest.approx(logged, rel=1e-4)
    # The last point's RMSE is that of the final EXR, less the reference's variance.
    mean, _ = _exr(local_client, a, tmp_path)
    reference, ref_var = _exr(local_client, ref, tmp_path)
    expected = np.sqrt(max(np.mean((mean - reference) ** 2) - np.mean(ref_var), 0.0))
    assert report["jobs"][0]["points"][-1]["rmse"] == pytest.approx(expected, rel=1e-5)


def test02_a_one_pass_job_is_one_point_and_the_figure_draws(local_client, three):
    a, _, ref = three
    report = local_client.get("/compare", params={"jobs": f"{ref},{a}"}).json()
    assert len(report["jobs"][0]["points"]) == 1 and "rmse" not in report["jobs"][0]["points"][0]
    png = local_client.get("/compare.png", params={"jobs": f"{a},{ref}", "reference": ref})
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"


def test03_bad_comparisons_are_422s_naming_the_parameter(local_client, three):
    a, b, ref = three
    other = submit(local_client, dict(BODY, width=24, spp=4))["id"]
    poll_job(get_json(local_client), other)
    cases = [({"jobs": ""}, "jobs"), ({"jobs": "0123456789ab"}, "jobs"),
             ({"jobs": ",".join([a] * 1 + [f"{i:012x}" for i in range(9)])}, "jobs"),
             ({"jobs": a, "reference": "0123456789ab"}, "reference"),
             ({"jobs": f"{a},{other}", "reference": ref}, "reference")]
    for params, field in cases:
        response = local_client.get("/compare", params=params)
        assert response.status_code == 422, (params, response.text)
        assert field in str(response.json()["detail"]), (params, response.text)
    assert local_client.get("/compare").status_code == 422  # jobs is required



def test04_a_comparison_is_bounded_in_pixels_and_runs_one_at_a_time(local_client, three,
                                                                   monkeypatch):
    """It holds whole-frame float64 films: frames above MAX_PIXELS are a 422
    naming `jobs`, and a second comparison while one runs is a 429 to retry,
    not a second set of frames in memory."""
    from service import compare

    a, b, ref = three
    monkeypatch.setattr(compare, "MAX_PIXELS", 16 * 16 - 1)
    big = local_client.get("/compare", params={"jobs": a})
    assert big.status_code == 422 and "jobs" in str(big.json()["detail"]), big.text
    monkeypatch.setattr(compare, "MAX_PIXELS", 16 * 16)
    assert compare._RUNNING.acquire(blocking=False)  # a comparison under way
    try:
        for path in ("/compare", "/compare.png"):
            busy = local_client.get(path, params={"jobs": a, "reference": ref})
            assert busy.status_code == 429, busy.text
            assert int(busy.headers["retry-after"]) >= 1
    finally:
        compare._RUNNING.release()
    assert local_client.get("/compare", params={"jobs": a, "reference": ref}).status_code == 200
