"""Jobs whose method plans a DAG, through the service (embedded executor):
units of a later stage are enqueued only after the units they need are done,
the API shows each unit's phase, and the EXR equals the renderer's own
in-process run of the same DAG bit for bit."""

from __future__ import annotations

from datetime import datetime

import pytest
from sqlalchemy import select

from service.models import WorkUnit

from conftest import TINY, assert_equals_renderer, get_json, poll_job, submit

DAG_BODIES = {
    "photon": dict(TINY, method="photon", spp=3, tile_size=16, progressive=False),
    "radiosity": dict(TINY, method="radiosity", spp=2, tile_size=16, progressive=False),
    "mlt": dict(TINY, method="mlt", spp=4, progressive=False),
}


def _time(value: str) -> datetime:
    return datetime.fromisoformat(value.replace("Z", "+00:00"))


@pytest.mark.parametrize("method", sorted(DAG_BODIES))
def test01_dag_units_wait_for_their_needs_and_the_image_matches_the_renderer(
        method, local_client, tmp_path):
    body = DAG_BODIES[method]
    get = get_json(local_client)
    job = poll_job(get, submit(local_client, body)["id"])
    assert job["status"] == "done", job
    units = get(f"/jobs/{job['id']}/units")
    assert len({u["kind"] for u in units}) >= 2, "a DAG job has more than one phase"
    by_index = {u["index"]: u for u in units}
    for u in units:
        for need in u["needs"]:
            assert by_index[need]["stage"] < u["stage"]
            # Enqueued only once what it needs had finished.
            assert _time(u["enqueued_at"]) >= _time(by_index[need]["finished_at"]), (u, need)
    assert job["samples"] == body["width"] * body["height"] * body["spp"]

    exr = tmp_path / f"{method}.exr"
    exr.write_bytes(local_client.get(job["result_url"]).content)
    assert_equals_renderer(exr, body)


@pytest.mark.parametrize("method, options, field", [
    ("mlt", {"chains": 0}, "chains"),
    ("mlt", {"sigma": "wide"}, "sigma"),
    ("photon", {"radius": -1}, "radius"),
    ("photon", {"mode": "kd"}, "mode"),
    ("radiosity", {"ff_rays": 0}, "ff_rays"),
    ("radiosity", {"hemicube_res": 7}, "hemicube_res"),
    ("bdpt", {"strategy": "s=two"}, "strategy"),
    ("bdpt", {"strategy": "s=\u00b9"}, "strategy"),  # "¹".isdigit(), but int() refuses it
])
def test02_bad_method_options_are_refused_at_submission(method, options, field, local_client):
    """Rule 5: a job whose options its method cannot run is a 422 naming the
    option, not a job that fails on a worker."""
    response = local_client.post("/jobs", json=dict(TINY, method=method, options=options))
    assert response.status_code == 422, response.text
    detail = response.json()["detail"][0]
    assert detail["loc"][-1] == field and f"options.{field}" in detail["msg"], detail


def test03_the_embedded_pool_reads_no_input_from_the_store(local_app, local_client):
    """A DAG unit's inputs go to the pool by digest (the ledger records each
    done unit's) and come from memory, kept as they landed: the store is not
    read again for them."""
    executor = local_app.state.farm.executor
    before = executor.films_loaded
    job = poll_job(get_json(local_client), submit(local_client, DAG_BODIES["photon"])["id"])
    assert job["status"] == "done", job
    assert executor.films_loaded == before
    with local_app.state.farm.sessions() as session:
        digests = list(session.scalars(select(WorkUnit.film_digest)
                                       .where(WorkUnit.job_id == job["id"])))
    assert len(digests) == 15 and all(digests)
