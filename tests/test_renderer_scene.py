"""The scene format: what it accepts, and the errors that name the problem."""

import json

import numpy as np
import pytest

from renderer import SceneError, build_scene, builtin_scene_names, load_scene, resolve_document, \
    scene_hash

MINIMAL = {
    "camera": {"origin": [0, 0, 5], "target": [0, 0, 0], "fov": 40},
    "materials": {"m": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
    "shapes": [{"type": "rectangle", "material": "m"}],
}


def test01_builtin_scenes_resolve_and_build():
    assert {"cornell-box", "furnace-point", "furnace-emitter"} <= set(builtin_scene_names())
    for name in builtin_scene_names():
        assert build_scene(resolve_document(name)).arrays.bvh_nodes.shape[0] >= 1


def test02_cornell_box_is_the_reference_scene():
    """Geometry numbers straight from shared/scenes/cornell-box.md."""
    scene = load_scene("cornell-box")
    a = scene.arrays
    assert a.tri_p.shape[0] == 6 * 2 + 2 * 12
    assert a.light_area[0] == pytest.approx(0.1748, rel=1e-9)
    assert tuple(a.light_rgb[0]) == (18.387, 13.9873, 6.75357)
    light = a.tri_p[a.tri_light >= 0].reshape(-1, 3)
    assert np.allclose(np.unique(light, axis=0),
                       [[-0.23, 0.99, -0.18], [-0.23, 0.99, 0.2], [0.23, 0.99, -0.18], [0.23, 0.99, 0.2]])
    assert np.allclose(a.tri_n[a.tri_light >= 0], [0, -1, 0])
    # small box corners (spec: 8 corners of translate*rotate_y(-17)*scale(0.3))
    small = np.unique(np.round(a.tri_p[12:24].reshape(-1, 3), 5), axis=0)
    assert [0.13582, -1, 0.0054] in np.round(small, 4).tolist() or \
        np.any(np.all(np.abs(small - [0.13582, -1, 0.005397]) < 1e-5, axis=1))
    assert scene.camera["fov"] == 39.3077 and scene.camera["width"] == scene.camera["height"] == 256


def test03_camera_rays_match_mitsuba_table():
    from renderer.kernels.camera import camera_ray
    from renderer.scene import camera_array

    cam = camera_array(load_scene("cornell-box").camera, 256, 256)
    table = {(0.5, 0.5): (-0.3177954, 0.3177954, -0.8933153),
             (255.5, 0.5): (0.3177954, 0.3177954, -0.8933153),
             (128.5, 128.5): (0.0013951, -0.0013951, -0.9999981),
             (30.5, 128.5): (-0.2625024, -0.0013462, -0.9649304)}
    for (px, py), expected in table.items():
        assert camera_ray(cam, 256, 256, px, py) == pytest.approx(expected, abs=2e-7)


def test04_hash_is_content_identity():
    a = resolve_document(MINIMAL)
    b = resolve_document(json.loads(json.dumps(MINIMAL)))
    assert scene_hash(a) == scene_hash(b)
    changed = json.loads(json.dumps(MINIMAL))
    changed["materials"]["m"]["albedo"] = [0.5, 0.5, 0.4]
    assert scene_hash(resolve_document(changed)) != scene_hash(a)


@pytest.mark.parametrize("mutate, location, words", [
    (lambda d: d["shapes"][0].update(material="nope"), "shapes[0].material", "unknown material"),
    (lambda d: d["shapes"][0].update(type="torus"), "shapes[0].type", "allowed"),
    (lambda d: d["materials"]["m"].update(albedo=[2, 0, 0]), "materials.m.albedo", "<= 1"),
    (lambda d: d["materials"].update(g={"type": "glass"}), "materials.g.type", "unknown material type"),
    (lambda d: d["camera"].update(fov=0), "camera.fov", ">= 0.001"),
    (lambda d: d["camera"].update(width=0), "camera.width", "integer"),
    (lambda d: d["camera"].update(up=[0, 0, 1]), "camera.up", "parallel"),
    (lambda d: d["shapes"][0].update(to_world=[[1, 0]] * 4), "shapes[0].to_world[0]", "4 numbers"),
    (lambda d: d["shapes"][0].update(to_world=[[0] * 4] * 4), "shapes[0].to_world", "singular"),
    (lambda d: d["shapes"][0].update(emitter={"type": "area"}), "shapes[0].emitter", "radiance"),
    (lambda d: d["shapes"].append({"type": "mesh", "material": "m", "vertices": [[0, 0, 0]],
                                   "faces": [[0, 1, 2]]}), "shapes[1].faces", "out of range"),
    (lambda d: d["shapes"].append({"type": "sphere", "material": "m",
                                   "to_world": [{"scale": [1, 2, 1]}]}), "shapes[1].to_world",
     "similarity"),
    (lambda d: d.update(lights=[]), "", "unknown top-level"),
    (lambda d: d["shapes"][0].update(material=["m"]), "shapes[0].material", "material name"),
    (lambda d: d["shapes"].append({"type": "mesh", "material": "m", "vertices": [[0, 0, 0]] * 3,
                                   "faces": [[0.5, 1, 2]]}), "shapes[1].faces", "integers"),
])
def test05_invalid_documents_name_the_problem(mutate, location, words):
    doc = json.loads(json.dumps(MINIMAL))
    mutate(doc)
    with pytest.raises(SceneError) as err:
        resolve_document(doc)
    assert err.value.location == location
    assert words in err.value.message


def test06_malformed_scene_file_gets_a_clear_error(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"camera": {"origin": [0, 0, 5],,}}')
    with pytest.raises(SceneError, match=r"invalid JSON in bad.json at line 1, column"):
        resolve_document(bad)
    with pytest.raises(SceneError, match="unknown scene"):
        resolve_document(tmp_path / "missing.json")


def test07_mesh_from_obj_file_and_transform_ops(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 4 3\n")
    doc = json.loads(json.dumps(MINIMAL))
    doc["shapes"] = [{"type": "mesh", "file": "tri.obj", "material": "m",
                      "to_world": [{"scale": [2, 2, 2]}, {"translate": [0, 0, -1]}]}]
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    scene = load_scene(path)
    assert scene.arrays.tri_p.shape == (2, 3, 3)
    assert scene.arrays.tri_p[:, :, 2].max() == -1.0 and scene.arrays.tri_p[:, :, 0].max() == 2.0
    # the resolved document names the mesh by its asset's digest: no file, no numbers
    shape = scene.doc["shapes"][0]
    assert "vertices" not in shape and "file" not in shape and shape["triangles"] == 2
    assert list(scene.doc.assets) == [shape["mesh"]]
    doc["shapes"][0]["file"] = "../outside.obj"
    path.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="inside the scene's directory"):
        load_scene(path)


def _with(*shapes, emitters=()) -> dict:
    """MINIMAL plus `shapes` (shapes[1], ...) and point `emitters`."""
    doc = json.loads(json.dumps(MINIMAL))
    doc["shapes"].extend(shapes)
    doc["emitters"] = list(emitters)
    return doc


LIGHT = {"type": "area", "radiance": [1, 1, 1]}
BIG = 1e7  # beyond MAX_COORDINATE = 1e6


@pytest.mark.parametrize("doc, location, words", [
    (_with({"type": "rectangle", "material": "m", "emitter": {"type": "area", "radiance": [1e300, 1, 1]}}),
     "shapes[1].emitter.radiance[0]", "<= 1000000"),
    (_with(emitters=[{"type": "point", "position": [0, 1, 0], "intensity": [1, 2e6, 1]}]),
     "emitters[0].intensity[1]", "<= 1000000"),
    (_with(emitters=[{"type": "point", "position": [0, -BIG, 0], "intensity": 1}]),
     "emitters[0].position[1]", ">= -1000000"),
    (_with({"type": "mesh", "material": "m", "vertices": [[0, 0, 0], [BIG, 0, 0], [0, 1, 0]],
            "faces": [[0, 1, 2]]}), "shapes[1].vertices", "vertex 1"),
    (_with({"type": "sphere", "material": "m", "center": [BIG, 0, 0]}), "shapes[1].center[0]", "<="),
    (_with({"type": "sphere", "material": "m", "radius": BIG}), "shapes[1].radius", "<="),
    (_with({"type": "rectangle", "material": "m", "to_world": [{"translate": [0, 0, 1e300]}]}),
     "shapes[1].to_world[0].translate[2]", "<="),
    (_with({"type": "rectangle", "material": "m", "to_world": [{"scale": [1, BIG, 1]}]}),
     "shapes[1].to_world[0].scale[1]", "<="),
    (_with({"type": "rectangle", "material": "m",
            "to_world": [{"rotate": {"axis": [0, 1, 0], "angle": 1e300}}]}),
     "shapes[1].to_world[0].rotate.angle", "<="),
    (_with({"type": "rectangle", "material": "m",
            "to_world": [[1, 0, 0, BIG], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}),
     "shapes[1].to_world[0][3]", "<="),
    (_with({"type": "rectangle", "material": "m",
            "to_world": [{"scale": [1e6, 1e6, 1e6]}, {"scale": [10, 10, 10]}]}),
     "shapes[1].to_world", "composed matrix"),
    (_with({"type": "mesh", "material": "m", "vertices": [[0, 0, 0], [1, 0, float("nan")], [0, 1, 0]],
            "faces": [[0, 1, 2]]}), "shapes[1].vertices", "finite"),
    ({**MINIMAL, "camera": {**MINIMAL["camera"], "origin": [0, 0, BIG]}}, "camera.origin[2]", "<="),
    # lengths the renderer squares or divides by, and the GGX alpha and the field of
    # view, far from underflow (renderer/scene_format.py's module doc)
    (_with({"type": "sphere", "material": "m", "radius": 1e-320}), "shapes[1].radius",
     ">= 1e-06"),
    (_with({"type": "sphere", "material": "m", "radius": 1e-6,
            "to_world": [{"scale": [0.5, 0.5, 0.5]}]}), "shapes[1].to_world",
     "the radius is 5e-07 after to_world; from 1e-06"),
    ({**MINIMAL, "camera": {**MINIMAL["camera"], "fov": 1e-320}}, "camera.fov", ">= 0.001"),
    ({**MINIMAL, "camera": {**MINIMAL["camera"], "target": [0, 0, 5 - 1e-9]}}, "camera.target",
     "at least 1e-06 from origin"),
    (_with({"type": "rectangle", "material": "m",
            "to_world": [{"rotate": {"axis": [1e-320, 0, 0], "angle": 30}}]}),
     "shapes[1].to_world[0].rotate.axis", "at least 1e-06"),
    ({**MINIMAL, "materials": {"m": {"type": "glossy", "roughness": 1e-320}}},
     "materials.m.roughness", ">= 0.001"),
])
def test08_scene_numbers_are_finite_and_bounded(doc, location, words):
    with pytest.raises(SceneError) as err:
        resolve_document(doc)
    assert (err.value.location, words in err.value.message) == (location, True), err.value


@pytest.mark.parametrize("shape, location, words", [
    # each number is in bounds; the transform carries the points out of them
    ({"type": "mesh", "material": "m", "vertices": [[0, 0, 0], [1e6, 0, 0], [0, 1, 0]],
      "faces": [[0, 1, 2]], "to_world": [{"scale": [10, 10, 10]}]}, "shapes[1].vertices",
     "vertex 1 lies at [10000000.0, 0.0, 0.0] after to_world"),
    ({"type": "cube", "material": "m", "to_world": [{"translate": [1e6, 0, 0]}]},
     "shapes[1].to_world", "after to_world"),
    ({"type": "sphere", "material": "m", "center": [1e6, 0, 0], "to_world": [{"translate": [1, 0, 0]}]},
     "shapes[1].to_world", "the centre lies at"),
    ({"type": "sphere", "material": "m", "radius": 1e6, "to_world": [{"scale": [2, 2, 2]}]},
     "shapes[1].to_world", "the radius is 2e+06"),
])
def test09_points_are_bounded_again_after_to_world(shape, location, words):
    with pytest.raises(SceneError) as err:
        resolve_document(_with(shape))
    assert (err.value.location, words in err.value.message) == (location, True), err.value


def _mesh(vertices, faces=((0, 1, 2),)) -> dict:
    return {"type": "mesh", "material": "m", "vertices": vertices, "faces": [list(f) for f in faces]}


@pytest.mark.parametrize("shape, location", [
    (_mesh([[0, 1, 0], [1, 1, 0], [2, 1, 0]]), "shapes[1].faces[0]"),                  # collinear
    (_mesh([[0, 1, 0], [0, 1, 0], [0, 1, 0]]), "shapes[1].faces[0]"),                  # one point
    (_mesh([[0, 1, 0], [1, 1, 0], [2, 1, 1e-200]]), "shapes[1].faces[0]"),             # a sliver
    (_mesh([[0, 1, 0], [1, 1, 0], [0, 1, 1], [0, 1, 2]], [(0, 1, 2), (0, 2, 3)]),      # face 1 only
     "shapes[1].faces[1]"),
    (_mesh([[0, 0, 0], [1e-7, 0, 0], [0, 1e-7, 0]]), "shapes[1].faces[0]"),            # area 5e-15
    # a primitive whose triangles the transform flattens (det 1e-6: not singular)
    ({"type": "rectangle", "material": "m", "to_world": [{"scale": [1e-12, 1e6, 1]}]},
     "shapes[1].to_world"),
    ({"type": "disk", "material": "m", "to_world": [{"scale": [1e-7, 1e-7, 1e6]}]}, "shapes[1].to_world"),
])
def test10_emitters_need_an_area_other_shapes_do_not(shape, location):
    """A light without area crashed every method's render process (SIGSEGV:
    light sampling picks a triangle among none): refused, naming the face."""
    resolve_document(_with(shape))  # emitting nothing, a degenerate shape is merely never hit
    with pytest.raises(SceneError) as err:
        resolve_document(_with({**shape, "emitter": LIGHT}))
    assert err.value.location == location, err.value
    assert "area" in err.value.message


def test11_only_format_version_1_is_read():
    assert resolve_document(MINIMAL)["format"] == "rayfarm-scene/1"  # absent: the current one
    assert resolve_document({**MINIMAL, "format": "rayfarm-scene/1"})["format"] == "rayfarm-scene/1"
    for version in ("rayfarm-scene/99", "rayfarm-scene/2", 1, None):
        with pytest.raises(SceneError) as err:
            resolve_document({**MINIMAL, "format": version})
        assert err.value.location == "format" and "rayfarm-scene/1" in err.value.message


@pytest.mark.parametrize("value", ["yes", "false", 1, 0, None])
def test12_flip_normals_is_true_or_false(value):
    for flag in (True, False):
        assert resolve_document(_with({"type": "rectangle", "material": "m",
                                       "flip_normals": flag}))["shapes"][1]["flip_normals"] is flag
    with pytest.raises(SceneError) as err:
        resolve_document(_with({"type": "rectangle", "material": "m", "flip_normals": value}))
    assert err.value.location == "shapes[1].flip_normals" and "true or false" in err.value.message


def test13_documents_nested_too_deep_are_refused_before_anything_recurses(tmp_path):
    deep = [[0]]
    for _ in range(2000):  # deeper than Python's stack: copying or printing it would fail
        deep = [deep]
    for doc in (dict(MINIMAL, name=deep), dict(MINIMAL, shapes=[{"type": "mesh", "vertices": deep}])):
        with pytest.raises(SceneError, match="more than 16 levels deep"):
            resolve_document(doc)
    path = tmp_path / "deep.json"
    path.write_text(json.dumps(dict(MINIMAL, name=[[[[[[[[[[[[[[[[[0]]]]]]]]]]]]]]]]])))
    with pytest.raises(SceneError, match="deep.json nests lists and objects more than 16"):
        resolve_document(path)
    path.write_text('{"name": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(SceneError, match="deep.json is nested too deeply"):
        resolve_document(path)
