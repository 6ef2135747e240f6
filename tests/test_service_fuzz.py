"""Property-based API test: requests generated from the service's own
/openapi.json (schemathesis), valid and invalid, against an in-process app.

Asserted for every request: no 5xx, and its status is one the schema
documents for that route (so the schema is honest about 401, 403, 404, 409,
413, 422 and 429); afterwards the service still answers /healthz. Bounded
to about a minute: few examples per operation, and a farm that accepts only
small jobs (so fuzzed jobs that pass cost the two shared cores little).
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np
import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import status_code_conformance

from conftest import ADMIN_HEADERS, TEST_ADMIN_TOKEN


@pytest.fixture(scope="module")
def auth_headers() -> dict:
    """What every generated request carries: the admin's bearer token (every
    route but /healthz and the static assets needs one)."""
    return dict(ADMIN_HEADERS)


def _requests_only(app):
    """`app` as schemathesis sees it: HTTP goes through; the lifespan is the
    fixture's (schemathesis would otherwise open a second farm on it)."""
    async def asgi(scope, receive, send):
        if scope["type"] != "lifespan":
            await app(scope, receive, send)
            return
        while True:
            message = await receive()
            if message["type"] == "lifespan.startup":
                await send({"type": "lifespan.startup.complete"})
            elif message["type"] == "lifespan.shutdown":
                await send({"type": "lifespan.shutdown.complete"})
                return
    return asgi


@pytest.fixture(scope="module")
def fuzz_app(tmp_path_factory):
    """A service of its own (the fuzzer creates users, tokens and jobs) whose
    accepted jobs are small: at most 2^18 samples (POST /jobs' example is
    128 x 128 x 16), 64 tiles, one render process."""
    from service.main import create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path_factory.mktemp("fuzz-farm"), broker_url="",
                        database_url="", local_workers=1, poll_interval=0.05,
                        admin_token=TEST_ADMIN_TOKEN, max_work=1 << 18, max_units=64)
    app = create_app(settings)
    with TestClient(app) as client:
        yield app, client


@pytest.fixture(scope="module")
def api_schema(fuzz_app, auth_headers):
    app, _ = fuzz_app
    schema = schemathesis.openapi.from_asgi("/openapi.json", _requests_only(app),
                                            headers=auth_headers)
    # Event streams never end by themselves; test_service_events.py covers them.
    return schema.exclude(path_regex=r"events$")


EXAMPLES = 25  # generated per operation and mode (valid, invalid), about 40 operations
STATUSES: Counter = Counter()  # every fuzzed request's status, reported by test02
CHECKS = [not_a_server_error, status_code_conformance]


def _strategies(schema, operation, mode: str) -> list[tuple[object, int]]:
    """(strategy, examples to draw) for one operation: its documented examples
    once each (they reach the 201s), or generated valid or invalid requests."""
    if mode == "examples":
        return [(strategy, 1) for strategy in schema.get_strategies_from_examples(operation)]
    generation = GenerationMode.POSITIVE if mode == "valid" else GenerationMode.NEGATIVE
    return [(operation.as_strategy(generation_mode=generation), EXAMPLES)]


@pytest.mark.parametrize("mode", ["examples", "valid", "invalid"])
def test01_no_request_is_a_server_error_and_every_status_is_documented(api_schema, auth_headers,
                                                                      mode):
    # Hypothesis runs per operation here rather than through schemathesis'
    # pytest plugin: its from_fixture loader reads Function._nodeid, which
    # pytest 9.2 no longer has.
    failures: dict[str, str] = {}
    for result in api_schema.get_all_operations():
        operation = result.ok()
        for strategy, examples in _strategies(api_schema, operation, mode):
            @given(case=strategy)
            @settings(max_examples=examples, deadline=None, database=None,
                      phases=[Phase.generate, Phase.shrink],
                      suppress_health_check=list(HealthCheck))
            def exercise(case):
                response = case.call(headers=auth_headers)
                STATUSES[response.status_code] += 1
                case.validate_response(response, checks=CHECKS)

            try:
                exercise()
            except Unsatisfiable:
                assert mode == "invalid", operation.label  # nothing there to make invalid
            except (Exception, BaseExceptionGroup) as exc:  # report every operation's failures
                failures[operation.label] = f"{type(exc).__name__}: {exc}"
    assert not failures, "\n\n".join(f"{label}\n{text}" for label, text in failures.items())


def test02_the_service_answers_healthz_afterwards(fuzz_app):
    print(f"fuzzed {sum(STATUSES.values())} requests; statuses: {dict(sorted(STATUSES.items()))}")
    assert not any(status >= 500 for status in STATUSES)
    _, client = fuzz_app
    response = client.get("/healthz")
    assert response.status_code == 200 and response.json()["status"] == "ok", response.text


# -- tiny and huge numbers in every numeric field -------------------------------------------
# Strict JSON has no NaN or Infinity, but it has these: each goes into each numeric
# field of a request. The answer is a 4xx naming the field, or a job that
# finishes with a finite image; never a 5xx, a failed job or a NaN pixel.

EXTREMES = (1e308, -1e308, 1e-300, 1e-320, 10**20, -1, 0)  # 1e-300: a target overflowed
TINY_JOB = {"scene": "cornell-box", "method": "path-mis", "spp": 2, "depth": 2, "width": 8,
            "height": 8, "tile_size": 8, "seed": 1, "progressive": False}


