"""The local executor: a process pool that runs units, and `render()` on top.

Used by `rayfarm render` and by the service's embedded mode. Each render
process is single-threaded Numba (one unit per process, one process per core,
the same shape as the Celery prefork pool) and warms its kernels at start.

Every process is owned by one thread of the pool (its *slot*), which hands it
one unit at a time over a pipe and waits for the film or for the process's
death. So the pool knows exactly which unit each process is rendering
(`LocalPool.rendering`), and a process that dies (a segfault in a kernel, a
SIGKILL, `os._exit`) costs only the unit it was rendering: that unit's future
fails with `RenderProcessDied` (its exit signal or code), the slot starts a
new process, and the other processes never notice. (A `ProcessPoolExecutor`
breaks as a whole on one death and fails every unit in flight.)

The same makes a rendering unit stoppable (`LocalPool.stop(tag)`): its slot's
process is killed, the unit's future fails with `UnitStopped` (not a death),
and the slot starts a new process and takes the next unit once it has warmed
up (it loads Numba's on-disk cache: about half a second). A kernel holds the
GIL for as long as it runs, so nothing short of a signal stops it sooner.

Render processes die with the process that started them: each asks the
kernel for SIGKILL when its parent thread (the slot) exits (Linux
PR_SET_PDEATHSIG; a watchdog thread elsewhere), so a SIGKILLed service leaves
no renderer behind.

    >>> film = render("cornell-box", RenderSpec(spp=4, depth=3))
    >>> film.write_exr("out.exr")
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import tempfile
import threading
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, wait
from multiprocessing.connection import wait as wait_ready
from typing import Callable

from .assets import DirectorySource, write_assets
from .cache import cache_root
from .film import Film, PartialFilm, merge
from .plan import Unit
from .registry import METHODS
from .runtime import execute_unit, scene_text, warm_up
from .scene_format import resolve_document
from .spec import RenderSpec
from .unitlog import capture_unit_log

__all__ = ["LocalPool", "RenderProcessDied", "UnitStopped", "process_death", "render"]


def process_death(exitcode: int) -> str:
    """How a render process ended, in words: ``render process died with
    SIGSEGV`` (a negative exit code is the signal) or ``... exited with code 3``."""
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"render process died with {name}"
    return f"render process exited with code {exitcode}"


class RenderProcessDied(RuntimeError):
    """The process rendering a unit died before it returned the unit's film."""

    def __init__(self, exitcode: int):
        self.exitcode = exitcode
        super().__init__(process_death(exitcode))


class UnitStopped(RuntimeError):
    """The unit was stopped on request (`LocalPool.stop`) while a process rendered it."""


# -- the render process ---------------------------------------------------------------

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _die_with_parent(parent_pid: int) -> None:
    """SIGKILL this process when the thread that started it exits (the pool's
    slot, or the whole service with it). Linux does it in the kernel, even
    while a kernel holds the GIL; elsewhere a thread polls the parent."""
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    else:
        def watch() -> None:
            while os.getppid() == parent_pid:
                time.sleep(1.0)
            os._exit(1)
        threading.Thread(target=watch, name="rayfarm-parent-watchdog", daemon=True).start()
    if os.getppid() != parent_pid:  # the parent died before we asked
        os._exit(1)


def _child_main(conn, parent_pid: int, cache) -> None:
    """A render process: warm up, say so, then render units until told to stop
    (None) or until the pool's end of the pipe closes."""
    _die_with_parent(parent_pid)
    import numba

    from . import cache as disk_caches

    if cache is not None:  # the parent's cache directory (or None) and cap, whatever our env
        disk_caches.configure(*cache)
    # Ctrl-C in a terminal reaches the whole process group: let the parent
    # shut the pool down in order instead of every child dying mid-unit.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    numba.set_num_threads(1)
    warm_up()
    conn.send("ready")
    while True:
        try:
            args = conn.recv()
        except EOFError:
            return
        if args is None:
            return
        scene_key, text, spec, unit, inputs, job_id, asset_dir = args
        captured = None
        try:  # the unit's own log lines and traceback travel with its outcome
            with capture_unit_log(job_id, unit.get("index")) as captured:
                film = execute_unit(scene_key, lambda: text, spec, unit, inputs,
                                    DirectorySource(asset_dir) if asset_dir else None)
            outcome = (True, film, captured.to_dict())
        except BaseException as exc:  # noqa: BLE001 - reported to the unit's future
            outcome = (False, exc, captured.to_dict() if captured is not None else None)
        try:
            conn.send(outcome)
        except Exception as exc:  # e.g. an exception that does not pickle
            conn.send((False, RuntimeError(f"{type(outcome[1]).__name__}: {outcome[1]} "
                                           f"(not sent whole: {exc})"), outcome[2]))
        # Sent: the film and the inputs must not live on while the next unit
        # renders (a splat batch is the whole frame: 200 MB at 2048^2)
        args = inputs = film = outcome = None


