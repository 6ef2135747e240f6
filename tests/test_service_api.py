"""The HTTP API in embedded mode (local process pool, SQLite): real parts."""

from __future__ import annotations

import copy
import io

import numpy as np
import pytest
from PIL import Image

from renderer import BOUNDS, METHODS, SAMPLERS, builtin_scene_names, resolve_document

from conftest import (TINY, assert_bit_identical, assert_complete_progress, assert_denoised_beside_raw,
                      channels_of, get_json, poll_job, submit, wait_for)




def assert_422(response, field: str, *words: str) -> str:
    """422 in FastAPI's shape, naming `field` in loc and message, with `words`."""
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, list) and detail, detail
    loc, msg = detail[0]["loc"], detail[0]["msg"]
    assert field.split(".")[0] in loc, (loc, msg)
    for word in words:
        assert word in msg, (word, msg)
    return msg


def test01_submit_poll_download_exr_and_png(local_client, tmp_path, reference_channels):
    job = submit(local_client, TINY)
    # one method, one name: the alias `path` is stored as the method it names
    assert job["status"] == "queued" and job["width"] == 32 and job["method"] == "path-mis"
    job = poll_job(get_json(local_client), job["id"])
    assert job["status"] == "done", job
    # Progressive by default: 3 sample passes (1, 1, 2 spp), each one unit (its 16
    # tiles hold few samples: renderer.plan groups them).
    assert_complete_progress(job["progress"], units=3, samples=32 * 32 * 4)
    assert job["progressive"] is True and job["priority"] == 0
    assert job["samples"] == 32 * 32 * 4
    assert job["started"] and job["finished"] and job["seconds"] >= 0
    response = local_client.get(job["result_url"])
    assert response.status_code == 200 and response.headers["content-type"] == "image/x-exr"
    exr = tmp_path / "result.exr"
    exr.write_bytes(response.content)
    from renderer import read_exr

    channels, header = read_exr(exr)
    assert {"R", "G", "B", "var.R", "var.G", "var.B", "samples.Y", "albedo.R", "albedo.G",
            "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth.Z"} == set(channels)
    assert channels["R"].shape == (32, 32)
    assert header["rayfarm.job_id"] == job["id"]
    assert header["rayfarm.scene"] == "cornell-box"
    assert header["rayfarm.spp"] == 4 and header["rayfarm.tile_size"] == 8  # typed: ints
    assert header["rayfarm.method"] == "path-mis" and header["rayfarm.samples"] == str(32 * 32 * 4)
    assert header["rayfarm.scene_hash"] == job["scene_hash"]
    # the achieved error statistic, as the var channels give it (float32 in the file)
    from renderer.film import image_error

    rgb = np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float64)
    var = np.stack([channels[f"var.{c}"] for c in "RGB"], axis=-1).astype(np.float64)
    assert header["rayfarm.rel_error"] == pytest.approx(image_error(rgb, var), rel=1e-3)
    # The farm's merge of stored unit films is the renderer's own render, bit for bit.
    assert_bit_identical(channels, reference_channels(TINY))
    png = local_client.get(job["preview_url"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(png.content)).size == (32, 32)
    # not submitted with denoise: no denoised image, and the route says why
    assert job["denoise"] is False and job["denoised_url"] is None
    missing = local_client.get(f"/jobs/{job['id']}/denoised.png")
    assert missing.status_code == 404 and "not submitted with denoise" in missing.json()["detail"]


def test01b_a_denoised_job_keeps_its_raw_image_and_adds_the_denoised_one(
        local_client, tmp_path, reference_channels):
    """`"denoise": true`: the merged frame denoised once (renderer.denoise),
    denoised.R/G/B beside the raw channels, which stay the renderer's bits."""
    job = submit(local_client, dict(TINY, denoise=True))
    assert job["denoise"] is True and job["denoised_url"] is None  # not before it is done
    assert local_client.get(f"/jobs/{job['id']}/denoised.png").status_code == 404
    job = poll_job(get_json(local_client), job["id"])
    assert job["status"] == "done" and job["denoised_url"] == f"/jobs/{job['id']}/denoised.png"
    exr = tmp_path / "denoised.exr"
    exr.write_bytes(local_client.get(job["result_url"]).content)
    assert_denoised_beside_raw(exr, reference_channels(TINY))
    png = local_client.get(job["denoised_url"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(png.content)).size == (32, 32)
    assert png.content != local_client.get(job["preview_url"]).content


def test02_width_and_height_default_to_the_scene_camera(local_client):
    body = {k: v for k, v in TINY.items() if k not in ("width", "height")}
    job = submit(local_client, dict(body, spp=64))  # seconds of work: still running at DELETE
    camera = resolve_document("cornell-box")["camera"]
    assert (job["width"], job["height"]) == (camera["width"], camera["height"])
    assert local_client.post(f"/jobs/{job['id']}/cancel").json()["status"] == "canceled"


def test03_results_are_404_until_done_and_cancel_is_409_after(local_client):
    body = dict(TINY, width=256, height=256, spp=64, tile_size=16)
    job = submit(local_client, body)
    response = local_client.get(f"/jobs/{job['id']}/result.exr")
    assert response.status_code == 404 and "exists once it is done" in response.json()["detail"]
    canceled = local_client.post(f"/jobs/{job['id']}/cancel")
    assert canceled.status_code == 200 and canceled.json()["status"] == "canceled"
    assert canceled.json()["finished"] is not None
    again = local_client.post(f"/jobs/{job['id']}/cancel")
    assert again.status_code == 409 and "canceled" in again.json()["detail"]
    # No unit finished (canceled at once): no partial result either (test03b).
    if canceled.json()["progress"]["units_done"] == 0:
        assert local_client.get(f"/jobs/{job['id']}/result.exr").status_code == 404


def test03b_a_canceled_jobs_finished_units_download_as_a_partial_result(local_client, tmp_path):
    from renderer import read_exr

    body = dict(TINY, width=64, height=64, spp=512, tile_size=8, progressive=False)  # 64 units
    job = submit(local_client, body)
    wait_for(lambda: local_client.get(f"/jobs/{job['id']}").json()["progress"]["units_done"] >= 2,
             120, "two units finished")
    canceled = local_client.post(f"/jobs/{job['id']}/cancel").json()
    done = canceled["progress"]["units_done"]
    assert canceled["partial"] and canceled["result_url"] == f"/jobs/{job['id']}/result.exr"
    assert 2 <= done < 64
    exr = local_client.get(canceled["result_url"])
    assert exr.status_code == 200
    (tmp_path / "partial.exr").write_bytes(exr.content)
    channels, header = read_exr(tmp_path / "partial.exr")
    assert header["rayfarm.partial"] == 1 and header["rayfarm.job_id"] == job["id"]
    tiles = channels["samples.Y"].reshape(8, 8, 8, 8).max(axis=(1, 3))  # per 8 x 8 tile
    assert (tiles == 512).sum() == local_client.get(f"/jobs/{job['id']}").json()[
        "progress"]["units_done"] == done  # the finished tiles, and only those
    assert (tiles == 0).sum() == 64 - done
    png = local_client.get(f"/jobs/{job['id']}/preview.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert local_client.get(canceled["result_url"]).content == exr.content  # written once


def test04_unknown_job_is_404(local_client):
    assert local_client.get("/jobs/0123456789ab").status_code == 404
    assert local_client.delete("/jobs/0123456789ab").status_code == 404
    assert local_client.post("/jobs/0123456789ab/cancel").status_code == 404
    assert local_client.get("/jobs/../../etc/passwd/result.exr").status_code == 404


def _bound_cases():
    for name, (lo, hi) in BOUNDS.items():
        yield pytest.param(name, lo - 1, (str(lo), str(hi)), id=f"{name}-below")
        if name != "seed":
            yield pytest.param(name, hi + 1, (str(lo), str(hi)), id=f"{name}-above")


@pytest.mark.parametrize("field,value,words", list(_bound_cases()))
def test05_out_of_bounds_fields_are_422_naming_field_and_bounds(local_client, field, value, words):
    response = local_client.post("/jobs", json=dict(TINY, **{field: value}))
    assert_422(response, field, field, *words)


@pytest.mark.parametrize("field,registry", [
    ("scene", builtin_scene_names()), ("method", list(METHODS)), ("sampler", list(SAMPLERS))])
def test06_unknown_names_are_422_listing_the_allowed_ones(local_client, field, registry):
    response = local_client.post("/jobs", json=dict(TINY, **{field: "no-such-thing"}))
    msg = assert_422(response, field, field, "no-such-thing", "allowed")
    for name in registry:
        assert name in msg


def test07_work_above_max_work_is_422(local_client, local_settings):
    spp = BOUNDS["spp"][1]
    body = dict(TINY, width=256, height=256, spp=spp)
    assert 256 * 256 * spp > local_settings.max_work
    assert_422(local_client.post("/jobs", json=body), "spp", str(local_settings.max_work))


def test08_too_many_units_is_422_on_tile_size(local_client):
    body = dict(TINY, width=8192, height=8192, spp=1, tile_size=4)
    assert_422(local_client.post("/jobs", json=body), "tile_size", "tile_size", "65536")


@pytest.mark.parametrize("body,field", [
    ({"spp": "4"}, "spp"),                   # strings are not integers
    ({"depth": 2.5}, "depth"),
    ({"options": {"no_such_option": 1}}, "options"),
    ({"colour": "red"}, "colour"),           # unknown request fields are refused
    ({"scene": 42}, "scene"),
])
def test09_wrong_types_and_unknown_fields_are_422(local_client, body, field):
    response = local_client.post("/jobs", json=dict(TINY, **body))
    assert response.status_code == 422, response.text
    assert any(field in map(str, d["loc"]) for d in response.json()["detail"]), response.json()


def _inline(mutate) -> dict:
    doc = copy.deepcopy(resolve_document("cornell-box"))
    mutate(doc)
    return doc


@pytest.mark.parametrize("mutate,location", [
    (lambda d: d["shapes"][2].__setitem__("material", "gold"), "shapes[2].material"),
    (lambda d: d["shapes"][0].__setitem__("to_world", [[0] * 4] * 4), "shapes[0].to_world"),
    (lambda d: d["camera"].__setitem__("fov", 500), "camera.fov"),
    (lambda d: d["materials"]["red"].__setitem__("albedo", [2, 0, 0]), "materials.red.albedo"),
    (lambda d: d.__setitem__("shapes", "many"), "shapes"),
    (lambda d: d["shapes"][1].__setitem__("type", "torus"), "shapes[1].type"),
])
def test10_malformed_inline_scene_is_422_naming_the_location(local_client, mutate, location):
    response = local_client.post("/jobs", json=dict(TINY, scene=_inline(mutate)))
    msg = assert_422(response, "scene", f"scene.{location}")
    assert response.json()["detail"][0]["loc"] == ["body", "scene", location]
    assert msg


def test11_inline_scene_renders_like_the_builtin(local_client, tmp_path):
    body = dict(TINY, scene=_inline(lambda d: d.__setitem__("name", "my-box")))
    job = submit(local_client, body)
    assert job["scene"] == "inline:my-box"
    job = poll_job(get_json(local_client), job["id"])
    assert job["status"] == "done", job
    (tmp_path / "a.exr").write_bytes(local_client.get(job["result_url"]).content)
    builtin = poll_job(get_json(local_client), submit(local_client, TINY)["id"])
    (tmp_path / "b.exr").write_bytes(local_client.get(builtin["result_url"]).content)
    # Only the name differs: same geometry, same pixels.
    assert_bit_identical(channels_of(tmp_path / "a.exr"), channels_of(tmp_path / "b.exr"))


def test12_service_stays_healthy_after_garbage(local_client):
    garbage = [b"not json", b"[]", b"{}", b'{"scene": {"camera": [1]}}', b"null",
               b'{"scene": {"shapes": [{"type": "mesh", "material": "x"}]}}']
    for payload in garbage:
        response = local_client.post("/jobs", content=payload,
                                     headers={"content-type": "application/json"})
        assert response.status_code == 422, (payload, response.text)
    deep = {"camera": {"origin": [[[[]]]], "target": [0, 0, 0], "fov": 40}, "shapes": []}
    assert local_client.post("/jobs", json=dict(TINY, scene=deep)).status_code == 422
    # A material given as a list once escaped the scene validator as a TypeError.
    odd = _inline(lambda d: d["shapes"][0].__setitem__("material", ["white"]))
    assert_422(local_client.post("/jobs", json=dict(TINY, scene=odd)), "scene", "scene")
    health = local_client.get("/healthz")
    assert health.status_code == 200 and health.json()["status"] == "ok"
    assert health.json()["scheduler"] == "running" and health.json()["database"] == "ok"
    job = poll_job(get_json(local_client), submit(local_client, TINY)["id"])
    assert job["status"] == "done"


def test13_list_jobs_newest_first_and_filter_by_status(local_client):
    first = submit(local_client, TINY)
    second = submit(local_client, TINY)
    ids = [j["id"] for j in local_client.get("/jobs").json()]
    assert ids.index(second["id"]) < ids.index(first["id"])
    poll_job(get_json(local_client), second["id"])
    poll_job(get_json(local_client), first["id"])
    done = local_client.get("/jobs", params={"status": "done"}).json()
    assert done and all(j["status"] == "done" for j in done)
    assert_422(local_client.get("/jobs", params={"status": "sleeping"}), "status", "allowed")


def test13b_list_jobs_filters_by_method_scene_sampler_and_owner_or_says_why_not(local_client,
                                                                               make_user):
    path = submit(local_client, dict(TINY, sampler="random"))  # "path": stored as path-mis
    raster = submit(local_client, dict(TINY, method="raster", scene="veach-mis"))
    mine = submit(make_user("filter-owner"), TINY)

    def listed(**params) -> set[str]:
        response = local_client.get("/jobs", params={**params, "limit": 1000})
        assert response.status_code == 200, response.text
        return {j["id"] for j in response.json()}

    for method in ("path", "path-mis"):  # an alias finds its method's jobs
        assert path["id"] in listed(method=method) and raster["id"] not in listed(method=method)
    assert raster["id"] in listed(method="raster") and path["id"] not in listed(method="raster")
    assert raster["id"] in listed(scene="veach-mis") and path["id"] not in listed(scene="veach-mis")
    assert path["id"] in listed(sampler="random") and raster["id"] not in listed(sampler="random")
    assert listed(owner="filter-owner") == {mine["id"]}
    assert listed(method="raster", scene="cornell-box").isdisjoint({raster["id"], path["id"]})
    assert_422(local_client.get("/jobs", params={"methd": "raster"}), "methd",
               "unknown query parameter")
    assert_422(local_client.get("/jobs", params={"method": "nope"}), "method", "allowed")
    assert_422(local_client.get("/jobs", params={"sampler": "nope"}), "sampler", "allowed")


def test14_registries_scenes_docs_and_dashboard(local_client):
    methods = local_client.get("/methods").json()
    assert [m["name"] for m in methods] == [m.name for m in dict.fromkeys(METHODS.values())]
    assert methods[0] == {**next(iter(METHODS.values())).describe(), "noise_target": True}
    # which AOV layers each method writes, and why not where it writes none
    by_name = {m["name"]: m for m in methods}
    assert by_name["path-mis"]["aovs"] == ["albedo", "normal", "depth"]
    assert by_name["path-mis"]["aov_note"] is None
    assert by_name["light"]["aovs"] == [] and "splatted" in by_name["light"]["aov_note"]
    samplers = local_client.get("/samplers").json()
    assert [s["name"] for s in samplers] == list(SAMPLERS)
    assert [s["name"] for s in samplers if s["default"]] == ["sobol"]  # what a job gets unasked
    scenes = local_client.get("/scenes").json()
    assert [s["name"] for s in scenes if s["kind"] == "builtin"] == builtin_scene_names()
    assert local_client.get("/docs").status_code == 200
    schemas = local_client.get("/openapi.json").json()["components"]["schemas"]
    assert {"JobCreate", "JobPublic"} <= set(schemas)
    spp = schemas["JobCreate"]["properties"]["spp"]  # optional: a target may give max_spp
    assert [b["maximum"] for b in spp["anyOf"] if b.get("type") == "integer"] == [BOUNDS["spp"][1]]
    # The dashboard and the API docs: every asset they load is served here (no CDN);
    # tests/test_dashboard_browser.py drives the dashboard itself in Chromium.
    page = local_client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    docs = local_client.get("/docs").text + local_client.get("/redoc").text
    import re

    links = re.findall(r'(?:src|href)="([^"]+)"', page.text + docs)
    assets = [a.split("#")[0] for a in links if not a.startswith("#")]
    assert assets and all(a.startswith("/") and not a.startswith("//") for a in assets), assets
    for asset in assets:
        assert local_client.get(asset).status_code == 200, asset


def test15_a_preview_replaced_while_it_is_sent_arrives_whole(local_client, local_app):
    """The store replaces a running job's preview.png and noise.png by renaming
    a new file over the old one while clients fetch them. Each response must be
    one whole file with a Content-Length that matches its body: a FileResponse
    took the length from one stat and the bytes from a later open, and a
    rename between the two sent a body the length did not match (the
    browser's ERR_CONTENT_LENGTH_MISMATCH, seen in a dashboard test)."""
    import os
    import threading

    job = poll_job(get_json(local_client), submit(local_client, TINY)["id"])
    store = local_app.state.farm.store
    for kind, path in (("preview.png", store.preview_path(job["id"])),
                       ("noise.png", store.noise_path(job["id"]))):
        small = path.read_bytes()
        buffer = io.BytesIO()
        Image.open(io.BytesIO(small)).resize((97, 89)).save(buffer, format="PNG")
        versions = (small, buffer.getvalue())
        assert len(versions[0]) != len(versions[1])
        stop = threading.Event()

        def replace_over_and_over():
            k = 0
            while not stop.is_set():
                tmp = path.with_name(f".{path.name}.test")
                tmp.write_bytes(versions[k % 2])
                os.replace(tmp, path)  # as Store._write_atomic does
                k += 1

        writer = threading.Thread(target=replace_over_and_over)
        writer.start()
        try:
            for _ in range(200):
                response = local_client.get(f"/jobs/{job['id']}/{kind}")
                assert response.status_code == 200, response.text
                assert int(response.headers["content-length"]) == len(response.content), kind
                assert response.content in versions, kind
        finally:
            stop.set()
            writer.join()
            path.write_bytes(small)
