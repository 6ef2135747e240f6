"""Uploaded scenes (POST /scenes with mesh files), the scene list, thumbnails,
deletion and the request-body limits: real service, real files, real server."""

from __future__ import annotations

import copy
import io
import json
import os
import socket
import tarfile
import tempfile
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from renderer import builtin_scene_names, resolve_document, scene_text

from conftest import (ADMIN_HEADERS, TINY, assert_bit_identical, channels_of, embedded_env,
                      get_json, poll_job, real_scenes, start_serve, submit, wait_for,
                      zip_of_folder)

WALL = {"type": "rectangle", "material": "white"}
ROOM = {
    "description": "a box room, a light under the ceiling, a cube from an OBJ file",
    "camera": {"origin": [0, 0, 3.9], "target": [0, 0, 0], "fov": 45, "fov_axis": "x",
               "width": 256, "height": 192},
    "materials": {"white": {"type": "diffuse", "albedo": 0.7},
                  "red": {"type": "diffuse", "albedo": [0.7, 0.1, 0.1]},
                  "green": {"type": "diffuse", "albedo": [0.1, 0.6, 0.1]}},
    "shapes": [
        dict(WALL, to_world=[{"rotate": {"axis": [1, 0, 0], "angle": -90}},
                             {"translate": [0, -1, 0]}]),
        dict(WALL, to_world=[{"rotate": {"axis": [1, 0, 0], "angle": 90}},
                             {"translate": [0, 1, 0]}]),
        dict(WALL, to_world=[{"translate": [0, 0, -1]}]),
        dict(WALL, material="red",
             to_world=[{"rotate": {"axis": [0, 1, 0], "angle": 90}}, {"translate": [-1, 0, 0]}]),
        dict(WALL, material="green",
             to_world=[{"rotate": {"axis": [0, 1, 0], "angle": -90}}, {"translate": [1, 0, 0]}]),
        dict(WALL, to_world=[{"scale": [0.3, 0.3, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                             {"translate": [0, 0.99, 0]}],
             emitter={"type": "area", "radiance": [15, 15, 15]}),
        {"type": "mesh", "file": "cube.obj", "material": "red",
         "to_world": [{"scale": [0.35, 0.35, 0.35]}, {"rotate": {"axis": [0, 1, 0], "angle": 30}},
                      {"translate": [0.2, -0.65, 0]}]},
    ],
}
MESH = 6  # index of the mesh shape
TRIANGLES = 6 * 2 + 12  # six rectangles and the OBJ cube's six quads, fanned
CUBE_OBJ = """# the cube [-1, 1]^3, faces counter-clockwise seen from outside
v -1 -1 -1
v 1 -1 -1
v 1 1 -1
v -1 1 -1
v -1 -1 1
v 1 -1 1
v 1 1 1
v -1 1 1
f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 4 8 7 3
f 1 5 8 4
f 2 3 7 6
"""


def room(name: str, **changes) -> dict:
    """The room under its own name (each test uploads content new to the session)."""
    doc = copy.deepcopy(ROOM)
    doc["name"] = name
    doc.update(changes)
    return doc


def scene_bytes(doc) -> bytes:
    return json.dumps(doc, indent=1).encode()


def upload(client, scene: bytes | None, files=(("cube.obj", CUBE_OBJ.encode()),),
           scene_name: str = "room.json", extra=()):
    parts = [] if scene is None else [("scene", (scene_name, scene, "application/json"))]
    parts += [("files", (name, data, "text/plain")) for name, data in files]
    return client.post("/scenes", files=parts + list(extra))


def upload_created(client, doc: dict) -> dict:
    response = upload(client, scene_bytes(doc))
    assert response.status_code == 201, response.text
    return response.json()


def resolved_locally(tmp_path: Path, doc: dict, obj: str = CUBE_OBJ) -> dict:
    """The document as `rayfarm render` resolves it from files on disk."""
    folder = tmp_path / "local-scene"
    folder.mkdir(exist_ok=True)
    (folder / "cube.obj").write_text(obj)
    (folder / "room.json").write_text(json.dumps(doc))
    return resolve_document(folder / "room.json")


def assert_422(response, loc: list, *words: str) -> str:
    """422 in FastAPI's shape: `loc` exactly, the message starting with its location."""
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, list) and len(detail) == 1, detail
    assert detail[0]["loc"] == loc, detail
    msg = detail[0]["msg"]
    where = ".".join(str(p) for p in loc[1:2]) + "".join(
        f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc[2:])
    assert msg.startswith(where + ":"), (where, msg)
    for word in words:
        assert word in msg, (word, msg)
    return msg


def wait_for_thumbnail(client, scene_id: str) -> str:
    def ready():
        return client.get(f"/scenes/{scene_id}").json()["thumbnail_url"]
    return wait_for(ready, 120, f"the thumbnail of {scene_id}", interval=0.1)


# -- upload, list, thumbnail, render ----------------------------------------------------------

def test01_upload_with_an_obj_mesh_is_stored_by_hash_and_listed(local_client, tmp_path):
    doc = room("test01-room")
    response = upload(local_client, scene_bytes(doc))
    assert response.status_code == 201, response.text
    scene = response.json()
    key, text = scene_text(resolved_locally(tmp_path, doc))
    assert scene["id"] == scene["scene_hash"] == key  # the content hash of the resolved scene
    assert response.headers["location"] == f"/scenes/{key}"
    assert scene["kind"] == "uploaded" and scene["name"] == "test01-room"
    assert scene["description"] == ROOM["description"]
    assert (scene["width"], scene["height"], scene["triangles"]) == (256, 192, TRIANGLES)
    assert scene["bytes"] == len(text.encode()) and scene["created"]
    listed = local_client.get("/scenes").json()
    kinds = [s["kind"] for s in listed]
    assert [s["id"] for s in listed[:len(builtin_scene_names())]] == builtin_scene_names()
    assert kinds == sorted(kinds)  # built-ins first
    mine = [s for s in listed if s["id"] == key]
    assert len(mine) == 1 and mine[0]["kind"] == "uploaded"
    one = local_client.get(f"/scenes/{key}").json()
    assert {k: v for k, v in one.items() if k != "thumbnail_url"} == \
        {k: v for k, v in scene.items() if k != "thumbnail_url"}
    # A scene file without a name is named after the uploaded file.
    unnamed = {k: v for k, v in room("").items() if k != "name"}
    unnamed["description"] = "test01 unnamed"
    response = upload(local_client, scene_bytes(unnamed), scene_name="attic.json")
    assert response.status_code == 201 and response.json()["name"] == "attic"


def test02_thumbnails_are_rendered_in_the_background(local_client, local_settings):
    scene = upload_created(local_client, room("test02-room"))
    url = wait_for_thumbnail(local_client, scene["id"])
    assert url == f"/scenes/{scene['id']}/thumbnail.png"
    png = local_client.get(url)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    image = np.asarray(Image.open(io.BytesIO(png.content)).convert("RGB"))
    assert image.shape == (96, 128, 3)  # 128 on the long side, the camera's 4:3
    assert image.std() > 10 and len(np.unique(image.reshape(-1, 3), axis=0)) > 100
    stored = local_settings.data_dir / "store" / "scenes" / f"{scene['id']}.png"
    assert stored.read_bytes() == png.content
    # Built-ins get theirs at start; a camera smaller than 128 px keeps its size.
    for name, size in (("cornell-box", (128, 128)), ("furnace-point", (16, 16))):
        assert wait_for_thumbnail(local_client, name) == f"/scenes/{name}/thumbnail.png"
        image = Image.open(io.BytesIO(local_client.get(f"/scenes/{name}/thumbnail.png").content))
        assert image.size == size


def test03_job_on_an_uploaded_scene_renders_it_bit_for_bit(local_client, tmp_path,
                                                           reference_channels):
    doc = room("test03-room")
    scene = upload_created(local_client, doc)
    body = dict(TINY, scene=scene["id"], width=32, height=24)
    job = submit(local_client, body)
    assert job["scene"] == "test03-room" and job["scene_hash"] == scene["id"]
    resolved = resolved_locally(tmp_path, doc)
    inline = submit(local_client, dict(body, scene=resolved))
    assert inline["scene_hash"] == scene["id"]
    get = get_json(local_client)
    job, inline = poll_job(get, job["id"]), poll_job(get, inline["id"])
    assert job["status"] == inline["status"] == "done", (job, inline)
    (tmp_path / "upload.exr").write_bytes(local_client.get(job["result_url"]).content)
    (tmp_path / "inline.exr").write_bytes(local_client.get(inline["result_url"]).content)
    uploaded = channels_of(tmp_path / "upload.exr")
    assert uploaded["R"].shape == (24, 32) and uploaded["R"].max() > 0
    assert_bit_identical(uploaded, channels_of(tmp_path / "inline.exr"))
    assert_bit_identical(uploaded, reference_channels(dict(body, scene=resolved)))


def test04_uploading_the_same_content_again_answers_the_existing_record(local_client):
    doc = room("test04-room")
    first = upload(local_client, scene_bytes(doc))
    assert first.status_code == 201
    # Other bytes (indentation, file name), the same resolved scene: the same id.
    again = upload(local_client, json.dumps(doc).encode(), scene_name="copy.json")
    assert again.status_code == 200, again.text
    assert "location" not in again.headers
    assert again.json()["id"] == first.json()["id"]
    assert again.json()["created"] == first.json()["created"]
    ids = [s["id"] for s in local_client.get("/scenes").json()]
    assert ids.count(first.json()["id"]) == 1


# -- invalid uploads: 422 naming the field, the location and the line -------------------------

def _bad_json():
    lines = scene_bytes(room("bad")).decode().splitlines()
    lines[3] = lines[3] + ","  # line 4: '"origin": [,'  (a value is missing)
    return "\n".join(lines).encode()


def _broken_line_2():
    lines = scene_bytes(room("bad")).decode().splitlines()
    lines[1] = lines[1] + " ]"  # line 2: an extra bracket
    return "\n".join(lines).encode()


def _not_utf8():
    text = json.dumps(room("bad", description="caf\u00e9"), indent=1, ensure_ascii=False)
    return text.encode("latin-1")  # the e-acute is one byte 0xe9, not UTF-8


def _line_of(data: bytes, needle: bytes) -> str:
    return str(data[:data.index(needle)].count(b"\n") + 1)


def _with_shape(i, **changes):
    doc = room("bad")
    doc["shapes"][i] = dict(doc["shapes"][i], **changes)
    return scene_bytes(doc)


def _cases():
    ok_files = (("cube.obj", CUBE_OBJ.encode()),)
    bad_obj = CUBE_OBJ.replace("v 1 -1 -1", "v 1 x -1").encode()  # line 3 of the file
    latin = _not_utf8()
    yield pytest.param(_bad_json(), ok_files, ["body", "scene"],
                       ("invalid JSON in room.json at line 4, column 14", "Expecting value"),
                       id="bad-json")
    yield pytest.param(_broken_line_2(), ok_files, ["body", "scene"],
                       ("invalid JSON in room.json at line 2, column",), id="bad-json-line")
    yield pytest.param(latin, ok_files, ["body", "scene"],
                       ("room.json is not UTF-8 text", "0xe9", f"line {_line_of(latin, b'caf')}"),
                       id="not-utf8")
    yield pytest.param(b"  \n", ok_files, ["body", "scene"], ("room.json is empty",), id="empty")
    yield pytest.param(b"[1, 2]", (), ["body", "scene"], ("must be a JSON object",), id="array")
    yield pytest.param(b'"cornell-box"', (), ["body", "scene"], ("must be a JSON object",),
                       id="string")
    yield pytest.param(_with_shape(2, to_world=[[0] * 4] * 4), ok_files,
                       ["body", "scene", "shapes[2].to_world"], ("singular",), id="singular")
    yield pytest.param(scene_bytes(room("bad", camera=dict(ROOM["camera"], fov=500))), ok_files,
                       ["body", "scene", "camera.fov"], ("179",), id="fov")
    yield pytest.param(_with_shape(1, material="gold"), ok_files,
                       ["body", "scene", "shapes[1].material"], ("gold",), id="material")
    yield pytest.param(scene_bytes(room("bad")), (), ["body", "scene", f"shapes[{MESH}].file"],
                       ("cube.obj",), id="mesh-missing")
    yield pytest.param(_with_shape(MESH, file="meshes/cube.obj"), ok_files,
                       ["body", "scene", f"shapes[{MESH}].file"], ("not found",),
                       id="mesh-elsewhere")
    yield pytest.param(_with_shape(MESH, file="../cube.obj"), ok_files,
                       ["body", "scene", f"shapes[{MESH}].file"], ("inside",),
                       id="mesh-parent")
    yield pytest.param(scene_bytes(room("bad")), (("cube.obj", bad_obj),),
                       ["body", "scene", f"shapes[{MESH}].file"],
                       ("cube.obj:3", "cannot parse", "v 1 x -1"), id="mesh-unparsable")
    yield pytest.param(scene_bytes(room("bad")), (("cube.obj", b"v 0 0 0\nv 1 0 0\nf 1 2 9\n"),),
                       ["body", "scene", f"shapes[{MESH}].file"],
                       ("cube.obj:3", "face vertex index 9 is out of range", "2 vertices"),
                       id="mesh-index")
    # A file's name is its path in the scene's folder: relative, inside it.
    for i, (name, words) in enumerate([
            ("../evil.obj", ("leaves the upload's folder",)),
            ("a/../../evil.obj", ("leaves the upload's folder",)),
            ("..\\evil.obj", ("backslash",)), ("..", ("leaves the upload's folder",)),
            ("/tmp/x.obj", ("absolute path",)), ("C:/x.obj", ("drive letter",)),
            ("a/" * 17 + "x.obj", ("17 folders deep", "RAYFARM_MAX_UPLOAD_DEPTH")),
            ("x" * 256 + ".obj", ("longer than 255 bytes",))]):
        yield pytest.param(scene_bytes(room("bad")), (("cube.obj", CUBE_OBJ.encode()),
                                                      (name, CUBE_OBJ.encode())),
                           ["body", "files", 1], words, id=f"file-name-{i}")
    yield pytest.param(scene_bytes(room("bad")), ok_files + ok_files, ["body", "files", 1],
                       ("'cube.obj' is uploaded twice", "files[0]"), id="duplicate")
    yield pytest.param(scene_bytes(room("bad")), (("room.json", b"{}"),), ["body", "files", 0],
                       ("'room.json' is uploaded twice", "also as scene"), id="duplicate-scene")
    yield pytest.param(scene_bytes(room("bad")), (("room.json/cube.obj", b"{}"),),
                       ["body", "files", 0], ("'room.json' is a file of the upload",),
                       id="file-and-folder")
    yield pytest.param(None, ok_files, ["body", "scene"], ("holds no scene file",),
                       id="no-scene")


@pytest.mark.parametrize("scene,files,loc,words", list(_cases()))
def test05_invalid_uploads_are_422_naming_where(local_client, scene, files, loc, words):
    assert_422(upload(local_client, scene, files), loc, *words)


def test06_form_shape_errors_are_422(local_client):
    doc = scene_bytes(room("bad"))
    extra = [("colour", (None, b"red"))]
    assert_422(upload(local_client, doc, extra=extra), ["body", "colour"],
               "unknown form field", "scene, files")
    # A part named by a digit int() refuses (str.isdigit("¹") is True): found by
    # test_service_fuzz as a 500.
    assert_422(upload(local_client, doc, extra=[("¹", (None, b"x"))]), ["body", "¹"],
               "unknown form field")
    twice = [("scene", ("again.json", doc, "application/json"))]
    assert_422(upload(local_client, doc, extra=twice), ["body", "scene"], "at most 1")
    assert_422(local_client.post("/scenes", json=room("bad")), ["body", "scene"],
               "multipart/form-data")
    # httpx escapes control characters in file names; a raw body need not.
    tab = (b'--xx\r\nContent-Disposition: form-data; name="scene"; filename="a.json"\r\n\r\n'
           + doc + b'\r\n--xx\r\nContent-Disposition: form-data; name="files"; '
           b'filename="cu\tbe.obj"\r\n\r\n' + CUBE_OBJ.encode() + b"\r\n--xx--\r\n")
    assert_422(local_client.post("/scenes", content=tab,
                                 headers={"content-type": "multipart/form-data; boundary=xx"}),
               ["body", "files", 0], "control character")
    truncated = (b'--xx\r\nContent-Disposition: form-data; name="scene"; filename="a.json"\r\n'
                 b"\r\n{}")
    assert_422(local_client.post("/scenes", content=truncated,
                                 headers={"content-type": "multipart/form-data; boundary=xx"}),
               ["body", "form"], "closing boundary")
    assert local_client.get("/healthz").json()["status"] == "ok"


def test07_file_names_never_write_outside_the_data_dir(local_client, local_settings):
    data_dir = local_settings.data_dir.resolve()
    watched = [data_dir.parent, data_dir.parent.parent, Path(tempfile.gettempdir())]
    before = {d: set(os.listdir(d)) for d in watched}
    doc = room("test07", shapes=ROOM["shapes"][:MESH] + [dict(ROOM["shapes"][MESH],
                                                                file="../evil.obj")])
    for name in ["../evil.obj", "../../evil.obj", "../" * 12 + "tmp/evil.obj", "evil.obj"]:
        response = upload(local_client, scene_bytes(doc), files=[(name, CUBE_OBJ.encode())])
        assert response.status_code == 422, response.text
    for folder, names in before.items():
        assert not any("evil" in n for n in set(os.listdir(folder)) - names), folder
    assert not [p for p in data_dir.rglob("*evil*")]
    assert list((data_dir / "uploads").iterdir()) == []  # each upload's directory is deleted


# -- folders: relative paths, archives, a folder's files, the main file -----------------------

def _folder(name: str) -> dict[str, bytes]:
    """A scene's folder (path -> bytes): the room naming its mesh in a subfolder."""
    doc = room(name, shapes=ROOM["shapes"][:MESH] + [dict(ROOM["shapes"][MESH],
                                                           file="models/cube.obj")])
    return {"room.json": scene_bytes(doc), "models/cube.obj": CUBE_OBJ.encode(),
            "LICENSE.txt": b"CC0\n"}


def zipped(files: dict[str, bytes], top: str = "") -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in files.items():
            archive.writestr(top + name, data)
    return out.getvalue()


def tarred(files: dict[str, bytes], mode: str = "w:gz") -> bytes:
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode=mode) as archive:
        for name, data in files.items():
            info = tarfile.TarInfo("./" + name)
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))
    return out.getvalue()


