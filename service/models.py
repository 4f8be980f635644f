"""The API's JSON shapes (pydantic): what a client sends and gets back. Stored records stay in worker.store."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from worker.store import JobRecord

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


def _aware(value: datetime | None) -> datetime | None:
    """Stored times are naive UTC; say so on the way out."""
    return value.replace(tzinfo=UTC) if value is not None and value.tzinfo is None else value


class StagePublic(BaseModel):
    name: str
    state: Literal["pending", "running", "done", "failed", "cancelled"]
    progress: float = Field(description="0..1 of this stage")
    started_at: datetime | None
    finished_at: datetime | None
    seconds: float | None = Field(None, description="Run time of the stage's last run")
    runs: int = Field(description="How often the stage's work started (a resumed job does not run a finished stage again)")
    eta_s: float | None = None
    message: str = ""


class ErrorPublic(BaseModel):
    stage: str
    message: str


class JobPublic(BaseModel):
    id: str
    state: JobState
    stage: str | None = Field(description="The stage running now, or the last one that ran")
    progress: float = Field(description="0..1 overall, stages weighted by their usual share of the time")
    message: str
    stages: list[StagePublic]
    error: ErrorPublic | None
    eta_s: float | None = Field(None, description="Seconds until the whole job is done (the running stage's "
                                "estimate plus the expected time of the stages after it); while running")
    metrics: dict[str, Any]
    artifacts: dict[str, str] = Field(description="Artifact name -> URL")
    options: dict[str, Any]
    input: dict[str, Any] = Field(description="The uploaded video: name and bytes")
    attempts: int = Field(description="Deliveries to a worker (more than 1 after a lost worker)")
    cancel_requested: bool
    created_at: datetime
    updated_at: datetime

    @classmethod
    def of(cls, job: JobRecord, base: str = "") -> JobPublic:
        stages = []
        for st in job.stages:
            data = st.model_dump()
            data["started_at"], data["finished_at"] = _aware(st.started_at), _aware(st.finished_at)
            if data["state"] == "skipped":
                data["state"] = "done"
            stages.append(StagePublic(**data))
        left = [st.eta_s for st in job.stages if st.state not in ("done", "skipped")]
        eta = round(sum(e for e in left if e is not None), 1) if job.state == "running" and any(
            e is not None for e in left) else None
        return cls(
            id=job.id, state=job.state, stage=job.stage, progress=job.progress, message=job.message, eta_s=eta,
            stages=stages, error=ErrorPublic(**job.error) if job.error else None, metrics=job.metrics,
            artifacts={name: f"{base}/api/jobs/{job.id}/artifacts/{name}" for name in job.artifacts},
            options=job.options, input={"name": job.input_name, "bytes": job.input_bytes}, attempts=job.attempts,
            cancel_requested=job.cancel_requested, created_at=_aware(job.created_at),
            updated_at=_aware(job.updated_at),
        )


class JobList(BaseModel):
    items: list[JobPublic]
    total: int
    limit: int
    offset: int


class BrokerHealth(BaseModel):
    url: str = Field(description="The broker URL without credentials")
    embedded: bool
    reachable: bool
    error: str | None = None


class WorkerHealth(BaseModel):
    name: str
    hostname: str
    pid: int
    device: str
    last_seen: datetime


class HealthPublic(BaseModel):
    """What anyone may see: whether the service can take and run jobs (HTTP 200) or not (503)."""

    status: Literal["ok", "degraded"] = Field(description="ok: database and broker reachable and a worker alive")


class Health(HealthPublic):
    """The same with what is where: for a valid token, or anyone when tokens are off."""

    version: str
    database: dict[str, Any]
    broker: BrokerHealth
    workers: list[WorkerHealth]
    workers_alive: int
    jobs: dict[str, int] = Field(description="Job counts by state (the caller's own when tokens are on)")
    reasons: list[str] = Field(default_factory=list, description="Why the status is degraded")


class Live(BaseModel):
    status: Literal["ok"] = "ok"
