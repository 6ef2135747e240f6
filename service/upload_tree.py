"""An upload as a folder: its files placed at their relative paths, or an
archive unpacked, inside one directory; then the main scene file found.

    tree = UploadTree(directory / "tree", limits)
    tree.add_part("files[2]", "models/Mesh000.obj", part_path)   # moved in
    tree.unpack("scene", "room.zip", archive_path)              # or an archive
    main = tree.main_file(requested="scene.xml")                # a relative path
    tree.name                                                   # "room" (the archive's)

Everything a client names is hostile until checked: a path is a relative
POSIX path of plain names (no '..', no absolute path or drive letter, no
backslash, no control character) within the depth and length limits; an
archive member is a regular file or a folder (never a link or a device);
a name comes once. Archives are unpacked by streaming, the limits enforced
on the bytes actually written, never on the sizes an archive declares: the
number of members, the total unpacked bytes, each zip member's compression
ratio (a compressed tar's as a whole) and, for tars, the size of their
extended headers (which `tarfile` reads into memory). Nested archives stay
files. A refusal is an `InvalidRequest` (422) or a `TooLarge` (413) naming
the member. Nothing is written outside the tree: every file is created
there, by this module, with O_EXCL and O_NOFOLLOW.
"""

from __future__ import annotations

import bz2
import gzip
import lzma
import os
import re
import stat
import tarfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from .errors import InvalidRequest, TooLarge

__all__ = ["UploadLimits", "UploadTree", "SCENE_SUFFIXES", "ARCHIVE_SUFFIXES", "archive_kind",
           "scene_suffix"]

SCENE_SUFFIXES = (".json", ".xml", ".gltf", ".glb")
ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tbz2", ".tar.xz", ".txz")
MAX_NAME = 255  # bytes of one file name on common filesystems
CHUNK = 1 << 20
# A member's compression ratio is judged once it has unpacked this much: a
# small file of zeros compresses a thousandfold and is harmless.
RATIO_FLOOR = 1 << 20
# `tarfile` reads a pax or GNU long-name header whole into memory, and a
# chain of them recursively: no read of a tar may ask for more than this.
MAX_TAR_READ = 64 << 10
_DRIVE = re.compile(r"^[A-Za-z]:")
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
_COMPRESSED_TAR = {b"\x1f\x8b": "gzip", b"BZh": "bzip2", b"\xfd7zXZ\x00": "xz"}
_SKIPPED = ("__MACOSX",)  # macOS' resource forks in zips: never the main scene file


@dataclass(frozen=True)
class UploadLimits:
    """What one upload may hold (the settings `max_upload_*`)."""

    max_files: int = 4096
    max_bytes: int = 1 << 30
    max_ratio: float = 200.0
    max_depth: int = 16
    max_path_bytes: int = 1024
    max_seconds: float = 600.0  # the whole check: unpacking and importing

    @classmethod
    def from_settings(cls, settings) -> "UploadLimits":
        return cls(max_files=settings.max_upload_files,
                   max_bytes=settings.max_upload_unpacked_bytes,
                   max_ratio=settings.max_upload_ratio,
                   max_depth=settings.max_upload_depth,
                   max_path_bytes=settings.max_upload_path_bytes,
                   max_seconds=settings.upload_check_seconds)


def scene_suffix(name: str) -> str | None:
    """The scene suffix of a file name (lower case), or None."""
    lowered = name.lower()
    return next((s for s in SCENE_SUFFIXES if lowered.endswith(s)), None)


def archive_kind(name: str, path: Path) -> str | None:
    """"zip" or "tar" if the file is an archive (by its name, else by its first
    bytes), else None. A name that says archive over bytes that are none is a
    422: the client meant an archive."""
    with open(path, "rb") as fh:
        head = fh.read(512)
    by_bytes = ("zip" if head.startswith(_ZIP_MAGIC) else
                "tar" if any(head.startswith(m) for m in _COMPRESSED_TAR) or head[257:262] == b"ustar"
                else None)
    lowered = name.lower()
    by_name = ("zip" if lowered.endswith(".zip") else
               "tar" if lowered.endswith(ARCHIVE_SUFFIXES) else None)
    if by_name is not None and by_bytes != by_name:
        raise InvalidRequest("scene", f"'{name}' is named like a {by_name} archive but is none "
                                      f"({'a ' + by_bytes + ' archive' if by_bytes else 'unknown bytes'})")
    if by_name is None and scene_suffix(name):
        return None  # a scene file by its name: its reader judges its bytes
    return by_bytes