def test13_a_scene_folder_comes_as_relative_paths_an_archive_or_a_folder(local_client, tmp_path):
    """One folder sent four ways is one scene: the scene file with its files
    at relative paths, a zip of the folder (its top folder kept), a .tar.gz,
    and the folder's files alone (a browser's folder picker). Files the scene
    does not name ride along; the record names its main file."""
    folder = _folder("test13-room")
    mesh = ("files", ("models/cube.obj", folder["models/cube.obj"], "text/plain"))
    first = local_client.post("/scenes", files=[
        ("scene", ("room.json", folder["room.json"], "application/json")), mesh,
        ("files", ("LICENSE.txt", folder["LICENSE.txt"], "text/plain"))])
    assert first.status_code == 201, first.text
    record = first.json()
    assert record["source"] == "room.json" and record["report"] == []
    assert record["triangles"] == TRIANGLES
    local = tmp_path / "local"
    for name, data in folder.items():
        (local / name).parent.mkdir(parents=True, exist_ok=True)
        (local / name).write_bytes(data)
    assert record["id"] == scene_text(resolve_document(local / "room.json"))[0]
    ways = {"zip": [("scene", ("room.zip", zipped(folder, "test13/"), "application/zip"))],
            "tar.gz": [("scene", ("room.tar.gz", tarred(folder), "application/gzip"))],
            "folder": [("files", (f"test13/{name}", data, "application/octet-stream"))
                       for name, data in folder.items()]}
    for way, parts in ways.items():
        again = local_client.post("/scenes", files=parts)
        assert again.status_code == 200, (way, again.text)
        assert again.json()["id"] == record["id"], way
    # Several scene files at the top level: 422 asking for `main`, which picks one.
    two = dict(folder, **{"other.json": folder["room.json"]})
    ambiguous = local_client.post("/scenes", files=[("scene", ("two.zip", zipped(two)))])
    assert_422(ambiguous, ["body", "main"], "several scene files", "other.json, room.json")
    chosen = local_client.post("/scenes", files=[("scene", ("two.zip", zipped(two)))],
                               data={"main": "room.json"})
    assert chosen.status_code == 200 and chosen.json()["id"] == record["id"], chosen.text
    assert_422(local_client.post("/scenes", files=[("scene", ("two.zip", zipped(two)))],
                                 data={"main": "nope.json"}),
               ["body", "main"], "no file 'nope.json'", "other.json, room.json")
    assert_422(local_client.post("/scenes", files=[("scene", ("two.zip", zipped(two)))],
                                 data={"main": "LICENSE.txt"}),
               ["body", "main"], "not a scene file")
    assert_422(local_client.post("/scenes", files=[("scene", ("room.json", folder["room.json"])),
                                                   mesh], data={"main": "room.json"}),
               ["body", "main"], "with a scene part")
    assert_422(local_client.post("/scenes", files=[("scene", ("a.zip", zipped(folder))), mesh]),
               ["body", "files", 0], "an archive alone")
    assert_422(local_client.post("/scenes", files=[("scene", ("a.zip", b"not a zip"))]),
               ["body", "scene"], "named like a zip archive but is none")


