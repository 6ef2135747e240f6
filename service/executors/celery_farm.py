"""The farm executor: units go to Celery workers through Redis.

Redis is transport, not truth. A unit is *crashed* (an attempt spent) when
its render process died under it: the worker records billiard's
WorkerLostError as the task's FAILURE and does not redeliver it
(worker/celery_app.py). A unit is *lost*, and enqueued again under a
new task id (its attempt count unchanged), when
- the worker rendering it is lost by presence (its heartbeats stopped for
  `worker_lost_seconds`, worker/presence.py) while the unit's latest task is
  among those its presence record says it runs: at once, not after a lease
  (a SIGKILL leaves the message unacknowledged for Redis's visibility
  timeout, an hour by default; we don't wait for that either);
- the worker was started again under its name after its previous process
  died holding the unit's latest task (its new record lists the task as
  `abandoned`): at once, although the name never looked lost;
- it started but no heartbeat of it has been seen for a lease: the unit's
  heartbeat key lives a few heartbeat intervals and its render process keeps
  refreshing it, so a long unit that still renders is never re-run by lease;
- it has been queued longer than a lease while the queue is empty and no
  live worker holds its message: the message itself is gone (e.g. Redis
  restarted without persistence). A worker's presence lists the messages it
  holds (prefetched or running): on a cold start its render processes compile
  kernels for minutes while its main process holds prefetched units, and
  those are neither in the queue nor lost (taking them for lost rendered them
  twice). The messages a lost worker held are lost with it;
- a worker declined it (blocklisted for its job, or disabled meanwhile);
- it was sent to one worker's own queue (below) and that worker is lost or
  stopped before taking it.
While a live worker is blocklisted for a job, the job's units go to the own
queue (Celery's `worker_direct`) of the least loaded live worker that is not:
from the shared queue, an idle blocklisted worker took each of them and
declined it, over and over, while the others were busy.
Results are collected from every task id a unit ever had; the first wins,
and since units are deterministic a late duplicate changes nothing.

Unit films travel by digest (worker/tasks.py `publish_film`): a task's result
names the SHA-256 of the film its worker put in Redis (`input_key`), and
`observe` fetches those bytes and checks them against it. A film gone from
Redis before the service read it makes the unit lost (rendered again, no
attempt spent); bytes that do not match their digest are a failed attempt
(and are deleted, so the retry publishes them afresh). A DAG unit's ticket
names its inputs by digest; they are normally still in Redis where their
workers left them, so `submit` only refreshes their TTL and uploads them from
the store only when they expired. A film no later unit reads is deleted from
Redis once stored (`release`), the others when their job is over (`drop_films`).

Redis serves a queue first in, first out (per message priority), so the
executor keeps only a few units per live render process in it (`limit`):
the scheduler's fair share decides what runs next, not a deep queue filled
by whichever job came first.

`cancel` and `stop` end tasks whether they wait or render: a revoke with
terminate and SIGKILL (a Numba kernel holds the GIL, so a gentler signal
would wait for it), which kills the render process and records the task
REVOKED, never a crash (worker/celery_app.py); plus a marker in Redis that
workers check before they start a unit (the job's `cancel_key`, or the
task's `stopped_key`), since a revoke broadcast reaches only the workers
listening at that moment. A unit whose latest task is REVOKED (e.g. by
another scheduler that lost its lease) is lost and enqueued again.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import re
import threading
import time
import uuid
from collections import Counter
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, Callable, Sequence

import redis

from renderer import process_death
from renderer.scene_format import scene_asset_digests
from worker.celery_app import create_celery_app
from worker.keys import (FILM_TTL, QUEUE, TASK_RENDER_UNIT, asset_key, cancel_key, heartbeat_key, input_key,
                         job_films_key, scene_key, stopped_key, unit_log_key)
from worker.presence import forget_worker, read_workers, set_disabled
from celery.utils.nodenames import worker_direct

# The Redis result backend's key (and pub/sub channel) of a task's state.
RESULT_KEY_PREFIX = "celery-task-meta-"

from ..settings import Settings
from .base import Executor, Flight, Observation, RunningUnit, Ticket, WorkerInfo

__all__ = ["CeleryExecutor"]

log = logging.getLogger(__name__)

SCENE_TTL = 7 * 24 * 3600  # refreshed whenever a unit of the scene is enqueued
CANCEL_TTL = 24 * 3600
PRIORITY_SEP = "\x06\x16"  # kombu's Redis transport: queue<sep><priority> lists
PRIORITY_STEPS = (0, 3, 6, 9)  # kombu's default; a message goes to the step at or below


def redis_priority(priority: int) -> int:
    """A job priority (-100..100, higher first) as a Redis message priority
    (0 is served first there). Four steps only, so it is coarse; the scheduler
    orders what it enqueues by the exact priority."""
    if priority >= 50:
        return 0
    if priority > 0:
        return 3
    return 6 if priority == 0 else 9


class CeleryExecutor(Executor):
    name = "celery"
    # Units in flight per live render process (see `limit`), and in all while no
    # worker has reported yet.
    MIN_AHEAD, MAX_AHEAD = 2, 8
    NO_WORKER_SLOTS = 4

    def __init__(self, settings: Settings, load_scene_text: Callable[[str], str],
                 load_unit_film: Callable[[str, int], bytes] | None = None,
                 asset_dir=None):
        self.app = create_celery_app(settings)
        self.asset_dir = None if asset_dir is None else Path(asset_dir)
        self._scene_assets: dict[str, list[str]] = {}  # scene hash -> the digests it names
        self.lease = timedelta(seconds=settings.unit_lease_seconds)
        self.lease_seconds = settings.unit_lease_seconds
        # The unit heartbeat's TTL: a few beats, never more than the lease.
        self.heartbeat_ttl = min(3 * settings.worker_heartbeat_seconds, self.lease_seconds)
        self.lost_seconds = settings.worker_lost_seconds
        self._beat_seen: dict[str, datetime] = {}  # task id -> when its unit's heartbeat was last seen
        # Tasks whose worker is lost by presence or restarted -> (that worker,
        # why), and the tasks live workers hold (read at most once a second).
        self._lost_tasks: dict[str, tuple[str, str]] = {}
        self._held_tasks: set[str] = set()
        self._lost_read = -1e9
        self._presence: list[WorkerInfo] = []  # as of `_lost_read`
        # Tasks sent to one worker's own queue -> that worker, and how many were
        # sent to each since presence was last read (see `_direct_target`).
        self._directed: dict[str, str] = {}
        self._directed_since: Counter[str] = Counter()
        self._stranded: dict[str, str] = {}  # directed tasks whose worker is gone
        self.redis = redis.Redis.from_url(settings.broker_url)
        self._load_scene_text = load_scene_text
        self._load_unit_film = load_unit_film
        self._published: dict[str, float] = {}
        # Tasks whose film no later unit reads (dropped from Redis at `release`),
        # and the digest each finished task's film had.
        self._transient: set[str] = set()
        self._digest_of: dict[str, str] = {}
        self.inputs_uploaded = 0  # inputs sent from the store because they had expired
        self._uncanceled: set[str] = set()  # jobs whose cancel marker we removed
        self.poll_interval = settings.poll_interval
        self._unit_seconds = 0.1  # a running mean of render seconds per unit (see limit)
        self._processes, self._processes_read = 0, -1e9
        self._listener: threading.Thread | None = None  # on_progress's pub/sub thread
        self._listening = threading.Event()

    # -- submitting ------------------------------------------------------------
    def _publish_scene(self, scene_hash: str) -> None:
        # Check at most every few seconds that the scene is still in Redis
        # (it may have restarted), refreshing its expiry.
        now = time.monotonic()
        if now - self._published.get(scene_hash, -1e9) < 5.0:
            return
        key = scene_key(scene_hash)
        text = None
        if not self.redis.expire(key, SCENE_TTL):
            text = self._load_scene_text(scene_hash)
            self.redis.set(key, text, ex=SCENE_TTL)
        # Its assets go with it, with the same lifetime (a worker reads them
        # when it first builds the scene).
        digests = self._scene_assets.get(scene_hash)
        if digests is None:
            text = text if text is not None else self._load_scene_text(scene_hash)
            digests = scene_asset_digests(json.loads(text))
            if len(self._scene_assets) >= 64:
                self._scene_assets.pop(next(iter(self._scene_assets)))
            self._scene_assets[scene_hash] = digests
        if digests:
            pipe = self.redis.pipeline(transaction=False)
            for digest in digests:
                pipe.expire(asset_key(digest), SCENE_TTL)
            for digest, present in zip(digests, pipe.execute()):
                if not present:
                    if self.asset_dir is None:
                        raise RuntimeError(f"asset {digest[:12]} of scene {scene_hash[:12]} is "
                                           "not in the broker and this executor cannot read the "
                                           "store")
                    blob = (self.asset_dir / digest).read_bytes()
                    self.redis.set(asset_key(digest), blob, ex=SCENE_TTL)
        self._published[scene_hash] = now

    def _refresh_inputs(self, ticket: Ticket) -> dict[str, str]:
        """Make sure each input of the ticket is in Redis under its digest and
        return index -> digest. Normally it is (its worker published it): only
        its TTL is refreshed. One that expired (EXPIRE answers 0) is uploaded
        from the store, the truth."""
        if not ticket.inputs:
            return {}
        pipe = self.redis.pipeline(transaction=False)
        for digest in ticket.inputs.values():
            pipe.expire(input_key(digest), FILM_TTL)
        digests = {}
        for (index, digest), present in zip(ticket.inputs.items(), pipe.execute()):
            if not present:
                digest = self._upload_input(ticket.job_id, index, digest)
            digests[str(index)] = digest
        return digests

    def _upload_input(self, job_id: str, index: int, digest: str) -> str:
        if self._load_unit_film is None:
            raise RuntimeError(f"input {digest[:12]} expired from the broker and this "
                               "executor cannot read the store")
        data = self._load_unit_film(job_id, index)
        stored = hashlib.sha256(data).hexdigest()
        if stored != digest:  # the store is the truth; the ledger's digest is stale
            log.error("unit %s/%d: stored film has digest %s, the ledger says %s",
                      job_id, index, stored[:12], digest[:12])
        self.redis.set(input_key(stored), data, ex=FILM_TTL)
        self.inputs_uploaded += 1
        return stored

    def submit(self, ticket: Ticket) -> str:
        self._publish_scene(ticket.scene_hash)
        if ticket.job_id not in self._uncanceled:  # a retried or requeued job runs again
            self.redis.delete(cancel_key(ticket.job_id))
            if len(self._uncanceled) >= 10000:  # bounded; forgetting costs one DEL
                self._uncanceled.clear()
            self._uncanceled.add(ticket.job_id)
        task_id = uuid.uuid4().hex
        payload = {"job_id": ticket.job_id, "index": ticket.index,
                   "scene_hash": ticket.scene_hash, "spec": ticket.spec, "unit": ticket.unit,
                   "lease_seconds": self.lease_seconds, "heartbeat_seconds": self.heartbeat_ttl,
                   "blocked": list(ticket.blocked),
                   "inputs": self._refresh_inputs(ticket)}
        target = self._direct_target(ticket.blocked) if ticket.blocked else None
        self.app.send_task(TASK_RENDER_UNIT, args=[payload], task_id=task_id,
                           queue=worker_direct(target) if target else QUEUE,
                           priority=redis_priority(ticket.priority))
        if target is not None:
            self._directed[task_id] = target
            self._directed_since[target] += 1
        if not ticket.is_input:
            self._transient.add(task_id)
        return task_id

    def _direct_target(self, blocked: Sequence[str]) -> str | None:
        """The worker whose own queue a unit of a job that `blocked` workers
        decline should go to: None (the shared queue) unless a live worker is
        blocklisted; then the least loaded live, enabled worker that is not
        (messages it holds, and units sent to it since presence was read, per
        render process), or None if there is none (the scheduler fails the
        job when every live worker is blocklisted)."""
        self._read_presence()  # presence, read at most once a second
        live = [w for w in self._presence if w.state in ("busy", "idle") and not w.disabled]
        blocked = set(blocked)
        if not any(w.name in blocked for w in live):
            return None
        allowed = [w for w in live if w.name not in blocked]
        if not allowed:
            return None
        return min(allowed, key=lambda w: ((len(w.reserved) + self._directed_since[w.name])
                                           / max(w.concurrency, 1), w.name)).name

    # -- observing -------------------------------------------------------------
    def _metas(self, task_ids: list[str]) -> dict[str, dict | None]:
        backend = self.app.backend
        raw = self.redis.mget([backend.get_key_for_task(t) for t in task_ids]) if task_ids else []
        return {t: (backend.decode(r) if r is not None else None) for t, r in zip(task_ids, raw)}

    def queue_length(self) -> int:
        pipe = self.redis.pipeline()
        for pri in PRIORITY_STEPS:
            pipe.llen(f"{QUEUE}{PRIORITY_SEP}{pri}" if pri else QUEUE)
        return sum(pipe.execute())

    def observe(self, flights: Sequence[Flight], now: datetime) -> list[Observation]:
        if not flights:
            return []
        metas = self._metas([t for f in flights for t in f.task_ids])
        beats = self.redis.mget([heartbeat_key(f.job_id, f.index) for f in flights])
        lost_tasks = self._read_presence()
        queue_length: int | None = None
        out = []
        for flight, beat in zip(flights, beats):
            obs = self._decide(flight, [metas[t] for t in flight.task_ids], beat, now, lost_tasks)
            if obs is None and flight.task_ids and (flight.task_ids[-1] in self._held_tasks
                                                    or flight.task_ids[-1] in self._directed):
                # A live worker holds it (e.g. still warming up), or it waits in
                # a live worker's own queue (a stopped one's is `_stranded`).
                obs = Observation("queued")
            if obs is None:  # queued for more than a lease: lost only if the queue is empty
                if queue_length is None:
                    queue_length = self.queue_length()
                obs = Observation("lost", cause="message",
                                  error=f"queued for over {self.lease_seconds:g} s and not in "
                                        "the broker's queue") if queue_length == 0 \
                    else Observation("queued")
            out.append(obs)
        return out

    def _read_presence(self) -> dict[str, tuple[str, str]]:
        """Read the workers' presence (at most once a second) and return task id
        -> (worker, why) for the units lost workers were rendering or held, and
        those the previous process of a restarted worker held; the same read
        refreshes `_presence`, the tasks live workers hold (`_held_tasks`) and
        the directed tasks of stopped workers (`_stranded`)."""
        now = time.monotonic()
        if now - self._lost_read >= 1.0:
            lost, held = {}, set()
            self._presence = self.workers()
            for w in self._presence:
                tasks = {r.task_id for r in w.running if r.task_id} | set(w.reserved)
                if w.state == "lost":
                    why = (f"worker {w.name} lost (no presence heartbeat for "
                           f"{self.lost_seconds:g} s)")
                    lost.update(dict.fromkeys(tasks | set(w.abandoned), (w.name, why)))
                elif w.state in ("busy", "idle"):
                    held |= tasks
                    # Its new process holds none of them (unless taken again).
                    why = f"worker {w.name} was restarted; its previous process died holding it"
                    lost.update(dict.fromkeys(set(w.abandoned) - tasks, (w.name, why)))
            self._lost_tasks, self._held_tasks = lost, held
            # A unit in the own queue of a worker that is lost, stopped or
            # forgotten waits for nobody: it is enqueued again at once.
            gone = {w.name for w in self._presence if w.state in ("lost", "offline")}
            gone |= set(self._directed.values()) - {w.name for w in self._presence}
            self._stranded = {t: name for t, name in self._directed.items()
                              if name in gone and t not in lost}
            self._directed_since.clear()
            self._lost_read = now
        return self._lost_tasks

    def _decide(self, flight: Flight, metas: list[dict | None], beat: bytes | None,
                now: datetime, lost_tasks: dict[str, tuple[str, str]]) -> Observation | None:
        for task_id, meta in zip(flight.task_ids, metas):
            if meta and meta.get("status") == "SUCCESS":
                result = meta.get("result") or {}
                if "declined" in result or "canceled" in result:
                    continue  # only the latest task's matters (below)
                obs = self._landed(task_id, result)
                # An earlier task whose film is gone or bad leaves the unit to
                # its latest task (the retry it was enqueued again for).
                if obs.state == "done" or task_id == flight.task_ids[-1]:
                    return obs
        latest = metas[-1] if metas else None
        latest_id = flight.task_ids[-1] if flight.task_ids else None
        status = latest.get("status") if latest else None
        if status == "SUCCESS":  # declined or canceled (a done result returned above)
            result = latest.get("result") or {}
            if "canceled" in result:  # the job was canceled then enqueued again (retried)
                return Observation("lost", cause="message", worker=result.get("worker"),
                                   error="the worker found its job canceled")
            return Observation("lost", cause="declined", worker=result.get("worker"),
                               error=f"declined by {result.get('worker')}: {result['declined']}")
        if status == "REVOKED":  # stopped by a scheduler that no longer wanted it
            return Observation("lost", cause="message", worker=(latest or {}).get("worker"),
                               error="its task was revoked")
        if status == "FAILURE":
            crash = _process_death(latest)
            if crash is not None:
                return Observation("crashed", error=crash, worker=latest.get("worker"),
                                   log=self._failure_log(flight.task_ids[-1], latest))
            if (latest.get("result") or {}).get("exc_type") == "InputUnavailable":
                # An input expired meanwhile: enqueued again, it is re-sent from the store.
                return Observation("lost", cause="message",
                                   error="an input film expired from the broker")
            return Observation("failed", error=_error_text(latest), worker=latest.get("worker"),
                               log=self._failure_log(flight.task_ids[-1], latest))
        if latest_id in lost_tasks:
            worker, why = lost_tasks[latest_id]
            return Observation("lost", cause="worker", worker=worker, error=why)
        if beat is None and status in (None, "PENDING") and latest_id in self._stranded:
            name = self._stranded[latest_id]
            return Observation("lost", cause="worker", worker=name,
                               error=f"sent to worker {name}, which stopped before taking it")
        if beat is not None:
            if latest_id is not None:
                self._beat_seen[latest_id] = now
            return Observation("running", worker=beat.decode(errors="replace"))
        if status == "STARTED" or flight.state == "running":
            started = flight.started_at if flight.state == "running" else None
            if started is not None:
                # The lease runs from the last heartbeat seen (or the start).
                seen = max(started, self._beat_seen.get(latest_id, started))
                if now - seen > self.lease:
                    return Observation("lost", cause="lease",
                                       error=f"no heartbeat for {self.lease_seconds:g} s")
            worker = (latest or {}).get("result") or {}
            return Observation("running", worker=worker.get("hostname") if isinstance(worker, dict) else None)
        if now - flight.enqueued_at > self.lease:
            return None
        return Observation("queued")

    def _failure_log(self, task_id: str, meta: dict) -> dict:
        """A failed task's captured log (left in Redis by the worker), with the
        traceback of the result backend if the worker left none."""
        try:
            raw = self.redis.get(unit_log_key(task_id))
            captured = json.loads(raw) if raw else {}
        except (redis.RedisError, ValueError) as exc:
            log.warning("the log of task %s is unreadable: %s", task_id, exc)
            captured = {}
        if not captured.get("traceback") and meta.get("traceback"):
            captured["traceback"] = str(meta["traceback"])
        return {"lines": list(captured.get("lines") or ()), "dropped": captured.get("dropped", 0),
                "traceback": captured.get("traceback")}

    def _landed(self, task_id: str, result: dict) -> Observation:
        """A finished task's film, fetched by the digest its result names and
        checked against it."""
        digest = result.get("digest")
        if not isinstance(digest, str):
            return Observation("failed", error=f"task returned no film digest: {sorted(result)}")
        film = self.redis.get(input_key(digest))
        if film is None:  # expired (or Redis restarted) before we read it: render it again
            log.warning("film %s of task %s is gone from the broker", digest[:12], task_id)
            return Observation("lost", cause="message",
                               error=f"film {digest[:12]} expired from the broker before it was stored")
        if hashlib.sha256(film).hexdigest() != digest:
            self.redis.delete(input_key(digest))  # so the retry's worker publishes it afresh
            return Observation("failed", error=f"film {digest[:12]} in the broker does not "
                                               "match its digest (corrupted)")
        self._digest_of[task_id] = digest
        self._note_seconds(result.get("stats") or {})
        return Observation("done", film=film, digest=digest, worker=result.get("worker"),
                           log=result.get("log"))

    def _note_seconds(self, stats: dict) -> None:
        try:
            seconds = float(stats.get("seconds", 0.0))
        except (TypeError, ValueError):
            return
        self._unit_seconds += 0.2 * (seconds - self._unit_seconds)

    # -- cleaning up -----------------------------------------------------------
    def release(self, task_ids: Sequence[str]) -> None:
        transient = set()
        for task_id in task_ids:
            self.app.backend.forget(task_id)
            self._beat_seen.pop(task_id, None)
            self._directed.pop(task_id, None)
            digest = self._digest_of.pop(task_id, None)
            if task_id in self._transient:
                self._transient.discard(task_id)
                if digest is not None:
                    transient.add(digest)
        if task_ids:
            self.redis.delete(*[unit_log_key(t) for t in task_ids])
        if transient:  # stored; no later unit reads them
            self.drop_films(sorted(transient))

    def drop_films(self, digests: Sequence[str]) -> None:
        for start in range(0, len(digests), 512):
            self.redis.delete(*(input_key(d) for d in digests[start:start + 512]))

    def cancel(self, job_id: str, task_ids: Sequence[str]) -> None:
        # The marker makes any worker skip the job's units still queued (also
        # workers started later, which a revoke broadcast does not reach) and
        # refuse to publish the film of one that finishes after it. Every film
        # published before it is in the job's film set (worker/tasks.py
        # `publish_film` does both in one atomic step), so reading the set after
        # setting the marker finds them all: they go now, not when they expire.
        # (The job is over or starts again from its store: its later units, if
        # any, get their inputs uploaded again, `_refresh_inputs`.)
        self.redis.set(cancel_key(job_id), "1", ex=CANCEL_TTL)
        self._uncanceled.discard(job_id)
        self._revoke(task_ids)
        published = sorted(d.decode() for d in self.redis.smembers(job_films_key(job_id)))
        self.redis.delete(job_films_key(job_id))
        if published:
            self.drop_films(published)
        self.release(task_ids)

    def stop(self, task_ids: Sequence[str]) -> None:
        if not task_ids:
            return
        pipe = self.redis.pipeline(transaction=False)
        for task_id in task_ids:
            pipe.set(stopped_key(task_id), "1", ex=CANCEL_TTL)
        pipe.execute()
        self._revoke(task_ids)
        self.release(task_ids)

    def _revoke(self, task_ids: Sequence[str]) -> None:
        """Revoke the tasks on every worker, killing a render process that runs
        one (see the module doc)."""
        if task_ids:
            self.app.control.revoke(list(task_ids), terminate=True, signal="SIGKILL")

    def render_processes(self) -> int:
        return self._live_processes()

    def limit(self) -> int:
        """Units to keep in flight (running, reserved by a worker or waiting in
        Redis): `ahead` per render process of the live workers, as their presence
        records say (worker/presence.py), or `NO_WORKER_SLOTS` while none has
        reported (the first units wait for it in Redis). `ahead` covers one
        scheduler tick of the mean unit (the service only notices finished units
        on its ticks), between `MIN_AHEAD` and `MAX_AHEAD`: enough that no process
        idles between ticks, few enough that the broker's first-in, first-out
        queue holds little work, and fair share, not the queue, decides what
        runs next."""
        processes = self._live_processes()
        if not processes:
            return self.NO_WORKER_SLOTS
        per_tick = math.ceil(self.poll_interval / max(self._unit_seconds, 1e-3)) + 1
        return min(max(per_tick, self.MIN_AHEAD), self.MAX_AHEAD) * processes

    def capacity(self, in_flight: int) -> int:
        # A broker that is down raises here: the tick fails and the scheduler
        # reports it (/healthz `scheduler_error`), as a failed send would.
        return max(self.limit() - in_flight, 0)

    def _live_processes(self) -> int:
        """Render processes of the workers that beat recently (read at most once a second)."""
        now = time.monotonic()
        if now - self._processes_read >= 1.0:
            self._processes = sum(w.concurrency for w in self.workers()
                                  if w.state in ("busy", "idle") and not w.disabled)
            self._processes_read = now
        return self._processes

    def workers(self) -> list[WorkerInfo]:
        """Every worker that reported to this broker (worker/presence.py):
        lost when its last beat is older than `worker_lost_seconds`."""
        now, records = read_workers(self.redis)
        out = []
        for r in records:
            last_seen = float(r.get("last_seen", 0.0))
            running = tuple(RunningUnit(u["job_id"], int(u["index"]), _utc(u.get("since")),
                                        u.get("task_id"))
                            for u in r["running"])
            reserved = tuple(r.get("reserved") or ())
            abandoned = tuple(r.get("abandoned") or ())
            if r.get("state") == "offline":
                state, running, reserved, abandoned = "offline", (), (), ()
            elif now - last_seen > self.lost_seconds:
                state = "lost"
            else:
                state = "busy" if running else "idle"
            out.append(WorkerInfo(
                name=r["name"], kind="celery", host=r.get("host", ""), state=state,
                concurrency=int(r.get("concurrency", 1)), running=running,
                units_done=int(r.get("units_done", 0)), samples=int(r.get("samples", 0)),
                rays=int(r.get("rays", 0)), seconds=float(r.get("seconds", 0.0)),
                started=_utc(r.get("started")), last_seen=_utc(last_seen),
                silent_seconds=max(now - last_seen, 0.0), disabled=bool(r.get("disabled")),
                reserved=reserved, abandoned=abandoned))
        return out

    def set_worker_enabled(self, name: str, enabled: bool) -> None:
        # The marker first (a restarted worker reads it; a prefetched unit is
        # declined by it), then the broadcast: the worker stops or starts
        # consuming now rather than at its next beat.
        set_disabled(self.redis, name, not enabled)
        control = self.app.control.add_consumer if enabled else self.app.control.cancel_consumer
        control(QUEUE, destination=[name])
        self._processes_read = -1e9  # its processes no longer count (see limit)

    def remove_worker(self, name: str) -> None:
        forget_worker(self.redis, name)

    def health(self) -> dict:
        try:
            self.redis.ping()
            broker = "ok"
        except redis.RedisError as exc:
            broker = f"unreachable: {exc}"
        return {"executor": self.name, "broker": broker}

    # -- landing ---------------------------------------------------------------
    def on_progress(self, callback) -> None:
        """Call `callback` whenever a task's state is stored: Celery's Redis
        result backend PUBLISHes every result on the channel named by its key
        (celery-task-meta-<id>), so the scheduler collects a landed unit at
        once instead of at its next poll (poll_interval). Pub/sub channels are
        server-wide, so another farm on the same Redis only wakes us early."""
        if self._listener is not None:
            return
        self._listening.set()
        self._listener = threading.Thread(target=self._listen, args=(callback,),
                                          name="rayfarm-landing", daemon=True)
        self._listener.start()

    def _listen(self, callback) -> None:
        while self._listening.is_set():
            pubsub = self.redis.pubsub(ignore_subscribe_messages=True)
            try:
                pubsub.psubscribe(f"{RESULT_KEY_PREFIX}*")
                while self._listening.is_set():
                    if pubsub.get_message(timeout=1.0) is not None:
                        callback()
            except (redis.RedisError, OSError, ValueError) as exc:
                # Redis gone or restarting: the scheduler polls meanwhile
                if self._listening.is_set():
                    log.info("landing listener: %s; retrying", exc)
                    time.sleep(1.0)
            finally:
                try:
                    pubsub.close()
                except (redis.RedisError, OSError):
                    pass

    def close(self) -> None:
        self._listening.clear()
        if self._listener is not None:
            self._listener.join(5.0)
            self._listener = None
        self.redis.close()
        self.app.close()


def _utc(epoch) -> datetime | None:
    return datetime.fromtimestamp(float(epoch), timezone.utc) if epoch not in (None, "") else None


def _error_text(meta: dict[str, Any]) -> str:
    result = meta.get("result")
    if isinstance(result, dict) and "exc_type" in result:
        message = result.get("exc_message")
        if isinstance(message, (list, tuple)):
            message = " ".join(map(str, message))
        return f"{result['exc_type']}: {message}"
    return str(result)


# billiard's words for a render process that died under its task.
_WORKER_LOST = re.compile(r"exited prematurely: (?:signal (\d+)|exitcode (\d+))")


def _process_death(meta: dict[str, Any]) -> str | None:
    """A FAILURE that is a dead render process (billiard's WorkerLostError), in
    `renderer.process_death`'s words, or None for any other failure."""
    result = meta.get("result")
    if not (isinstance(result, dict) and result.get("exc_type") == "WorkerLostError"):
        return None
    message = result.get("exc_message")
    if isinstance(message, (list, tuple)):
        message = " ".join(map(str, message))
    found = _WORKER_LOST.search(str(message))
    if found is None:
        return f"render process died ({message})"
    return process_death(-int(found[1]) if found[1] else int(found[2]))
