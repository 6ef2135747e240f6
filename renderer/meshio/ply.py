"""PLY, ASCII and binary (see renderer.meshio)."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from ..errors import SceneError
from .common import MAX_HEADER_BYTES, MeshData, _fan, _floats, _per_line, _token_starts

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
_UV_NAMES = (("u", "v"), ("s", "t"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))


@dataclass
class _Prop:
    name: str
    dtype: str  # value type
    count_dtype: str | None = None  # list properties: the count's type


@dataclass
class _Element:
    name: str
    count: int
    line: int
    props: list[_Prop] = field(default_factory=list)


def _ply_header(data: bytes, label: str) -> tuple[str, list[_Element], int]:
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if not data.startswith(b"ply") or end < 0:
        raise SceneError("not a PLY file (no 'ply' ... 'end_header' header in the first "
                         f"{MAX_HEADER_BYTES} bytes)", f"{label}:1")
    body = data.find(b"\n", end)
    body = len(data) if body < 0 else body + 1
    lines = data[:end].decode("ascii", "replace").split("\n")
    fmt, elements = None, []
    for lineno, raw in enumerate(lines, 1):
        parts = raw.split()
        loc = f"{label}:{lineno}"
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian",
                                                  "binary_big_endian"):
                raise SceneError(f"unknown PLY format: {raw.strip()[:60]}", loc)
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise SceneError(f"cannot parse: {raw.strip()[:60]}", loc)
            elements.append(_Element(parts[1], int(parts[2]), lineno))
        elif parts[0] == "property":
            if not elements:
                raise SceneError("a property before any element", loc)
            if len(parts) == 5 and parts[1] == "list":
                if parts[2] not in _PLY_TYPES or parts[3] not in _PLY_TYPES or \
                        _PLY_TYPES[parts[2]][0] == "f":
                    raise SceneError(f"unknown list property types: {raw.strip()[:60]}", loc)
                elements[-1].props.append(_Prop(parts[4], _PLY_TYPES[parts[3]],
                                                _PLY_TYPES[parts[2]]))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1].props.append(_Prop(parts[2], _PLY_TYPES[parts[1]]))
            else:
                raise SceneError(f"cannot parse property: {raw.strip()[:60]}", loc)
        else:
            raise SceneError(f"unknown PLY header line: {raw.strip()[:60]}", loc)
    if fmt is None:
        raise SceneError("the PLY header has no format line", f"{label}:1")
    return fmt, elements, body


def _ply_vertex_arrays(cols: dict[str, np.ndarray], el: _Element, label: str):
    loc = f"{label}:{el.line}"
    for axis in "xyz":
        if axis not in cols:
            raise SceneError(f"the vertex element has no '{axis}' property", loc)
    positions = np.stack([cols[a].astype(np.float64) for a in "xyz"], axis=1)
    normals = uvs = None
    if all(a in cols for a in ("nx", "ny", "nz")):
        normals = np.stack([cols[a].astype(np.float64) for a in ("nx", "ny", "nz")], axis=1)
    for u, v in _UV_NAMES:
        if u in cols and v in cols:
            uvs = np.stack([cols[u].astype(np.float64), cols[v].astype(np.float64)], axis=1)
            break
    return positions, normals, uvs


def _face_list(el: _Element, label: str) -> str:
    names = [p.name for p in el.props if p.count_dtype]
    for name in ("vertex_indices", "vertex_index"):
        if name in names:
            return name
    raise SceneError("the face element has no vertex_indices list", f"{label}:{el.line}")


def _read_ply(data: bytes, label: str, max_triangles: int) -> MeshData:
    fmt, elements, body = _ply_header(data, label)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise SceneError("the PLY file has no vertex element", f"{label}:1")
    if fmt == "ascii":
        cols_by_el = _ply_ascii(data, body, elements, label)
    else:
        cols_by_el = _ply_binary(data, body, elements, label,
                                 "<" if fmt == "binary_little_endian" else ">")
    v_el = elements[names.index("vertex")]
    positions, normals, uvs = _ply_vertex_arrays(cols_by_el["vertex"], v_el, label)
    faces = np.zeros((0, 3), np.int64)
    if "face" in cols_by_el:
        f_el = elements[names.index("face")]
        counts, flat = cols_by_el["face"][_face_list(f_el, label)]
        if np.any(counts < 3):
            j = int(np.argmax(counts < 3))
            raise SceneError(f"face {j} has {int(counts[j])} vertices (at least 3 needed)",
                             f"{label}:{f_el.line}")
        ntri = int(np.sum(counts - 2))
        if ntri > max_triangles:
            raise SceneError(f"too many triangles ({ntri}; the limit is {max_triangles})", label)
        tri, poly = _fan(counts)
        faces = flat.astype(np.int64)[tri]
        bad = (faces < 0) | (faces >= len(positions))
        if np.any(bad):
            t = int(np.argmax(np.any(bad, axis=1)))
            raise SceneError(f"face {int(poly[t])} names vertex {int(faces[t][bad[t]][0])}; the "
                             f"file has {len(positions)} vertices", f"{label}:{f_el.line}")
    return MeshData(positions=np.ascontiguousarray(positions),
                    faces=np.ascontiguousarray(faces.reshape(-1, 3)),
                    normals=normals, uvs=uvs)


def _ply_binary(data: bytes, offset: int, elements: list[_Element], label: str, endian: str):
    out: dict[str, dict] = {}
    for el in elements:
        loc = f"{label}:{el.line}"
        remaining = len(data) - offset
        fixed = [p for p in el.props if p.count_dtype is None]
        lists = [p for p in el.props if p.count_dtype is not None]
        min_size = sum(np.dtype(p.dtype).itemsize for p in fixed) + \
            sum(np.dtype(p.count_dtype).itemsize for p in lists)
        if min_size == 0 and el.count:
            raise SceneError(f"element '{el.name}' has no properties", loc)
        if el.count * min_size > remaining:
            raise SceneError(f"element '{el.name}' announces {el.count} records: at least "
                             f"{el.count * min_size} bytes, but {remaining} remain in the file "
                             "(truncated, or a hostile count)", loc)
        if not lists:
            dt = np.dtype([(p.name, endian + p.dtype) for p in el.props])
            rec = np.frombuffer(data, dt, el.count, offset)
            offset += el.count * dt.itemsize
            if el.name in ("vertex", "face"):
                out[el.name] = {p.name: rec[p.name] for p in el.props}
            continue
        # Records with lists: try "every list as long as the first record's"
        # (triangle meshes), else walk the records one by one.
        cols, offset = _ply_binary_lists(data, offset, el, endian, label)
        if el.name in ("vertex", "face"):
            out[el.name] = cols
    if offset != len(data):
        pass  # trailing bytes (some writers pad): ignored
    return out


def _ply_binary_lists(data, offset, el: _Element, endian, label):
    loc = f"{label}:{el.line}"
    if el.count == 0:
        return {p.name: (np.zeros(0, np.int64), np.zeros(0)) if p.count_dtype else np.zeros(0)
                for p in el.props}, offset
    # first record's list lengths
    pos, firsts = offset, []
    for p in el.props:
        if p.count_dtype is None:
            pos += np.dtype(p.dtype).itemsize
        else:
            if pos + np.dtype(p.count_dtype).itemsize > len(data):
                raise SceneError(f"element '{el.name}' is truncated", loc)
            n = int(np.frombuffer(data, endian + p.count_dtype, 1, pos)[0])
            firsts.append(n)
            pos += np.dtype(p.count_dtype).itemsize + n * np.dtype(p.dtype).itemsize
    fields, it = [], iter(firsts)
    for p in el.props:
        if p.count_dtype is None:
            fields.append((p.name, endian + p.dtype))
        else:
            n = next(it)
            fields.append((p.name + "#n", endian + p.count_dtype))
            fields.append((p.name, endian + p.dtype, (n,)))
    dt = np.dtype(fields)
    if offset + el.count * dt.itemsize <= len(data):
        rec = np.frombuffer(data, dt, el.count, offset)
        if all(np.all(rec[p.name + "#n"] == n) for p, n in
               zip([p for p in el.props if p.count_dtype], firsts)):
            cols = {}
            for p, n in zip([p for p in el.props if p.count_dtype], firsts):
                cols[p.name] = (np.full(el.count, n, np.int64), rec[p.name].reshape(-1))
            for p in el.props:
                if p.count_dtype is None:
                    cols[p.name] = rec[p.name]
            return cols, offset + el.count * dt.itemsize
    # variable lengths: one record at a time (bounded by the file's size)
    mv = memoryview(data)
    pos = offset
    scal: dict[str, list] = {p.name: [] for p in el.props if p.count_dtype is None}
    lst: dict[str, tuple[list, list]] = {p.name: ([], []) for p in el.props if p.count_dtype}
    fmts = {p.name: struct.Struct(endian + _STRUCT[p.count_dtype or p.dtype]) for p in el.props}
    for r in range(el.count):
        for p in el.props:
            s = fmts[p.name]
            if pos + s.size > len(data):
                raise SceneError(f"element '{el.name}' is truncated at record {r}", loc)
            (val,) = s.unpack_from(mv, pos)
            pos += s.size
            if p.count_dtype is None:
                scal[p.name].append(val)
            else:
                size = np.dtype(p.dtype).itemsize * val
                if pos + size > len(data):
                    raise SceneError(f"element '{el.name}' is truncated at record {r}", loc)
                lst[p.name][0].append(val)
                lst[p.name][1].append((pos, val))
                pos += size
    cols = {k: np.asarray(v) for k, v in scal.items()}
    for p in el.props:
        if p.count_dtype:
            counts, spans = lst[p.name]
            chunks = [np.frombuffer(data, endian + p.dtype, n, o) for o, n in spans]
            cols[p.name] = (np.asarray(counts, np.int64),
                            np.concatenate(chunks) if chunks else np.zeros(0))
    return cols, pos


def _ply_ascii(data: bytes, offset: int, elements: list[_Element], label: str):
    header_lines = data[:offset].count(b"\n")
    buf = np.frombuffer(data, np.uint8)
    line_ends = np.flatnonzero(buf == 10)
    line_ends = line_ends[line_ends >= offset]
    if len(buf) > offset and (not len(line_ends) or line_ends[-1] != len(buf) - 1):
        line_ends = np.concatenate([line_ends, [len(buf)]])
    out: dict[str, dict] = {}
    line0 = 0  # index into line_ends of the element's first line
    for el in elements:
        loc = f"{label}:{el.line}"
        if el.count > len(line_ends) - line0:
            raise SceneError(f"element '{el.name}' announces {el.count} lines, but "
                             f"{len(line_ends) - line0} remain in the file (truncated, or a "
                             "hostile count)", loc)
        if el.count == 0:
            out[el.name] = {p.name: (np.zeros(0, np.int64), np.zeros(0)) if p.count_dtype
                            else np.zeros(0) for p in el.props}
            continue
        start = offset if line0 == 0 else int(line_ends[line0 - 1]) + 1
        end = int(line_ends[line0 + el.count - 1])
        first_line = header_lines + line0 + 1
        line0 += el.count
        if el.name not in ("vertex", "face"):
            continue
        block = data[start:end]
        values = _floats(block.replace(b"\r", b" "))
        arr = np.frombuffer(block, np.uint8)
        toks = _token_starts(arr)
        ends_rel = np.concatenate([np.flatnonzero(arr == 10), [len(arr)]])
        counts = _per_line(toks, ends_rel)
        if values is None or len(values) != len(toks):
            for i, line in enumerate(block.split(b"\n")):
                try:
                    [float(x) for x in line.split()]
                except ValueError:
                    raise SceneError(f"cannot parse: {line.decode('utf-8', 'replace')[:60]}",
                                     f"{label}:{first_line + i}") from None
            raise SceneError(f"cannot parse element '{el.name}'", loc)
        pos = np.concatenate([[0], np.cumsum(counts)[:-1]])
        line_end = pos + counts
        cols = {}
        for p in el.props:
            short = pos >= line_end
            if np.any(short):
                i = int(np.argmax(short))
                raise SceneError(f"record {i} of '{el.name}' has too few values",
                                 f"{label}:{first_line + i}")
            head = values[np.minimum(pos, len(values) - 1)]
            if p.count_dtype is None:
                cols[p.name] = head
                pos = pos + 1
            else:
                n = head.astype(np.int64)
                if np.any(n < 0) or np.any(head != n):
                    i = int(np.argmax((n < 0) | (head != n)))
                    raise SceneError(f"bad list length in record {i} of '{el.name}'",
                                     f"{label}:{first_line + i}")
                if np.any(pos + 1 + n > line_end):
                    i = int(np.argmax(pos + 1 + n > line_end))
                    raise SceneError(f"record {i} of '{el.name}' has too few values",
                                     f"{label}:{first_line + i}")
                idx = np.repeat(pos + 1 - np.concatenate([[0], np.cumsum(n)[:-1]]), n) + \
                    np.arange(int(n.sum()))
                items = values[idx]
                if p.dtype[0] != "f" and np.any(items != np.round(items)):
                    raise SceneError(f"'{p.name}' of '{el.name}' holds a non-integer", loc)
                cols[p.name] = (n, items)
                pos = pos + 1 + n
        over = pos != line_end
        if np.any(over):
            i = int(np.argmax(over))
            raise SceneError(f"record {i} of '{el.name}' has {int(counts[i])} values, not as "
                             "the header says", f"{label}:{first_line + i}")
        out[el.name] = cols
    return out
