"""Scene assets: meshes and textures as immutable binary blobs named by digest.

    blob = encode_mesh(positions, faces, normals, uvs)
    digest = asset_digest(blob)              # sha256 hex: the asset's name
    asset = decode_asset(blob)               # Asset(kind="mesh", positions=..., ...)

A resolved scene names its meshes and textures by digest (``{"type": "mesh",
"mesh": "<digest>"}``); the blobs travel beside the document (the store, the
executors, the CLI), so the document stays small and its hash is still the
scene's identity. An *asset source* is any callable digest -> blob;
`load_asset` fetches through one and checks the digest.

The encoding is canonical (the same arrays give the same bytes): a 16-byte
header, then little-endian arrays::

    magic b"RFAS", u16 version 1, u16 kind (1 mesh, 2 texture), u32 flags, u32 0
    mesh:    u64 V, u64 F, positions f64 (V, 3), faces u32 (F, 3),
             [normals f32 (V, 3) if flags & 1], [uvs f32 (V, 2) if flags & 2]
    texture: u32 H, u32 W, u32 C, u32 0, texels f32 (H, W, C), linear values

Positions stay float64 (the renderer's geometry is float64, and inline
meshes of today's scenes keep their exact coordinates); normals and UVs are
float32, as in Mitsuba's own meshes. -0.0 is stored as 0.0. Decoding checks
everything (sizes against the blob's length before any allocation, counts
within limits, indices within range, values finite) and refuses a malformed
blob with a SceneError; arrays are read-only views of the blob.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from .errors import SceneError

__all__ = ["Asset", "AssetSource", "encode_mesh", "encode_texture", "decode_asset",
           "asset_digest", "asset_header", "load_asset", "is_digest", "MAX_ASSET_TRIANGLES",
           "MAX_ASSET_VERTICES", "MAX_TEXTURE_TEXELS", "DirectorySource", "write_assets"]

MAGIC = b"RFAS"
VERSION = 1
KIND_MESH, KIND_TEXTURE = 1, 2
FLAG_NORMALS, FLAG_UVS = 1, 2
_HEADER = struct.Struct("<4sHHII")  # magic, version, kind, flags, reserved
_MESH_COUNTS = struct.Struct("<QQ")
_TEX_DIMS = struct.Struct("<IIII")
MAX_ASSET_TRIANGLES = 5_000_000
MAX_ASSET_VERTICES = 3 * MAX_ASSET_TRIANGLES
MAX_TEXTURE_TEXELS = 64 * 1024 * 1024  # pixels (an 8192^2 image)
_DIGEST = re.compile(r"[0-9a-f]{64}\Z")

AssetSource = Callable[[str], bytes]


@dataclass(frozen=True)
class Asset:
    """A decoded asset. Meshes: positions (V, 3) f64, faces (F, 3) u32,
    normals (V, 3) f32 | None, uvs (V, 2) f32 | None. Textures: texels
    (H, W, C) f32."""

    kind: str
    positions: np.ndarray | None = None
    faces: np.ndarray | None = None
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    texels: np.ndarray | None = None

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.positions, self.faces, self.normals, self.uvs,
                                      self.texels) if a is not None)


def asset_digest(blob: bytes) -> str:
    """The asset's name: the SHA-256 of its bytes, 64 lower-case hex digits."""
    return hashlib.sha256(blob).hexdigest()


def is_digest(value) -> bool:
    return isinstance(value, str) and bool(_DIGEST.match(value))


def _le(a: np.ndarray, dtype: str) -> bytes:
    out = np.ascontiguousarray(a, dtype=dtype)
    if out.dtype.kind == "f":
        out = out + out.dtype.type(0.0)  # -0.0 -> 0.0: the same value gives the same bytes
    return out.tobytes()


