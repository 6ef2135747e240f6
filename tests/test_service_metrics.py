"""GET /metrics: the farm's Prometheus metrics (service.metrics).

test01-04 run a service of their own (embedded pool of one process), so the
counters move only by what these tests do; test05 drives a scheduler tick by
tick on the fake executor (nothing renders) to see requeues, ticks and the
queue depth exactly; test06 builds two apps in one process.
"""

from __future__ import annotations

import types

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from conftest import ADMIN_HEADERS, TEST_ADMIN_TOKEN, TINY, get_json, poll_job, submit

FAMILIES = ("rayfarm_jobs", "rayfarm_units", "rayfarm_queue_depth", "rayfarm_workers",
            "rayfarm_disk_free_bytes", "rayfarm_samples", "rayfarm_rays",
            "rayfarm_unit_render_seconds", "rayfarm_units_requeued",
            "rayfarm_scheduler_tick_seconds", "rayfarm_http_request_seconds")


def scrape(client) -> tuple[str, dict[tuple[str, tuple], float]]:
    """GET /metrics without a token; returns the text and every sample by
    (name, sorted labels), as prometheus_client's own parser reads them."""
    anonymous = TestClient(client.app)  # no Authorization header, no cookie
    response = anonymous.get("/metrics")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text
    samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return text, samples


def value(samples, name: str, **labels) -> float:
    return samples.get((name, tuple(sorted(labels.items()))), 0.0)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    from service.main import create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path_factory.mktemp("metrics-farm"), broker_url="",
                        database_url="", local_workers=1, poll_interval=0.05,
                        admin_token=TEST_ADMIN_TOKEN)
    app = create_app(settings)
    with TestClient(app):  # the lifespan: farm, scheduler, pool
        yield app


@pytest.fixture(scope="module")
def client(app):
    with_token = TestClient(app, headers=ADMIN_HEADERS)
    yield with_token
    with_token.close()


def test01_metrics_is_public_and_parses(client):
    assert TestClient(client.app).get("/jobs").status_code == 401  # the token matters elsewhere
    text, samples = scrape(client)
    names = {f.name for f in text_string_to_metric_families(text)}
    assert set(FAMILIES) <= names, set(FAMILIES) - names
    # Every state is shown, 0 or not; the embedded pool is one worker, busy or idle.
    from service.states import JOB_STATUSES, UNIT_STATES
    for state in JOB_STATUSES:
        assert ("rayfarm_jobs", (("state", state),)) in samples
    for state in UNIT_STATES:
        assert ("rayfarm_units", (("state", state),)) in samples
    assert sum(value(samples, "rayfarm_workers", state=s) for s in ("busy", "idle")) == 1
    assert value(samples, "rayfarm_disk_free_bytes") > 0
    assert value(samples, "rayfarm_scheduler_tick_seconds_count") > 0  # the scheduler ticks
    for reason in ("lost", "lease", "crash", "failed"):
        assert ("rayfarm_units_requeued_total", (("reason", reason),)) in samples


# Issue 12, point 7: every metric by name, with its Prometheus type and labels.
TYPES = {"rayfarm_jobs": ("gauge", {"state"}), "rayfarm_units": ("gauge", {"state"}),
         "rayfarm_queue_depth": ("gauge", set()), "rayfarm_workers": ("gauge", {"state"}),
         "rayfarm_disk_free_bytes": ("gauge", set()), "rayfarm_samples": ("counter", set()),
         "rayfarm_rays": ("counter", set()),
         "rayfarm_unit_render_seconds": ("histogram", {"method"}),
         "rayfarm_units_requeued": ("counter", {"reason"}),
         "rayfarm_scheduler_tick_seconds": ("histogram", set()),
         "rayfarm_http_request_seconds": ("histogram", {"method", "route"})}


def test01b_every_metric_has_its_type_and_labels(client):
    poll_job(get_json(client), submit(client, TINY)["id"])  # a render-seconds sample by method
    text, _ = scrape(client)
    families = {f.name: f for f in text_string_to_metric_families(text)}
    assert set(TYPES) == set(FAMILIES)
    for name, (kind, labels) in TYPES.items():
        family = families[name]
        assert family.type == kind, (name, family.type)
        assert family.samples, name
        for sample in family.samples:
            assert set(sample.labels) - {"le"} == labels, (name, sample.labels)


def test02_a_tiny_job_moves_the_counters_by_exactly_its_own(client):
    _, before = scrape(client)
    job = poll_job(get_json(client), submit(client, TINY)["id"])
    assert job["status"] == "done", job
    _, after = scrape(client)
    units = job["progress"]["units_total"]
    assert units > 1 and job["samples"] == 32 * 32 * 4 and job["rays"] > job["samples"]

    def grew(name, **labels):
        return value(after, name, **labels) - value(before, name, **labels)

    assert grew("rayfarm_samples_total") == job["samples"]
    assert grew("rayfarm_rays_total") == job["rays"]
    assert grew("rayfarm_jobs", state="done") == 1
    assert grew("rayfarm_units", state="done") == units
    assert grew("rayfarm_unit_render_seconds_count", method="path-mis") == units
    assert grew("rayfarm_unit_render_seconds_count", method="raster") == 0
    unit_seconds = job["stats"]["seconds_per_unit"] * units
    assert grew("rayfarm_unit_render_seconds_sum", method="path-mis") == pytest.approx(unit_seconds)
    assert value(after, "rayfarm_queue_depth") == 0  # nothing waits any more


