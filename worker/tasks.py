"""Celery tasks: thin wrappers that run one job's pipeline and write what happens into the job store.

``run_job(job_id)``: claim the job in the store (a queued one, or a running one whose worker went
silent), run or resume the pipeline, write progress as it happens, record the end. Cancelling is a flag
in the job record that the progress callback reads at each report (at most every
``progress_interval_s``) and answers by raising ``Cancelled``.

Liveness does not depend on the task's own Python thread (a long C++ call may hold the GIL): the
worker's main process, which is not the pool process running the job, writes the heartbeat of the jobs
its pool runs and its own, and sweeps the store for running jobs whose heartbeat went stale, queueing
them again. A worker killed mid-job therefore stops heartbeating, any live worker re-queues the job
after ``stale_after_s``, and the pipeline resumes after the last finished stage.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

from celery import signals
from celery.exceptions import SoftTimeLimitExceeded

from neudf_core.progress import Cancelled
from worker.celery_app import TASK_RUN_JOB, NeudfCelery, QueueSettings, enqueue_job
from worker.pipeline import JobOptions, StageError, artifact_files, run_pipeline
from worker.store import JobRecord, JobStore, StageRecord, utcnow

log = logging.getLogger("neudf.worker")

_stores: dict[tuple[int, str], JobStore] = {}


def get_store(settings: QueueSettings) -> JobStore:
    """One store per process and database (a forked pool process makes its own)."""
    key = (os.getpid(), settings.resolved_database_url)
    if key not in _stores:
        _stores[key] = JobStore(settings.resolved_database_url)
    return _stores[key]


def find_input(job_dir: Path) -> Path | None:
    """The job's uploaded video (input/video.<ext>)."""
    files = sorted((job_dir / "input").glob("video.*"))
    return files[0] if files else None


class JobReporter:
    """The pipeline's progress callback for one job: writes the store, answers a cancel with Cancelled."""

    def __init__(self, store: JobStore, job: JobRecord, worker: str, settings: QueueSettings) -> None:
        self.store, self.job_id, self.worker, self.settings = store, job.id, worker, settings
        self.job_dir = settings.job_dir(job.id)
        self.stages: dict[str, StageRecord] = {s.name: s for s in job.stages}
        self.stage: str | None = None
        self._last_write = 0.0
        self.cancelled = False

    def __call__(self, fraction: float, message: str = "", **info: Any) -> None:
        stage, event = info.get("stage"), info.get("event", "progress")
        now = utcnow()
        record = self.stages.get(stage) if stage else None
        metrics: dict[str, Any] = {}
        artifacts = None
        if record is not None:
            self.stage = stage
            record.progress = float(info.get("stage_progress", record.progress))
            if event == "start":
                record.state, record.started_at, record.finished_at = "running", now, None
                record.runs += 1
                record.seconds = None
            elif event == "done":
                record.state, record.finished_at, record.progress = "done", now, 1.0
                record.seconds = info.get("seconds")
                metrics.update(info.get("metrics") or {})
            elif event == "skipped" and record.state != "done":
                record.state, record.progress = "done", 1.0
                record.seconds = info.get("seconds")
            record.message = message[:200]
            if "eta_s" in info:
                record.eta_s = round(float(info["eta_s"]), 1)
            if event in ("done", "skipped"):
                record.eta_s = None
                artifacts = list(artifact_files(self.job_dir))
        for key in ("iter", "loss", "psnr"):
            if key in info and stage == "train":
                metrics[f"train_{key}"] = info[key]
        forced = event != "progress"
        if not forced and time.monotonic() - self._last_write < self.settings.progress_interval_s:
            return
        self._last_write = time.monotonic()
        cancel = self.store.report(
            self.job_id, self.worker, stage=self.stage, progress=round(min(max(fraction, 0.0), 1.0), 5),
            message=message, stage_update=record.model_dump(mode="json") if record else None,
            metrics=metrics or None, artifacts=artifacts)
        if cancel:
            self.cancelled = True
            raise Cancelled(f"job {self.job_id} cancelled")


