"""The estimator lab: an experiment renders configurations (method, sampler,
options) x spp levels x R repeats as ordinary jobs of its owner, with seeds
derived from its own, plus a reference (a done job of the same scene, size
and depth, or one it renders), and, once they are all done, measures each
configuration against the reference with renderer.lab: bias (and its test),
variance, MSE, time, efficiency, the slope of error against spp, and the
verdicts "unbiased?" and "consistent?" — the lecture's chart, measured.

    experiment = create_experiment(session, store, settings, actor, body, now)
    experiment = get_experiment(sessions, store, actor, experiment_id)   # measures when due

The jobs are the farm's like any other (fair share, limits, the dashboard),
so an experiment needs room for them among its owner's active jobs (a 422
on `repeats` says how much). The measurement runs once, in the request
that first finds every job done; its figures (matplotlib: RMSE and bias
against spp, bias and variance maps at the largest spp) are written to the
store beside it. A job that fails, is canceled or deleted fails the
experiment, naming it; canceling the experiment cancels its jobs.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import uuid
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError

from renderer import METHODS, SceneError, SpecError, lab
from renderer.film import read_exr, rgb_of

from . import admission, states
from .access import Principal, require_change, require_submit, visible_jobs
from .errors import Conflict, InvalidRequest, NotFound, ResultNotReady
from .jobs import cancel_job, create_job, get_job
from .models import Experiment, Job, utcnow
from .schemas import ExperimentCreate, ExperimentPublic, JobCreate
from .settings import Settings
from .store import Store

__all__ = ["create_experiment", "planned_jobs", "get_experiment", "list_experiments",
           "cancel_experiment", "experiment_public", "job_states", "report_csv", "figure_path"]

TILE_SIZE = 64
FIGURES = ("plot", "maps")


def _seed(base: int, *parts: int) -> int:
    """A job's seed, derived from the experiment's and its place in it: distinct
    for every job, and the same for the same experiment submitted again."""
    digest = hashlib.sha256(":".join(map(str, (base, *parts))).encode()).digest()
    return int.from_bytes(digest[:7], "big")


def _label(config) -> str:
    if config.label:
        return config.label
    parts = [METHODS[config.method].name]  # validated before
    if config.sampler != "random":
        parts.append(config.sampler)
    parts += [f"{k}={v}" for k, v in sorted(config.options.items())]
    return " ".join(parts)


def _job(session, store, settings, actor, body: ExperimentCreate, now, field: str, **spec) -> Job:
    try:
        request = JobCreate(scene=body.scene, depth=body.depth, width=body.width,
                            height=body.height, tile_size=TILE_SIZE, priority=body.priority,
                            progressive=False, **spec)
        job = create_job(session, store, settings, actor, request, now)
    except (InvalidRequest, SpecError) as exc:
        raise InvalidRequest(f"{field}.{exc.field}", exc.message) from None
    except SceneError as exc:
        raise InvalidRequest("scene", str(exc)) from None
    session.flush()
    return job


def planned_jobs(body: ExperimentCreate) -> int:
    """The jobs the experiment creates: one per configuration, spp level and
    repeat, and its reference unless it names a done job. Each counts as a
    submission (`admission.check_submission_rate`)."""
    return len(body.configs) * len(body.spp) * body.repeats + (body.reference.job is None)


def create_experiment(session: Session, store: Store, settings: Settings, actor: Principal,
                      body: ExperimentCreate, now: datetime) -> Experiment:
    """Validate the experiment, add its jobs (and its reference's) and itself."""
    require_submit(actor)
    if list(body.spp) != sorted(set(body.spp)):
        raise InvalidRequest("spp", f"spp levels must ascend without repeats, not {body.spp}")
    for i, config in enumerate(body.configs):
        if config.method not in METHODS:
            raise InvalidRequest(f"configs[{i}].method", f"unknown method {config.method!r}; "
                                 "GET /methods lists them")
    labels = [_label(c) for c in body.configs]
    if len(set(labels)) != len(labels):
        raise InvalidRequest("configs", "two configurations have the same label: "
                             + ", ".join(sorted({x for x in labels if labels.count(x) > 1})))
    own_reference = body.reference.job is None
    total = planned_jobs(body)
    limits = admission.limits_for(settings, actor)
    active = admission.count_active_jobs(session, actor.user)
    if active + total > limits.max_active_jobs:
        raise InvalidRequest("repeats", f"the experiment plans {total} jobs; with {active} active, "
                             f"the {actor.role} limit of {limits.max_active_jobs} active jobs "
                             f"leaves room for {max(limits.max_active_jobs - active, 0)}: use "
                             "fewer configurations, spp levels or repeats")
    runs = []
    first = None
    for c, config in enumerate(body.configs):
        for s, spp in enumerate(body.spp):
            for r in range(body.repeats):
                job = _job(session, store, settings, actor, body, now, f"configs[{c}]",
                           method=config.method, spp=spp, sampler=config.sampler,
                           options=dict(config.options), seed=_seed(body.seed, c, s, r))
                first = first or job
                runs.append({"config": c, "spp": spp, "repeat": r, "job": job.id})
    if own_reference:
        spp = body.reference.spp or max(1024, 16 * body.repeats * body.spp[-1])
        reference = _job(session, store, settings, actor, body, now, "reference",
                         method=body.reference.method, spp=spp, sampler="random",
                         seed=_seed(body.seed, -1))
    else:
        try:
            reference = get_job(session, actor, body.reference.job)
        except NotFound:
            raise InvalidRequest("reference.job", f"no job '{body.reference.job}'") from None
        if reference.status != "done":
            raise InvalidRequest("reference.job", f"job '{reference.id}' is {reference.status}; "
                                 "a reference must be done")
        if (reference.scene_hash, reference.width, reference.height,
                reference.spec["depth"]) != (first.scene_hash, first.width, first.height,
                                             body.depth):
            raise InvalidRequest("reference.job", f"job '{reference.id}' renders "
                                 f"{reference.scene} at {reference.width}x{reference.height}, "
                                 f"depth {reference.spec['depth']}; the experiment "
                                 f"{first.scene} at {first.width}x{first.height}, depth "
                                 f"{body.depth}")
    if min(first.width, first.height) < body.block:
        raise InvalidRequest("block", f"{body.block}-pixel blocks do not fit a "
                                      f"{first.width}x{first.height} image")
    request = body.model_dump(mode="json")
    request["labels"] = labels
    request["width"], request["height"] = first.width, first.height
    experiment = Experiment(id=uuid.uuid4().hex[:12], owner=actor.user, created=now,
                            status="running", request=request, runs=runs,
                            reference_job=reference.id)
    session.add(experiment)
    return experiment


def _experiment(session: Session, actor: Principal, experiment_id: str) -> Experiment:
    found = session.scalars(select(Experiment).where(
        Experiment.id == experiment_id, visible_jobs(actor, Experiment.owner))).first()
    if found is None:
        raise NotFound(f"no experiment '{experiment_id}'")
    return found


def job_states(session: Session, experiment: Experiment) -> dict[str, Job]:
    ids = [run["job"] for run in experiment.runs] + [experiment.reference_job]
    return {job.id: job for job in session.scalars(select(Job).where(Job.id.in_(ids)))}


def _check_jobs(experiment: Experiment, jobs: dict[str, Job]) -> str | None:
    """Why the experiment cannot finish (a job gone, failed or canceled), or None."""
    labels = experiment.request["labels"]
    named = [(run["job"], f"{labels[run['config']]} at {run['spp']} spp, repeat {run['repeat']}")
             for run in experiment.runs] + [(experiment.reference_job, "the reference")]
    for job_id, what in named:
        job = jobs.get(job_id)
        if job is None:
            return f"job {job_id} ({what}) was deleted"
        if job.status in ("failed", "canceled"):
            return f"job {job_id} ({what}) is {job.status}" + (f": {job.error}" if job.error else "")
    return None


def _measure(store: Store, experiment: Experiment, jobs: dict[str, Job]) -> list[dict]:
    """The report (renderer.lab) and the figures, from the jobs' EXRs."""
    request = experiment.request
    ref_channels = read_exr(store.result_path(experiment.reference_job))[0]
    reference, reference_var = rgb_of(ref_channels), rgb_of(ref_channels, "var")
    report, maps = [], []
    for c, config in enumerate(request["configs"]):
        levels = []
        for spp in request["spp"]:
            renders = []
            for run in experiment.runs:
                if run["config"] == c and run["spp"] == spp:
                    renders.append(lab.Render(rgb_of(read_exr(store.result_path(run["job"]))[0]),
                                              jobs[run["job"]].unit_seconds))
            levels.append(lab.level_report(renders, reference, reference_var, request["block"]))
        summary = lab.config_report(request["spp"], levels)
        maps.append((levels[-1]["bias_map"], levels[-1]["variance_map"]))
        report.append({"label": request["labels"][c], "method": METHODS[config["method"]].name,
                       "sampler": config["sampler"], "options": config["options"],
                       "levels": [{"spp": spp, **{k: v for k, v in level.items()
                                                  if not k.endswith("_map")}}
                                  for spp, level in zip(request["spp"], levels)],
                       **summary})
    from .lab_figures import write_figures

    write_figures(store.experiment_dir(experiment.id), report, maps, reference)
    return report


def get_experiment(sessions: sessionmaker[Session], store: Store, actor: Principal,
                   experiment_id: str) -> tuple[Experiment, dict[str, Job]]:
    """The experiment and its jobs; a running one whose jobs are all done is
    measured first (once: a concurrent request's measurement wins)."""
    with sessions.begin() as session:
        experiment = _experiment(session, actor, experiment_id)
        jobs = job_states(session, experiment)
        if experiment.status != "running":
            return experiment, jobs
        problem = _check_jobs(experiment, jobs)
        if problem is None and not all(job.status == "done" for job in jobs.values()):
            return experiment, jobs
    report = None
    if problem is None:
        try:
            report = _measure(store, experiment, jobs)
        except (OSError, KeyError, ValueError) as exc:  # an EXR gone or unreadable
            problem = f"measuring failed: {exc}"
    try:
        with sessions.begin() as session:
            experiment = _experiment(session, actor, experiment_id)
            if experiment.status == "running":
                experiment.status = "failed" if problem else "done"
                experiment.error, experiment.report = problem, report
                experiment.finished = utcnow()
            jobs = job_states(session, experiment)
    except StaleDataError:
        with sessions() as session:
            experiment = _experiment(session, actor, experiment_id)
            jobs = job_states(session, experiment)
    return experiment, jobs


def list_experiments(session: Session, actor: Principal, limit: int = 100
                     ) -> list[tuple[Experiment, dict[str, Job]]]:
    found = session.scalars(select(Experiment).where(visible_jobs(actor, Experiment.owner))
                            .order_by(Experiment.created.desc()).limit(limit)).all()
    return [(e, job_states(session, e)) for e in found]


def cancel_experiment(session: Session, actor: Principal, experiment_id: str,
                      now: datetime) -> Experiment:
    """Cancel a running experiment and its jobs still active (not its reference
    if that is another job it only borrowed)."""
    experiment = _experiment(session, actor, experiment_id)
    require_change(actor, experiment.owner, f"experiment '{experiment_id}'")
    if experiment.status != "running":
        raise Conflict(f"experiment '{experiment_id}' is {experiment.status}; nothing to cancel")
    own = [run["job"] for run in experiment.runs]
    if experiment.request["reference"]["job"] is None:  # rendered for it, not borrowed
        own.append(experiment.reference_job)
    for job in session.scalars(select(Job).where(Job.id.in_(own))):
        if job.status not in states.FINAL_JOB:
            cancel_job(session, actor, job.id, now)
    experiment.status, experiment.finished = "canceled", now
    return experiment


def experiment_public(experiment: Experiment, jobs: dict[str, Job]) -> ExperimentPublic:
    done = experiment.status == "done"
    base = f"/experiments/{experiment.id}"
    runs = [dict(run, status=jobs[run["job"]].status if run["job"] in jobs else "deleted")
            for run in experiment.runs]
    return ExperimentPublic(
        id=experiment.id, owner=experiment.owner, status=experiment.status,
        created=experiment.created, finished=experiment.finished, request=experiment.request,
        jobs_total=len(runs) + 1,
        jobs_done=sum(r["status"] == "done" for r in runs)
        + (jobs.get(experiment.reference_job) is not None
           and jobs[experiment.reference_job].status == "done"),
        reference_job=experiment.reference_job, runs=runs, report=experiment.report,
        error=experiment.error, plot_url=f"{base}/plot.png" if done else None,
        maps_url=f"{base}/maps.png" if done else None,
        csv_url=f"{base}/report.csv" if done else None)


def report_csv(experiment: Experiment) -> str:
    """The report as CSV: a row per configuration and spp level."""
    if experiment.status != "done":
        raise ResultNotReady(f"experiment '{experiment.id}' is {experiment.status}; its report "
                             "exists once it is done")
    out = io.StringIO()
    fields = ["label", "method", "sampler", "options", "spp", "bias_p", "biased_blocks", "blocks",
              "unbiased", "relative_bias", "bias2", "variance", "mse", "rmse", "mse_reliable", "seconds", "efficiency",
              "slope", "last_slope", "config_unbiased", "consistent"]
    writer = csv.DictWriter(out, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for config in experiment.report:
        for level in config["levels"]:
            writer.writerow({"label": config["label"], "method": config["method"],
                             "sampler": config["sampler"],
                             "options": json.dumps(config["options"], sort_keys=True),
                             **{k: level[k] for k in fields[4:17]},
                             "slope": config["slope"], "last_slope": config["last_slope"],
                             "config_unbiased": config["unbiased"],
                             "consistent": config["consistent"]})
    return out.getvalue()


def figure_path(store: Store, experiment: Experiment, name: str):
    if name not in FIGURES:
        raise NotFound(f"no figure '{name}'")
    if experiment.status != "done":
        raise ResultNotReady(f"experiment '{experiment.id}' is {experiment.status}; its figures "
                             "exist once it is done")
    path = store.experiment_dir(experiment.id) / f"{name}.png"
    if not path.is_file():
        raise NotFound(f"experiment '{experiment.id}' has no {name}.png")
    return path
