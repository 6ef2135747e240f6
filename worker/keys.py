"""Names the service and the workers agree on in Redis: the one list of them."""

from __future__ import annotations

__all__ = ["TASK_RENDER_UNIT", "QUEUE", "scene_key", "heartbeat_key", "cancel_key"]

TASK_RENDER_UNIT = "rayfarm.render_unit"
QUEUE = "rayfarm.units"


def scene_key(scene_hash: str) -> str:
    """Where the service publishes a scene's canonical text for the workers."""
    return f"rayfarm:scene:{scene_hash}"


def heartbeat_key(job_id: str, index: int) -> str:
    """Present (with a TTL of one lease) while some worker renders the unit."""
    return f"rayfarm:hb:{job_id}:{index}"


def cancel_key(job_id: str) -> str:
    """Set when a job is canceled or failed, so workers skip its queued units."""
    return f"rayfarm:cancel:{job_id}"
