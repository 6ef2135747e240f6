"""Convergence of several jobs side by side (`GET /compare`): each job's
curve of error against samples and against render seconds, pass by pass,
and, when one job is named the reference, each one's true RMSE against it.

A progressive tile job's passes are rebuilt from its stored unit films: the
done units of passes 0..p merged (plain addition, as everywhere) give the
image after pass p, whose error statistic (`film.image_error`, what the
job's own convergence log holds) and, against the reference, RMSE are
measured. A job of one pass, or a DAG job (photon, BDPT, MLT: their units
are not passes of one image), is one point: its final image. The
reference's own variance is taken off each MSE (its noise adds to the
measured error), as the estimator lab does.

    report = compare_jobs(session, store, actor, ["a1...", "b2..."], reference="c3...")

`GET /compare.png` draws the same with matplotlib, for reports.

A comparison holds whole-frame float64 films (the job's passes as they add
up, their mean and variance, the reference's channels: 440 bytes a pixel
traced at 512x512), so it takes frames of at most `MAX_PIXELS` and runs one
at a time in a service: another caller meanwhile is told to retry (429),
instead of N requests holding N such frames.
"""

from __future__ import annotations

import io
import math
import threading

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from renderer import Film, PartialFilm
from renderer.film import image_error, read_exr, rgb_of
from renderer.lab import corrected_mse

from .access import Principal
from .errors import InvalidRequest, NotFound, RateLimited
from .jobs import get_job
from .models import Job, WorkUnit
from .store import Store

__all__ = ["MAX_JOBS", "MAX_PIXELS", "compare_jobs", "compare_figure"]

MAX_JOBS = 8
MAX_PIXELS = 2048 * 2048  # about 1.9 GB while a comparison runs (module doc)
_RUNNING = threading.Lock()  # one comparison at a time (module doc)
RETRY_AFTER = 5.0


def _film(width: int, height: int) -> Film:
    return Film(0, 0, np.zeros((height, width, 3)), np.zeros((height, width, 3)),
                np.zeros((height, width)))


def _point(spp: int, samples: int, seconds: float, mean: np.ndarray, var: np.ndarray,
           reference) -> dict:
    point = {"spp": spp, "samples": samples, "seconds": seconds,
             "rel_error": _finite(image_error(mean, var))}
    if reference is not None:
        point["rmse"] = math.sqrt(max(corrected_mse(mean, *reference)[0], 0.0))
    return point


def _curve(session: Session, store: Store, job: Job, reference) -> list[dict]:
    """A point per pass of the job (module doc): spp, samples, seconds,
    rel_error and, with a reference, rmse."""
    units = session.scalars(select(WorkUnit).where(
        WorkUnit.job_id == job.id, WorkUnit.state == "done").order_by(WorkUnit.index)).all()
    if units and all(u.unit.get("kind", "tile") == "tile" for u in units):
        by_pass: dict[int, list[WorkUnit]] = {}
        for unit in units:
            by_pass.setdefault(int(unit.unit.get("pass_index", 0)), []).append(unit)
        film = _film(job.width, job.height)
        points = []
        for index in sorted(by_pass):
            for unit in by_pass[index]:
                film.add(PartialFilm.from_bytes(store.unit_film(job.id, unit.index)))
            points.append(_point(max(int(u.unit["sample_end"]) for u in by_pass[index]),
                                 int(film.stats.get("samples", 0)),
                                 float(film.stats.get("seconds", 0.0)), film.mean(),
                                 film.variance_of_mean(), reference))
        return points
    channels = read_exr(store.result_path(job.id))[0]
    return [_point(int(job.spec["spp"]), int(channels["samples.Y"].sum()),
                   float(job.unit_seconds or 0.0), rgb_of(channels), rgb_of(channels, "var"),
                   reference)]


