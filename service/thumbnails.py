"""Scene thumbnails, made by one background thread of the service.

    thumbnails = Thumbnailer(store, pending=lambda: [scene_hash, ...])
    thumbnails.start()              # then renders every pending scene without a PNG
    thumbnails.request(scene_hash)  # after an upload
    thumbnails.stop()

A thumbnail is the scene's camera view at most `SIZE` px on its long side (the
camera's aspect kept; smaller cameras keep their size), path traced with
`SPP` samples and `DEPTH` bounces, stored atomically as
``<data>/store/scenes/<hash>.png``: content-addressed, so once per scene ever.
Never inside a request.

The thread renders in a child process, a batch of scenes at a time, and
stores what it sends back. Rendered in the service's own process, a thumbnail
would hold the GIL (Numba kernels do) and take a core from the scheduler and
the requests, which is felt by the farm's timing; the child runs at the
lowest CPU priority (nice 19) on one Numba thread, so jobs and the service
come first, and it can be killed when the service stops.
"""

from __future__ import annotations

import io
import json
import logging
import multiprocessing
import os
import queue
import threading
from pathlib import Path
from typing import Callable, Iterable

from renderer import RenderSpec, build_scene, merge, plan, run_unit
from renderer.film import tonemap_srgb8

from .store import Store

__all__ = ["Thumbnailer", "render_thumbnail", "thumbnail_size", "SIZE", "SPP", "DEPTH"]

log = logging.getLogger(__name__)

SIZE = 128
SPP = 16
DEPTH = 3


def thumbnail_size(width: int, height: int, size: int = SIZE) -> tuple[int, int]:
    """(w, h) with the long side at most `size`: ``thumbnail_size(256, 192) == (128, 96)``."""
    scale = min(1.0, size / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def render_thumbnail(doc: dict, load_asset=None) -> bytes:
    """PNG bytes of a resolved document's thumbnail, rendered in this process
    (its meshes and textures read through `load_asset`, an asset source)."""
    from PIL import Image

    width, height = thumbnail_size(doc["camera"]["width"], doc["camera"]["height"])
    spec = RenderSpec(method="path", spp=SPP, depth=DEPTH, width=width, height=height,
                      tile_size=max(width, height)).validate()
    scene = build_scene(doc, load_asset=load_asset)
    film = merge(width, height, [run_unit(scene, spec, unit) for unit in plan(spec)])
    buffer = io.BytesIO()
    Image.fromarray(tonemap_srgb8(film.mean())).save(buffer, format="PNG")
    return buffer.getvalue()


def _render_in_child(scene_files: list[tuple[str, str]], results,
                     asset_dir: str | None = None) -> None:
    """The child process: for each (hash, scene file) send (hash, png, error)."""
    from renderer.assets import DirectorySource

    try:
        os.nice(19)
    except OSError:
        pass
    import numba

    numba.set_num_threads(1)
    for key, path in scene_files:
        try:
            results.send((key, render_thumbnail(json.loads(Path(path).read_text()),
                                                DirectorySource(asset_dir) if asset_dir else None),
                          None))
        except Exception as exc:
            results.send((key, None, f"{type(exc).__name__}: {exc}"))
    results.close()


class Thumbnailer:
    """Makes the thumbnails of scenes in a daemon thread (see the module doc)."""

    def __init__(self, store: Store, pending: Callable[[], Iterable[str]] = tuple):
        self.store = store
        self._pending = pending  # called in the thread at start: scenes that need one
        self._queue: queue.Queue[str] = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._context = multiprocessing.get_context("forkserver")
        self.rendered = 0
        self.failed: dict[str, str] = {}  # scene hash -> why (not tried again)

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="rayfarm-thumbnails", daemon=True)
        self._thread.start()

    def request(self, scene_hash: str) -> None:
        """Make `scene_hash`'s thumbnail soon, unless it exists."""
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
        try:
            for scene_hash in self._pending():
                self._queue.put(scene_hash)
        except Exception:
            log.exception("listing the scenes that need thumbnails failed")
        while not self._stop.is_set():
            try:
                batch = [self._queue.get(timeout=0.2)]
            except queue.Empty:
                continue
            while True:  # everything asked for meanwhile goes into one child process
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            try:
                self.make(batch)
            except Exception:
                log.exception("making thumbnails failed")

    def make(self, scene_hashes: Iterable[str]) -> int:
        """Render and store the thumbnails of `scene_hashes` that do not exist yet,
        in one child process; returns how many were stored."""
        todo = [h for h in dict.fromkeys(scene_hashes)
                if h not in self.failed and not self.store.thumbnail_path(h).is_file()]
        if not todo:
            return 0
        receiving, sending = self._context.Pipe(duplex=False)
        child = self._context.Process(
            target=_render_in_child, name="rayfarm-thumbnail", daemon=True,
            args=([(h, str(self.store.scene_path(h))) for h in todo], sending,
                  str(self.store.asset_dir)))
        try:
            child.start()
        except (EOFError, ConnectionError) as exc:
            # The forkserver died under us: a SIGTERM to the service's process
            # group (a stop) reaches it first. Nothing failed: the next start makes them.
            sending.close()
            receiving.close()
            log.warning("the thumbnail process could not start (%s: the forkserver exited)",
                        type(exc).__name__)
            return 0
        sending.close()  # the child holds the only sending end: EOF when it exits
        stored, waiting = 0, set(todo)
        try:
            while waiting and not self._stop.is_set():
                if not receiving.poll(0.2):
                    continue
                try:
                    key, png, error = receiving.recv()
                except EOFError:
                    break
                waiting.discard(key)
                if png is None:
                    log.warning("thumbnail of scene %s failed: %s", key[:12], error)
                    self.failed[key] = error
                    continue
                self.store.put_thumbnail(key, png)
                stored += 1
        finally:
            receiving.close()
            if self._stop.is_set():
                child.terminate()
            child.join(10)
            if child.is_alive():
                child.kill()
                child.join()
        if waiting and not self._stop.is_set():
            for key in waiting:
                self.failed[key] = f"the thumbnail process exited with code {child.exitcode}"
        self.rendered += stored
        return stored
