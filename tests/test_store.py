"""The job store (``worker/store.py``) on SQLite and PostgreSQL: a job is claimed once, a silent one is found
and queued again, a finished one never runs again, cancelling."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import new_job, postgres_schema
from worker.store import JobStore


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'jobs.db'}"
    else:
        yield from postgres_schema()


def test_store_claims_once_and_recovers_silent_jobs(store_url: str) -> None:
    store = JobStore(store_url)
    job_id = new_job(store)
    first = store.claim(job_id, "w1", stale_after_s=60)
    assert first is not None and first.state == "running" and first.attempts == 1
    assert store.claim(job_id, "w2", stale_after_s=60) is None  # a duplicate delivery while w1 is alive
    assert not store.report(job_id, "w1", stage="frames", progress=0.1, message="x")
    assert store.report(job_id, "w2", stage="frames", progress=0.2, message="x")  # not w2's job: stop
    time.sleep(1.1)
    assert [j.id for j in store.stale_running(stale_after_s=1)] == [job_id]
    assert store.requeue_stale(job_id, stale_after_s=1) and not store.requeue_stale(job_id, stale_after_s=1)
    second = store.claim(job_id, "w2", stale_after_s=60)
    assert second is not None and second.attempts == 2 and second.worker == "w2"
    assert not store.finish(job_id, "w1", "succeeded")  # w1 lost it
    assert store.finish(job_id, "w2", "succeeded") and store.get(job_id).state == "succeeded"
    assert store.claim(job_id, "w3", stale_after_s=0) is None  # finished jobs are never run again


def test_store_cancel(store_url: str) -> None:
    store = JobStore(store_url)
    queued, running = new_job(store), new_job(store)
    assert store.request_cancel(queued) == "cancelled"
    assert store.claim(queued, "w1", 60) is None
    store.claim(running, "w1", 60)
    assert store.request_cancel(running) == "running"
    assert store.report(running, "w1", stage="train", progress=0.5, message="x")  # the flag reaches the worker
    assert store.request_cancel(uuid.uuid4().hex) is None
    assert not store.delete(running)
    store.finish(running, "w1", "cancelled")
    assert store.delete(running) and store.get(running) is None
