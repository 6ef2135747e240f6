"""Shading at every hit: textures, per-vertex normals and uvs, two-sided
materials, and texture images read from files.

The renders are tiny (8 x 8 to 16 x 16 pixels, few samples); where a change
of inputs must not change the estimator (a constant texture against the
constant itself) the films are compared bit for bit, so no tolerance is
involved. Statistical comparisons use the films' own variances.
"""

import struct
import zlib

import numpy as np
import pytest
from scipy.stats import norm

from renderer import RenderSpec, build_scene, render_serial, resolve_document
from renderer.errors import SceneError, SpecError
from renderer.kernels.shading import tex_eval
from renderer.runtime import run_plan
from renderer.scene import _texture_arrays
from renderer.textures import MAX_TEXELS, read_texture

from test_renderer_light_bdpt import block_stats

DIGEST_A = "a" * 64
DIGEST_B = "b" * 64


def furnace(albedo, textures=None, **material):
    """The emitting furnace (renderer/scenes/furnace-emitter.json) with the
    sphere's albedo given as `albedo` (an RGB or a texture reference)."""
    doc = resolve_document("furnace-emitter")
    doc["materials"]["grey"] = {"type": "diffuse", "albedo": albedo, **material}
    if textures:
        doc["textures"] = textures
    return resolve_document(doc)


def rect_scene(material, shape_extra=None, camera_z=3.0, textures=None):
    """A unit-square rectangle (Mitsuba's [-1, 1]^2, front +z) lit by a point
    light beside the camera; the camera on the +z or -z axis."""
    doc = {
        "camera": {"origin": [0, 0, camera_z], "target": [0, 0, 0], "up": [0, 1, 0],
                   "fov": 30, "width": 8, "height": 8},
        "materials": {"m": material},
        "shapes": [{"type": "rectangle", "material": "m", **(shape_extra or {})}],
        "emitters": [{"type": "point", "position": [0.3, 0.2, camera_z], "intensity": [5, 5, 5]}],
    }
    if textures:
        doc["textures"] = textures
    return resolve_document(doc)


# ----------------------------------------------------------------- validation

def test01_the_scene_format_checks_what_shading_adds():
    base = resolve_document("furnace-emitter")

    def refused(change, where):
        doc = {**base, **change}
        with pytest.raises(SceneError) as exc:
            resolve_document(doc)
        assert exc.value.location.startswith(where), (exc.value.location, str(exc.value))
        return str(exc.value)

    grey = {"type": "diffuse", "albedo": [0.5] * 3}
    assert "uv" in refused({"materials": {"grey": {**grey, "uv": [1, 2]}}}, "materials.grey.uv")
    assert "smooth" in refused({"materials": {"grey": {**grey, "smooth": True}}},
                               "materials.grey.smooth")
    refused({"materials": {"grey": {**grey, "twosided": 1}}}, "materials.grey.twosided")
    assert "unknown texture 'nope'" in refused(
        {"materials": {"grey": {"type": "diffuse", "albedo": {"texture": "nope"}}}},
        "materials.grey.albedo.texture")
    refused({"materials": {"grey": {"type": "diffuse", "albedo": {"texture": "c", "x": 1}}},
             "textures": {"c": {"type": "checkerboard"}}}, "materials.grey.albedo")
    refused({"textures": {"c": {"type": "bitmap", "image": "not-a-digest"}}}, "textures.c.image")
    refused({"textures": {"c": {"type": "bitmap", "image": DIGEST_A, "filter": "cubic"}}},
            "textures.c.filter")
    refused({"textures": {"c": {"type": "checkerboard", "colour0": [1, 0, 0]}}},
            "textures.c.colour0")
    refused({"textures": {"c": {"type": "checkerboard", "color0": [2, 0, 0]}}},
            "textures.c.color0")
    refused({"textures": {"c": {"type": "noise"}}}, "textures.c.type")
    tri = {"type": "mesh", "material": "grey", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
           "faces": [[0, 1, 2]]}
    refused({"shapes": [{**tri, "normals": [[0, 0, 1]] * 2}]}, "shapes[0].normals")
    refused({"shapes": [{**tri, "uvs": [[0, 0, 0]] * 3}]}, "shapes[0].uvs")
    # twosided false is left out of the resolved document (older scenes keep
    # their hash), as is an empty textures map
    doc = resolve_document({**base, "materials": {"grey": {**grey, "twosided": False}}})
    assert doc["materials"]["grey"] == grey and "textures" not in doc
    # a bitmap whose image is not among the assets is refused when built
    textured = furnace({"texture": "t"}, {"t": {"type": "bitmap", "image": DIGEST_A}})
    with pytest.raises(SceneError, match="is not available"):
        build_scene(textured, {})


