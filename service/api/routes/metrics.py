"""/metrics: the farm's Prometheus metrics (service.metrics). Public, like
/healthz: it shows counts by state, method and route, never a job id or a user."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from ...metrics import CONTENT_TYPE_LATEST

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=Response)
def metrics(request: Request) -> Response:
    """The Prometheus text format (a sync handler: the scrape reads the ledger)."""
    return Response(request.app.state.metrics.exposition(), media_type=CONTENT_TYPE_LATEST)
