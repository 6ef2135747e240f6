"""The farm's one task: render a work unit.

The task takes ids and parameters only; the scene's canonical text travels by
content hash (`rayfarm:scene:<hash>` in Redis, read only when this process
has not built that scene yet), and so do the films of the units it needs
(`input_key(digest)`). It publishes its own film the same way, under its
SHA-256 with a TTL, and returns only that digest, the film's size and stats,
the worker's name and the unit's own log (renderer.unitlog: its log lines; a
failed unit's log, with its traceback, goes to `unit_log_key(task id)` with a
TTL, since Celery's failure result holds only the exception): the service
copies the bytes into its store from there, and a later unit that needs them
finds them already in place. While it runs, a heartbeat key with a short TTL
(a few heartbeat intervals, refreshed three times per TTL by this process and
on every beat by the worker's main process, which never holds the GIL in a
kernel) tells the service the unit is alive, and the worker's presence record
(worker/presence.py) shows the unit (with its task id) and, once it is done,
counts it.

A unit whose job was canceled (`cancel_key`), or whose task the service
stopped (`stopped_key`: preempted, withdrawn or over its time budget), before
it started is skipped, and one whose job was canceled while it rendered does
not publish its film (`publish_film`); all return ``{"canceled": True,
"worker": name}``. A task stopped while it renders is not asked: the service
revokes it with SIGKILL (a Numba kernel holds the GIL for as long as it runs,
so a check in Python would wait for the kernel), and the worker's pool starts
a new render process.

A worker declines a unit, returning ``{"declined": reason, "worker": name}``
at once without rendering, when it is blocklisted for the unit's job (the
payload's ``blocked``) or an admin disabled it (a unit it had prefetched
before the drain): the service enqueues the unit again without spending an
attempt, for another worker.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import threading
from typing import Any

import redis
from celery import Celery

from renderer import PartialFilm, execute_unit
from renderer.unitlog import capture_unit_log

from . import presence
from .keys import (FILM_TTL, TASK_RENDER_UNIT, asset_key, cancel_key, heartbeat_key, input_key, job_films_key,
                   scene_key, stopped_key, unit_log_key)

__all__ = ["register_tasks", "render_unit", "publish_film", "Heartbeat", "SceneUnavailable", "InputUnavailable"]

log = logging.getLogger(__name__)


class SceneUnavailable(RuntimeError):
    """The scene's text is not in Redis (expired, or Redis lost it)."""


class InputUnavailable(RuntimeError):
    """A unit's input (another unit's film) is not in Redis."""


_inputs: dict[str, bytes] = {}  # digest -> bytes: the inputs this process fetched lately
_INPUTS_KEPT = 4


def _fetch_input(client: redis.Redis, digest: str) -> bytes:
    """An input's bytes by digest, from this process's small cache or Redis
    (every gather tile of a photon pass needs the same photon map)."""
    data = _inputs.get(digest)
    if data is None:
        data = client.get(input_key(digest))
        if data is None:
            raise InputUnavailable(f"input {digest[:12]} is not in the broker")
        if hashlib.sha256(data).hexdigest() != digest:
            # Deleted, so the service's next enqueue of this unit (it takes the
            # failure for a lost unit) uploads the bytes again from its store.
            client.delete(input_key(digest))
            raise InputUnavailable(f"input {digest[:12]} in the broker does not match its digest")
        _inputs[digest] = data
        while len(_inputs) > _INPUTS_KEPT:
            _inputs.pop(next(iter(_inputs)))
    return data


def _asset_source(client: redis.Redis):
    """Where a render process reads a scene's assets: the renderer's disk
    cache ("assets"), else the broker (then kept in the cache), so a worker
    host fetches each asset once. Checked against its digest on every read."""
    from renderer.cache import disk_cache

    def load(digest: str) -> bytes:
        cache = disk_cache("assets")
        data = cache.get(digest) if cache is not None else None
        if data is not None and hashlib.sha256(data).hexdigest() == digest:
            return data
        data = client.get(asset_key(digest))
        if data is None:
            raise SceneUnavailable(f"asset {digest[:12]} is not in the broker")
        if hashlib.sha256(data).hexdigest() != digest:
            client.delete(asset_key(digest))  # the service publishes it again from its store
            raise SceneUnavailable(f"asset {digest[:12]} in the broker does not match its digest")
        if cache is not None:
            cache.put(digest, data)
        return data
    return load


class Heartbeat:
    """Keep `key` alive (value `value`, TTL `ttl` seconds) while the block runs.

    >>> with Heartbeat(client, "rayfarm:hb:abc:3", ttl=60, value="worker-1"):
    ...     render()
    """

    def __init__(self, client: redis.Redis, key: str, ttl: float, value: str):
        self.client, self.key, self.value = client, key, value
        self.ttl_ms = max(int(ttl * 1000), 1000)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="rayfarm-heartbeat", daemon=True)

    def _set(self) -> None:
        try:
            self.client.set(self.key, self.value, px=self.ttl_ms)
        except redis.RedisError as exc:  # the render goes on; the lease may run out
            log.warning("heartbeat %s not refreshed: %s", self.key, exc)

    def _beat(self) -> None:
        # Three refreshes per lease, so one slow round trip never lets it lapse.
        while not self._stop.wait(self.ttl_ms / 3000):
            self._set()

    def __enter__(self) -> "Heartbeat":
        self._set()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        try:
            self.client.delete(self.key)
        except redis.RedisError:
            pass


