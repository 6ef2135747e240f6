"""The renderer's on-disk caches (radiosity solutions): a directory and a byte
cap it is handed, least recently used entries evicted.

The renderer is a library: it does not know the farm's data directory. Who
runs it says where its caches live, in this order:

1. `configure(directory, max_bytes)`, called by the service and the Celery
   worker with ``Settings.cache_dir`` (default ``<data_dir>/cache``) and
   ``Settings.cache_max_bytes``; a `LocalPool` hands it to its processes;
2. ``$RAYFARM_CACHE_DIR`` (the renderer's own CLI, the tests);
3. ``$RAYFARM_DATA_DIR/cache``;
4. otherwise no disk cache at all (the in-process caches still work): a
   library call never writes into the home directory or the working directory.

``$RAYFARM_CACHE_MAX_BYTES`` caps the size when `configure` was not called
(default 1 GiB). Each named cache is a subdirectory (``<root>/radiosity``),
a `DiskCache` with the whole cap.

    >>> cache = DiskCache("/tmp/c", max_bytes=1 << 20)
    >>> cache.put("abc", b"bytes"); cache.get("abc")
    b'bytes'
"""

from __future__ import annotations

import os
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["CACHES", "DEFAULT_MAX_BYTES", "DiskCache", "CacheInfo", "cache_root", "configure",
           "disk_cache", "reset"]

DEFAULT_MAX_BYTES = 1 << 30
CACHES = ("radiosity", "assets")  # the named caches of the renderer (subdirectories of the root)
_KEY = re.compile(r"[0-9A-Za-z_-]{1,128}")
_SUFFIX = ".entry"
_STALE_TMP_SECONDS = 3600.0  # a temporary file this old was left by a dead process

_configured: tuple[Path | None, int] | None = None


def configure(directory: str | os.PathLike | None, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
    """Where this process's caches live, whatever the environment says
    (directory None: no disk cache at all)."""
    global _configured
    if max_bytes <= 0:
        raise ValueError(f"max_bytes must be positive, not {max_bytes}")
    _configured = (None if directory is None else Path(directory).expanduser(), int(max_bytes))


def reset() -> None:
    """Forget `configure`: the environment decides again."""
    global _configured
    _configured = None


def cache_root() -> tuple[Path | None, int]:
    """The cache root directory (None: no disk cache) and the byte cap. A
    `LocalPool` hands this to its processes (`configure` there)."""
    if _configured is not None:
        return _configured
    max_bytes = int(os.environ.get("RAYFARM_CACHE_MAX_BYTES") or DEFAULT_MAX_BYTES)
    if os.environ.get("RAYFARM_CACHE_DIR"):
        return Path(os.environ["RAYFARM_CACHE_DIR"]).expanduser(), max_bytes
    if os.environ.get("RAYFARM_DATA_DIR"):
        return Path(os.environ["RAYFARM_DATA_DIR"]).expanduser() / "cache", max_bytes
    return None, max_bytes


def disk_cache(name: str) -> "DiskCache | None":
    """The named cache (see `CACHES`) at the current root, or None (no disk cache)."""
    root, max_bytes = cache_root()
    return None if root is None else DiskCache(root / name, max_bytes)


@dataclass(frozen=True)
class CacheInfo:
    directory: Path
    entries: int
    bytes: int
    max_bytes: int


class DiskCache:
    """Bytes by key in one directory, at most `max_bytes` in total.

    - Writes are atomic (a temporary file, then a rename): a reader sees a
      whole entry or none, also from another process.
    - Least recently used goes first: an entry's modification time is its last
      use (`get` touches it; access times are unreliable under noatime), and
      after each `put` the oldest entries are removed until the total fits.
    - Two processes may share the directory: every step tolerates a file that
      another process removed or replaced meanwhile.
    - Errors of the file system (read-only, full) only cost the reuse: `get`
      returns None, `put` returns False.
    """

    def __init__(self, directory: str | os.PathLike, max_bytes: int = DEFAULT_MAX_BYTES):
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, not {max_bytes}")
        self.directory = Path(directory)
        self.max_bytes = int(max_bytes)

    def path(self, key: str) -> Path:
        if not isinstance(key, str) or not _KEY.fullmatch(key):
            raise ValueError(f"not a valid cache key: {key!r}")
        return self.directory / f"{key}{_SUFFIX}"

    def get(self, key: str) -> bytes | None:
        """The entry's bytes (and it becomes the most recently used), or None."""
        path = self.path(key)
        try:
            data = path.read_bytes()
        except OSError:
            return None
        try:
            os.utime(path)  # touch: used now
        except OSError:
            pass  # evicted meanwhile, or a read-only cache: the bytes are still good
        return data

    def put(self, key: str, data: bytes) -> bool:
        """Store an entry, then evict the least recently used until the total
        fits the cap; False if it was not stored (larger than the cap, or the
        file system refused)."""
        path = self.path(key)
        if len(data) > self.max_bytes:
            return False
        tmp = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=f".{key}.", suffix=".tmp")
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
            os.replace(tmp, path)
            tmp = None
        except OSError:
            return False
        finally:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
        self.evict(keep=path)
        return True

    def _entries(self) -> list[tuple[int, str, int, Path]]:
        """(last use in ns, name, size, path) of every entry; stale temporary files removed."""
        entries = []
        try:
            listing = list(os.scandir(self.directory))
        except OSError:
            return []
        now = time.time()
        for item in listing:
            try:
                st = item.stat(follow_symlinks=False)
            except OSError:
                continue  # removed meanwhile
            if item.name.endswith(_SUFFIX) and item.is_file(follow_symlinks=False):
                entries.append((st.st_mtime_ns, item.name, st.st_size, Path(item.path)))
            elif item.name.endswith(".tmp") and now - st.st_mtime > _STALE_TMP_SECONDS:
                Path(item.path).unlink(missing_ok=True)
        return entries

    def evict(self, keep: Path | None = None) -> int:
        """Remove least recently used entries until the total is within the cap
        (never `keep`, the entry just written); returns how many were removed."""
        entries = sorted(self._entries())
        total = sum(size for _, _, size, _ in entries)
        removed = 0
        for _, _, size, path in entries:
            if total <= self.max_bytes:
                break
            if path == keep:
                continue
            try:
                path.unlink()
                removed += 1
            except FileNotFoundError:
                pass  # another process evicted it: it no longer counts either
            except OSError:
                continue
            total -= size
        return removed

    def clear(self) -> int:
        """Remove every entry (and temporary file); returns how many entries."""
        removed = 0
        try:
            listing = list(os.scandir(self.directory))
        except OSError:
            return 0
        for item in listing:
            if item.name.endswith(_SUFFIX) or item.name.endswith(".tmp"):
                try:
                    os.unlink(item.path)
                    removed += item.name.endswith(_SUFFIX)
                except FileNotFoundError:
                    pass
        return removed

    def info(self) -> CacheInfo:
        entries = self._entries()
        return CacheInfo(self.directory, len(entries), sum(e[2] for e in entries),
                         self.max_bytes)
