"""Mitsuba textures as native ones: bitmaps and checkerboards, their UV
scale and offset; the others approximated by a constant."""

from __future__ import annotations

from pathlib import Path

from ...errors import SceneError
from .values import _Obj
from .xmltree import _Node


class TextureMapper:
    """Textures (a base of scene._Importer)."""

    def _add_texture(self, node: _Node, entry: dict) -> str:
        """The texture's name; an identical one already there is shared."""
        for name, other in self.textures.items():
            if other == entry:
                return name
        base = node.attrs.get("id") or self.anonymous("texture", node)
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
            from ...assets import asset_digest, encode_texture  # type: ignore[attr-defined]
            from ...textures import read_texture  # type: ignore[import-not-found]
        except ImportError:
            return {"file": self.rel(path), **({"raw": True} if raw else {})}
        key = (path, raw)
        if key not in self.texture_cache:
            blob = encode_texture(read_texture(path, raw=raw, name=self.rel(path)))
            digest = asset_digest(blob)
            self.assets[digest] = blob
            self.texture_cache[key] = digest
        return {"image": self.texture_cache[key]}
