"""The job store: one SQL table of jobs (plus one of workers), the single source of truth for a job.

The API writes a job when it accepts an upload and reads it for every request; workers on any machine
claim a job, write its progress as it happens and its end. SQLite under the data folder by default, any
SQLAlchemy URL (PostgreSQL, ...) to share it between machines.

Every state change is one conditional UPDATE (``... WHERE state = 'queued'``), so two workers, or a
worker and a cancelling user, never both win. On SQLite (in WAL mode) a writing transaction starts with
BEGIN IMMEDIATE: a deferred transaction that reads and then writes can fail at once on a busy database
instead of waiting, and we would rather wait. A reading transaction stays deferred: it reads a snapshot
and never waits behind a writer, so a page polling its job is never held up by a worker's progress write.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from datetime import UTC, datetime, timedelta
from typing import Any

from pydantic import BaseModel
from sqlalchemy import JSON, Boolean, DateTime, Float, Integer, String, create_engine, event, func, select, update
from sqlalchemy.engine import Engine
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

FINISHED_STATES = ("succeeded", "failed", "cancelled")


def utcnow() -> datetime:
    """Naive UTC: the one form SQLite and PostgreSQL compare alike."""
    return datetime.now(UTC).replace(tzinfo=None)


class Base(DeclarativeBase):
    pass


class JobRow(Base):
    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str | None] = mapped_column(String(64), index=True)
    state: Mapped[str] = mapped_column(String(16), index=True)
    stage: Mapped[str | None] = mapped_column(String(32))
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str] = mapped_column(String(500), default="")
    stages: Mapped[list[dict[str, Any]]] = mapped_column(JSON)
    error: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    metrics: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    artifacts: Mapped[list[str]] = mapped_column(JSON, default=list)
    options: Mapped[dict[str, Any]] = mapped_column(JSON)
    input_name: Mapped[str] = mapped_column(String(255))
    input_bytes: Mapped[int] = mapped_column(Integer, default=0)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    worker: Mapped[str | None] = mapped_column(String(128))
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime)
    created_at: Mapped[datetime] = mapped_column(DateTime, index=True)
    updated_at: Mapped[datetime] = mapped_column(DateTime)


class WorkerRow(Base):
    __tablename__ = "workers"

    name: Mapped[str] = mapped_column(String(128), primary_key=True)
    hostname: Mapped[str] = mapped_column(String(128))
    pid: Mapped[int] = mapped_column(Integer)
    device: Mapped[str] = mapped_column(String(32))
    started_at: Mapped[datetime] = mapped_column(DateTime)
    last_seen: Mapped[datetime] = mapped_column(DateTime, index=True)


class StageRecord(BaseModel):
    name: str
    state: str = "pending"  # pending, running, done, skipped, failed, cancelled
    progress: float = 0.0
    started_at: datetime | None = None
    finished_at: datetime | None = None
    seconds: float | None = None
    runs: int = 0  # how many times this stage's work was started (a resumed job does not re-run it)
    message: str = ""
    eta_s: float | None = None


class JobRecord(BaseModel):
    """A snapshot of one job as stored."""

    id: str
    owner: str | None
    state: str
    stage: str | None
    progress: float
    message: str
    stages: list[StageRecord]
    error: dict[str, Any] | None
    metrics: dict[str, Any]
    artifacts: list[str]
    options: dict[str, Any]
    input_name: str
    input_bytes: int
    cancel_requested: bool
    worker: str | None
    attempts: int
    heartbeat_at: datetime | None
    created_at: datetime
    updated_at: datetime

    @classmethod
    def of(cls, row: JobRow) -> JobRecord:
        data = {c: getattr(row, c) for c in cls.model_fields if c != "stages"}
        return cls(stages=[StageRecord.model_validate(s) for s in row.stages], **data)

    @property
    def finished(self) -> bool:
        return self.state in FINISHED_STATES


class WorkerRecord(BaseModel):
    name: str
    hostname: str
    pid: int
    device: str
    started_at: datetime
    last_seen: datetime


_WRITE = "neudf_write"  # execution option of the engine that opens writing transactions


def _sqlite_transactions(engine: Engine, busy_timeout_s: float) -> None:
    @event.listens_for(engine, "connect")
    def _connect(dbapi_connection, _record) -> None:  # type: ignore[no-untyped-def]
        dbapi_connection.isolation_level = None  # let us emit BEGIN ourselves
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")  # readers never block the writer
        cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_s * 1000)}")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _begin(conn) -> None:  # type: ignore[no-untyped-def]
        conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get(_WRITE) else "BEGIN")


class JobStore:
    """Job records in a SQL database. Safe to use from several processes; make one per process.

    ``busy_timeout_s``: how long a write waits for another writer's lock before it fails (SQLite).
    """

    def __init__(self, url: str, *, busy_timeout_s: float = 30.0) -> None:
        self.url = url
        self.busy_timeout_s = busy_timeout_s
        self._pid = os.getpid()
        self._engine = self._make_engine()

    def _make_engine(self) -> Engine:
        if self.url.startswith("sqlite"):
            engine = create_engine(self.url, connect_args={"timeout": self.busy_timeout_s,
                                                           "check_same_thread": False})
            _sqlite_transactions(engine, self.busy_timeout_s)
        else:
            engine = create_engine(self.url, pool_pre_ping=True)
        try:
            Base.metadata.create_all(engine)
        except DBAPIError:  # another process created the tables between our check and our CREATE
            Base.metadata.create_all(engine)
        return engine

    @property
    def engine(self) -> Engine:
        if os.getpid() != self._pid:  # a forked worker child must not share its parent's connections
            self._engine.dispose(close=False)
            self._pid = os.getpid()
            self._engine = self._make_engine()
        return self._engine

    @contextmanager
    def session(self, *, write: bool = True) -> Iterator[Session]:
        """One transaction; ``write=False`` for one that only reads (it never waits for a writer)."""
        engine = self.engine.execution_options(**{_WRITE: True}) if write else self.engine
        with sessionmaker(engine, expire_on_commit=False).begin() as session:
            yield session

    def reading(self) -> AbstractContextManager[Session]:
        return self.session(write=False)

    def ping(self) -> None:
        with self.reading() as s:
            s.execute(select(1))

    # -- the API's side -------------------------------------------------------------------------------
    def create(self, *, job_id: str, owner: str | None, stages: list[str], options: dict[str, Any],
               input_name: str, input_bytes: int) -> JobRecord:
        now = utcnow()
        row = JobRow(id=job_id, owner=owner, state="queued", stage=None, progress=0.0, message="queued",
                     stages=[StageRecord(name=n).model_dump(mode="json") for n in stages], error=None,
                     metrics={}, artifacts=[], options=options, input_name=input_name, input_bytes=input_bytes,
                     cancel_requested=False, worker=None, attempts=0, heartbeat_at=None,
                     created_at=now, updated_at=now)
        with self.session() as s:
            s.add(row)
            s.flush()
            return JobRecord.of(row)

    def get(self, job_id: str) -> JobRecord | None:
        with self.reading() as s:
            row = s.get(JobRow, job_id)
            return JobRecord.of(row) if row else None

    def list(self, *, owner: str | None = None, any_owner: bool = True, limit: int = 20,
             offset: int = 0) -> tuple[list[JobRecord], int]:
        """Newest first. With ``any_owner=False`` only the jobs of ``owner``."""
        query = select(JobRow)
        count = select(func.count()).select_from(JobRow)
        if not any_owner:
            query = query.where(JobRow.owner == owner)
            count = count.where(JobRow.owner == owner)
        query = query.order_by(JobRow.created_at.desc(), JobRow.id.desc()).limit(limit).offset(offset)
        with self.reading() as s:
            rows = s.scalars(query).all()
            return [JobRecord.of(r) for r in rows], int(s.scalar(count) or 0)

    def request_cancel(self, job_id: str) -> str | None:
        """Cancel a queued job at once, flag a running one. The job's state after, None if unknown."""
        now = utcnow()
        with self.session() as s:
            done = s.execute(update(JobRow).where(JobRow.id == job_id, JobRow.state == "queued").values(
                state="cancelled", cancel_requested=True, message="cancelled before it started", updated_at=now))
            if done.rowcount:
                return "cancelled"
            s.execute(update(JobRow).where(JobRow.id == job_id, JobRow.state == "running").values(
                cancel_requested=True, updated_at=now))
            row = s.get(JobRow, job_id)
            return row.state if row else None

    def delete(self, job_id: str) -> bool:
        """Remove a finished job's record; False when it is not finished (or gone)."""
        with self.session() as s:
            row = s.get(JobRow, job_id, with_for_update=True)
            if row is None or row.state not in FINISHED_STATES:
                return False
            s.delete(row)
            return True

    def discard(self, job_id: str) -> None:
        """Remove a job whatever its state (an upload whose enqueue failed)."""
        with self.session() as s:
            row = s.get(JobRow, job_id)
            if row is not None:
                s.delete(row)

    # -- the worker's side ----------------------------------------------------------------------------
    def claim(self, job_id: str, worker: str, stale_after_s: float) -> JobRecord | None:
        """Take a queued job, or a running one whose process went silent. None when not ours to run."""
        now = utcnow()
        cutoff = now - timedelta(seconds=stale_after_s)
        with self.session() as s:
            done = s.execute(
                update(JobRow)
                .where(JobRow.id == job_id)
                .where((JobRow.state == "queued") | ((JobRow.state == "running") & (JobRow.heartbeat_at < cutoff)))
                .values(state="running", worker=worker, heartbeat_at=now, updated_at=now,
                        attempts=JobRow.attempts + 1, message="started")
            )
            if not done.rowcount:
                return None
            return JobRecord.of(s.get(JobRow, job_id))

    def heartbeat(self, job_id: str, worker: str | None = None) -> None:
        query = update(JobRow).where(JobRow.id == job_id, JobRow.state == "running")
        if worker is not None:
            query = query.where(JobRow.worker == worker)
        with self.session() as s:
            s.execute(query.values(heartbeat_at=utcnow()))

    def report(self, job_id: str, worker: str, *, stage: str | None, progress: float, message: str,
               stage_update: dict[str, Any] | None = None, metrics: dict[str, Any] | None = None,
               artifacts: list[str] | None = None) -> bool:
        """Write progress of a job this worker runs. Returns whether the user asked to cancel it."""
        now = utcnow()
        with self.session() as s:
            row = s.get(JobRow, job_id, with_for_update=True)
            if row is None or row.worker != worker or row.state != "running":
                return True  # deleted, or taken over by another worker: stop
            row.stage, row.progress, row.message = stage, progress, message[:500]
            row.heartbeat_at = row.updated_at = now
            if stage_update and stage:
                row.stages = [({**st, **stage_update} if st["name"] == stage else st) for st in row.stages]
            if metrics:
                row.metrics = {**row.metrics, **metrics}
            if artifacts is not None:
                row.artifacts = sorted(set(artifacts))
            return row.cancel_requested

    def update_stage(self, job_id: str, worker: str, stage_update: dict[str, Any]) -> None:
        """Write one stage's record (``stage_update["name"]``) of a job this worker runs, nothing else."""
        with self.session() as s:
            row = s.get(JobRow, job_id, with_for_update=True)
            if row is None or row.worker != worker or row.state != "running":
                return
            row.stages = [({**st, **stage_update} if st["name"] == stage_update["name"] else st) for st in row.stages]

    def finish(self, job_id: str, worker: str | None, state: str, *, message: str = "",
               error: dict[str, Any] | None = None, metrics: dict[str, Any] | None = None,
               artifacts: list[str] | None = None, stage_state: str | None = None) -> bool:
        """Record the end of a job. With ``worker`` given, only when that worker still holds it."""
        assert state in FINISHED_STATES
        now = utcnow()
        with self.session() as s:
            row = s.get(JobRow, job_id, with_for_update=True)
            if row is None or (worker is not None and row.worker != worker) or row.state in FINISHED_STATES:
                return False
            row.state, row.message, row.updated_at, row.heartbeat_at = state, message[:500], now, now
            row.error = error
            if state == "succeeded":
                row.progress = 1.0
            if metrics:
                row.metrics = {**row.metrics, **metrics}
            if artifacts is not None:
                row.artifacts = sorted(set(artifacts))
            if stage_state:  # the stage that was running ends with the job
                row.stages = [({**st, "state": stage_state, "finished_at": now.isoformat()}
                               if st["state"] == "running" else st) for st in row.stages]
            return True

    def stale_running(self, stale_after_s: float) -> list[JobRecord]:
        cutoff = utcnow() - timedelta(seconds=stale_after_s)
        with self.reading() as s:
            rows = s.scalars(select(JobRow).where(JobRow.state == "running", JobRow.heartbeat_at < cutoff)).all()
            return [JobRecord.of(r) for r in rows]

    def requeue_stale(self, job_id: str, stale_after_s: float) -> bool:
        """Put a silent running job back to queued; True for the one caller that did it."""
        now = utcnow()
        cutoff = now - timedelta(seconds=stale_after_s)
        with self.session() as s:
            done = s.execute(update(JobRow).where(JobRow.id == job_id, JobRow.state == "running",
                                                  JobRow.heartbeat_at < cutoff).values(
                state="queued", worker=None, updated_at=now, message="worker lost; queued again"))
            return bool(done.rowcount)

    def queued_ids(self) -> list[str]:
        with self.reading() as s:
            return list(s.scalars(select(JobRow.id).where(JobRow.state == "queued").order_by(JobRow.created_at)))

    def counts(self, *, owner: str | None = None, any_owner: bool = True) -> dict[str, int]:
        """Jobs by state; with ``any_owner=False`` only those of ``owner``."""
        query = select(JobRow.state, func.count()).group_by(JobRow.state)
        if not any_owner:
            query = query.where(JobRow.owner == owner)
        with self.reading() as s:
            return {state: int(n) for state, n in s.execute(query).all()}

    def rename_owner(self, old: str, new: str) -> int:
        """Give the jobs of owner key ``old`` to ``new`` (a changed way of deriving keys); how many moved."""
        with self.session() as s:
            return s.execute(update(JobRow).where(JobRow.owner == old).values(owner=new)).rowcount

    # -- workers --------------------------------------------------------------------------------------
    def worker_beat(self, name: str, hostname: str, pid: int, device: str) -> None:
        now = utcnow()
        with self.session() as s:
            row = s.get(WorkerRow, name)
            if row is None:
                s.add(WorkerRow(name=name, hostname=hostname, pid=pid, device=device, started_at=now, last_seen=now))
            else:
                row.last_seen = now

    def worker_gone(self, name: str) -> None:
        with self.session() as s:
            row = s.get(WorkerRow, name)
            if row is not None:
                s.delete(row)

    def workers(self, seen_within_s: float) -> list[WorkerRecord]:
        cutoff = utcnow() - timedelta(seconds=seen_within_s)
        with self.reading() as s:
            rows = s.scalars(select(WorkerRow).where(WorkerRow.last_seen >= cutoff).order_by(WorkerRow.name)).all()
            return [WorkerRecord.model_validate(r, from_attributes=True) for r in rows]
