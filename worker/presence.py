"""Worker presence: each Celery worker says it is alive, what it renders, what it did.

    rayfarm:workers                  set of worker names
    rayfarm:worker:<name>            hash: host, pid, concurrency, started, last_seen,
                                     state (online | offline), units_done, samples,
                                     rays, seconds, reserved (JSON list of the task
                                     ids this worker holds: prefetched or running),
                                     abandoned (JSON list of the task ids a previous
                                     process under this name held when it died)
    rayfarm:worker:<name>:running    hash: render process id -> {"job_id", "index", "since",
                                     "task_id"}
    rayfarm:workers:disabled         set of the names an admin disabled (no expiry)

Times are Redis's own clock (`TIME`), so the service compares them with the
same clock whatever the machines' clocks say. The worker's main process beats
every `worker_heartbeat_seconds` from a thread: it never renders (prefork),
so a long unit never delays a beat, and a killed worker simply stops beating
(the service shows it as lost). Its render processes record the unit they
run and add to the counters when it is done. The keys expire a day after the
last beat; the service reads them (`read_workers`), it never writes them.

A worker started again under its old name (`rayfarm worker --name`) after its
previous process died (killed, not stopped: a clean stop leaves the record
"offline" with nothing held) cannot be rendering what that process held. It
lists those tasks, the units its render processes ran and the messages it
had prefetched, as `abandoned` in its new record, and the service enqueues
them again at once, as it does a lost worker's, instead of waiting for their
lease: the new process beats under the same name, so the worker never looks
lost.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading

import redis

from typing import Callable

from .keys import DISABLED_WORKERS, WORKERS, heartbeat_key, worker_key, worker_running_key

__all__ = ["Presence", "unit_started", "unit_finished", "forget_dead_processes", "read_workers",
           "redis_now", "set_disabled", "is_disabled", "forget_worker"]

log = logging.getLogger(__name__)

PRESENCE_TTL = 24 * 3600
MAX_ABANDONED = 4096  # carried over from incarnation to incarnation of a crash loop


def _task_ids(raw) -> list[str]:
    """A JSON list of task ids from a presence field ([] if unreadable)."""
    try:
        value = json.loads(raw or "[]")
    except (ValueError, TypeError):
        return []
    return [str(t) for t in value] if isinstance(value, list) else []


def redis_now(client: redis.Redis) -> float:
    """Seconds since the epoch on the Redis server's clock."""
    seconds, micros = client.time()
    return seconds + micros / 1e6


