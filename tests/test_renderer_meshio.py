"""Mesh files read in full (OBJ, PLY, Mitsuba .serialized), assets by digest,
and the native format's meshes, normals, UVs and unknown-field refusals."""

import json
import struct
import zlib

import numpy as np
import pytest

from renderer import SceneError, build_scene, resolve_document, scene_hash
from renderer.assets import (asset_digest, asset_header, decode_asset, encode_mesh,
                             encode_texture, load_asset)
from renderer.meshio import MeshData, read_mesh, write_serialized
from renderer.primitives import world_mesh_data
from renderer.scene_format import FIELDS, resolve_scene

from conftest import real_scenes

CAMERA = {"origin": [0, 0, 5], "target": [0, 0, 0], "fov": 40}


def slow_obj(text: str) -> np.ndarray:
    """A trivially correct OBJ reader: every triangle's corners as
    (position, uv, normal) rows, NaN where a corner has none."""
    v, vt, vn, tris = [], [], [], []

    def at(items, s):
        i = int(s)
        return items[i - 1 if i > 0 else len(items) + i]
    for line in text.splitlines():
        p = line.split()
        if not p:
            continue
        if p[0] == "v":
            v.append([float(x) for x in p[1:4]])
        elif p[0] == "vt":
            vt.append([float(x) for x in p[1:3]])
        elif p[0] == "vn":
            vn.append([float(x) for x in p[1:4]])
        elif p[0] == "f":
            corners = []
            for tok in p[1:]:
                f = tok.split("/") + ["", ""]
                corners.append(at(v, f[0]) + (at(vt, f[1]) if f[1] else [np.nan] * 2)
                               + (at(vn, f[2]) if f[2] else [np.nan] * 3))
            for j in range(1, len(corners) - 1):
                tris.append([corners[0], corners[j], corners[j + 1]])
    return np.asarray(tris, dtype=np.float64)


def corners(mesh: MeshData) -> np.ndarray:
    """The same rows from a MeshData (split vertices or not: the corners agree)."""
    f = mesh.faces
    uv = mesh.uvs[f] if mesh.uvs is not None else np.full(f.shape + (2,), np.nan)
    n = mesh.normals[f] if mesh.normals is not None else np.full(f.shape + (3,), np.nan)
    return np.concatenate([mesh.positions[f], uv, n], axis=2)


OBJ = """# a quad and a triangle, with every corner form
mtllib scene.mtl
o first
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
vn 0 0.6 0.8
usemtl red
f 1/1/1 2/2/1 3/3/2 4/4/2
s 1
g second part
usemtl blue
f -4/-1/-2 -2/-3/-1 -1/-2/-1
  f 1//1 2//2 4//1
usemtl blue
f 2/3 3/4 4/1
"""


def test01_obj_in_full(tmp_path):
    """vt/vn, negative indices, quads fanned, v//vn and v/vt forms, indented
    records, usemtl/o/g runs, mtllib; vertices split where a position pairs
    with several UVs or normals; all as the slow reader sees it."""
    path = tmp_path / "a.obj"
    path.write_text(OBJ)
    mesh = read_mesh(path)
    want = slow_obj(OBJ)
    got = corners(mesh)
    # faces without vt (or vn) among faces with them: (0, 0) UVs, normals dropped
    uv = want[:, :, 3:5]
    uv[np.isnan(uv)] = 0.0
    assert mesh.normals is None and "normals are ignored" in " ".join(mesh.notes)
    assert np.array_equal(got[:, :, :5], want[:, :, :5])
    assert mesh.face_groups == [("red", 0, 2), ("blue", 2, 3)]
    assert mesh.objects == [("first", 0, 2), ("second part", 2, 3)]
    assert mesh.mtllibs == ["scene.mtl"]
    # every corner with one UV and one normal: the file's vertices are kept as they are
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\nvn 0 0 1\n"
                    "vn 0 0 1\nf 1/1/1 2/2/2 3/3/3\n")
    mesh = read_mesh(path)
    assert mesh.positions.shape == (3, 3) and mesh.faces.tolist() == [[0, 1, 2]]
    assert mesh.uvs.tolist() == [[0, 0], [1, 0], [0, 1]] and mesh.normals.shape == (3, 3)


