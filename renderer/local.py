"""The local executor: a process pool that runs units, and `render()` on top.

Used by `rayfarm render` and by the service's embedded mode. Each child
process is single-threaded Numba (one unit per process, one process per core,
the same shape as the Celery prefork pool) and warms its kernels at start.
Each child claims a slot in a small shared array and writes there the tag of
the unit it is rendering (0 when idle), so the parent knows exactly which
units are being rendered (`LocalPool.rendering`), not just which were handed
to the pool's queue.

    >>> film = render("cornell-box", RenderSpec(spp=4, depth=3))
    >>> film.write_exr("out.exr")
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Callable

from .cache import cache_root
from .film import Film, PartialFilm, merge
from .plan import Unit
from .registry import METHODS
from .runtime import execute_unit, scene_text, warm_up
from .scene_format import resolve_document
from .spec import RenderSpec
from .unitlog import capture_unit_log

__all__ = ["LocalPool", "render"]


_slot: int | None = None  # this child's index into the shared `rendering` array
_rendering = None


def _init_child(claimed, rendering, cache=None) -> None:
    global _slot, _rendering
    import signal

    import numba

    from . import cache as disk_caches

    if cache is not None:  # the parent's cache directory (or None) and cap, whatever our env
        disk_caches.configure(*cache)

    # Ctrl-C in a terminal reaches the whole process group: let the parent
    # shut the pool down in order instead of every child dying mid-unit.
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    with claimed.get_lock():
        _slot = claimed.value % len(rendering)
        claimed.value += 1
    _rendering = rendering
    numba.set_num_threads(1)
    warm_up()


def _run(scene_key: str, text: str, spec: dict, unit: dict, tag: int,
         inputs: dict[int, bytes] | None = None, job_id: str | None = None
         ) -> tuple[bytes, dict]:
    """Render one unit in a child: (film bytes, its captured log). A failure
    carries its log as the exception's `unit_log` (pickled with it)."""
    if _rendering is not None:
        _rendering[_slot] = tag
    captured = None
    try:
        with capture_unit_log(job_id, unit.get("index")) as captured:
            film = execute_unit(scene_key, lambda: text, spec, unit, inputs)
        return film, captured.to_dict()
    except Exception as exc:
        exc.unit_log = captured.to_dict() if captured is not None else None
        raise
    finally:
        if _rendering is not None:
            _rendering[_slot] = 0


