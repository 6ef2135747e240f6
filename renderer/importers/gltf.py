"""glTF 2.0 importer: a `.gltf` (JSON, with its buffers and images by relative
URI or as base64 `data:` URIs) or a `.glb` (the binary container) in, a
native rayfarm document plus its assets out.

    imported = import_gltf(Path("models/box.glb"))   # -> Imported(doc, assets, report)

Everything the file holds is validated before it is used: the JSON's types,
indices into every array, accessors against their buffer views and buffers,
component types and normalized flags, the node hierarchy (a forest of strict
trees, bounded depth; cycles refused). Refusals are `SceneError`s whose
location is a JSON pointer into the file (``box.gltf#/accessors/3``).
What the file asks for that rayfarm does not render as written goes into the
import report. docs/scene-format.md ("glTF 2.0") documents the mapping.

The work is bounded: the file, every buffer and image are read at most once
and only when used; triangles, shapes and node depth have limits, so a hostile
file is refused before it costs memory or time.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import struct
import tempfile
import urllib.parse
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import SceneError
from ..scene_format import (COLLINEAR, MAX_COORDINATE, MAX_FILE_BYTES, MAX_RADIANCE,
                            MAX_TRIANGLES, MIN_EMITTER_AREA, MIN_ROUGHNESS)
from . import Imported, ReportEntry

from ..assets import asset_digest, encode_mesh, encode_texture

__all__ = ["import_gltf", "SUPPORTED_EXTENSIONS", "POINT_CANDELA_PER_WATT_SR"]

# Extensions this importer renders (or maps, as the report says); a file that
# *requires* any other is refused naming it.
SUPPORTED_EXTENSIONS = frozenset({
    "KHR_lights_punctual", "KHR_materials_emissive_strength", "KHR_materials_transmission",
    "KHR_materials_ior", "KHR_texture_transform", "KHR_mesh_quantization",
})
# glTF gives point lights in candela (lm/sr); rayfarm's point intensity is
# radiant (W/sr). 683 lm/W is the luminous efficacy the photometric units are
# defined by (and Blender's glTF exporter and importer use).
POINT_CANDELA_PER_WATT_SR = 683.0

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
MAX_JSON_NESTING = 64
MAX_NODE_DEPTH = 128  # levels of the node hierarchy
MAX_SHAPES = 100_000  # mesh primitives placed by nodes
MAX_TOTAL_BYTES = 1024 * 1024 * 1024  # buffers and images read, all together
MAX_ACCESSOR_ELEMENTS = 3 * MAX_TRIANGLES
MAX_ZERO_ELEMENTS = 1 << 20  # elements of an accessor with no buffer view
MAX_TEXTURE_BYTES = 512 * 1024 * 1024  # texture assets made, all together
DEFAULT_LONG_SIDE = 512  # pixels along the longer side of the image
DEFAULT_FOV = 40.0  # degrees, the framing camera's field of view

COMPONENTS = {  # componentType -> (numpy little-endian dtype, bytes)
    5120: ("<i1", 1), 5121: ("<u1", 1), 5122: ("<i2", 2), 5123: ("<u2", 2),
    5125: ("<u4", 4), 5126: ("<f4", 4),
}
COMPONENT_NAMES = {5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT",
                   5125: "UNSIGNED_INT", 5126: "FLOAT"}
TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
MODES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES",
         5: "TRIANGLE_STRIP", 6: "TRIANGLE_FAN"}
FILTER_NEAREST = 9728
WRAP_REPEAT = 10497
IMAGE_SUFFIX = {"image/png": ".png", "image/jpeg": ".jpg"}


def _read_texture(path: Path, raw: bool, name: str) -> np.ndarray:
    """(H, W, C) float32 linear texels (sRGB decoded unless `raw`); errors call
    the image `name`."""
    try:
        from ..textures import read_texture
    except ImportError:  # until the shading branch's reader is merged: then unused
        return _read_texture_pillow(path, raw)
    return read_texture(path, raw=raw, name=name)


def _read_texture_pillow(path: Path, raw: bool) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.width * im.height > 1 << 26:
                raise SceneError(f"image of {im.width}x{im.height} pixels is too large", path.name)
            im = im.convert("RGBA" if "A" in im.getbands() else "RGB")
            texels = np.asarray(im, dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise SceneError(f"cannot decode image: {exc}", path.name) from None
    if not raw:
        rgb = texels[..., :3]
        texels[..., :3] = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    return texels


# ----------------------------------------------------------------------------

def import_gltf(path: Path, root: Path | None = None) -> Imported:
    """Import a `.gltf` or `.glb` file; every relative URI must stay inside
    `root` (default: the file's folder)."""
    path = Path(path)
    root = Path(root) if root is not None else path.parent
    return _Importer(path, root).run()


class _Importer:
    def __init__(self, path: Path, root: Path):
        self.path = path
        self.root = root.resolve()
        try:
            self.name = path.resolve().relative_to(self.root).as_posix()
        except ValueError:
            raise SceneError("the scene file lies outside its root folder", path.name) from None
        self.bytes_read = 0
        self.bin_chunk: bytes | None = None
        self.buffers: dict[int, bytes] = {}
        self.accessors: dict[tuple, np.ndarray] = {}
        self.images: dict[tuple[int, bool], np.ndarray] = {}
        self.report: list[ReportEntry] = []
        self.reported: set[tuple[str, str]] = set()
        self.assets: dict[str, bytes] = {}
        self.textures: dict[str, dict] = {}
        self.texture_keys: dict[tuple, str] = {}
        self.materials: dict[int, tuple[str, dict, list[float] | None, bool]] = {}
        self.material_names: set[str] = set()
        self.meshes: dict[tuple[int, int], dict | None] = {}
        self.triangles = 0
        self.skipped_modes: set[str] = set()
        self.texture_bytes = 0

    # -- errors, report -------------------------------------------------------

    def where(self, ptr: str) -> str:
        return f"{self.name}#{ptr}"

    def fail(self, message: str, ptr: str = "") -> SceneError:
        return SceneError(message, self.where(ptr) if ptr else self.name)

    def note(self, ptr: str, action: str, what: str = "") -> None:
        element = f"#{ptr}{' ' + what if what else ''}" if ptr else (what or "#")
        if (element, action) not in self.reported:
            self.reported.add((element, action))
            self.report.append(ReportEntry(element=element, file=self.name, line=None,
                                           action=action))

    # -- typed access to the JSON ---------------------------------------------

    def obj(self, value: Any, ptr: str) -> dict:
        if not isinstance(value, dict):
            raise self.fail(f"expected a JSON object, got {_show(value)}", ptr)
        return value

    def get(self, o: dict, key: str, ptr: str, kind: str, default: Any = None,
            required: bool = False) -> Any:
        """o[key] checked to be of `kind`: int (>= 0), number, bool, str, obj, list."""
        if key not in o:
            if required:
                raise self.fail(f"missing required property '{key}'", ptr)
            return default
        v, p = o[key], f"{ptr}/{key}"
        ok = {
            "int": isinstance(v, int) and not isinstance(v, bool) and v >= 0,
            "number": isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v),
            "bool": isinstance(v, bool),
            "str": isinstance(v, str),
            "obj": isinstance(v, dict),
            "list": isinstance(v, list),
        }[kind]
        if not ok:
            want = {"int": "a non-negative integer", "number": "a finite number",
                    "bool": "true or false", "str": "a string", "obj": "a JSON object",
                    "list": "a JSON array"}[kind]
            raise self.fail(f"expected {want}, got {_show(v)}", p)
        return v

    def index(self, o: dict, key: str, ptr: str, collection: str, required: bool = False):
        i = self.get(o, key, ptr, "int", required=required)
        if i is not None and i >= len(self.array(collection)):
            raise self.fail(f"{key} {i} does not exist (the file has "
                            f"{len(self.array(collection))} {collection})", f"{ptr}/{key}")
        return i

    def array(self, name: str) -> list:
        return self.get(self.gltf, name, "", "list", default=[])

    def item(self, collection: str, i: int) -> tuple[dict, str]:
        ptr = f"/{collection}/{i}"
        o = self.obj(self.array(collection)[i], ptr)
        self.get(o, "name", ptr, "str")  # names label shapes, materials and the report
        return o, ptr

    def numbers(self, o: dict, key: str, ptr: str, n: int, default: list[float],
                lo: float = -math.inf, hi: float = math.inf) -> list[float]:
        v = o.get(key, default)
        p = f"{ptr}/{key}"
        if (not isinstance(v, list) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                           and math.isfinite(x) for x in v)):
            raise self.fail(f"expected {n} finite numbers, got {_show(v)}", p)
        if any(not lo <= x <= hi for x in v):
            raise self.fail(f"values must lie in [{lo:g}, {hi:g}], got {_show(v)}", p)
        return [float(x) for x in v]

    def number(self, o: dict, key: str, ptr: str, default: float, lo: float = -math.inf,
               hi: float = math.inf) -> float:
        v = float(self.get(o, key, ptr, "number", default=default))
        if not lo <= v <= hi:
            raise self.fail(f"must lie in [{lo:g}, {hi:g}], got {v:g}", f"{ptr}/{key}")
        return v

    def extension(self, o: dict, ptr: str, name: str) -> dict | None:
        exts = self.get(o, "extensions", ptr, "obj", default={})
        if name not in exts:
            return None
        return self.obj(exts[name], f"{ptr}/extensions/{name}")

    def other_extensions(self, o: dict, ptr: str, handled: tuple[str, ...], what: str) -> None:
        for name in self.get(o, "extensions", ptr, "obj", default={}):
            if name not in handled:
                self.note(ptr, f"extension {name} ignored", what)

    # -- files ----------------------------------------------------------------

    def count_bytes(self, n: int, ptr: str) -> None:
        self.bytes_read += n
        if self.bytes_read > MAX_TOTAL_BYTES:
            raise self.fail(f"the buffers and images read exceed {MAX_TOTAL_BYTES} bytes", ptr)

    def local_file(self, uri: str, ptr: str) -> Path:
        """A relative URI resolved inside the root folder."""
        if "\\" in uri or uri.startswith("/") or "\0" in uri:
            raise self.fail(f"URI {uri!r} is not a relative path", ptr)
        parsed = urllib.parse.urlsplit(uri)
        if parsed.scheme or parsed.netloc:
            raise self.fail(f"URI {uri!r}: only relative paths and data: URIs are read", ptr)
        rel = urllib.parse.unquote(parsed.path)
        target = (self.path.parent / rel).resolve()
        if target != self.root and self.root not in target.parents:
            raise self.fail(f"URI {uri!r} leads outside the scene's folder", ptr)
        if not target.is_file():
            raise self.fail(f"file not found: {rel}", ptr)
        if target.stat().st_size > MAX_FILE_BYTES:
            raise self.fail(f"{rel} is larger than {MAX_FILE_BYTES} bytes", ptr)
        return target

    def data_uri(self, uri: str, ptr: str) -> tuple[bytes, str]:
        """The bytes and media type of a base64 data: URI."""
        head, sep, payload = uri.partition(",")
        if not sep or not head.endswith(";base64"):
            raise self.fail("a data: URI must be base64 (data:<type>;base64,...)", ptr)
        if len(payload) > MAX_FILE_BYTES * 4 // 3 + 4:
            raise self.fail(f"data: URI larger than {MAX_FILE_BYTES} bytes", ptr)
        try:
            data = base64.b64decode(payload, validate=True)
        except (binascii.Error, ValueError):
            raise self.fail("data: URI is not valid base64", ptr) from None
        self.count_bytes(len(data), ptr)
        return data, head[len("data:"):-len(";base64")]

    def load(self) -> None:
        p = self.path
        if not p.is_file():
            raise self.fail("file not found")
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise self.fail(f"file larger than {MAX_FILE_BYTES} bytes")
        data = p.read_bytes()
        if p.suffix.lower() == ".glb" or data[:4] == GLB_MAGIC:
            text = self.parse_glb(data)
        else:
            text = data
        try:
            s = text.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise self.fail(f"the JSON is not UTF-8 (byte {exc.start})") from None

        def no_constants(name):
            raise ValueError(f"{name} is not JSON")
        try:
            gltf = json.loads(s, parse_constant=no_constants)
        except json.JSONDecodeError as exc:
            raise self.fail(f"invalid JSON at line {exc.lineno}, column {exc.colno}: "
                            f"{exc.msg}") from None
        except (ValueError, RecursionError) as exc:
            raise self.fail(f"invalid JSON: {exc}"[:200]) from None
        if _nesting(gltf) > MAX_JSON_NESTING:
            raise self.fail(f"the JSON nests more than {MAX_JSON_NESTING} levels deep")
        self.gltf = self.obj(gltf, "")

    def parse_glb(self, data: bytes) -> bytes:
        if len(data) < 20:
            raise self.fail("a .glb needs a 12-byte header and a JSON chunk")
        magic, version, length = struct.unpack_from("<4sII", data, 0)
        if magic != GLB_MAGIC:
            raise self.fail("not a binary glTF (.glb): the file does not start with 'glTF'")
        if version != 2:
            raise self.fail(f"binary glTF version {version} (this importer reads version 2)")
        if length != len(data):
            raise self.fail(f"the .glb header gives a length of {length} bytes, the file "
                            f"has {len(data)}")
        offset, chunks = 12, []
        while offset < length:
            if offset + 8 > length:
                raise self.fail(f"truncated chunk header at byte {offset} of the .glb")
            clen, ctype = struct.unpack_from("<II", data, offset)
            if offset + 8 + clen > length:
                raise self.fail(f"chunk at byte {offset} of the .glb runs past the end of "
                                f"the file ({clen} bytes)")
            chunks.append((ctype, data[offset + 8: offset + 8 + clen]))
            offset += 8 + clen
        if not chunks or chunks[0][0] != CHUNK_JSON:
            raise self.fail("the first chunk of a .glb must be JSON")
        if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN:
            self.bin_chunk = chunks[1][1]
        return chunks[0][1]

    # -- buffers, views, accessors --------------------------------------------

    def buffer(self, i: int) -> bytes:
        if i in self.buffers:
            return self.buffers[i]
        b, ptr = self.item("buffers", i)
        length = self.get(b, "byteLength", ptr, "int", required=True)
        uri = self.get(b, "uri", ptr, "str")
        if uri is None:
            if i != 0 or self.bin_chunk is None:
                raise self.fail("buffer has no uri (only the first buffer of a .glb may "
                                "stand for its BIN chunk, and this file has none)", ptr)
            data = self.bin_chunk
        elif uri.startswith("data:"):
            data, _ = self.data_uri(uri, f"{ptr}/uri")
        else:
            f = self.local_file(uri, f"{ptr}/uri")
            self.count_bytes(f.stat().st_size, f"{ptr}/uri")
            data = f.read_bytes()
        if len(data) < length:
            raise self.fail(f"byteLength is {length} but the buffer holds {len(data)} bytes",
                            ptr)
        self.buffers[i] = data[:length]
        return self.buffers[i]

    def view(self, i: int) -> tuple[memoryview, int | None, str]:
        v, ptr = self.item("bufferViews", i)
        b = self.index(v, "buffer", ptr, "buffers", required=True)
        offset = self.get(v, "byteOffset", ptr, "int", default=0)
        length = self.get(v, "byteLength", ptr, "int", required=True)
        stride = self.get(v, "byteStride", ptr, "int")
        if stride is not None and not (4 <= stride <= 252 and stride % 4 == 0):
            raise self.fail(f"byteStride must be a multiple of 4 in [4, 252], got {stride}",
                            f"{ptr}/byteStride")
        data = self.buffer(b)
        if offset + length > len(data):
            raise self.fail(f"bytes {offset}..{offset + length} lie outside buffer {b} "
                            f"({len(data)} bytes)", ptr)
        return memoryview(data)[offset:offset + length], stride, ptr

    def accessor(self, i: int, use: str, types: tuple[str, ...],
                 components: tuple[int, ...]) -> np.ndarray:
        """Accessor i as float64 (or int64 for integers that are not
        normalized), shape (count, n). `use` names what reads it in messages."""
        key = (i, types, components)
        if key in self.accessors:
            return self.accessors[key]
        a, ptr = self.item("accessors", i)
        ctype = self.get(a, "componentType", ptr, "int", required=True)
        atype = self.get(a, "type", ptr, "str", required=True)
        count = self.get(a, "count", ptr, "int", required=True)
        normalized = self.get(a, "normalized", ptr, "bool", default=False)
        if ctype not in COMPONENTS:
            raise self.fail(f"unknown componentType {ctype}", f"{ptr}/componentType")
        if atype not in TYPES:
            raise self.fail(f"unknown type {atype!r}", f"{ptr}/type")
        if atype not in types or ctype not in components:
            allowed = ", ".join(COMPONENT_NAMES[c] for c in components)
            raise self.fail(f"{use} must be a {' or '.join(types)} of {allowed}; this accessor "
                            f"is a {atype} of {COMPONENT_NAMES[ctype]}", ptr)
        if normalized and ctype in (5125, 5126):
            raise self.fail(f"normalized is not allowed for {COMPONENT_NAMES[ctype]}",
                            f"{ptr}/normalized")
        if not 1 <= count <= MAX_ACCESSOR_ELEMENTS:
            raise self.fail(f"count must lie in [1, {MAX_ACCESSOR_ELEMENTS}], got {count}",
                            f"{ptr}/count")
        dtype, size = COMPONENTS[ctype]
        n = TYPES[atype]
        if "bufferView" in a:
            view, stride, vptr = self.view(self.index(a, "bufferView", ptr, "bufferViews"))
            offset = self.get(a, "byteOffset", ptr, "int", default=0)
            elem = n * size
            stride = stride or elem
            if stride < elem:
                raise self.fail(f"byteStride {stride} of {vptr} is smaller than one element "
                                f"({elem} bytes)", ptr)
            end = offset + stride * (count - 1) + elem
            if end > len(view):
                raise self.fail(f"{count} elements of {elem} bytes every {stride} from byte "
                                f"{offset} need {end} bytes; buffer view "
                                f"{a['bufferView']} has {len(view)}", ptr)
            out = np.ndarray((count, n), dtype=dtype, buffer=view, offset=offset,
                             strides=(stride, size)).copy()
        else:  # all zeros (or sparse): cheap to ask for, so bounded tighter
            if count > MAX_ZERO_ELEMENTS:
                raise self.fail(f"an accessor without a bufferView may have at most "
                                f"{MAX_ZERO_ELEMENTS} elements, this one has {count}",
                                f"{ptr}/count")
            out = np.zeros((count, n), dtype=dtype)
        sparse = self.get(a, "sparse", ptr, "obj")
        if sparse is not None:
            self.apply_sparse(out, sparse, f"{ptr}/sparse", count, n, dtype, size)
        with np.errstate(invalid="ignore", over="ignore"):  # NaN and inf are checked by use
            if dtype == "<f4":
                out = out.astype(np.float64)
            elif normalized:
                out = _normalize(out, ctype)
            else:
                out = out.astype(np.int64)
        self.accessors[key] = out
        return out

    def apply_sparse(self, out: np.ndarray, sparse: dict, ptr: str, count: int, n: int,
                     dtype: str, size: int) -> None:
        k = self.get(sparse, "count", ptr, "int", required=True)
        if not 1 <= k <= count:
            raise self.fail(f"sparse count must lie in [1, {count}], got {k}", f"{ptr}/count")
        ind = self.obj(self.get(sparse, "indices", ptr, "obj", required=True), f"{ptr}/indices")
        val = self.obj(self.get(sparse, "values", ptr, "obj", required=True), f"{ptr}/values")
        ictype = self.get(ind, "componentType", f"{ptr}/indices", "int", required=True)
        if ictype not in (5121, 5123, 5125):
            raise self.fail("sparse indices must be UNSIGNED_BYTE, UNSIGNED_SHORT or "
                            "UNSIGNED_INT", f"{ptr}/indices/componentType")
        idtype, isize = COMPONENTS[ictype]

        def packed(o: dict, p: str, dt: str, width: int) -> np.ndarray:
            view, _, _ = self.view(self.index(o, "bufferView", p, "bufferViews", required=True))
            off = self.get(o, "byteOffset", p, "int", default=0)
            if off + k * width > len(view):
                raise self.fail(f"{k} sparse entries of {width} bytes from byte {off} run past "
                                f"the buffer view ({len(view)} bytes)", p)
            return np.frombuffer(view, dtype=dt, count=k * (width // np.dtype(dt).itemsize),
                                 offset=off)

        idx = packed(ind, f"{ptr}/indices", idtype, isize).astype(np.int64)
        if np.any(idx >= count) or np.any(np.diff(idx) <= 0):
            raise self.fail(f"sparse indices must increase strictly and stay below {count}",
                            f"{ptr}/indices")
        out[idx] = packed(val, f"{ptr}/values", dtype, n * size).reshape(k, n)

    # -- the document ---------------------------------------------------------

    def run(self) -> Imported:
        self.load()
        g = self.gltf
        asset = self.obj(self.get(g, "asset", "", "obj", required=True), "/asset")
        version = self.get(asset, "version", "/asset", "str", required=True)
        if not version.startswith("2."):
            raise self.fail(f"glTF version {version} (this importer reads 2.x)", "/asset/version")
        min_version = self.get(asset, "minVersion", "/asset", "str")
        if min_version is not None and min_version not in ("2.0",):
            raise self.fail(f"the file needs glTF {min_version} (this importer reads 2.0)",
                            "/asset/minVersion")
        required = self.get(g, "extensionsRequired", "", "list", default=[])
        for k, name in enumerate(required):
            if name not in SUPPORTED_EXTENSIONS:
                raise self.fail(f"the file requires extension {name}, which this importer does "
                                f"not support (supported: {', '.join(sorted(SUPPORTED_EXTENSIONS))})",
                                f"/extensionsRequired/{k}")
        used = self.get(g, "extensionsUsed", "", "list", default=[])
        for name in used:
            if name not in SUPPORTED_EXTENSIONS:
                self.note("/extensionsUsed", f"extension {name} ignored", str(name))
        self.quantized = "KHR_mesh_quantization" in used or "KHR_mesh_quantization" in required
        for what in ("animations", "skins"):
            if self.array(what):
                self.note(f"/{what}", "ignored: the scene is rendered at rest, every node "
                          "with its own transform" if what == "animations" else
                          "ignored: skinned meshes are rendered in their bind pose")
        lights = self.punctual_lights()

        roots, sptr = self.scene_roots()
        shapes: list[dict] = []
        emitters: list[dict] = []
        camera: dict | None = None
        camera_ptr = ""
        for node, world, nptr in self.walk(roots, sptr):
            n = self.obj(self.array("nodes")[node], nptr)
            if "mesh" in n:
                shapes.extend(self.place_mesh(self.index(n, "mesh", nptr, "meshes"), world,
                                              n, nptr))
            if "camera" in n:
                ci = self.index(n, "camera", nptr, "cameras")
                c, cptr = self.item("cameras", ci)
                ctype = self.get(c, "type", cptr, "str", required=True)
                if ctype == "perspective" and camera is None:
                    camera, camera_ptr = self.camera(c, cptr, world, nptr), cptr
                elif ctype == "perspective":
                    self.note(cptr, f"ignored: the first perspective camera ({camera_ptr}) "
                              "is the one rendered", f"(at {nptr})")
                else:
                    self.note(cptr, f"ignored: {ctype} cameras are not rendered", f"(at {nptr})")
            light = self.extension(n, nptr, "KHR_lights_punctual")
            if light is not None:
                li = self.get(light, "light", f"{nptr}/extensions/KHR_lights_punctual", "int",
                              required=True)
                if li not in lights:
                    raise self.fail(f"light {li} does not exist",
                                    f"{nptr}/extensions/KHR_lights_punctual/light")
                em = lights[li](world, nptr)
                if em is not None:
                    emitters.append(em)
            self.other_extensions(n, nptr, ("KHR_lights_punctual",), "")
            if len(shapes) > MAX_SHAPES:
                raise self.fail(f"the scene places more than {MAX_SHAPES} mesh primitives",
                                nptr)
        if not shapes:
            skipped = sorted(self.skipped_modes)
            raise self.fail("the scene has no triangles to render" + (
                f": its primitives are {', '.join(skipped)}, which rayfarm does not render "
                "(only surfaces)" if skipped else ""), sptr or "/")
        if camera is None:
            camera = self.default_camera(shapes)
            self.note("/cameras", "no perspective camera in the scene: a default camera frames "
                      "the scene's bounds from +z (docs/scene-format.md, glTF 2.0)")
        if not emitters and not any("emitter" in s for s in shapes):
            self.note("/", "the scene has no lights (glTF viewers add their own): it renders "
                      "black unless lights are added")
        for s in shapes:
            s.pop("_bounds", None)
        materials = {name: mat for name, mat, _, _ in self.materials.values()}
        doc: dict[str, Any] = {
            "name": self.path.stem,
            "description": _description(asset, self.name),
            "camera": camera,
            "materials": materials,
            "shapes": shapes,
        }
        if emitters:
            doc["emitters"] = emitters
        if self.textures:
            doc["textures"] = self.textures
        return Imported(doc=doc, assets=self.assets, report=self.report)

    def scene_roots(self) -> tuple[list[int], str]:
        scenes = self.array("scenes")
        if not scenes:
            raise self.fail("the file has no scenes: nothing to render", "/scenes")
        si = self.index(self.gltf, "scene", "", "scenes")
        if si is None:
            si = 0
        s, sptr = self.item("scenes", si)
        nodes = self.get(s, "nodes", sptr, "list", default=[])
        roots = [self._node_ref(v, f"{sptr}/nodes/{k}") for k, v in enumerate(nodes)]
        if not roots:
            raise self.fail("the scene has no nodes: nothing to render", sptr)
        return roots, sptr

    def _node_ref(self, v: Any, ptr: str) -> int:
        n = len(self.array("nodes"))
        if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v < n:
            raise self.fail(f"expected a node index in [0, {n}), got {_show(v)}", ptr)
        return v

    def walk(self, roots: list[int], sptr: str):
        """(node, world matrix, pointer) for every node under the roots, parents
        first. The hierarchy must be a forest of strict trees: a node with two
        parents, a root with a parent, or a cycle is refused."""
        nodes = self.array("nodes")
        parent: dict[int, int] = {}
        for i, raw in enumerate(nodes):
            ptr = f"/nodes/{i}"
            n = self.obj(raw, ptr)
            for k, c in enumerate(self.get(n, "children", ptr, "list", default=[])):
                c = self._node_ref(c, f"{ptr}/children/{k}")
                if c in parent or c == i:
                    raise self.fail(f"node {c} has two parents (nodes {parent.get(c, i)} and "
                                    f"{i}): the node hierarchy must be a set of trees (a cycle?)",
                                    f"{ptr}/children/{k}")
                parent[c] = i
        seen: set[int] = set()
        for k, r in enumerate(roots):
            if r in parent:
                raise self.fail(f"root node {r} is also a child of node {parent[r]}: the node "
                                "hierarchy must be a set of trees (a cycle?)", f"{sptr}/nodes/{k}")
            if r in seen:
                raise self.fail(f"root node {r} is listed twice", f"{sptr}/nodes/{k}")
            seen.add(r)
        stack = [(r, np.eye(4), 1) for r in reversed(roots)]
        while stack:
            i, parent_world, depth = stack.pop()
            ptr = f"/nodes/{i}"
            if depth > MAX_NODE_DEPTH:
                raise self.fail(f"the node hierarchy is more than {MAX_NODE_DEPTH} levels deep",
                                ptr)
            n = self.obj(nodes[i], ptr)
            world = parent_world @ self.local_matrix(n, ptr)
            yield i, world, ptr
            children = self.get(n, "children", ptr, "list", default=[])
            stack.extend((c, world, depth + 1) for c in reversed(children))

    def local_matrix(self, n: dict, ptr: str) -> np.ndarray:
        if "matrix" in n:
            m = np.asarray(self.numbers(n, "matrix", ptr, 16, [], -MAX_COORDINATE,
                                        MAX_COORDINATE)).reshape(4, 4).T  # column-major
            if not np.allclose(m[3], [0, 0, 0, 1]):
                raise self.fail("the last row of a node matrix must be [0, 0, 0, 1]",
                                f"{ptr}/matrix")
            if any(k in n for k in ("translation", "rotation", "scale")):
                self.note(ptr, "translation/rotation/scale ignored: the node also gives a "
                          "matrix, which is used")
            return m
        t = self.numbers(n, "translation", ptr, 3, [0, 0, 0], -MAX_COORDINATE, MAX_COORDINATE)
        q = self.numbers(n, "rotation", ptr, 4, [0, 0, 0, 1], -1.0001, 1.0001)
        s = self.numbers(n, "scale", ptr, 3, [1, 1, 1], -MAX_COORDINATE, MAX_COORDINATE)
        norm = math.sqrt(sum(c * c for c in q))
        if not abs(norm - 1) < 1e-3:
            raise self.fail(f"rotation must be a unit quaternion (its length is {norm:.6g})",
                            f"{ptr}/rotation")
        x, y, z, w = (c / norm for c in q)
        r = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        m = np.eye(4)
        m[:3, :3] = r * np.asarray(s)[None, :]
        m[:3, 3] = t
        return m

    # -- meshes ---------------------------------------------------------------

    def place_mesh(self, mi: int, world: np.ndarray, node: dict, nptr: str) -> list[dict]:
        mesh, mptr = self.item("meshes", mi)
        prims = self.get(mesh, "primitives", mptr, "list", required=True)
        if not prims:
            raise self.fail("a mesh needs at least one primitive", f"{mptr}/primitives")
        if self.get(mesh, "weights", mptr, "list") or "weights" in node:
            self.note(mptr, "morph target weights ignored: the base shape is rendered")
        if "skin" in node:
            self.note(nptr, "skin ignored: the mesh is rendered in its bind pose")
        if not np.all(np.isfinite(world)) or np.any(np.abs(world) > MAX_COORDINATE):
            raise self.fail(f"the node's world transform has entries beyond "
                            f"+-{MAX_COORDINATE:g}", nptr)
        if abs(np.linalg.det(world[:3, :3])) < 1e-12:
            self.note(nptr, "not rendered: its world transform is singular (a zero scale hides "
                      "it)")
            return []
        label = self.get(node, "name", nptr, "str") or self.get(mesh, "name", mptr, "str") or ""
        out = []
        for k in range(len(prims)):
            prim = self.primitive(mi, k)
            if prim is None:
                continue
            pptr = f"{mptr}/primitives/{k}"
            name, _, emission, _ = self.material(prim["material"])
            self.triangles += prim["triangles"]
            if self.triangles > MAX_TRIANGLES:
                raise self.fail(f"the scene has more than {MAX_TRIANGLES} triangles", pptr)
            shape = {"type": "mesh", "mesh": prim["digest"], "material": name,
                     "to_world": world.tolist(),
                     "name": f"{label or 'mesh ' + str(mi)}/{k}"}
            if emission is not None:
                digest = self.emitting_mesh(prim, world, pptr)
                if digest is None:
                    self.note(pptr, "emission ignored: none of its triangles has an area")
                else:
                    shape["mesh"] = digest
                    shape["emitter"] = {"type": "area", "radiance": emission}
            lo, hi = _world_bounds(prim["positions"], world)
            shape["_bounds"] = (lo, hi)
            out.append(shape)
        return out

    def primitive(self, mi: int, k: int) -> dict | None:
        """Mesh mi's primitive k in local space, encoded as an asset (cached)."""
        key = (mi, k)
        if key in self.meshes:
            return self.meshes[key]
        self.meshes[key] = None
        prim_raw = self.get(self.item("meshes", mi)[0], "primitives", f"/meshes/{mi}", "list")[k]
        ptr = f"/meshes/{mi}/primitives/{k}"
        p = self.obj(prim_raw, ptr)
        attrs = self.obj(self.get(p, "attributes", ptr, "obj", required=True), f"{ptr}/attributes")
        mode = self.get(p, "mode", ptr, "int", default=4)
        if mode not in MODES:
            raise self.fail(f"unknown primitive mode {mode}", f"{ptr}/mode")
        material = self.index(p, "material", ptr, "materials")
        if mode < 4:
            self.skipped_modes.add(MODES[mode])
            self.note(ptr, f"ignored: {MODES[mode]} have no area to render")
            return None
        if self.extension(p, ptr, "KHR_draco_mesh_compression") is not None:
            self.note(ptr, "KHR_draco_mesh_compression ignored: the uncompressed accessors "
                      "are read")
        self.other_extensions(p, ptr, ("KHR_draco_mesh_compression",), "")
        if p.get("targets"):
            self.note(ptr, "morph targets ignored: the base shape is rendered")
        for name in attrs:
            if name.startswith("COLOR_"):
                self.note(ptr, f"vertex colours ({name}) ignored")
        if "POSITION" not in attrs:
            raise self.fail("a primitive needs a POSITION attribute", f"{ptr}/attributes")
        floats = (5126,)
        quant_pos = (5120, 5121, 5122, 5123) if self.quantized else ()
        pos = self.accessor(self.index(attrs, "POSITION", f"{ptr}/attributes", "accessors"),
                            f"POSITION of {ptr}", ("VEC3",), floats + quant_pos
                            ).astype(np.float64)
        nv = len(pos)
        _check_finite(self, pos, attrs["POSITION"], "POSITION")
        if np.any(np.abs(pos) > MAX_COORDINATE):
            j = int(np.argmax(np.any(np.abs(pos) > MAX_COORDINATE, axis=1)))
            raise self.fail(f"vertex {j} lies at {pos[j].tolist()}; every coordinate must be "
                            f"within +-{MAX_COORDINATE:g}", f"/accessors/{attrs['POSITION']}")
        normals = None
        if "NORMAL" in attrs:
            ni = self.index(attrs, "NORMAL", f"{ptr}/attributes", "accessors")
            normals = self.accessor(ni, f"NORMAL of {ptr}", ("VEC3",),
                                    floats + ((5120, 5122) if self.quantized else ()))
            if normals.dtype != np.float64:
                raise self.fail("integer NORMAL must be normalized", f"/accessors/{ni}")
            self.same_count(normals, nv, ni, "NORMAL", ptr)
            length = np.linalg.norm(normals, axis=1)
            bad = ~np.isfinite(length) | (length < 1e-6)
            if np.any(bad):
                self.note(ptr, f"NORMAL ignored: {int(bad.sum())} of its {nv} normals are zero "
                          "or not finite; the geometric normals are used")
                normals = None
            else:
                normals = normals / length[:, None]
        uvs = None
        if "TEXCOORD_0" in attrs:
            ti = self.index(attrs, "TEXCOORD_0", f"{ptr}/attributes", "accessors")
            uvs = self.accessor(ti, f"TEXCOORD_0 of {ptr}", ("VEC2",),
                                floats + (5121, 5123) + ((5120, 5122) if self.quantized else ()))
            if uvs.dtype != np.float64 and not self.quantized:
                raise self.fail("integer TEXCOORD_0 must be normalized", f"/accessors/{ti}")
            uvs = uvs.astype(np.float64)
            self.same_count(uvs, nv, ti, "TEXCOORD_0", ptr)
            if not np.all(np.isfinite(uvs)):
                self.note(ptr, "TEXCOORD_0 ignored: it holds values that are not finite")
                uvs = None
        if "indices" in p:
            ii = self.index(p, "indices", ptr, "accessors")
            idx = self.accessor(ii, f"the indices of {ptr}", ("SCALAR",), (5121, 5123, 5125))
            if idx.dtype != np.int64:
                raise self.fail("indices must not be normalized", f"/accessors/{ii}/normalized")
            idx = idx[:, 0]
            if idx.size and idx.max() >= nv:
                j = int(np.argmax(idx >= nv))
                raise self.fail(f"index {j} is {int(idx[j])}, beyond the primitive's {nv} "
                                f"vertices", f"/accessors/{ii}")
        else:
            idx = np.arange(nv, dtype=np.int64)
        faces = self.triangulate(idx, mode, ptr)
        if len(faces) == 0:
            self.note(ptr, "ignored: it has no triangles")
            return None
        blob = encode_mesh(pos, faces, normals, uvs)
        digest = asset_digest(blob)
        self.assets[digest] = blob
        entry = {"digest": digest, "positions": pos, "faces": faces, "normals": normals,
                 "uvs": uvs, "material": material, "triangles": len(faces)}
        self.meshes[key] = entry
        return entry

    def same_count(self, arr: np.ndarray, nv: int, ai: int, what: str, ptr: str) -> None:
        if len(arr) != nv:
            raise self.fail(f"{what} has {len(arr)} elements but POSITION has {nv} (all "
                            f"attributes of {ptr} must have the same count)", f"/accessors/{ai}")

    def triangulate(self, idx: np.ndarray, mode: int, ptr: str) -> np.ndarray:
        n = len(idx)
        if mode == 4:
            if n % 3:
                self.note(ptr, f"the last {n % 3} vertices ignored: TRIANGLES needs a multiple "
                          f"of 3 ({n} given)")
            return idx[: n - n % 3].reshape(-1, 3)
        if n < 3:
            return np.zeros((0, 3), np.int64)
        i = np.arange(n - 2)
        if mode == 5:  # strip: every other triangle swaps two vertices to keep the winding
            odd = i % 2
            return np.stack([idx[i], idx[i + 1 + odd], idx[i + 2 - odd]], axis=1)
        return np.stack([idx[i + 1], idx[i + 2], np.full(n - 2, idx[0])], axis=1)  # fan

    def emitting_mesh(self, prim: dict, world: np.ndarray, ptr: str) -> str | None:
        """The primitive's asset without the triangles an area light cannot
        have (no area, or a sliver, in world space); None if none is left."""
        wv = prim["positions"] @ world[:3, :3].T + world[:3, 3]
        tri = wv[prim["faces"]]
        e1, e2, e3 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], tri[:, 2] - tri[:, 1]
        longest = np.max(np.linalg.norm(np.stack([e1, e2, e3], axis=1), axis=2), axis=1)
        double_area = np.linalg.norm(np.cross(e1, e2), axis=1)
        keep = (0.5 * double_area >= MIN_EMITTER_AREA) & (double_area >= COLLINEAR * longest ** 2)
        if keep.all():
            return prim["digest"]
        if not keep.any():
            return None
        self.note(ptr, f"{int((~keep).sum())} degenerate triangles left out of its area light")
        blob = encode_mesh(prim["positions"], prim["faces"][keep], prim["normals"], prim["uvs"])
        digest = asset_digest(blob)
        self.assets[digest] = blob
        return digest

    # -- materials ------------------------------------------------------------

    def material(self, mi: int | None) -> tuple[str, dict, list[float] | None, bool]:
        """(native name, native material, area radiance or None, two-sided)."""
        key = -1 if mi is None else mi
        if key in self.materials:
            return self.materials[key]
        if mi is None:
            m, ptr, label = {}, "/materials/default", "default"
            self.note(ptr, "a primitive without a material gets glTF's default material "
                      "(white, metallic 1, roughness 1): a rough white conductor")
        else:
            m, ptr = self.item("materials", mi)
            label = self.get(m, "name", ptr, "str") or f"material{mi}"
        name = label if label not in self.material_names else f"{label}#{key}"
        while name in self.material_names:
            name += "'"
        self.material_names.add(name)
        what = f'"{label}"'
        pbr = self.obj(self.get(m, "pbrMetallicRoughness", ptr, "obj", default={}),
                       f"{ptr}/pbrMetallicRoughness")
        pptr = f"{ptr}/pbrMetallicRoughness"
        base = self.numbers(pbr, "baseColorFactor", pptr, 4, [1, 1, 1, 1], 0, 1)
        metallic = self.number(pbr, "metallicFactor", pptr, 1.0, 0, 1)
        rough = self.number(pbr, "roughnessFactor", pptr, 1.0, 0, 1)
        self.other_extensions(pbr, pptr, (), what)
        double = self.get(m, "doubleSided", ptr, "bool", default=False)
        alpha_mode = self.get(m, "alphaMode", ptr, "str", default="OPAQUE")
        if alpha_mode not in ("OPAQUE", "MASK", "BLEND"):
            raise self.fail(f"unknown alphaMode {alpha_mode!r}", f"{ptr}/alphaMode")
        cutoff = self.number(m, "alphaCutoff", ptr, 0.5, 0, math.inf)
        for tex in ("normalTexture", "occlusionTexture"):
            if tex in m:
                self.texture_info(m, tex, ptr)  # validated, then reported
                self.note(f"{ptr}/{tex}", "ignored: " + (
                    "rayfarm has no normal mapping yet" if tex == "normalTexture" else
                    "a path tracer computes occlusion itself"), what)
        handled = ("KHR_materials_emissive_strength", "KHR_materials_transmission",
                   "KHR_materials_ior")
        self.other_extensions(m, ptr, handled, what)

        base_tex = self.texture_info(pbr, "baseColorTexture", pptr)
        mr_tex = self.texture_info(pbr, "metallicRoughnessTexture", pptr)
        base_img = self.texels(base_tex, raw=False) if base_tex else None
        mr_img = self.texels(mr_tex, raw=True) if mr_tex else None

        transmission = 0.0
        tx = self.extension(m, ptr, "KHR_materials_transmission")
        if tx is not None:
            xptr = f"{ptr}/extensions/KHR_materials_transmission"
            transmission = self.number(tx, "transmissionFactor", xptr, 0.0, 0, 1)
            if "transmissionTexture" in tx:
                self.texture_info(tx, "transmissionTexture", xptr)
                self.note(xptr, "transmissionTexture ignored: transmissionFactor is used "
                          "everywhere", what)
        ior = 1.5
        ix = self.extension(m, ptr, "KHR_materials_ior")
        if ix is not None:
            ior = self.number(ix, "ior", f"{ptr}/extensions/KHR_materials_ior", 1.5, 0, 10)
            if ior == 0:  # the extension's way of saying "no refraction": an ior of 1
                ior = 1.0

        metal_mean = metallic
        if mr_img is not None:
            metal_tex = metallic * mr_img[..., 2 if mr_img.shape[2] >= 3 else 0]
            metal_mean = float(metal_tex.mean())
            if metal_tex.min() < 0.5 <= metal_tex.max():
                self.note(pptr, "metallicRoughnessTexture: metallic varies across the texture; "
                          f"the whole surface is approximated as "
                          f"{'metal' if metal_mean >= 0.5 else 'non-metal'} (mean "
                          f"{metal_mean:.2f})", what)
        out: dict[str, Any]
        if transmission >= 0.5:
            if not 1.0 <= ior <= 4.0:
                self.note(ptr, f"ior {ior:g} clamped into [1, 4]", what)
                ior = min(max(ior, 1.0), 4.0)
            out = {"type": "dielectric", "ior": ior}
            self.note(ptr, f"approximated as a smooth dielectric (ior {ior:g}): "
                      "baseColor, roughness and metallic are not rendered"
                      + (f"; transmission {transmission:g} rounded to 1" if transmission < 1
                         else ""), what)
        else:
            if transmission > 0:
                self.note(ptr, f"transmission {transmission:g} rounded to 0 (opaque)", what)
            colour: Any = base[:3]
            if base_img is not None:
                colour = self.baked(base_tex, "base_color", np.clip(
                    _rgb(base_img) * np.asarray(base[:3], np.float32), 0, 1), name)
            if metal_mean >= 0.5:
                out = {"type": "glossy", "specular": colour,
                       "roughness": self.roughness(rough, mr_img, mr_tex, name, what, ptr)}
                if metal_mean < 1:
                    self.note(ptr, f"metallic {metal_mean:.2f} approximated as 1: a GGX conductor "
                              "(specular = baseColor, alpha = roughness^2)", what)
            else:
                out = {"type": "diffuse", "albedo": colour}
                self.note(ptr, "approximated as diffuse (albedo = baseColor): the dielectric "
                          "specular layer of the metallic-roughness model is not rendered"
                          + (f"; metallic {metal_mean:.2f} rounded to 0" if metal_mean > 0
                             else ""), what)
            if double:
                out["twosided"] = True
            opacity = self.opacity(alpha_mode, cutoff, base[3], base_img, base_tex, name, what,
                                   ptr)
            if opacity is not None:
                out["opacity"] = opacity
        if out["type"] == "dielectric" and alpha_mode != "OPAQUE":
            self.note(ptr, f"alphaMode {alpha_mode} ignored on a transmissive material", what)
        emission = self.emission(m, ptr, name, what, double)
        self.materials[key] = (name, out, emission, double)
        return self.materials[key]

    def roughness(self, rough: float, mr_img, mr_tex, name: str, what: str, ptr: str):
        """The GGX alpha: glTF's roughness squared, at least MIN_ROUGHNESS."""
        if mr_img is not None:
            g = mr_img[..., 1 if mr_img.shape[2] >= 3 else 0]
            alpha = np.clip((rough * g) ** 2, MIN_ROUGHNESS, 1.0).astype(np.float32)
            if (rough * g).min() ** 2 < MIN_ROUGHNESS:
                self.note(ptr, f"roughness below {math.sqrt(MIN_ROUGHNESS):.3f} raised to it "
                          f"(GGX alpha {MIN_ROUGHNESS:g})", what)
            return self.baked(mr_tex, "roughness", alpha[..., None], name)
        alpha = rough * rough
        if alpha < MIN_ROUGHNESS:
            self.note(ptr, f"roughness {rough:g} raised to {math.sqrt(MIN_ROUGHNESS):.4f} "
                      f"(GGX alpha {MIN_ROUGHNESS:g}, the least rayfarm renders)", what)
            alpha = MIN_ROUGHNESS
        return alpha

    def opacity(self, mode: str, cutoff: float, alpha: float, img, tex, name: str, what: str,
                ptr: str):
        if mode == "OPAQUE":
            return None
        a = alpha if img is None or img.shape[2] not in (2, 4) else img[..., -1] * alpha
        if mode == "MASK":
            a = (np.asarray(a) >= cutoff).astype(np.float32)
            self.note(ptr, f"alphaMode MASK: opacity = 1 where alpha >= {cutoff:g}, else 0",
                      what)
        else:
            self.note(ptr, "alphaMode BLEND approximated as opacity = alpha (a stochastic mask, "
                      "as Mitsuba's mask)", what)
        if np.ndim(a) == 0:
            return None if float(a) >= 1 else float(a)
        if a.min() >= 1:
            return None
        return self.baked(tex, "opacity", np.asarray(a, np.float32)[..., None], name)

    def emission(self, m: dict, ptr: str, name: str, what: str, double: bool):
        factor = self.numbers(m, "emissiveFactor", ptr, 3, [0, 0, 0], 0, 1)
        strength = 1.0
        sx = self.extension(m, ptr, "KHR_materials_emissive_strength")
        if sx is not None:
            strength = self.number(sx, "emissiveStrength",
                                   f"{ptr}/extensions/KHR_materials_emissive_strength", 1.0, 0,
                                   MAX_RADIANCE)
        tex = self.texture_info(m, "emissiveTexture", ptr)
        rgb = np.asarray(factor) * strength
        if tex is not None and rgb.max() > 0:
            mean = _rgb(self.texels(tex, raw=False)).reshape(-1, 3).mean(axis=0)
            rgb = rgb * mean
            self.note(f"{ptr}/emissiveTexture", "approximated: the area light's radiance is "
                      f"emissiveFactor x the texture's mean ({', '.join(f'{c:.3g}' for c in mean)})",
                      what)
        if rgb.max() <= 0:
            return None
        if rgb.max() > MAX_RADIANCE:
            raise self.fail(f"emitted radiance {rgb.max():g} exceeds {MAX_RADIANCE:g}", ptr)
        if double:
            self.note(ptr, "emission from the front side only (rayfarm's area lights are "
                      "one-sided)", what)
        return [float(c) for c in rgb]

    # -- textures -------------------------------------------------------------

    def texture_info(self, o: dict, key: str, ptr: str) -> dict | None:
        """A textureInfo, resolved: texture and image indices, sampler, uv transform."""
        if key not in o:
            return None
        tptr = f"{ptr}/{key}"
        info = self.obj(o[key], tptr)
        ti = self.index(info, "index", tptr, "textures", required=True)
        tex_coord = self.get(info, "texCoord", tptr, "int", default=0)
        for field in ("scale", "strength"):
            if field in info:
                self.get(info, field, tptr, "number")
        tx = self.extension(info, tptr, "KHR_texture_transform")
        scale, offset = [1.0, 1.0], [0.0, 0.0]
        if tx is not None:
            xptr = f"{tptr}/extensions/KHR_texture_transform"
            offset = self.numbers(tx, "offset", xptr, 2, [0, 0], -MAX_COORDINATE, MAX_COORDINATE)
            scale = self.numbers(tx, "scale", xptr, 2, [1, 1], -MAX_COORDINATE, MAX_COORDINATE)
            rotation = self.number(tx, "rotation", xptr, 0.0)
            if rotation != 0:
                self.note(xptr, f"rotation {rotation:g} ignored (offset and scale are used)")
            tex_coord = self.get(tx, "texCoord", xptr, "int", default=tex_coord)
        self.other_extensions(info, tptr, ("KHR_texture_transform",), "")
        if tex_coord != 0:
            self.note(tptr, f"texCoord {tex_coord} approximated by TEXCOORD_0 (the only UV set "
                      "rayfarm reads)")
        t, texptr = self.item("textures", ti)
        source = self.index(t, "source", texptr, "images")
        if source is None:
            for ext in self.get(t, "extensions", texptr, "obj", default={}).values():
                if isinstance(ext, dict) and "source" in ext:
                    raise self.fail(f"the texture's image is only given by an extension "
                                    f"({', '.join(t['extensions'])}), which this importer "
                                    "does not read", texptr)
            raise self.fail("the texture has no source image", texptr)
        self.other_extensions(t, texptr, (), "")
        filt, wrap = "bilinear", True
        si = self.index(t, "sampler", texptr, "samplers")
        if si is not None:
            s, sptr = self.item("samplers", si)
            if self.get(s, "magFilter", sptr, "int") == FILTER_NEAREST:
                filt = "nearest"
            for w in ("wrapS", "wrapT"):
                mode = self.get(s, w, sptr, "int", default=WRAP_REPEAT)
                if mode != WRAP_REPEAT:
                    wrap = False
            if not wrap:
                self.note(sptr, "clamped or mirrored wrapping approximated by repeat")
        return {"image": source, "filter": filt, "uv_scale": scale, "uv_offset": offset,
                "ptr": tptr}

    def texels(self, info: dict, raw: bool) -> np.ndarray:
        key = (info["image"], raw)
        if key in self.images:
            return self.images[key]
        img, iptr = self.item("images", info["image"])
        uri = self.get(img, "uri", iptr, "str")
        if uri is not None and not uri.startswith("data:"):
            f = self.local_file(uri, f"{iptr}/uri")
            texels = self.decode(f, raw, iptr, f.relative_to(self.root).as_posix())
        else:
            if uri is not None:
                data, mime = self.data_uri(uri, f"{iptr}/uri")
            else:
                bv = self.index(img, "bufferView", iptr, "bufferViews", required=True)
                view, _, _ = self.view(bv)
                data = bytes(view)
                mime = self.get(img, "mimeType", iptr, "str", required=True)
            if mime not in IMAGE_SUFFIX:
                raise self.fail(f"image type {mime!r} is not read (PNG and JPEG are)", iptr)
            with tempfile.TemporaryDirectory(prefix="rayfarm-gltf-") as tmp:
                f = Path(tmp) / f"image{IMAGE_SUFFIX[mime]}"
                f.write_bytes(data)
                texels = self.decode(f, raw, iptr, f"{self.name}#{iptr}")
        texels = np.asarray(texels, dtype=np.float32)
        if texels.ndim == 2:
            texels = texels[..., None]
        if texels.ndim != 3 or texels.shape[2] not in (1, 2, 3, 4) or texels.size == 0:
            raise self.fail(f"unexpected image shape {texels.shape}", iptr)
        if not np.all(np.isfinite(texels)):
            raise self.fail("the image holds values that are not finite", iptr)
        self.images[key] = texels
        return texels

    def decode(self, f: Path, raw: bool, ptr: str, name: str) -> np.ndarray:
        self.count_bytes(f.stat().st_size, ptr)
        try:
            return _read_texture(f, raw, name)
        except SceneError as exc:
            raise self.fail(exc.message, ptr) from None

    def baked(self, info: dict, purpose: str, texels: np.ndarray, material: str) -> dict:
        """A bitmap texture entry for `texels` (the glTF factors already
        multiplied in), named after the material and its input."""
        self.texture_bytes += texels.size * 4
        if self.texture_bytes > MAX_TEXTURE_BYTES:
            raise self.fail(f"the textures of the scene's materials exceed {MAX_TEXTURE_BYTES} "
                            "bytes of texels", info["ptr"])
        blob = encode_texture(np.ascontiguousarray(texels, dtype=np.float32))
        digest = asset_digest(blob)
        self.assets[digest] = blob
        entry = {"type": "bitmap", "image": digest, "filter": info["filter"]}
        if info["uv_scale"] != [1.0, 1.0]:
            entry["uv_scale"] = info["uv_scale"]
        if info["uv_offset"] != [0.0, 0.0]:
            entry["uv_offset"] = info["uv_offset"]
        key = (digest, json.dumps(entry, sort_keys=True))
        if key not in self.texture_keys:
            name = f"{material}.{purpose}"
            while name in self.textures:
                name += "'"
            self.texture_keys[key] = name
            self.textures[name] = entry
        return {"texture": self.texture_keys[key]}

    # -- cameras, lights ------------------------------------------------------

    def camera(self, c: dict, cptr: str, world: np.ndarray, nptr: str) -> dict:
        p = self.obj(self.get(c, "perspective", cptr, "obj", required=True), f"{cptr}/perspective")
        pptr = f"{cptr}/perspective"
        yfov = self.number(p, "yfov", pptr, 0.0, 0, math.pi)
        if not math.radians(1e-3) <= yfov <= math.radians(179):
            raise self.fail(f"yfov must lie in (0, pi) radians, got {yfov:g}", f"{pptr}/yfov")
        aspect = self.get(p, "aspectRatio", pptr, "number")
        if aspect is not None and not 1e-3 <= aspect <= 1e3:
            raise self.fail(f"aspectRatio must lie in [0.001, 1000], got {aspect:g}",
                            f"{pptr}/aspectRatio")
        width, height = _resolution(aspect or 1.0)
        if aspect is None:
            self.note(pptr, f"no aspectRatio: the image is square ({width}x{height})")
        self.note(pptr, "znear/zfar ignored: rayfarm does not clip")
        return {"type": "perspective", "to_world": _camera_to_world(world, self, nptr),
                "fov": math.degrees(yfov), "fov_axis": "y", "width": width, "height": height}

    def default_camera(self, shapes: list[dict]) -> dict:
        lo = np.min([s["_bounds"][0] for s in shapes], axis=0)
        hi = np.max([s["_bounds"][1] for s in shapes], axis=0)
        centre = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
        distance = radius / math.sin(math.radians(DEFAULT_FOV) / 2)
        m = np.eye(4)
        m[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # looks along -z, +x to the right of the image
        m[:3, 3] = centre + [0.0, 0.0, distance]
        width, height = _resolution(1.0)
        return {"type": "perspective", "to_world": m.tolist(), "fov": DEFAULT_FOV,
                "fov_axis": "smaller", "width": width, "height": height}

    def punctual_lights(self) -> dict[int, Callable]:
        ext = self.extension(self.gltf, "", "KHR_lights_punctual")
        if ext is None:
            return {}
        xptr = "/extensions/KHR_lights_punctual"
        out = {}
        for i, raw in enumerate(self.get(ext, "lights", xptr, "list", default=[])):
            lptr = f"{xptr}/lights/{i}"
            light = self.obj(raw, lptr)
            ltype = self.get(light, "type", lptr, "str", required=True)
            if ltype not in ("point", "spot", "directional"):
                raise self.fail(f"unknown light type {ltype!r}", f"{lptr}/type")
            colour = self.numbers(light, "color", lptr, 3, [1, 1, 1], 0, 1)
            intensity = self.number(light, "intensity", lptr, 1.0, 0, math.inf)
            radiant = np.asarray(colour) * intensity / POINT_CANDELA_PER_WATT_SR
            if "range" in light:
                self.number(light, "range", lptr, 1.0, 0, math.inf)
                self.note(lptr, "range ignored: the light falls off with the inverse square "
                          "everywhere")
            out[i] = self.light_factory(ltype, radiant, lptr)
        return out

    def light_factory(self, ltype: str, radiant: np.ndarray, lptr: str) -> Callable:
        def place(world: np.ndarray, nptr: str) -> dict | None:
            if ltype == "directional":
                self.note(lptr, "ignored: rayfarm has no directional light yet")
                return None
            if ltype == "spot":
                self.note(lptr, "spot light approximated as a point light (its cone is "
                          "ignored)")
            if radiant.max() > MAX_RADIANCE:
                raise self.fail(f"intensity of {radiant.max():g} W/sr exceeds "
                                f"{MAX_RADIANCE:g}", lptr)
            position = world[:3, 3]
            if np.any(np.abs(position) > MAX_COORDINATE):
                raise self.fail(f"the light lies beyond +-{MAX_COORDINATE:g}", nptr)
            if radiant.max() <= 0:
                return None
            return {"type": "point", "position": [float(x) for x in position],
                    "intensity": [float(c) for c in radiant]}
        return place


# ----------------------------------------------------------------------------

def _show(value: Any) -> str:
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _nesting(value: Any) -> int:
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            deepest = max(deepest, depth)
            stack.extend((c, depth + 1) for c in (item.values() if isinstance(item, dict)
                                                   else item))
    return deepest


def _normalize(a: np.ndarray, ctype: int) -> np.ndarray:
    """glTF's normalized integers as floats (signed ones clamped at -1)."""
    scale = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}[ctype]
    return np.maximum(a.astype(np.float64) / scale, -1.0)