def _finite(value: float) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def compare_jobs(session: Session, store: Store, actor: Principal, ids: list[str],
                 reference: str | None = None) -> dict:
    """The jobs' curves (module doc); `InvalidRequest` naming `jobs` or
    `reference` for a job that is not there, not done, or not the reference's size."""
    ids = list(dict.fromkeys(ids))
    if not ids:
        raise InvalidRequest("jobs", "name at least one job", source="query")
    if len(ids) > MAX_JOBS:
        raise InvalidRequest("jobs", f"at most {MAX_JOBS} jobs at once, not {len(ids)}",
                             source="query")
    jobs = []
    for job_id in ids:
        try:
            job = get_job(session, actor, job_id)
        except NotFound:
            raise InvalidRequest("jobs", f"no job '{job_id}'", source="query") from None
        if job.status != "done":
            raise InvalidRequest("jobs", f"job '{job_id}' is {job.status}; compare done jobs",
                                 source="query")
        jobs.append(job)
    for job in jobs:
        if job.width * job.height > MAX_PIXELS:
            raise InvalidRequest("jobs", f"job '{job.id}' has {job.width}x{job.height} pixels; "
                                         f"a comparison takes frames of at most {MAX_PIXELS} "
                                         "pixels (2048x2048)", source="query")
    if not _RUNNING.acquire(blocking=False):
        raise RateLimited("another comparison is running in this service; retry in a few "
                          "seconds", retry_after=RETRY_AFTER)
    try:
        return _compare(session, store, actor, jobs, reference)
    finally:
        _RUNNING.release()


def _compare(session: Session, store: Store, actor: Principal, jobs: list[Job],
             reference: str | None) -> dict:
    ref = None
    if reference:
        try:
            ref_job = get_job(session, actor, reference)
        except NotFound:
            raise InvalidRequest("reference", f"no job '{reference}'", source="query") from None
        if ref_job.status != "done":
            raise InvalidRequest("reference", f"job '{reference}' is {ref_job.status}; a "
                                              "reference must be done", source="query")
        for job in jobs:
            if (job.width, job.height) != (ref_job.width, ref_job.height):
                raise InvalidRequest("reference", f"job '{job.id}' is {job.width}x{job.height}, "
                                                  f"the reference {ref_job.width}x"
                                                  f"{ref_job.height}", source="query")
        channels = read_exr(store.result_path(ref_job.id))[0]
        ref = (rgb_of(channels), rgb_of(channels, "var"))
    return {"reference": reference or None,
            "jobs": [{"id": job.id, "label": f"{job.spec['method']} · {job.spec['sampler']}",
                      "method": job.spec["method"], "sampler": job.spec["sampler"],
                      "spp": job.spec["spp"], "scene": job.scene,
                      "points": _curve(session, store, job, ref)} for job in jobs]}


def compare_figure(report: dict) -> bytes:
    """`report` drawn with matplotlib (error statistic, or true RMSE when there
    is a reference, against samples and against seconds, log-log) as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    key = "rmse" if report["reference"] else "rel_error"
    ylabel = "RMSE against the reference" if report["reference"] else \
        "error statistic (95th pct. relative std. error)"
    fig = Figure(figsize=(10, 4))
    by_samples, by_seconds = fig.subplots(1, 2)
    for job in report["jobs"]:
        pts = [p for p in job["points"] if p.get(key)]
        label = f"{job['id'][:8]} {job['label']}"
        by_samples.loglog([p["samples"] for p in pts], [p[key] for p in pts], "o-", label=label)
        by_seconds.loglog([max(p["seconds"], 1e-6) for p in pts], [p[key] for p in pts], "o-",
                          label=label)
    by_samples.set(xlabel="samples", ylabel=ylabel, title="Error against samples")
    by_seconds.set(xlabel="render seconds", ylabel=ylabel, title="Error against time")
    for ax in (by_samples, by_seconds):
        ax.grid(True, which="both", alpha=0.3)
    by_samples.legend(fontsize=8)
    out = io.BytesIO()
    fig.savefig(out, format="png", dpi=110, bbox_inches="tight")
    return out.getvalue()