UNIT_LOG_TTL = 24 * 3600  # the service reads it on its next tick; a day covers an outage

_clients: dict[tuple[int, str], redis.Redis] = {}


def _redis(url: str) -> redis.Redis:
    """One client per process (prefork children must not share sockets)."""
    key = (os.getpid(), url)
    if key not in _clients:
        _clients[key] = redis.Redis.from_url(url)
    return _clients[key]


# Publishing a film is one atomic step with the cancel check: a film published
# before the job's cancel marker is set is in the job's film set when the
# service, having set the marker, reads it (and drops it); one published after
# is refused. Checking the marker in a separate call left a window in which
# neither side took the film back (it stayed in Redis for a day). Returns 0
# (canceled), 1 (published) or 2 (not there yet: call again with the bytes,
# which are sent only then).
_PUBLISH_LUA = """
if redis.call('EXISTS', KEYS[1]) == 1 then return 0 end
if redis.call('EXPIRE', KEYS[2], ARGV[1]) == 0 then
  if #ARGV < 3 then return 2 end
  redis.call('SET', KEYS[2], ARGV[3], 'EX', ARGV[1])
end
redis.call('SADD', KEYS[3], ARGV[2])
redis.call('EXPIRE', KEYS[3], ARGV[1])
return 1
"""


def publish_film(client: redis.Redis, job_id: str, film: bytes) -> str | None:
    """Put `film` in Redis under its SHA-256 (`input_key`, TTL `FILM_TTL`),
    note it in the job's film set and return the digest, unless the job is
    canceled (None). Bytes already there (a retried unit renders the same
    bytes) only get their TTL refreshed, not sent again."""
    digest = hashlib.sha256(film).hexdigest()
    script = client.register_script(_PUBLISH_LUA)
    keys = [cancel_key(job_id), input_key(digest), job_films_key(job_id)]
    done = script(keys=keys, args=[FILM_TTL, digest])
    if done == 2:
        done = script(keys=keys, args=[FILM_TTL, digest, film])
    return digest if done == 1 else None


def render_unit(client: redis.Redis, worker: str, payload: dict[str, Any],
                task_id: str | None = None) -> dict[str, Any]:
    """Run one unit described by `payload`, publish its film (`publish_film`)
    and return ``{"digest": sha256, "bytes": n, "stats": {...}, "worker": name,
    "log": captured}``; if it raises, its captured log is left under
    `unit_log_key(task_id)` first.

    `payload`: ``job_id``, ``index``, ``scene_hash``, ``spec`` (a RenderSpec
    dict), ``unit`` (a Unit dict), ``heartbeat_seconds`` (the unit heartbeat's
    TTL; older services sent ``lease_seconds``), ``blocked`` (workers that
    decline it) and ``inputs`` (unit index -> SHA-256 of the film bytes it
    needs, in Redis under `input_key`, where the worker that rendered that
    unit put them).
    """
    job_id, index, scene = payload["job_id"], int(payload["index"]), payload["scene_hash"]
    if client.exists(cancel_key(job_id), *([stopped_key(task_id)] if task_id else [])):
        return {"canceled": True, "worker": worker}
    if worker in (payload.get("blocked") or ()):
        return {"declined": "blocklisted for the job", "worker": worker}
    if presence.is_disabled(client, worker):
        return {"declined": "disabled", "worker": worker}

    def load_scene_text() -> str:
        text = client.get(scene_key(scene))
        if text is None:
            raise SceneUnavailable(f"scene {scene[:12]} is not in the broker")
        return text.decode()

    ttl = float(payload.get("heartbeat_seconds") or payload["lease_seconds"])
    presence.unit_started(client, worker, job_id, index, task_id, ttl)
    stats = None
    captured = None
    try:
        with Heartbeat(client, heartbeat_key(job_id, index), ttl, worker), \
                capture_unit_log(job_id, index) as captured:
            inputs = {int(i): _fetch_input(client, digest)
                      for i, digest in (payload.get("inputs") or {}).items()}
            film = execute_unit(scene, load_scene_text, payload["spec"], payload["unit"], inputs,
                                load_asset=_asset_source(client))
            # Published while the heartbeat still says the unit is alive.
            digest = publish_film(client, job_id, film)
        stats = PartialFilm.stats_from_bytes(film)
        if digest is None:  # canceled while it rendered: the service will never store it
            return {"canceled": True, "worker": worker}
    except Exception:
        if captured is not None and task_id:
            _leave_log(client, task_id, captured.to_dict())
        raise
    finally:
        presence.unit_finished(client, worker, stats)
    return {"digest": digest, "bytes": len(film), "stats": stats, "worker": worker,
            "log": captured.to_dict()}


def _leave_log(client: redis.Redis, task_id: str, log_data: dict) -> None:
    try:
        client.set(unit_log_key(task_id), json.dumps(log_data), ex=UNIT_LOG_TTL)
    except redis.RedisError as exc:  # the failure itself still reaches the service
        log.warning("the log of task %s was not kept: %s", task_id, exc)


def register_tasks(app: Celery) -> None:
    """Register the farm's task on `app` under its public name."""

    @app.task(name=TASK_RENDER_UNIT, bind=True)
    def _render_unit_task(self, payload: dict[str, Any]) -> dict[str, Any]:
        client = _redis(self.app.conf.broker_url)
        worker = self.request.hostname or f"pid-{os.getpid()}"
        return render_unit(client, worker, payload, task_id=self.request.id)
