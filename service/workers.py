"""Worker control: drain (disable), enable, remove. Plain Python, no HTTP.

Admins only (`access.require_admin`). A disabled worker finishes the units it
renders and takes no new ones (the executor: Celery cancels the worker's
consumer and keeps a marker in Redis, so a restarted worker stays disabled and
declines a unit it had prefetched; the embedded pool gets no new submissions).
Only a worker that no longer beats (lost, or offline after a clean shutdown)
can be removed from the list; a live one is a Conflict.

    set_enabled(executor, actor, "rayfarm-12@render3", enabled=False)
"""

from __future__ import annotations

from .access import Principal, require_admin
from .errors import Conflict, NotFound
from .executors import Executor, WorkerInfo

__all__ = ["find", "set_enabled", "remove"]


def find(executor: Executor, name: str) -> WorkerInfo:
    for worker in executor.workers():
        if worker.name == name:
            return worker
    raise NotFound(f"no worker '{name}'")


def set_enabled(executor: Executor, actor: Principal, name: str, enabled: bool) -> WorkerInfo:
    """Disable (drain) or enable worker `name`; returns it as it is now."""
    require_admin(actor)
    find(executor, name)
    executor.set_worker_enabled(name, enabled)
    return find(executor, name)


def remove(executor: Executor, actor: Principal, name: str) -> None:
    """Forget a lost or offline worker (a live one is a Conflict: stop it first)."""
    require_admin(actor)
    worker = find(executor, name)
    if worker.state not in ("lost", "offline"):
        raise Conflict(f"worker '{name}' is {worker.state}: only lost or offline workers can be "
                       "removed (disable it to drain it, then stop it)")
    executor.remove_worker(name)
