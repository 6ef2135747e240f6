"""Assembles the FastAPI app; nothing else lives here.

    app = create_app(Settings(data_dir="/tmp/farm"))
    uvicorn.run(app)
"""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI
from fastapi.middleware.cors import CORSMiddleware
from starlette.concurrency import run_in_threadpool

from .api.auth import PROTECTED, Authenticate
from .api.deps import unicode_body
from .api.errors import install_error_handlers, responses
from .api.limits import install_body_limits
from .api.routes import (auth, compare, dashboard, events, experiments, health, jobs, methods,
                         metrics, scenes, workers)
from .api.security import AllowedHosts, SecurityHeaders, allowed_hosts, relative_slash_redirects
from .farm import Farm
from .metrics import HTTPMetrics, PrometheusMetrics
from .settings import Settings

__all__ = ["create_app"]

_UNAUTHORIZED = responses(401)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The rayfarm HTTP service; its lifespan opens the farm and runs the scheduler."""
    settings = settings if settings is not None else Settings()
    farm_metrics = PrometheusMetrics()  # this app's own registry (service.metrics)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # the local pool warms up
        farm = await run_in_threadpool(Farm.open, settings, farm_metrics)
        app.state.farm = farm
        farm_metrics.watch(farm)
        await run_in_threadpool(farm.start)  # leads, or stands by for another replica
        try:
            yield
        finally:
            farm_metrics.watch(None)
            await run_in_threadpool(farm.close)

    # docs_url/redoc_url/openapi_url: served by the dashboard module, the docs
    # from local assets (no CDN), the schema behind authentication.
    app = FastAPI(title="rayfarm", version="0.1.0", lifespan=lifespan, docs_url=None,
                  redoc_url=None, openapi_url=None, dependencies=[Depends(unicode_body)],
                  description="A render farm: submit render jobs, follow them, fetch the EXR. "
                              "Every route but /healthz and /metrics needs "
                              "`Authorization: Bearer <token>`.")
    app.state.settings = settings
    app.state.metrics = farm_metrics
    install_error_handlers(app)
    # From the inside out: a body's sender is known before the body is read
    # (but a login's); every body is bounded (a declared oversized one is
    # refused before anything else is done for it); the Host is one of ours.
    # docs/hardening.md has the whole front door.
    app.add_middleware(Authenticate)
    install_body_limits(app, settings)
    if settings.cors_origins:  # none by default: the dashboard is same-origin
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST", "PATCH", "DELETE"],
                           allow_headers=["Authorization", "Content-Type"],
                           allow_credentials=False, max_age=600)
    app.add_middleware(AllowedHosts, hosts=allowed_hosts(settings.allowed_hosts))
    app.add_middleware(SecurityHeaders)
    # Outermost: times every answer; a request answered before routing (a 404,
    # a 413 of a declared oversized body) is "unmatched".
    app.add_middleware(HTTPMetrics, metrics=farm_metrics)
    # Every resource router needs a caller: a route added to one is protected
    # whether or not its handler asks who the caller is.
    for module in (jobs, compare, experiments, events, scenes, workers, methods):
        app.include_router(module.router, dependencies=PROTECTED, responses=_UNAUTHORIZED)
    app.include_router(auth.admin)
    for module in (auth, health, metrics, dashboard):
        app.include_router(module.router)
    dashboard.mount_assets(app)
    relative_slash_redirects(app.router)
    return app
