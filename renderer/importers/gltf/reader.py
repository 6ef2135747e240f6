"""The importer's state and its located reading of the JSON: errors and
report entries name a JSON pointer into the file."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import SceneError
from .. import ReportEntry


class _Reader:
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


def _show(value: Any) -> str:
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
