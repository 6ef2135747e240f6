"""The farm's Prometheus metrics: one registry per app, served at GET /metrics.

    metrics = PrometheusMetrics()          # create_app makes one per app
    farm = Farm.open(settings, metrics)    # the scheduler reports through it
    metrics.watch(farm)                    # the scrape-time gauges read this farm
    metrics.exposition()                   # bytes in the Prometheus text format

The scheduler knows only `FarmMetrics`, three methods that do nothing unless
a `PrometheusMetrics` stands behind them, so it carries no metrics plumbing.
A registry of its own per app, never prometheus_client's global one: tests
build many apps in one process, and each counts only its own farm.

Every label is a small fixed set (states, methods, routes, reasons): no job
id, user or raw path ever becomes a label (see docs/operations.md, "Metrics").
"""

from __future__ import annotations

import logging
import shutil
import time
from collections import Counter
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter as PromCounter, Histogram
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector
from sqlalchemy import func, select

from . import states
from .executors.base import WORKER_STATES
from .models import Job, WorkUnit

if TYPE_CHECKING:
    from .farm import Farm

__all__ = ["FarmMetrics", "PrometheusMetrics", "HTTPMetrics", "CONTENT_TYPE_LATEST",
           "REQUEUE_REASONS", "UNMATCHED"]

log = logging.getLogger(__name__)

# Why a unit was enqueued again: lost (its worker lost by presence), lease (no
# unit heartbeat for a lease), message (gone from the broker), declined (by a
# blocklisted or disabled worker), crash (its render process died: an attempt
# spent), failed (an attempt raised and is retried), preempted or withdrawn (put
# back to pending for another owner's fair share of the render processes).
REQUEUE_REASONS = ("lost", "lease", "message", "declined", "crash", "failed", "preempted",
                   "withdrawn")
UNMATCHED = "unmatched"  # the route label of a request no route answered (404 of an unknown path)
_HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
# Render seconds of one unit: from a small tile to a long MLT chain.
_UNIT_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600)
_TICK_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10)


class FarmMetrics:
    """What the scheduler reports; this base class drops it all (the default)."""

    def unit_done(self, method: str, seconds: float, samples: int, rays: int) -> None:
        """A unit's film was stored and the unit marked done (committed)."""

    def requeued(self, reason: str) -> None:
        """A unit was enqueued again, for one of `REQUEUE_REASONS`."""

    def tick(self, seconds: float) -> None:
        """One scheduler tick took this long."""