def _job_cases(methods: list[dict]) -> list[tuple[str, dict]]:
    """(label, job body): every extreme in every numeric field of the job body,
    of its noise target and of every method's numeric options (GET /methods),
    and BDPT's s=K with a K of 10^20."""
    cases = []
    for field in ("spp", "depth", "tile_size", "seed", "width", "height", "priority"):
        cases += [(f"{field}={v!r}", {**TINY_JOB, field: v}) for v in EXTREMES]
    for field in ("rel_error", "max_spp", "max_seconds"):
        for v in EXTREMES:
            body = {k: v for k, v in TINY_JOB.items() if k != "spp"}
            cases.append((f"target.{field}={v!r}",
                          {**body, "target": {"rel_error": 0.5, "max_spp": 64, field: v}}))
    for method in methods:
        for option in method["options"]:
            if option["type"] in ("int", "float"):
                cases += [(f"{method['name']} {option['name']}={v!r}",
                           {**TINY_JOB, "method": method["name"], "options": {option["name"]: v}})
                          for v in EXTREMES]
    cases.append(("bdpt strategy=s=10^20",
                  {**TINY_JOB, "method": "bdpt", "options": {"strategy": f"s={10**20}"}}))
    return cases


def _admin_of_its_own(app, name: str) -> TestClient:
    """A client of `app` (its farm the fixture's) as a new admin with a token of
    its own: a fresh submission budget, whatever the other tests spent."""
    admin = TestClient(app, headers=ADMIN_HEADERS)
    assert admin.post("/users", json={"name": name, "role": "admin"}).status_code == 201
    secret = admin.post("/tokens", json={"user": name}).json()["token"]
    return TestClient(app, headers={"Authorization": f"Bearer {secret}"})


def test03_extreme_numbers_in_a_job_are_a_4xx_or_a_finite_image(fuzz_app, tmp_path):
    from renderer import read_exr

    client = _admin_of_its_own(fuzz_app[0], "fuzz-jobs")
    methods = client.get("/methods").json()
    accepted, problems = {}, []
    for label, body in _job_cases(methods):
        response = client.post("/jobs", json=body)
        if response.status_code == 201:
            accepted[response.json()["id"]] = label
        elif not 400 <= response.status_code < 500:
            problems.append(f"{label}: {response.status_code} {response.text[:200]}")
        elif response.status_code == 422:  # naming the field it refused
            detail = response.json()["detail"][0]
            if not detail.get("loc") or not detail.get("msg"):
                problems.append(f"{label}: 422 without a field: {response.text[:200]}")
    assert accepted, "every extreme refused: nothing was rendered"
    # The list is read while they run: a job's figures (its ETA after a first
    # pass) are computed only then.
    final = {}
    deadline = time.monotonic() + 300
    while len(final) < len(accepted) and time.monotonic() < deadline:
        listed = client.get("/jobs", params={"limit": 1000})
        assert listed.status_code == 200, listed.text
        final.update({j["id"]: j for j in listed.json()
                      if j["id"] in accepted and j["status"] in ("done", "failed", "canceled")})
        time.sleep(0.02)
    assert len(final) == len(accepted), sorted(set(accepted.values()) - {
        accepted[i] for i in final})
    for job_id, label in accepted.items():
        job = final[job_id]
        if job["status"] != "done":
            problems.append(f"{label}: {job['status']}: {job['error']}")
            continue
        exr = tmp_path / f"{job_id}.exr"
        exr.write_bytes(client.get(job["result_url"]).content)
        channels, _ = read_exr(exr)
        if not all(np.all(np.isfinite(channels[c])) for c in "RGB"):
            problems.append(f"{label}: non-finite pixels")
    assert not problems, "\n".join(problems)


def test04_extreme_numbers_elsewhere_are_never_a_server_error(fuzz_app):
    """Experiments (their accepted jobs canceled at once), user shares, token
    lifetimes, priorities and the list queries, with every extreme."""
    client = _admin_of_its_own(fuzz_app[0], "fuzz-requests")
    tiny = {"scene": "cornell-box", "width": 8, "height": 8, "depth": 1, "repeats": 2,
            "spp": [1], "block": 4, "configs": [{"method": "raster"}], "reference": {"spp": 1}}
    created = client.post("/jobs", json=TINY_JOB)
    assert created.status_code == 201, created.text
    job = created.json()["id"]
    client.post("/users", json={"name": "fuzz-numbers"})
    requests = []
    for i, v in enumerate(EXTREMES):
        for field in ("repeats", "block", "depth", "width", "height", "seed", "priority"):
            requests.append(("POST", "/experiments", {**tiny, field: v}, None))
        requests.append(("POST", "/experiments", {**tiny, "spp": [v]}, None))
        requests.append(("POST", "/experiments", {**tiny, "reference": {"spp": v}}, None))
        requests.append(("POST", "/experiments",
                         {**tiny, "configs": [{"method": "photon", "options": {"radius": v}}]},
                         None))
        requests.append(("POST", "/users", {"name": f"fuzz-share-{i}", "share": v}, None))
        requests.append(("PATCH", "/users/fuzz-numbers", {"share": v}, None))
        requests.append(("POST", "/tokens", {"user": "fuzz-numbers", "expires_in_days": v}, None))
        requests.append(("PATCH", f"/jobs/{job}", {"priority": v}, None))
        for path in ("/jobs", "/experiments"):
            requests.append(("GET", path, None, {"limit": v}))
        requests.append(("GET", "/jobs", None, {"offset": v}))
    problems = []
    for method, path, body, params in requests:
        response = client.request(method, path, json=body, params=params)
        if response.status_code >= 500:
            problems.append(f"{method} {path} {body or params}: {response.status_code} "
                            f"{response.text[:200]}")
        elif method == "POST" and path == "/experiments" and response.status_code == 201:
            client.post(f"/experiments/{response.json()['id']}/cancel")
    assert not problems, "\n".join(problems)
