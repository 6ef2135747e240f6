"""The container: a .gltf's JSON or a .glb's chunks, buffers by relative
URI or data: URI, and the buffer views over them."""

from __future__ import annotations

import base64
import binascii
import json
import struct
import urllib.parse
from pathlib import Path

from ...scene_format import MAX_FILE_BYTES, _nesting
from .reader import _Reader

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
MAX_JSON_NESTING = 64
MAX_TOTAL_BYTES = 1024 * 1024 * 1024  # buffers and images read, all together


class _Container(_Reader):
    # -- files ----------------------------------------------------------------

    def count_bytes(self, n: int, ptr: str) -> None:
        self.bytes_read += n
        if self.bytes_read > MAX_TOTAL_BYTES:
            raise self.fail(f"the buffers and images read exceed {MAX_TOTAL_BYTES} bytes", ptr)

    def local_file(self, uri: str, ptr: str) -> Path:
        """A relative URI resolved inside the root folder."""
        if "\\" in uri or uri.startswith("/") or "\0" in uri:
            raise self.fail(f"URI {uri!r} is not a relative path", ptr)
        parsed = urllib.parse.urlsplit(uri)
        if parsed.scheme or parsed.netloc:
            raise self.fail(f"URI {uri!r}: only relative paths and data: URIs are read", ptr)
        rel = urllib.parse.unquote(parsed.path)
        target = (self.path.parent / rel).resolve()
        if target != self.root and self.root not in target.parents:
            raise self.fail(f"URI {uri!r} leads outside the scene's folder", ptr)
        if not target.is_file():
            raise self.fail(f"file not found: {rel}", ptr)
        if target.stat().st_size > MAX_FILE_BYTES:
            raise self.fail(f"{rel} is larger than {MAX_FILE_BYTES} bytes", ptr)
        return target

    def data_uri(self, uri: str, ptr: str) -> tuple[bytes, str]:
        """The bytes and media type of a base64 data: URI."""
        head, sep, payload = uri.partition(",")
        if not sep or not head.endswith(";base64"):
            raise self.fail("a data: URI must be base64 (data:<type>;base64,...)", ptr)
        if len(payload) > MAX_FILE_BYTES * 4 // 3 + 4:
            raise self.fail(f"data: URI larger than {MAX_FILE_BYTES} bytes", ptr)
        try:
            data = base64.b64decode(payload, validate=True)
        except (binascii.Error, ValueError):
            raise self.fail("data: URI is not valid base64", ptr) from None
        self.count_bytes(len(data), ptr)
        return data, head[len("data:"):-len(";base64")]

    def load(self) -> None:
        p = self.path
        if not p.is_file():
            raise self.fail("file not found")
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise self.fail(f"file larger than {MAX_FILE_BYTES} bytes")
        data = p.read_bytes()
        if p.suffix.lower() == ".glb" or data[:4] == GLB_MAGIC:
            text = self.parse_glb(data)
        else:
            text = data
        try:
            s = text.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise self.fail(f"the JSON is not UTF-8 (byte {exc.start})") from None

        def no_constants(name):
            raise ValueError(f"{name} is not JSON")
        try:
            gltf = json.loads(s, parse_constant=no_constants)
        except json.JSONDecodeError as exc:
            raise self.fail(f"invalid JSON at line {exc.lineno}, column {exc.colno}: "
                            f"{exc.msg}") from None
        except (ValueError, RecursionError) as exc:
            raise self.fail(f"invalid JSON: {exc}"[:200]) from None
        if _nesting(gltf) > MAX_JSON_NESTING:
            raise self.fail(f"the JSON nests more than {MAX_JSON_NESTING} levels deep")
        self.gltf = self.obj(gltf, "")

    def parse_glb(self, data: bytes) -> bytes:
        if len(data) < 20:
            raise self.fail("a .glb needs a 12-byte header and a JSON chunk")
        magic, version, length = struct.unpack_from("<4sII", data, 0)
        if magic != GLB_MAGIC:
            raise self.fail("not a binary glTF (.glb): the file does not start with 'glTF'")
        if version != 2:
            raise self.fail(f"binary glTF version {version} (this importer reads version 2)")
        if length != len(data):
            raise self.fail(f"the .glb header gives a length of {length} bytes, the file "
                            f"has {len(data)}")
        offset, chunks = 12, []
        while offset < length:
            if offset + 8 > length:
                raise self.fail(f"truncated chunk header at byte {offset} of the .glb")
            clen, ctype = struct.unpack_from("<II", data, offset)
            if offset + 8 + clen > length:
                raise self.fail(f"chunk at byte {offset} of the .glb runs past the end of "
                                f"the file ({clen} bytes)")
            chunks.append((ctype, data[offset + 8: offset + 8 + clen]))
            offset += 8 + clen
        if not chunks or chunks[0][0] != CHUNK_JSON:
            raise self.fail("the first chunk of a .glb must be JSON")
        if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN:
            self.bin_chunk = chunks[1][1]
        return chunks[0][1]

    # -- buffers, views ----------------------------------------------------

    def buffer(self, i: int) -> bytes:
        if i in self.buffers:
            return self.buffers[i]
        b, ptr = self.item("buffers", i)
        length = self.get(b, "byteLength", ptr, "int", required=True)
        uri = self.get(b, "uri", ptr, "str")
        if uri is None:
            if i != 0 or self.bin_chunk is None:
                raise self.fail("buffer has no uri (only the first buffer of a .glb may "
                                "stand for its BIN chunk, and this file has none)", ptr)
            data = self.bin_chunk
        elif uri.startswith("data:"):
            data, _ = self.data_uri(uri, f"{ptr}/uri")
        else:
            f = self.local_file(uri, f"{ptr}/uri")
            self.count_bytes(f.stat().st_size, f"{ptr}/uri")
            data = f.read_bytes()
        if len(data) < length:
            raise self.fail(f"byteLength is {length} but the buffer holds {len(data)} bytes",
                            ptr)
        self.buffers[i] = data[:length]
        return self.buffers[i]

    def view(self, i: int) -> tuple[memoryview, int | None, str]:
        v, ptr = self.item("bufferViews", i)
        b = self.index(v, "buffer", ptr, "buffers", required=True)
        offset = self.get(v, "byteOffset", ptr, "int", default=0)
        length = self.get(v, "byteLength", ptr, "int", required=True)
        stride = self.get(v, "byteStride", ptr, "int")
        if stride is not None and not (4 <= stride <= 252 and stride % 4 == 0):
            raise self.fail(f"byteStride must be a multiple of 4 in [4, 252], got {stride}",
                            f"{ptr}/byteStride")
        data = self.buffer(b)
        if offset + length > len(data):
            raise self.fail(f"bytes {offset}..{offset + length} lie outside buffer {b} "
                            f"({len(data)} bytes)", ptr)
        return memoryview(data)[offset:offset + length], stride, ptr