def encode_mesh(positions, faces, normals=None, uvs=None) -> bytes:
    """The canonical blob of a triangle mesh (arrays are checked, not trusted)."""
    p = np.asarray(positions, dtype=np.float64)
    f = np.asarray(faces)
    if p.ndim != 2 or p.shape[1] != 3:
        raise SceneError(f"mesh positions must be (V, 3), got {p.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and f.dtype.kind not in "iu"):
        raise SceneError(f"mesh faces must be (F, 3) integers, got {f.shape} {f.dtype}")
    if len(p) > MAX_ASSET_VERTICES or len(f) > MAX_ASSET_TRIANGLES:
        raise SceneError(f"mesh too large ({len(p)} vertices, {len(f)} triangles; the limits "
                         f"are {MAX_ASSET_VERTICES} and {MAX_ASSET_TRIANGLES})")
    if f.size and (f.min() < 0 or f.max() >= len(p)):
        raise SceneError(f"face index out of range (mesh has {len(p)} vertices)")
    flags, parts = 0, []
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64)
        if n.shape != p.shape:
            raise SceneError(f"mesh normals must be (V, 3) like positions, got {n.shape}")
        flags |= FLAG_NORMALS
        parts.append(_le(n, "<f4"))
    if uvs is not None:
        t = np.asarray(uvs, dtype=np.float64)
        if t.shape != (len(p), 2):
            raise SceneError(f"mesh uvs must be (V, 2), got {t.shape}")
        flags |= FLAG_UVS
        parts.append(_le(t, "<f4"))
    head = _HEADER.pack(MAGIC, VERSION, KIND_MESH, flags, 0) + _MESH_COUNTS.pack(len(p), len(f))
    return b"".join([head, _le(p, "<f8"), _le(f, "<u4"), *parts])


def encode_texture(texels) -> bytes:
    """The canonical blob of an (H, W, C) texture of linear values, C in 1, 3, 4."""
    t = np.asarray(texels, dtype=np.float32)
    if t.ndim == 2:
        t = t[:, :, None]
    if t.ndim != 3 or t.shape[2] not in (1, 3, 4) or t.shape[0] < 1 or t.shape[1] < 1:
        raise SceneError(f"texture texels must be (H, W, C) with C in 1, 3, 4, got {t.shape}")
    if t.shape[0] * t.shape[1] > MAX_TEXTURE_TEXELS:
        raise SceneError(f"texture too large ({t.shape[1]} x {t.shape[0]}; the limit is "
                         f"{MAX_TEXTURE_TEXELS} pixels)")
    h, w, c = t.shape
    return b"".join([_HEADER.pack(MAGIC, VERSION, KIND_TEXTURE, 0, 0),
                     _TEX_DIMS.pack(h, w, c, 0), _le(t, "<f4")])


def asset_header(blob: bytes) -> dict:
    """What a blob holds, from its header alone (no arrays decoded, sizes
    checked): {"kind", "bytes", and "vertices", "triangles", "normals", "uvs"
    for meshes or "width", "height", "channels" for textures}. Admission
    counts triangles and bytes with it."""
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise SceneError("an asset must be bytes")
    n = len(blob)
    if n < _HEADER.size:
        raise SceneError(f"asset too short ({n} bytes) to hold a header")
    magic, version, kind, flags, reserved = _HEADER.unpack_from(blob, 0)
    if magic != MAGIC:
        raise SceneError("not a rayfarm asset (bad magic)")
    if version != VERSION:
        raise SceneError(f"unknown asset version {version} (this renderer reads {VERSION})")
    if reserved:
        raise SceneError("asset header's reserved field is not zero")
    if kind == KIND_MESH:
        if flags & ~(FLAG_NORMALS | FLAG_UVS):
            raise SceneError(f"unknown mesh flags {flags:#x}")
        if n < _HEADER.size + _MESH_COUNTS.size:
            raise SceneError("mesh asset truncated in its header")
        nv, nf = _MESH_COUNTS.unpack_from(blob, _HEADER.size)
        if nv > MAX_ASSET_VERTICES or nf > MAX_ASSET_TRIANGLES:
            raise SceneError(f"mesh asset too large ({nv} vertices, {nf} triangles)")
        per_v = 24 + (12 if flags & FLAG_NORMALS else 0) + (8 if flags & FLAG_UVS else 0)
        want = _HEADER.size + _MESH_COUNTS.size + nv * per_v + nf * 12
        if n != want:
            raise SceneError(f"mesh asset of {nv} vertices and {nf} triangles must have "
                             f"{want} bytes, not {n}")
        return {"kind": "mesh", "bytes": n, "vertices": nv, "triangles": nf,
                "normals": bool(flags & FLAG_NORMALS), "uvs": bool(flags & FLAG_UVS)}
    if kind == KIND_TEXTURE:
        if flags:
            raise SceneError(f"unknown texture flags {flags:#x}")
        if n < _HEADER.size + _TEX_DIMS.size:
            raise SceneError("texture asset truncated in its header")
        h, w, c, pad = _TEX_DIMS.unpack_from(blob, _HEADER.size)
        if c not in (1, 3, 4) or h < 1 or w < 1 or pad:
            raise SceneError(f"texture asset of {w} x {h} x {c} is malformed")
        if h * w > MAX_TEXTURE_TEXELS:
            raise SceneError(f"texture asset too large ({w} x {h})")
        want = _HEADER.size + _TEX_DIMS.size + h * w * c * 4
        if n != want:
            raise SceneError(f"texture asset of {w} x {h} x {c} must have {want} bytes, not {n}")
        return {"kind": "texture", "bytes": n, "width": w, "height": h, "channels": c}
    raise SceneError(f"unknown asset kind {kind}")


