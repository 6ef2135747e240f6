"""/jobs: submit, list, inspect (units and their logs), reprioritize, pause, resume, retry, requeue,
cancel, delete, download (EXR, preview, noise map, float pixels)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, Response, status
from fastapi.responses import FileResponse

from ... import admission, blocklist, jobs
from ... import pixels as pixel_data
from ...errors import NotFound
from ...models import utcnow
from ...schemas import JobCreate, JobPublic, JobUpdate, UnitLogPublic, UnitPublic, WorkerBlockPublic
from ..auth import ActorDep
from ..deps import FarmDep, SessionDep
from ..errors import responses

router = APIRouter(prefix="/jobs", tags=["jobs"])
_NO_STORE = {"Cache-Control": "no-store"}  # previews change while the job runs
_CHANGE = responses(403, 404, 409)  # a viewer may not; no such job; not in that state
MAX_OFFSET = 2**31 - 1  # the database's integers end somewhere (SQLite: 2**63 - 1)


def _changing_png(path, job_id: str) -> Response:
    """A PNG the service may replace while it is sent: a running job's preview
    and noise map, which the store writes to a temporary name and renames over
    the old one. Read whole from one open file. A FileResponse takes the size
    from one stat and the bytes from a later open, so a rename between the two
    sent a Content-Length the body did not match (the browser's
    ERR_CONTENT_LENGTH_MISMATCH and uvicorn's "Too little data for declared
    Content-Length", seen once in tests/test_dashboard_browser.py test07)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:  # its job was deleted meanwhile
        raise NotFound(f"job '{job_id}' has no {path.name}") from None
    return Response(data, media_type="image/png", headers=_NO_STORE)


@router.post("", status_code=status.HTTP_201_CREATED, response_model=JobPublic,
             responses=responses(403, 413, 422, 429, 507))
def create_job(body: JobCreate, session: SessionDep, farm: FarmDep, actor: ActorDep,
               response: Response) -> JobPublic:
    """Submit a render job; it is queued and rendered in the background. 429
    with Retry-After past the role's submissions per minute (per token) or
    active jobs (per owner); 507 with Retry-After while the disk is full."""
    farm.disk.check_room()
    admission.check_submission_rate(farm.limiter, farm.settings, actor)
    job = jobs.create_job(session, farm.store, farm.settings, actor, body, utcnow())
    session.commit()
    farm.scheduler.wake()
    response.headers["Location"] = f"/jobs/{job.id}"
    return JobPublic.from_job(job, utcnow())


@router.get("", response_model=list[JobPublic], responses=responses(422))
def list_jobs(request: Request, session: SessionDep, actor: ActorDep,
              status: Annotated[str | None, Query(max_length=32)] = None,
              method: Annotated[str | None, Query(max_length=64)] = None,
              scene: Annotated[str | None, Query(max_length=200)] = None,
              sampler: Annotated[str | None, Query(max_length=64)] = None,
              owner: Annotated[str | None, Query(max_length=64)] = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0) -> list[JobPublic]:
    """The caller's jobs (all jobs for admins and viewers), newest first,
    optionally only those with the given `status`, `method` (an alias counts
    as its method), `scene`, `sampler` and `owner`. Any other query parameter
    is a 422: a filter that is silently ignored would list the wrong jobs."""
    jobs.check_query(request.query_params.keys(), JOB_FILTERS)
    now = utcnow()
    return [JobPublic.from_job(j, now) for j in jobs.list_jobs(
        session, actor, status=status, method=method, scene=scene, sampler=sampler, owner=owner,
        limit=limit, offset=offset)]


JOB_FILTERS = ("status", "method", "scene", "sampler", "owner", "limit", "offset")


@router.get("/{job_id}", response_model=JobPublic, responses=responses(404))
def get_job(job_id: str, session: SessionDep, actor: ActorDep) -> JobPublic:
    """A job's status, progress (units done / total), timings and error."""
    return JobPublic.from_job(jobs.get_job(session, actor, job_id), utcnow())


@router.get("/{job_id}/units", response_model=list[UnitPublic], responses=responses(404))
def list_units(job_id: str, session: SessionDep, actor: ActorDep) -> list[UnitPublic]:
    """A job's work units: state, attempts, worker, timings."""
    return [UnitPublic.from_unit(u) for u in jobs.list_units(session, actor, job_id)]


@router.get("/{job_id}/units/{index}/log", response_model=UnitLogPublic,
            responses=responses(404, 422))
def unit_log(job_id: str, index: Annotated[int, Path(ge=0, le=MAX_OFFSET)],
             session: SessionDep, farm: FarmDep, actor: ActorDep) -> UnitLogPublic:
    """What a unit's tasks logged while they rendered: per task, the last log
    lines and, if it failed, the exception's traceback (oldest task first)."""
    unit, logs = jobs.unit_logs(session, farm.store, actor, job_id, index)
    return UnitLogPublic.from_unit(unit, logs)


@router.get("/{job_id}/blocklist", response_model=list[WorkerBlockPublic],
            responses=responses(404))
def list_blocklist(job_id: str, session: SessionDep, actor: ActorDep) -> list[WorkerBlockPublic]:
    """The workers that failed units of the job: blocklisted for it (`blocked`
    set) once `worker_failures_per_job` of its units failed there."""
    job = jobs.get_job(session, actor, job_id)
    return [WorkerBlockPublic.from_row(r) for r in blocklist.list_blocks(session, job.id)]


@router.delete("/{job_id}/blocklist/{worker}", status_code=status.HTTP_204_NO_CONTENT,
               responses=responses(403, 404))
def clear_blocklist(job_id: str, worker: str, farm: FarmDep, actor: ActorDep) -> Response:
    """Take a worker off the job's blocklist, with its failure count (the job's
    owner or an admin); its next units may go to it again."""
    jobs.retrying(farm.sessions, job_id, lambda session: _clear(session, actor, job_id, worker))
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _clear(session, actor, job_id: str, worker: str):
    job = jobs.get_job(session, actor, job_id)
    blocklist.clear(session, actor, job, worker)
    return job


@router.post("/{job_id}/cancel", response_model=JobPublic, responses=_CHANGE)
def cancel_job(job_id: str, farm: FarmDep, actor: ActorDep) -> JobPublic:
    """Cancel a queued, running or paused job: its unfinished units are dropped
    (409 if it already finished)."""
    job = jobs.cancel_job_retrying(farm.sessions, actor, job_id, utcnow)
    farm.scheduler.wake()  # its tasks are canceled and its slots go to others at once
    return JobPublic.from_job(job, utcnow())


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, responses=_CHANGE)
def delete_job(job_id: str, farm: FarmDep, actor: ActorDep) -> Response:
    """Delete a job, its units and its images (an active job is canceled first)."""
    owner = jobs.retrying(farm.sessions, job_id, lambda session: jobs.delete_job(
        session, farm.store, actor, job_id, utcnow()))
    # Again after the commit: a preview the scheduler wrote meanwhile goes too
    # (one written later, the scheduler removes itself: the job is gone).
    farm.store.delete_job(job_id)
    farm.events.publish("deleted", job_id, {"job_id": job_id}, owner=owner)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.patch("/{job_id}", response_model=JobPublic, responses=responses(403, 404, 409, 422))