def _check_finite(imp: _Importer, arr: np.ndarray, ai: int, what: str) -> None:
    bad = ~np.all(np.isfinite(arr), axis=1)
    if np.any(bad):
        j = int(np.argmax(bad))
        raise imp.fail(f"{what} element {j} is not finite ({arr[j].tolist()})",
                       f"/accessors/{ai}")


def _rgb(texels: np.ndarray) -> np.ndarray:
    c = texels.shape[2]
    return texels[..., :3] if c >= 3 else np.repeat(texels[..., :1], 3, axis=2)


def _world_bounds(positions: np.ndarray, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    wv = positions @ world[:3, :3].T + world[:3, 3]
    return wv.min(axis=0), wv.max(axis=0)


def _resolution(aspect: float) -> tuple[int, int]:
    """(width, height) with the longer side DEFAULT_LONG_SIDE pixels."""
    if aspect >= 1:
        return DEFAULT_LONG_SIDE, max(1, round(DEFAULT_LONG_SIDE / aspect))
    return max(1, round(DEFAULT_LONG_SIDE * aspect)), DEFAULT_LONG_SIDE


def _camera_to_world(world: np.ndarray, imp: _Importer, nptr: str) -> list[list[float]]:
    """The Mitsuba-convention sensor matrix (looks along local +z, +y up, +x to
    the left) of a glTF camera node (looks along local -z, +y up, +x to the
    right): the node's rotation and translation, turned half a turn about y.
    Scale is dropped (it does not change a pinhole's picture); a mirror stays."""
    a = world[:3, :3]
    q, r = np.linalg.qr(a)
    q = q * np.sign(np.diag(r))[None, :]  # columns of `a`, orthonormalised in order
    scales = np.linalg.norm(a, axis=0)
    if not np.allclose(a, q * scales[None, :], atol=1e-6 * max(scales.max(), 1e-300)):
        imp.note(nptr, "the camera node's transform shears: its rotation part is used")
    m = np.eye(4)
    m[:3, :3] = q @ np.diag([-1.0, 1.0, -1.0])
    m[:3, 3] = world[:3, 3]
    return m.tolist()


def _description(asset: dict, name: str) -> str:
    parts = [f"glTF 2.0 scene {name}"]
    for key in ("generator", "copyright"):
        if isinstance(asset.get(key), str):
            parts.append(f"{key}: {asset[key][:300]}")
    return "; ".join(parts)
