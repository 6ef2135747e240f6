"""Assembles the FastAPI app; nothing else lives here.

    app = create_app(Settings(data_dir="/tmp/farm"))
    uvicorn.run(app)
"""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool

from .api.errors import install_error_handlers
from .api.limits import install_body_limits
from .api.routes import dashboard, events, health, jobs, methods, scenes, workers
from .farm import Farm
from .settings import Settings

__all__ = ["create_app"]


def create_app(settings: Settings | None = None) -> FastAPI:
    """The rayfarm HTTP service; its lifespan opens the farm and runs the scheduler."""
    settings = settings if settings is not None else Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        farm = await run_in_threadpool(Farm.open, settings)  # the local pool warms up
        app.state.farm = farm
        farm.scheduler.start()
        farm.thumbnails.start()
        try:
            yield
        finally:
            await run_in_threadpool(farm.close)

    # docs_url/redoc_url: served by the dashboard module from local assets (no CDN).
    app = FastAPI(title="rayfarm", version="0.1.0", lifespan=lifespan, docs_url=None,
                  redoc_url=None,
                  description="A render farm: submit render jobs, follow them, fetch the EXR.")
    app.state.settings = settings
    install_error_handlers(app)
    install_body_limits(app, settings)
    for module in (jobs, events, scenes, workers, methods, health, dashboard):
        app.include_router(module.router)
    dashboard.mount_assets(app)
    return app
