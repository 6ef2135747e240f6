"""Mitsuba's .serialized meshes (see renderer.meshio).

A file of shapes, each a little-endian uint16 0x041C, uint16
version (3 or 4), then a zlib stream: uint32 flags, (v4) a NUL-terminated
name, uint64 vertex and triangle counts, positions, [normals], [uvs],
[colours] in float32 or float64, then uint32 (uint64 past 2^32 vertices)
indices. The file ends with each shape's offset (uint64; uint32 in v3) and
a uint32 shape count.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import SceneError
from .common import MAX_HEADER_BYTES, MeshData

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
