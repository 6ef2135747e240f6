"""The Mitsuba XML importer: both dialects give the same document, transforms
compose in Mitsuba's order, spectra become Mitsuba 3's RGB, hostile files are
refused naming file and line, and the shared real scenes import with the
report entries their quirks call for."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from renderer import resolve_document
from renderer.errors import SceneError
from renderer.importers import import_scene
from renderer.importers.mitsuba import UNBOUNDED_DEPTH, look_at
from renderer.importers.spectra import srgb_to_linear, xyz_to_srgb

from conftest import real_scenes

CAMERA_06 = """
  <sensor type="thinlens">
    <float name="fov" value="40"/>
    <string name="fovAxis" value="diagonal"/>
    <float name="apertureRadius" value="0.05"/>
    <float name="focusDistance" value="4"/>
    <float name="nearClip" value="0.1"/>
    <transform name="toWorld"><lookAt origin="0, 1, 5" target="0, 1, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sampleCount" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="48"/>
      <rfilter type="gaussian"><float name="stddev" value="0.3"/></rfilter></film>
  </sensor>"""
CAMERA_3 = """
  <sensor type="thinlens">
    <float name="fov" value="40"/>
    <string name="fov_axis" value="diagonal"/>
    <float name="aperture_radius" value="0.05"/>
    <float name="focus_distance" value="4"/>
    <float name="near_clip" value="0.1"/>
    <transform name="to_world"><lookat origin="0, 1, 5" target="0, 1, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="48"/>
      <rfilter type="gaussian"><float name="stddev" value="0.3"/></rfilter></film>
  </sensor>"""

# (0.5/0.6 dialect, 2.x/3.x dialect) of the same scene content
DIALECTS = [
    ("""<integrator type="path"><integer name="maxDepth" value="8"/></integrator>""",
     """<integrator type="path"><integer name="max_depth" value="8"/></integrator>"""),
    ("""<bsdf type="dielectric" id="g"><float name="intIOR" value="1.6"/>
          <float name="extIOR" value="1.1"/></bsdf>
        <shape type="sphere"><float name="radius" value="0.5"/><ref id="g"/></shape>""",
     """<bsdf type="dielectric" id="g"><float name="int_ior" value="1.6"/>
          <float name="ext_ior" value="1.1"/></bsdf>
        <shape type="sphere"><float name="radius" value="0.5"/><ref id="g"/></shape>"""),
    ("""<shape type="rectangle"><boolean name="flipNormals" value="true"/>
          <bsdf type="roughconductor"><float name="alpha" value="0.3"/>
            <string name="distribution" value="ggx"/>
            <rgb name="specularReflectance" value="0.5, 0.6, 0.7"/></bsdf></shape>""",
     """<shape type="rectangle"><boolean name="flip_normals" value="true"/>
          <bsdf type="roughconductor"><float name="alpha" value="0.3"/>
            <string name="distribution" value="ggx"/>
            <rgb name="specular_reflectance" value="0.5, 0.6, 0.7"/></bsdf></shape>"""),
    ("""<shape type="cube"><bsdf type="twosided"><bsdf type="roughplastic">
          <rgb name="diffuseReflectance" value="0.2, 0.3, 0.4"/>
          <texture type="checkerboard" name="unused"/></bsdf></bsdf>
          <emitter type="area"><rgb name="radiance" value="2, 3, 4"/></emitter></shape>""",
     """<shape type="cube"><bsdf type="twosided"><bsdf type="roughplastic">
          <rgb name="diffuse_reflectance" value="0.2, 0.3, 0.4"/>
          <texture type="checkerboard" name="unused"/></bsdf></bsdf>
          <emitter type="area"><rgb name="radiance" value="2, 3, 4"/></emitter></shape>"""),
    ("""<shape type="disk"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">
          <string name="filename" value="tex.png"/><string name="filterType" value="nearest"/>
          <float name="uscale" value="2"/><float name="vscale" value="3"/>
          <float name="uoffset" value="0.5"/></texture></bsdf></shape>""",
     """<shape type="disk"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">
          <string name="filename" value="tex.png"/><string name="filter_type" value="nearest"/>
          <transform name="to_uv"><scale x="2" y="3"/><translate x="0.5"/></transform>
          </texture></bsdf></shape>"""),
]


def scene(body: str, version: str = "3.0.0") -> str:
    return f'<?xml version="1.0"?>\n<scene version="{version}">\n{body}\n</scene>\n'


def load(tmp_path: Path, body: str, name: str = "scene.xml", version: str = "3.0.0", **files):
    (tmp_path / name).write_text(scene(body, version))
    for fname, text in files.items():
        (tmp_path / fname).write_text(text)
    return import_scene(tmp_path / name)


def refused(tmp_path: Path, text: str, **files) -> SceneError:
    (tmp_path / "scene.xml").write_text(text)
    for fname, content in files.items():
        (tmp_path / fname).write_text(content)
    with pytest.raises(SceneError) as info:
        import_scene(tmp_path / "scene.xml")
    return info.value


def actions(imported) -> list[str]:
    return [f"{e.file}:{e.line} {e.element}: {e.action}" for e in imported.report]


def png_1x1() -> bytes:
    """A valid 1x1 grey PNG."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00\x80\x80\x80")) + chunk(b"IEND", b""))