def _error(stage: str | None, message: str) -> dict[str, str]:
    return {"stage": stage or "worker", "message": message}


def run_job(settings: QueueSettings, job_id: str, worker: str) -> str:
    """Run or resume one job as ``worker`` (a name unique to this process). Returns the job's end state."""
    store = get_store(settings)
    job = store.claim(job_id, worker, settings.stale_after_s)
    if job is None:
        current = store.get(job_id)
        log.info("job %s not taken: %s", job_id, current.state if current else "deleted")
        return current.state if current else "deleted"
    if job.attempts > settings.max_attempts:
        store.finish(job_id, worker, "failed", message="gave up", error=_error(
            job.stage, f"the worker running this job was lost {job.attempts - 1} times; gave up"), stage_state="failed")
        return "failed"
    job_dir = settings.job_dir(job_id)
    video = find_input(job_dir)
    if video is None:
        store.finish(job_id, worker, "failed", error=_error("frames", "the uploaded video is missing"))
        return "failed"
    reporter = JobReporter(store, job, worker, settings)
    log.info("job %s: attempt %d on %s", job_id, job.attempts, worker)
    try:
        reporter(job.progress, "resuming" if job.attempts > 1 else "starting")
        metrics = run_pipeline(video, job_dir, JobOptions.model_validate(job.options), reporter,
                               device=settings.resolved_device())
    except Cancelled:
        store.finish(job_id, worker, "cancelled", message=f"cancelled during {reporter.stage or 'start'}",
                     stage_state="cancelled", artifacts=list(artifact_files(job_dir)))
        return "cancelled"
    except StageError as exc:
        cause = exc.__cause__
        message = (f"the job ran past its time limit of {settings.task_time_limit_s} s"
                   if isinstance(cause, SoftTimeLimitExceeded) else str(exc.message))
        log.warning("job %s failed in %s: %s", job_id, exc.stage, message)
        store.finish(job_id, worker, "failed", message=f"failed in {exc.stage}", error=_error(exc.stage, message),
                     stage_state="failed", artifacts=list(artifact_files(job_dir)))
        return "failed"
    except SoftTimeLimitExceeded:
        store.finish(job_id, worker, "failed", error=_error(
            reporter.stage, f"the job ran past its time limit of {settings.task_time_limit_s} s"), stage_state="failed")
        return "failed"
    except Exception as exc:  # a bug outside any stage: still recorded, never a silent loss
        log.exception("job %s crashed", job_id)
        store.finish(job_id, worker, "failed", error=_error(reporter.stage, f"{type(exc).__name__}: {exc}"),
                     stage_state="failed")
        return "failed"
    store.finish(job_id, worker, "succeeded", message="done", metrics=metrics,
                 artifacts=list(artifact_files(job_dir)))
    log.info("job %s succeeded", job_id)
    return "succeeded"


def recover_stale_jobs(app: NeudfCelery, store: JobStore) -> list[str]:
    """Queue again the running jobs whose worker went silent; the ids queued."""
    settings = app.neudf_settings
    requeued = []
    for job in store.stale_running(settings.stale_after_s):
        if job.cancel_requested:
            store.finish(job.id, None, "cancelled", message="cancelled (its worker was lost)", stage_state="cancelled")
        elif job.attempts >= settings.max_attempts:
            store.finish(job.id, None, "failed", error=_error(
                job.stage, f"the worker running this job was lost {job.attempts} times; gave up"), stage_state="failed")
        elif store.requeue_stale(job.id, settings.stale_after_s):
            log.warning("job %s: worker %s silent for %.0f s; queued again", job.id, job.worker, settings.stale_after_s)
            enqueue_job(app, job.id)
            requeued.append(job.id)
    return requeued


def _active_job_ids() -> list[str]:
    from celery.worker import state

    ids = []
    for request in list(state.active_requests):
        if request.task_name == TASK_RUN_JOB and request.args:
            ids.append(str(request.args[0]))
    return ids


