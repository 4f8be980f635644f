"""REST routes (../shared/CONTRACT.md): jobs, their artifacts, cancel, delete, health, liveness.

The upload is read from the request stream part by part and written straight into a staging file,
counting bytes: past ``max_upload_mb`` (the file) or that plus ``FORM_OVERHEAD_BYTES`` (the whole body,
fields included) the request ends with 413 and the partial file is removed, as it does past
``MAX_FORM_PARTS`` parts; a body that is not well-formed multipart gets 400. (FastAPI's ``UploadFile``
would first spool the whole body to a temporary file with no limit.)
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import FileResponse, JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool

from service.auth import TokenAuth
from service.jobs import JobRejected, JobService
from service.models import Health, HealthPublic, JobList, JobPublic, Live
from service.settings import Settings, get_settings
from worker.pipeline import JobOptions
from worker.tasks import LIVE_ARTIFACTS

router = APIRouter(prefix="/api")
_bearer = HTTPBearer(auto_error=False, description="Needed when NEUDF_AUTH_TOKENS is set")

MAX_FIELD_BYTES = 4096
MAX_FORM_PARTS = 32
FORM_OVERHEAD_BYTES = 64 * 1024  # room for the form's fields and boundaries beside the file
MAX_OFFSET = 10**9
MEDIA_TYPES = {".glb": "model/gltf-binary", ".ply": "application/octet-stream", ".png": "image/png",
               ".json": "application/json", ".jsonl": "application/x-ndjson", ".obj": "model/obj",
               ".mtl": "model/mtl", ".usdz": "model/vnd.usdz+zip"}


def get_service(request: Request) -> JobService:
    return request.app.state.service


def get_auth(request: Request) -> TokenAuth:
    return request.app.state.auth


def client_address(request: Request) -> str:
    return request.client.host if request.client else "unknown"


def get_owner(
    request: Request,
    auth: Annotated[TokenAuth, Depends(get_auth)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str | None:
    """The caller's owner key when tokens are configured (401 without a valid one, 429 after many bad ones)."""
    return auth.owner(credentials.credentials if credentials else None, client_address(request))


ServiceDep = Annotated[JobService, Depends(get_service)]
OwnerDep = Annotated[str | None, Depends(get_owner)]


class _UploadSink:
    """Callbacks for python-multipart: the ``file`` part into a file (size-capped), other parts as fields."""

    def __init__(self, path: Path, limit: int) -> None:
        self.path, self.limit = path, limit
        self.file_bytes = 0
        self.parts = 0
        self.complete = False  # the closing boundary arrived
        self.filename: str | None = None
        self.fields: dict[str, str] = {}
        self.error: JobRejected | None = None
        self._headers: dict[bytes, bytes] = {}
        self._field_name = self._header_value = b""
        self._part: str | None = None  # "file" or a field name
        self._buffer = bytearray()
        self._out = None

    def callbacks(self) -> dict:
        return {
            "on_part_begin": self._part_begin, "on_header_field": self._header_field,
            "on_header_value": self._header_val, "on_header_end": self._header_end,
            "on_headers_finished": self._headers_done, "on_part_data": self._data, "on_part_end": self._part_end,
            "on_end": self._end,
        }

    def _part_begin(self) -> None:
        self._headers, self._part, self._buffer = {}, None, bytearray()
        self._field_name = self._header_value = b""
        self.parts += 1
        if self.parts > MAX_FORM_PARTS and self.error is None:
            self.error = JobRejected(413, f"the form has more than {MAX_FORM_PARTS} fields")

    def _end(self) -> None:
        self.complete = True

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._field_name += data[start:end]
        self._check_header()

    def _header_val(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]
        self._check_header()

    def _check_header(self) -> None:
        if len(self._field_name) + len(self._header_value) > MAX_FIELD_BYTES and self.error is None:
            self.error = JobRejected(413, "a form part's header is too long")

    def _header_end(self) -> None:
        self._headers[self._field_name.lower()] = self._header_value
        self._field_name = self._header_value = b""

    def _headers_done(self) -> None:
        if self.error is not None:
            return
        _, params = parse_options_header(self._headers.get(b"content-disposition", b""))
        name = params.get(b"name", b"").decode("utf-8", "replace")
        if name == "file":
            if self._out is not None:
                self.error = JobRejected(422, "send one file per job")
                return
            self._part = "file"
            self.filename = params.get(b"filename", b"video").decode("utf-8", "replace") or "video"
            self._out = open(self.path, "wb")  # noqa: SIM115 - closed in _part_end / close()
        else:
            self._part = name

    def _data(self, data: bytes, start: int, end: int) -> None:
        if self.error is not None:
            return
        if self._part == "file":
            self.file_bytes += end - start
            if self.file_bytes > self.limit:
                self.error = JobRejected(413, f"the upload is larger than the limit of {self.limit / 2**20:g} MB")
                return
            self._out.write(data[start:end])
        elif self._part is not None:
            self._buffer += data[start:end]
            if len(self._buffer) > MAX_FIELD_BYTES:
                self.error = JobRejected(413, f"form field {self._part[:40]!r} is longer than {MAX_FIELD_BYTES} bytes")

    def _part_end(self) -> None:
        if self._part == "file" and self._out is not None:
            self._out.close()
        elif self._part is not None and self.error is None:
            self.fields[self._part] = self._buffer.decode("utf-8", "replace").strip()
        self._part = None

    def close(self) -> None:
        if self._out is not None and not self._out.closed:
            self._out.close()


