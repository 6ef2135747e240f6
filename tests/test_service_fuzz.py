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


# -- bounded bodies and text that is not text -------------------------------------------------
# Self-contained: what follows uses only the module's fixtures.

import asyncio  # noqa: E402
import re  # noqa: E402
import json  # noqa: E402

CHUNK = 64 << 10
DECLARED = 2 << 30  # a 2 GiB body, as its Content-Length says
SMALL = 64 << 10  # the limit of a route without one of its own (RAYFARM_MAX_BODY_BYTES)


# Routes outside the OpenAPI schema: the dashboard, the docs, static assets, no route at all.
UNLISTED = [("GET", "/"), ("GET", "/docs"), ("GET", "/redoc"), ("GET", "/openapi.json"),
            ("POST", "/static/app.css"), ("PUT", "/docs-assets/x"), ("POST", "/no-such-route")]


def _routes(app) -> list[tuple[str, str]]:
    """(method, concrete path) of every operation of the OpenAPI schema, and `UNLISTED`."""
    out = list(UNLISTED)
    for path, operations in app.openapi()["paths"].items():
        out += [(method.upper(), re.sub(r"\{[^}]+\}", "0123456789ab", path))
                for method in operations]
    return out


def _asgi(app, method: str, path: str, headers: list, feed: int) -> tuple[int, int]:
    """One request straight to the app: its status and the body bytes it read
    (`feed` bytes are on offer, in 64 KiB chunks; then the client is gone)."""
    read = 0
    status: dict = {}

    async def receive():
        nonlocal read
        if "start" in status or read >= feed:
            return {"type": "http.disconnect"}
        read += CHUNK
        return {"type": "http.request", "body": b" " * CHUNK, "more_body": read < feed}

    async def send(message):
        if message["type"] == "http.response.start":
            status["start"] = message["status"]

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
             "method": method, "scheme": "http", "path": path, "raw_path": path.encode(),
             "query_string": b"", "root_path": "", "client": ("127.0.0.1", 50000),
             "server": ("testserver", 80), "state": {},
             "headers": [(b"host", b"testserver"), (b"content-type", b"application/json"),
                         *headers]}
    asyncio.run(app(scope, receive, send))
    return status.get("start", 0), read


def test03_an_oversized_body_to_any_route_is_refused_before_it_is_read(fuzz_app):
    app, _ = fuzz_app
    declared = [(b"content-length", str(DECLARED).encode())]
    chunked = [(b"transfer-encoding", b"chunked")]
    bearer = [(b"authorization", f"Bearer {TEST_ADMIN_TOKEN}".encode())]
    public = {("POST", "/auth/login")}
    routes = _routes(app)
    assert len(routes) > 40 and ("PATCH", "/jobs/0123456789ab") in routes
    failures = []
    for method, path in routes:
        # 2 GiB declared, with a token or without: 413 at once, nothing read.
        for who in ([], bearer):
            status, read = _asgi(app, method, path, declared + who, DECLARED)
            if status != 413 or read:
                failures.append(f"{method} {path} declared {'admin' if who else 'anonymous'}: "
                                f"{status}, {read} bytes read")
        # Without a Content-Length: a stranger's body to a protected route is never read,
        # and a public route reads no more than its limit.
        status, read = _asgi(app, method, path, chunked, 4 * SMALL)
        limit = SMALL + CHUNK
        if (method, path) in public and (status != 413 or read > limit):
            failures.append(f"{method} {path} chunked anonymous: {status}, {read} bytes read")
        if status == 401 and read:
            failures.append(f"{method} {path} chunked anonymous: 401 after {read} bytes read")
        if status not in (401, 413) and read > limit:
            failures.append(f"{method} {path} chunked anonymous: {status}, {read} bytes read")
        # The admin's: the route's limit, counted while it streams (event streams never end).
        if path.endswith("events") or (method, path) in {("POST", "/jobs"), ("POST", "/scenes")}:
            continue
        status, read = _asgi(app, method, path, chunked + bearer, 4 * SMALL)
        if read > limit or (read and status != 413):
            failures.append(f"{method} {path} chunked admin: {status}, {read} bytes read")
    assert not failures, "\n".join(failures)