def normalised(doc: dict) -> dict:
    """The document with materials and textures renamed by order (their
    generated names carry file and line, which differ between two files)."""
    doc = dict(doc)
    doc.pop("name")
    tex_names = {name: f"t{i}" for i, name in enumerate(doc.get("textures", {}))}
    mat_names = {name: f"m{i}" for i, name in enumerate(doc["materials"])}

    def fix(value):
        if isinstance(value, dict) and set(value) == {"texture"}:
            return {"texture": tex_names[value["texture"]]}
        return value
    doc["materials"] = {mat_names[n]: {k: fix(v) for k, v in m.items()}
                        for n, m in doc["materials"].items()}
    doc["textures"] = {tex_names[n]: t for n, t in doc.get("textures", {}).items()}
    doc["shapes"] = [dict(s, material=mat_names[s["material"]]) for s in doc["shapes"]]
    return doc


@pytest.mark.parametrize("old,new", DIALECTS)
def test_both_dialects_give_the_same_document(tmp_path, old, new):
    (tmp_path / "tex.png").write_bytes(png_1x1())
    a = load(tmp_path, CAMERA_06 + old, name="old.xml", version="0.6.0")
    b = load(tmp_path, CAMERA_3 + new, name="new.xml")
    assert normalised(a.doc) == normalised(b.doc)
    cam = a.doc["camera"]
    assert cam["type"] == "thinlens" and cam["aperture_radius"] == 0.05
    assert cam["focus_distance"] == 4 and cam["fov_axis"] == "diagonal"
    assert (cam["width"], cam["height"]) == (64, 48)
    assert cam["filter"] == {"type": "gaussian", "stddev": 0.3}
    assert any("near_clip" in x or "nearClip" in x for x in actions(a))
    assert any("16 samples per pixel" in x for x in actions(b))


def test_dialect_values_map_to_native_materials(tmp_path):
    out = load(tmp_path, CAMERA_3 + "".join(new for _, new in DIALECTS[:4]))
    mats = list(out.doc["materials"].values())
    assert mats[0] == {"type": "dielectric", "ior": pytest.approx(1.6 / 1.1)}
    assert mats[1] == {"type": "glossy", "specular": [0.5, 0.6, 0.7], "roughness": 0.3}
    assert mats[2] == {"type": "diffuse", "albedo": [0.2, 0.3, 0.4], "twosided": True}
    assert out.doc["defaults"] == {"max_depth": 7}  # Mitsuba's max_depth counts the camera ray
    rect = out.doc["shapes"][1]
    assert rect["type"] == "rectangle" and rect["flip_normals"] is True
    assert out.doc["shapes"][2]["emitter"] == {"type": "area", "radiance": [2.0, 3.0, 4.0]}
    text = "\n".join(actions(out))
    assert "approximated as diffuse (reflectance = diffuse_reflectance)" in text
    assert 'texture type="checkerboard" name="unused"' in text  # nothing dropped silently