def _quoted(name: str) -> str:
    return repr(name.encode("utf-8", "backslashreplace").decode("utf-8"))


class UploadTree:
    """The folder an upload becomes (see the module doc)."""

    def __init__(self, root: Path, limits: UploadLimits):
        self.root = Path(root)
        self.root.mkdir(mode=0o700)
        self.limits = limits
        self.files: dict[str, str] = {}  # relative path -> where it came from (for messages)
        self.dirs: set[str] = set()
        self.members = 0
        self.bytes = 0
        # What the tree's folder stands for, as renderer.importers.scene_name
        # takes it: an archive's name ("room" of room.zip), "" for files sent
        # alone (their folder's name never comes with them).
        self.name = ""

    # -- paths -----------------------------------------------------------------------------
    def check_path(self, name: str, field: str, what: str, directory: bool = False
                   ) -> tuple[str, ...]:
        """The parts of a client's relative path; `what` names it in messages
        ("archive member 'a/b'", "'a/b'"). An empty path is allowed only for a
        folder (a tar's "./")."""
        def refuse(reason: str):
            raise InvalidRequest(field, f"{what}: {reason}")

        if not isinstance(name, str) or not name:
            refuse("has no name")
        try:
            encoded = name.encode("utf-8")
        except UnicodeEncodeError:
            refuse("its name is not valid UTF-8")
        if any(ord(c) < 32 or c == "\x7f" for c in name):
            refuse("its name holds a control character")
        if "\\" in name:
            refuse("its path holds a backslash (paths inside an upload use '/')")
        if name.startswith("/"):
            refuse("an absolute path (paths inside an upload are relative to its folder)")
        if _DRIVE.match(name):
            refuse("a path with a drive letter (paths inside an upload are relative)")
        parts = tuple(p for p in name.split("/") if p not in ("", "."))
        if ".." in parts:
            refuse("its path leaves the upload's folder ('..')")
        if not parts and not directory:
            refuse("names no file")
        if len(encoded) > self.limits.max_path_bytes:
            refuse(f"its path is longer than {self.limits.max_path_bytes} bytes "
                   "(RAYFARM_MAX_UPLOAD_PATH_BYTES)")
        if any(len(p.encode()) > MAX_NAME for p in parts):
            refuse(f"a name in its path is longer than {MAX_NAME} bytes")
        folders = len(parts) - (0 if directory else 1)
        if folders > self.limits.max_depth:
            refuse(f"its path is {folders} folders deep, more than "
                   f"{self.limits.max_depth} (RAYFARM_MAX_UPLOAD_DEPTH)")
        return parts

    def _count_member(self, field: str, what: str) -> None:
        self.members += 1
        if self.members > self.limits.max_files:
            raise TooLarge(f"{field}: {what}: more than {self.limits.max_files} files in one "
                           "upload (RAYFARM_MAX_UPLOAD_FILES)")

    def _add_dirs(self, parts: tuple[str, ...], field: str, what: str) -> None:
        for i in range(1, len(parts) + 1):
            key = "/".join(parts[:i])
            if key in self.files:
                raise InvalidRequest(field, f"{what}: '{key}' is a file of the upload "
                                            f"({self.files[key]}) and a folder here")
            self.dirs.add(key)

    def _new_file(self, parts: tuple[str, ...], field: str, what: str,
                  origin: str | None = None) -> Path:
        key = "/".join(parts)
        if key in self.files:
            raise InvalidRequest(field, f"{what}: '{key}' is uploaded twice (also as "
                                        f"{self.files[key]})")
        if key in self.dirs:
            raise InvalidRequest(field, f"{what}: '{key}' is a folder of the upload and a "
                                        "file here")
        self._add_dirs(parts[:-1], field, what)
        self.files[key] = origin or what
        target = self.root.joinpath(*parts)
        target.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        return target

    # -- named files -----------------------------------------------------------------------
    def add_part(self, field: str, name: str, source: Path, size: int | None = None) -> str:
        """Move a received part into the tree at its checked relative path; returns it."""
        what = _quoted(name) if name else "a file without a name"
        parts = self.check_path(name, field, what)
        self._count_member(field, what)
        size = source.stat().st_size if size is None else size
        self._count_bytes(size, field, what)
        target = self._new_file(parts, field, what, origin=field)
        os.replace(source, target)
        return "/".join(parts)

    def _count_bytes(self, size: int, field: str, what: str) -> None:
        self.bytes += size
        if self.bytes > self.limits.max_bytes:
            raise TooLarge(f"{field}: {what}: the upload's files hold more than "
                           f"{self.limits.max_bytes} bytes once unpacked "
                           "(RAYFARM_MAX_UPLOAD_UNPACKED_BYTES)")

    # -- archives --------------------------------------------------------------------------
    def unpack(self, field: str, name: str, path: Path, kind: str, scratch: Path) -> None:
        """Unpack the archive at `path` ("zip" or "tar", from `archive_kind`),
        the client's file `name` ("" if it gave none), into the tree;
        `scratch` is a file name beside it for a compressed tar's plain bytes."""
        self.name = _archive_stem(name)
        name = name or "the archive"
        if kind == "zip":
            self._unpack_zip(field, name, path)
        else:
            self._unpack_tar(field, name, path, scratch)

    def _write_member(self, field: str, what: str, parts: tuple[str, ...], source: BinaryIO,
                      packed: int | None, chunk: int = CHUNK) -> None:
        """Stream one member into the tree, counting what it really unpacks to;
        `packed` is its compressed size (None: not known by member)."""
        target = self._new_file(parts, field, what)
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        written = 0
        with os.fdopen(fd, "wb") as out:
            while True:
                data = source.read(chunk)
                if not data:
                    break
                written += len(data)
                self._count_bytes(len(data), field, what)
                if (packed is not None and written > RATIO_FLOOR
                        and written > self.limits.max_ratio * max(packed, 1)):
                    raise TooLarge(f"{field}: {what} unpacks to more than "
                                   f"{self.limits.max_ratio:g} times its compressed size "
                                   f"({packed} bytes): a decompression bomb? "
                                   "(RAYFARM_MAX_UPLOAD_RATIO)")
                out.write(data)

    def _unpack_zip(self, field: str, name: str, path: Path) -> None:
        declared = _zip_declared_entries(path)
        if declared is not None and declared > self.limits.max_files:
            raise TooLarge(f"{field}: the archive {_quoted(name)} holds {declared} members, "
                           f"more than {self.limits.max_files} files in one upload "
                           "(RAYFARM_MAX_UPLOAD_FILES)")
        try:
            archive = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError,
                NotImplementedError) as exc:
            raise InvalidRequest(field, f"{_quoted(name)} is not a readable zip archive: "
                                        f"{exc}") from None
        with archive:
            for info in archive.infolist():
                what = f"archive member {_quoted(info.filename)}"
                self._count_member(field, what)
                mode = info.external_attr >> 16
                kind = stat.S_IFMT(mode)
                if kind == stat.S_IFLNK:
                    raise InvalidRequest(field, f"{what}: a symbolic link (an upload holds "
                                                "files and folders only)")
                if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
                    raise InvalidRequest(field, f"{what}: not a regular file or folder "
                                                f"(mode {oct(mode)})")
                if info.is_dir():
                    self._add_dirs(self.check_path(info.filename, field, what, directory=True),
                                   field, what)
                    continue
                parts = self.check_path(info.filename, field, what)
                if info.flag_bits & 0x1:
                    raise InvalidRequest(field, f"{what}: encrypted (send it unencrypted)")
                try:
                    with archive.open(info) as source:
                        self._write_member(field, what, parts, source, info.compress_size)
                except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError,
                        NotImplementedError, RuntimeError, lzma.LZMAError) as exc:
                    raise InvalidRequest(field, f"{what}: cannot be unpacked: {exc}") from None

    def _unpack_tar(self, field: str, name: str, path: Path, scratch: Path) -> None:
        with open(path, "rb") as fh:
            head = fh.read(6)
        codec = next((c for m, c in _COMPRESSED_TAR.items() if head.startswith(m)), None)
        plain = path
        if codec is not None:
            self._decompress(field, name, path, codec, scratch)
            plain = scratch
        last = None  # the member before a refused header, for the message
        try:
            with open(plain, "rb") as raw:
                archive = tarfile.open(fileobj=_BoundedReads(raw), mode="r:")
                with archive:
                    while True:
                        try:
                            member = archive.next()
                        except (tarfile.TarError, OSError, ValueError, UnicodeError,
                                RecursionError) as exc:
                            raise InvalidRequest(field, f"{_quoted(name)}: a corrupt tar header "
                                                        f"{_after(last)}: {exc}") from None
                        if member is None:
                            break
                        last = _quoted(member.name)
                        self._tar_member(field, archive, member)
        except _LargeRead as exc:
            raise InvalidRequest(field, f"{_quoted(name)}: an extended tar header of {exc.size} "
                                        f"bytes {_after(last)} (at most {MAX_TAR_READ})"
                                        ) from None
        except (tarfile.TarError, OSError, ValueError, UnicodeError, RecursionError) as exc:
            raise InvalidRequest(field, f"{_quoted(name)} is not a readable tar archive: "
                                        f"{exc}") from None
        finally:
            if plain != path:
                plain.unlink(missing_ok=True)

    def _tar_member(self, field: str, archive: tarfile.TarFile, member: tarfile.TarInfo) -> None:
        what = f"archive member {_quoted(member.name)}"
        self._count_member(field, what)
        if member.isdir():
            self._add_dirs(self.check_path(member.name, field, what, directory=True), field, what)
            return
        if not member.isreg() or member.issparse():
            raise InvalidRequest(field, f"{what}: {_tar_kind(member)} (an upload holds files and "
                                        "folders only)")
        parts = self.check_path(member.name, field, what)
        try:
            source = archive.extractfile(member)
            self._write_member(field, what, parts, source, None, chunk=MAX_TAR_READ)
        except (tarfile.TarError, OSError, ValueError, EOFError) as exc:
            raise InvalidRequest(field, f"{what}: cannot be unpacked: {exc}") from None

    def _decompress(self, field: str, name: str, path: Path, codec: str, out_path: Path) -> None:
        """A compressed tar's plain bytes into `out_path`, bounded by the total
        and ratio limits as they are read (the tar's own headers count too)."""
        opener = {"gzip": lambda raw: gzip.GzipFile(fileobj=raw, mode="rb"),
                  "bzip2": bz2.BZ2File, "xz": lzma.LZMAFile}[codec]
        # Headers take 512 bytes a member or more, and padding up to 511 more.
        bound = self.limits.max_bytes + 3 * 1024 * (self.limits.max_files + 2)
        written = 0
        try:
            with open(path, "rb") as raw, opener(raw) as source, open(out_path, "xb") as out:
                while True:
                    chunk = source.read(CHUNK)
                    if not chunk:
                        break
                    written += len(chunk)
                    if written > bound:
                        raise TooLarge(f"{field}: the archive {_quoted(name)} unpacks to more "
                                       f"than {self.limits.max_bytes} bytes "
                                       "(RAYFARM_MAX_UPLOAD_UNPACKED_BYTES)")
                    if written > RATIO_FLOOR and written > self.limits.max_ratio * raw.tell():
                        raise TooLarge(f"{field}: the archive {_quoted(name)} unpacks to more "
                                       f"than {self.limits.max_ratio:g} times its compressed "
                                       "size: a decompression bomb? (RAYFARM_MAX_UPLOAD_RATIO)")
                    out.write(chunk)
        except (OSError, EOFError, zlib.error, lzma.LZMAError, ValueError) as exc:
            raise InvalidRequest(field, f"{_quoted(name)}: its {codec} data is corrupt: "
                                        f"{exc}") from None

    # -- the main scene file ---------------------------------------------------------------
    def main_file(self, requested: str | None = None) -> str:
        """The relative path of the scene file to import: `requested` (the
        form's `main`: a path in the upload, or a name only one file ends
        with), else the one scene file at the shallowest level."""
        scenes = sorted(k for k in self.files if scene_suffix(k)
                        and not any(p.startswith(".") or p in _SKIPPED for p in k.split("/")))
        if requested is not None:
            parts = self.check_path(requested, "main", _quoted(requested))
            key = "/".join(parts)
            if key not in self.files:
                ending = [k for k in self.files if k.endswith("/" + key)]
                if len(ending) != 1:
                    listed = ", ".join(scenes[:20]) or "none"
                    raise InvalidRequest("main", f"no file '{key}' in the upload"
                                         + (f" (several end so: {', '.join(ending[:20])})"
                                            if ending else "") + f"; its scene files: {listed}")
                key = ending[0]
            if not scene_suffix(key):
                raise InvalidRequest("main", f"'{key}' is not a scene file (the main file ends "
                                             f"in {', '.join(SCENE_SUFFIXES)})")
            return key
        if not scenes:
            raise InvalidRequest("scene", "the upload holds no scene file (a file ending in "
                                          f"{', '.join(SCENE_SUFFIXES)})")
        depth = min(k.count("/") for k in scenes)
        shallowest = [k for k in scenes if k.count("/") == depth]
        if len(shallowest) > 1:
            raise InvalidRequest("main", "the upload holds several scene files at its top "
                                         f"level ({', '.join(shallowest[:20])}); name the one "
                                         "to render in the form field main (-F main=scene.xml)")
        return shallowest[0]


