"""Names the service and the workers agree on in Redis: the one list of them."""

from __future__ import annotations

__all__ = ["TASK_RENDER_UNIT", "QUEUE", "WORKERS", "FILM_TTL", "scene_key", "heartbeat_key",
           "cancel_key", "worker_key", "worker_running_key", "input_key"]

TASK_RENDER_UNIT = "rayfarm.render_unit"
QUEUE = "rayfarm.units"
WORKERS = "rayfarm:workers"  # the set of worker names that ever reported
# Lifetime of a unit's film under `input_key` (seconds). A worker sets it when it
# publishes the film; the service refreshes it whenever it enqueues a unit that
# reads the film, and deletes films no later unit reads once they are stored.
FILM_TTL = 24 * 3600


def scene_key(scene_hash: str) -> str:
    """Where the service publishes a scene's canonical text for the workers."""
    return f"rayfarm:scene:{scene_hash}"


def input_key(digest: str) -> str:
    """A unit's film bytes by their SHA-256: published by the worker that
    rendered the unit, copied from there into the service's store, and read by
    the later units that need it as an input (a photon map, a bootstrap...)."""
    return f"rayfarm:input:{digest}"


def heartbeat_key(job_id: str, index: int) -> str:
    """Present (with a TTL of one lease) while some worker renders the unit."""
    return f"rayfarm:hb:{job_id}:{index}"


def cancel_key(job_id: str) -> str:
    """Set when a job is canceled or failed, so workers skip its queued units."""
    return f"rayfarm:cancel:{job_id}"


def worker_key(name: str) -> str:
    """A worker's presence and counters (a hash; see worker/presence.py)."""
    return f"rayfarm:worker:{name}"


def worker_running_key(name: str) -> str:
    """The units a worker's processes render now (a hash: process id -> unit)."""
    return f"rayfarm:worker:{name}:running"
