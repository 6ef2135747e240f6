"""The Celery application of the farm, built from `Settings` (never at import).

    app = create_celery_app(Settings(broker_url="redis://localhost:6379/0"))
    app.send_task(TASK_RENDER_UNIT, args=[payload], queue=QUEUE)

Redis is both broker and result backend. Messages are acknowledged late
(`task_acks_late`): a worker killed as a whole leaves its unit's message
unacknowledged, and since a unit's result is deterministic a second delivery
changes nothing. But a render process that dies under its unit (a segfault,
a SIGKILL of that process) is *not* redelivered by the broker
(`task_reject_on_worker_lost` off): the worker acknowledges the message and
records a FAILURE with billiard's `WorkerLostError` ("Worker exited
prematurely: signal 11 (SIGSEGV)"), the service counts that as a crashed
attempt, and the ledger's attempt count decides whether it runs again. (With
redelivery on, a unit that crashes every process looped forever.) A message
that Redis itself loses is the service's business: it watches heartbeats and
enqueues the unit again (see service/executors).

The service stops a unit it no longer wants rendered (its job canceled, the
unit preempted or over its time budget) with `revoke(terminate=True,
signal="SIGKILL")`. Celery then records the task REVOKED, acknowledges its
message and kills the render process; billiard reports that death as
`Terminated`, not as `WorkerLostError`, so no FAILURE is stored and nothing
counts it as a crash (and the service has moved the unit on under a new
task anyway).
"""

from __future__ import annotations

import logging

from celery import Celery
from celery.signals import (after_setup_logger, after_setup_task_logger, task_failure,
                            task_revoked, worker_init, worker_process_init, worker_ready,
                            worker_shutdown)

from .keys import QUEUE
from .settings import Settings

__all__ = ["create_celery_app"]

log = logging.getLogger(__name__)


def create_celery_app(settings: Settings) -> Celery:
    """A Celery app on `settings.broker_url` with the farm's task registered."""
    if not settings.broker_url:
        raise ValueError("the Celery app needs RAYFARM_BROKER_URL (e.g. redis://localhost:6379/0)")
    app = Celery("rayfarm", broker=settings.broker_url, backend=settings.broker_url,
                 set_as_current=False)
    app.conf.update(
        task_serializer="json",
        result_serializer="json",
        accept_content=["json"],
        task_acks_late=True,
        # A dead render process is a FAILURE the service counts, not a redelivery
        # behind the ledger's back (see the module doc).
        task_reject_on_worker_lost=False,
        worker_prefetch_multiplier=1,
        task_track_started=True,
        # A result (also a failure) names the worker it came from: the service
        # counts failed units per worker and job (blocklisting, service.workers).
        result_extended=True,
        task_default_queue=QUEUE,
        # Each worker also consumes its own queue (`<name>.dq2`): the service
        # sends a job's units there when a live worker is blocklisted for the
        # job, so that worker never takes them from the shared queue only to
        # decline them again and again (service/executors/celery_farm.py).
        worker_direct=True,
        # Results are collected within seconds; don't keep stale films for a day.
        result_expires=3600,
        # Each child warms the Numba kernels at start (loading the on-disk cache or
        # compiling); Celery's default of 4 s would kill it mid-compilation.
        worker_proc_alive_timeout=600.0,
        worker_hijack_root_logger=False,
        broker_connection_retry_on_startup=True,
    )
    app.conf.rayfarm_heartbeat_seconds = settings.worker_heartbeat_seconds
    global _log_format
    _log_format = settings.log_format
    # The render processes are forked from here: they inherit the cache directory.
    settings.configure_renderer()
    from .tasks import register_tasks

    register_tasks(app)
    return app


_log_format = "text"  # of the last app built: a `rayfarm worker` builds one


@after_setup_logger.connect
@after_setup_task_logger.connect
def _json_logs(logger=None, **_kwargs) -> None:
    # RAYFARM_LOG_FORMAT=json: Celery's handlers (the render processes inherit
    # them) write one JSON object per line, with the unit's ids while it renders.
    if _log_format == "json" and logger is not None:
        from renderer.unitlog import JsonLogFormatter

        for handler in logger.handlers:
            handler.setFormatter(JsonLogFormatter())


@worker_process_init.connect
def _warm_up_child(**_kwargs) -> None:
    # One unit per process, one process per core: Numba runs single-threaded
    # here, and compiles (or loads its cache) once, before the first task.
    import numba

    from renderer import warm_up

    numba.set_num_threads(1)
    warm_up()
    log.info("render process warmed up")