def update_job(job_id: str, body: JobUpdate, farm: FarmDep, actor: ActorDep) -> JobPublic:
    """Change a job's priority (higher runs first, from the scheduler's next tick)."""
    job = jobs.retrying(farm.sessions, job_id, lambda session: jobs.set_priority(
        session, actor, job_id, body.priority, utcnow()))
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/pause", response_model=JobPublic, responses=_CHANGE)
def pause_job(job_id: str, farm: FarmDep, actor: ActorDep) -> JobPublic:
    """Enqueue no more of the job's units; those in flight finish (409 unless queued or running)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.pause_job(session, actor, job_id, utcnow()))
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/resume", response_model=JobPublic, responses=_CHANGE)
def resume_job(job_id: str, farm: FarmDep, actor: ActorDep) -> JobPublic:
    """Continue a paused job (409 if it is not paused)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.resume_job(session, actor, job_id, utcnow()))
    farm.scheduler.wake()
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/retry", response_model=JobPublic, responses=_CHANGE)
def retry_job(job_id: str, farm: FarmDep, actor: ActorDep) -> JobPublic:
    """Run the failed units again; a failed job runs again, keeping its done units
    (409 if there is nothing to retry)."""
    job = jobs.retrying(farm.sessions, job_id,
                        lambda session: jobs.retry_job(session, actor, job_id, utcnow()))
    farm.scheduler.wake()
    return JobPublic.from_job(job, utcnow())


