"""Every bad input is a 4xx that names the problem, never a 500.

Each case here answered 500, or was accepted, before its fix: non-finite
JSON numbers (Python's reader takes NaN, Infinity and 1e999; no JSON writer
may send them back), an offset past SQLite's integers, an over-long
multipart boundary, "yes" for a boolean, numbers a render cannot hold, a
light with no area (it crashed the render process), a radiosity job that
could never be solved. The fuzz test (test_service_fuzz.py) looks for the
cases nobody listed.
"""

from __future__ import annotations

import copy
import json

import pytest

from renderer import resolve_document

from conftest import TINY

NON_FINITE = ["NaN", "Infinity", "-Infinity", "1e999"]
INT_FIELDS = ["spp", "depth", "width", "height", "tile_size", "seed", "priority"]


def strict_json(response):
    """The body, read by a JSON reader that refuses NaN and Infinity."""
    def refuse(token):
        raise ValueError(f"{token} is no JSON")
    return json.loads(response.text, parse_constant=refuse)


def assert_422_at(response, loc: list, *words: str) -> dict:
    """422 in FastAPI's shape, strict JSON, the first error at `loc`, its msg
    starting with the field's name and holding `words`."""
    assert response.status_code == 422, response.text
    detail = strict_json(response)["detail"]
    assert isinstance(detail, list) and detail, detail
    error = detail[0]
    assert {"loc", "msg", "type"} <= set(error), error
    assert error["loc"] == loc, error
    assert error["msg"].startswith(str(loc[1])), error  # the field (or "scene", "form"...)
    for word in words:
        assert word in error["msg"], (word, error)
    return error


def raw_json(client, method: str, path: str, text: str):
    return client.request(method, path, content=text.encode(),
                          headers={"content-type": "application/json"})


def with_literal(body: dict, field: str, literal: str) -> str:
    """`body` as JSON text with `field` set to a bare `literal` (NaN, 1e999...)."""
    rest = json.dumps({k: v for k, v in body.items() if k != field})
    return f'{rest[:-1]}, "{field}": {literal}}}'


@pytest.mark.parametrize("literal", NON_FINITE)
@pytest.mark.parametrize("field", INT_FIELDS)
def test01_non_finite_numbers_in_integer_fields_are_422(local_client, field, literal):
    response = raw_json(local_client, "POST", "/jobs", with_literal(TINY, field, literal))
    error = assert_422_at(response, ["body", field], field, "integer")
    assert isinstance(error["input"], str)  # "nan", "inf": the number's repr


@pytest.mark.parametrize("literal", NON_FINITE)
def test02_non_finite_priority_in_patch_is_422(local_client, literal):
    # The body is checked before the job is looked up: the job need not exist.
    response = raw_json(local_client, "PATCH", "/jobs/0123456789ab", f'{{"priority": {literal}}}')
    assert_422_at(response, ["body", "priority"], "priority", "integer")


@pytest.mark.parametrize("literal", NON_FINITE)
def test03_non_finite_numbers_anywhere_in_options_or_an_inline_scene_are_422(local_client,
                                                                            literal):
    body = dict(TINY, method="photon")
    text = json.dumps(body)[:-1] + f', "options": {{"radius": {literal}}}}}'
    assert_422_at(raw_json(local_client, "POST", "/jobs", text), ["body", "options"],
                  "options: radius must be a finite number", "JSON has no NaN or Infinity")
    # even where no renderer check would look: a scene's description
    scene = json.dumps(resolve_document("cornell-box"))[:-1] + f', "description": {literal}}}'
    text = json.dumps(dict(TINY, scene="@"))
    text = text.replace('"@"', scene)
    assert_422_at(raw_json(local_client, "POST", "/jobs", text), ["body", "scene"],
                  "scene: description must be a finite number")


@pytest.mark.parametrize("depth", [40, 900])  # 900: Python's own stack would give out first
def test03b_free_form_parts_nested_too_deep_are_422(local_client, depth):
    deep = "[" * depth + "]" * depth
    text = json.dumps(dict(TINY, method="photon"))[:-1] + f', "options": {{"radius": {deep}}}}}'
    assert_422_at(raw_json(local_client, "POST", "/jobs", text), ["body", "options"],
                  "options: nests lists and objects more than 32 levels deep (at radius[0]")
    text = json.dumps(dict(TINY, scene="@")).replace('"@"', f'{{"name": {deep}}}')
    assert_422_at(raw_json(local_client, "POST", "/jobs", text), ["body", "scene"],
                  "scene: nests lists and objects more than 32 levels deep (at name[0]")


def test04_non_finite_numbers_in_float_fields_are_422(local_client):
    for literal in NON_FINITE:
        response = raw_json(local_client, "POST", "/users",
                            f'{{"name": "nan-user", "share": {literal}}}')
        assert response.status_code == 422, response.text
        assert strict_json(response)["detail"][0]["msg"].startswith("share"), response.text


