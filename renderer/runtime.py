"""Running one work unit: the function every executor calls.

The local process pool, the Celery task and the tests all run units through
`run_unit` (in-process objects) or `execute_unit` (plain data in, bytes out,
for process and network boundaries). Built scenes (arrays + BVH) are cached
per process by content hash, so a worker builds each scene once.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections import OrderedDict
from typing import Callable

from .film import PartialFilm
from .plan import Unit
from .registry import METHODS
from .scene import Scene, build_scene
from .scene_format import canonical_json, resolve_document, scene_hash
from .spec import RenderSpec

__all__ = ["run_unit", "run_plan", "render_serial", "execute_unit", "SceneCache", "warm_up"]

log = logging.getLogger(__name__)


class SceneCache:
    """A small per-process LRU of built scenes keyed by scene hash."""

    def __init__(self, capacity: int = 8):
        self.capacity = capacity
        self._scenes: OrderedDict[str, Scene] = OrderedDict()

    def get(self, key: str, load_text: Callable[[], str],
            load_asset: Callable[[str], bytes] | None = None) -> Scene:
        """The built scene `key`; on a miss its text comes from `load_text()`
        and the assets it names from `load_asset(digest)` (checked against
        their digests), each fetched once for the build."""
        scene = self._scenes.get(key)
        if scene is None:
            import json

            doc = json.loads(load_text())
            if scene_hash(doc) != key:
                raise ValueError(f"scene text does not match its hash {key[:12]}")
            t0 = time.perf_counter()
            scene = build_scene(doc, load_asset=load_asset)
            log.info("scene %s built in %.3f s", key[:12], time.perf_counter() - t0)
            self._scenes[key] = scene
            while len(self._scenes) > self.capacity:
                self._scenes.popitem(last=False)
        else:
            self._scenes.move_to_end(key)
        return scene


_CACHE = SceneCache()


def run_unit(scene: Scene, spec: RenderSpec, unit: Unit,
             inputs: dict[int, PartialFilm] | None = None) -> PartialFilm:
    """Render one unit and return its partial film, with its timing in `stats`.
    `inputs` holds the films of the units in `unit.needs`, by index."""
    inputs = inputs or {}
    missing = [i for i in unit.needs if i not in inputs]
    if missing:
        raise ValueError(f"unit {unit.index} needs the results of units {missing}")
    t0 = time.perf_counter()
    film = METHODS[spec.method].render(scene, spec, unit, inputs)
    film.stats["seconds"] = time.perf_counter() - t0
    log.info("unit %d (%s, stage %d) of %s: %d samples, %d rays in %.3f s", unit.index,
             unit.kind, unit.stage, spec.method, int(film.stats.get("samples", 0)),
             int(film.stats.get("rays", 0)), film.stats["seconds"])
    return film


def execute_unit(scene_key: str, load_scene_text: Callable[[], str], spec: dict,
                 unit: dict, inputs: dict[int, bytes] | None = None,
                 load_asset: Callable[[str], bytes] | None = None) -> bytes:
    """Run a unit from plain data; returns the partial film's bytes.

    `load_scene_text()` is called only if this process has not built the
    scene `scene_key` yet (the farm fetches it from the broker by hash), and
    then `load_asset(digest)` for each mesh or texture the scene names.
    `inputs` are the film bytes of the units it needs, by index.
    """
    _crash_if_asked(spec)
    scene = _CACHE.get(scene_key, load_scene_text, load_asset)
    films = {int(i): PartialFilm.from_bytes(b) for i, b in (inputs or {}).items()}
    return run_unit(scene, RenderSpec.from_dict(spec), Unit.from_dict(unit), films).to_bytes()


# A render process whose environment holds this variable kills itself with
# SIGSEGV on every unit of a job whose seed it names: the farm's tests use it to
# crash render processes on purpose (tests/test_service_crashes.py), now that
# every scene that used to crash a kernel is refused at submission. Only the
# processes a test starts have it; nothing a request sends can set it.
CRASH_SEED_ENV = "RAYFARM_TEST_CRASH_SEED"


def _crash_if_asked(spec: dict) -> None:
    seed = os.environ.get(CRASH_SEED_ENV)
    if seed and str(spec.get("seed")) == seed.strip():
        import resource

        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # no core file for a deliberate crash
        os.kill(os.getpid(), signal.SIGSEGV)


def warm_up(processes: int = 1) -> None:
    """Compile (or load from Numba's cache) every kernel: call at process start,
    so no request ever waits for a compilation.

    With `processes` > 1 and a cold cache, the method families (the modules
    their kernels live in) compile in that many processes at once: this one
    warms the first family, the other families go to spawned processes
    meanwhile, which leave their kernels in Numba's on-disk cache for this
    process to load. An empty cache (`kernels.cache_is_empty`) spawns them
    at once; otherwise they are spawned only if the first method compiled
    anything (Numba counted a cache miss), so on a warm cache nothing is
    spawned. On a cold cache two processes took 132 s where one took 223 s
    (2 cores). Spawning at once instead of after the first method (the path
    kernel, compiled alone for 160 s on a 2-core AMD EPYC): a cold
    warm_up(processes=2) took 326 s there, against 409 s for the test
    suite's compile before (which also solved radiosity in full). Numba
    writes each cache file to a temporary name and renames it, so processes
    compiling a shared kernel at the same time leave one whole file."""
    from .kernels import cache_is_empty

    families = _method_families()
    first, rest = families[0], [name for family in families[1:] for name in family]
    cold = processes > 1 and cache_is_empty()
    if not cold:
        _warm_methods(first[:1])
    pool = None
    if processes > 1 and (cold or _cache_misses() > 0):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(min(processes, len(families) - 1),
                                   mp_context=multiprocessing.get_context("spawn"))
        pending = [pool.submit(_warm_methods, family) for family in families[1:]]
    try:
        _warm_methods(first if cold else first[1:])
        if pool is not None:
            for future in pending:
                future.result()
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    _warm_methods(rest)


def _cache_misses() -> int:
    """Kernels of the renderer compiled in this process so far (not loaded
    from Numba's on-disk cache)."""
    import sys

    from numba.core.dispatcher import Dispatcher

    misses = 0
    for name, module in list(sys.modules.items()):
        if name.startswith(__package__ + ".") and module is not None:
            for obj in vars(module).values():
                if isinstance(obj, Dispatcher):
                    misses += sum(obj.stats.cache_misses.values())
    return misses


def _method_families() -> list[list[str]]:
    """Method names grouped by the module of their `run` (the kernels they
    share), the biggest group first."""
    groups: dict[str, list[str]] = {}
    for method in dict.fromkeys(METHODS.values()):
        run = getattr(method.run, "func", method.run)
        groups.setdefault(run.__module__, []).append(method.name)
    return sorted(groups.values(), key=len, reverse=True)


def _warm_methods(names: list[str]) -> None:
    scene = build_scene(resolve_document("cornell-box"))
    for name in names:
        method = METHODS[name]
        for options in ({}, *method.warm_options):
            run_plan(scene, RenderSpec(method=name, spp=2, depth=2, width=4, height=4,
                                       tile_size=4, options={**method.warm_base, **options}))


def run_plan(scene: Scene, spec: RenderSpec, progressive: bool = False) -> list[PartialFilm]:
    """Run every unit of a job's plan in this process, in unit order (which is
    a topological order of its DAG); returns the films in unit order. For
    tests, warm-up and small renders; `renderer.local.render` runs the same
    DAG on a process pool."""
    films: list[PartialFilm] = []
    for unit in METHODS[spec.method].make_plan(spec, progressive):
        films.append(run_unit(scene, spec, unit, {i: films[i] for i in unit.needs}))
    return films


def render_serial(scene: Scene, spec: RenderSpec, progressive: bool = False):
    """`run_plan` merged into the finished film (in-process, no pool)."""
    from .film import merge

    return merge(spec.width, spec.height, run_plan(scene, spec, progressive))


def scene_text(doc: dict) -> tuple[str, str]:
    """(hash, canonical text) of a resolved document: how scenes travel."""
    return scene_hash(doc), canonical_json(doc)
