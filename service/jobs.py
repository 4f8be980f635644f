"""The service layer: what both the REST API and the web page do with jobs.

Accepting an upload is all or nothing: the file is checked (not empty, a decodable video within the
limits, valid options) while it still sits in a staging folder; only an accepted upload becomes a job
folder, a job record and a queue message, and if the queue cannot take the message the record and folder
go again. A rejected upload leaves nothing behind; an accepted one is kept in the job's input/ folder.
"""

from __future__ import annotations

import logging
import re
import shutil
import time
import uuid
from pathlib import Path
from typing import Any

from kombu.utils.url import maybe_sanitize_url
from pydantic import ValidationError

import neudf_core
from service.models import BrokerHealth, Health, JobPublic, WorkerHealth
from service.settings import Settings
from worker.celery_app import broker_reachable, create_celery, enqueue_job
from worker.errors import StageError
from worker.pipeline import STAGE_NAMES, JobOptions, artifact_files
from worker.stages.frames import VideoInfo, VideoLimits, probe_video
from worker.store import JobRecord, JobStore

log = logging.getLogger("neudf.service")

_ARTIFACT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_VIDEO_EXT = re.compile(r"\.[A-Za-z0-9]{1,5}")
_OPTION_FIELDS = set(JobOptions.model_fields)


