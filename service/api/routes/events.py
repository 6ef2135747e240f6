"""Server-sent event streams: one job's (`/jobs/{id}/events`) and every job's (`/events`).

    curl -N localhost:8000/jobs/<id>/events
    event: job
    data: {"id": "...", "status": "running", "progress": {...}, ...}

A job's stream opens with its snapshot (`job`, then `units` once planned),
then carries `unit`, `job` and `preview` events as they are committed (see
`service.events` for their data) and ends with an `end` event once the job is
done, failed, canceled or deleted (`?follow=true` keeps it open across a
requeue). A comment line every `KEEPALIVE` seconds keeps proxies from closing
an idle stream. Every event has an `id:`; a reconnecting client gets a fresh
snapshot rather than a replay.

A stream ends when its caller's login does (a revoked token, a logout, a
disabled user, a new role), within about a second however busy it is: the
hub's `logins` count moves when the ledger says a login may have ended
(service.revocations), and the stream then checks its own caller once,
between two events or when the hub wakes it. At every keep-alive it checks
too (an expired token).
"""

from __future__ import annotations

import asyncio
from typing import AsyncIterator

from fastapi import APIRouter
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from ... import auth, jobs, states
from ...events import JOB_KINDS, Subscription, sse_frame
from ...farm import Farm
from ...models import utcnow
from ...schemas import JobPublic, UnitPublic
from ...access import Principal
from ..auth import ActorDep
from ..deps import FarmDep
from ..errors import responses

router = APIRouter(tags=["events"])

KEEPALIVE = 15.0  # seconds between keep-alive comments on a quiet stream
RETRY_MS = 2000  # how soon EventSource reconnects after a dropped stream
_HEADERS = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
_SSE_DOC = {200: {"content": {"text/event-stream": {}},
                  "description": "a stream of server-sent events"}}


_KEEPALIVE = ": keep-alive\n\n"


def _still_valid(farm: Farm, actor: Principal) -> bool:
    with farm.sessions() as session:
        return auth.still_valid(session, actor, utcnow())


class _Login:
    """The stream's caller: is its login over? Asked of the ledger only when
    the hub's `logins` count moved, or when `always` (a keep-alive)."""

    def __init__(self, farm: Farm, actor: Principal):
        self.farm, self.actor = farm, actor
        self.seen = farm.events.logins  # read before the first check (in the stream's start)

    async def ended(self, always: bool = False) -> bool:
        logins = self.farm.events.logins
        if logins == self.seen and not always:
            return False
        self.seen = logins
        return not await run_in_threadpool(_still_valid, self.farm, self.actor)


def _job_snapshot(farm: Farm, actor: Principal, job_id: str) -> tuple[dict, list[dict]]:
    with farm.sessions() as session:
        job = jobs.get_job(session, actor, job_id)  # NotFound (or not the caller's) -> 404
        units = [UnitPublic.from_unit(u).model_dump(mode="json")
                 for u in jobs.list_units(session, actor, job_id)]
        return JobPublic.from_job(job, utcnow()).model_dump(mode="json"), units


async def _job_stream(farm: Farm, actor: Principal, sub: Subscription, job_id: str,
                      snapshot: tuple, follow: bool) -> AsyncIterator[str]:
    login = _Login(farm, actor)
    try:
        yield f"retry: {RETRY_MS}\n\n"
        if await login.ended(always=True):  # it may have ended since it was authenticated
            return
        while True:
            job, units = snapshot
            yield sse_frame("job", job)
            if units:
                yield sse_frame("units", units)
            if job["status"] in states.FINAL_JOB and not follow:
                yield sse_frame("end", {"job_id": job_id, "status": job["status"]})
                return
            while True:
                event = await sub.next(KEEPALIVE)
                if await login.ended(always=event is None):
                    return
                if sub.overflowed:  # we fell behind: start again from a snapshot
                    sub.overflowed = False
                    break
                if event is None:
                    yield _KEEPALIVE
                    continue
                yield event.sse()
                if event.kind == "deleted":
                    yield sse_frame("end", {"job_id": job_id, "status": "deleted"})
                    return
                if (event.kind == "job" and event.data["status"] in states.FINAL_JOB
                        and not follow):
                    yield sse_frame("end", {"job_id": job_id, "status": event.data["status"]})
                    return
            snapshot = await run_in_threadpool(_job_snapshot, farm, actor, job_id)
    finally:
        sub.close()


@router.get("/jobs/{job_id}/events", response_class=StreamingResponse,
            responses={**_SSE_DOC, **responses(404)})
async def job_events(job_id: str, farm: FarmDep, actor: ActorDep,
                     follow: bool = False) -> StreamingResponse:
    """Server-sent events of one job: a snapshot (`job`, `units`), then `unit`,
    `job` and `preview` events as they happen; `end` when the job is final
    (404 for an unknown job, or one the caller may not see)."""
    # Subscribed before the snapshot (no event falls between them); nothing is
    # sent before the snapshot has shown that the caller may see the job.
    sub = farm.events.subscribe(job_id, asyncio.get_running_loop())
    try:
        snapshot = await run_in_threadpool(_job_snapshot, farm, actor, job_id)
    except BaseException:
        sub.close()
        raise
    return StreamingResponse(_job_stream(farm, actor, sub, job_id, snapshot, follow),
                             media_type="text/event-stream", headers=_HEADERS)


async def _all_stream(farm: Farm, actor: Principal, sub: Subscription) -> AsyncIterator[str]:
    login = _Login(farm, actor)
    try:
        yield f"retry: {RETRY_MS}\n\n"
        if await login.ended(always=True):  # it may have ended since it was authenticated
            return
        while True:
            event = await sub.next(KEEPALIVE)
            if await login.ended(always=event is None):
                return
            if sub.overflowed:
                sub.overflowed = False
                yield sse_frame("resync", {})  # reload the list: events were dropped
            if event is None:
                yield _KEEPALIVE
                continue
            yield event.sse()
    finally:
        sub.close()


@router.get("/events", response_class=StreamingResponse, responses=_SSE_DOC)
async def all_events(farm: FarmDep, actor: ActorDep) -> StreamingResponse:
    """Server-sent events of every job the caller may see: `job` (any status or
    progress change, new jobs included) and `deleted`; `resync` asks the
    client to reload the list. Never ends by itself."""
    sub = farm.events.subscribe(None, asyncio.get_running_loop(), kinds=JOB_KINDS,
                                owner=None if actor.sees_everything else actor.user)
    return StreamingResponse(_all_stream(farm, actor, sub), media_type="text/event-stream", headers=_HEADERS)