def test_defaults_substitution_refs_nested_objects_and_includes(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "mats.xml").write_text(scene(
        '<bsdf type="diffuse" id="wall"><rgb name="reflectance" value="$refl"/></bsdf>'))
    out = load(tmp_path, CAMERA_3 + """
      <default name="refl" value="0.25, 0.5, 0.75"/>
      <default name="depth" value="3"/>
      <default name="refl" value="0.9"/>
      <integrator type="$method"><integer name="max_depth" value="$depth"/></integrator>
      <include filename="parts/mats.xml"/>
      <texture type="checkerboard" id="check"><rgb name="color0" value="0.1"/></texture>
      <shape type="rectangle" id="a"><ref id="wall"/></shape>
      <shape type="rectangle"><bsdf type="diffuse"><ref name="reflectance" id="check"/></bsdf></shape>
      <shape type="rectangle"><bsdf type="mask"><float name="opacity" value="0.3"/>
        <ref id="wall"/></bsdf></shape>""")
    doc = out.doc
    assert doc["materials"]["wall"] == {"type": "diffuse", "albedo": [0.25, 0.5, 0.75]}
    assert doc["defaults"] == {"max_depth": 2}
    assert doc["shapes"][0] == {"type": "rectangle", "material": "wall", "name": "a",
                                "to_world": np.eye(4).tolist()}
    tex = doc["materials"][doc["shapes"][1]["material"]]["albedo"]
    assert doc["textures"][tex["texture"]] == {"type": "checkerboard", "color0": [0.1] * 3,
                                               "color1": [0.2] * 3}
    masked = doc["materials"][doc["shapes"][2]["material"]]
    assert masked == {"type": "diffuse", "albedo": [0.25, 0.5, 0.75], "opacity": 0.3}
    assert not any("mask" in a for a in actions(out))
    assert any("'$method' is not used" in a for a in actions(out))


def test_a_mask_passes_its_opacity_on(tmp_path):
    """A mask's opacity reaches the native material: a bitmap (whose alpha
    channel Mitsuba 3 does not read: reported), a number (clamped into [0, 1]:
    reported), a mask inside a mask multiplies; an emitting shape keeps its
    material without the mask (reported: area lights have no masks)."""
    from PIL import Image

    Image.fromarray(np.full((2, 2, 4), 128, np.uint8)).save(tmp_path / "leaf.png")
    out = load(tmp_path, CAMERA_3 + """
      <shape type="rectangle" id="a"><bsdf type="mask"><texture type="bitmap" name="opacity">
        <string name="filename" value="leaf.png"/></texture><bsdf type="diffuse"/></bsdf></shape>
      <shape type="rectangle" id="b"><bsdf type="mask"><float name="opacity" value="1.5"/>
        <bsdf type="diffuse"/></bsdf></shape>
      <shape type="rectangle" id="c"><bsdf type="mask"><float name="opacity" value="0.5"/>
        <bsdf type="mask"><float name="opacity" value="0.4"/><bsdf type="diffuse"/></bsdf></bsdf>
      </shape>
      <shape type="rectangle" id="d"><bsdf type="mask" id="veil"><float name="opacity" value="0.5"/>
        <bsdf type="diffuse"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="1"/></emitter></shape>""")
    mats = {s["name"]: out.doc["materials"][s["material"]] for s in out.doc["shapes"]}
    tex = out.doc["textures"][mats["a"]["opacity"]["texture"]]
    assert tex["type"] == "bitmap" and tex["image"] in out.assets
    assert "opacity" not in mats["b"]  # 1.5 clamped to 1: opaque
    assert mats["c"]["opacity"] == pytest.approx(0.2)
    assert mats["d"] == {"type": "diffuse", "albedo": [0.5] * 3}
    assert out.doc["materials"]["veil"]["opacity"] == 0.5
    text = "\n".join(actions(out))
    assert "the image's alpha channel is not read" in text
    assert "opacity 1.5 clamped to 1" in text
    assert "the opacity mask of an emitting shape is ignored" in text
    resolve_document(out.doc)  # what the importer wrote, the format takes