def _form_field(schema: dict[str, Any]) -> dict[str, Any]:
    """One option's JSON schema as a form field: an optional one is simply left out, so its null branch goes."""
    field = {k: v for k, v in schema.items() if k != "anyOf" and not (k == "default" and v is None)}
    branches = [b for b in schema.get("anyOf", []) if b.get("type") != "null"]
    if len(branches) == 1:
        field.update(branches[0])
    return field


def upload_form_schema() -> dict[str, Any]:
    """The multipart body of ``POST /api/jobs``: ``file`` and every field of :class:`JobOptions`, as the model
    describes them (a new option shows in the API docs by itself)."""
    options = JobOptions.model_json_schema()
    properties = {"file": {"type": "string", "format": "binary", "description": "The video (MP4, MOV, ...)"}}
    properties.update({name: _form_field(field) for name, field in options["properties"].items()})
    return {"type": "object", "required": ["file"], "properties": properties}


_UPLOAD_BODY = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": upload_form_schema()}}}}


@router.post("/jobs", status_code=201, response_model=JobPublic, openapi_extra=_UPLOAD_BODY,
             responses={400: {}, 401: {}, 413: {}, 415: {}, 422: {}, 503: {}}, tags=["jobs"])
async def create_job(request: Request, service: ServiceDep, owner: OwnerDep,
                     settings: Annotated[Settings, Depends(get_settings)]) -> JobPublic:
    """Upload a video (multipart field ``file``) with optional ``preset``, ``frames``, ``iters``; 201 with the job."""
    content_type = request.headers.get("content-type", "")
    ctype, params = parse_options_header(content_type)
    if ctype != b"multipart/form-data" or not params.get(b"boundary"):
        raise JobRejected(415, "send the video as multipart/form-data with a 'file' field")
    limit = settings.max_upload_bytes
    declared = request.headers.get("content-length")
    declared_bytes = int(declared) if declared and declared.isdigit() else 0
    if declared_bytes > limit + FORM_OVERHEAD_BYTES:
        raise JobRejected(413, f"the upload is larger than the limit of {settings.max_upload_mb:g} MB")
    await run_in_threadpool(service.check_room, owner, declared_bytes)
    staging = service.staging_dir()
    sink = _UploadSink(staging / "upload", limit)
    try:
        await _receive_form(request, params[b"boundary"], sink, limit + FORM_OVERHEAD_BYTES, settings)
        if sink.filename is None:
            raise JobRejected(422, "the form has no 'file' field with the video")
        job = await run_in_threadpool(service.create, staging / "upload", sink.filename, sink.fields, owner)
    finally:
        sink.close()
        shutil.rmtree(staging, ignore_errors=True)
    return service.public(job)