@pytest.mark.parametrize("text, line, match", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", 4, "vertex index 4 is out of range"),
    ("v 0 0 0\nv 1 0 0\nf 1 2 -3\nv 0 1 0\n", 3, "vertex index -3 is out of range"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/2 2/1 3/1\n", 5, "texture coordinate index 2"),
    ("v 0 0 0\nv 1 0 x\nv 0 1 0\nf 1 2 3\n", 2, "cannot parse vertex"),
    ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", 2, "a vertex needs 3 numbers"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", 4, "at least 3 vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3.5\n", 4, "cannot parse face corner"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", 4, "index 0 is invalid"),
    ("v 0 0 0\nbogus 1\n", 2, "unknown OBJ record"),
])
def test02_obj_errors_name_file_and_line(tmp_path, text, line, match):
    path = tmp_path / "m.obj"
    path.write_text(text)
    with pytest.raises(SceneError, match=match) as info:
        read_mesh(path, label="models/m.obj")
    assert info.value.location == f"models/m.obj:{line}"


def test03_real_obj_files_parse_as_the_slow_reader_reads_them():
    real = real_scenes()
    files = sorted(real.glob("classroom/models/*.obj")) + sorted(real.glob("living-room/models/*.obj"))
    assert files, "the shared scenes have OBJ files"
    total = 0
    for path in files:
        mesh = read_mesh(path)
        assert mesh.uvs is not None and mesh.normals is not None and len(mesh.faces)
        total += len(mesh.faces)
    biggest = max(files, key=lambda p: p.stat().st_size)
    assert np.allclose(corners(read_mesh(biggest)), slow_obj(biggest.read_text()), rtol=0, atol=0)
    assert total > 100_000


def _ply(fmt: str, body: bytes, faces: int = 2, vertex_count: int = 4) -> bytes:
    return (f"ply\nformat {fmt} 1.0\ncomment made by a test\nelement vertex {vertex_count}\n"
            "property float x\nproperty float y\nproperty float z\nproperty float nx\n"
            "property float ny\nproperty float nz\nproperty float s\nproperty float t\n"
            f"element face {faces}\nproperty list uchar int vertex_indices\n"
            "end_header\n").encode() + body


QUAD_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
QUAD_N = np.tile([0.0, 0.0, 1.0], (4, 1))
QUAD_UV = QUAD_V[:, :2] * 0.5


def test04_ply_ascii_and_binary_both_endians(tmp_path):
    """The same mesh (a triangle then a quad, fanned) from ASCII, binary
    little- and big-endian PLY; lists of mixed lengths in binary too."""
    rows = np.concatenate([QUAD_V, QUAD_N, QUAD_UV], axis=1)
    ascii_body = b"".join(b" ".join(b"%g" % x for x in r) + b"\n" for r in rows) + \
        b"3 0 1 2\n4 0 1 2 3\n"
    bodies = {"ascii": ascii_body}
    for fmt, e in (("binary_little_endian", "<"), ("binary_big_endian", ">")):
        bodies[fmt] = rows.astype(e + "f4").tobytes() + struct.pack(e + "B3i", 3, 0, 1, 2) + \
            struct.pack(e + "B4i", 4, 0, 1, 2, 3)
    for fmt, body in bodies.items():
        path = tmp_path / f"{fmt}.ply"
        path.write_bytes(_ply(fmt, body))
        mesh = read_mesh(path)
        assert mesh.faces.tolist() == [[0, 1, 2], [0, 1, 2], [0, 2, 3]], fmt
        assert np.array_equal(mesh.positions, QUAD_V) and np.array_equal(mesh.normals, QUAD_N)
        assert np.array_equal(mesh.uvs, QUAD_UV)


