"""Mitsuba XML scenes (the 0.5/0.6 dialect and the 2.x/3.x one) in.

    imported = import_mitsuba(Path("veach-bidir/scene.xml"))

The file is read with expat (line numbers for every element; DOCTYPE and
entity declarations refused, so no entity expansion and no external
entities), `<include>`s are spliced in, `$name`s substituted from the
`<default>`s, and property names of the old dialect (`toWorld`, `intIOR`)
turned into the new one (`to_world`, `int_ior`) as Mitsuba 3 upgrades them.
Then each object maps onto the native document: what rayfarm renders as
written maps silently; what it approximates or ignores gets a `ReportEntry`
naming the element, its file and line, and what was done instead.
docs/scene-format.md ("Mitsuba XML") has the whole mapping.

Refusals are `SceneError`s located at "file:line".
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from xml.parsers import expat

import numpy as np

from ..assets import asset_digest, encode_mesh
from ..errors import SceneError
from ..meshio import read_mesh
from ..primitives import world_mesh
from . import Imported, ReportEntry
from .spectra import blackbody, spectrum_to_rgb, srgb_to_linear, uniform_to_rgb

__all__ = ["import_mitsuba", "MAX_XML_BYTES", "MAX_ELEMENTS", "MAX_NESTING", "MAX_INCLUDE_DEPTH",
           "MAX_REF_DEPTH", "MAX_SHAPES", "UNBOUNDED_DEPTH"]

MAX_XML_BYTES = 32 * 1024 * 1024  # one XML file
MAX_ELEMENTS = 200_000  # elements over the scene and all its includes
MAX_NESTING = 32  # elements inside elements, per file
MAX_INCLUDE_DEPTH = 8  # includes inside includes
MAX_REF_DEPTH = 16  # objects inside objects (bsdf in twosided in mask ...), refs followed
MAX_SHAPES = 100_000  # shapes after instances are flattened (each instance copies its group)
# Mitsuba's max_depth -1 means unbounded; a job takes at most 64 bounces (spec.py).
UNBOUNDED_DEPTH = 64
# rayfarm renders no cut-outs yet: a mask's opacity is reported, not passed on
# (the native format refuses opacity other than 1 until the renderer has them).
OPACITY_MASKS = False
CYLINDER_SEGMENTS = 64

PROPERTY_TAGS = {"float", "integer", "boolean", "string", "rgb", "srgb", "spectrum", "blackbody",
                 "point", "vector", "transform"}
OBJECT_TAGS = {"bsdf", "texture", "shape", "emitter", "sensor", "film", "rfilter", "sampler",
               "integrator", "medium", "phase", "volume"}

# Mitsuba 3's table of named indices of refraction.
IOR_NAMES = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501,
    "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046,
    "sodium chloride": 1.544, "amber": 1.55, "pet": 1.575, "diamond": 2.419,
}
# RGB (eta, k) of the conductors scenes name most, as Mitsuba's RGB modes see them.
CONDUCTORS = {
    "Ag": ((0.155265, 0.116723, 0.138342), (4.82835, 3.12225, 2.14696)),
    "Al": ((1.65746, 0.880369, 0.521229), (9.22387, 6.26952, 4.837)),
    "Au": ((0.143119, 0.374957, 1.44248), (3.98316, 2.38572, 1.60322)),
    "Cu": ((0.200438, 0.924033, 1.10221), (3.91295, 2.45285, 2.14219)),
    "Cr": ((4.36968, 2.9167, 1.6547), (5.20643, 4.23136, 3.75495)),
}


class _Node:
    __slots__ = ("tag", "attrs", "file", "line", "children")

    def __init__(self, tag: str, attrs: dict, file: str, line: int):
        self.tag, self.attrs, self.file, self.line = tag, attrs, file, line
        self.children: list[_Node] = []

    @property
    def loc(self) -> str:
        return f"{self.file}:{self.line}"

    def describe(self) -> str:
        return " ".join([self.tag] + [f'{k}="{self.attrs[k]}"' for k in ("type", "name", "id")
                                      if k in self.attrs])


def _snake(name: str) -> str:
    """Mitsuba 3's upgrade of old property names: camelCase -> snake_case."""
    return re.sub(r"(?<=[a-z0-9])([A-Z]+)", lambda m: "_" + m.group(1).lower(), name).lower()


def _numbers(text: str, node: _Node, what: str) -> list[float]:
    if "$" in text:
        name = re.search(r"\$[A-Za-z_][A-Za-z0-9_]*", text)
        raise SceneError(f"{what}: the parameter {name.group(0) if name else '$'} has no value "
                         "(no <default> gives one)", node.loc)
    try:
        values = [float(t) for t in re.split(r"[,\s]+", text.strip()) if t]
    except ValueError:
        raise SceneError(f"{what}: expected numbers, got '{text[:60]}'", node.loc) from None
    if not all(math.isfinite(v) for v in values):
        raise SceneError(f"{what}: numbers must be finite, got '{text[:60]}'", node.loc)
    return values


def _parse_xml(path: Path, rel: str) -> _Node:
    """The element tree of one XML file, refusing what could attack the reader."""
    try:
        size = path.stat().st_size
        if size > MAX_XML_BYTES:
            raise SceneError(f"the XML file is {size} bytes; at most {MAX_XML_BYTES}", f"{rel}:1")
        data = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"cannot read {rel}: {exc.strerror}", rel) from None
    parser = expat.ParserCreate()
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    stack: list[_Node] = []
    top: list[_Node] = []
    count = [0]

    def refuse(what: str):
        def handler(*_args):
            raise SceneError(f"{what} are refused (entity expansion and external entities "
                             "could exhaust or leak the service)", f"{rel}:{parser.CurrentLineNumber}")
        return handler

    def start(tag, attrs):
        count[0] += 1
        if count[0] > MAX_ELEMENTS:
            raise SceneError(f"more than {MAX_ELEMENTS} elements", f"{rel}:{parser.CurrentLineNumber}")
        if len(stack) >= MAX_NESTING:
            raise SceneError(f"elements nest more than {MAX_NESTING} deep",
                             f"{rel}:{parser.CurrentLineNumber}")
        node = _Node(tag, attrs, rel, parser.CurrentLineNumber)
        (stack[-1].children if stack else top).append(node)
        stack.append(node)

    parser.StartDoctypeDeclHandler = refuse("DOCTYPE declarations")
    parser.EntityDeclHandler = refuse("entity declarations")
    parser.ExternalEntityRefHandler = refuse("external entities")
    parser.StartElementHandler = start
    parser.EndElementHandler = lambda tag: stack.pop()
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        raise SceneError(f"not well-formed XML: {expat.ErrorString(exc.code)}",
                         f"{rel}:{exc.lineno}") from None
    if not top:
        raise SceneError("the file has no root element", f"{rel}:1")
    return top[0]


