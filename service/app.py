"""The FastAPI application: REST API under /api, OpenAPI at /docs, the web page at /.

``create_app(settings)`` builds everything from the settings it is given (or ``get_settings()``): the job
service, the routes, the page and, when ``settings.embedded_worker`` is set, a local Celery worker
process that lives as long as the app.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

import neudf_core
from service.api import router
from service.jobs import JobRejected, JobService
from service.settings import Settings, get_settings

log = logging.getLogger("neudf.service")


def create_app(settings: Settings | None = None, *, with_page: bool = True) -> FastAPI:
    settings = settings or get_settings()
    service = JobService(settings)
    service.sweep_uploads()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        embedded = None
        if settings.embedded_worker:
            from service.embedded import EmbeddedWorker

            embedded = EmbeddedWorker(settings)
            embedded.start()
            app.state.embedded_worker = embedded
        try:
            yield
        finally:
            if embedded is not None:
                embedded.stop()

    app = FastAPI(
        title="NeUDF service",
        version=neudf_core.__version__,
        description="Phone video in, open-surface mesh (GLB) out. Upload a video, follow the job, fetch the mesh.",
        lifespan=lifespan,
    )
    app.state.service = service
    app.state.settings = settings
    app.dependency_overrides[get_settings] = lambda: settings

    @app.exception_handler(JobRejected)
    async def _rejected(_: Request, exc: JobRejected) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if exc.status == 401 else None
        return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=headers)

    app.include_router(router)
    if with_page:
        from web.page import mount_page

        mount_page(app, service)
    return app
