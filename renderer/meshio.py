"""Mesh files in full: Wavefront OBJ, PLY (ASCII and binary) and Mitsuba's
`.serialized`.

    mesh = read_mesh(Path("models/Mesh000.obj"), label="models/Mesh000.obj")
    mesh.positions (V, 3) float64, mesh.faces (F, 3) int64,
    mesh.normals (V, 3) float64 | None, mesh.uvs (V, 2) float64 | None

Every output vertex has one position, normal and UV: where an OBJ corner
pairs a position with another UV or normal than elsewhere, the vertex is
split. Polygons are fanned into triangles (0, j, j + 1). UVs are given as the
file holds them (Mitsuba's obj and ply loaders flip v by default; that
convention belongs to the importer). A file without normals gives
`normals=None` (Mitsuba 3 then computes smooth vertex normals unless
`face_normals` is set: again the importer's choice).

Speed: the text formats are parsed a block at a time with numpy (lines of
one kind joined, tokens counted and converted in bulk), so a 2M-triangle OBJ
takes seconds; a per-line Python path runs only to locate an error.
Bounds: the file's size, and every count a header announces is checked
against the bytes that remain before anything is allocated.

Errors are `SceneError`s whose location is ``label:line`` (`label` defaults
to the file's name).
"""

from __future__ import annotations

import re
import struct
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SceneError

__all__ = ["MeshData", "read_mesh", "read_mtl", "MESH_SUFFIXES", "MAX_MESH_FILE_BYTES",
           "MAX_MESH_TRIANGLES"]

MESH_SUFFIXES = {".obj": "obj", ".ply": "ply", ".serialized": "serialized"}
MAX_MESH_FILE_BYTES = 512 * 1024 * 1024
MAX_MESH_TRIANGLES = 5_000_000
MAX_HEADER_BYTES = 64 * 1024  # a PLY header, a .serialized shape's name


@dataclass
class MeshData:
    """One triangle mesh as read from a file (local space, 0-based faces)."""

    positions: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    # OBJ `usemtl` runs: (material name or None before the first, first face, face count)
    face_groups: list[tuple[str | None, int, int]] | None = None
    objects: list[tuple[str, int, int]] | None = None  # OBJ `o`/`g` runs, likewise
    mtllibs: list[str] = field(default_factory=list)  # OBJ `mtllib` names, in order
    face_normals: bool = False  # a .serialized file's FaceNormals flag
    notes: list[str] = field(default_factory=list)  # what was read other than as written

    @property
    def triangle_count(self) -> int:
        return len(self.faces)


def read_mesh(path: Path, *, fmt: str | None = None, shape_index: int = 0,
              label: str | None = None, max_bytes: int = MAX_MESH_FILE_BYTES,
              max_triangles: int = MAX_MESH_TRIANGLES) -> MeshData:
    """Read a mesh file; `fmt` is ``obj``, ``ply`` or ``serialized`` (default:
    from the suffix); `shape_index` picks a shape of a .serialized file."""
    path = Path(path)
    label = label or path.name
    if fmt is None:
        fmt = MESH_SUFFIXES.get(path.suffix.lower())
        if fmt is None:
            raise SceneError(f"unsupported mesh file type '{path.suffix}' (allowed: "
                             f"{', '.join(MESH_SUFFIXES)})", label)
    if fmt not in MESH_SUFFIXES.values():
        raise SceneError(f"unknown mesh format '{fmt}'", label)
    if not path.is_file():
        raise SceneError(f"mesh file not found: {label}", label)
    size = path.stat().st_size
    if size > max_bytes:
        raise SceneError(f"mesh file too large ({size} bytes; the limit is {max_bytes})", label)
    data = path.read_bytes()
    if fmt == "obj":
        mesh = _read_obj(data, label, max_triangles)
    elif fmt == "ply":
        mesh = _read_ply(data, label, max_triangles)
    else:
        mesh = _read_serialized(data, label, shape_index, max_triangles)
    _check_finite(mesh, label)
    return mesh


