"""Names the service and the workers agree on in Redis: the one list of them."""

from __future__ import annotations

__all__ = ["TASK_RENDER_UNIT", "QUEUE", "WORKERS", "FILM_TTL", "scene_key", "heartbeat_key",
           "cancel_key", "stopped_key", "asset_key", "job_films_key", "worker_key", "worker_running_key", "input_key", "unit_log_key",
           "DISABLED_WORKERS"]

TASK_RENDER_UNIT = "rayfarm.render_unit"
QUEUE = "rayfarm.units"
WORKERS = "rayfarm:workers"  # the set of worker names that ever reported
# The names of the workers an admin disabled (drained): kept without expiry, so
# a restarted worker stays disabled; its tasks decline units while it is in it.
DISABLED_WORKERS = "rayfarm:workers:disabled"

# Lifetime of a unit's film under `input_key` (seconds). A worker sets it when it
# publishes the film; the service refreshes it whenever it enqueues a unit that
# reads the film, and deletes films no later unit reads once they are stored.
FILM_TTL = 24 * 3600


def scene_key(scene_hash: str) -> str:
    """Where the service publishes a scene's canonical text for the workers."""
    return f"rayfarm:scene:{scene_hash}"


def asset_key(digest: str) -> str:
    """A scene's asset (a mesh or texture blob, renderer.assets) by its
    SHA-256: published by the service with the scene's text and its TTL."""
    return f"rayfarm:asset:{digest}"


def input_key(digest: str) -> str:
    """A unit's film bytes by their SHA-256: published by the worker that
    rendered the unit, copied from there into the service's store, and read by
    the later units that need it as an input (a photon map, a bootstrap...)."""
    return f"rayfarm:input:{digest}"


def heartbeat_key(job_id: str, index: int) -> str:
    """Present while some worker renders the unit: its value the worker's name,
    its TTL a few heartbeat intervals (refreshed three times per TTL), so it
    lapses soon after the render process stops."""
    return f"rayfarm:hb:{job_id}:{index}"


def cancel_key(job_id: str) -> str:
    """Set when a job is canceled or failed, so workers skip its queued units."""
    return f"rayfarm:cancel:{job_id}"


def stopped_key(task_id: str) -> str:
    """Set when the service stopped one task (preempted, withdrawn, over its
    time budget) while its job goes on: a worker that missed the revoke
    broadcast (started later, or reconnecting) skips the task all the same."""
    return f"rayfarm:stopped:{task_id}"


def job_films_key(job_id: str) -> str:
    """The digests of the films a job's units published (a set, TTL `FILM_TTL`).
    A worker adds to it in the same atomic step that checks `cancel_key`, so
    the service, having set the marker, finds here every film it must drop."""
    return f"rayfarm:films:{job_id}"


def worker_key(name: str) -> str:
    """A worker's presence and counters (a hash; see worker/presence.py)."""
    return f"rayfarm:worker:{name}"


def worker_running_key(name: str) -> str:
    """The units a worker's processes render now (a hash: process id -> unit)."""
    return f"rayfarm:worker:{name}:running"


def unit_log_key(task_id: str) -> str:
    """A failed task's captured log (JSON, renderer.unitlog), for the service to
    keep: Celery's result keeps the exception's type, message and traceback only."""
    return f"rayfarm:unitlog:{task_id}"