def test02_methods_that_cannot_render_a_feature_refuse_the_job_naming_it():
    doc = furnace({"texture": "c"}, {"c": {"type": "checkerboard"}}, twosided=True)
    with pytest.raises(SpecError, match="radiosity.*textures"):
        RenderSpec(method="radiosity", width=8, height=8).validate(scene=doc)
    RenderSpec(method="photon", width=8, height=8).validate(scene=doc)
    glossy = resolve_document({**doc, "materials": {"grey": {
        "type": "glossy", "roughness": {"texture": "c"}}}})
    with pytest.raises(SpecError, match="photon.*textured glossy"):
        RenderSpec(method="photon", width=8, height=8).validate(scene=glossy)
    for method in ("path", "direct", "raster", "light", "bdpt", "mlt"):
        RenderSpec(method=method, width=8, height=8).validate(scene=glossy)


# ------------------------------------------------------------------- lookups

def test03_texture_lookups_follow_mitsuba_3():
    """Bilinear and nearest lookups against hand-computed values: uv (0, 0)
    at the top-left of the stored image (row 0), texel centres at
    (i + 0.5) / W, wrap mode repeat; uv_scale / uv_offset; the checkerboard's
    parity (color0 where both fractional parts are above 1/2 or neither)."""
    a, b, c, d = [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]
    image = np.array([[a, b], [c, d]], np.float32)  # row 0: a b; row 1: c d
    grey = np.array([[[0.2], [0.4]], [[0.6], [0.8]]], np.float32)
    doc = {"textures": {
        "bi": {"type": "bitmap", "image": DIGEST_A, "filter": "bilinear", "uv_scale": [1, 1],
               "uv_offset": [0, 0]},
        "near": {"type": "bitmap", "image": DIGEST_A, "filter": "nearest", "uv_scale": [1, 1],
                 "uv_offset": [0, 0]},
        "moved": {"type": "bitmap", "image": DIGEST_A, "filter": "nearest", "uv_scale": [2, 2],
                  "uv_offset": [0.5, 0]},
        "grey": {"type": "bitmap", "image": DIGEST_B, "filter": "bilinear", "uv_scale": [1, 1],
                 "uv_offset": [0, 0]},
        "check": {"type": "checkerboard", "color0": [0.4] * 3, "color1": [0.2] * 3,
                  "uv_scale": [1, 1], "uv_offset": [0, 0]}}}
    index, info, data = _texture_arrays(doc, {DIGEST_A: image, DIGEST_B: grey})

    def at(name, u, v):
        return np.array(tex_eval(info, data, index[name], u, v))

    np.testing.assert_allclose(at("bi", 0.25, 0.25), a)  # the centre of texel (0, 0)
    np.testing.assert_allclose(at("bi", 0.25, 0.75), c)  # row 1 is further down in v
    np.testing.assert_allclose(at("bi", 0.5, 0.5), np.mean([a, b, c, d], axis=0))
    # x = 0.375 * 2 - 0.5 = 0.25 texels past a's centre towards b
    np.testing.assert_allclose(at("bi", 0.375, 0.25), [0.75, 0.25, 0.0])
    # u = 0: halfway between the last column (wrapped) and the first
    np.testing.assert_allclose(at("bi", 0.0, 0.25), [0.5, 0.5, 0.0])
    np.testing.assert_allclose(at("bi", 1.25, -0.75), a)  # repeat
    np.testing.assert_allclose(at("grey", 0.5, 0.25), [0.3] * 3, rtol=1e-6)  # one channel: grey
    np.testing.assert_allclose(at("near", 0.6, 0.1), b)
    np.testing.assert_allclose(at("near", 0.49, 0.51), c)
    np.testing.assert_allclose(at("near", -0.1, 0.1), b)  # repeat: u = 0.9
    # uv' = 2 uv + (0.5, 0): (0.1, 0.3) -> (0.7, 0.6): column 1, row 1
    np.testing.assert_allclose(at("moved", 0.1, 0.3), d)
    assert at("check", 0.25, 0.25)[0] == 0.4 and at("check", 0.75, 0.75)[0] == 0.4
    assert at("check", 0.75, 0.25)[0] == 0.2 and at("check", 0.25, 0.75)[0] == 0.2
    assert at("check", 1.75, -0.25)[0] == 0.4  # fractional parts 0.75, 0.75