class Presence:
    """The main process's heartbeat: `start()` when the worker is ready,
    `stop()` when it shuts down (it is then shown offline, not lost).
    `consume(bool)`, if given, starts or stops the worker consuming the queue
    when the disabled set says otherwise (see the module doc), and
    `consuming()` says whether it consumes now: the request is sent again on
    every beat until the consumer follows it (a remote-control message sent
    before the worker's event loop listens is lost). `reserved()`, if
    given, lists the task ids the worker holds (prefetched or running): the
    service must not take a unit whose message a live worker holds for lost
    merely because it has waited long (its render processes may still be
    compiling kernels, minutes on a cold cache)."""

    def __init__(self, client: redis.Redis, name: str, concurrency: int, interval: float,
                 consume: Callable[[bool], None] | None = None,
                 reserved: Callable[[], list[str]] | None = None,
                 consuming: Callable[[], bool | None] | None = None):
        self.client, self.name, self.concurrency, self.interval = client, name, concurrency, interval
        self._consume = consume
        self._reserved = reserved
        self._consuming_now = consuming
        self._consuming = True  # the flag as last followed (a worker starts consuming its queue)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rayfarm-presence", daemon=True)

    def _held(self) -> str:
        if self._reserved is None:
            return "[]"
        try:
            return json.dumps(sorted(self._reserved()))
        except RuntimeError:  # the event loop changed the set meanwhile: next beat
            return self.client.hget(worker_key(self.name), "reserved") or "[]"

    def _beat(self, **fields) -> None:
        fields.setdefault("reserved", self._held())
        now = redis_now(self.client)
        pipe = self.client.pipeline()
        pipe.sadd(WORKERS, self.name)
        pipe.hset(worker_key(self.name), mapping={"last_seen": now, **fields})
        pipe.expire(worker_key(self.name), PRESENCE_TTL)
        pipe.expire(worker_running_key(self.name), PRESENCE_TTL)
        pipe.execute()

    def _follow_disabled(self) -> None:
        if self._consume is None:
            return
        wanted = not self.client.sismember(DISABLED_WORKERS, self.name)
        changed = wanted != self._consuming  # the service may have told the consumer already
        if changed:
            log.info("worker %s %s", self.name, "enabled: consuming again" if wanted
                     else "disabled: no new units (running ones finish)")
            self._consuming = wanted
        if self._consuming_now is None:  # the consumer cannot be seen: ask once
            if changed:
                self._consume(wanted)
            return
        actual = self._consuming_now()  # None: shutting down, leave the consumer be
        if actual is not None and actual != wanted:
            self._consume(wanted)  # asked again on every beat until the consumer follows

    def _beat_units(self) -> None:
        """Refresh the heartbeat key of every unit a live render process of
        this worker renders. The render process beats too, from a thread, but
        a Numba kernel holds the GIL for as long as it runs: this process never
        renders, so a long unit stays alive however long its kernels take. A
        dead render process's record goes, so its unit's heartbeat lapses."""
        key = worker_running_key(self.name)
        pipe = self.client.pipeline()
        for pid, raw in self.client.hgetall(key).items():
            if not _process_alive(int(pid)):
                pipe.hdel(key, pid)
                continue
            unit = json.loads(raw)
            if unit.get("ttl"):
                pipe.set(heartbeat_key(unit["job_id"], int(unit["index"])), self.name,
                         px=max(int(float(unit["ttl"]) * 1000), 1000))
        pipe.execute()

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self._beat(state="online")
                self._beat_units()
                self._follow_disabled()
            except redis.RedisError as exc:  # keep beating; the broker may come back
                log.warning("presence heartbeat failed: %s", exc)
            except Exception:  # a control message that failed: try again next beat
                log.exception("presence: could not follow the disabled flag")

    def _abandoned(self) -> list[str]:
        """The task ids the previous process under this name held, if it died
        (see the module doc), with those its own predecessors had abandoned."""
        old = {k.decode(): v.decode() for k, v in
               self.client.hgetall(worker_key(self.name)).items()}
        if not old or old.get("state") == "offline":
            return []
        tasks = set(_task_ids(old.get("reserved"))) | set(_task_ids(old.get("abandoned")))
        for raw in self.client.hvals(worker_running_key(self.name)):
            try:
                task_id = json.loads(raw).get("task_id")
            except (ValueError, AttributeError):
                continue
            if task_id:
                tasks.add(str(task_id))
        return sorted(tasks)[:MAX_ABANDONED]

    def start(self) -> None:
        now = redis_now(self.client)
        abandoned = self._abandoned()
        if abandoned:
            log.warning("worker %s was started again after its previous process died: %d "
                        "units it held go back to the queue", self.name, len(abandoned))
        self.client.delete(worker_key(self.name), worker_running_key(self.name))
        self._beat(state="online", host=socket.gethostname(), pid=os.getpid(),
                   concurrency=self.concurrency, started=now, units_done=0, samples=0, rays=0,
                   seconds=0.0, abandoned=json.dumps(abandoned))
        self._follow_disabled()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        try:
            self._beat(state="offline", reserved="[]", abandoned="[]")
            self.client.delete(worker_running_key(self.name))
        except redis.RedisError as exc:
            log.warning("could not mark worker %s offline: %s", self.name, exc)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def unit_started(client: redis.Redis, name: str, job_id: str, index: int,
                 task_id: str | None = None, ttl: float | None = None) -> None:
    """A render process of worker `name` starts rendering unit `index` of
    `job_id` as task `task_id` (the service re-enqueues the unit at once if
    this worker is lost while that task is still the unit's latest); the
    worker's main process keeps its heartbeat key (TTL `ttl`) alive meanwhile."""
    try:
        client.hset(worker_running_key(name), str(os.getpid()),
                    json.dumps({"job_id": job_id, "index": index, "since": redis_now(client),
                                "task_id": task_id, "ttl": ttl}))
    except redis.RedisError as exc:
        log.warning("presence: unit start not recorded: %s", exc)


