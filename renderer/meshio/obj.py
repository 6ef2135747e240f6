"""Wavefront OBJ and MTL (see renderer.meshio)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import SceneError
from .common import MeshData, _fan, _floats, _per_line, _token_starts

_K_OTHER, _K_SKIP, _K_V, _K_VT, _K_VN, _K_F, _K_INDENTED = 0, 1, 2, 3, 4, 5, 6


def _line_table(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start and end (exclusive, before the newline) offsets of every line, and
    each line's kind, classified from its first bytes."""
    buf = np.frombuffer(data, np.uint8)
    if not len(buf):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8)
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
        plural = {"vertex": "vertices"}.get(what, what + "s")
        raise SceneError(f"face {what} index {int(raw[c])} is out of range (the file has {total} "
                         f"{plural}{' above this line' if raw[c] < 0 else ''})",
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
        # Does every position pair with one UV and one normal? (a scatter and a
        # gather: most exporters write such files, and then nothing is split)
        functional = True
        for attr in (ti_k, ni_k):
            seen = np.full(len(positions), -2, np.int64)
            seen[vi] = attr
            functional = functional and bool(np.array_equal(seen[vi], attr))
        if functional:
            faces = vi[tri_corners]
            if has_t:
                uvs = np.zeros((len(positions), 2))
                uvs[vi] = np.where((ti_k >= 0)[:, None], texcoords[np.maximum(ti_k, 0)], 0.0)
            if has_n:
                normals = np.zeros((len(positions), 3))
                normals[vi] = normals_in[ni_k]
        else:
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
            faces = inverse.reshape(-1)[tri_corners]
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
