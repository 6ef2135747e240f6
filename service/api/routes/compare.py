"""/compare: several done jobs' convergence side by side (service.compare),
as JSON for the dashboard's plot and as a matplotlib figure."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from ... import compare
from ..auth import ActorDep
from ..deps import FarmDep, SessionDep
from ..errors import responses

router = APIRouter(prefix="/compare", tags=["jobs"])

Jobs = Annotated[str, Query(max_length=20 * 33, description="job ids, comma separated (at most "
                                                           f"{compare.MAX_JOBS})")]
Reference = Annotated[str | None, Query(max_length=32, description="a done job of the same size: "
                                                                   "each curve's RMSE against it")]


def _ids(jobs: str) -> list[str]:
    return [j for j in (part.strip() for part in jobs.split(",")) if j]


@router.get("", responses=responses(422, 429))
def compare_jobs(session: SessionDep, farm: FarmDep, actor: ActorDep, jobs: Jobs,
                 reference: Reference = None) -> dict:
    """Each job's error against samples and render seconds, pass by pass (its
    error statistic; with `reference`, its RMSE against that job's image)."""
    return compare.compare_jobs(session, farm.store, actor, _ids(jobs), reference)


@router.get(".png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, **responses(422, 429)})
def compare_png(session: SessionDep, farm: FarmDep, actor: ActorDep, jobs: Jobs,
                reference: Reference = None) -> Response:
    """The same drawn with matplotlib (log-log, against samples and seconds)."""
    report = compare.compare_jobs(session, farm.store, actor, _ids(jobs), reference)
    return Response(compare.compare_figure(report), media_type="image/png")
