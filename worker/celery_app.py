"""The Celery application of the farm, built from `Settings` (never at import).

    app = create_celery_app(Settings(broker_url="redis://localhost:6379/0"))
    app.send_task(TASK_RENDER_UNIT, args=[payload], queue=QUEUE)

Redis is both broker and result backend. Delivery is at-least-once
(`task_acks_late` + `task_reject_on_worker_lost`): a unit whose worker dies is
delivered again, and since a unit's result is deterministic a second delivery
changes nothing. A message that Redis itself loses is the service's business:
it watches heartbeats and enqueues the unit again (see service/executors).
"""

from __future__ import annotations

import logging

from celery import Celery
from celery.signals import worker_process_init, worker_ready, worker_shutdown

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
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_track_started=True,
        # A result (also a failure) names the worker it came from: the service
        # counts failed units per worker and job (blocklisting, service.workers).
        result_extended=True,
        task_default_queue=QUEUE,
        # Results are collected within seconds; don't keep stale films for a day.
        result_expires=3600,
        # Each child warms the Numba kernels at start (loading the on-disk cache or
        # compiling); Celery's default of 4 s would kill it mid-compilation.
        worker_proc_alive_timeout=600.0,
        worker_hijack_root_logger=False,
        broker_connection_retry_on_startup=True,
    )
    app.conf.rayfarm_heartbeat_seconds = settings.worker_heartbeat_seconds
    # The render processes are forked from here: they inherit the cache directory.
    settings.configure_renderer()
    from .tasks import register_tasks

    register_tasks(app)
    return app


@worker_process_init.connect
def _warm_up_child(**_kwargs) -> None:
    # One unit per process, one process per core: Numba runs single-threaded
    # here, and compiles (or loads its cache) once, before the first task.
    import numba

    from renderer import warm_up

    numba.set_num_threads(1)
    warm_up()
    log.info("render process warmed up")


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

    _presence = Presence(redis.Redis.from_url(app.conf.broker_url), hostname,
                         int(concurrency), float(app.conf.rayfarm_heartbeat_seconds or 2.0),
                         consume=consume)
    try:
        _presence.start()
    except Exception:  # presence is for the dashboard; never stop the worker for it
        log.exception("could not register the worker's presence")


@worker_shutdown.connect
def _stop_presence(**_kwargs) -> None:
    if _presence is not None:
        _presence.stop()
