"""/jobs: submit, list, inspect, reprioritize, pause, resume, retry, requeue,
cancel, delete, download (EXR, preview, noise map)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status
from fastapi.responses import FileResponse

from ... import jobs
from ...models import utcnow
from ...schemas import JobCreate, JobPublic, JobUpdate, UnitPublic
from ..deps import FarmDep, SessionDep

router = APIRouter(prefix="/jobs", tags=["jobs"])
_NO_STORE = {"Cache-Control": "no-store"}  # previews change while the job runs


@router.post("", status_code=status.HTTP_201_CREATED, response_model=JobPublic)
def create_job(body: JobCreate, session: SessionDep, farm: FarmDep,
               response: Response) -> JobPublic:
    """Submit a render job; it is queued and rendered in the background."""
    job = jobs.create_job(session, farm.store, farm.settings, body, utcnow())
    session.commit()
    response.headers["Location"] = f"/jobs/{job.id}"
    return JobPublic.from_job(job, utcnow())


@router.get("", response_model=list[JobPublic])
def list_jobs(session: SessionDep, status: str | None = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              offset: Annotated[int, Query(ge=0)] = 0) -> list[JobPublic]:
    """Jobs, newest first (optionally only those with `status`)."""
    now = utcnow()
    return [JobPublic.from_job(j, now)
            for j in jobs.list_jobs(session, status=status, limit=limit, offset=offset)]


@router.get("/{job_id}", response_model=JobPublic)
def get_job(job_id: str, session: SessionDep) -> JobPublic:
    """A job's status, progress (units done / total), timings and error."""
    return JobPublic.from_job(jobs.get_job(session, job_id), utcnow())


@router.get("/{job_id}/units", response_model=list[UnitPublic])
def list_units(job_id: str, session: SessionDep) -> list[UnitPublic]:
    """A job's work units: state, attempts, worker, timings."""
    return [UnitPublic.from_unit(u) for u in jobs.list_units(session, job_id)]


@router.post("/{job_id}/cancel", response_model=JobPublic)
def cancel_job(job_id: str, farm: FarmDep) -> JobPublic:
    """Cancel a queued, running or paused job: its unfinished units are dropped
    (409 if it already finished)."""
    return JobPublic.from_job(jobs.cancel_job_retrying(farm.sessions, job_id, utcnow), utcnow())


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_job(job_id: str, farm: FarmDep) -> Response:
    """Delete a job, its units and its images (an active job is canceled first)."""
    def delete(session):
        jobs.delete_job(session, farm.store, job_id, utcnow())
        return None
    jobs.retrying(farm.sessions, job_id, delete)
    farm.events.publish("deleted", job_id, {"job_id": job_id})
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.patch("/{job_id}", response_model=JobPublic)
def update_job(job_id: str, body: JobUpdate, farm: FarmDep) -> JobPublic:
    """Change a job's priority (higher runs first, from the scheduler's next tick)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.set_priority(session, job_id, body.priority, utcnow()))
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/pause", response_model=JobPublic)
def pause_job(job_id: str, farm: FarmDep) -> JobPublic:
    """Enqueue no more of the job's units; those in flight finish (409 unless queued or running)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.pause_job(session, job_id, utcnow()))
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/resume", response_model=JobPublic)
def resume_job(job_id: str, farm: FarmDep) -> JobPublic:
    """Continue a paused job (409 if it is not paused)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.resume_job(session, job_id, utcnow()))
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/retry", response_model=JobPublic)
def retry_job(job_id: str, farm: FarmDep) -> JobPublic:
    """Run the failed units again; a failed job runs again, keeping its done units
    (409 if there is nothing to retry)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.retry_job(session, job_id, utcnow()))
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/requeue", response_model=JobPublic)
def requeue_job(job_id: str, farm: FarmDep) -> JobPublic:
    """Start the job again from nothing: units and results forgotten, queued
    (409 if it is queued already)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.requeue_job(session, farm.store, job_id, utcnow()))
    return JobPublic.from_job(job, utcnow())


@router.get("/{job_id}/result.exr", response_class=FileResponse,
            responses={200: {"content": {"image/x-exr": {}}}, 404: {}})
def result_exr(job_id: str, session: SessionDep, farm: FarmDep) -> FileResponse:
    """The merged image: float R, G, B and var.R/G/B (404 until the job is done)."""
    path = jobs.result_file(session, farm.store, job_id, "result.exr")
    return FileResponse(path, media_type="image/x-exr", filename=f"{job_id}.exr")


@router.get("/{job_id}/preview.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, 404: {}})
def preview_png(job_id: str, session: SessionDep, farm: FarmDep) -> FileResponse:
    """A tonemapped sRGB preview, refreshed as units land (404 until the first one has)."""
    path = jobs.result_file(session, farm.store, job_id, "preview.png")
    return FileResponse(path, media_type="image/png", headers=_NO_STORE)


@router.get("/{job_id}/noise.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, 404: {}})
def noise_png(job_id: str, session: SessionDep, farm: FarmDep) -> FileResponse:
    """The noise heatmap: each pixel's relative standard error (from the variance
    channels) on a log scale from 0.1 % (dark) to 100 % (bright) through an
    inferno colormap; grey where fewer than two samples landed. Refreshed with
    the preview (404 until the first unit is done)."""
    path = jobs.result_file(session, farm.store, job_id, "noise.png")
    return FileResponse(path, media_type="image/png", headers=_NO_STORE)
