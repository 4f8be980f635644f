"""What the API and the workers must agree on: ``QueueSettings``, read from ``NEUDF_*`` environment variables.

The service's ``Settings`` (service/settings.py) extends it with what only the API needs; a worker reads
this one alone. Nothing is read at import time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from neudf_core.device import resolve_device

__all__ = ["QueueSettings"]


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
        return resolve_device(self.device)  # torch is imported only when it is called: the API never calls it