class PrometheusMetrics(FarmMetrics):
    """The metrics of one app, in a registry of its own."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.farm: Farm | None = None
        r = self.registry
        self.unit_seconds = Histogram(
            "rayfarm_unit_render_seconds", "Render time of the units collected done, by method",
            ["method"], buckets=_UNIT_BUCKETS, registry=r)
        self.samples = PromCounter("rayfarm_samples", "Camera samples of the units collected "
                                   "done (rate() is samples per second)", registry=r)
        self.rays = PromCounter("rayfarm_rays", "Rays traced by the units collected done "
                                "(rate() is rays per second)", registry=r)
        self.requeues = PromCounter(
            "rayfarm_units_requeued", "Units enqueued again: lost (worker lost), lease (no "
            "heartbeat for a lease), message (gone from the broker), declined (by a "
            "blocklisted or disabled worker), crash (the render process died), failed "
            "(an attempt retried)", ["reason"], registry=r)
        self.tick_seconds = Histogram("rayfarm_scheduler_tick_seconds",
                                      "Duration of one scheduler tick",
                                      buckets=_TICK_BUCKETS, registry=r)
        self.http_seconds = Histogram(
            "rayfarm_http_request_seconds", "HTTP requests by method and route template "
            f"({UNMATCHED!r}: no route); an event stream counts when it ends",
            ["method", "route"], registry=r)
        for reason in REQUEUE_REASONS:  # shown at 0 before the first one
            self.requeues.labels(reason)
        r.register(_FarmCollector(self))

    def watch(self, farm: "Farm | None") -> None:
        """Read the scrape-time gauges from this farm (None: leave them out)."""
        self.farm = farm

    # -- FarmMetrics ----------------------------------------------------------------
    def unit_done(self, method: str, seconds: float, samples: int, rays: int) -> None:
        self.unit_seconds.labels(method).observe(max(float(seconds), 0.0))
        self.samples.inc(max(int(samples), 0))
        self.rays.inc(max(int(rays), 0))

    def requeued(self, reason: str) -> None:
        self.requeues.labels(reason if reason in REQUEUE_REASONS else "other").inc()

    def tick(self, seconds: float) -> None:
        self.tick_seconds.observe(seconds)

    # -- HTTP -------------------------------------------------------------------------
    def request(self, method: str, route: str, seconds: float) -> None:
        method = method if method in _HTTP_METHODS else "other"  # the client picks it
        self.http_seconds.labels(method, route).observe(seconds)

    def exposition(self) -> bytes:
        """Every metric in the Prometheus text format (reads the ledger: call off the loop)."""
        return generate_latest(self.registry)


class _FarmCollector(Collector):
    """The gauges read at scrape time: the ledger's jobs and units by state, the
    queue depth, the executor's workers by state and the data dir's free bytes."""

    def __init__(self, metrics: PrometheusMetrics):
        self.metrics = metrics

    def describe(self):  # the names, without reading the ledger at registration
        return [GaugeMetricFamily(name, doc) for name, doc in _GAUGES.items()]

    def collect(self):
        farm = self.metrics.farm
        if farm is None:
            return
        with farm.sessions() as session:
            jobs = dict(session.execute(select(Job.status, func.count()).group_by(Job.status)).all())
            units = dict(session.execute(
                select(WorkUnit.state, func.count()).group_by(WorkUnit.state)).all())
            depth = session.scalar(
                select(func.count()).select_from(WorkUnit).join(Job, Job.id == WorkUnit.job_id)
                .where(WorkUnit.state == "pending", Job.status == "running"))
        yield _by_state("rayfarm_jobs", jobs, states.JOB_STATUSES)
        yield _by_state("rayfarm_units", units, states.UNIT_STATES)
        queue = GaugeMetricFamily("rayfarm_queue_depth", _GAUGES["rayfarm_queue_depth"])
        queue.add_metric([], depth or 0)
        yield queue
        try:
            workers = Counter(w.state for w in farm.executor.workers())
        except Exception as exc:  # e.g. the broker is unreachable: /healthz says so
            log.warning("metrics: no workers (%s: %s)", type(exc).__name__, exc)
        else:
            yield _by_state("rayfarm_workers", workers, WORKER_STATES)
        try:
            free = shutil.disk_usage(farm.settings.data_dir).free
        except OSError as exc:
            log.warning("metrics: no disk usage of the data dir (%s)", exc)
        else:
            disk = GaugeMetricFamily("rayfarm_disk_free_bytes", _GAUGES["rayfarm_disk_free_bytes"])
            disk.add_metric([], free)
            yield disk


_GAUGES = {
    "rayfarm_jobs": "Jobs in the ledger, by state",
    "rayfarm_units": "Work units in the ledger, by state",
    "rayfarm_queue_depth": "Pending units of running jobs (waiting for a slot)",
    "rayfarm_workers": "Render workers as the executor last saw them, by state",
    "rayfarm_disk_free_bytes": "Free bytes on the data directory's filesystem",
}


def _by_state(name: str, counts: dict, known: tuple[str, ...]) -> GaugeMetricFamily:
    """One sample per known state (0 when none), so a state never vanishes from a graph."""
    family = GaugeMetricFamily(name, _GAUGES[name], labels=["state"])
    for state in known:
        family.add_metric([state], counts.get(state, 0))
    return family


class HTTPMetrics:
    """Times every HTTP request into `rayfarm_http_request_seconds`, as a pure
    ASGI middleware: it wraps neither `receive` nor `send`, so nothing is
    buffered and event streams stream. The route label is the matched route's
    path template (`/jobs/{job_id}`, a mount's `/static/{path}`), read from the
    scope once the app has routed it, never the raw path."""

    def __init__(self, app, metrics: PrometheusMetrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        root_path = scope.get("root_path", "")
        start = time.perf_counter()
        try:
            await self.app(scope, receive, send)
        finally:
            self.metrics.request(scope["method"], _route_template(scope, root_path),
                                 time.perf_counter() - start)


def _route_template(scope, root_path: str) -> str:
    route = scope.get("route")  # FastAPI puts the matched APIRoute here
    template = getattr(route, "path_format", None)
    if isinstance(template, str):
        return template
    if "app_root_path" in scope:  # routed into a mount: its prefix is a fixed string
        prefix = scope.get("root_path", "")
        if prefix.startswith(root_path) and len(prefix) > len(root_path):
            return prefix[len(root_path):] + "/{path}"
    return UNMATCHED
