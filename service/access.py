"""Who is asking, and what they may see and change: the one place of the farm's
access rules. Domain code (jobs, scenes, events) takes a `Principal` and asks
here; routes never check ownership themselves, so a forgotten check cannot leak.

    actor = Principal("ana", "artist", token_id="3f9c0a1b2d4e5f60")
    query = select(Job).where(visible_jobs(actor))     # ana's jobs only
    require_change(actor, job.owner)                   # NotFound for someone else's

Roles (as Deadline's and OpenCue's, reduced to three):

    admin    everything, every owner's jobs and uploads, users and tokens
    artist   submits; sees and acts on its own jobs and uploads only
    viewer   reads everything, changes nothing

Someone else's job or upload is *not found* for an artist (404, never 403:
no existence leak); a viewer sees it, so a change it may not make is a 403.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import Forbidden, NotFound

__all__ = ["ROLES", "Principal", "SYSTEM", "visible_jobs", "can_see", "require_change",
           "require_submit", "require_admin"]

ROLES = ("admin", "artist", "viewer")


@dataclass(frozen=True)
class Principal:
    """The caller: a user, its role, and the API token it came with (None for
    the service itself); `via` is how it authenticated: "bearer" or "cookie"
    (then `session_id` is the dashboard login made from that token)."""

    user: str
    role: str
    token_id: str | None = None
    via: str = "bearer"
    session_id: str | None = None  # the dashboard login (a session token) it came with

    @property
    def sees_everything(self) -> bool:
        return self.role in ("admin", "viewer")

    @property
    def is_admin(self) -> bool:
        return self.role == "admin"


# The service acting for itself (bootstrap, CLI on the ledger): an admin.
SYSTEM = Principal("admin", "admin", token_id=None, via="system")


def visible_jobs(actor: Principal, owner_column):
    """A WHERE clause: the rows of `owner_column` the actor may see."""
    from sqlalchemy import true  # here: the CLI's client commands import this module

    return true() if actor.sees_everything else owner_column == actor.user


def can_see(actor: Principal, owner: str | None) -> bool:
    return actor.sees_everything or owner == actor.user


def require_change(actor: Principal, owner: str, what: str) -> None:
    """May `actor` change a thing of `owner`? NotFound when it cannot even see
    it (`what` names it, as the lookup's own 404 would), Forbidden for a viewer."""
    if not can_see(actor, owner):
        raise NotFound(f"no {what}")
    if actor.role == "viewer":
        raise Forbidden(f"user '{actor.user}' is a viewer: it can read, not change, {what}")
    if not actor.is_admin and owner != actor.user:
        raise NotFound(f"no {what}")


def require_submit(actor: Principal) -> None:
    if actor.role not in ("admin", "artist"):
        raise Forbidden(f"user '{actor.user}' is a {actor.role}: only artists and admins "
                        "submit jobs and upload scenes")


def require_admin(actor: Principal) -> None:
    if not actor.is_admin:
        raise Forbidden(f"user '{actor.user}' is a {actor.role}: only admins manage users "
                        "and tokens")
