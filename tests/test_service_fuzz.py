"""Property-based API test: requests generated from the service's own
/openapi.json (schemathesis), valid and invalid, against an in-process app.

Asserted for every request: no 5xx, and its status is one the schema
documents for that route (so the schema is honest about 401, 403, 404, 409,
413, 422 and 429); afterwards the service still answers /healthz. Bounded
to about a minute: few examples per operation, and a farm that accepts only
small jobs (so fuzzed jobs that pass cost the two shared cores little).
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import secrets
import time
from collections import Counter
from pathlib import Path

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
    128 x 128 x 16), 64 tiles, one render process; uploads of at most 64
    files and 10 MiB unpacked."""
    from service.main import create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path_factory.mktemp("fuzz-farm"), broker_url="",
                        database_url="", local_workers=1, poll_interval=0.05,
                        admin_token=TEST_ADMIN_TOKEN, max_work=1 << 18, max_units=64,
                        max_upload_files=FUZZ_UPLOAD_FILES, max_upload_unpacked_bytes=10 << 20)
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
    its own: a fresh submission budget, whatever the other tests spent. The
    name gets a random suffix: Hypothesis draws string constants it finds in
    this module's source, so the fuzzer of test01 may have made `name` already."""
    admin = TestClient(app, headers=ADMIN_HEADERS)
    name = f"{name}-{secrets.token_hex(4)}"
    created = admin.post("/users", json={"name": name, "role": "admin"})
    assert created.status_code == 201, created.text
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


# -- bounded bodies and text that is not text -------------------------------------------------

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


def test05_an_oversized_body_to_any_route_is_refused_before_it_is_read(fuzz_app):
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


def test06_a_lone_surrogate_in_any_string_field_is_a_422_naming_it(fuzz_app):
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


# -- hostile uploads -------------------------------------------------------------------------

ROOM_JSON = json.dumps({
    "camera": {"origin": [0, 0, 4], "target": [0, 0, 0], "fov": 40, "width": 16, "height": 16},
    "materials": {"white": {"type": "diffuse", "albedo": 0.7}},
    "shapes": [{"type": "mesh", "file": "models/tri.obj", "material": "white",
                "emitter": {"type": "area", "radiance": [1, 1, 1]}}]}).encode()
TRI_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


def _zip(*members) -> bytes:
    """A zip of (name or ZipInfo, bytes) members, written as given (names unchecked)."""
    import io
    import warnings
    import zipfile

    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Duplicate name": meant
        for name, data in members:
            archive.writestr(name, data, compress_type=zipfile.ZIP_DEFLATED)
    return out.getvalue()


def _tar(*members, mode: str = "w:gz", pax: dict | None = None) -> bytes:
    """A tar of (name, bytes or a tarfile type with a link name) members."""
    import io
    import tarfile

    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode=mode, format=tarfile.PAX_FORMAT) as archive:
        for name, data in members:
            info = tarfile.TarInfo(name)
            if isinstance(data, bytes):
                info.size = len(data)
            else:
                info.type, info.linkname = data
            info.pax_headers = dict(pax or {})
            archive.addfile(info, io.BytesIO(data) if isinstance(data, bytes) else None)
    return out.getvalue()


def _encrypted(archive: bytes) -> bytes:
    """The zip with its last member flagged encrypted (Python's zipfile writes
    no encrypted members): bit 0 of the flags in its local and central headers."""
    data = bytearray(archive)
    for signature, at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
        data[data.rindex(signature) + at] |= 0x1
    return bytes(data)