# -------------------------------------------------------------------- renders

@pytest.mark.parametrize("method", ["path-mis", "bdpt", "photon", "light"])
def test04_a_constant_texture_renders_as_its_constant(method):
    """The furnace whose albedo is a texture of constant value 0.5 (a bitmap
    read nearest, a checkerboard of two equal colours) renders as the
    furnace of albedo 0.5: the same samples, the same values."""
    spec = RenderSpec(method=method, width=8, height=8, spp=8, depth=2, seed=3)
    plain = render_serial(build_scene(furnace([0.5] * 3)), spec)
    half = np.full((2, 3, 3), 0.5, np.float32)
    for tex in ({"type": "bitmap", "image": DIGEST_A, "filter": "nearest"},
                {"type": "checkerboard", "color0": [0.5] * 3, "color1": [0.5] * 3}):
        film = render_serial(build_scene(furnace({"texture": "t"}, {"t": tex}),
                                         {DIGEST_A: half}), spec)
        # the photon method folds the albedo into the visible point's weight:
        # the same value rounded once more
        rtol = 1e-12 if method == "photon" else 0.0
        np.testing.assert_allclose(film.mean(), plain.mean(), rtol=rtol, atol=0)
        assert film.mean().mean() > 0.5


@pytest.mark.parametrize("method", ["path-mis", "raster", "bdpt"])
def test05_checkerboard_on_a_rectangle_shows_in_the_albedo_aov(method):
    """Mitsuba's rectangle uv ((x + 1) / 2, (y + 1) / 2) and its checkerboard:
    the top-left quarter of the image (x < 0, y > 0) is color1, the top-right
    color0; the albedo AOV holds the texture's value at the hit."""
    doc = rect_scene({"type": "diffuse", "albedo": {"texture": "c"}},
                     textures={"c": {"type": "checkerboard", "color0": [0.8, 0.1, 0.1],
                                     "color1": [0.1, 0.1, 0.8]}})
    film = render_serial(build_scene(doc), RenderSpec(method=method, width=8, height=8, spp=4,
                                                      depth=1))
    aovs = film.aovs()
    albedo = np.stack([aovs[f"albedo.{c}"] for c in "RGB"], axis=-1)
    np.testing.assert_allclose(albedo[0, 0], [0.1, 0.1, 0.8])
    np.testing.assert_allclose(albedo[0, 7], [0.8, 0.1, 0.1])
    np.testing.assert_allclose(albedo[7, 0], [0.8, 0.1, 0.1])
    beauty = film.mean()
    assert beauty[0, 0, 2] > beauty[0, 0, 0] and beauty[0, 7, 0] > beauty[0, 7, 2]


@pytest.mark.parametrize("method", ["path-mis", "raster", "light", "photon"])
def test06_a_two_sided_material_shows_its_front_from_behind(method):
    """A one-sided diffuse rectangle seen from behind is black; a two-sided
    one seen from behind looks as its front does from the front (mirrored
    geometry, the same light and camera relative to the lit side)."""
    spec = RenderSpec(method=method, width=8, height=8, spp=16, depth=1, seed=5)
    white = {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}
    front = render_serial(build_scene(rect_scene(white)), spec).mean()
    back = render_serial(build_scene(rect_scene(white, {"flip_normals": True})), spec).mean()
    two = render_serial(build_scene(rect_scene({**white, "twosided": True},
                                               {"flip_normals": True})), spec).mean()
    assert front.mean() > 0.05
    assert np.all(back == 0.0)
    # the flipped winding intersects with other rounding: equal to far below the noise
    np.testing.assert_allclose(two, front, rtol=1e-6, atol=1e-9)