def test05_ply_hostile_counts_and_truncation(tmp_path):
    """Header counts beyond what the file can hold are refused before any
    allocation, naming the header line; a truncated body too."""
    rows = np.concatenate([QUAD_V, QUAD_N, QUAD_UV], axis=1).astype("<f4").tobytes()
    body = rows + struct.pack("<B3i", 3, 0, 1, 2) * 2
    path = tmp_path / "m.ply"
    path.write_bytes(_ply("binary_little_endian", body, faces=4 * 10 ** 11))
    with pytest.raises(SceneError, match="announces 400000000000 records") as info:
        read_mesh(path, label="m.ply")
    assert info.value.location == "m.ply:13"
    path.write_bytes(_ply("binary_little_endian", rows, vertex_count=10 ** 12))
    with pytest.raises(SceneError, match="announces"):
        read_mesh(path)
    path.write_bytes(_ply("binary_little_endian", body[:-3]))  # the last index cut short
    with pytest.raises(SceneError, match="truncated|remain"):
        read_mesh(path)
    path.write_bytes(_ply("ascii", b"0 0 0 0 0 1 0 0\n", faces=0, vertex_count=2 ** 40))
    with pytest.raises(SceneError, match="announces"):
        read_mesh(path)
    path.write_bytes(_ply("ascii", b"0 0 0 0 0 1 0 0\n" * 4 + b"3 0 1 9\n", faces=1))
    with pytest.raises(SceneError, match="names vertex 9"):
        read_mesh(path)


def test06_serialized_versions_precisions_and_shapes(tmp_path):
    a = MeshData(positions=QUAD_V, faces=np.array([[0, 1, 2], [0, 2, 3]]), normals=QUAD_N,
                 uvs=QUAD_UV, objects=[("quad", 0, 2)])
    b = MeshData(positions=QUAD_V * 2, faces=np.array([[0, 1, 2]]), face_normals=True)
    path = tmp_path / "m.serialized"
    for version in (3, 4):
        for double in (False, True):
            write_serialized(path, [a, b], version=version, double=double)
            m0, m1 = read_mesh(path), read_mesh(path, shape_index=1)
            assert m0.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
            assert np.array_equal(m0.normals, QUAD_N) and np.array_equal(m0.uvs, QUAD_UV)
            assert np.array_equal(m1.positions, QUAD_V * 2) and m1.normals is None
            assert m1.face_normals and not m0.face_normals
            assert (m0.objects == [("quad", 0, 2)]) == (version == 4)
    with pytest.raises(SceneError, match="shape_index 2 is out of range"):
        read_mesh(path, shape_index=2)
    # a shape announcing far more than its compressed bytes hold (a zlib bomb's count)
    payload = struct.pack("<I", 0x1000) + b"bomb\0" + struct.pack("<QQ", 10 ** 6, 4 * 10 ** 6)
    blob = struct.pack("<HH", 0x041C, 4) + zlib.compress(payload)
    path.write_bytes(blob + struct.pack("<QI", 0, 1))
    with pytest.raises(SceneError, match="far more than"):
        read_mesh(path)
    write_serialized(path, [a])
    shape = path.read_bytes()[:-12]  # without its offset table
    path.write_bytes(shape[:-10] + struct.pack("<QI", 0, 1))
    with pytest.raises(SceneError, match="corrupt|truncated"):
        read_mesh(path)


def test07_assets_round_trip_and_refuse_malformed_blobs():
    p = np.array([[0, 0, -0.0], [1, 0, 0], [0, 1, 0]])
    blob = encode_mesh(p, [[0, 1, 2]], np.tile([0, 0, 1.0], (3, 1)), p[:, :2])
    # canonical: the same content in other dtypes and with -0.0 gives the same bytes
    assert encode_mesh(p.astype(np.float32) + 0.0, np.array([[0, 1, 2]], np.int16),
                       np.tile([0, 0, 1], (3, 1)), p[:, :2].astype(np.float32)) == blob
    digest = asset_digest(blob)
    assert len(digest) == 64 and load_asset({digest: blob}, digest) == blob
    a = decode_asset(blob)
    assert a.kind == "mesh" and a.faces.tolist() == [[0, 1, 2]] and a.positions[0, 2] == 0.0
    assert asset_header(blob)["triangles"] == 1
    texels = np.arange(24, dtype=np.float32).reshape(2, 4, 3)
    assert np.array_equal(decode_asset(encode_texture(texels)).texels, texels)
    bad_index = bytearray(blob)
    bad_index[32 + 72: 32 + 76] = struct.pack("<I", 3)  # face 0's first index -> 3
    nan = bytearray(blob)
    nan[32:40] = struct.pack("<d", float("nan"))
    for bad, match in ((blob[:-1], "must have"), (blob + b"\0", "must have"),
                       (b"XXXX" + blob[4:], "bad magic"), (bytes(bad_index), "vertex 3"),
                       (bytes(nan), "non-finite"),
                       (blob[:32 - 16] + struct.pack("<QQ", 2 ** 40, 1) + blob[32:], "too large")):
        with pytest.raises(SceneError, match=match):
            decode_asset(bad)
    with pytest.raises(SceneError, match="does not match"):
        load_asset({digest: blob + b"x"}, digest)
    with pytest.raises(SceneError, match="not available"):
        load_asset({}, digest)