def _archive_stem(name: str) -> str:
    """An archive's file name without its folder and suffix ("room" of
    "room.tar.gz"); "" for a name no scene should be called."""
    base = (name or "").replace("\\", "/").rsplit("/", 1)[-1]
    lowered = base.lower()
    suffix = max((s for s in ARCHIVE_SUFFIXES if lowered.endswith(s)), key=len, default="")
    stem = base[:len(base) - len(suffix)]
    return stem if stem.isprintable() and len(stem.encode("utf-8", "replace")) <= MAX_NAME else ""


def _after(member: str | None) -> str:
    return f"after archive member {member}" if member else "before its first member"


def _tar_kind(member: tarfile.TarInfo) -> str:
    if member.issym():
        return f"a symbolic link to {_quoted(member.linkname)}"
    if member.islnk():
        return f"a hard link to {_quoted(member.linkname)}"
    if member.ischr() or member.isblk():
        return "a device"
    if member.isfifo():
        return "a FIFO"
    if member.issparse():
        return "a sparse file"
    return f"a tar member of type {member.type!r}"


def _zip_declared_entries(path: Path) -> int | None:
    """The entry count a zip's end record declares (None if not found): a
    zip declaring a million members is refused before `zipfile` builds them."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        fh.seek(max(0, size - (1 << 16) - 22))
        tail = fh.read()
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(tail):
        return None
    count = int.from_bytes(tail[at + 10:at + 12], "little")
    if count == 0xFFFF and at >= 20 and tail[at - 20:at - 16] == b"PK\x06\x07":
        return None  # zip64: zipfile reads its record; the member count is checked as it goes
    return count


class _LargeRead(Exception):
    def __init__(self, size):
        self.size = size


class _BoundedReads:
    """A tar file for `tarfile` that refuses any one read above MAX_TAR_READ
    (the data of members is read in chunks of that size)."""

    def __init__(self, raw: BinaryIO):
        self.raw = raw

    def read(self, size: int = -1) -> bytes:
        if size is None or size < 0 or size > MAX_TAR_READ:
            raise _LargeRead(size)
        return self.raw.read(size)

    def seek(self, offset: int, whence: int = 0) -> int:
        return self.raw.seek(offset, whence)

    def tell(self) -> int:
        return self.raw.tell()