class WorkerMonitor:
    """Runs in the worker's main process: heartbeats (the worker's and its jobs') and the stale-job sweep."""

    def __init__(self, app: NeudfCelery, nodename: str) -> None:
        self.app, self.nodename = app, nodename
        self.settings = app.neudf_settings
        self._stop = threading.Event()
        self._ticks = 0
        self._thread = threading.Thread(target=self._loop, name="neudf-monitor", daemon=True)

    def start(self) -> None:
        store = get_store(self.settings)
        if self.settings.embedded_broker:
            # A filesystem message is gone once read; a job whose message died with a worker between
            # receiving and claiming it would wait forever. Re-sending is harmless: a claim happens once.
            for job_id in store.queued_ids():
                enqueue_job(self.app, job_id)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        try:
            get_store(self.settings).worker_gone(self.nodename)
        except Exception:  # shutting down: the row just ages out
            log.debug("could not remove worker row", exc_info=True)

    def prune_processed(self, older_than_s: float = 86400) -> None:
        """The embedded broker keeps consumed messages (inside DATA_DIR); a day of them is plenty."""
        folder = self.settings.broker_folders["processed"]
        now = time.time()
        for path in folder.glob("*.msg") if folder.is_dir() else []:
            try:
                if now - path.stat().st_mtime > older_than_s:
                    path.unlink()
            except OSError:
                continue

    def tick(self) -> None:
        store = get_store(self.settings)
        self._ticks += 1
        if self.settings.embedded_broker and self._ticks % 600 == 1:
            self.prune_processed()
        store.worker_beat(self.nodename, socket.gethostname(), os.getpid(), self.settings.device)
        for job_id in _active_job_ids():
            store.heartbeat(job_id, None)
        recover_stale_jobs(self.app, store)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.tick()
            except Exception:  # a database hiccup must not kill the monitor
                log.exception("worker monitor tick failed")
            self._stop.wait(self.settings.heartbeat_s)


# Imported once in the worker's main process, so each job's fresh pool process is forked with them
# loaded instead of spending seconds importing torch and friends. Importing torch does not start CUDA, so
# forking after it is safe; the device is picked inside the job's process.
PRELOAD = ("torch", "neudf_core.trainer", "neudf_core.meshing", "worker.stages.frames", "worker.stages.poses",
           "worker.stages.scene", "worker.stages.export")


def preload_modules() -> None:
    import importlib

    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except Exception:  # a broken stage module shows up as that stage's error, with its job
            log.warning("could not preload %s", name, exc_info=True)


def register_tasks(app: NeudfCelery) -> None:
    """Add the job task to ``app`` and hook the monitor onto its worker's start and stop."""

    @app.task(name=TASK_RUN_JOB, bind=True, acks_late=True, reject_on_worker_lost=True, ignore_result=True)
    def run_job_task(self, job_id: str) -> str:  # noqa: ANN001 - Celery's bound task
        worker = f"{self.request.hostname}:{os.getpid()}"
        return run_job(self.app.neudf_settings, job_id, worker)

    monitors: dict[str, WorkerMonitor] = {}

    def on_ready(sender: Any = None, **_: Any) -> None:
        if getattr(sender, "app", None) is not app:
            return
        monitors["main"] = WorkerMonitor(app, sender.hostname)
        monitors["main"].start()

    def on_init(sender: Any = None, **_: Any) -> None:
        if getattr(sender, "app", None) is app:
            preload_modules()

    def on_shutdown(sender: Any = None, **_: Any) -> None:
        monitor = monitors.pop("main", None)
        if monitor is not None:
            monitor.stop()

    # weak=False: the handlers are closures that would otherwise be collected at once.
    signals.worker_init.connect(on_init, weak=False)
    signals.worker_ready.connect(on_ready, weak=False)
    signals.worker_shutdown.connect(on_shutdown, weak=False)
    app._neudf_signal_handlers = (on_init, on_ready, on_shutdown)  # type: ignore[attr-defined]