class _Process:
    """One render process of a slot and the pool's end of its pipe."""

    def __init__(self, context, cache):
        self.conn, child_conn = context.Pipe()
        self.process = context.Process(target=_child_main, name="rayfarm-render",
                                       args=(child_conn, os.getpid(), cache), daemon=True)
        self.process.start()
        child_conn.close()

    def wait_ready(self, give_up: Callable[[], bool]) -> bool:
        """Wait for the warm-up; False if the process died instead or
        `give_up()` (the pool is closing: no need to wait seconds for it)."""
        while not give_up():
            ready = wait_ready([self.conn, self.process.sentinel], timeout=0.2)
            if self.conn in ready:
                try:
                    return self.conn.recv() == "ready"
                except (EOFError, OSError):  # closed, or reset by the process's death
                    break
            if ready:  # the process died
                break
        self.process.kill()
        self.process.join()
        return False

    def run(self, args: tuple) -> tuple[bool, object, dict | None] | None:
        """Render one unit: (True, film, log), (False, exception, log) or None
        if the process died first."""
        try:
            self.conn.send(args)
        except OSError:  # the process is gone (a broken pipe)
            pass
        else:
            # A result sent just before dying still counts: read the pipe first.
            if self.conn in wait_ready([self.conn, self.process.sentinel]) or self.conn.poll():
                try:
                    return self.conn.recv()
                except (EOFError, OSError):  # a SIGKILL may reset the pipe, not close it
                    pass
        self.process.join()
        return None

    @property
    def exitcode(self) -> int:
        return self.process.exitcode if self.process.exitcode is not None else -signal.SIGKILL

    def stop(self) -> None:
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.process.join(10)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()


# -- the pool ----------------------------------------------------------------------------