def _check_finite(mesh: MeshData, label: str) -> None:
    for name in ("positions", "normals", "uvs"):
        a = getattr(mesh, name)
        if a is not None and not np.all(np.isfinite(a)):
            j = int(np.argmax(~np.all(np.isfinite(a), axis=1)))
            raise SceneError(f"{name[:-1]} {j} is not finite: {a[j].tolist()}", label)


# ----------------------------------------------------------------------------
# Shared helpers.

_WS = b" \t\r\n\v\f"
_SPACE = ord(" ")


def _floats(block: bytes, dtype=np.float64) -> np.ndarray | None:
    """All whitespace-separated numbers of `block`, or None if one does not parse."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            return np.fromstring(block, dtype=dtype, sep=" ")
        except (DeprecationWarning, ValueError):
            return None


def _token_starts(arr: np.ndarray) -> np.ndarray:
    """Offsets where a whitespace-separated token starts in the byte array."""
    space = (arr == 32) | (arr == 10) | (arr == 9) | (arr == 13)
    start = ~space
    start[1:] &= space[:-1]
    return np.flatnonzero(start)


def _per_line(positions: np.ndarray, line_ends: np.ndarray) -> np.ndarray:
    """How many of the sorted `positions` fall in each line (ends exclusive, sorted)."""
    upto = np.searchsorted(positions, line_ends)
    return np.diff(np.concatenate([[0], upto]))


def _fan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (as corner indices into the flat corner list) of polygons of
    `counts` corners, fanned (0, j, j + 1); and each triangle's polygon."""
    counts = counts.astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ntri = np.maximum(counts - 2, 0)
    poly = np.repeat(np.arange(len(counts)), ntri)
    first_tri = np.concatenate([[0], np.cumsum(ntri)[:-1]])
    j = np.arange(len(poly)) - first_tri[poly] + 1
    base = starts[poly]
    return np.stack([base, base + j, base + j + 1], axis=1), poly


# ----------------------------------------------------------------------------
# Wavefront OBJ.

_K_OTHER, _K_SKIP, _K_V, _K_VT, _K_VN, _K_F, _K_INDENTED = 0, 1, 2, 3, 4, 5, 6