def _hostile_uploads():
    """(label, multipart parts, form data, status, words in the refusal): each
    names the member, the field or the limit."""
    import os
    import stat
    import tarfile
    import zipfile

    ok = [("room.json", ROOM_JSON), ("models/tri.obj", TRI_OBJ)]
    link = zipfile.ZipInfo("models/tri.obj")
    link.external_attr = (stat.S_IFLNK | 0o777) << 16
    noise = os.urandom(1 << 16) * 64  # 4 MiB that deflate cannot shrink (its window is 32 KiB)
    cases = [
        ("zip slip", _zip(*ok, ("../../evil.json", b"{}")), 422, ["'../../evil.json'", "'..'"]),
        ("absolute", _zip(*ok, ("/tmp/evil.json", b"{}")), 422, ["'/tmp/evil.json'", "absolute"]),
        ("drive letter", _zip(*ok, ("C:/evil.json", b"{}")), 422, ["C:/evil.json", "drive"]),
        ("backslash", _zip(*ok, ("models\\evil.obj", b"")), 422, ["evil.obj", "backslash"]),
        ("zip symlink", _zip(ok[0], (link, b"/etc/passwd")), 422,
         ["'models/tri.obj'", "symbolic link"]),
        ("encrypted", _encrypted(_zip(*ok)), 422, ["'models/tri.obj'", "encrypted"]),
        ("duplicate", _zip(*ok, ok[1]), 422, ["'models/tri.obj' is uploaded twice"]),
        ("file and folder", _zip(*ok, ("room.json/x.obj", b"")), 422,
         ["'room.json/x.obj'", "'room.json' is a file"]),
        ("tar symlink", _tar(ok[0], ("models/tri.obj", (tarfile.SYMTYPE, "/etc/passwd"))), 422,
         ["'models/tri.obj'", "symbolic link to '/etc/passwd'"]),
        ("tar hard link", _tar(ok[0], ("models/tri.obj", (tarfile.LNKTYPE, "/etc/shadow"))), 422,
         ["'models/tri.obj'", "hard link"]),
        ("tar device", _tar(*ok, ("null", (tarfile.CHRTYPE, ""))), 422, ["'null'", "device"]),
        ("tar slip", _tar(*ok, ("../evil.json", b"{}")), 422, ["'../evil.json'", "'..'"]),
        ("pax header", _tar(*ok, pax={"comment": "x" * (1 << 17)}), 422,
         ["extended tar header", "before its first member"]),
        ("zip bomb", _zip(*ok, ("models/big.obj", bytes(8 << 20))), 413,
         ["'models/big.obj'", "times its compressed size", "RAYFARM_MAX_UPLOAD_RATIO"]),
        ("tar bomb", _tar(*ok, ("models/big.obj", bytes(8 << 20))), 413,
         ["'hostile.tar.gz'", "times its compressed size"]),
        ("too many", _zip(*ok, *((f"m/{i}.obj", b"") for i in range(FUZZ_UPLOAD_FILES))), 413,
         ["more than 64 files", "RAYFARM_MAX_UPLOAD_FILES"]),
        ("too big", _zip(*ok, ("a.bin", noise), ("b.bin", noise), ("c.bin", noise)), 413,
         ["'c.bin'", "RAYFARM_MAX_UPLOAD_UNPACKED_BYTES"]),
        ("too deep", _zip(*ok, ("a/" * 17 + "x.obj", b"")), 422,
         ["17 folders deep", "RAYFARM_MAX_UPLOAD_DEPTH"]),
        ("long name", _zip(*ok, ("x" * 300, b"")), 422, ["longer than 255 bytes"]),
        ("no scene file", _zip(ok[1]), 422, ["holds no scene file"]),
        ("two scene files", _zip(*ok, ("b.json", ROOM_JSON)), 422,
         ["main", "b.json, room.json"]),
        ("not a zip", b"PK\x03\x04" + bytes(100), 422, ["'hostile.zip'", "not a readable zip"]),
        ("cut short", _zip(*ok)[:-30], 422, ["'hostile.zip'"]),
        ("not gzip", b"\x1f\x8b" + bytes(100), 422, ["'hostile.tar.gz'", "corrupt"]),
    ]
    for label, data, status, words in cases:
        name = "hostile.tar.gz" if data[:2] == b"\x1f\x8b" else "hostile.zip"
        yield label, [("scene", (name, data))], {}, status, words
    archive = _zip(*ok, ("b.json", ROOM_JSON))
    for main, words in (("../room.json", ["'..'"]), ("/room.json", ["absolute"]),
                        ("nope.json", ["no file 'nope.json'"]),
                        ("models/tri.obj", ["not a scene file"])):
        yield f"main {main}", [("scene", ("hostile.zip", archive))], {"main": main}, 422, words
    # Files at relative paths are checked alike, naming the part.
    for name, words in (("../evil.obj", ["files[0]", "'..'"]), ("/evil.obj", ["absolute"])):
        yield f"file {name}", [("scene", ("room.json", ROOM_JSON)), ("files", (name, TRI_OBJ))], \
            {}, 422, words


