"""What stands between the network and the Gradio page: tokens, the files the page may touch, body limits.

Gradio mounted into FastAPI checks neither tokens nor the file paths its inputs name (a mounted app never
counts as launched, so Gradio skips its own path check), and it copies a named file before any handler of
ours runs. ``PageGuard`` wraps every request that is not the REST API's (which checks its own tokens):

- with tokens on, a request without a valid one (``Authorization: Bearer`` or the cookie ``/login`` sets)
  gets 401, or a redirect to ``/login`` for a page load; too many bad ones from one address get 429;
- a body must say its length and stay under a limit (413; 411 without a length): JSON bodies under
  ``PAGE_JSON_LIMIT``, file uploads under the upload limit;
- every ``"path"`` a JSON body names must be a regular file in Gradio's upload folder (400 otherwise), so
  no input reaches a device, a FIFO or another user's file;
- a file the page serves from a job folder (``/gradio_api/file=...``) must be a whole artifact or a
  chosen frame of a job the caller sees (404 otherwise); the job's files go with the job.

Errors are ``{"detail": "reason"}`` like the API's.
"""

from __future__ import annotations

import html
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from gradio.utils import get_upload_folder
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.app import rejection
from service.auth import TOKEN_MAX_CHARS, TokenAuth
from service.jobs import JobRejected, JobService

COOKIE = "neudf_token"
COOKIE_MAX_AGE_S = 7 * 86400
PAGE_JSON_LIMIT = 1024 * 1024
# Served by FastAPI itself and public by design; /api/* checks its own tokens.
PUBLIC_PATHS = frozenset({"/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json", "/login", "/logout"})
FILE_ROUTES = ("/gradio_api/file=", "/gradio_api/file/")
LOGIN_FORM_LIMIT = 4096


def _public(path: str) -> bool:
    return path in PUBLIC_PATHS or path.startswith("/api/")


def _file_requested(path: str) -> str | None:
    """The file a Gradio file route is asked for, as the route reads it; None for other routes."""
    for prefix in FILE_ROUTES:
        if path.startswith(prefix):
            return path[len(prefix):]
    return None


def page_token(conn: HTTPConnection) -> str | None:
    scheme, _, value = conn.headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    return conn.cookies.get(COOKIE) or None


def client_of(conn: HTTPConnection) -> str:
    return conn.client.host if conn.client else "unknown"


def page_upload(path: str) -> Path:
    """``path`` resolved, when it is a regular file in Gradio's upload folder; JobRejected 400 otherwise."""
    resolved = Path(os.path.abspath(path)).resolve()
    if not resolved.is_relative_to(Path(get_upload_folder()).resolve()) or not resolved.is_file():
        raise JobRejected(400, "the page only takes files uploaded through it")
    return resolved


def _named_paths(value: Any) -> Iterator[Any]:
    if isinstance(value, dict):
        for key, item in value.items():
            if key == "path":
                yield item
            else:
                yield from _named_paths(item)
    elif isinstance(value, list):
        for item in value:
            yield from _named_paths(item)


def check_named_paths(body: bytes) -> None:
    """JobRejected 400 unless every ``"path"`` in a JSON body is a page upload (not JSON: Gradio refuses it)."""
    try:
        data = json.loads(body) if body else None
    except ValueError:
        return
    except RecursionError:
        raise JobRejected(400, "the body nests too deeply") from None
    for path in _named_paths(data):
        if not isinstance(path, str):
            raise JobRejected(400, "a file path must be a string")
        page_upload(path)


async def read_body(receive: Receive, limit: int) -> bytes:
    body = bytearray()
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            raise JobRejected(400, "the client went away")
        body += message.get("body", b"")
        if len(body) > limit:
            raise JobRejected(413, f"the request body is larger than {limit} bytes")
        if not message.get("more_body"):
            return bytes(body)


def replay(body: bytes, receive: Receive) -> Receive:
    """A receive that hands out ``body`` once, then whatever the client sends next (its disconnect)."""
    sent = False

    async def _receive() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return _receive