def decode_asset(blob: bytes) -> Asset:
    """The arrays of a blob, validated (see the module doc)."""
    info = asset_header(blob)
    if info["kind"] == "texture":
        off = _HEADER.size + _TEX_DIMS.size
        t = np.frombuffer(blob, "<f4", info["height"] * info["width"] * info["channels"], off)
        if not np.all(np.isfinite(t)):
            raise SceneError("texture asset holds non-finite texels")
        return Asset(kind="texture",
                     texels=t.reshape(info["height"], info["width"], info["channels"]))
    nv, nf = info["vertices"], info["triangles"]
    off = _HEADER.size + _MESH_COUNTS.size
    p = np.frombuffer(blob, "<f8", nv * 3, off).reshape(nv, 3)
    off += nv * 24
    f = np.frombuffer(blob, "<u4", nf * 3, off).reshape(nf, 3)
    off += nf * 12
    n = t = None
    if info["normals"]:
        n = np.frombuffer(blob, "<f4", nv * 3, off).reshape(nv, 3)
        off += nv * 12
    if info["uvs"]:
        t = np.frombuffer(blob, "<f4", nv * 2, off).reshape(nv, 2)
    for name, a in (("positions", p), ("normals", n), ("uvs", t)):
        if a is not None and not np.all(np.isfinite(a)):
            raise SceneError(f"mesh asset holds non-finite {name}")
    if nf and int(f.max()) >= nv:
        raise SceneError(f"mesh asset's faces name vertex {int(f.max())} of {nv}")
    return Asset(kind="mesh", positions=p, faces=f, normals=n, uvs=t)


def load_asset(source: AssetSource | Mapping[str, bytes] | None, digest: str,
               where: str = "") -> bytes:
    """The blob named `digest` from `source` (a callable or a mapping),
    checked against its digest; a SceneError at `where` if it is missing or
    does not match."""
    if not is_digest(digest):
        raise SceneError("an asset is named by its SHA-256: 64 lower-case hex digits", where)
    if source is None:
        raise SceneError(f"asset {digest[:12]} is not available (no asset source given)", where)
    try:
        blob = source[digest] if isinstance(source, Mapping) else source(digest)
    except (KeyError, FileNotFoundError):
        blob = None
    if blob is None:
        raise SceneError(f"asset {digest[:12]} is not available", where)
    if asset_digest(blob) != digest:
        raise SceneError(f"asset {digest[:12]} does not match its digest", where)
    return bytes(blob) if not isinstance(blob, bytes) else blob


class DirectorySource:
    """An asset source reading `<directory>/<digest>` files (the store's
    asset folder, a render's temporary folder); picklable, so it crosses
    process boundaries as a path."""

    def __init__(self, directory):
        self.directory = str(directory)

    def __call__(self, digest: str) -> bytes:
        if not is_digest(digest):
            raise KeyError(digest)
        import os

        with open(os.path.join(self.directory, digest), "rb") as fh:
            return fh.read()

    def __repr__(self) -> str:
        return f"DirectorySource({self.directory!r})"


def write_assets(directory, assets: Mapping[str, bytes]) -> None:
    """Write blobs as `<directory>/<digest>` files (a DirectorySource reads them)."""
    import os

    os.makedirs(directory, exist_ok=True)
    for digest, blob in assets.items():
        if not is_digest(digest) or asset_digest(blob) != digest:
            raise SceneError(f"asset {str(digest)[:12]} does not match its digest")
        path = os.path.join(directory, digest)
        if not os.path.exists(path):
            tmp = path + ".tmp"
            with open(tmp, "wb") as fh:
                fh.write(blob)
            os.replace(tmp, path)