SURROGATE = "\ud800"  # half of a UTF-16 pair: not text


def _string_fields(schema: dict, node: dict, path: tuple = (), depth: int = 0):
    """The paths of every string a request body of this JSON schema may hold
    (a free-form object's: one key "x"; a list's: its first item)."""
    if depth > 8:
        return
    if "$ref" in node:
        node = schema["components"]["schemas"][node["$ref"].rsplit("/", 1)[1]]
    for key in ("anyOf", "oneOf", "allOf"):
        for option in node.get(key, ()):
            yield from _string_fields(schema, option, path, depth + 1)
    kind = node.get("type")
    if kind == "string" or isinstance(node.get("const"), str) or any(
            isinstance(v, str) for v in node.get("enum", ())):
        yield path
    if kind == "object" or "properties" in node:
        for name, sub in node.get("properties", {}).items():
            yield from _string_fields(schema, sub, path + (name,), depth + 1)
        extra = node.get("additionalProperties")
        if isinstance(extra, dict):
            yield from _string_fields(schema, extra, path + ("x",), depth + 1)
        elif extra is True or (kind == "object" and not node.get("properties")):
            yield path + ("x",)
    if kind == "array" and isinstance(node.get("items"), dict):
        yield from _string_fields(schema, node["items"], path + (0,), depth + 1)


def _holding(path: tuple, leaf):
    """A JSON document with `leaf` at `path` and nothing else."""
    if not path:
        return leaf
    head, rest = path[0], path[1:]
    return [_holding(rest, leaf)] if isinstance(head, int) else {head: _holding(rest, leaf)}


def test04_a_lone_surrogate_in_any_string_field_is_a_422_naming_it(fuzz_app):
    app, client = fuzz_app
    schema = client.get("/openapi.json", headers=ADMIN_HEADERS).json()
    failures, checked = [], 0
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            content = operation.get("requestBody", {}).get("content", {})
            if "application/json" not in content:
                continue
            url = re.sub(r"\{[^}]+\}", "0123456789ab", path)
            fields = set(_string_fields(schema, content["application/json"]["schema"]))
            for field in sorted(fields, key=str):
                # json.dumps writes the surrogate as the escape "\ud800", as a client would
                body = json.dumps(_holding(field, f"a{SURROGATE}b"))
                response = client.request(method.upper(), url, content=body, headers={
                    **ADMIN_HEADERS, "content-type": "application/json"})
                checked += 1
                loc = response.json()["detail"][0]["loc"] if response.status_code == 422 else None
                if loc != ["body", *field]:
                    failures.append(f"{method.upper()} {path} {field}: {response.status_code} "
                                    f"{response.text[:200]}")
    assert checked >= 15, checked
    assert not failures, "\n".join(failures)
    # A key, the surrogate's UTF-8 bytes (ED A0 80: not UTF-8), other bytes that are
    # not UTF-8, and the public login: 422s too, the field named where there is one.
    for body, loc in ((b'{"options": {"\\udc00": 1}}', ["body", "options", "\\udc00"]),
                      (b'{"name": "a\xed\xa0\x80b"}', ["body", "name"]),
                      (b'{"name": "a\xffb"}', ["body"])):
        response = client.post("/jobs", content=body,
                               headers={**ADMIN_HEADERS, "content-type": "application/json"})
        assert response.status_code == 422 and response.json()["detail"][0]["loc"] == loc, \
            response.text
    anonymous = client.post("/auth/login", content=b'{"token": "rf_\\ud800"}',
                            headers={"content-type": "application/json"})
    assert anonymous.status_code == 422 and "token" in anonymous.json()["detail"][0]["msg"]
    # In an uploaded scene file, and in a URL (decoded with replacement characters).
    scene = json.dumps({"camera": {"w\ud800": 1}}).encode()
    upload = client.post("/scenes", files={"scene": ("room.json", scene)}, headers=ADMIN_HEADERS)
    assert upload.status_code == 422 and "camera" in upload.json()["detail"][0]["msg"], upload.text
    assert client.get("/jobs/%ED%A0%80", headers=ADMIN_HEADERS).status_code == 404
    assert client.get("/jobs?scene=%ED%A0%80", headers=ADMIN_HEADERS).status_code == 200