class LocalPool:
    """A pool of single-threaded render processes (default: one per core).

    Units wait in the pool's own queue and are handed to the process pool only
    when a process is about to be free (at most one waiting per process), by a
    feeder thread. So a future canceled while it waits is simply dropped here:
    the process pool never holds canceled work. (Python 3.11's process pool
    raises InvalidStateError from its manager thread if a child dies, for
    example from a Ctrl-C or a SIGTERM to the process group, while canceled
    futures are still in its queue.)
    """

    def __init__(self, workers: int | None = None):
        self.workers = workers or os.cpu_count() or 1
        warm_up()  # compile here once, so the children only load Numba's cache
        context = multiprocessing.get_context("forkserver")
        self._rendering = context.Array("q", self.workers, lock=False)
        self._executor = ProcessPoolExecutor(
            max_workers=self.workers, mp_context=context, initializer=_init_child,
            initargs=(context.Value("i", 0), self._rendering, cache_root()))
        self._waiting: deque[tuple[Future, tuple]] = deque()
        self._handed = 0  # units in the process pool (rendering or next in line)
        self._closed = False
        self._changed = threading.Condition()
        self._feeder = threading.Thread(target=self._feed, name="rayfarm-pool-feeder", daemon=True)
        self._feeder.start()

    def submit(self, scene_key: str, text: str, spec: dict, unit: dict, tag: int = 0,
               inputs: dict[int, bytes] | None = None, job_id: str | None = None) -> Future:
        """Run one unit; the future's result is the partial film's bytes. A
        nonzero `tag` shows in `rendering()` while a process renders the unit;
        `inputs` are the film bytes of the units it needs; `job_id` names the
        job in its log records. Canceling the future works until a process is
        about to take it. Once the future is done, `future.unit_log` is the
        unit's captured log (renderer.unitlog), or None if the process died."""
        future: Future = Future()
        future.unit_log = None
        with self._changed:
            if self._closed:
                raise RuntimeError("the pool is shut down")
            self._waiting.append((future, (scene_key, text, spec, unit, tag, inputs, job_id)))
            self._changed.notify()
        return future

    def _feed(self) -> None:
        while True:
            with self._changed:
                while not self._closed and (not self._waiting or self._handed > self.workers):
                    self._changed.wait()
                if self._closed:
                    return
                future, args = self._waiting.popleft()
                if not future.set_running_or_notify_cancel():
                    continue  # canceled while it waited
                self._handed += 1
            try:
                inner = self._executor.submit(_run, *args)
            except Exception as exc:  # a broken pool: the unit fails, its executor decides
                self._settle(future, None, exc)
                continue
            inner.add_done_callback(lambda done, outer=future: self._settle(outer, done))

    def _settle(self, outer: Future, inner: Future | None, error: BaseException | None = None):
        if inner is not None:
            error = inner.exception() if not inner.cancelled() else RuntimeError("canceled")
        if error is None:
            film, outer.unit_log = inner.result()
            outer.set_result(film)
        else:
            outer.unit_log = getattr(error, "unit_log", None)
            outer.set_exception(error)
        with self._changed:
            self._handed -= 1
            self._changed.notify()

    def rendering(self) -> list[int]:
        """Tags of the units the processes are rendering right now."""
        return [tag for tag in self._rendering[:] if tag]

    def shutdown(self, cancel: bool = True) -> None:
        """Stop the pool: units still waiting are canceled (or, with `cancel`
        False, all work is finished first); units in the processes finish."""
        with self._changed:
            while not cancel and (self._waiting or self._handed):
                self._changed.wait()
            self._closed = True
            waiting, self._waiting = list(self._waiting), deque()
            self._changed.notify_all()
        self._feeder.join()
        for future, _args in waiting:
            future.cancel()
        self._executor.shutdown(wait=True, cancel_futures=cancel)

    def __enter__(self) -> "LocalPool":
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()


def render(scene_source, spec: RenderSpec, *, pool: LocalPool | None = None,
           workers: int | None = None, progressive: bool = False,
           progress: Callable[[Unit, PartialFilm], None] | None = None) -> Film:
    """Render a scene locally through plan -> units -> merge, like the farm: a
    unit is submitted as soon as every unit it needs is done (plan.py)."""
    doc = resolve_document(scene_source)
    spec.validate(scene=doc)
    key, text = scene_text(doc)
    units = METHODS[spec.method].make_plan(spec, progressive)
    own_pool = pool is None
    pool = pool or LocalPool(workers)
    # Each unit waits for the count of its needs still missing; a finished
    # unit releases its dependents. Bytes are kept only for units others need.
    needed = {i for u in units for i in u.needs}
    missing = {u.index: len(set(u.needs)) for u in units}
    dependents: dict[int, list[Unit]] = {}
    for u in units:
        for i in set(u.needs):
            dependents.setdefault(i, []).append(u)
    try:
        results: dict[int, bytes] = {}
        parts: dict[int, PartialFilm] = {}
        ready = deque(u for u in units if not u.needs)
        futures: dict[Future, Unit] = {}
        while ready or futures:
            while ready:
                u = ready.popleft()
                futures[pool.submit(key, text, spec.to_dict(), u.to_dict(),
                                    inputs={i: results[i] for i in u.needs})] = u
            done, _ = wait(futures, return_when=FIRST_COMPLETED)
            for fut in done:
                unit = futures.pop(fut)
                data = fut.result()
                if unit.index in needed:
                    results[unit.index] = data
                parts[unit.index] = PartialFilm.from_bytes(data)
                if progress is not None:
                    progress(unit, parts[unit.index])
                for dependent in dependents.get(unit.index, ()):
                    missing[dependent.index] -= 1
                    if missing[dependent.index] == 0:
                        ready.append(dependent)
        if len(parts) != len(units):
            raise RuntimeError("plan has units whose needs never complete")
    finally:
        if own_pool:
            pool.shutdown()
    return merge(spec.width, spec.height, (parts[u.index] for u in units))