def _line_table(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start and end (exclusive, before the newline) offsets of every line, and
    each line's kind, classified from its first bytes."""
    buf = np.frombuffer(data, np.uint8)
    ends = np.flatnonzero(buf == 10)
    if len(buf) and (not len(ends) or ends[-1] != len(buf) - 1):
        ends = np.concatenate([ends, [len(buf)]])
    starts = np.concatenate([[0], ends[:-1] + 1]).astype(np.int64)
    padded = np.concatenate([buf, np.zeros(3, np.uint8)])
    c0, c1, c2 = padded[starts], padded[starts + 1], padded[starts + 2]
    ws1 = (c1 == 32) | (c1 == 9)
    ws2 = (c2 == 32) | (c2 == 9)
    kind = np.full(len(starts), _K_OTHER, np.uint8)
    v = c0 == ord("v")
    kind[v & ws1] = _K_V
    kind[v & (c1 == ord("t")) & ws2] = _K_VT
    kind[v & (c1 == ord("n")) & ws2] = _K_VN
    kind[(c0 == ord("f")) & ws1] = _K_F
    blank = (starts >= ends) | (c0 == ord("#")) | (c0 == 13) | ((c0 == ord("s")) & ws1)
    kind[blank] = _K_SKIP
    kind[((c0 == 32) | (c0 == 9)) & (starts < ends)] = _K_INDENTED
    return starts, ends, kind


def _gather(data: bytes, starts: np.ndarray, ends: np.ndarray, lines: np.ndarray) -> bytes:
    """The lines `lines` (indices, sorted) joined by newlines, in runs of
    consecutive lines so that a block of 1M vertex lines is one slice."""
    if not len(lines):
        return b""
    breaks = np.flatnonzero(np.diff(lines) != 1) + 1
    first = np.concatenate([[0], breaks])
    last = np.concatenate([breaks - 1, [len(lines) - 1]])
    return b"\n".join(data[starts[lines[a]]:ends[lines[b]]] for a, b in zip(first, last))


_OBJ_DELETE = bytes.maketrans(b"vtnf\t\r/", b"       ")


def _obj_values(data, starts, ends, lines, label, what, need, keep, strip):
    """The first `keep` numbers of each line in `lines` (which start with the
    `strip` keyword), as a (len(lines), keep) array; lines with fewer than
    `need` numbers are refused."""
    n = len(lines)
    if not n:
        return np.zeros((0, keep))
    block = _gather(data, starts, ends, lines)
    block = block.translate(_OBJ_DELETE)
    values = _floats(block)
    arr = np.frombuffer(block, np.uint8)
    toks = _token_starts(arr)
    line_ends = np.concatenate([np.flatnonzero(arr == 10), [len(arr)]])
    counts = _per_line(toks, line_ends)
    if values is None or len(values) != len(toks) or np.any(counts < need):
        # find the first offending line, to name it
        for li in lines:
            parts = data[starts[li]:ends[li]].split()
            try:
                nums = [float(x) for x in parts[1:]]
            except ValueError:
                raise SceneError(f"cannot parse {what}: {_show(data, starts[li], ends[li])}",
                                 f"{label}:{li + 1}") from None
            if len(nums) < need:
                raise SceneError(f"a {what} needs {need} numbers: "
                                 f"{_show(data, starts[li], ends[li])}", f"{label}:{li + 1}")
        raise SceneError(f"cannot parse the {what} lines", label)
    if np.all(counts == counts[0]):
        out = values.reshape(n, counts[0])[:, :keep]
    else:
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        idx = offsets[:, None] + np.arange(keep)[None, :]
        valid = np.arange(keep)[None, :] < counts[:, None]
        out = np.where(valid, values[np.minimum(idx, len(values) - 1)], 0.0)
    if out.shape[1] < keep:
        out = np.concatenate([out, np.zeros((n, keep - out.shape[1]))], axis=1)
    return np.ascontiguousarray(out, dtype=np.float64)


def _show(data: bytes, a: int, b: int) -> str:
    return data[a:b].decode("utf-8", "replace").strip()[:60]


def _obj_corners(data, starts, ends, flines, label):
    """Per face line: the corner count; per corner: v, vt, vn indices as
    written (0 = absent) and the line it is on. None if the fast path fails."""
    block = _gather(data, starts, ends, flines)
    block = block.replace(b"//", b"/0/").translate(bytes.maketrans(b"f\t\r", b"   "))
    arr = np.frombuffer(block, np.uint8)
    line_ends = np.concatenate([np.flatnonzero(arr == 10), [len(arr)]])
    toks = _token_starts(arr)
    nv = _per_line(toks, line_ends)
    slashes = np.flatnonzero(arr == ord("/"))
    # each corner token's slashes: corner c's token spans [toks[c], toks[c + 1])
    per_tok = np.diff(np.concatenate([np.searchsorted(slashes, toks), [len(slashes)]]))
    if np.any(per_tok > 2):
        return None
    k = per_tok + 1
    values = _floats(block.replace(b"/", b" "), np.int64)
    if values is None or len(values) != int(k.sum()):
        return None
    off = np.concatenate([[0], np.cumsum(k)[:-1]])
    vi = values[off]
    ti = np.where(k >= 2, values[np.minimum(off + 1, len(values) - 1)], 0)
    ni = np.where(k >= 3, values[np.minimum(off + 2, len(values) - 1)], 0)
    return nv, vi, ti, ni


def _obj_corners_slow(data, starts, ends, flines, label):
    """The same as `_obj_corners`, one token at a time, naming the bad line."""
    nv, vi, ti, ni = [], [], [], []
    for li in flines:
        parts = data[starts[li]:ends[li]].split()[1:]
        nv.append(len(parts))
        for p in parts:
            fields = p.split(b"/")
            if len(fields) > 3 or not fields[0]:
                raise SceneError(f"cannot parse face corner '{p.decode('utf-8', 'replace')[:30]}'"
                                 f": {_show(data, starts[li], ends[li])}", f"{label}:{li + 1}")
            try:
                nums = [int(f) if f else 0 for f in fields] + [0, 0]
            except ValueError:
                raise SceneError(f"cannot parse face corner '{p.decode('utf-8', 'replace')[:30]}'"
                                 f": {_show(data, starts[li], ends[li])}", f"{label}:{li + 1}") \
                    from None
            vi.append(nums[0])
            ti.append(nums[1])
            ni.append(nums[2])
    return (np.asarray(nv, np.int64), np.asarray(vi, np.int64), np.asarray(ti, np.int64),
            np.asarray(ni, np.int64))


def _resolve_index(raw, before, total, corner_line, label, what):
    """OBJ indices (1-based, or negative: relative to the `before` elements
    defined above the line) to 0-based, absent (0) to -1; range-checked."""
    idx = np.where(raw > 0, raw - 1, np.where(raw < 0, before + raw, -1))
    bad = (raw != 0) & ((idx < 0) | (idx >= total))
    if np.any(bad):
        c = int(np.argmax(bad))
        raise SceneError(f"{what} index {int(raw[c])} is out of range (the file has {total} "
                         f"{what}s{' above this line' if raw[c] < 0 else ''})",
                         f"{label}:{int(corner_line[c]) + 1}")
    return idx


def _runs(marker_lines, names, flines, tri_prefix):
    """Runs of faces between marker lines (usemtl or o/g): [(name, first, count)]."""
    total = int(tri_prefix[-1])
    cuts = [(0, None)]
    for li, name in zip(marker_lines, names):
        cuts.append((int(tri_prefix[np.searchsorted(flines, li)]), name))
    out: list = []
    for i, (start, name) in enumerate(cuts):
        end = cuts[i + 1][0] if i + 1 < len(cuts) else total
        if end <= start:
            continue
        if out and out[-1][0] == name and out[-1][1] + out[-1][2] == start:
            out[-1] = (name, out[-1][1], out[-1][2] + end - start)
        else:
            out.append((name, start, end - start))
    return out


def _read_obj(data: bytes, label: str, max_triangles: int) -> MeshData:
    starts, ends, kind = _line_table(data)
    if np.any(kind == _K_INDENTED):  # indented records: classify them too
        data = re.sub(rb"(?m)^[ \t]+", b"", data)
        starts, ends, kind = _line_table(data)
    vlines = np.flatnonzero(kind == _K_V)
    tlines = np.flatnonzero(kind == _K_VT)
    nlines = np.flatnonzero(kind == _K_VN)
    flines = np.flatnonzero(kind == _K_F)
    notes: list[str] = []
    mtllibs: list[str] = []
    mtl_lines, mtl_names, obj_lines, obj_names = [], [], [], []
    for li in np.flatnonzero(kind == _K_OTHER):
        line = data[starts[li]:ends[li]].decode("utf-8", "replace").strip()
        key, _, rest = line.partition(" ")
        rest = rest.strip()
        if key == "usemtl":
            mtl_lines.append(li)
            mtl_names.append(rest)
        elif key in ("o", "g"):
            obj_lines.append(li)
            obj_names.append(rest)
        elif key == "mtllib":
            mtllibs.append(rest)
        elif key in ("l", "p", "vp", "curv", "curv2", "surf", "cstype", "deg", "bmat", "step",
                     "parm", "trim", "hole", "scrv", "sp", "end", "con", "mg", "bevel",
                     "c_interp", "d_interp", "lod", "shadow_obj", "trace_obj", "ctech", "stech",
                     "maplib", "usemap"):
            note = f"'{key}' records ignored (only triangles and polygons are rendered)"
            if note not in notes:
                notes.append(note)
        elif key in ("v", "vt", "vn", "f") or not key:
            raise SceneError(f"cannot parse: {line[:60]}", f"{label}:{li + 1}")
        else:
            raise SceneError(f"unknown OBJ record '{key[:20]}'", f"{label}:{li + 1}")

    positions = _obj_values(data, starts, ends, vlines, label, "vertex", 3, 3, "v")
    texcoords = _obj_values(data, starts, ends, tlines, label, "texture coordinate", 1, 2, "vt")
    normals_in = _obj_values(data, starts, ends, nlines, label, "normal", 3, 3, "vn")

    corners = _obj_corners(data, starts, ends, flines, label) if len(flines) else None
    if corners is None:
        corners = _obj_corners_slow(data, starts, ends, flines, label)
    nv, vi, ti, ni = corners
    if np.any(nv < 3):
        li = flines[int(np.argmax(nv < 3))]
        raise SceneError(f"a face needs at least 3 vertices: {_show(data, starts[li], ends[li])}",
                         f"{label}:{li + 1}")
    ntri = int(np.sum(nv - 2))
    if ntri > max_triangles:
        raise SceneError(f"too many triangles ({ntri}; the limit is {max_triangles})", label)
    corner_line = np.repeat(flines, nv)
    vi = _resolve_index(vi, np.searchsorted(vlines, corner_line), len(vlines), corner_line,
                        label, "vertex")
    ti = _resolve_index(ti, np.searchsorted(tlines, corner_line), len(tlines), corner_line,
                        label, "texture coordinate")
    ni = _resolve_index(ni, np.searchsorted(nlines, corner_line), len(nlines), corner_line,
                        label, "normal")
    if np.any(vi < 0):
        c = int(np.argmax(vi < 0))
        raise SceneError("face vertex index 0 is invalid (OBJ indices start at 1)",
                         f"{label}:{int(corner_line[c]) + 1}")
    has_t, has_n = bool(np.any(ti >= 0)), bool(np.any(ni >= 0))
    if has_n and np.any(ni < 0):
        notes.append("some faces have normals and some do not: the file's normals are ignored")
        has_n = False
        ni = np.full_like(ni, -1)
    if has_t and np.any(ti < 0):
        notes.append("some faces have texture coordinates and some do not: those get (0, 0)")
    tri_corners, tri_poly = _fan(nv)
    normals = uvs = None
    if not has_t and not has_n:
        faces = vi[tri_corners]
    else:
        ti_k = ti if has_t else np.full_like(ti, -1)
        ni_k = ni if has_n else np.full_like(ni, -1)
        nt, nn = len(tlines) + 1, len(nlines) + 1
        if (len(vlines) + 1) * nt * nn < (1 << 62):
            key = (vi * nt + (ti_k + 1)) * nn + (ni_k + 1)
            ukeys, inverse = np.unique(key, return_inverse=True)
            uv_ = ukeys // (nt * nn)
            ut = (ukeys // nn) % nt - 1
            un = ukeys % nn - 1
        else:
            rows = np.stack([vi, ti_k, ni_k], axis=1)
            urows, inverse = np.unique(rows, axis=0, return_inverse=True)
            uv_, ut, un = urows[:, 0], urows[:, 1], urows[:, 2]
        inverse = inverse.reshape(-1)
        if len(np.unique(uv_)) == len(uv_):
            # every position pairs with one UV and normal: keep the file's vertices
            faces = vi[tri_corners]
            if has_t:
                uvs = np.zeros((len(positions), 2))
                uvs[uv_] = np.where((ut >= 0)[:, None], texcoords[np.maximum(ut, 0)], 0.0)
            if has_n:
                normals = np.zeros((len(positions), 3))
                normals[uv_] = normals_in[un]
        else:
            faces = inverse[tri_corners]
            positions = positions[uv_]
            if has_t:
                uvs = np.where((ut >= 0)[:, None], texcoords[np.maximum(ut, 0)], 0.0)
            if has_n:
                normals = normals_in[un]
    tri_prefix = np.concatenate([[0], np.cumsum(nv - 2)])
    face_groups = _runs(mtl_lines, mtl_names, flines, tri_prefix) if mtl_lines else None
    objects = _runs(obj_lines, obj_names, flines, tri_prefix) if obj_lines else None
    return MeshData(positions=np.ascontiguousarray(positions, np.float64),
                    faces=np.ascontiguousarray(faces.reshape(-1, 3), np.int64),
                    normals=None if normals is None else np.ascontiguousarray(normals),
                    uvs=None if uvs is None else np.ascontiguousarray(uvs),
                    face_groups=face_groups, objects=objects, mtllibs=mtllibs, notes=notes)


def read_mtl(path: Path, *, label: str | None = None,
             max_bytes: int = 16 * 1024 * 1024) -> dict[str, dict[str, list[str]]]:
    """A Wavefront MTL file: {material: {keyword: [arguments]}} (Kd, Ks, Ns,
    d, Ni, illum, map_Kd, ...), as written; the importer maps them."""
    path = Path(path)
    label = label or path.name
    if not path.is_file():
        raise SceneError(f"material library not found: {label}", label)
    if path.stat().st_size > max_bytes:
        raise SceneError(f"material library too large (limit {max_bytes} bytes)", label)
    out: dict[str, dict[str, list[str]]] = {}
    current = None
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if parts[0] == "newmtl":
            current = " ".join(parts[1:])
            out[current] = {}
        elif current is None:
            raise SceneError(f"'{parts[0][:20]}' before any newmtl", f"{label}:{lineno}")
        else:
            out[current][parts[0]] = parts[1:]
    return out


# ----------------------------------------------------------------------------
# PLY.

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


# ----------------------------------------------------------------------------
# Mitsuba .serialized: shapes, each a little-endian uint16 0x041C, uint16
# version (3 or 4), then a zlib stream: uint32 flags, (v4) a NUL-terminated
# name, uint64 vertex and triangle counts, positions, [normals], [uvs],
# [colours] in float32 or float64, then uint32 (uint64 past 2^32 vertices)
# indices. The file ends with each shape's offset (uint64; uint32 in v3) and
# a uint32 shape count.

_SER_NORMALS, _SER_UVS, _SER_COLORS, _SER_FACE_NORMALS = 0x1, 0x2, 0x8, 0x10
_SER_SINGLE, _SER_DOUBLE = 0x1000, 0x2000


def _read_serialized(data: bytes, label: str, shape_index: int, max_triangles: int) -> MeshData:
    if len(data) < 8 or struct.unpack_from("<H", data, 0)[0] != 0x041C:
        raise SceneError("not a Mitsuba .serialized file (bad header)", label)
    version = struct.unpack_from("<H", data, 2)[0]
    if version not in (3, 4):
        raise SceneError(f"unknown .serialized version {version} (3 and 4 are read)", label)
    (count,) = struct.unpack_from("<I", data, len(data) - 4)
    osize = 8 if version == 4 else 4
    table = len(data) - 4 - count * osize
    if count == 0 or table < 4:
        raise SceneError(f"the end-of-file table announces {count} shapes; the file has "
                         f"{len(data)} bytes", label)
    if not 0 <= shape_index < count:
        raise SceneError(f"shape_index {shape_index} is out of range (the file holds {count} "
                         f"shape{'s' if count != 1 else ''}: 0..{count - 1})", label)
    offsets = np.frombuffer(data, "<u8" if version == 4 else "<u4", count, table).astype(np.int64)
    if np.any(offsets < 0) or np.any(offsets > table - 4) or np.any(np.diff(offsets) <= 0):
        raise SceneError("the end-of-file table of shape offsets is inconsistent", label)
    start = int(offsets[shape_index])
    stop = int(offsets[shape_index + 1]) if shape_index + 1 < count else table
    where = f"{label} (shape {shape_index})"
    if struct.unpack_from("<HH", data, start) != (0x041C, version):
        raise SceneError("shape header missing at its offset", where)
    z = zlib.decompressobj()
    src = data[start + 4:stop]
    try:
        head = z.decompress(src, 4 + MAX_HEADER_BYTES + 16)
    except zlib.error as exc:
        raise SceneError(f"corrupt compressed data: {exc}", where) from None
    if len(head) < 4:
        raise SceneError("truncated shape", where)
    (flags,) = struct.unpack_from("<I", head, 0)
    pos, name = 4, ""
    if version == 4:
        nul = head.find(b"\0", 4)
        if nul < 0:
            raise SceneError("the shape's name is not terminated", where)
        name = head[4:nul].decode("utf-8", "replace")
        pos = nul + 1
    if len(head) < pos + 16:
        raise SceneError("truncated shape", where)
    nverts, ntris = struct.unpack_from("<QQ", head, pos)
    pos += 16
    if ntris > max_triangles:
        raise SceneError(f"too many triangles ({ntris}; the limit is {max_triangles})", where)
    if nverts > 3 * max_triangles + 3:
        raise SceneError(f"too many vertices ({nverts})", where)
    fsize = 8 if flags & _SER_DOUBLE else 4
    per_vertex = 3 + 3 * bool(flags & _SER_NORMALS) + 2 * bool(flags & _SER_UVS) + \
        3 * bool(flags & _SER_COLORS)
    isize = 8 if nverts > 0xFFFFFFFF else 4
    need = pos + nverts * per_vertex * fsize + ntris * 3 * isize
    # zlib rarely compresses better than ~1000:1; a larger claim is a hostile count
    if need - pos > 1032 * max(len(src), 1) + 4096:
        raise SceneError(f"the shape announces {nverts} vertices and {ntris} triangles, far "
                         f"more than its {len(src)} compressed bytes can hold", where)
    try:
        rest = z.decompress(z.unconsumed_tail, need - len(head) + 1) if len(head) < need else b""
    except zlib.error as exc:
        raise SceneError(f"corrupt compressed data: {exc}", where) from None
    raw = head + rest
    if len(raw) < need:
        raise SceneError(f"truncated shape: {len(raw)} bytes of {need} decompressed", where)
    fdt = "<f8" if fsize == 8 else "<f4"

    def take(n, dt, size):
        nonlocal pos
        a = np.frombuffer(raw, dt, n, pos)
        pos += n * size
        return a

    positions = take(nverts * 3, fdt, fsize).astype(np.float64).reshape(-1, 3)
    normals = uvs = None
    if flags & _SER_NORMALS:
        normals = take(nverts * 3, fdt, fsize).astype(np.float64).reshape(-1, 3)
    if flags & _SER_UVS:
        uvs = take(nverts * 2, fdt, fsize).astype(np.float64).reshape(-1, 2)
    if flags & _SER_COLORS:
        take(nverts * 3, fdt, fsize)
    faces = take(ntris * 3, "<u8" if isize == 8 else "<u4", isize).astype(np.int64).reshape(-1, 3)
    if len(faces) and faces.max() >= nverts:
        t = int(np.argmax(np.any(faces >= nverts, axis=1)))
        raise SceneError(f"triangle {t} names vertex {int(faces[t].max())}; the shape has "
                         f"{nverts} vertices", where)
    notes = [f"vertex colours of shape '{name}' ignored"] if flags & _SER_COLORS else []
    return MeshData(positions=positions, faces=faces, normals=normals, uvs=uvs,
                    face_normals=bool(flags & _SER_FACE_NORMALS), notes=notes,
                    objects=[(name, 0, len(faces))] if name else None)


def write_serialized(path: Path, shapes: list[MeshData], *, version: int = 4,
                     double: bool = False) -> None:
    """Write meshes as a Mitsuba .serialized file (tests and tools make inputs with it)."""
    fdt = "<f8" if double else "<f4"
    out = bytearray()
    offsets = []
    for mesh in shapes:
        offsets.append(len(out))
        flags = _SER_DOUBLE if double else _SER_SINGLE
        flags |= _SER_NORMALS if mesh.normals is not None else 0
        flags |= _SER_UVS if mesh.uvs is not None else 0
        flags |= _SER_FACE_NORMALS if mesh.face_normals else 0
        payload = bytearray(struct.pack("<I", flags))
        if version == 4:
            name = mesh.objects[0][0] if mesh.objects else ""
            payload += name.encode() + b"\0"
        payload += struct.pack("<QQ", len(mesh.positions), len(mesh.faces))
        payload += np.asarray(mesh.positions, fdt).tobytes()
        if mesh.normals is not None:
            payload += np.asarray(mesh.normals, fdt).tobytes()
        if mesh.uvs is not None:
            payload += np.asarray(mesh.uvs, fdt).tobytes()
        payload += np.asarray(mesh.faces, "<u4").tobytes()
        out += struct.pack("<HH", 0x041C, version) + zlib.compress(bytes(payload))
    out += np.asarray(offsets, "<u8" if version == 4 else "<u4").tobytes()
    out += struct.pack("<I", len(shapes))
    Path(path).write_bytes(bytes(out))