def smooth_box(perturb, seed=0):
    """A closed box (the cube, normals inwards) that emits 0.5 and reflects
    with albedo 0.5; each vertex normal is the inward face normal tilted by
    a random vector of length `perturb`. Every face has its own vertices."""
    rng = np.random.default_rng(seed)
    cube = resolve_document({"camera": {"origin": [0.1, 0.2, 0.3], "target": [0, 0, -1],
                                        "fov": 90, "width": 8, "height": 8},
                             "materials": {"m": {"type": "diffuse"}},
                             "shapes": [{"type": "cube", "material": "m"}]})
    from renderer.primitives import FIXED
    v, f = FIXED["cube"]
    verts = v[f].reshape(-1, 3)
    faces = np.arange(len(verts)).reshape(-1, 3)[:, ::-1]  # inwards
    tri = verts.reshape(-1, 3, 3)
    n = -np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.repeat(n / np.linalg.norm(n, axis=1)[:, None], 3, axis=0)
    normals = n + perturb * rng.normal(size=n.shape)
    doc = {"camera": cube["camera"],
           "materials": {"m": {"type": "diffuse", "albedo": [0.5] * 3}},
           "shapes": [{"type": "mesh", "material": "m", "vertices": verts.tolist(),
                       "faces": faces.tolist(), "normals": normals.tolist(),
                       "emitter": {"type": "area", "radiance": [0.5] * 3}}]}
    return resolve_document(doc)


def test07_shading_normals_never_add_energy_and_path_and_light_tracing_agree():
    """In a closed box that emits 0.5 and reflects 0.5, the radiance of a
    path of at most `depth` bounces is 1 - 0.5^(depth + 1) with geometric
    normals; tilted shading normals may lose energy (directions rejected by
    the side checks) but never add any: every 4 x 4 block's mean stays below
    the bound (one-sided z-test). Light tracing, which carries the adjoint
    correction of shading normals, agrees with path tracing over the image
    (variances from the films: block_stats)."""
    depth = 2
    bound = 1 - 0.5 ** (depth + 1)
    scene = build_scene(smooth_box(0.4))
    z = norm.isf(0.01 / 4)
    path = run_plan(scene, RenderSpec(method="path-mis", width=8, height=8, spp=256,
                                      depth=depth, seed=1))
    mean, var = block_stats(path, 8, 8, 4)
    assert np.all(mean <= bound + z * np.sqrt(var)), (mean, bound)
    mean, var = block_stats(path, 8, 8, 8)
    assert np.all(mean < bound - 3 * np.sqrt(var))  # the normals did change something
    light = run_plan(scene, RenderSpec(method="light", width=8, height=8, spp=1024,
                                       depth=depth, seed=2))
    lmean, lvar = block_stats(light, 8, 8, 8)
    z = norm.isf(0.005)
    assert np.all(np.abs(mean - lmean) <= z * np.sqrt(var + lvar)), (mean, lmean)
    # the comparison has power: a 5 % error would show
    assert not np.all(np.abs(mean - 1.05 * lmean) <= z * np.sqrt(var + lvar))


def test08_the_normal_aov_is_the_interpolated_shading_normal():
    tilted = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    doc = rect_scene({"type": "diffuse", "albedo": [0.5] * 3})
    doc["shapes"][0] = {**doc["shapes"][0], "type": "mesh",
                        "vertices": [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                        "faces": [[0, 1, 2], [0, 2, 3]], "normals": [tilted.tolist()] * 4}
    film = render_serial(build_scene(resolve_document(doc)),
                         RenderSpec(method="path-mis", width=8, height=8, spp=2, depth=1))
    aovs = film.aovs()
    normal = np.stack([aovs[f"normal.{c}"] for c in "XYZ"], axis=-1)
    np.testing.assert_allclose(normal[4, 4], tilted, atol=1e-12)


# ------------------------------------------------------------------- images

def _png_header_only(width, height):
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2,
                                                                 0, 0, 0))
            + chunk(b"IEND", b""))