def test13b_a_check_that_takes_too_long_is_stopped(local_app):
    """An upload whose check outlasts RAYFARM_UPLOAD_CHECK_SECONDS is a 413
    (a file that makes an importer spin must not hold a slot forever)."""
    from service import scenes
    from service.errors import TooLarge
    from service.upload_tree import UploadLimits

    store = local_app.state.farm.store
    with store.upload_dir() as directory:
        (directory / "part-0").write_bytes(scene_bytes(room("test13b")))
        (directory / "part-1").write_text(CUBE_OBJ)
        with pytest.raises(TooLarge, match="RAYFARM_UPLOAD_CHECK_SECONDS"):
            scenes.check_upload(store, scenes.UploadedFile("scene", 0, "room.json",
                                                           directory / "part-0"),
                                [scenes.UploadedFile("files", 0, "cube.obj", directory / "part-1")],
                                directory, None, UploadLimits(max_seconds=1e-3))


def test14_a_mitsuba_scene_uploads_with_its_import_report(local_client):
    """The shared cornell-box, its folder zipped: the import report (the
    integrator parameters no Mitsuba release knows, the <mode> element...)
    comes back from the upload, is stored with the scene and shown by
    GET /scenes/{id} and GET /scenes; each entry names file and line."""
    scene = real_scenes("cornell-box/scene.xml") / "cornell-box" / "scene.xml"
    pytest.importorskip("renderer.importers.mitsuba",
                        reason="the Mitsuba importer is not in this checkout")
    archive = zipped({"cornell-box/scene.xml": scene.read_bytes(),
                      "cornell-box/LICENSE.txt": (scene.parent / "LICENSE.txt").read_bytes()})
    response = local_client.post("/scenes", files=[("scene", ("cornell-box.zip", archive))])
    assert response.status_code in (200, 201), response.text
    record = response.json()
    assert record["source"] == "cornell-box/scene.xml"
    report = record["report"]
    assert report and all(set(e) == {"element", "file", "line", "action"} for e in report)
    assert all(e["file"] == "scene.xml" or e["file"].endswith("/scene.xml") for e in report)
    assert any(isinstance(e["line"], int) and e["line"] > 1 for e in report)
    assert any("integrator" in e["element"] or "mode" in e["element"] for e in report), report
    assert local_client.get(f"/scenes/{record['id']}").json()["report"] == report
    listed = {s["id"]: s for s in local_client.get("/scenes").json()}
    assert listed[record["id"]]["report"] == report


