"""The service layer: what both the REST API and the web page do with jobs.

Accepting an upload is all or nothing: the file is checked (not empty, a decodable video within the
limits, valid options, room for it: the caller's unfinished jobs and the free disk) while it still sits in a
staging folder; only an accepted upload becomes a job folder, a job record and a queue message, and if the
store or the queue cannot take it the folder goes again (first, so that it goes even when the record
cannot). A rejected upload leaves nothing behind; an accepted one is kept in the job's input/ folder.
Folders under jobs/ without a record (a process killed mid-create) are swept at start.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import time
import uuid
from pathlib import Path
from typing import Any

from kombu.utils.url import maybe_sanitize_url
from pydantic import ValidationError
from sqlalchemy.exc import SQLAlchemyError

import neudf_core
from service.models import BrokerHealth, Health, HealthPublic, JobPublic, WorkerHealth
from service.settings import Settings
from worker.capture.frames import VideoInfo, VideoLimits, probe_video
from worker.celery_app import broker_reachable, create_celery, enqueue_job
from worker.errors import StageError
from worker.pipeline import STAGE_NAMES, JobOptions, artifact_files, completed_stages
from worker.store import JobRecord, JobStore
from worker.tasks import finished_artifacts

# JobRecord is what the service hands its callers (the API, the page): they name it from here.
__all__ = ["JobService", "JobRejected", "JobRecord", "probe_upload", "STORE_BUSY"]

log = logging.getLogger("neudf.service")

_ARTIFACT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_VIDEO_EXT = re.compile(r"\.[A-Za-z0-9]{1,5}")
_OPTION_FIELDS = set(JobOptions.model_fields)


STORE_BUSY = "the job store is busy or unreachable; try again shortly"
UNFINISHED = ("queued", "running")


class JobRejected(Exception):
    """A request the service turns down: an HTTP status, a one-line reason and, for a wait, its seconds."""

    def __init__(self, status: int, detail: str, retry_after_s: float | None = None) -> None:
        super().__init__(detail)
        self.status, self.detail, self.retry_after_s = status, detail, retry_after_s


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
        self.store = JobStore(settings.resolved_database_url, busy_timeout_s=settings.db_wait_s)
        self.celery = create_celery(settings)  # sends jobs by name: no task code in the API

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
            named = ", ".join(repr(name[:40]) for name in unknown[:5]) + (f" and {len(unknown) - 5} more"
                                                                         if len(unknown) > 5 else "")
            raise JobRejected(422, f"unknown field(s) {named}; accepted: file, {', '.join(sorted(_OPTION_FIELDS))}")
        values: dict[str, Any] = {k: v for k, v in fields.items() if str(v).strip() != ""}
        if self.settings.default_preset:
            values.setdefault("preset", self.settings.default_preset)
        try:
            return JobOptions.model_validate(values)
        except ValidationError as exc:
            reasons = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in exc.errors())
            raise JobRejected(422, f"invalid options: {reasons}") from None

    def check_room(self, owner: str | None, incoming_bytes: int = 0) -> None:
        """JobRejected unless the caller may add a job: 429 past its unfinished jobs, 507 short of disk."""
        counts = self.store.counts(owner=owner, any_owner=not self.settings.auth_enabled)
        unfinished = sum(counts.get(state, 0) for state in UNFINISHED)
        if unfinished >= self.settings.max_unfinished_jobs:
            raise JobRejected(429, f"{unfinished} jobs are queued or running (at most "
                                   f"{self.settings.max_unfinished_jobs}); wait for one to finish or cancel one", 60)
        free_mb = (shutil.disk_usage(self.settings.root).free - incoming_bytes) / 2**20
        if free_mb < self.settings.min_free_disk_mb:
            raise JobRejected(507, "the server is short of disk space for a new job; try again later")

    def create(self, upload: Path, input_name: str, fields: dict[str, str], owner: str | None) -> JobRecord:
        """Turn an upload (a file in a staging folder) into a queued job, or raise JobRejected."""
        size = upload.stat().st_size if upload.is_file() else 0
        if size == 0:
            raise JobRejected(400, "the uploaded file is empty")
        if size > self.settings.max_upload_bytes:
            raise JobRejected(413, f"the upload is larger than the limit of {self.settings.max_upload_mb:g} MB")
        options = self.parse_options(fields)
        self.check_room(owner)
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
        except SQLAlchemyError as exc:
            shutil.rmtree(job_dir, ignore_errors=True)
            log.warning("job store refused job %s: %s", job_id, exc)
            raise JobRejected(503, STORE_BUSY, 5) from exc
        try:
            enqueue_job(self.celery, job_id)
        except Exception as exc:  # any broker error: the job must go again, whole
            shutil.rmtree(job_dir, ignore_errors=True)
            self._discard(job_id)
            log.exception("could not queue job %s", job_id)
            raise JobRejected(503, "the job queue is unreachable; try again later", 5) from exc
        log.info("job %s queued: %s, %d bytes, %dx%d, %d frames, %.1f s", job_id, input_name, size, info.width,
                 info.height, info.frames, info.seconds)
        return job

    def _discard(self, job_id: str) -> None:
        try:
            self.store.discard(job_id)
        except SQLAlchemyError:  # the record stays queued without its video: a worker fails it ("video missing")
            log.warning("could not remove the record of unqueued job %s", job_id, exc_info=True)

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
        """The file behind an artifact name, once whole; only the fixed names of ``artifact_files`` ever resolve."""
        job = self.get(job_id, owner)
        if not _ARTIFACT_NAME.fullmatch(name[:64]) or ".." in name:
            raise JobRejected(400, f"invalid artifact name {name[:64]!r}")
        job_dir = self.settings.job_dir(job.id)
        files = finished_artifacts(job_dir)
        path = files.get(name)
        if path is None:
            available = ", ".join(sorted(files)) or "none yet"
            raise JobRejected(404, f"job {job_id} has no artifact {name!r} (available: {available})")
        resolved = path.resolve()
        if not resolved.is_relative_to(job_dir.resolve()):  # a link pointing out of the job: refuse
            raise JobRejected(404, f"job {job_id} has no artifact {name!r}")
        return resolved

    def frames(self, job_id: str, owner: str | None, limit: int = 24) -> list[Path]:
        """Up to ``limit`` of the job's chosen frames, evenly spread, once the frames stage has finished."""
        self.get(job_id, owner)
        job_dir = self.settings.job_dir(job_id)
        if "frames" not in completed_stages(job_dir):
            return []
        files = sorted((job_dir / "data" / "image").glob("*.png"))
        if len(files) <= limit:
            return files
        step = (len(files) - 1) / (limit - 1)
        return [files[round(i * step)] for i in range(limit)]

    # -- what the page shows ---------------------------------------------------------------------------
    @property
    def files_root(self) -> Path:
        """The folder all jobs' files live under: the page shows files from it (each checked by ``check_page_file``)."""
        return self.settings.jobs_dir

    def check_page_file(self, requested: str, owner: str | None) -> None:
        """JobRejected 404 for a file the page is asked for (``requested``, resolved as Gradio resolves it) that lies
        in the jobs folder and is not a whole artifact or a chosen frame of a job the caller sees. Files elsewhere
        are Gradio's to check."""
        target = Path(os.path.abspath(requested)).resolve()
        jobs = self.files_root.resolve()
        if not target.is_relative_to(jobs) or target == jobs:
            return
        job_id = target.relative_to(jobs).parts[0]
        self.get(job_id, owner)
        job_dir = self.settings.job_dir(job_id)
        shown = {p.resolve() for p in finished_artifacts(job_dir).values()} | {p.resolve() for p in
                                                                             self.frames(job_id, owner, limit=10**6)}
        if target not in shown or not target.is_file():
            raise JobRejected(404, "no such file")

    def training_log(self, job: JobRecord) -> list[dict[str, Any]]:
        """The whole lines of the job's metrics.jsonl so far (``job``: a record the caller got from ``get`` or ``list``)."""
        from worker.export import read_metrics_log

        path = artifact_files(self.settings.job_dir(job.id)).get("metrics.jsonl")
        return read_metrics_log(path) if path is not None else []

    @staticmethod
    def presets() -> list[str]:
        """The training presets a job may name."""
        from neudf_core.config import available_presets

        return available_presets()

    def public(self, job: JobRecord) -> JobPublic:
        return JobPublic.of(job)

    # -- health -----------------------------------------------------------------------------------------
    def health(self, owner: str | None, *, details: bool) -> HealthPublic:
        """ok only with the database and the broker reachable and a worker alive. ``details``: what is where (for
        a valid token, or anyone when tokens are off); job counts are the caller's own when tokens are on."""
        reasons = []
        database: dict[str, Any] = {"url": maybe_sanitize_url(self.settings.resolved_database_url), "reachable": True}
        counts: dict[str, int] = {}
        workers = []
        seen_within_s = 3 * self.settings.heartbeat_s + 5
        try:
            self.store.ping()
            counts = self.store.counts(owner=owner, any_owner=not self.settings.auth_enabled)
            workers = self.store.workers(seen_within_s=seen_within_s)
        except Exception as exc:  # any database error means "unreachable"; its text stays in the log
            log.warning("health: database unreachable: %s", exc)
            database.update(reachable=False, error=type(exc).__name__)
            reasons.append("database unreachable")
        ok, error = broker_reachable(self.celery)
        if not ok:
            log.warning("health: broker unreachable: %s", error)
            reasons.append("broker unreachable")
        if not workers:
            reasons.append(f"no worker has reported in the last {seen_within_s:.0f} s")
        status = "ok" if not reasons else "degraded"
        if not details:
            return HealthPublic(status=status)
        broker = BrokerHealth(url=maybe_sanitize_url(self.settings.resolved_broker_url),
                              embedded=self.settings.embedded_broker, reachable=ok,
                              error=error.split(":", 1)[0] if error else None)
        return Health(status=status, version=neudf_core.__version__, database=database, broker=broker,
                      workers=[WorkerHealth(**w.model_dump()) for w in workers], workers_alive=len(workers),
                      jobs=counts, reasons=reasons)

    def sweep_uploads(self, older_than_s: float = 3600) -> int:
        """Remove staging folders left by uploads cut off mid-way (a restarted API)."""
        return _remove_old(self.settings.uploads_dir.glob("*"), older_than_s)

    def sweep_orphans(self, older_than_s: float = 3600) -> int:
        """Remove job folders that have no record (a create cut off between its folder and its record)."""
        folders = [f for f in self.settings.jobs_dir.glob("*") if self.store.get(f.name) is None] \
            if self.settings.jobs_dir.is_dir() else []
        return _remove_old(folders, older_than_s)


def _remove_old(paths: Any, older_than_s: float) -> int:
    removed = 0
    now = time.time()
    for path in paths:
        if now - path.stat().st_mtime > older_than_s:
            shutil.rmtree(path, ignore_errors=True)
            removed += 1
    return removed


def _looks_like_id(job_id: str) -> bool:
    return bool(re.fullmatch(r"[0-9a-f]{32}", job_id))