def test_transforms_compose_in_mitsubas_order(tmp_path):
    out = load(tmp_path, CAMERA_3 + """
      <shape type="rectangle"><transform name="to_world">
        <translate x="1"/><rotate y="1" angle="90"/><scale value="2"/></transform></shape>
      <shape type="cube"><transform name="to_world">
        <matrix value="1 2 3 4 0 1 0 5 0 0 1 6 0 0 0 1"/><scale x="-1"/></transform></shape>
      <shape type="disk"><transform name="to_world">
        <matrix value="0 -1 0 1 0 0 0 0 1"/><translate value="1 2 3"/></transform></shape>""")
    m0, m1, m2 = (np.asarray(s["to_world"]) for s in out.doc["shapes"])
    # translate first, then rotate 90 degrees about +y (x -> -z), then scale by 2
    assert np.allclose(m0 @ [0, 0, 0, 1], [0, 0, -2, 1])
    assert np.allclose(m0 @ [0, 0, 1, 1], [2, 0, -2, 1])
    expected = np.diag([-1.0, 1, 1, 1]) @ np.array([[1, 2, 3, 4], [0, 1, 0, 5], [0, 0, 1, 6],
                                                    [0, 0, 0, 1.0]])
    assert np.allclose(m1, expected)
    rot = np.eye(4)
    rot[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    assert np.allclose(m2, np.array([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1.0]]) @ rot)
    cam = np.asarray(out.doc["camera"]["to_world"])
    # Mitsuba's look-at: +z towards the target, +y up, +x to the left
    assert np.allclose(cam, [[-1, 0, 0, 0], [0, 1, 0, 1], [0, 0, -1, 5], [0, 0, 0, 1]])
    assert np.allclose(look_at([0, 0, 0], [1, 0, 0], [0, 1, 0])[:3, :3],
                       [[0, 0, 1], [0, 1, 0], [-1, 0, 0]])


def test_spectra_become_mitsuba3_rgb(tmp_path):
    out = load(tmp_path, CAMERA_3 + """
      <bsdf type="diffuse" id="flat"><spectrum name="reflectance" value="360:0.3, 830:0.3"/></bsdf>
      <bsdf type="diffuse" id="one"><spectrum name="reflectance" value="0.3"/></bsdf>
      <bsdf type="diffuse" id="red"><spectrum name="reflectance"
            value="400:0.05, 560:0.05, 600:0.8, 700:0.8"/></bsdf>
      <bsdf type="diffuse" id="hex"><srgb name="reflectance" value="#ff8000"/></bsdf>
      <bsdf type="diffuse" id="bright"><rgb name="reflectance" value="1.5, 0.5, 0.5"/></bsdf>
      <shape type="rectangle"><ref id="flat"/></shape>
      <shape type="rectangle"><ref id="one"/></shape>
      <shape type="rectangle"><ref id="red"/></shape>
      <shape type="rectangle"><ref id="hex"/></shape>
      <shape type="rectangle"><ref id="bright"/>
        <emitter type="area"><spectrum name="radiance" value="2"/></emitter></shape>""")
    mats = out.doc["materials"]
    assert mats["flat"]["albedo"] == pytest.approx([0.3] * 3, abs=1e-3)  # D65-weighted: grey
    assert mats["one"]["albedo"] == [0.3, 0.3, 0.3]
    r, g, b = mats["red"]["albedo"]
    assert r > 0.5 and r > 3 * g and g >= b >= 0
    assert mats["hex"]["albedo"] == pytest.approx([1.0, srgb_to_linear(128 / 255), 0.0])
    assert mats["bright"]["albedo"] == [1.0, 0.5, 0.5]
    assert any("clamped to [0, 1]" in a for a in actions(out))
    # an emitted constant spectrum is equal-energy white in sRGB, as Mitsuba 3 makes it
    radiance = out.doc["shapes"][4]["emitter"]["radiance"]
    assert radiance == pytest.approx(list(2 * xyz_to_srgb([1, 1, 1])))
    assert radiance[0] > radiance[1] > radiance[2]