def unit_finished(client: redis.Redis, name: str, stats: dict | None) -> None:
    """The render process is done with its unit; `stats` (samples, rays,
    seconds) if it finished it, None if it failed."""
    try:
        pipe = client.pipeline()
        pipe.hdel(worker_running_key(name), str(os.getpid()))
        if stats is not None:
            key = worker_key(name)
            pipe.hincrby(key, "units_done", 1)
            pipe.hincrby(key, "samples", int(stats.get("samples", 0)))
            pipe.hincrby(key, "rays", int(stats.get("rays", 0)))
            pipe.hincrbyfloat(key, "seconds", float(stats.get("seconds", 0.0)))
        pipe.execute()
    except redis.RedisError as exc:
        log.warning("presence: unit end not recorded: %s", exc)


def forget_dead_processes(client: redis.Redis, name: str, payload: dict | None) -> None:
    """In worker `name`'s main process, after one of its render processes died
    under a unit (`payload`, the task's): delete that unit's heartbeat and the
    "running" entries of render processes of this host that no longer exist."""
    pipe = client.pipeline()
    if payload and "job_id" in payload and "index" in payload:
        pipe.delete(heartbeat_key(payload["job_id"], int(payload["index"])))
    for pid in client.hkeys(worker_running_key(name)):
        if pid.isascii() and pid.isdigit() and not _process_alive(int(pid)):
            pipe.hdel(worker_running_key(name), pid)
    pipe.execute()


def read_workers(client: redis.Redis) -> tuple[float, list[dict]]:
    """(Redis's clock now, every known worker as a dict of its hash fields
    plus `name`, `disabled` (a bool), `reserved` and `abandoned` (lists of task
    ids) and `running`: a list of {"job_id", "index", "since", "task_id"}).
    Workers whose keys expired are forgotten."""
    names = sorted(n.decode() for n in client.smembers(WORKERS))
    disabled = {n.decode() for n in client.smembers(DISABLED_WORKERS)}
    pipe = client.pipeline()
    for name in names:
        pipe.hgetall(worker_key(name))
        pipe.hgetall(worker_running_key(name))
    replies = pipe.execute()
    now = redis_now(client)
    out, gone = [], []
    for name, fields, running in zip(names, replies[0::2], replies[1::2]):
        if not fields:
            gone.append(name)
            continue
        record = {k.decode(): v.decode() for k, v in fields.items()}
        record["name"] = name
        record["disabled"] = name in disabled
        record["reserved"] = _task_ids(record.get("reserved"))
        record["abandoned"] = _task_ids(record.get("abandoned"))  # [] from an older worker
        record["running"] = sorted((json.loads(v) for v in running.values()),
                                   key=lambda r: (r["job_id"], r["index"]))
        out.append(record)
    if gone:
        client.srem(WORKERS, *gone)
    return now, out


def set_disabled(client: redis.Redis, name: str, disabled: bool) -> None:
    """Mark worker `name` disabled (drained) or enabled again; the worker's
    presence thread follows within a beat (module doc)."""
    if disabled:
        client.sadd(DISABLED_WORKERS, name)
    else:
        client.srem(DISABLED_WORKERS, name)


def is_disabled(client: redis.Redis, name: str) -> bool:
    return bool(client.sismember(DISABLED_WORKERS, name))


def forget_worker(client: redis.Redis, name: str) -> None:
    """Remove a worker's presence (an admin removing a lost or offline worker)."""
    pipe = client.pipeline()
    pipe.srem(WORKERS, name)
    pipe.srem(DISABLED_WORKERS, name)
    pipe.delete(worker_key(name), worker_running_key(name))
    pipe.execute()