class PageGuard:
    """ASGI middleware: the checks of the module doc on every request outside the REST API."""

    def __init__(self, app: ASGIApp, service: JobService, auth: TokenAuth) -> None:
        self.app, self.service, self.auth = app, service, auth
        self.upload_limit = service.settings.max_upload_bytes + 64 * 1024

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or _public(scope["path"]):
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        try:
            owner = self.auth.owner(page_token(conn), client_of(conn))
            if scope["type"] == "http":
                receive = await self._check_request(scope, conn, receive, owner)
        except JobRejected as exc:
            await self._refuse(exc, scope, conn, receive, send)
            return
        await self.app(scope, receive, send)

    async def _check_request(self, scope: Scope, conn: HTTPConnection, receive: Receive, owner: str | None) -> Receive:
        requested = _file_requested(scope["path"])
        if requested is not None:
            # files in the jobs folder: only the caller's jobs' artifacts and frames
            await run_in_threadpool(self.service.check_page_file, requested, owner)
        if scope["method"] in ("GET", "HEAD", "OPTIONS"):
            return receive
        declared = conn.headers.get("content-length")
        if declared is None or not declared.isdigit():
            raise JobRejected(411, "a request to the page must give its Content-Length")
        multipart = conn.headers.get("content-type", "").startswith("multipart/")
        limit = self.upload_limit if multipart else PAGE_JSON_LIMIT
        if int(declared) > limit:
            raise JobRejected(413, f"the request body is larger than {limit} bytes")
        if multipart:  # a file upload: Gradio streams it into its upload folder, capped by max_file_size
            return receive
        body = await read_body(receive, limit)
        await run_in_threadpool(check_named_paths, body)
        return replay(body, receive)

    async def _refuse(self, exc: JobRejected, scope: Scope, conn: HTTPConnection, receive: Receive,
                      send: Send) -> None:
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008})
            return
        response: Response = rejection(exc)
        if exc.status == 401 and scope["method"] == "GET" and "text/html" in conn.headers.get("accept", ""):
            response = RedirectResponse("/login", status_code=303)
            response.delete_cookie(COOKIE, path="/")
        await response(scope, receive, send)


def _login_page(message: str = "", status: int = 200) -> HTMLResponse:
    note = f"<p style='color:#b00020'>{html.escape(message)}</p>" if message else ""
    return HTMLResponse(
        "<!doctype html><html><head><meta charset='utf-8'><title>NeUDF: sign in</title></head>"
        "<body style='font-family:system-ui,sans-serif;max-width:28rem;margin:4rem auto'>"
        "<h2>NeUDF</h2><p>This service needs an access token.</p>"
        f"{note}<form method='post' action='/login'>"
        f"<input type='password' name='token' maxlength='{TOKEN_MAX_CHARS}' autofocus required "
        "placeholder='Access token' style='width:100%;padding:0.4rem'>"
        "<button type='submit' style='margin-top:0.6rem'>Sign in</button></form></body></html>",
        status_code=status)


def add_login_routes(app: FastAPI, auth: TokenAuth) -> None:
    """/login asks for a token and keeps a valid one in an HttpOnly, same-site cookie; /logout drops it."""

    @app.get("/login", include_in_schema=False)
    def login_form() -> HTMLResponse:
        return _login_page()

    @app.post("/login", include_in_schema=False)
    async def login(request: Request) -> Response:
        declared = request.headers.get("content-length", "")
        if not declared.isdigit() or int(declared) > LOGIN_FORM_LIMIT:
            return _login_page("The form is too large.", 413)
        token = (parse_qs((await request.body()).decode("utf-8", "replace")).get("token") or [""])[0].strip()
        try:
            auth.owner(token, client_of(request))
        except JobRejected as exc:
            return _login_page(exc.detail, exc.status)
        response = RedirectResponse("/", status_code=303)
        response.set_cookie(COOKIE, token, max_age=COOKIE_MAX_AGE_S, path="/", httponly=True, samesite="strict",
                            secure=request.url.scheme == "https")
        return response

    @app.post("/logout", include_in_schema=False)
    def logout() -> Response:
        response = RedirectResponse("/login", status_code=303)
        response.delete_cookie(COOKIE, path="/")
        return response