def test_shapegroups_instances_cylinders_and_the_default_camera(tmp_path):
    out = load(tmp_path, """
      <shape type="shapegroup" id="g">
        <shape type="sphere"><point name="center" x="1" y="0" z="0"/></shape>
        <shape type="cube"><transform name="to_world"><scale value="0.5"/></transform></shape>
      </shape>
      <shape type="instance"><ref id="g"/><transform name="to_world">
        <translate z="10"/></transform></shape>
      <shape type="instance"><ref id="g"/></shape>
      <shape type="cylinder"><float name="radius" value="0.25"/></shape>
      <shape type="hair"/>
      <shape type="sphere"><bsdf type="null"/></shape>
      <shape type="disk"><bsdf type="null"/>
        <emitter type="area"><rgb name="radiance" value="1"/></emitter></shape>""")
    shapes = out.doc["shapes"]
    assert [s["type"] for s in shapes] == ["sphere", "cube", "sphere", "cube", "mesh", "disk"]
    assert out.doc["materials"][shapes[5]["material"]] == {"type": "diffuse",
                                                           "albedo": [0.0, 0.0, 0.0]}
    assert all(m["type"] != "null" for m in out.doc["materials"].values())
    assert np.allclose(np.asarray(shapes[0]["to_world"])[:3, 3], [0, 0, 10])
    assert np.allclose(shapes[1]["to_world"], np.diag([0.5, 0.5, 0.5, 1]) + np.pad(
        np.array([[0, 0, 0, 0]] * 2 + [[0, 0, 0, 10]] + [[0, 0, 0, 0.0]]), 0))
    v = np.asarray(shapes[4]["vertices"])
    f = np.asarray(shapes[4]["faces"])
    assert np.allclose(np.hypot(v[:, 0], v[:, 1]), 0.25)
    centre = v[f].mean(axis=1)
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(np.einsum("ij,ij->i", normal[:, :2], centre[:, :2]) > 0)  # outwards
    text = "\n".join(actions(out))
    assert "no 'hair' shape" in text and "no sensor" in text and "open prism" in text
    assert "null bsdf makes it invisible" in text and "null bsdf is a black" in text
    cam = out.doc["camera"]
    assert cam["fov"] == 45 and np.allclose(np.asarray(cam["to_world"])[:3, 2], [0, 0, 1])


@pytest.mark.parametrize("text,where,words", [
    ('<?xml version="1.0"?>\n<!DOCTYPE lolz [\n <!ENTITY lol "lol">\n'
     ' <!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">\n]>\n'
     '<scene version="3.0.0"><string name="x" value="&lol2;"/></scene>', "scene.xml:2", "DOCTYPE"),
    ('<?xml version="1.0"?>\n<!DOCTYPE scene [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>\n'
     '<scene version="3.0.0">&xxe;</scene>', "scene.xml:2", "refused"),
    ('<?xml version="1.0"?>\n<scene version="3.0.0">\n' + "<bsdf type='twosided'>" * 40
     + "</bsdf>" * 40 + "</scene>", "scene.xml:3", "nest"),
    (scene('<include filename="a.xml"/>'), "b.xml:4", "include cycle"),
    (scene('<bsdf type="twosided" id="A"><ref id="B"/></bsdf>\n'
           '<bsdf type="twosided" id="B"><ref id="A"/></bsdf>\n'
           '<shape type="rectangle"><ref id="A"/></shape>'), "scene.xml:", "reference cycle"),
    (scene('<shape type="obj">\n<string name="filename" value="models/missing.obj"/></shape>'),
     "scene.xml:4", "'models/missing.obj' not found"),
    (scene('<shape type="obj"><string name="filename" value="../outside.obj"/></shape>'),
     "scene.xml:3", "outside the scene's folder"),
    (scene('<shape type="obj"><string name="filename" value="/etc/passwd"/></shape>'),
     "scene.xml:3", "absolute path"),
    (scene('<shape type="rectangle"><ref id="nobody"/></shape>'), "scene.xml:3", "unknown id"),
    (scene('<shape type="rectangle">\n<float name="x" value="1"/>'), "scene.xml:5", "XML"),
    (scene('<shape type="rectangle"><transform name="to_world"><shear/></transform></shape>'),
     "scene.xml:3", "unknown transform operation"),
    (scene('<bsdf type="diffuse" id="a"/>\n<bsdf type="diffuse" id="a"/>'), "scene.xml:4",
     "defined twice"),
    (scene('<sensor type="orthographic"/>'), "scene.xml:3", "orthographic"),
    (scene('<shape type="shapegroup" id="g">\n<shape type="instance"><ref id="g"/></shape>'
           '</shape>'), "scene.xml:", "reference cycle"),
    (scene("".join(f'<shape type="shapegroup" id="g{i}">'
                   + (f'<shape type="instance"><ref id="g{i - 1}"/></shape>' * 40 if i else
                      '<shape type="cube"/>' * 40) + "</shape>\n" for i in range(4))
           + '<shape type="instance"><ref id="g3"/></shape>'), "scene.xml:", "more than 100000"),
    (scene('<bsdf type="diffuse" id="a"><rgb name="reflectance" value="nan, 0, 0"/></bsdf>'
           '<shape type="rectangle"><ref id="a"/></shape>'), "scene.xml:3", "finite"),
])
def test_hostile_or_broken_files_are_refused_naming_file_and_line(tmp_path, text, where, words):
    files = {"a.xml": scene('\n<include filename="b.xml"/>'),
             "b.xml": scene('\n<include filename="a.xml"/>')}
    (tmp_path / "outside.obj").write_text("v 0 0 0\n")
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "scene.xml").write_text(text)
    for name, content in files.items():
        (tmp_path / "root" / name).write_text(content)
    with pytest.raises(SceneError) as info:
        import_scene(tmp_path / "root" / "scene.xml")
    assert info.value.location.startswith(where), info.value
    assert words in str(info.value)