@router.post("/{job_id}/requeue", response_model=JobPublic, responses=_CHANGE)
def requeue_job(job_id: str, farm: FarmDep, actor: ActorDep) -> JobPublic:
    """Start the job again from nothing: units and results forgotten, queued
    (409 if it is queued already)."""
    job = jobs.retrying(farm.sessions, job_id, lambda session: jobs.requeue_job(
        session, farm.store, actor, job_id, utcnow()))
    farm.scheduler.wake()
    return JobPublic.from_job(job, utcnow())


@router.get("/{job_id}/result.exr", response_class=FileResponse,
            responses={200: {"content": {"image/x-exr": {}}}, **responses(404)})
def result_exr(job_id: str, session: SessionDep, farm: FarmDep, actor: ActorDep) -> FileResponse:
    """The merged image: float R, G, B, var.R/G/B, samples.Y, the AOV layers the
    method writes, and denoised.R/G/B for a job with `denoise` (404 until the
    job is done)."""
    path = jobs.result_file(session, farm.store, actor, job_id, "result.exr")
    return FileResponse(path, media_type="image/x-exr", filename=f"{job_id}.exr")


@router.get("/{job_id}/preview.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, **responses(404)})
def preview_png(job_id: str, session: SessionDep, farm: FarmDep, actor: ActorDep) -> Response:
    """A tonemapped sRGB preview (404 until the first unit has landed). It is
    refreshed as units land while it is being fetched: a job nobody looks at
    keeps its first preview until its final one (service.previews)."""
    return _changing_png(jobs.result_file(session, farm.store, actor, job_id, "preview.png"),
                         job_id)


@router.get("/{job_id}/denoised.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, **responses(404)})
def denoised_png(job_id: str, session: SessionDep, farm: FarmDep,
                 actor: ActorDep) -> FileResponse:
    """The denoised frame, tonemapped like the preview: Intel Open Image Denoise
    run once over the merged image (no tiles, so no seams) of a job submitted
    with `denoise` (404 until it is done). A biased post-process: the EXR keeps
    the raw R/G/B and their variance beside denoised.R/G/B."""
    path = jobs.result_file(session, farm.store, actor, job_id, "denoised.png")
    return FileResponse(path, media_type="image/png", headers=_NO_STORE)


@router.get("/{job_id}/pixels", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}, **responses(404, 422)})
def job_pixels(job_id: str, session: SessionDep, farm: FarmDep, actor: ActorDep,
               layer: Annotated[str, Query(max_length=64)] = "beauty") -> Response:
    """One layer of the image as float data, for an HDR viewer: little-endian
    float32, row-major, channels interleaved (height x width x channels).
    Headers: `X-Image-Width`, `X-Image-Height`, `X-Image-Channels` (this
    layer's EXR channel names, in order), `X-Image-Layers` (every layer:
    beauty, var, samples and the job's AOVs and denoised), `X-Image-Source`
    (final, partial or running). A running job's is the frame merged so far
    (404 until its first unit is done); a canceled or failed one's, that of
    its finished units. 422 for a layer the image does not have."""
    pixels = pixel_data.job_pixels(session, farm.store, actor, job_id, layer)
    return Response(pixels.data, media_type="application/octet-stream", headers={
        **_NO_STORE, "X-Image-Width": str(pixels.width), "X-Image-Height": str(pixels.height),
        "X-Image-Channels": ",".join(pixels.channels), "X-Image-Layers": ",".join(pixels.layers),
        "X-Image-Source": pixels.source})


@router.get("/{job_id}/noise.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, **responses(404)})
def noise_png(job_id: str, session: SessionDep, farm: FarmDep, actor: ActorDep) -> Response:
    """The noise heatmap: each pixel's relative standard error (from the variance
    channels) on a log scale from 0.1 % (dark) to 100 % (bright) through an
    inferno colormap; grey where fewer than two samples landed. Refreshed like
    the preview, while it is being fetched (404 until the first unit is done)."""
    return _changing_png(jobs.result_file(session, farm.store, actor, job_id, "noise.png"),
                         job_id)
