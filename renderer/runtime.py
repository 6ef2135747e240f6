"""Running one work unit: the function every executor calls.

The local process pool, the Celery task and the tests all run units through
`run_unit` (in-process objects) or `execute_unit` (plain data in, bytes out,
for process and network boundaries). Built scenes (arrays + BVH) are cached
per process by content hash, so a worker builds each scene once.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from typing import Callable

from .film import PartialFilm
from .plan import Unit
from .registry import METHODS
from .scene import Scene, build_scene
from .scene_format import canonical_json, resolve_document, scene_hash
from .spec import RenderSpec

__all__ = ["run_unit", "execute_unit", "SceneCache", "warm_up"]


class SceneCache:
    """A small per-process LRU of built scenes keyed by scene hash."""

    def __init__(self, capacity: int = 8):
        self.capacity = capacity
        self._scenes: OrderedDict[str, Scene] = OrderedDict()

    def get(self, key: str, load_text: Callable[[], str]) -> Scene:
        scene = self._scenes.get(key)
        if scene is None:
            import json

            doc = json.loads(load_text())
            if scene_hash(doc) != key:
                raise ValueError(f"scene text does not match its hash {key[:12]}")
            scene = build_scene(doc)
            self._scenes[key] = scene
            while len(self._scenes) > self.capacity:
                self._scenes.popitem(last=False)
        else:
            self._scenes.move_to_end(key)
        return scene


_CACHE = SceneCache()


def run_unit(scene: Scene, spec: RenderSpec, unit: Unit) -> PartialFilm:
    """Render one unit and return its partial film, with its timing in `stats`."""
    t0 = time.perf_counter()
    film = METHODS[spec.method].run(scene, spec, unit)
    film.stats["seconds"] = time.perf_counter() - t0
    return film


def execute_unit(scene_key: str, load_scene_text: Callable[[], str], spec: dict,
                 unit: dict) -> bytes:
    """Run a unit from plain data; returns the partial film's bytes.

    `load_scene_text()` is called only if this process has not built the
    scene `scene_key` yet (the farm fetches it from the broker by hash).
    """
    scene = _CACHE.get(scene_key, load_scene_text)
    return run_unit(scene, RenderSpec.from_dict(spec), Unit.from_dict(unit)).to_bytes()


def warm_up() -> None:
    """Compile (or load from Numba's cache) every kernel: call at process start,
    so no request ever waits for a compilation."""
    doc = resolve_document("cornell-box")
    scene = build_scene(doc)
    for method in dict.fromkeys(METHODS.values()):
        spec = RenderSpec(method=method.name, spp=2, depth=2, width=4, height=4, tile_size=4)
        run_unit(scene, spec, Unit(0, 0, 0, 4, 4, 0, 2))


def scene_text(doc: dict) -> tuple[str, str]:
    """(hash, canonical text) of a resolved document: how scenes travel."""
    return scene_hash(doc), canonical_json(doc)
