"""/experiments: the estimator lab (service.experiments) — submit an
experiment (its jobs run on the farm like any other), follow it, read its
report as JSON or CSV and its figures."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status
from fastapi.responses import FileResponse

from ... import admission, experiments, jobs
from ...models import utcnow
from ...schemas import ExperimentCreate, ExperimentPublic
from ..auth import ActorDep
from ..deps import FarmDep, SessionDep
from ..errors import responses

router = APIRouter(prefix="/experiments", tags=["experiments"])


@router.post("", status_code=status.HTTP_201_CREATED, response_model=ExperimentPublic,
             responses=responses(403, 422, 429, 507))
def create_experiment(body: ExperimentCreate, session: SessionDep, farm: FarmDep,
                      actor: ActorDep, response: Response) -> ExperimentPublic:
    """Submit an experiment: every configuration at every spp level, `repeats`
    times with derived seeds, and a reference unless one is given, as jobs of
    the caller. When they are done, GET reports per configuration: bias and
    its test, variance, MSE, time, efficiency, the RMSE slope, "unbiased?" and
    "consistent?" (renderer.lab). Each of its jobs counts as a submission: 429
    with Retry-After past the role's submissions per minute (per token), as
    POST /jobs; 507 with Retry-After while the disk is full."""
    farm.disk.check_room()
    admission.check_submission_rate(farm.limiter, farm.settings, actor,
                                    jobs=experiments.planned_jobs(body), field="repeats")
    experiment = experiments.create_experiment(session, farm.store, farm.settings, actor, body,
                                               utcnow())
    session.commit()
    farm.scheduler.wake()
    response.headers["Location"] = f"/experiments/{experiment.id}"
    return experiments.experiment_public(experiment, experiments.job_states(session, experiment))


@router.get("", response_model=list[ExperimentPublic])
def list_experiments(session: SessionDep, actor: ActorDep,
                     limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> list[ExperimentPublic]:
    """The caller's experiments (all for admins and viewers), newest first."""
    return [experiments.experiment_public(e, jobs)
            for e, jobs in experiments.list_experiments(session, actor, limit)]


@router.get("/{experiment_id}", response_model=ExperimentPublic, responses=responses(404))
def get_experiment(experiment_id: str, farm: FarmDep, actor: ActorDep) -> ExperimentPublic:
    """An experiment: its jobs' progress, and once they are all done its report."""
    return experiments.experiment_public(*experiments.get_experiment(
        farm.sessions, farm.store, actor, experiment_id))


@router.post("/{experiment_id}/cancel", response_model=ExperimentPublic,
             responses=responses(403, 404, 409))
def cancel_experiment(experiment_id: str, farm: FarmDep, actor: ActorDep) -> ExperimentPublic:
    """Cancel a running experiment and its jobs still active. The scheduler
    changes those jobs meanwhile (it plans them, units land), so the cancel
    is a transaction of its own, tried again on a stale read."""
    def cancel(session):
        experiment = experiments.cancel_experiment(session, actor, experiment_id, utcnow())
        session.flush()
        return experiments.experiment_public(experiment,
                                             experiments.job_states(session, experiment))

    public = jobs.retrying(farm.sessions, experiment_id, cancel, what="experiment")
    farm.scheduler.wake()
    return public


@router.get("/{experiment_id}/report.csv", response_class=Response,
            responses={200: {"content": {"text/csv": {}}}, **responses(404)})
def report_csv(experiment_id: str, farm: FarmDep, actor: ActorDep) -> Response:
    """The report, a row per configuration and spp level (404 until done)."""
    experiment, _ = experiments.get_experiment(farm.sessions, farm.store, actor, experiment_id)
    return Response(experiments.report_csv(experiment), media_type="text/csv", headers={
        "Content-Disposition": f'attachment; filename="experiment-{experiment.id}.csv"'})


@router.get("/{experiment_id}/{figure}.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, **responses(404)})
def figure(experiment_id: str, figure: str, farm: FarmDep, actor: ActorDep) -> FileResponse:
    """`plot.png` (RMSE and the bias score against spp) or `maps.png` (bias and
    variance maps at the largest spp), drawn with matplotlib (404 until done)."""
    experiment, _ = experiments.get_experiment(farm.sessions, farm.store, actor, experiment_id)
    return FileResponse(experiments.figure_path(farm.store, experiment, figure),
                        media_type="image/png")