class LocalPool:
    """A pool of single-threaded render processes (default: one per core).

    Units wait in the pool's own queue until a process is free, so a future
    canceled while it waits is simply dropped. Each process renders one unit
    at a time; a process that dies fails only its unit, with
    `RenderProcessDied`, and is replaced (see the module doc); `stop(tag)`
    ends a unit whether it waits or renders.
    """

    RESTART_PAUSE = 1.0  # seconds between attempts to start a process that dies in warm-up

    def __init__(self, workers: int | None = None):
        self.workers = workers or os.cpu_count() or 1
        # Compile here once (in parallel on a cold cache), so the processes only
        # load Numba's cache.
        warm_up(processes=self.workers)
        # Spawned, not forked from a forkserver: the parent of every render
        # process is this process (its slot thread), which PR_SET_PDEATHSIG needs.
        self._context = multiprocessing.get_context("spawn")
        self._cache = cache_root()
        self._rendering = [0] * self.workers  # per slot: the tag of the unit it renders
        self._stopping = [0] * self.workers  # per slot: the tag `stop` killed its process for
        self._processes: list[_Process | None] = [None] * self.workers  # per slot
        self._waiting: deque[tuple[Future, tuple, int]] = deque()
        self._busy = 0  # slots rendering a unit
        self._closed = False
        self._changed = threading.Condition()
        self._slots = [threading.Thread(target=self._serve, args=(slot,), daemon=True,
                                        name=f"rayfarm-pool-slot-{slot}")
                       for slot in range(self.workers)]
        for thread in self._slots:
            thread.start()

    def submit(self, scene_key: str, text: str, spec: dict, unit: dict, tag: int = 0,
               inputs: dict[int, bytes] | None = None, job_id: str | None = None,
               asset_dir: str | None = None) -> Future:
        """Run one unit; the future's result is the partial film's bytes. A
        nonzero `tag` shows in `rendering()` while a process renders the unit;
        `inputs` are the film bytes of the units it needs; `job_id` names the
        job in its log records; `asset_dir` holds the scene's assets as
        `<digest>` files (read once, when a process first builds the scene). Canceling the future works until a process
        takes it. Once the future is done, `future.unit_log` is the unit's
        captured log (renderer.unitlog), or None if the process died."""
        future: Future = Future()
        future.unit_log = None
        with self._changed:
            if self._closed:
                raise RuntimeError("the pool is shut down")
            self._waiting.append((future, (scene_key, text, spec, unit, inputs, job_id,
                                           None if asset_dir is None else str(asset_dir)), tag))
            self._changed.notify()
        return future

    def _next(self) -> tuple[Future, tuple, int] | None:
        """The next unit for a free slot (counted busy), or None once closed."""
        with self._changed:
            while True:
                while not self._closed and not self._waiting:
                    self._changed.wait()
                if self._closed:
                    return None
                future, args, tag = self._waiting.popleft()
                if future.set_running_or_notify_cancel():  # else canceled while it waited
                    self._busy += 1
                    return future, args, tag

    def _serve(self, slot: int) -> None:
        """A slot: keep one render process, feed it units one at a time."""
        process: _Process | None = None
        try:
            while True:
                if process is None or not process.process.is_alive():
                    process = self._processes[slot] = self._start(process)
                    if process is None:
                        return
                item = self._next()
                if item is None:
                    return
                future, args, tag = item
                with self._changed:  # `stop` reads both under the lock
                    self._rendering[slot] = tag
                try:
                    outcome = process.run(args)
                finally:
                    with self._changed:
                        self._rendering[slot] = 0
                        stopped, self._stopping[slot] = self._stopping[slot] == tag != 0, 0
                if outcome is None and stopped:
                    future.set_exception(UnitStopped(f"unit stopped on request "
                                                     f"({process_death(process.exitcode)})"))
                elif outcome is None:
                    future.set_exception(RenderProcessDied(process.exitcode))
                else:
                    future.unit_log = outcome[2]
                    if outcome[0]:
                        future.set_result(outcome[1])
                    else:
                        future.set_exception(outcome[1])
                with self._changed:
                    self._busy -= 1
                    self._changed.notify_all()
                # This thread waits for the next unit next: what it no longer
                # needs must not live on in its frame (the last unit's film
                # and inputs, hundreds of MB for a large tile).
                item = future = args = outcome = None
        finally:
            if process is not None:
                process.stop()

    def _start(self, dead: _Process | None) -> _Process | None:
        """A new, warmed-up render process (None once the pool is closed). One
        that dies while warming up fails the next waiting unit with its exit,
        so a renderer that cannot start shows up as failed units, not a hang."""
        if dead is not None:
            dead.stop()
        while not self._closed:
            process = _Process(self._context, self._cache)
            if process.wait_ready(lambda: self._closed):
                return process
            process.stop()
            if self._closed:
                return None
            item = self._next()
            if item is None:
                return None
            future, _args, _tag = item
            future.set_exception(RuntimeError(
                f"{process_death(process.exitcode)} while starting (warming up its kernels)"))
            with self._changed:
                self._busy -= 1
                self._changed.notify_all()
            time.sleep(self.RESTART_PAUSE)
        return None

    def stop(self, tag: int) -> bool:
        """Stop the unit submitted with `tag` (nonzero): dropped if it still
        waits (its future canceled), else its process is killed (its future
        fails with `UnitStopped`, unless the film was already on its way) and
        the slot goes on with a new process. False if no unit has that tag."""
        if not tag:
            return False
        with self._changed:
            for entry in self._waiting:
                if entry[2] == tag:
                    self._waiting.remove(entry)
                    entry[0].cancel()
                    return True
            if tag not in self._rendering:
                return False
            slot = self._rendering.index(tag)
            self._stopping[slot] = tag
            # Under the lock: the slot cannot move on to its next unit meanwhile.
            self._processes[slot].process.kill()
            return True

    def waiting(self) -> int:
        """Units submitted that no process has taken yet (canceled ones too,
        until a free process drops them)."""
        return len(self._waiting)

    def rendering(self) -> list[int]:
        """Tags of the units the processes are rendering right now."""
        return [tag for tag in self._rendering if tag]

    def pids(self) -> list[int]:
        """The process ids of the live render processes."""
        return [p.process.pid for p in self._processes if p is not None and p.process.is_alive()]

    def shutdown(self, cancel: bool = True) -> None:
        """Stop the pool: units still waiting are canceled and units rendering
        are stopped (`UnitStopped`: a unit may render for minutes); with
        `cancel` False, all work is finished first."""
        with self._changed:
            while not cancel and (self._waiting or self._busy):
                self._changed.wait()
            self._closed = True
            waiting, self._waiting = list(self._waiting), deque()
            for slot, tag in enumerate(self._rendering):
                if tag:
                    self._stopping[slot] = tag
                    self._processes[slot].process.kill()
            self._changed.notify_all()
        for future, _args, _tag in waiting:
            future.cancel()
        for thread in self._slots:
            thread.join()

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
    # The render processes read the scene's meshes and textures from files:
    # a blob is written once, not pickled with every unit.
    asset_tmp = tempfile.TemporaryDirectory(prefix="rayfarm-assets-") if doc.assets else None
    if asset_tmp is not None:
        write_assets(asset_tmp.name, doc.assets)
    asset_dir = asset_tmp.name if asset_tmp is not None else None
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
                                    inputs={i: results[i] for i in u.needs},
                                    asset_dir=asset_dir)] = u
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
        if asset_tmp is not None:
            asset_tmp.cleanup()
    return merge(spec.width, spec.height, (parts[u.index] for u in units))
