"""Celery tasks: thin wrappers that run one job's pipeline and write what happens into the job store.

``run_job(job_id)``: claim the job in the store (a queued one, or a running one whose worker went
silent), run or resume the pipeline, write progress as it happens, record the end. Cancelling is a flag
in the job record that the progress callback reads at each report (at most every
``progress_interval_s``) and answers by raising ``Cancelled``.

Liveness does not depend on the task's own Python thread (a long C++ call may hold the GIL): the
worker's main process, which is not the pool process running the job, writes the heartbeat of the jobs
its pool runs and its own, and sweeps the store for running jobs whose heartbeat went stale, queueing
them again. A worker killed mid-job therefore stops heartbeating, any live worker re-queues the job
after ``stale_after_s``, and the pipeline resumes after the last finished stage. A pool process killed
while its worker lives on (the out-of-memory killer, the hard time limit) fails its job instead: running
it again would meet the same end. An embedded worker (``parent_pid`` set) ends with its `neudf serve`.

What users read of a failure is the stage's own message with server paths reduced to file names; an
unexpected error's text goes to the worker's log only.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import socket
import threading
import time
from pathlib import Path
from typing import Any

import psutil
from billiard.exceptions import WorkerLostError
from celery import signals
from celery.exceptions import SoftTimeLimitExceeded, TimeLimitExceeded

from neudf_core.progress import Cancelled
from worker.celery_app import TASK_RUN_JOB, NeudfCelery, enqueue_job
from worker.pipeline import JobOptions, StageError, artifact_files, completed_stages, run_pipeline
from worker.settings import QueueSettings
from worker.store import JobRecord, JobStore, StageRecord, utcnow

log = logging.getLogger("neudf.worker")

_stores: dict[tuple[int, str], JobStore] = {}


def get_store(settings: QueueSettings) -> JobStore:
    """One store per process and database (a forked pool process makes its own)."""
    key = (os.getpid(), settings.resolved_database_url)
    if key not in _stores:
        _stores[key] = JobStore(settings.resolved_database_url)
    return _stores[key]


# Not every stage writes its files atomically, so an artifact is handed out once the stage that writes it has
# finished (its marker is written after its outputs are whole). The capture stages write these whole (atomically),
# metrics.jsonl grows a line at a time (served as its whole lines); anything else is the export stage's.
WHOLE_WHEN_WRITTEN = frozenset({"capture.json", "frames.json", "cameras.png"})
LIVE_ARTIFACTS = frozenset({"metrics.jsonl"})
WRITTEN_BY = {"frames.png": "frames", "validation.png": "train"}


def finished_artifacts(job_dir: Path) -> dict[str, Path]:
    """The job's artifacts that may be handed out now: whole files only."""
    done = set(completed_stages(job_dir))
    return {name: path for name, path in artifact_files(job_dir).items()
            if name in WHOLE_WHEN_WRITTEN or name in LIVE_ARTIFACTS or WRITTEN_BY.get(name, "export") in done}


_ABS_PATH = re.compile(r"(?<![\w.~-])(?:/[^\s/'\"(),:;]+)+/?")


def public_message(exc: StageError) -> str:
    """A stage failure as users read it: the stage's own words without server paths; never an internal error's text."""
    cause = exc.__cause__
    if cause is not None and not isinstance(cause, StageError) and exc.message.startswith(f"{type(cause).__name__}:"):
        # the pipeline's wrapping of an unexpected error: its text (paths, values) is for the log
        return internal_error_message(cause)
    return _ABS_PATH.sub(lambda m: Path(m.group(0)).name or "/", exc.message)


def internal_error_message(exc: BaseException) -> str:
    return f"an internal error ({type(exc).__name__}) stopped the job; the worker's log has the details"


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
        if record is not None and event == "plan":  # a stage still to run, with its expected seconds
            if record.state != "done":
                record.eta_s = round(float(info.get("eta_s", 0.0)), 1)
            self.store.update_stage(self.job_id, self.worker, record.model_dump(mode="json"))
            return
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
                artifacts = list(finished_artifacts(self.job_dir))
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
                     stage_state="cancelled", artifacts=list(finished_artifacts(job_dir)))
        return "cancelled"
    except StageError as exc:
        cause = exc.__cause__
        message = (f"the job ran past its time limit of {settings.task_time_limit_s} s"
                   if isinstance(cause, SoftTimeLimitExceeded) else public_message(exc))
        log.warning("job %s failed in %s: %s", job_id, exc.stage, exc.message, exc_info=cause is not None)
        store.finish(job_id, worker, "failed", message=f"failed in {exc.stage}", error=_error(exc.stage, message),
                     stage_state="failed", artifacts=list(finished_artifacts(job_dir)))
        return "failed"
    except SoftTimeLimitExceeded:
        store.finish(job_id, worker, "failed", error=_error(
            reporter.stage, f"the job ran past its time limit of {settings.task_time_limit_s} s"), stage_state="failed")
        return "failed"
    except Exception as exc:  # a bug outside any stage: still recorded, never a silent loss
        log.exception("job %s crashed", job_id)
        store.finish(job_id, worker, "failed", error=_error(reporter.stage, internal_error_message(exc)),
                     stage_state="failed")
        return "failed"
    store.finish(job_id, worker, "succeeded", message="done", metrics=metrics,
                 artifacts=list(finished_artifacts(job_dir)))
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
        elif _send_again(app, job.id) and store.requeue_stale(job.id, settings.stale_after_s):
            log.warning("job %s: worker %s silent for %.0f s; queued again", job.id, job.worker, settings.stale_after_s)
            requeued.append(job.id)
    return requeued