def test_a_missing_file_names_a_case_insensitive_near_match(tmp_path):
    (tmp_path / "Mesh.OBJ").write_text("v 0 0 0\n")
    err = refused(tmp_path, scene('<shape type="obj"><string name="filename" value="mesh.obj"/>'
                                  '</shape>'))
    assert "there is 'Mesh.OBJ'" in str(err)


def test_integrator_blocks_and_films_are_never_refused(tmp_path):
    broken = load(tmp_path, """
      <integrator type="path"><ref id="nobody"/></integrator>
      <sensor type="perspective"><sampler type="independent">
        <integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="$w"/><rfilter type="tent"/></film>
      </sensor>
      <shape type="rectangle"/>""", name="broken.xml")
    assert broken.doc["defaults"] == {"max_depth": UNBOUNDED_DEPTH}
    assert (broken.doc["camera"]["width"], broken.doc["camera"]["height"]) == (768, 576)
    text = "\n".join(actions(broken))
    assert "unknown id 'nobody'" in text and "$w has no value" in text and "$spp" in text
    out = load(tmp_path, CAMERA_3 + """
      <integrator type="no-such-method"><integer name="max_depth" value="-1"/>
        <string name="mode" value="$undefined"/><integer name="sampleNum" value="100"/>
        <integrator type="aov"/></integrator>
      <mode type="final"/>
      <shape type="rectangle"/>""")
    assert out.doc["defaults"] == {"max_depth": UNBOUNDED_DEPTH}
    text = "\n".join(actions(out))
    assert "unbounded" in text and 'name="sampleNum"' in text and "mode type" in text


def _real(name: str):
    return import_scene(real_scenes(f"{name}/scene.xml") / name / "scene.xml")