def _doc(*shapes) -> dict:
    return {"camera": dict(CAMERA), "materials": {"m": {"type": "diffuse"}},
            "shapes": list(shapes)}


def test08_meshes_become_assets_from_every_source(tmp_path):
    """Inline arrays, an .obj, a .ply and an asset digest give the same
    resolved shape (by digest) and scene hash; resolving a resolved document
    with its assets gives it back; normals and UVs reach world_mesh_data."""
    v = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    inline = {"type": "mesh", "material": "m", "vertices": v, "faces": [[0, 1, 2], [0, 2, 3]],
              "normals": QUAD_N.tolist(), "uvs": QUAD_UV.tolist()}
    (tmp_path / "q.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v)
                                    + "".join(f"vt {s} {t}\n" for s, t in QUAD_UV)
                                    + "vn 0 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1\n")
    rows = np.concatenate([QUAD_V, QUAD_N, QUAD_UV], axis=1).astype("<f4").tobytes()
    (tmp_path / "q.ply").write_bytes(_ply("binary_little_endian", rows + struct.pack(
        "<B4i", 4, 0, 1, 2, 3), faces=1))
    docs = [_doc(inline)] + [_doc({"type": "mesh", "material": "m", "file": name})
                             for name in ("q.obj", "q.ply")]
    resolved = [resolve_document(d, base_dir=tmp_path) for d in docs]
    assert len({scene_hash(r) for r in resolved}) == 1
    doc = resolved[0]
    (digest,) = doc.assets
    assert doc["shapes"][0]["mesh"] == digest and doc["shapes"][0]["triangles"] == 2
    assert "vertices" not in json.dumps(doc)
    by_digest = _doc({"type": "mesh", "material": "m", "mesh": digest})
    again, assets = resolve_scene(by_digest, assets=doc.assets)
    assert scene_hash(again) == scene_hash(doc) and assets == doc.assets
    with pytest.raises(SceneError, match="not available") as info:
        resolve_scene(by_digest)
    assert info.value.location == "shapes[0].mesh"
    scene = build_scene(doc)
    assert scene.triangle_count == 2
    # a mirroring, non-uniform to_world: normals by the inverse transpose, unit length
    shape = dict(doc["shapes"][0], to_world=[[2, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0.5, 0],
                                             [0, 0, 0, 1]], flip_normals=True)
    world = world_mesh_data(shape, doc.assets)
    assert np.allclose(world.normals, [0, 0, -1]) and np.array_equal(world.uvs, QUAD_UV)
    tri = world.positions[world.faces[0]]
    geometric = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    assert np.dot(geometric, world.normals[0]) > 0  # shading and geometric sides agree
    # admission counts the scene's triangles from the document, no asset decoded
    from renderer import RenderSpec
    from renderer.memory import SCENE_TRIANGLE, job_memory, scene_memory

    assert scene_memory(json.loads(json.dumps(doc))) == 2 * SCENE_TRIANGLE
    spec = RenderSpec(method="path", spp=1, width=8, height=8, tile_size=8)
    bare, counted = job_memory(spec), job_memory(spec, scene=scene_memory(doc))
    assert counted.total(2) - bare.total(2) == 2 * 2 * SCENE_TRIANGLE
    # a zero normal ("vn 0 0 0") becomes Mitsuba's smooth one: unit face
    # normals weighted by the face's angle at the vertex
    from renderer.meshio import vertex_normals

    fan = {"type": "mesh", "material": "m", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0],
                                                         [0, 0, 1]],
           "faces": [[0, 1, 2], [0, 3, 1]], "normals": [[0, 0, 0]] + [[0, 0, 1]] * 3}
    repaired = resolve_document(_doc(fan))
    n0 = decode_asset(repaired.assets[repaired["shapes"][0]["mesh"]]).normals[0]
    want = np.array([0, np.pi / 2, np.pi / 2]) / np.linalg.norm([0, np.pi / 2, np.pi / 2])
    assert np.allclose(n0, want, atol=1e-7)  # float32 in the asset
    fan["vertices"][3] = [1, 0, 1]  # the second face's angle at vertex 0 becomes 45 degrees
    want = np.array([0, np.pi / 4, np.pi / 2]) / np.linalg.norm([0, np.pi / 4, np.pi / 2])
    assert np.allclose(vertex_normals(np.asarray(fan["vertices"], float),
                                      np.asarray(fan["faces"]))[0], want)
    # face_normals drops the vertex normals from the asset
    flat = resolve_document(_doc(dict(inline, face_normals=True)))
    assert decode_asset(flat.assets[flat["shapes"][0]["mesh"]]).normals is None


