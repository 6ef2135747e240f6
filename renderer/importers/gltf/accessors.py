"""Accessors: typed, bounded views of buffer data (strided, sparse or all
zeros) read as float64 or int64 arrays."""

from __future__ import annotations

import numpy as np

from ...scene_format import MAX_TRIANGLES
from .container import _Container
from .reader import _Reader

MAX_ACCESSOR_ELEMENTS = 3 * MAX_TRIANGLES
MAX_ZERO_ELEMENTS = 1 << 20  # elements of an accessor with no buffer view

COMPONENTS = {  # componentType -> (numpy little-endian dtype, bytes)
    5120: ("<i1", 1), 5121: ("<u1", 1), 5122: ("<i2", 2), 5123: ("<u2", 2),
    5125: ("<u4", 4), 5126: ("<f4", 4),
}
COMPONENT_NAMES = {5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT",
                   5125: "UNSIGNED_INT", 5126: "FLOAT"}
TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


class _Accessors(_Container):
    # -- accessors ----------------------------------------------------------

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


def _normalize(a: np.ndarray, ctype: int) -> np.ndarray:
    """glTF's normalized integers as floats (signed ones clamped at -1)."""
    scale = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}[ctype]
    return np.maximum(a.astype(np.float64) / scale, -1.0)


def _check_finite(imp: _Reader, arr: np.ndarray, ai: int, what: str) -> None:
    bad = ~np.all(np.isfinite(arr), axis=1)
    if np.any(bad):
        j = int(np.argmax(bad))
        raise imp.fail(f"{what} element {j} is not finite ({arr[j].tolist()})",
                       f"/accessors/{ai}")
