"""Property-based API test: requests generated from the service's own
/openapi.json (schemathesis), valid and invalid, against an in-process app.

Asserted for every request: no 5xx, and its status is one the schema
documents for that route (so the schema is honest about 401, 403, 404, 409,
413, 422 and 429); afterwards the service still answers /healthz. Bounded
to about a minute: few examples per operation, and a farm that accepts only
small jobs (so fuzzed jobs that pass cost the two shared cores little).
"""

from __future__ import annotations

from collections import Counter

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