def _hdr_rle_row(pixels):
    """A new-style run-length scanline: per channel one run of the first
    value over half the row, then the rest as a literal dump."""
    w = len(pixels)
    out = bytearray([2, 2, w >> 8, w & 255])
    half = w // 2
    for c in range(4):
        vals = [p[c] for p in pixels]
        assert all(x == vals[0] for x in vals[:half])
        out += bytes([128 + half, vals[0], w - half]) + bytes(vals[half:])
    return bytes(out)


def test09_read_texture_decodes_each_format_and_refuses_bad_files(tmp_path):
    from PIL import Image

    Image.fromarray(np.array([[[255, 0, 0], [0, 128, 255]]], np.uint8)).save(tmp_path / "a.png")
    srgb = read_texture(tmp_path / "a.png")
    assert srgb.shape == (1, 2, 3) and srgb.dtype == np.float32
    np.testing.assert_allclose(srgb[0, 1], [0.0, ((128 / 255 + 0.055) / 1.055) ** 2.4, 1.0],
                               rtol=1e-6)
    np.testing.assert_allclose(read_texture(tmp_path / "a.png", raw=True)[0, 1],
                               [0, 128 / 255, 1], rtol=1e-6)
    Image.fromarray(np.array([[10, 20]], np.uint8), "L").save(tmp_path / "g.png")
    assert read_texture(tmp_path / "g.png", raw=True).shape == (1, 2, 1)
    # Radiance: flat (2 x 3) and run-length encoded (1 x 8) scanlines;
    # value = mantissa * 2^(exponent - 136) (Bruce Walter's rgbe.c, as Mitsuba)
    flat = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 2 +X 3\n" + bytes(
        [128, 64, 0, 129] * 3 + [0, 0, 0, 0] * 3)
    (tmp_path / "f.hdr").write_bytes(flat)
    np.testing.assert_array_equal(read_texture(tmp_path / "f.hdr")[0, 0], [1.0, 0.5, 0.0])
    np.testing.assert_array_equal(read_texture(tmp_path / "f.hdr")[1], 0.0)
    pixels = [(128, 128, 128, 128)] * 4 + [(200, 100, 50, 130)] * 4
    (tmp_path / "r.hdr").write_bytes(b"#?RADIANCE\n\n-Y 1 +X 8\n" + _hdr_rle_row(pixels))
    rle = read_texture(tmp_path / "r.hdr")
    np.testing.assert_array_equal(rle[0, 0], [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(rle[0, 7], np.array([200, 100, 50]) * 2.0 ** -6)
    (tmp_path / "s.hdr").write_bytes(flat[:-5])
    with pytest.raises(SceneError, match="ends early"):
        read_texture(tmp_path / "s.hdr")
    # OpenEXR, linear as stored
    import OpenEXR
    rgb = np.arange(12, dtype=np.float32).reshape(2, 2, 3) / 4
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": rgb}) as exr:
        exr.write(str(tmp_path / "e.exr"))
    np.testing.assert_array_equal(read_texture(tmp_path / "e.exr"), rgb)
    # sizes refused from the header alone, before anything is decoded
    (tmp_path / "big.png").write_bytes(_png_header_only(9000, 9000))
    assert 9000 * 9000 > MAX_TEXELS
    with pytest.raises(SceneError, match="big.png is 9000 x 9000"):
        read_texture(tmp_path / "big.png")
    (tmp_path / "huge.png").write_bytes(_png_header_only(30000, 30000))
    with pytest.raises(SceneError, match="huge.png is too large to decode"):
        read_texture(tmp_path / "huge.png")  # Pillow's own check comes first
    (tmp_path / "huge.hdr").write_bytes(b"#?RADIANCE\n\n-Y 100000 +X 100000\n")
    with pytest.raises(SceneError, match="huge.hdr is 100000 x 100000"):
        read_texture(tmp_path / "huge.hdr")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nnonsense")
    with pytest.raises(SceneError, match="cannot read texture bad.png"):
        read_texture(tmp_path / "bad.png")
    (tmp_path / "x.tga").write_bytes(b"x")
    with pytest.raises(SceneError, match="unsupported texture file type"):
        read_texture(tmp_path / "x.tga")
    with pytest.raises(SceneError, match="not found: missing.png"):
        read_texture(tmp_path / "missing.png")