def _without_decoding(monkeypatch):
    """Meshes and images found and named but not decoded (seconds for the two
    big scenes; the mesh and texture readers have their own tests)."""
    from renderer.importers import mitsuba
    from renderer.meshio import MeshData

    triangle = MeshData(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
    monkeypatch.setattr(mitsuba.shapes, "read_mesh", lambda path, **kw: triangle)
    monkeypatch.setattr(mitsuba._Importer, "_image", lambda self, path, raw: {"image": path.name})


def test_the_shared_real_scenes_import_with_their_quirks_reported(monkeypatch):
    cornell = _real("cornell-box")
    text = "\n".join(actions(cornell))
    for wall in ("LeftWall", "RightWall", "BackWall"):
        assert f"material '{wall}' is one-sided and the camera sees its back" in text
    assert "'Floor' is one-sided" not in text
    assert 'mode type="final": ignored' in text and 'name="sampleNum": ignored' in text
    assert cornell.doc["defaults"] == {"max_depth": 64}
    assert cornell.doc["camera"]["filter"] == {"type": "tent", "radius": 1.0}
    assert len(cornell.doc["shapes"]) == 8 and cornell.doc["shapes"][-1]["emitter"]["radiance"] \
        == [17.0, 12.0, 4.0]

    veach = _real("veach-bidir")
    text = "\n".join(actions(veach))
    assert 'bsdf type="roughconductor" id="Lamp": approximated as glossy' in text
    assert "rendered as GGX" not in text
    lamp = veach.doc["materials"]["Lamp"]
    assert lamp["distribution"] == "beckmann" and lamp["roughness"] == 0.25
    assert 'hide name="radiance"' in text
    assert veach.doc["defaults"] == {"max_depth": 6}
    assert veach.doc["materials"]["Glass"] == {"type": "dielectric", "ior": 1.5}

    _without_decoding(monkeypatch)
    living = _real("living-room")
    text = "\n".join(actions(living))
    assert 'emitter type="envmap": ignored' in text
    assert 'bsdf type="roughplastic" (in bsdf type="twosided" id="Floor")' in text
    assert "integrator type=\"sppm\"" in text
    leaves = living.doc["materials"]["Leaves"]
    assert leaves["twosided"] and "texture" in leaves["albedo"] and "texture" in leaves["opacity"]
    assert 'bsdf type="mask" id="Leaves": ' not in text  # nothing about the mask itself
    assert len(living.doc["shapes"]) == 65 and living.doc["camera"]["width"] == 1280

    classroom = _real("classroom")
    text = "\n".join(actions(classroom))
    assert 'emitter type="sunsky": ignored' in text
    assert 'bsdf type="plastic" (in bsdf type="twosided" id="FluorescentTube")' in text
    assert classroom.doc["defaults"] == {"max_depth": 16}
    assert math.isclose(classroom.doc["camera"]["fov"], 60)


def test_mesh_files_become_assets_with_mitsubas_uv_convention(tmp_path):
    from renderer.assets import decode_asset
    from renderer.meshio import MeshData, write_serialized

    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "quad.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0.25\nvt 1 0.25\nvt 1 1\nvt 0 1\n"
        "f 1/1 2/2 3/3 4/4\n")
    (tmp_path / "m" / "tri.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float u\nproperty float v\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
        "0 0 0 0 0.25\n1 0 0 1 0.25\n0 1 0 0 1\n3 0 1 2\n")
    tri = MeshData(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
    big = MeshData(np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [2, 2, 0.0]]),
                   np.array([[0, 1, 2], [1, 3, 2]]), face_normals=True)
    write_serialized(tmp_path / "m" / "two.serialized", [tri, big])
    out = load(tmp_path, """
      <shape type="obj"><string name="filename" value="m/quad.obj"/></shape>
      <shape type="obj"><string name="filename" value="m\\quad.obj"/></shape>
      <shape type="ply"><string name="filename" value="m/tri.ply"/>
        <boolean name="face_normals" value="true"/></shape>
      <shape type="serialized"><string name="filename" value="m/two.serialized"/>
        <integer name="shape_index" value="1"/></shape>""")
    shapes = out.doc["shapes"]
    assert shapes[0]["mesh"] == shapes[1]["mesh"] and set(out.assets) == {
        s["mesh"] for s in shapes}
    quad = decode_asset(out.assets[shapes[0]["mesh"]])
    ply = decode_asset(out.assets[shapes[2]["mesh"]])
    ser = decode_asset(out.assets[shapes[3]["mesh"]])
    assert len(quad.faces) == 2 and np.allclose(sorted(set(quad.uvs[:, 1])), [0.0, 0.75])
    assert np.allclose(sorted(set(ply.uvs[:, 1])), [0.25, 1.0])  # PLY: v as written
    assert shapes[2]["face_normals"] and shapes[3]["face_normals"] and len(ser.faces) == 2
    assert "face_normals" not in shapes[0]