def _rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    x, y, z = axis / np.linalg.norm(axis)
    t = math.radians(angle_deg)
    c, s = math.cos(t), math.sin(t)
    r = np.eye(4)
    r[:3, :3] = [[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                 [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                 [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]]
    return r


def look_at(origin, target, up) -> np.ndarray:
    """Mitsuba's look-at: columns left, up, forward (+z), origin."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    forward = target - origin
    if np.linalg.norm(forward) == 0:
        raise ValueError("origin and target coincide")
    forward = forward / np.linalg.norm(forward)
    left = np.cross(up, forward)
    if np.linalg.norm(left) < 1e-12:
        raise ValueError("up is parallel to the viewing direction")
    left = left / np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(forward, left), forward, origin
    return m


def _fresnel0(eta, k) -> list[float]:
    """A conductor's reflectance at normal incidence."""
    return [((n - 1) ** 2 + kk * kk) / ((n + 1) ** 2 + kk * kk) for n, kk in zip(eta, k)]


class _Obj:
    """One object element's properties and nested objects; every property
    read is marked, and `finish` reports the ones nobody read."""

    def __init__(self, imp: "_Importer", node: _Node):
        self.imp, self.node = imp, node
        self.type = node.attrs.get("type", "")
        self.props: dict[str, _Node] = {}
        self.objects: list[_Node] = []
        self.used: set[str] = set()
        for ch in node.children:
            # A named property; a texture (or a ref to one) with a name is a
            # parameter too, while other objects (a shape's bsdf, a twosided's
            # nested bsdf) are nested objects, named or not (Mitsuba 3's
            # exporters name them).
            target = imp.deref(ch) if ch.tag == "ref" else ch
            if ch.tag in PROPERTY_TAGS or (target.tag == "texture" and "name" in ch.attrs):
                if "name" not in ch.attrs:
                    raise SceneError(f"<{ch.tag}> needs a name attribute", ch.loc)
                key = _snake(ch.attrs["name"])
                if key in self.props:
                    imp.note(self.props[key], "given twice: ignored, the later value is used")
                self.props[key] = ch
            elif target.tag in OBJECT_TAGS:
                self.objects.append(target)
            else:
                imp.note(ch, "ignored (not an element Mitsuba defines here)")

    def has(self, key: str) -> bool:
        return key in self.props

    def take(self, key: str) -> _Node | None:
        self.used.add(key)
        return self.props.get(key)

    def float(self, key: str, default: float | None = None) -> float | None:
        n = self.take(key)
        return default if n is None else self.imp.float_of(n)

    def int(self, key: str, default: int | None = None) -> int | None:
        n = self.take(key)
        if n is None:
            return default
        v = self.imp.float_of(n)
        if v != int(v):
            raise SceneError(f"'{n.attrs.get('name')}' must be an integer", n.loc)
        return int(v)

    def bool(self, key: str, default: bool) -> bool:
        n = self.take(key)
        if n is None:
            return default
        value = n.attrs.get("value", "").strip().lower()
        if n.tag != "boolean" or value not in ("true", "false"):
            raise SceneError(f"'{n.attrs.get('name')}' must be <boolean value=\"true\"/> or "
                             f"\"false\", got <{n.tag} value=\"{value[:20]}\">", n.loc)
        return value == "true"

    def string(self, key: str, default: str | None = None) -> str | None:
        n = self.take(key)
        if n is None:
            return default
        if n.tag != "string" or "value" not in n.attrs:
            if n.tag in ("float", "integer") and "value" in n.attrs:
                return n.attrs["value"]  # a string parameter given as a number: its text
            raise SceneError(f"'{n.attrs.get('name')}' must be a <string value=...>", n.loc)
        return n.attrs["value"]

    def color(self, key: str, default, *, emitter: bool = False, bounded: bool = True,
              texture: bool = True):
        n = self.take(key)
        if n is None:
            return [float(c) for c in (default if isinstance(default, (list, tuple))
                                       else [default] * 3)]
        return self.imp.color_of(n, emitter=emitter, bounded=bounded, texture=texture)

    def scalar_or_texture(self, key: str, default: float):
        """A float, or a texture for inputs that may be textured (roughness, opacity)."""
        n = self.take(key)
        if n is None:
            return default
        if n.tag in ("float", "integer"):
            return self.imp.float_of(n)
        value = self.imp.color_of(n, emitter=False, bounded=True, texture=True)
        if isinstance(value, dict):
            return value
        return float(np.mean(value))

    def transform(self, key: str) -> np.ndarray:
        n = self.take(key)
        return np.eye(4) if n is None else self.imp.transform_of(n)

    def point(self, key: str, default) -> list[float]:
        n = self.take(key)
        return list(default) if n is None else self.imp.point_of(n)

    def ignore(self, key: str, reason: str | None = None) -> None:
        if key in self.props:
            self.used.add(key)
            if reason:
                self.imp.note(self.props[key], reason)

    def children(self, tag: str) -> list[_Node]:
        return [n for n in self.objects if n.tag == tag]

    def finish(self, used_objects: tuple[str, ...] = ()) -> None:
        what = f'a {self.node.tag} of type "{self.type}"' if self.type else f"a {self.node.tag}"
        for key, n in self.props.items():
            if key not in self.used:
                self.imp.note(n, f"ignored (rayfarm does not read this parameter of {what})")
        for n in self.objects:
            if n.tag not in used_objects:
                self.imp.note(n, f"ignored (rayfarm does not use a nested {n.tag} in {what})")


class _Importer:
    def __init__(self, path: Path, root: Path | None):
        self.path = Path(path)
        self.root = Path(root if root is not None else self.path.parent).resolve()
        self.main = self.path.resolve()
        if not self.main.is_relative_to(self.root):
            raise SceneError("the scene file lies outside its root folder", self.path.name)
        self.report: list[ReportEntry] = []
        self.params: dict[str, str] = {}
        self.include_stack: list[Path] = []
        self.elements = 0
        self.ids: dict[str, _Node] = {}
        self.assets: dict[str, bytes] = {}
        self.materials: dict[str, dict] = {}
        self.material_of: dict[int, str] = {}
        self.textures: dict[str, dict] = {}
        self.texture_of: dict[int, object] = {}
        self.mesh_cache: dict[tuple, tuple] = {}
        self.texture_cache: dict[tuple, str] = {}
        self.map_stack: list[_Node] = []
        self.bounds: list[np.ndarray] = []
        self.groups: dict[int, list[dict]] = {}
        self.planar: list[tuple[dict, _Node]] = []
        self.flattened = 0  # shapes instances have copied  # rectangles and disks, to check their sides

    # -- reporting and locations ---------------------------------------------------------
    def note(self, node: _Node, action: str) -> None:
        element = node.describe()
        if "id" not in node.attrs:  # name the enclosing object that has one, for context
            owner = next((n for n in reversed(self.map_stack) if n is not node and "id" in n.attrs),
                         None)
            if owner is not None:
                element += f" (in {owner.describe()})"
        self.report.append(ReportEntry(element, node.file, node.line, action))

    def rel(self, path: Path) -> str:
        return path.relative_to(self.root).as_posix()

    def find_file(self, name: str, node: _Node, what: str) -> Path:
        """A file a scene names: relative to the naming file's folder, or else
        to the main scene's; inside the root either way."""
        name = name.replace("\\", "/")
        if not name:
            raise SceneError(f"{what}: empty file name", node.loc)
        if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
            raise SceneError(f"{what} '{name}' is an absolute path; a scene names its files "
                             "relative to its folder", node.loc)
        bases = [(self.root / node.file).parent, self.main.parent]
        for base in dict.fromkeys(bases):
            candidate = (base / name).resolve()
            if not candidate.is_relative_to(self.root):
                raise SceneError(f"{what} '{name}' lies outside the scene's folder", node.loc)
            if candidate.is_file():
                return candidate
        hint = ""
        parent = (bases[0] / name).parent
        if parent.is_dir():
            lower = Path(name).name.lower()
            near = [p.name for p in parent.iterdir() if p.name.lower() == lower]
            if near:
                hint = f" (there is '{near[0]}': names are case-sensitive)"
        raise SceneError(f"{what} '{name}' not found{hint}", node.loc)

    # -- includes, defaults, substitution --------------------------------------------------
    def substitute(self, text: str) -> str:
        return re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)",
                      lambda m: self.params.get(m.group(1), m.group(0)), text)

    def expand(self, node: _Node) -> list[_Node]:
        self.elements += 1
        if self.elements > MAX_ELEMENTS:
            raise SceneError(f"more than {MAX_ELEMENTS} elements with the includes", node.loc)
        attrs = {k: self.substitute(v) for k, v in node.attrs.items()}
        if node.tag == "default":
            if "name" not in attrs or "value" not in attrs:
                raise SceneError("<default> needs a name and a value", node.loc)
            self.params.setdefault(attrs["name"], attrs["value"])
            return []
        if node.tag == "include":
            if "filename" not in attrs:
                raise SceneError("<include> needs a filename", node.loc)
            path = self.find_file(attrs["filename"], node, "included file")
            if path in self.include_stack or path == self.main:
                chain = " -> ".join(self.rel(p) for p in [self.main, *self.include_stack, path])
                raise SceneError(f"include cycle: {chain}", node.loc)
            if len(self.include_stack) >= MAX_INCLUDE_DEPTH:
                raise SceneError(f"includes nest more than {MAX_INCLUDE_DEPTH} deep", node.loc)
            sub = _parse_xml(path, self.rel(path))
            if sub.tag != "scene":
                raise SceneError(f"an included file's root must be <scene>, not <{sub.tag}>",
                                 sub.loc)
            self.include_stack.append(path)
            out = [n for ch in sub.children for n in self.expand(ch)]
            self.include_stack.pop()
            return out
        new = _Node(node.tag, attrs, node.file, node.line)
        new.children = [n for ch in node.children for n in self.expand(ch)]
        if "id" in attrs and node.tag != "ref":
            if attrs["id"] in self.ids:
                raise SceneError(f"id '{attrs['id']}' is defined twice (first at "
                                 f"{self.ids[attrs['id']].loc})", node.loc)
            self.ids[attrs["id"]] = new
        return [new]

    def deref(self, ref: _Node) -> _Node:
        rid = ref.attrs.get("id")
        if rid not in self.ids:
            raise SceneError(f"<ref> to an unknown id '{rid}'", ref.loc)
        return self.ids[rid]

    def enter(self, node: _Node) -> None:
        """Guard against objects that contain themselves (by refs) or nest too deep."""
        if any(n is node for n in self.map_stack):
            chain = " -> ".join(n.describe() for n in [*self.map_stack, node])
            raise SceneError(f"reference cycle: {chain}", node.loc)
        if len(self.map_stack) >= MAX_REF_DEPTH:
            raise SceneError(f"objects nest (through refs) more than {MAX_REF_DEPTH} deep",
                             node.loc)
        self.map_stack.append(node)

    # -- values ----------------------------------------------------------------------------
    def float_of(self, n: _Node) -> float:
        if n.tag == "ref":
            raise SceneError("expected a number, got a reference", n.loc)
        if n.tag not in ("float", "integer") or "value" not in n.attrs:
            raise SceneError(f"'{n.attrs.get('name')}' must be a <float value=...>", n.loc)
        values = _numbers(n.attrs["value"], n, f"'{n.attrs.get('name')}'")
        if len(values) != 1:
            raise SceneError(f"'{n.attrs.get('name')}' must be one number", n.loc)
        return values[0]

    def point_of(self, n: _Node) -> list[float]:
        if n.tag not in ("point", "vector"):
            raise SceneError(f"'{n.attrs.get('name')}' must be a <point> or <vector>", n.loc)
        if "value" in n.attrs:
            values = _numbers(n.attrs["value"], n, "value")
            if len(values) == 1:
                values = values * 3
            if len(values) != 3:
                raise SceneError("a point needs 3 numbers", n.loc)
            return values
        return [(_numbers(n.attrs[a], n, a) or [0.0])[0] if a in n.attrs else 0.0 for a in "xyz"]

    def color_of(self, n: _Node, *, emitter: bool, bounded: bool, texture: bool):
        name = n.attrs.get("name", "")
        if n.tag in ("texture", "ref"):
            target = self.deref(n) if n.tag == "ref" else n
            if target.tag != "texture":
                raise SceneError(f"'{name}' refers to a {target.tag}, not a texture", n.loc)
            if not texture:
                self.note(n, "approximated: a texture here is not supported; white (1) is used")
                return [1.0, 1.0, 1.0]
            return self.texture(target)
        if n.tag in ("float", "integer"):
            rgb = [self.float_of(n)] * 3
        elif n.tag in ("rgb", "srgb"):
            text = n.attrs.get("value", "").strip()
            if text.startswith("#"):
                if not re.fullmatch(r"#[0-9a-fA-F]{6}", text):
                    raise SceneError(f"'{name}': a hex colour is #rrggbb, got '{text[:20]}'", n.loc)
                rgb = [srgb_to_linear(int(text[i:i + 2], 16) / 255) for i in (1, 3, 5)]
            else:
                rgb = _numbers(text, n, f"'{name}'")
                if len(rgb) == 1:
                    rgb = rgb * 3
                if len(rgb) != 3:
                    raise SceneError(f"'{name}': a colour needs 3 numbers", n.loc)
                if n.tag == "srgb":
                    rgb = [srgb_to_linear(c) for c in rgb]
        elif n.tag == "spectrum":
            rgb = self.spectrum_of(n, emitter=emitter, bounded=bounded)
        elif n.tag == "blackbody":
            temp = n.attrs.get("temperature", "").strip().rstrip("kK")
            t = _numbers(temp, n, "temperature")
            if len(t) != 1 or not 1.0 <= t[0] <= 1e5:
                raise SceneError("a blackbody needs a temperature in kelvin (1 to 1e5)", n.loc)
            scale = _numbers(n.attrs.get("scale", n.attrs.get("multiplier", "1")), n, "scale")[0]
            wl, values = blackbody(t[0])
            rgb = [c * scale for c in spectrum_to_rgb(wl, values, emitter=True, bounded=False)]
            self.note(n, "converted to RGB by integrating Planck's law against the CIE 1931 "
                         "curves (Mitsuba 3 renders black bodies only in its spectral modes)")
        else:
            raise SceneError(f"'{name}' must be a colour (rgb, srgb, spectrum, float) or a "
                             f"texture, not <{n.tag}>", n.loc)
        if bounded and not emitter and any(c < 0 or c > 1 for c in rgb):
            self.note(n, f"clamped to [0, 1]: a reflectance of {rgb} would create energy")
            rgb = [min(max(c, 0.0), 1.0) for c in rgb]
        elif any(c < 0 for c in rgb):
            self.note(n, "negative components clamped to 0")
            rgb = [max(c, 0.0) for c in rgb]
        return [float(c) for c in rgb]

    def spectrum_of(self, n: _Node, *, emitter: bool, bounded: bool) -> list[float]:
        if "filename" in n.attrs:
            path = self.find_file(n.attrs["filename"], n, "spectrum file")
            if path.stat().st_size > 1 << 20:
                raise SceneError("a spectrum file is at most 1 MiB", n.loc)
            pairs = []
            for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                line = line.split("#")[0].strip()
                if line:
                    v = _numbers(line, n, f"{self.rel(path)} line {i}")
                    if len(v) != 2:
                        raise SceneError(f"{self.rel(path)} line {i}: expected 'wavelength value'",
                                         n.loc)
                    pairs.append(v)
            wl, values = [p[0] for p in pairs], [p[1] for p in pairs]
        elif "wavelengths" in n.attrs:
            wl = _numbers(n.attrs["wavelengths"], n, "wavelengths")
            values = _numbers(n.attrs.get("values", ""), n, "values")
        else:
            text = n.attrs.get("value", "").strip()
            if ":" not in text:
                v = _numbers(text, n, "value")
                if len(v) != 1:
                    raise SceneError("a spectrum is one value or wavelength:value pairs", n.loc)
                return uniform_to_rgb(v[0], emitter=emitter)
            wl, values = [], []
            for token in re.split(r"[,\s]+", text):
                if not token:
                    continue
                parts = token.split(":")
                if len(parts) != 2:
                    raise SceneError(f"spectrum: expected wavelength:value, got '{token[:30]}'",
                                     n.loc)
                a, b = _numbers(parts[0], n, "wavelength"), _numbers(parts[1], n, "value")
                wl.append(a[0])
                values.append(b[0])
        if len(wl) != len(values) or len(wl) < 2:
            raise SceneError("a spectrum needs at least two wavelength:value pairs", n.loc)
        if any(b <= a for a, b in zip(wl, wl[1:])):
            raise SceneError("a spectrum's wavelengths must increase", n.loc)
        return spectrum_to_rgb(wl, values, emitter=emitter, bounded=bounded and not emitter)

    def transform_of(self, n: _Node) -> np.ndarray:
        if n.tag != "transform":
            raise SceneError(f"'{n.attrs.get('name')}' must be a <transform>", n.loc)
        m = np.eye(4)
        for op in n.children:
            a = op.attrs
            tag = op.tag.lower()

            def comps(default: float) -> list[float]:
                if "value" in a:
                    v = _numbers(a["value"], op, "value")
                    if len(v) == 1:
                        return v * 3
                    if len(v) != 3:
                        raise SceneError(f"<{op.tag}> value needs 1 or 3 numbers", op.loc)
                    return v
                return [_numbers(a[c], op, c)[0] if c in a else default for c in "xyz"]

            if tag == "translate":
                t = np.eye(4)
                t[:3, 3] = comps(0.0)
            elif tag == "scale":
                t = np.diag(comps(1.0) + [1.0])
            elif tag == "rotate":
                axis = np.asarray(comps(0.0) if "value" in a else
                                  [_numbers(a[c], op, c)[0] if c in a else 0.0 for c in "xyz"])
                angle = _numbers(a.get("angle", "0"), op, "angle")[0]
                if not np.linalg.norm(axis) > 0:
                    raise SceneError("<rotate> needs a non-zero axis (x, y, z)", op.loc)
                t = _rotation(axis, angle)
            elif tag == "matrix":
                v = _numbers(a.get("value", ""), op, "matrix")
                if len(v) == 9:
                    t = np.eye(4)
                    t[:3, :3] = np.reshape(v, (3, 3))
                elif len(v) == 16:
                    t = np.reshape(v, (4, 4))
                else:
                    raise SceneError(f"<matrix> needs 9 or 16 numbers, got {len(v)}", op.loc)
            elif tag == "lookat":
                try:
                    pts = [_numbers(a.get(k, d), op, k) for k, d in
                           (("origin", "0 0 0"), ("target", "0 0 1"), ("up", "0 1 0"))]
                    if any(len(p) != 3 for p in pts):
                        raise ValueError("origin, target and up need 3 numbers each")
                    t = look_at(*pts)
                except ValueError as exc:
                    raise SceneError(f"<lookat>: {exc}", op.loc) from None
            else:
                raise SceneError(f"unknown transform operation <{op.tag}> (allowed: translate, "
                                 "rotate, scale, matrix, lookat)", op.loc)
            m = t @ m
        if not np.all(np.isfinite(m)):
            raise SceneError("the transform is not finite", n.loc)
        return m

    # -- textures --------------------------------------------------------------------------
    def _add_texture(self, node: _Node, entry: dict) -> str:
        """The texture's name; an identical one already there is shared."""
        for name, other in self.textures.items():
            if other == entry:
                return name
        base = node.attrs.get("id") or f"texture@{node.loc}"
        name, i = base, 1
        while name in self.textures:
            i += 1
            name = f"{base}#{i}"
        self.textures[name] = entry
        return name

    def _uv(self, obj: _Obj, entry: dict) -> None:
        su, sv = obj.float("uscale", 1.0), obj.float("vscale", 1.0)
        ou, ov = obj.float("uoffset", 0.0), obj.float("voffset", 0.0)
        if obj.has("to_uv"):
            m = obj.transform("to_uv")
            if abs(m[0, 1]) > 1e-12 or abs(m[1, 0]) > 1e-12:
                self.note(obj.props["to_uv"], "approximated: only the scale and offset of "
                                             "to_uv are used (its rotation or shear is dropped)")
            su, sv, ou, ov = su * m[0, 0], sv * m[1, 1], ou + m[0, 3], ov + m[1, 3]
        if (su, sv) != (1.0, 1.0):
            entry["uv_scale"] = [su, sv]
        if (ou, ov) != (0.0, 0.0):
            entry["uv_offset"] = [ou, ov]

    def texture(self, node: _Node):
        """{"texture": name} for a bitmap or checkerboard; a constant colour
        (reported) for a texture rayfarm has no equivalent of."""
        key = id(node)
        if key in self.texture_of:
            return self.texture_of[key]
        self.enter(node)
        try:
            result = self._texture(node)
        finally:
            self.map_stack.pop()
        self.texture_of[key] = result
        return result

    def _texture(self, node: _Node):
        obj = _Obj(self, node)
        t = obj.type
        if t == "bitmap":
            fname = obj.string("filename")
            if fname is None:
                raise SceneError("a bitmap texture needs a filename", node.loc)
            path = self.find_file(fname, obj.props["filename"], "texture file")
            raw = obj.bool("raw", False)
            gamma = obj.float("gamma", None)
            if gamma is not None:
                raw = gamma == 1.0
                if gamma not in (1.0, -1.0):
                    self.note(obj.props["gamma"], "approximated: the file is decoded as sRGB")
            entry: dict = {"type": "bitmap"}
            filt = (obj.string("filter_type", "bilinear") or "").lower()
            if filt == "nearest":
                entry["filter"] = "nearest"
            else:
                entry["filter"] = "bilinear"
                if filt != "bilinear":
                    self.note(obj.props["filter_type"],
                              f"approximated: filter_type '{filt}' rendered as bilinear")
            for key in ("wrap_mode", "wrap_mode_u", "wrap_mode_v"):
                mode = obj.string(key, "repeat")
                if mode != "repeat":
                    self.note(obj.props[key], f"approximated: wrap mode '{mode}' rendered as "
                                              "repeat")
            self._uv(obj, entry)
            entry.update(self._image(path, raw))
            for key in ("max_anisotropy", "cache", "channel", "format", "accel"):
                obj.ignore(key, "ignored (no effect on rayfarm's filtering)" if key != "channel"
                           else "ignored: every channel of the image is used")
            obj.finish()
            return {"texture": self._add_texture(node, entry)}
        if t == "checkerboard":
            entry = {"type": "checkerboard",
                     "color0": obj.color("color0", 0.4, texture=False),
                     "color1": obj.color("color1", 0.2, texture=False)}
            self._uv(obj, entry)
            obj.finish()
            return {"texture": self._add_texture(node, entry)}
        if t == "scale":
            inner = obj.children("texture") or [self.deref(n) for n in obj.props.values()
                                                if n.tag == "ref"]
            self.note(node, "approximated: the scale factor is ignored, the nested texture is "
                            "used as is")
            for key in list(obj.props):
                obj.ignore(key)
            if inner:
                return self.texture(inner[0])
            return [0.5, 0.5, 0.5]
        self.note(node, f"approximated as a constant grey 0.5: rayfarm has no '{t}' texture")
        for key in list(obj.props):
            obj.ignore(key)
        return [0.5, 0.5, 0.5]

    def _image(self, path: Path, raw: bool) -> dict:
        """The texture's image as an asset, or (until the texture reader and
        the asset encoding are there) its file, relative to the root."""
        try:
            from ..assets import asset_digest, encode_texture  # type: ignore[attr-defined]
            from ..textures import read_texture  # type: ignore[import-not-found]
        except ImportError:
            return {"file": self.rel(path), **({"raw": True} if raw else {})}
        key = (path, raw)
        if key not in self.texture_cache:
            blob = encode_texture(read_texture(path, raw=raw, name=self.rel(path)))
            digest = asset_digest(blob)
            self.assets[digest] = blob
            self.texture_cache[key] = digest
        return {"image": self.texture_cache[key]}

    # -- BSDFs -----------------------------------------------------------------------------
    def material(self, node: _Node) -> str:
        """The name of the native material a bsdf element maps to."""
        key = id(node)
        if key not in self.material_of:
            mat = self.bsdf(node)
            base = node.attrs.get("id") or f"bsdf@{node.loc}"
            name, i = base, 1
            while name in self.materials:
                i += 1
                name = f"{base}#{i}"
            self.materials[name] = mat
            self.material_of[key] = name
        return self.material_of[key]

    def bsdf(self, node: _Node) -> dict:
        self.enter(node)
        try:
            return self._bsdf(node)
        finally:
            self.map_stack.pop()

    def _nested_bsdf(self, obj: _Obj, node: _Node) -> tuple[dict, list[_Node]]:
        inner = obj.children("bsdf")
        if not inner:
            raise SceneError(f"a {obj.type} bsdf needs a nested bsdf", node.loc)
        return self.bsdf(inner[0]), inner

    def _bsdf(self, node: _Node) -> dict:
        obj = _Obj(self, node)
        t = obj.type
        if t == "twosided":
            mat, inner = self._nested_bsdf(obj, node)
            if len(inner) > 1:
                self.note(inner[1], "approximated: the back side uses the front side's bsdf "
                                    "(rayfarm's two-sided materials are the same on both sides)")
            mat = dict(mat)
            if mat["type"] != "dielectric":
                mat["twosided"] = True
            obj.finish(("bsdf",))
            return mat
        if t == "mask":
            opacity = obj.scalar_or_texture("opacity", 0.5)
            mat, inner = self._nested_bsdf(obj, node)
            if OPACITY_MASKS:
                mat = dict(mat)
                mat["opacity"] = opacity
            else:
                self.note(node, "approximated: the opacity mask is ignored, the surface renders "
                                "solid (rayfarm does not render cut-outs yet)")
            obj.finish(("bsdf",))
            return mat
        if t in ("bumpmap", "normalmap", "coating", "roughcoating"):
            mat, _ = self._nested_bsdf(obj, node)
            what = {"bumpmap": "the bump map", "normalmap": "the normal map"}.get(
                t, "the dielectric coating")
            self.note(node, f"approximated: {what} is ignored, the nested bsdf renders without it")
            for key in list(obj.props):
                obj.ignore(key)
            obj.finish(("bsdf", "texture"))
            return mat
        if t == "blendbsdf":
            inner = obj.children("bsdf")
            if len(inner) != 2:
                raise SceneError("a blendbsdf needs two nested bsdfs", node.loc)
            weight = obj.scalar_or_texture("weight", 0.5)
            w = 0.5 if isinstance(weight, dict) else weight
            pick = 1 if w > 0.5 else 0
            self.note(node, f"approximated by its {'second' if pick else 'first'} bsdf alone "
                            f"(blend weight {'textured' if isinstance(weight, dict) else w})")
            mat = self.bsdf(inner[pick])
            obj.finish(("bsdf",))
            return mat
        if t in ("diffuse", "roughdiffuse"):
            mat = {"type": "diffuse", "albedo": obj.color("reflectance", 0.5)}
            if t == "roughdiffuse":
                alpha = obj.scalar_or_texture("alpha", 0.2)
                obj.ignore("use_fast_approx")
                self.note(node, "approximated as diffuse (Lambertian, reflectance = reflectance): "
                                f"the Oren-Nayar roughness alpha = {alpha} is ignored")
            obj.finish()
            return mat
        if t in ("plastic", "roughplastic", "pplastic"):
            mat = {"type": "diffuse", "albedo": obj.color("diffuse_reflectance", 0.5)}
            for key in ("int_ior", "ext_ior", "nonlinear", "alpha", "distribution",
                        "specular_reflectance", "sample_visible"):
                obj.ignore(key)
            self.note(node, "approximated as diffuse (reflectance = diffuse_reflectance): the "
                            "specular coating is dropped")
            obj.finish()
            return mat
        if t in ("conductor", "roughconductor"):
            return self._conductor(obj, node)
        if t in ("dielectric", "roughdielectric", "thindielectric"):
            return self._dielectric(obj, node)
        if t == "null":
            obj.finish()
            return {"type": "null"}  # the shape decides: left out, or a black emitter
        if t == "principled":
            base = obj.color("base_color", 0.5)
            metallic = obj.float("metallic", 0.0)
            rough = obj.float("roughness", 0.5)
            for key in list(obj.props):
                obj.ignore(key)
            if metallic > 0.5:
                alpha = min(max(rough * rough, 1e-3), 1.0)
                self.note(node, f"approximated as glossy (specular = base_color, roughness = "
                                f"roughness^2 = {alpha:g}): metallic {metallic} > 0.5")
                return {"type": "glossy", "specular": base, "roughness": alpha}
            self.note(node, "approximated as diffuse (reflectance = base_color): "
                            f"metallic {metallic} <= 0.5; the specular lobes are dropped")
            return {"type": "diffuse", "albedo": base}
        for key in list(obj.props):
            obj.ignore(key)
        self.note(node, f"approximated as diffuse (reflectance 0.5): rayfarm has no '{t}' bsdf")
        return {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}

    def _ior(self, obj: _Obj, key: str, default: str) -> float:
        n = obj.take(key)
        if n is None:
            return IOR_NAMES[default]
        if n.tag == "string":
            name = n.attrs.get("value", "").strip().lower()
            if name not in IOR_NAMES:
                raise SceneError(f"unknown index of refraction '{name}' (named ones: "
                                 f"{', '.join(sorted(IOR_NAMES))})", n.loc)
            return IOR_NAMES[name]
        v = self.float_of(n)
        if not v > 0:
            raise SceneError("an index of refraction must be > 0", n.loc)
        return v

    def _dielectric(self, obj: _Obj, node: _Node) -> dict:
        ior = self._ior(obj, "int_ior", "bk7") / self._ior(obj, "ext_ior", "air")
        notes = []
        if obj.type != "dielectric":
            obj.ignore("alpha")
            obj.ignore("alpha_u")
            obj.ignore("alpha_v")
            obj.ignore("distribution")
            obj.ignore("sample_visible")
            notes.append("a thin sheet rendered as the surface of a solid"
                         if obj.type == "thindielectric" else "its roughness is ignored")
        for key in ("specular_reflectance", "specular_transmittance"):
            n = obj.take(key)
            if n is not None and self.color_of(n, emitter=False, bounded=False,
                                               texture=True) != [1.0, 1.0, 1.0]:
                notes.append(f"{key} is ignored (rayfarm's glass reflects and transmits "
                             "all it does not absorb: none)")
        if ior < 1.0:
            notes.append(f"the relative index {ior:g} < 1 is inverted to {1 / ior:g}")
            ior = 1.0 / ior
        if ior > 4.0:
            notes.append(f"the relative index {ior:g} is clamped to 4")
            ior = 4.0
        if notes:
            self.note(node, f"approximated as smooth dielectric (ior = int_ior / ext_ior = "
                            f"{ior:g}): " + "; ".join(notes))
        obj.finish()
        return {"type": "dielectric", "ior": ior}

    def _conductor(self, obj: _Obj, node: _Node) -> dict:
        spec = obj.color("specular_reflectance", 1.0)
        notes = []
        material = obj.string("material", "none")
        ext = obj.float("ext_eta", 1.0) if not obj.has("ext_eta") or \
            obj.props["ext_eta"].tag != "string" else self._ior(obj, "ext_eta", "air")
        if obj.has("eta") or obj.has("k"):
            eta = obj.color("eta", 0.0, bounded=False, texture=False)
            k = obj.color("k", 1.0, bounded=False, texture=False)
            f0 = _fresnel0([e / ext for e in eta], [kk / ext for kk in k])
            notes.append(f"the conductor's Fresnel term of eta, k is approximated by its "
                         f"reflectance at normal incidence {[round(f, 4) for f in f0]}")
        elif material == "none":
            f0 = [1.0, 1.0, 1.0]
        elif material in CONDUCTORS:
            eta, k = CONDUCTORS[material]
            f0 = _fresnel0([e / ext for e in eta], [kk / ext for kk in k])
            notes.append(f"material '{material}': its Fresnel term is approximated by the "
                         f"reflectance at normal incidence {[round(f, 4) for f in f0]}")
        else:
            f0 = [1.0, 1.0, 1.0]
            notes.append(f"unknown conductor material '{material}' (known: none, "
                         f"{', '.join(sorted(CONDUCTORS))}): rendered as a perfect reflector")
        if isinstance(spec, dict):
            colour = spec
            if f0 != [1.0, 1.0, 1.0]:
                notes.append("the textured specular_reflectance is not scaled by the Fresnel "
                             "reflectance")
        else:
            colour = [min(max(s * f, 0.0), 1.0) for s, f in zip(spec, f0)]
        if obj.type == "conductor":
            mat = {"type": "mirror", "tint": colour}
            kind = "mirror (tint = specular_reflectance x reflectance)"
        else:
            distribution = (obj.string("distribution", "beckmann") or "").lower()
            obj.ignore("sample_visible")
            if obj.has("alpha_u") or obj.has("alpha_v"):
                au, av = obj.float("alpha_u", 0.1), obj.float("alpha_v", 0.1)
                alpha = math.sqrt(au * av)
                obj.ignore("alpha")
                if au != av:
                    notes.append(f"the anisotropic roughness ({au}, {av}) is rendered isotropic "
                                 f"with alpha = sqrt(alpha_u alpha_v) = {alpha:g}")
            else:
                alpha = obj.scalar_or_texture("alpha", 0.1)
            if distribution != "ggx":
                notes.append(f"the {distribution} distribution is rendered as GGX of the same alpha")
            if isinstance(alpha, (int, float)) and alpha < 1e-3:
                mat = {"type": "mirror", "tint": colour if isinstance(colour, list) else
                       [1.0, 1.0, 1.0]}
                kind = "mirror"
                notes.append(f"alpha {alpha:g} is below rayfarm's smallest roughness 0.001")
            else:
                if isinstance(alpha, (int, float)) and alpha > 1.0:
                    notes.append(f"alpha {alpha:g} is clamped to 1")
                    alpha = 1.0
                mat = {"type": "glossy", "specular": colour, "roughness": alpha}
                kind = "glossy (GGX, specular = specular_reflectance x reflectance)"
        if notes:
            self.note(node, f"approximated as {kind}: " + "; ".join(notes))
        obj.finish()
        return mat

    # -- shapes ----------------------------------------------------------------------------
    def _track_bounds(self, lo, hi, m: np.ndarray) -> None:
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])], dtype=np.float64)
        self.bounds.append(corners @ m[:3, :3].T + m[:3, 3])

    def _mesh(self, path: Path, fmt: str, shape_index: int, flip_uv: bool) -> tuple:
        """(digest, lo, hi, face normals?, reader's notes) of a mesh file, as an asset."""
        key = (path, fmt, shape_index, flip_uv)
        if key not in self.mesh_cache:
            mesh = read_mesh(path, fmt=fmt, shape_index=shape_index, label=self.rel(path))
            uvs = mesh.uvs
            if flip_uv and uvs is not None:
                uvs = np.array(uvs, dtype=np.float64)
                uvs[:, 1] = 1.0 - uvs[:, 1]
            blob = encode_mesh(mesh.positions, mesh.faces, mesh.normals, uvs)
            digest = asset_digest(blob)
            self.assets[digest] = blob
            pos = np.asarray(mesh.positions)
            self.mesh_cache[key] = (digest, pos.min(axis=0), pos.max(axis=0), mesh.face_normals,
                                    list(mesh.notes))
        return self.mesh_cache[key]

    def shape(self, node: _Node) -> list[dict]:
        self.enter(node)
        try:
            return self._shape(node)
        finally:
            self.map_stack.pop()

    def _shape(self, node: _Node) -> list[dict]:
        obj = _Obj(self, node)
        t = obj.type
        m = obj.transform("to_world")
        if t == "shapegroup":
            shapes = [s for ch in obj.children("shape") for s in self.shape(ch)]
            self.groups[id(node)] = shapes
            obj.finish(("shape",))
            return []
        if t == "instance":
            refs = obj.children("shape")
            if not refs or refs[0].attrs.get("type") != "shapegroup":
                raise SceneError("an instance needs a <ref> to a shapegroup", node.loc)
            group = refs[0]
            if id(group) not in self.groups:
                self.shape(group)
            self.flattened += len(self.groups[id(group)])
            if self.flattened > MAX_SHAPES:
                raise SceneError(f"instances flatten into more than {MAX_SHAPES} shapes",
                                 node.loc)
            out = []
            for s in self.groups[id(group)]:
                s = dict(s)
                s["to_world"] = (m @ np.asarray(s["to_world"])).tolist()
                out.append(s)
            obj.finish(("shape",))
            return out
        out: dict = {}
        bsdfs = obj.children("bsdf")
        if bsdfs:
            out["material"] = self.material(bsdfs[0])
            for extra in bsdfs[1:]:
                self.note(extra, "ignored: a shape has one bsdf, the first is used")
        else:
            if "default-diffuse" not in self.materials:
                self.materials["default-diffuse"] = {"type": "diffuse", "albedo": [0.5] * 3}
            out["material"] = "default-diffuse"
        for em in obj.children("emitter"):
            emitter = self.area_emitter(em)
            if emitter is not None:
                out["emitter"] = emitter
        for ch in obj.children("medium"):
            self.note(ch, "ignored: rayfarm renders no participating media")
        if self.materials[out["material"]]["type"] == "null":
            if "emitter" not in out:
                self.note(node, "left out: its null bsdf makes it invisible")
                for key in list(obj.props):
                    obj.ignore(key)
                obj.finish(("bsdf", "emitter", "medium", "texture"))
                return []
            black = f"{out['material']} (black)"
            self.materials[black] = {"type": "diffuse", "albedo": [0.0, 0.0, 0.0]}
            self.note(bsdfs[0], "approximated: an emitter with a null bsdf is a black diffuse "
                                "surface (it blocks the light that Mitsuba lets through it)")
            out["material"] = black
        if "id" in node.attrs:
            out["name"] = node.attrs["id"]
        flip = obj.bool("flip_normals", False)
        if t in ("rectangle", "cube", "disk"):
            out["type"] = t
            self._track_bounds([-1, -1, -1], [1, 1, 1], m)
        elif t == "sphere":
            center = obj.point("center", [0.0, 0.0, 0.0])
            radius = obj.float("radius", 1.0)
            mtm = m[:3, :3].T @ m[:3, :3]
            if not np.allclose(mtm, np.eye(3) * mtm[0, 0], rtol=1e-6, atol=1e-12):
                raise SceneError("a sphere's to_world must be a rotation, a uniform scale and a "
                                 "translation (Mitsuba refuses others too)", node.loc)
            out.update({"type": "sphere", "center": center, "radius": radius})
            self._track_bounds(np.subtract(center, radius), np.add(center, radius), m)
        elif t in ("obj", "ply", "serialized"):
            fname = obj.string("filename")
            if fname is None:
                raise SceneError(f"a {t} shape needs a filename", node.loc)
            path = self.find_file(fname, obj.props["filename"], "mesh file")
            shape_index = obj.int("shape_index", 0) if t == "serialized" else 0
            flip_uv = obj.bool("flip_tex_coords", True) if t == "obj" else False
            out["type"] = "mesh"
            digest, lo, hi, face_normals, notes = self._mesh(path, t, shape_index, flip_uv)
            out["mesh"] = digest
            self._track_bounds(lo, hi, m)
            for text in notes:
                self.note(obj.props["filename"], text)
            if obj.bool("face_normals", False) or face_normals:
                out["face_normals"] = True
            obj.ignore("max_smooth_angle", "ignored: the file's vertex normals are used as "
                                           "they are (rayfarm does not re-smooth)")
            obj.ignore("collapse", None)
        elif t == "cylinder":
            p0 = np.asarray(obj.point("p0", [0, 0, 0]), dtype=np.float64)
            p1 = np.asarray(obj.point("p1", [0, 0, 1]), dtype=np.float64)
            radius = obj.float("radius", 1.0)
            vertices, faces = self._cylinder(p0, p1, radius, node)
            out.update({"type": "mesh", "vertices": vertices, "faces": faces})
            self._track_bounds(np.min(vertices, axis=0), np.max(vertices, axis=0), m)
            self.note(node, f"approximated by a {CYLINDER_SEGMENTS}-sided open prism (rayfarm "
                            "has no analytic cylinder)")
        else:
            self.note(node, f"ignored: rayfarm has no '{t}' shape")
            for key in list(obj.props):
                obj.ignore(key)
            obj.finish(("bsdf", "emitter", "medium", "texture"))
            return []
        out["to_world"] = m.tolist()
        if flip:
            out["flip_normals"] = True
        if t in ("rectangle", "disk"):
            self.planar.append((out, node))
        obj.finish(("bsdf", "emitter", "medium"))
        return [out]

    def _cylinder(self, p0, p1, radius, node) -> tuple[list, list]:
        axis = p1 - p0
        if not np.linalg.norm(axis) > 0 or not radius > 0:
            raise SceneError("a cylinder needs p0 != p1 and a radius > 0", node.loc)
        w = axis / np.linalg.norm(axis)
        u = np.cross(w, [1.0, 0.0, 0.0] if abs(w[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(w, u)
        angles = np.linspace(0, 2 * math.pi, CYLINDER_SEGMENTS, endpoint=False)
        ring = radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
        vertices = np.concatenate([p0 + ring, p1 + ring])
        n = CYLINDER_SEGMENTS
        faces = []
        for k in range(n):
            a0, b0, a1, b1 = k, (k + 1) % n, n + k, n + (k + 1) % n
            faces += [[a0, b0, b1], [a0, b1, a1]]
        return vertices.tolist(), faces

    # -- emitters --------------------------------------------------------------------------
    def area_emitter(self, node: _Node) -> dict | None:
        obj = _Obj(self, node)
        if obj.type != "area":
            self.note(node, f"ignored: a shape's emitter must be 'area' for rayfarm, not "
                            f"'{obj.type}'")
            for key in list(obj.props):
                obj.ignore(key)
            return None
        radiance = obj.color("radiance", 1.0, emitter=True, bounded=False, texture=True)
        if isinstance(radiance, dict):
            self.note(obj.props["radiance"], "approximated: a textured radiance is rendered as "
                                             "a constant 1")
            radiance = [1.0, 1.0, 1.0]
        obj.ignore("sampling_weight", "ignored: rayfarm chooses lights by its own weights")
        obj.finish()
        return {"type": "area", "radiance": radiance}

    def emitter(self, node: _Node) -> dict | None:
        obj = _Obj(self, node)
        t = obj.type
        if t in ("point", "spot"):
            m = obj.transform("to_world")
            position = obj.point("position", m[:3, 3].tolist())
            intensity = obj.color("intensity", 1.0, emitter=True, bounded=False, texture=False)
            obj.ignore("sampling_weight", "ignored: rayfarm chooses lights by its own weights")
            if t == "spot":
                for key in ("cutoff_angle", "beam_width", "texture"):
                    obj.ignore(key)
                self.note(node, "approximated as a point light: the cone is ignored, it lights "
                                "every direction with its intensity")
            obj.finish(("texture",))
            return {"type": "point", "position": [float(c) for c in position],
                    "intensity": intensity}
        for key in list(obj.props):
            obj.ignore(key)
        reason = ("an area emitter needs a shape" if t == "area" else
                  f"rayfarm has no '{t}' light yet")
        self.note(node, f"ignored: {reason}; the scene renders without it")
        return None

    # -- sensor, film, filter, integrator ----------------------------------------------------
    def camera(self, node: _Node) -> dict:
        obj = _Obj(self, node)
        t = obj.type
        if t not in ("perspective", "thinlens"):
            raise SceneError(f"unsupported sensor type '{t}' (rayfarm renders perspective and "
                             "thinlens cameras; another projection would be misread)", node.loc)
        cam: dict = {"type": t, "to_world": self.sensor_to_world(obj)}
        films = obj.children("film")
        width, height = 768, 576
        filt: dict = {"type": "gaussian", "stddev": 0.5}
        if films:
            try:
                width, height, filt = self.film(films[0])
            except SceneError as exc:  # a film is never a reason to refuse the file
                self.note(films[0], f"ignored ({exc}): a 768x576 film with a gaussian filter "
                                    "is used")
        if obj.has("fov") and obj.has("focal_length"):
            raise SceneError("give either fov or focal_length, not both", node.loc)
        if obj.has("fov"):
            cam["fov"] = obj.float("fov")
            axis = (obj.string("fov_axis", "x") or "").lower()
            if axis not in ("x", "y", "smaller", "larger", "diagonal"):
                raise SceneError(f"unknown fov_axis '{axis}' (allowed: x, y, smaller, larger, "
                                 "diagonal)", obj.props["fov_axis"].loc)
            cam["fov_axis"] = axis
        else:
            text = obj.string("focal_length", "50mm") or ""
            value = _numbers(text.strip().removesuffix("mm"), node, "focal_length")
            if len(value) != 1 or not value[0] > 0:
                raise SceneError("focal_length must be a length like '50mm'", node.loc)
            cam["fov"] = math.degrees(2 * math.atan(math.hypot(36.0, 24.0) / (2 * value[0])))
            cam["fov_axis"] = "diagonal"
        if t == "thinlens":
            for key, alias in (("aperture_radius", "aperture_radius"),
                               ("focus_distance", "focus_distance")):
                v = obj.float(key)
                if v is None:
                    raise SceneError(f"a thinlens sensor needs {alias}", node.loc)
                cam[key] = v
        for key in ("near_clip", "far_clip"):
            obj.ignore(key, "ignored: rayfarm's camera does not clip")
        for key in ("shutter_open", "shutter_close", "shutter_open_time"):
            obj.ignore(key, "ignored: rayfarm renders no motion blur")
        for key in ("principal_point_offset_x", "principal_point_offset_y"):
            obj.ignore(key, "ignored: rayfarm's image centre is the principal point")
        for s in obj.children("sampler"):
            try:
                self.sampler(s)
            except SceneError as exc:  # the job's spp decides anyway
                self.note(s, f"ignored ({exc})")
        for ch in obj.children("medium"):
            self.note(ch, "ignored: rayfarm renders no participating media")
        cam.update({"width": width, "height": height, "filter": filt})
        obj.finish(("film", "sampler", "medium"))
        return cam

    def sensor_to_world(self, obj: _Obj) -> list:
        """The sensor's to_world: a rotation (or a mirror) and a translation.
        Mitsuba 3 refuses a scale there; a uniform or per-axis scale is divided
        out (reported), a shear refused."""
        m = obj.transform("to_world")
        r = m[:3, :3]
        if np.allclose(r.T @ r, np.eye(3), atol=1e-4):
            return m.tolist()
        lengths = np.linalg.norm(r, axis=0)
        if not np.all(lengths > 0):
            raise SceneError("the sensor's to_world is singular", obj.props["to_world"].loc)
        r = r / lengths
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-4):
            raise SceneError("the sensor's to_world shears: a camera's transform must be a "
                             "rotation (or a mirror) and a translation", obj.props["to_world"].loc)
        self.note(obj.props["to_world"], f"approximated: its scale {lengths.round(6).tolist()} "
                                         "is divided out (a camera's transform has none; "
                                         "Mitsuba 3 refuses it)")
        m = m.copy()
        m[:3, :3] = r
        return m.tolist()

    def sampler(self, node: _Node) -> None:
        obj = _Obj(self, node)
        spp = obj.int("sample_count", None)
        self.note(node, "ignored: the job's sampler and spp decide" +
                  (f" (the file asks for {spp} samples per pixel)" if spp is not None else ""))
        for key in list(obj.props):
            obj.ignore(key)

    def film(self, node: _Node) -> tuple[int, int, dict]:
        obj = _Obj(self, node)
        width, height = obj.int("width", 768), obj.int("height", 576)
        if not (1 <= width <= 8192 and 1 <= height <= 8192):
            raise SceneError(f"the film's size {width}x{height} is outside 1 to 8192", node.loc)
        if obj.type not in ("hdrfilm", "ldrfilm", "specfilm"):
            self.note(node, f"approximated as hdrfilm: rayfarm has no '{obj.type}' film")
        elif obj.type == "ldrfilm":
            self.note(node, "approximated: rayfarm writes an HDR EXR (and a tonemapped PNG "
                            "preview) instead of a low dynamic range image")
        for key in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"):
            obj.ignore(key, "ignored: rayfarm renders the whole frame")
        for key in ("filename", "file_format", "pixel_format", "component_format", "gamma",
                    "banner", "high_quality_edges", "exposure", "tonemap_method", "attach_log",
                    "sample_border", "rfilter"):
            obj.ignore(key, "ignored: the job decides the output; rayfarm writes an EXR")
        filt = {"type": "gaussian", "stddev": 0.5}
        filters = obj.children("rfilter")
        if filters:
            filt = self.rfilter(filters[0])
        obj.finish(("rfilter",))
        return width, height, filt

    def rfilter(self, node: _Node) -> dict:
        obj = _Obj(self, node)
        t = obj.type
        if t == "box":
            r = obj.float("radius", 0.5)
            if r != 0.5:
                self.note(obj.props["radius"], "ignored: rayfarm's box filter is one pixel wide")
            out = {"type": "box"}
        elif t == "tent":
            out = {"type": "tent", "radius": self._clamped(obj, "radius", 1.0, 0.01, 8.0)}
        elif t == "gaussian":
            out = {"type": "gaussian", "stddev": self._clamped(obj, "stddev", 0.5, 0.01, 2.0)}
        else:
            for key in list(obj.props):
                obj.ignore(key)
            self.note(node, f"approximated as a gaussian of stddev 0.5: rayfarm has no '{t}' "
                            "filter")
            out = {"type": "gaussian", "stddev": 0.5}
        obj.finish()
        return out

    def _clamped(self, obj: _Obj, key: str, default: float, lo: float, hi: float) -> float:
        v = obj.float(key, default)
        if not lo <= v <= hi:
            clamped = min(max(v, lo), hi)
            self.note(obj.props[key], f"clamped to {clamped:g}: rayfarm's filters take {lo:g} "
                                      f"to {hi:g} pixels")
            return clamped
        return v

    def integrator(self, node: _Node) -> int:
        """Rayfarm's default depth (bounces) from the block's max_depth."""
        found: list[tuple[int, _Node]] = []

        def walk(n: _Node, depth: int = 0) -> None:
            if depth > MAX_REF_DEPTH:
                return
            o = _Obj(self, n)
            if o.has("max_depth"):
                p = o.props["max_depth"]
                try:
                    found.append((o.int("max_depth"), p))
                except SceneError:
                    self.note(p, "ignored: max_depth is not an integer")
            for ch in o.children("integrator"):
                walk(ch, depth + 1)
            for key in list(o.props):
                if key != "max_depth":
                    o.ignore(key, "ignored: the job's method and options decide")

        try:
            walk(node)
        except SceneError as exc:  # an integrator block is never a reason to refuse the file
            self.note(node, f"ignored ({exc}): the default depth is capped at "
                            f"{UNBOUNDED_DEPTH} bounces")
            return UNBOUNDED_DEPTH
        t = node.attrs.get("type", "")
        if not found:
            self.note(node, f"its type '{t}' is not used (the job's method decides how to "
                            f"render); no max_depth: Mitsuba's unbounded depth is capped at "
                            f"{UNBOUNDED_DEPTH} bounces")
            return UNBOUNDED_DEPTH
        depth, p = found[0]
        if depth < 0:
            bounces = UNBOUNDED_DEPTH
            how = f"max_depth {depth} (unbounded) -> at most {UNBOUNDED_DEPTH} bounces"
        else:
            bounces = min(max(depth - 1, 0), UNBOUNDED_DEPTH)
            how = f"max_depth {depth} -> depth {bounces} (bounces: Mitsuba's max_depth - 1)"
            if depth - 1 > UNBOUNDED_DEPTH:
                how += f", capped at {UNBOUNDED_DEPTH}"
            if depth == 0:
                how += " (Mitsuba renders nothing at max_depth 0; rayfarm shows the emitters)"
        self.note(node, f"its type '{t}' is not used (the job's method decides how to "
                        f"render); the default depth comes from {how}")
        return bounces

    # -- the scene -------------------------------------------------------------------------
    def run(self) -> Imported:
        top = _parse_xml(self.main, self.rel(self.main))
        if top.tag != "scene":
            raise SceneError(f"the root element must be <scene>, not <{top.tag}>", top.loc)
        scene = self.expand(top)[0]
        cameras, shapes, emitters = [], [], []
        depth = None
        for node in scene.children:
            tag = node.tag
            if tag == "sensor":
                if cameras:
                    self.note(node, "ignored: rayfarm renders the first sensor")
                else:
                    cameras.append(self.camera(node))
            elif tag == "integrator":
                if depth is not None:
                    self.note(node, "ignored: only the first integrator gives defaults")
                else:
                    depth = self.integrator(node)
            elif tag == "shape":
                shapes.extend(self.shape(node))
            elif tag == "emitter":
                em = self.emitter(node)
                if em is not None:
                    emitters.append(em)
            elif tag in ("bsdf", "texture"):
                if "id" not in node.attrs:
                    self.note(node, f"ignored: a {tag} at the top level without an id is never "
                                    "used")
            elif tag in ("medium", "phase", "volume"):
                self.note(node, "ignored: rayfarm renders no participating media")
            elif tag == "ref":
                self.note(node, "ignored: a reference at the top level has no effect")
            else:
                self.note(node, f"ignored (<{tag}> is not an element rayfarm reads at the top "
                                "level of a scene)")
        if depth is None:
            depth = UNBOUNDED_DEPTH
            self.note(scene, f"no integrator: Mitsuba's default path tracer is unbounded; the "
                             f"default depth is capped at {UNBOUNDED_DEPTH} bounces")
        if not cameras:
            cameras.append(self.default_camera(scene))
        self.materials = {k: v for k, v in self.materials.items() if v["type"] != "null"}
        self.check_sides(cameras[0])
        name = self.path.stem if self.path.stem != "scene" else (self.path.parent.name or "scene")
        doc: dict = {"name": name, "camera": cameras[0], "materials": self.materials,
                     "shapes": shapes, "emitters": emitters, "defaults": {"max_depth": depth}}
        if self.textures:
            doc["textures"] = self.textures
        main = self.rel(self.main)  # the report in file order: the main file's first
        self.report.sort(key=lambda e: (e.file != main, e.file, e.line or 0))
        return Imported(doc=doc, assets=self.assets, report=self.report)

    def check_sides(self, camera: dict) -> None:
        """Say where a one-sided rectangle or disk turns its back to the
        camera: Mitsuba renders it black from there, and so does rayfarm."""
        eye = np.asarray(camera["to_world"])[:3, 3]
        for shape, node in self.planar:
            mat = self.materials[shape["material"]]
            if mat.get("twosided") or mat["type"] == "dielectric":
                continue
            vertices, faces = world_mesh(shape)
            a, b, c = vertices[faces[0]]
            normal = np.cross(b - a, c - a)
            if np.dot(normal, eye - vertices.mean(axis=0)) < 0:
                self.note(node, f"its material '{shape['material']}' is one-sided and the camera "
                                "sees its back: it renders black there (as in Mitsuba; wrap the "
                                "bsdf in twosided to light both sides)")

    def default_camera(self, scene: _Node) -> dict:
        """Mitsuba 3's camera for a scene without one: fov 45 along x, looking
        along +z at the bounds' centre from far enough to see them."""
        if not self.bounds:
            raise SceneError("the scene has no sensor, and no geometry whose bounds could frame "
                             "a default camera", scene.loc)
        pts = np.concatenate(self.bounds)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        center, extent = (lo + hi) / 2, float(np.max(hi - lo))
        distance = extent / (2 * math.tan(math.radians(45 / 2)))
        origin = [center[0], center[1], lo[2] - distance]
        self.note(scene, "no sensor: a default perspective camera (fov 45) looks along +z at the "
                         "scene's bounds, as Mitsuba 3 frames it")
        return {"type": "perspective",
                "to_world": look_at(origin, center, [0.0, 1.0, 0.0]).tolist(),
                "fov": 45.0, "fov_axis": "x", "width": 768, "height": 576,
                "filter": {"type": "gaussian", "stddev": 0.5}}


def import_mitsuba(path: Path, root: Path | None = None) -> Imported:
    """Import a Mitsuba XML scene (see the module doc). `root` is the folder
    every file it names must lie in (default: the scene file's folder)."""
    try:
        return _Importer(Path(path), root).run()
    except RecursionError:
        raise SceneError("the scene nests too deeply", Path(path).name) from None
