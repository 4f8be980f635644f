"""The FastAPI application: REST API under /api, OpenAPI at /docs.

``create_app(settings)`` builds everything from the settings it is given (or ``get_settings()``): the job
service (``app.state.service``), the token checks (``app.state.auth``), the routes and, when
``settings.embedded_worker`` is set, a local Celery worker process that lives as long as the app. The web
page at / is not the service's: `neudf serve` (web/cli.py) mounts it onto this app (``web.page.mount_page``).

Every error leaves as ``{"detail": "reason"}``: a refusal with its status, a busy or unreachable job store
as 503, invalid parameters as 422 naming the parameter, anything unexpected as 500 without its text (which
goes to the log).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import SQLAlchemyError

import neudf_core
from service.api import router
from service.auth import TokenAuth
from service.jobs import STORE_BUSY, JobRejected, JobService
from service.settings import Settings, get_settings

log = logging.getLogger("neudf.service")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    service = JobService(settings)
    service.sweep_uploads()
    service.sweep_orphans()

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
    app.state.auth = TokenAuth(settings, service.store)
    app.dependency_overrides[get_settings] = lambda: settings
    add_error_handlers(app)
    app.include_router(router)
    return app


def rejection(exc: JobRejected) -> JSONResponse:
    headers = {}
    if exc.status == 401:
        headers["WWW-Authenticate"] = "Bearer"
    if exc.retry_after_s is not None:
        headers["Retry-After"] = str(max(1, round(exc.retry_after_s)))
    return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=headers)


def add_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(JobRejected)
    async def _rejected(_: Request, exc: JobRejected) -> JSONResponse:
        return rejection(exc)

    @app.exception_handler(SQLAlchemyError)
    async def _store(request: Request, exc: SQLAlchemyError) -> JSONResponse:
        log.warning("job store error on %s %s: %s", request.method, request.url.path, exc)
        return rejection(JobRejected(503, STORE_BUSY, 5))

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        # loc and msg only: FastAPI's default answer echoes the input, however large
        reasons = "; ".join(f"{'.'.join(map(str, e['loc'][1:] or e['loc']))}: {e['msg']}" for e in exc.errors()[:5])
        return JSONResponse({"detail": reasons[:500]}, status_code=422)

    @app.exception_handler(Exception)
    async def _unexpected(_: Request, exc: Exception) -> JSONResponse:  # the server logs it with its traceback
        return JSONResponse({"detail": "internal error; the server's log has the details"}, status_code=500)