class JobRejected(Exception):
    """A request the service turns down: an HTTP status and a one-line reason."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status, self.detail = status, detail


def probe_upload(path: Path, settings: Settings) -> VideoInfo:
    """Check that ``path`` is a video the pipeline can use; JobRejected saying why not (415: not a video)."""
    limits = VideoLimits(max_seconds=settings.video_max_seconds, min_frames=settings.video_min_frames,
                         max_pixels=settings.video_max_pixels)
    try:
        return probe_video(path, limits)
    except StageError as exc:
        raise JobRejected(415 if exc.kind == "not_video" else 422, exc.message) from None
    except Exception as exc:  # a decoder error the probe did not name: still the file's fault
        raise JobRejected(415, f"the file could not be read as a video ({type(exc).__name__})") from None


class JobService:
    """Jobs for one deployment: the store, the queue and the files, behind the checks users need."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        settings.root.mkdir(parents=True, exist_ok=True)
        settings.uploads_dir.mkdir(parents=True, exist_ok=True)
        self.store = JobStore(settings.resolved_database_url)
        self.celery = create_celery(settings, with_tasks=False)

    # -- who sees what --------------------------------------------------------------------------------
    def visible(self, job: JobRecord | None, owner: str | None) -> bool:
        return job is not None and (not self.settings.auth_enabled or job.owner == owner)

    def get(self, job_id: str, owner: str | None) -> JobRecord:
        job = self.store.get(job_id) if _looks_like_id(job_id) else None
        if not self.visible(job, owner):
            raise JobRejected(404, f"no job with id {job_id!r}")
        return job  # type: ignore[return-value]

    def list(self, owner: str | None, limit: int = 20, offset: int = 0) -> tuple[list[JobRecord], int]:
        return self.store.list(owner=owner, any_owner=not self.settings.auth_enabled, limit=limit, offset=offset)

    # -- accepting a job --------------------------------------------------------------------------------
    def staging_dir(self) -> Path:
        """A fresh folder for one upload in flight; the caller removes it (accepted files move out first)."""
        folder = self.settings.uploads_dir / uuid.uuid4().hex
        folder.mkdir(parents=True)
        return folder

    def parse_options(self, fields: dict[str, str]) -> JobOptions:
        unknown = sorted(set(fields) - _OPTION_FIELDS)
        if unknown:
            raise JobRejected(422, f"unknown field(s) {', '.join(unknown)}; accepted: file, "
                                   f"{', '.join(sorted(_OPTION_FIELDS))}")
        values: dict[str, Any] = {k: v for k, v in fields.items() if str(v).strip() != ""}
        values.setdefault("preset", self.settings.default_preset)
        try:
            return JobOptions.model_validate(values)
        except ValidationError as exc:
            reasons = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in exc.errors())
            raise JobRejected(422, f"invalid options: {reasons}") from None

    def create(self, upload: Path, input_name: str, fields: dict[str, str], owner: str | None) -> JobRecord:
        """Turn an upload (a file in a staging folder) into a queued job, or raise JobRejected."""
        size = upload.stat().st_size if upload.is_file() else 0
        if size == 0:
            raise JobRejected(400, "the uploaded file is empty")
        if size > self.settings.max_upload_bytes:
            raise JobRejected(413, f"the upload is larger than the limit of {self.settings.max_upload_mb:g} MB")
        options = self.parse_options(fields)
        info = probe_upload(upload, self.settings)
        job_id = uuid.uuid4().hex
        job_dir = self.settings.job_dir(job_id)
        (job_dir / "input").mkdir(parents=True)
        ext = Path(input_name).suffix.lower()
        target = job_dir / "input" / f"video{ext if _VIDEO_EXT.fullmatch(ext) else '.bin'}"
        shutil.move(str(upload), target)
        try:
            job = self.store.create(job_id=job_id, owner=owner, stages=list(STAGE_NAMES),
                                    options=options.model_dump(exclude_none=True), input_name=input_name[:255],
                                    input_bytes=size)
            enqueue_job(self.celery, job_id)
        except Exception as exc:
            self.store.discard(job_id)
            shutil.rmtree(job_dir, ignore_errors=True)
            log.exception("could not queue job %s", job_id)
            raise JobRejected(503, f"the job queue is unreachable ({type(exc).__name__}); try again later") from exc
        log.info("job %s queued: %s, %d bytes, %dx%d, %d frames, %.1f s", job_id, input_name, size, info.width,
                 info.height, info.frames, info.seconds)
        return job

    def create_from_file(self, source: Path, input_name: str, fields: dict[str, str], owner: str | None) -> JobRecord:
        """The page's way in: copy a file (Gradio's upload) into staging, then as ``create``."""
        staging = self.staging_dir()
        try:
            upload = staging / "upload"
            shutil.copyfile(source, upload)
            return self.create(upload, input_name, fields, owner)
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    # -- acting on a job --------------------------------------------------------------------------------
    def cancel(self, job_id: str, owner: str | None) -> JobRecord:
        job = self.get(job_id, owner)
        if job.finished:
            raise JobRejected(409, f"job {job_id} already {job.state}; only queued or running jobs can be cancelled")
        state = self.store.request_cancel(job_id)
        if state in ("succeeded", "failed"):
            raise JobRejected(409, f"job {job_id} already {state}")
        return self.get(job_id, owner)

    def delete(self, job_id: str, owner: str | None) -> None:
        job = self.get(job_id, owner)
        if not self.store.delete(job_id):
            raise JobRejected(409, f"job {job_id} is {job.state}; cancel it and wait for it to stop before deleting")
        shutil.rmtree(self.settings.job_dir(job_id), ignore_errors=True)

    def artifact(self, job_id: str, name: str, owner: str | None) -> Path:
        """The file behind an artifact name; only the fixed names of ``artifact_files`` ever resolve."""
        job = self.get(job_id, owner)
        if not _ARTIFACT_NAME.fullmatch(name) or ".." in name:
            raise JobRejected(400, f"invalid artifact name {name!r}")
        job_dir = self.settings.job_dir(job.id)
        files = artifact_files(job_dir)
        path = files.get(name)
        if path is None:
            available = ", ".join(sorted(files)) or "none yet"
            raise JobRejected(404, f"job {job_id} has no artifact {name!r} (available: {available})")
        resolved = path.resolve()
        if not resolved.is_relative_to(job_dir.resolve()):  # a link pointing out of the job: refuse
            raise JobRejected(404, f"job {job_id} has no artifact {name!r}")
        return resolved

    def frames(self, job_id: str, owner: str | None, limit: int = 24) -> list[Path]:
        """Up to ``limit`` of the job's chosen frames, evenly spread."""
        self.get(job_id, owner)
        files = sorted((self.settings.job_dir(job_id) / "data" / "image").glob("*.png"))
        if len(files) <= limit:
            return files
        step = (len(files) - 1) / (limit - 1)
        return [files[round(i * step)] for i in range(limit)]

    def public(self, job: JobRecord) -> JobPublic:
        return JobPublic.of(job)

    # -- health -----------------------------------------------------------------------------------------
    def health(self) -> Health:
        reasons = []
        database: dict[str, Any] = {"url": maybe_sanitize_url(self.settings.resolved_database_url), "reachable": True}
        counts: dict[str, int] = {}
        workers = []
        try:
            self.store.ping()
            counts = self.store.counts()
            workers = self.store.workers(seen_within_s=3 * self.settings.heartbeat_s + 5)
        except Exception as exc:
            database.update(reachable=False, error=f"{type(exc).__name__}: {exc}"[:300])
            reasons.append("database unreachable")
        ok, error = broker_reachable(self.celery)
        if not ok:
            reasons.append("broker unreachable")
        if not workers:
            reasons.append("no worker has reported in the last "
                           f"{3 * self.settings.heartbeat_s + 5:.0f} s")
        broker = BrokerHealth(url=maybe_sanitize_url(self.settings.resolved_broker_url),
                              embedded=self.settings.embedded_broker, reachable=ok, error=error)
        return Health(status="ok" if not reasons else "degraded", version=neudf_core.__version__, database=database,
                      broker=broker, workers=[WorkerHealth(**w.model_dump()) for w in workers],
                      workers_alive=len(workers), jobs=counts, reasons=reasons)

    def sweep_uploads(self, older_than_s: float = 3600) -> int:
        """Remove staging folders left by uploads cut off mid-way (a restarted API)."""
        removed = 0
        now = time.time()
        for folder in self.settings.uploads_dir.glob("*"):
            if now - folder.stat().st_mtime > older_than_s:
                shutil.rmtree(folder, ignore_errors=True)
                removed += 1
        return removed


def _looks_like_id(job_id: str) -> bool:
    return bool(re.fullmatch(r"[0-9a-f]{32}", job_id))