async def _receive_form(request: Request, boundary: bytes, sink: _UploadSink, body_limit: int,
                        settings: Settings) -> None:
    """Stream the body through the multipart parser into ``sink``; JobRejected on the first broken limit."""
    parser = MultipartParser(boundary, sink.callbacks())
    received = 0
    try:
        async for chunk in request.stream():
            received += len(chunk)
            if received > body_limit:
                raise JobRejected(413, f"the upload is larger than the limit of {settings.max_upload_mb:g} MB")
            parser.write(chunk)
            if sink.error is not None:
                raise sink.error
        parser.finalize()
    except FormParserError as exc:
        raise JobRejected(400, f"the body is not well-formed multipart/form-data ({exc})"[:200]) from None
    sink.close()
    if sink.error is not None:
        raise sink.error
    if not sink.complete:
        raise JobRejected(400, "the body ended before the form's closing boundary")


@router.get("/jobs", response_model=JobList, tags=["jobs"])
def list_jobs(service: ServiceDep, owner: OwnerDep, limit: Annotated[int, Query(ge=1, le=200)] = 20,
              offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0) -> JobList:
    """Jobs, newest first."""
    jobs, total = service.list(owner, limit, offset)
    return JobList(items=[service.public(j) for j in jobs], total=total, limit=limit, offset=offset)


@router.get("/jobs/{job_id}", response_model=JobPublic, responses={404: {}}, tags=["jobs"])
def get_job(job_id: str, service: ServiceDep, owner: OwnerDep) -> JobPublic:
    """One job: state, stage, progress overall and per stage, error, metrics, artifact URLs."""
    return service.public(service.get(job_id, owner))


@router.get("/jobs/{job_id}/artifacts/{name:path}", responses={400: {}, 404: {}}, tags=["jobs"],
            response_class=FileResponse)
def get_artifact(job_id: str, name: str, service: ServiceDep, owner: OwnerDep) -> Response:
    """A file of the job, once whole: mesh.glb, mesh.obj (+ mesh.mtl, mesh.png), mesh.usdz, mesh.ply, preview.png, ...
    (metrics.jsonl while training: the lines written so far)."""
    path = service.artifact(job_id, name, owner)
    media_type = MEDIA_TYPES.get(path.suffix, "application/octet-stream")
    if name in LIVE_ARTIFACTS:
        return Response(_whole_lines(path), media_type=media_type,
                        headers={"Content-Disposition": f'attachment; filename="{name}"'})
    return FileResponse(path, media_type=media_type, filename=name)


def _whole_lines(path: Path) -> bytes:
    """A growing text file up to its last complete line."""
    data = path.read_bytes()
    return data[:data.rfind(b"\n") + 1]


@router.post("/jobs/{job_id}/cancel", response_model=JobPublic, responses={404: {}, 409: {}}, tags=["jobs"])
def cancel_job(job_id: str, service: ServiceDep, owner: OwnerDep) -> JobPublic:
    """Cancel a queued job at once, or a running one at its next progress report. 409 for a finished job."""
    return service.public(service.cancel(job_id, owner))


@router.delete("/jobs/{job_id}", status_code=204, responses={404: {}, 409: {}}, tags=["jobs"])
def delete_job(job_id: str, service: ServiceDep, owner: OwnerDep) -> Response:
    """Remove a finished job and its files. 409 while it is queued or running."""
    service.delete(job_id, owner)
    return Response(status_code=204)


@router.get("/health", response_model=Health | HealthPublic, responses={401: {}, 429: {}, 503: {}}, tags=["health"])
def health(request: Request, service: ServiceDep, auth: Annotated[TokenAuth, Depends(get_auth)],
           credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> JSONResponse:
    """200 when the database and the broker are reachable and a worker is alive, else 503. With tokens on, what is
    where (and the caller's job counts) only for a valid token; a bad token gets 401."""
    token = credentials.credentials if credentials else None
    owner = auth.owner(token, client_address(request)) if token or not auth.enabled else None
    result = service.health(owner, details=token is not None or not auth.enabled)
    return JSONResponse(result.model_dump(mode="json"), status_code=200 if result.status == "ok" else 503)


@router.get("/live", response_model=Live, tags=["health"])
async def live() -> Live:  # async: answers on the event loop even when every worker thread is busy
    """The API process answers (nothing else is checked)."""
    return Live()