@pytest.mark.parametrize("where, change", [
    ("camera.aperture", lambda d: d["camera"].update(aperture=0.1)),
    ("materials.m.texture", lambda d: d["materials"]["m"].update(texture="wood.png")),
    ("materials.m.roughness", lambda d: d["materials"]["m"].update(roughness=0.2)),
    ("shapes[0].smooth", lambda d: d["shapes"][0].update(smooth=True)),
    ("shapes[0].uv", lambda d: d["shapes"][0].update(uv=[[0, 0]])),
    ("shapes[0].radius", lambda d: d["shapes"][0].update(radius=2)),
    ("shapes[0].emitter.power", lambda d: d["shapes"][0].update(
        emitter={"type": "area", "radiance": [1, 1, 1], "power": 3})),
    ("shapes[0].to_world[0].rotate.degrees", lambda d: d["shapes"][0].update(
        to_world=[{"rotate": {"axis": [0, 1, 0], "angle": 3, "degrees": 3}}])),
    ("emitters[0].radius", lambda d: d.update(emitters=[
        {"type": "point", "position": [0, 0, 1], "intensity": [1, 1, 1], "radius": 1}])),
])
def test09_unknown_fields_are_refused_at_every_level(where, change):
    doc = _doc({"type": "rectangle", "material": "m"})
    change(doc)
    with pytest.raises(SceneError, match="unknown field") as info:
        resolve_document(doc)
    assert info.value.location == where
    assert "aperture" not in FIELDS["camera"] and "uv" not in FIELDS["shape.mesh"]


def test10_import_scene_reads_a_native_scene_folder(tmp_path):
    """A JSON scene's mesh files (relative paths, subfolders) become assets;
    nothing leaves the root; an unknown suffix is refused."""
    from renderer.importers import Imported, import_scene

    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(_doc({"type": "mesh", "material": "m",
                                      "file": "models/tri.obj"})))
    imported = import_scene(scene)
    assert isinstance(imported, Imported) and imported.report == []
    assert list(imported.assets) == [imported.doc["shapes"][0]["mesh"]]
    assert scene_hash(resolve_document(imported.doc, assets=imported.assets)) == \
        scene_hash(imported.doc)
    scene.write_text(json.dumps(_doc({"type": "mesh", "material": "m", "file": "../x.obj"})))
    with pytest.raises(SceneError, match="inside the scene's directory"):
        import_scene(scene)
    (tmp_path / "scene.txt").write_text("{}")
    with pytest.raises(SceneError, match="unknown scene file type"):
        import_scene(tmp_path / "scene.txt")