# A Mitsuba scene.xml in a folder "attic", naming its mesh in a subfolder;
# its max_depth 4 is a job's depth 3 (Mitsuba's max_depth is our depth + 1).
ATTIC = {"scene.xml": b"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film>
  </sensor>
  <shape type="obj"><string name="filename" value="models/cube.obj"/><bsdf type="diffuse"/></shape>
  <shape type="rectangle"><transform name="to_world"><translate z="2"/></transform>
    <emitter type="area"><rgb name="radiance" value="5, 5, 5"/></emitter></shape>
</scene>
""", "models/cube.obj": CUBE_OBJ.encode()}
ATTIC_DEPTH = 3


def test14c_a_mitsuba_scene_is_named_after_its_folder_however_it_is_uploaded(local_client,
                                                                             tmp_path):
    """A scene.xml is named after its folder, as the importer names it
    locally, whichever way the folder arrives: zipped under its name, its
    contents zipped or tarred as attic.zip (the archive's name stands for the
    folder), its files by their paths (the folder picker). Loose files carry
    no folder's name: the scene is then named by the file's stem, never after
    the service's unpacking folder."""
    pytest.importorskip("renderer.importers.mitsuba",
                        reason="the Mitsuba importer is not in this checkout")
    from renderer.cli import load_scene as read_scene_file  # what `rayfarm render FILE` reads

    folder = tmp_path / "attic"
    for name, data in ATTIC.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    local = read_scene_file(str(folder / "scene.xml"))
    assert local["name"] == "attic"

    def uploaded(parts) -> dict:
        response = local_client.post("/scenes", files=parts)
        assert response.status_code in (200, 201), response.text
        return response.json()

    for how, parts in {
            "zip -r attic.zip attic": [("scene", ("attic.zip", zipped(ATTIC, top="attic/")))],
            "its contents zipped": [("scene", ("attic.zip", zipped(ATTIC)))],
            "its contents tarred": [("scene", ("attic.tar.gz", tarred(ATTIC)))],
            "the folder picker": [("files", (f"attic/{name}", data))
                                  for name, data in ATTIC.items()]}.items():
        record = uploaded(parts)
        assert (record["name"], record["id"]) == ("attic", scene_text(local)[0]), how
        assert record["default_depth"] == ATTIC_DEPTH, how
    loose = uploaded([("scene", ("scene.xml", ATTIC["scene.xml"])),
                      ("files", ("models/cube.obj", ATTIC["models/cube.obj"]))])
    assert loose["name"] == "scene"
    assert loose["id"] == scene_text(dict(local, name="scene"))[0]


# A small render of the shared veach-bidir (seconds, not minutes), at the
# file's own depth: its max_depth 7 less one (Mitsuba's max_depth is our depth + 1).
VEACH_JOB = {"method": "path-mis", "spp": 16, "width": 64, "height": 64, "tile_size": 32,
             "seed": 11}
VEACH_DEPTH = 6


def test14b_a_zipped_mitsuba_folder_renders_as_the_renderer_renders_its_file(
        local_client, tmp_path, reference_channels):
    """veach-bidir's folder zipped as a user zips it (meshes, license and the
    Tungsten render beside scene.xml), uploaded to POST /scenes and rendered
    by the farm with no depth given: the same scene hash as scene.xml
    imported locally, the file's depth as `rayfarm render FILE` takes it, and
    the EXR bit for bit the renderer's own render of that file with that spec."""
    from renderer.cli import load_scene as read_scene_file  # what `rayfarm render FILE` reads
    from renderer.spec import default_depth

    folder = real_scenes("veach-bidir/scene.xml") / "veach-bidir"
    archive = zip_of_folder(folder, tmp_path)
    with archive.open("rb") as data:
        response = local_client.post("/scenes", files=[("scene", (archive.name, data,
                                                                  "application/zip"))])
    assert response.status_code in (200, 201), response.text
    assert response.json()["source"] == "veach-bidir/scene.xml"
    local = read_scene_file(str(folder / "scene.xml"))
    body = dict(VEACH_JOB, scene=response.json()["id"])
    job = poll_job(get_json(local_client), submit(local_client, body)["id"])
    assert job["status"] == "done", job
    assert job["scene_hash"] == scene_text(local)[0]
    assert job["depth"] == default_depth(local) == VEACH_DEPTH
    (tmp_path / "farm.exr").write_bytes(local_client.get(job["result_url"]).content)
    farm = channels_of(tmp_path / "farm.exr")
    assert farm["R"].shape == (64, 64) and farm["R"].max() > 0
    assert_bit_identical(farm, reference_channels(dict(body, scene=local, depth=VEACH_DEPTH)))


# -- jobs, lookups and deletion --------------------------------------------------------------

def test08_jobs_name_uploads_by_id_and_unknown_ids_are_422(local_client):
    response = local_client.post("/jobs", json=dict(TINY, scene="0" * 64))
    assert response.status_code == 422, response.text
    detail = response.json()["detail"][0]
    assert detail["loc"] == ["body", "scene"]
    for words in [*builtin_scene_names(), "uploaded scene is named by its id", "0" * 64]:
        assert words in detail["msg"]


def test09_unknown_scenes_are_404_naming_the_id(local_client):
    for path in ["/scenes/no-such-scene", "/scenes/no-such-scene/thumbnail.png"]:
        response = local_client.get(path)
        assert response.status_code == 404 and "no-such-scene" in response.json()["detail"]
    assert local_client.delete("/scenes/no-such-scene").status_code == 404


def test10_delete_forgets_an_upload_but_its_jobs_finish(local_client):
    scene = upload_created(local_client, room("test10-room"))
    job = submit(local_client, dict(TINY, scene=scene["id"], width=32, height=24, spp=16))
    assert local_client.delete(f"/scenes/{scene['id']}").status_code == 204
    missing = local_client.get(f"/scenes/{scene['id']}")
    assert missing.status_code == 404 and scene["id"] in missing.json()["detail"]
    assert scene["id"] not in [s["id"] for s in local_client.get("/scenes").json()]
    assert local_client.get(f"/scenes/{scene['id']}/thumbnail.png").status_code == 404
    assert local_client.post("/jobs", json=dict(TINY, scene=scene["id"])).status_code == 422
    assert local_client.delete(f"/scenes/{scene['id']}").status_code == 404
    job = poll_job(get_json(local_client), job["id"])
    assert job["status"] == "done" and local_client.get(job["result_url"]).status_code == 200
    builtin = local_client.delete("/scenes/cornell-box")
    assert builtin.status_code == 409 and "built in" in builtin.json()["detail"]
    again = upload(local_client, scene_bytes(room("test10-room")))
    assert again.status_code == 201 and again.json()["id"] == scene["id"]


def test11_thumbnail_is_404_until_rendered_and_rendered_once(tmp_path):
    from service import scenes
    from service.access import SYSTEM
    from service.db import open_ledger
    from service.errors import ResultNotReady
    from service.models import utcnow
    from service.settings import Settings
    from service.store import Store
    from service.thumbnails import Thumbnailer

    settings = Settings(data_dir=tmp_path / "data", database_url="")
    store = Store(settings.data_dir)
    engine, sessions = open_ledger(settings)
    try:
        with store.upload_dir() as directory:
            (directory / "part-0").write_bytes(scene_bytes(room("test11")))
            (directory / "part-1").write_text(CUBE_OBJ)
            info, created = scenes.add_upload(
                sessions, store, SYSTEM, scenes.UploadedFile("scene", 0, "room.json", directory / "part-0"),
                [scenes.UploadedFile("files", 0, "cube.obj", directory / "part-1")], directory,
                utcnow())
        assert created and not directory.exists()
        with sessions() as session:
            with pytest.raises(ResultNotReady, match="no thumbnail yet"):
                scenes.thumbnail_file(session, store, SYSTEM, info.id)
        thumbnails = Thumbnailer(store)  # its thread not started: driven by hand
        assert thumbnails.make([info.id]) == 1 and thumbnails.failed == {}
        with sessions() as session:
            path = scenes.thumbnail_file(session, store, SYSTEM, info.id)
        assert path == store.root / "store" / "scenes" / f"{info.id}.png"
        assert Image.open(path).size == (128, 96)
        assert thumbnails.make([info.id]) == 0 and thumbnails.rendered == 1  # once per hash
    finally:
        engine.dispose()


# -- the request path stays light -----------------------------------------------------------

def test11b_an_uploads_mesh_files_are_parsed_outside_the_serving_process(local_client,
                                                                        monkeypatch):
    # Parsing a large .obj holds the GIL for tens of seconds: in the service's
    # own process it stalled every request. A child process parses it, and a
    # reader patched here (in the serving process) is never called.
    from renderer import scene_meshes

    parsed = []
    original = scene_meshes.read_mesh
    monkeypatch.setattr(scene_meshes, "read_mesh",
                        lambda path, **kw: parsed.append(path) or original(path, **kw))
    response = upload(local_client, scene_bytes(room("test11b-room")))
    assert response.status_code == 201, response.text
    assert response.json()["triangles"] == TRIANGLES
    assert parsed == [], "the upload's mesh was parsed in the serving process"
    # What the child refuses still names where, as test05 shows for every refusal.
    bad = CUBE_OBJ.replace("v 1 -1 -1", "v 1 x -1").encode()
    assert_422(upload(local_client, scene_bytes(room("test11b-bad")), (("cube.obj", bad),)),
               ["body", "scene", f"shapes[{MESH}].file"], "cube.obj:3", "cannot parse")


def test11c_a_job_on_an_upload_is_submitted_without_parsing_the_stored_scene(local_client,
                                                                            local_app,
                                                                            monkeypatch):
    # The stored text of a 59 MiB mesh takes seconds to parse; a job needs
    # only the record's camera and hash, unless its method checks the scene
    # (radiosity counts its patches).
    scene = upload_created(local_client, room("test11c-room"))
    store = local_app.state.farm.store
    read = []
    original = store.scene_text
    monkeypatch.setattr(store, "scene_text", lambda key: read.append(key) or original(key))
    job = submit(local_client, dict(TINY, scene=scene["id"]))
    assert job["scene_hash"] == scene["id"]
    assert read == [], "the request parsed the uploaded scene's stored text"
    submit(local_client, dict(TINY, scene=scene["id"], method="radiosity", width=16, height=16))
    assert read == [scene["id"]]
    done = poll_job(get_json(local_client), job["id"])
    assert done["status"] == "done", done


def test11d_uploads_beyond_the_bound_at_once_are_429_with_retry_after(tmp_path):
    child, base = start_serve(embedded_env(tmp_path / "data", RAYFARM_LOCAL_WORKERS="1",
                                           RAYFARM_MAX_CONCURRENT_UPLOADS="1"),
                              tmp_path / "serve.log")
    try:
        scene = json.dumps(room("test11d")).encode()
        head = (b'--b\r\nContent-Disposition: form-data; name="scene"; filename="room.json"'
                b"\r\n\r\n")
        tail = (b'\r\n--b\r\nContent-Disposition: form-data; name="files"; '
                b'filename="cube.obj"\r\n\r\n' + CUBE_OBJ.encode() + b"\r\n--b--\r\n")
        host, port = base.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port)), timeout=30) as slow:
            # An upload that holds the one slot: its body arrives slowly.
            slow.sendall(b"POST /scenes HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                         b"Authorization: " + ADMIN_HEADERS["Authorization"].encode() +
                         b"\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                         b"Content-Length: %d\r\n\r\n" % (len(head) + len(scene) + len(tail))
                         + head + scene[:10])
            with httpx.Client(base_url=base, timeout=60, headers=ADMIN_HEADERS) as client:
                files = [("scene", ("room.json", json.dumps(room("test11d-2")).encode())),
                         ("files", ("cube.obj", CUBE_OBJ.encode()))]
                busy = wait_for(lambda: (lambda r: r if r.status_code == 429 else None)(
                    client.post("/scenes", files=files)), 30, "an upload beyond the bound")
                assert int(busy.headers["retry-after"]) >= 1
                assert "RAYFARM_MAX_CONCURRENT_UPLOADS" in busy.json()["detail"]
                slow.sendall(scene[10:] + tail)
                answer = b""
                while b"\r\n\r\n" not in answer:
                    answer += slow.recv(4096)
                assert answer.startswith(b"HTTP/1.1 201"), answer
                # The slot is free again.
                assert client.post("/scenes", files=files).status_code == 201
    finally:
        child.stop()