def _send_again(app: NeudfCelery, job_id: str) -> bool:
    """Send a silent job's message before marking it queued: a claim takes a silent running job as it takes a
    queued one, and when the broker refuses, the job stays silent for the next sweep to try again (marked
    queued first, it would wait for a message nobody sends)."""
    try:
        enqueue_job(app, job_id)
    except Exception:  # any broker error: the next sweep tries again
        log.warning("job %s: could not send it to the queue again; retrying at the next sweep", job_id, exc_info=True)
        return False
    return True


def fail_lost_process(store: JobStore, job_id: str, exc: BaseException, settings: QueueSettings) -> None:
    """Record the end of a job whose pool process died under a live worker (no re-delivery: see the module doc)."""
    if isinstance(exc, TimeLimitExceeded):
        message = f"the job ran past its time limit of {settings.task_time_limit_s} s"
    else:
        message = ("the job's process was killed, most often by the out-of-memory killer; try fewer frames, a "
                   "smaller max_size or a lower mesh_resolution")
    job = store.get(job_id)
    log.warning("job %s: pool process lost (%s); failing it", job_id, exc)
    store.finish(job_id, None, "failed", message="failed", error=_error(job.stage if job else None, message),
                 stage_state="failed")


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

    def parent_gone(self) -> bool:
        return self.settings.parent_pid is not None and os.getppid() != self.settings.parent_pid

    def end_with_parent(self) -> None:
        """End this worker and its pool at once, as a lost worker: a running job's heartbeat stops and a live
        worker queues it again after ``stale_after_s`` (the next `neudf serve` starts one)."""
        log.warning("neudf serve (pid %s) is gone; this worker ends and hands back its job", self.settings.parent_pid)
        self.stop()
        if os.getpgrp() == os.getpid():  # `neudf serve` starts its worker in a session of its own: one signal ends all
            os.killpg(os.getpid(), signal.SIGKILL)
        for child in psutil.Process().children(recursive=True):
            child.kill()
        os.kill(os.getpid(), signal.SIGKILL)

    def tick(self) -> None:
        if self.parent_gone():
            self.end_with_parent()
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
PRELOAD = ("torch", "neudf_core.trainer", "neudf_core.extract", "worker.capture.frames", "worker.capture.poses",
           "worker.capture.scene", "worker.export")


def preload_modules() -> None:
    import importlib

    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except Exception:  # a broken stage module shows up as that stage's error, with its job
            log.warning("could not preload %s", name, exc_info=True)


def register_tasks(app: NeudfCelery) -> None:
    """Add the job task to ``app`` and hook the monitor onto its worker's start and stop."""

    @app.task(name=TASK_RUN_JOB, bind=True, acks_late=True, reject_on_worker_lost=False, ignore_result=True)
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

    def on_failure(sender: Any = None, exception: BaseException | None = None, args: Any = None, **_: Any) -> None:
        # Sent in the worker's main process when the pool process running a job died (the task itself records
        # every failure it lives to see).
        if getattr(sender, "app", None) is not app or getattr(sender, "name", None) != TASK_RUN_JOB or not args:
            return
        if isinstance(exception, WorkerLostError | TimeLimitExceeded):
            fail_lost_process(get_store(app.neudf_settings), str(args[0]), exception, app.neudf_settings)

    # weak=False: the handlers are closures that would otherwise be collected at once.
    signals.worker_init.connect(on_init, weak=False)
    signals.worker_ready.connect(on_ready, weak=False)
    signals.worker_shutdown.connect(on_shutdown, weak=False)
    signals.task_failure.connect(on_failure, weak=False)
    app._neudf_signal_handlers = (on_init, on_ready, on_shutdown, on_failure)  # type: ignore[attr-defined]