def test_named_nested_objects_as_mitsuba3_exporters_write_them(tmp_path):
    out = load(tmp_path, CAMERA_3 + """
      <texture type="checkerboard" id="c"/>
      <bsdf type="diffuse" id="d"><ref name="reflectance" id="c"/></bsdf>
      <shape type="rectangle"><ref name="bsdf" id="d"/></shape>
      <shape type="rectangle"><bsdf type="twosided" name="bsdf">
        <bsdf type="conductor" name="bsdf"/></bsdf></shape>""")
    mats = [out.doc["materials"][s["material"]] for s in out.doc["shapes"]]
    assert mats[0] == {"type": "diffuse", "albedo": {"texture": "c"}}
    assert mats[1] == {"type": "mirror", "tint": [1.0, 1.0, 1.0], "twosided": True}
    assert not any("bsdf" in e.element for e in out.report)  # nothing reported as ignored
    err = refused(tmp_path, scene('<shape type="sphere"><float name="radius" value="$r"/></shape>'))
    assert "$r has no value" in str(err) and err.location == "scene.xml:3"


def test_a_scaled_sensor_transform_is_made_rigid_and_reported(tmp_path):
    out = load(tmp_path, """
      <sensor type="perspective"><transform name="to_world"><scale x="-2" y="2" z="2"/>
        <translate z="3"/></transform>
        <film type="hdrfilm"><rfilter type="tent"><float name="radius" value="50"/></rfilter>
        </film></sensor>
      <shape type="rectangle"/>""")
    assert np.allclose(out.doc["camera"]["to_world"],
                       [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]])
    assert out.doc["camera"]["filter"] == {"type": "tent", "radius": 8.0}
    text = "\n".join(actions(out))
    assert "scale [2.0, 2.0, 2.0] is divided out" in text and "clamped to 8" in text
    err = refused(tmp_path, scene('<sensor type="perspective"><transform name="to_world">\n'
                                  '<matrix value="1 1 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>'
                                  '</transform></sensor>'))
    assert "shears" in str(err) and err.location == "scene.xml:3"


def test_the_integrator_blocks_depth_is_the_jobs_default():
    from renderer.scene_format import resolve_document
    from renderer.spec import default_depth

    doc = resolve_document("cornell-box")
    assert "defaults" not in doc and default_depth(doc) == 5
    with_defaults = resolve_document(dict(doc, defaults={"max_depth": 12}))
    assert with_defaults["defaults"] == {"max_depth": 12} and default_depth(with_defaults) == 12
    for bad in ({"max_depth": 65}, {"max_depth": True}, {"maxDepth": 3}, [3]):
        with pytest.raises(SceneError) as info:
            resolve_document(dict(doc, defaults=bad))
        assert info.value.location.startswith("defaults")


def test_a_scene_is_named_by_its_stem_or_for_scene_xml_its_folder(tmp_path, monkeypatch):
    """cbox.xml is 'cbox'; scene.xml takes its folder's name, also when given
    relative to the folder it is in (`rayfarm render scene.xml` there), and
    the same document with the root one folder up (an upload holding the
    folder); a root that stands for another folder (an upload's unpacking
    folder) is called what it stands for, "" for nothing known."""
    from renderer.importers import scene_name

    folder = tmp_path / "attic"
    folder.mkdir()
    body = '<shape type="sphere"><bsdf type="diffuse"/></shape>'
    assert load(folder, body, name="cbox.xml").doc["name"] == "cbox"
    assert load(folder, body).doc["name"] == "attic"
    # Objects without an id are named from the scene file's folder, not the root's.
    assert import_scene(folder / "scene.xml", root=tmp_path).doc == load(folder, body).doc
    monkeypatch.chdir(folder)
    assert import_scene(Path("scene.xml")).doc["name"] == "attic"
    assert scene_name(folder / "scene.xml", folder, root_name="room") == "room"
    assert scene_name(folder / "scene.xml", folder, root_name="") == "scene"
    assert scene_name(folder / "scene.xml", tmp_path, root_name="room") == "attic"