# -- size limits, on a real server ----------------------------------------------------------

def test12_bodies_above_the_limits_are_413_before_they_are_read(spawn_serve):
    child, base = spawn_serve(RAYFARM_MAX_UPLOAD_BYTES="4096", RAYFARM_MAX_JOB_BYTES="2048",
                              RAYFARM_MAX_UPLOAD_FILES="2")
    total = 32 << 20

    def assert_413(response, limit: str, setting: str):
        assert response.status_code == 413, response.text
        detail = response.json()["detail"]
        assert limit in detail and setting in detail, detail

    # Content-Length over the limit: answered before the body is read, so the
    # server never even asks for it (no "100 Continue", as curl expects).
    host, port = base.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(b"POST /scenes HTTP/1.1\r\nHost: 127.0.0.1\r\nExpect: 100-continue\r\n"
                     b"Content-Type: multipart/form-data; boundary=b\r\n"
                     b"Content-Length: 1000000000\r\n\r\n")
        answer = b""
        while b"\r\n\r\n" not in answer:
            answer += sock.recv(4096)
        assert answer.startswith(b"HTTP/1.1 413"), answer
    with httpx.Client(base_url=base, timeout=60, headers=ADMIN_HEADERS) as client:
        big = client.post("/scenes", files={"scene": ("room.json", b" " * total)})
        assert_413(big, "4096", "RAYFARM_MAX_UPLOAD_BYTES")
        # No Content-Length (chunked): cut off while streaming.
        sent = 0

        def chunks(head: bytes, size: int = total):
            nonlocal sent
            yield head
            while sent < size:
                sent += 64 << 10
                yield b" " * (64 << 10)

        head = b'--b\r\nContent-Disposition: form-data; name="scene"; filename="room.json"\r\n\r\n'
        chunked = client.post("/scenes", content=chunks(head),
                              headers={"content-type": "multipart/form-data; boundary=b"})
        assert_413(chunked, "4096", "RAYFARM_MAX_UPLOAD_BYTES")
        assert sent < total // 2  # the server stopped reading; the rest was never sent
        # POST /jobs (inline scene documents) has its own, smaller limit.
        assert_413(client.post("/jobs", json=dict(TINY, scene=room("x" * 4000))), "2048",
                   "RAYFARM_MAX_JOB_BYTES")
        sent = 0
        assert_413(client.post("/jobs", content=chunks(b'{"scene": "', 1 << 20),
                               headers={"content-type": "application/json"}),
                   "2048", "RAYFARM_MAX_JOB_BYTES")
        # The number of files is bounded too.
        files = [("scene", ("room.json", json.dumps(room("test12")).encode()))] + [
            ("files", (f"m{i}.obj", b"v 0 0 0\n")) for i in range(3)]
        assert_413(client.post("/scenes", files=files), "at most 2 files",
                   "RAYFARM_MAX_UPLOAD_FILES")
        # Below the limits all is well.
        small = client.post("/scenes", files=[
            ("scene", ("room.json", json.dumps(room("test12")).encode())),
            ("files", ("cube.obj", CUBE_OBJ.encode()))])
        assert small.status_code == 201, small.text
        assert client.get("/healthz").json()["status"] in ("ok", "degraded")
    uploads = child.log_path.parent / "serve-data" / "uploads"
    assert uploads.is_dir() and list(uploads.iterdir()) == []
