"""Property values of a Mitsuba element: numbers, points, colours (rgb, srgb,
spectra, black bodies), transforms; `_Obj` reads one object element's
properties, turning the old dialect's names (`toWorld`, `intIOR`) into the
new one's (`to_world`, `int_ior`) as Mitsuba 3 upgrades them, and reports
the ones nobody read.
"""

from __future__ import annotations

import math
import re

import numpy as np

from ...errors import SceneError
from ..spectra import blackbody, spectrum_to_rgb, srgb_to_linear, uniform_to_rgb
from .xmltree import _Node

PROPERTY_TAGS = {"float", "integer", "boolean", "string", "rgb", "srgb", "spectrum", "blackbody",
                 "point", "vector", "transform"}
OBJECT_TAGS = {"bsdf", "texture", "shape", "emitter", "sensor", "film", "rfilter", "sampler",
               "integrator", "medium", "phase", "volume"}


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



class ValueReader:
    """Values of property elements (a base of scene._Importer)."""

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