def test05_offset_and_limit_are_bounded(local_client):
    for offset in (2**63, 2**31):
        response = local_client.get("/jobs", params={"offset": offset})
        assert_422_at(response, ["query", "offset"], "offset", "2147483647")
    assert local_client.get("/jobs", params={"offset": 2**31 - 1}).json() == []
    assert_422_at(local_client.get("/jobs", params={"limit": 10**30}), ["query", "limit"], "limit")


def test06_an_over_long_multipart_boundary_is_422_on_form(local_client):
    boundary = "b" * 300  # python-multipart refuses more than 256 bytes
    body = (f'--{boundary}\r\nContent-Disposition: form-data; name="scene"; filename="s.json"'
            f'\r\n\r\n{{}}\r\n--{boundary}--\r\n').encode()
    response = local_client.post("/scenes", content=body, headers={
        "content-type": f"multipart/form-data; boundary={boundary}"})
    assert_422_at(response, ["body", "form"], "form", "Boundary length 300", "256")


@pytest.mark.parametrize("value", ["yes", "true", 1, 0, "false", None])
def test07_booleans_are_true_or_false(local_client, value):
    response = local_client.post("/jobs", json=dict(TINY, progressive=value))
    assert_422_at(response, ["body", "progressive"], "progressive", "boolean")


def _inline(mutate) -> dict:
    doc = copy.deepcopy(resolve_document("cornell-box"))
    mutate(doc)
    return dict(TINY, scene=doc)


LIGHT = 0  # cornell-box's shapes[0] is its light, shapes[1] the floor


@pytest.mark.parametrize("mutate, location, words", [
    (lambda d: d["shapes"][LIGHT]["emitter"].update(radiance=[1e300, 1, 1]),
     "shapes[0].emitter.radiance[0]", "<= 1000000"),
    (lambda d: d["shapes"][1].update(to_world=[{"translate": [0, 2e6, 0]}]),
     "shapes[1].to_world[0].translate[1]", "<= 1000000"),
    (lambda d: d["shapes"][1].update(to_world=[{"scale": [1e6, 1e6, 1e6]}, {"translate": [0, 1, 0]}]),
     "shapes[1].to_world", "after to_world"),
    (lambda d: d.update(format="rayfarm-scene/99"), "format", "rayfarm-scene/1"),
    (lambda d: d["shapes"][1].update(flip_normals="yes"), "shapes[1].flip_normals", "true or false"),
    # a light with a collinear face segfaulted every render process of its job
    (lambda d: d["shapes"][LIGHT].update(type="mesh", faces=[[0, 1, 2], [0, 1, 3]], vertices=[
        [0, 0.9, 0], [0.1, 0.9, 0], [0.2, 0.9, 0], [0, 0.9, 0.1]]),
     "shapes[0].faces[0]", "collinear"),
])
def test08_inline_scenes_out_of_the_renderer_s_range_are_422(local_client, mutate, location,
                                                             words):
    response = local_client.post("/jobs", json=_inline(mutate))
    assert_422_at(response, ["body", "scene", location], "scene", location, words)


def test09_a_radiosity_job_that_could_not_be_solved_is_refused_at_submission(local_client):
    body = dict(TINY, method="radiosity", options={"patch_size": 1e-3})
    assert_422_at(local_client.post("/jobs", json=body), ["body", "options", "patch_size"],
                  "options.patch_size", "250000")


@pytest.mark.parametrize("body, loc, words", [
    (b'{"scene": "\xff"}', ["body"], "UnicodeDecodeError"),  # FastAPI answered a bare 400
    (b"[" * 100_000 + b"]" * 100_000, ["body"], "RecursionError"),  # so too
    (b'{"spp": 4,', ["body", 10], "invalid JSON at character 10"),  # FastAPI's own json_invalid
])
def test10_a_body_that_is_no_json_is_422_on_body(local_client, body, loc, words):
    response = local_client.post("/jobs", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text
    error = strict_json(response)["detail"][0]
    assert error["loc"] == loc and error["type"] == "json_invalid", error
    assert error["msg"].startswith("body: invalid JSON") and words in error["msg"], error


def test10b_a_write_gone_stale_in_any_route_is_a_409_not_a_500():
    """The net under the routes' own retries (jobs.retrying): a StaleDataError
    (optimistic locking, service.models) that reaches the app is a conflict
    to try again, in the same error shape as every other."""
    from fastapi import FastAPI
    from fastapi.testclient import TestClient
    from sqlalchemy.orm.exc import StaleDataError

    from service.api.errors import install_error_handlers

    app = FastAPI()
    install_error_handlers(app)

    @app.post("/stale")
    def stale():
        raise StaleDataError("UPDATE statement on table 'jobs' expected to update 1 row(s)")

    response = TestClient(app).post("/stale")
    assert response.status_code == 409, response.text
    assert response.json() == {"detail": "the farm changed this meanwhile; try again"}


def test11_the_service_still_answers(local_client):
    assert local_client.get("/healthz").json()["status"] == "ok"