def test03_http_requests_are_labelled_by_route_template_never_by_raw_path(client):
    job = submit(client, TINY)
    jid = job["id"]
    poll_job(get_json(client), jid)
    _, before = scrape(client)
    for _ in range(3):
        assert client.get(f"/jobs/{jid}").status_code == 200
    unknown = "/no-such-page-3f9c2a"
    assert client.get(unknown).status_code == 404
    assert client.get("/static/app.css").status_code == 200
    text, after = scrape(client)

    def grew(**labels):
        return (value(after, "rayfarm_http_request_seconds_count", **labels)
                - value(before, "rayfarm_http_request_seconds_count", **labels))

    assert grew(method="GET", route="/jobs/{job_id}") == 3
    assert grew(method="GET", route="unmatched") == 1
    assert grew(method="GET", route="/static/{path}") == 1
    # The scrape before this one is counted by the time of this one.
    assert grew(method="GET", route="/metrics") == 1
    assert jid not in text and unknown not in text and "app.css" not in text
    assert "admin" not in text  # no user names either
    routes = {dict(labels).get("route") for (name, labels) in after
              if name == "rayfarm_http_request_seconds_count"}
    assert all(r == "unmatched" or r.startswith("/") for r in routes), routes


def test04_an_unknown_method_is_one_label_not_many(client):
    _, before = scrape(client)
    for verb in ("FOO", "BAR"):
        client.request(verb, "/healthz")
    _, after = scrape(client)
    assert (value(after, "rayfarm_http_request_seconds_count", method="other", route="/healthz")
            - value(before, "rayfarm_http_request_seconds_count", method="other",
                    route="/healthz")) == 2
    assert not any(dict(labels).get("method") in ("FOO", "BAR") for _, labels in after)


# -- the scheduler's reports, on a fake executor -------------------------------------------

def test05_the_scheduler_reports_requeues_ticks_and_done_units(tmp_path):
    from renderer import PartialFilm
    from service import jobs
    from service.access import Principal
    from service.db import open_ledger
    from service.executors import Observation
    from service.metrics import PrometheusMetrics
    from service.models import utcnow
    from service.scheduler import Scheduler
    from service.schemas import JobCreate
    from service.settings import Settings
    from service.store import Store

    from fake_executor import FakeExecutor

    class Flaky(FakeExecutor):
        """Unit 0's first task is lost, unit 1's first attempt fails."""

        def __init__(self, slots):
            super().__init__(slots)
            self.tricks = {0: "lost", 1: "failed"}

        def observe(self, flights, now):
            out = super().observe(flights, now)
            for i, flight in enumerate(flights):
                trick = self.tricks.pop(flight.index, None)
                if trick == "lost":
                    out[i] = Observation("lost")
                elif trick == "failed":
                    out[i] = Observation("failed", error="boom")
            return out

    settings = Settings(data_dir=tmp_path / "data", broker_url="", database_url="")
    engine, sessions = open_ledger(settings)
    store = Store(settings.data_dir)
    executor = Flaky(slots=4)
    metrics = PrometheusMetrics()
    metrics.watch(types.SimpleNamespace(sessions=sessions, executor=executor, settings=settings))
    scheduler = Scheduler(settings, sessions, store, executor, metrics=metrics)
    try:
        with sessions.begin() as session:  # 16 units of 8x8 pixels
            job_id = jobs.create_job(session, store, settings, Principal("admin", "admin"),
                                     JobCreate(scene="cornell-box", method="path", spp=1,
                                               depth=1, width=32, height=32, tile_size=8,
                                               progressive=False), utcnow()).id
        get = metrics.registry.get_sample_value
        scheduler.tick()  # plan, put 4 in flight
        assert get("rayfarm_queue_depth") == 12
        assert get("rayfarm_units", {"state": "queued"}) == 4
        assert get("rayfarm_jobs", {"state": "running"}) == 1
        scheduler.tick()  # unit 0 lost, unit 1 failed: both enqueued again
        assert get("rayfarm_units_requeued_total", {"reason": "lost"}) == 1
        assert get("rayfarm_units_requeued_total", {"reason": "failed"}) == 1
        assert get("rayfarm_unit_render_seconds_count", {"method": "path-mis"}) is None
        for index in range(4):
            executor.finish(job_id, index)
        scheduler.tick()
        assert get("rayfarm_unit_render_seconds_count", {"method": "path-mis"}) == 4
        assert get("rayfarm_units", {"state": "done"}) == 4
        assert get("rayfarm_queue_depth") == 8  # 4 more went in flight
        assert get("rayfarm_scheduler_tick_seconds_count") == scheduler.ticks == 3
        assert get("rayfarm_units_requeued_total", {"reason": "lost"}) == 1  # no more
        assert get("rayfarm_units_requeued_total", {"reason": "failed"}) == 1
        expected = sum(PartialFilm.from_bytes(store.unit_film(job_id, i)).stats.get("samples", 0)
                       for i in range(4))
        assert get("rayfarm_samples_total") == expected
    finally:
        engine.dispose()


def test06_every_app_has_a_registry_of_its_own(tmp_path):
    """Two apps in one process (no lifespan: no farm, so no ledger gauges):
    creating the second does not clash, and each counts only its own requests."""
    from service.main import create_app
    from service.settings import Settings

    one = create_app(Settings(data_dir=tmp_path / "one", admin_token=TEST_ADMIN_TOKEN))
    two = create_app(Settings(data_dir=tmp_path / "two", admin_token=TEST_ADMIN_TOKEN))
    for _ in range(3):
        TestClient(one).get("/metrics")
    _, seen_by_two = scrape(TestClient(two))
    assert value(seen_by_two, "rayfarm_http_request_seconds_count",
                 method="GET", route="/metrics") == 0
    _, seen_by_one = scrape(TestClient(one))
    assert value(seen_by_one, "rayfarm_http_request_seconds_count",
                 method="GET", route="/metrics") == 3
    assert ("rayfarm_jobs", (("state", "done"),)) not in seen_by_one  # no farm to read