@worker_init.connect
def _start_drained(sender=None, **_kwargs) -> None:
    # A worker an admin disabled stays disabled across a restart (its name is
    # in the disabled set): it must not consume the shared queue even for the
    # moment before its presence's first beat cancels the consumer, or it takes
    # a unit only to decline it. Celery sends this signal after the worker
    # chose its queues and before its consumer starts (its own direct queue stays).
    import redis

    from .presence import is_disabled

    try:
        with redis.Redis.from_url(sender.app.conf.broker_url) as client:
            disabled = is_disabled(client, sender.hostname)
    except Exception:  # the presence thread follows the flag within a beat anyway
        log.exception("could not read whether worker %s is disabled", sender.hostname)
        return
    if disabled:  # (logging is not set up yet here: the presence thread says so at start)
        sender.app.amqp.queues.deselect(QUEUE)


_presence = None  # this worker's heartbeat (main process only)


@worker_ready.connect
def _start_presence(sender=None, **_kwargs) -> None:
    # The main process of a `rayfarm worker` (not the service, which only
    # sends tasks): say who we are, then beat until shutdown.
    global _presence
    import redis

    from .presence import Presence

    app = sender.app
    hostname = sender.hostname
    concurrency = getattr(getattr(sender, "controller", None), "concurrency", None) or 1

    def consume(on: bool) -> None:
        # Through the remote control, as the service's own broadcast: handled in
        # the worker's event loop, the only place its consumer may change.
        control = app.control.add_consumer if on else app.control.cancel_consumer
        control(QUEUE, destination=[hostname])

    def reserved() -> list[str]:
        # Every message this worker holds, prefetched or running (Celery's own
        # bookkeeping, in this process): the service keeps such a unit queued
        # however long it waits (service/executors/celery_farm.py).
        from celery.worker import state

        return [request.id for request in list(state.reserved_requests)]

    def consuming() -> bool | None:
        # Read in this thread while the event loop may change it: a dict lookup.
        # None once a shutdown began (its consumer stops; asking it to consume
        # again could take a unit during a warm shutdown) or before it exists.
        from celery.worker import state

        tasks = getattr(sender, "task_consumer", None)
        if tasks is None or state.should_stop not in (None, False) or \
                state.should_terminate not in (None, False):
            return None
        return bool(tasks.consuming_from(QUEUE))

    _presence = Presence(redis.Redis.from_url(app.conf.broker_url), hostname,
                         int(concurrency), float(app.conf.rayfarm_heartbeat_seconds or 2.0),
                         consume=consume, reserved=reserved, consuming=consuming)
    try:
        _presence.start()
    except Exception:  # presence is for the dashboard; never stop the worker for it
        log.exception("could not register the worker's presence")


@worker_shutdown.connect
def _stop_presence(**_kwargs) -> None:
    if _presence is not None:
        _presence.stop()


@task_failure.connect
def _forget_dead_render_process(sender=None, exception=None, args=None, **_kwargs) -> None:
    # In the main process, when a render process died under a unit: it never
    # said it finished, so drop what it left (its unit's heartbeat and its
    # "running" entry), or the unit would show running until they expire.
    from billiard.exceptions import WorkerLostError

    if _presence is None or not isinstance(exception, WorkerLostError):
        return
    from .presence import forget_dead_processes

    payload = args[0] if args else None
    try:
        forget_dead_processes(_presence.client, _presence.name,
                              payload if isinstance(payload, dict) else None)
    except Exception:  # presence is for the dashboard; never stop the worker for it
        log.exception("could not clear a dead render process's presence")


@task_revoked.connect
def _forget_stopped_unit(request=None, terminated=False, **_kwargs) -> None:
    # In the main process, when the service stopped a rendering unit: its render
    # process was killed and never said it finished, so drop its unit's
    # heartbeat (the unit may run again elsewhere) and its "running" entry.
    if _presence is None or not terminated:
        return
    from .presence import forget_dead_processes

    args = getattr(request, "args", None) or ()
    payload = args[0] if args else None
    try:
        forget_dead_processes(_presence.client, _presence.name,
                              payload if isinstance(payload, dict) else None)
    except Exception:  # presence is for the dashboard; never stop the worker for it
        log.exception("could not clear a stopped render process's presence")