FUZZ_UPLOAD_FILES = 64  # the fuzz farm's RAYFARM_MAX_UPLOAD_FILES


def _refusal(status: int, detail) -> str:
    return " ".join(d["msg"] for d in detail) if isinstance(detail, list) else str(detail)


# Sent over HTTP: one of each kind (the rest are checked in-process, alike and faster).
OVER_HTTP = {"zip slip", "tar symlink", "zip bomb", "tar bomb", "too many", "too big",
             "two scene files", "main ../room.json", "file ../evil.obj"}


def test07_hostile_uploads_are_a_4xx_naming_the_member_and_leave_nothing(fuzz_app, tmp_path):
    """Archives and paths meant to escape the upload's folder, exhaust memory
    or disk, or confuse the importer are each refused with a 4xx naming the
    member (or the field, or the limit): never a 5xx; no file outside the data
    dir, no upload left behind, no scene stored (so none ever reaches a
    render process). An archive inside the archive stays a file."""
    import tempfile

    from service.api.errors import error_response
    from service.scenes import UploadedFile, import_upload
    from service.upload_tree import UploadLimits

    app, _ = fuzz_app
    client = _admin_of_its_own(app, "fuzz-uploads")
    settings = app.state.farm.settings
    data_dir = settings.data_dir.resolve()
    scenes_dir = data_dir / "store" / "scenes"
    stored = set(os.listdir(scenes_dir))
    watched = [data_dir.parent, Path(tempfile.gettempdir())]
    before = {d: set(os.listdir(d)) for d in watched}
    failures = []
    for i, (label, parts, form, status, words) in enumerate(_hostile_uploads()):
        if label in OVER_HTTP:
            response = client.post("/scenes", files=parts, data=form)
        else:  # the upload's own code, as the route's child process runs it
            directory = tmp_path / f"upload-{i}"
            directory.mkdir()
            uploads = []
            for n, (field, (name, data)) in enumerate(parts):
                (directory / f"part-{n}").write_bytes(data)
                uploads.append(UploadedFile(field, n - 1 if field == "files" else 0, name,
                                            directory / f"part-{n}"))
            try:
                import_upload(uploads[0], uploads[1:], directory, form.get("main"),
                              UploadLimits.from_settings(settings))
                response = None
            except Exception as exc:  # noqa: BLE001 - what the route would answer
                response = error_response(exc)
        if response is None:
            failures.append(f"{label}: accepted")
            continue
        detail = json.loads(response.body if hasattr(response, "body") else response.content)
        text = _refusal(response.status_code, detail["detail"])
        if response.status_code != status or not all(w in text for w in words):
            failures.append(f"{label}: {response.status_code} {text[:300]}")
    assert not failures, "\n".join(failures)
    assert set(os.listdir(scenes_dir)) == stored  # nothing imported, nothing to render
    for folder, names in before.items():
        assert not any("evil" in n for n in set(os.listdir(folder)) - names), folder
    assert not [p for p in data_dir.rglob("*evil*")]
    assert not [p for p in tmp_path.rglob("*evil*")]
    assert list((data_dir / "uploads").iterdir()) == []
    # A nested archive is a file like any other: never unpacked.
    nested = _zip(("room.json", ROOM_JSON), ("models/tri.obj", TRI_OBJ),
                  ("inner.zip", _zip(("../../evil.json", b"{}"))))
    response = client.post("/scenes", files=[("scene", ("nested.zip", nested))])
    assert response.status_code == 201, response.text
    assert not [p for p in data_dir.rglob("*evil*")]
    assert client.get("/healthz").json()["status"] == "ok"
