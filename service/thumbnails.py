"""Scene thumbnails, rendered by one background thread of the service.

    thumbnails = Thumbnailer(store, pending=lambda: [scene_hash, ...])
    thumbnails.start()             # then renders every pending scene without a PNG
    thumbnails.request(scene_hash) # after an upload
    thumbnails.stop()

A thumbnail is the scene's camera view at most `SIZE` px on its long side (the
camera's aspect kept; smaller cameras keep their size), path traced with
`SPP` samples and `DEPTH` bounces, written atomically as
``<data>/store/scenes/<hash>.png``: content-addressed, so once per scene ever.
Never inside a request. It is rendered in `TILE`-px units, because a Numba
kernel holds the GIL while it runs: between units the service answers
requests. The thread uses one Numba thread, leaving the cores to the render
processes.
"""

from __future__ import annotations

import io
import json
import logging
import queue
import threading
from typing import Callable, Iterable

from renderer import RenderSpec, build_scene, merge, plan, run_unit
from renderer.film import tonemap_srgb8

from .store import Store

__all__ = ["Thumbnailer", "render_thumbnail", "thumbnail_size", "SIZE", "SPP", "DEPTH", "TILE"]

log = logging.getLogger(__name__)

SIZE = 128
SPP = 16
DEPTH = 3
TILE = 32


def thumbnail_size(width: int, height: int, size: int = SIZE) -> tuple[int, int]:
    """(w, h) with the long side at most `size`: ``thumbnail_size(256, 192) == (128, 96)``."""
    scale = min(1.0, size / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def render_thumbnail(doc: dict, stop: threading.Event | None = None) -> bytes | None:
    """PNG bytes of a resolved document's thumbnail (None if `stop` was set meanwhile)."""
    from PIL import Image

    width, height = thumbnail_size(doc["camera"]["width"], doc["camera"]["height"])
    spec = RenderSpec(method="path", spp=SPP, depth=DEPTH, width=width, height=height,
                      tile_size=TILE).validate()
    scene = build_scene(doc)
    parts = []
    for unit in plan(spec):
        if stop is not None and stop.is_set():
            return None
        parts.append(run_unit(scene, spec, unit))
    buffer = io.BytesIO()
    Image.fromarray(tonemap_srgb8(merge(width, height, parts).mean())).save(buffer, format="PNG")
    return buffer.getvalue()


class Thumbnailer:
    """Renders the thumbnails of scenes, one after the other, in a daemon thread."""

    def __init__(self, store: Store, pending: Callable[[], Iterable[str]] = tuple):
        self.store = store
        self._pending = pending  # called in the thread at start: scenes that need one
        self._queue: queue.Queue[str] = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.rendered = 0
        self.failed: dict[str, str] = {}  # scene hash -> why (not tried again)

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="rayfarm-thumbnails", daemon=True)
        self._thread.start()

    def request(self, scene_hash: str) -> None:
        """Render `scene_hash`'s thumbnail soon, unless it exists."""
        self._queue.put(scene_hash)

    def stop(self, timeout: float = 30.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        import numba

        numba.set_num_threads(1)  # this thread's kernels only
        try:
            for scene_hash in self._pending():
                self._queue.put(scene_hash)
        except Exception:
            log.exception("listing the scenes that need thumbnails failed")
        while not self._stop.is_set():
            try:
                scene_hash = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            self.make(scene_hash)

    def make(self, scene_hash: str) -> bool:
        """Render and store one thumbnail unless it exists; True if it exists now."""
        path = self.store.thumbnail_path(scene_hash)
        if path.is_file():
            return True
        if scene_hash in self.failed:
            return False
        try:
            png = render_thumbnail(json.loads(self.store.scene_text(scene_hash)), self._stop)
        except Exception as exc:
            log.exception("thumbnail of scene %s failed", scene_hash[:12])
            self.failed[scene_hash] = f"{type(exc).__name__}: {exc}"
            return False
        if png is None:
            return False
        self.store.put_thumbnail(scene_hash, png)
        self.rendered += 1
        return True
