"""The queue (``worker/celery_app.py``, ``worker/tasks.py``): a real Celery worker on the real Redis, a worker
SIGKILLed mid-job whose job finishes on a new worker without re-running its finished stages, a lost job sent
again once the broker is back, a pool process killed under a live worker (failed, not retried), and what
users read of an internal error. (The store's own claims: tests/test_store.py.)"""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.helpers import (
    QUICK_JOB,
    WorkerProcess,
    assert_monotonic_progress,
    assert_valid_glb,
    finished,
    free_port,
    neudf_env,
    new_job,
    postgres_schema,
    wait_job,
)
from worker.celery_app import create_celery
from worker.pipeline import STAGE_NAMES, completed_stages
from worker.settings import QueueSettings
from worker.store import JobStore
from worker.tasks import recover_stale_jobs


# -- real workers on the embedded broker and on the real Redis ------------------------------------------------
def _queue_stack(tmp_path: Path, broker_url: str | None) -> Iterator[dict[str, Any]]:
    """API in process, workers as processes. With Redis the store is PostgreSQL (SQLite without a server),
    as a scaled deployment has it; the embedded broker goes with SQLite, as `neudf serve` has it."""
    gen = None
    database_url = f"sqlite:///{tmp_path / 'jobs.db'}"
    if broker_url is not None:
        try:
            gen = postgres_schema()
            database_url = next(gen)
        except pytest.skip.Exception:
            gen = None
    data_dir = tmp_path / "data"
    extra = {"NEUDF_DATABASE_URL": database_url}
    if broker_url is not None:
        extra["NEUDF_BROKER_URL"] = broker_url
    env = neudf_env(data_dir, **extra)
    settings = Settings(data_dir=data_dir, broker_url=broker_url, database_url=database_url, heartbeat_s=1,
                        stale_after_s=5)
    workers: list[WorkerProcess] = []

    def start_worker() -> WorkerProcess:
        worker = WorkerProcess(env, tmp_path / f"worker{len(workers)}.log")
        workers.append(worker)
        return worker

    with TestClient(create_app(settings)) as client:
        try:
            yield {"client": client, "settings": settings, "start_worker": start_worker, "tmp": tmp_path}
        finally:
            for worker in workers:
                worker.stop()
            if gen is not None:
                gen.close()


@pytest.mark.redis
def test_lost_job_is_sent_again_once_the_broker_is_back(redis_db: str, tmp_path: Path) -> None:
    """A silent job stays silent (not queued without a message) while the broker refuses, and is sent once it is back."""
    import redis

    store_url = f"sqlite:///{tmp_path / 'jobs.db'}"
    down = QueueSettings(data_dir=tmp_path / "data", database_url=store_url, stale_after_s=1,
                         broker_url=f"redis://127.0.0.1:{free_port()}/0")
    store = JobStore(store_url)
    job_id = new_job(store)
    store.claim(job_id, "w1", stale_after_s=60)
    time.sleep(1.1)  # w1 went silent
    assert recover_stale_jobs(create_celery(down), store) == []
    assert store.get(job_id).state == "running"  # still the sweep's to find
    up = down.model_copy(update={"broker_url": redis_db})
    assert recover_stale_jobs(create_celery(up), store) == [job_id]
    assert store.get(job_id).state == "queued"
    assert redis.Redis.from_url(redis_db).llen(up.queue) == 1  # its message waits for a worker


@pytest.fixture
def embedded_stack(tmp_path: Path) -> Iterator[dict[str, Any]]:
    yield from _queue_stack(tmp_path, None)


@pytest.mark.slow
def test_killed_pool_process_fails_its_job(embedded_stack: dict[str, Any], tiny_video: Path) -> None:
    """The job process dies (as under the out-of-memory killer) while its worker lives: failed, not run again."""
    client = embedded_stack["client"]
    worker = embedded_stack["start_worker"]()
    _wait_worker(client)
    job_id = _upload(client, tiny_video)
    get = lambda: client.get(f"/api/jobs/{job_id}").json()  # noqa: E731
    job, _ = wait_job(get, lambda j: j["state"] == "running" or finished(j), poll_s=0.1)
    assert job["state"] == "running", job
    for child in psutil.Process(worker.process.pid).children(recursive=True):
        child.send_signal(signal.SIGKILL)
    job, _ = wait_job(get, finished, timeout_s=60)
    assert job["state"] == "failed" and "out-of-memory" in job["error"]["message"], job
    time.sleep(embedded_stack["settings"].stale_after_s + 3)  # past any re-delivery or stale sweep
    job = get()
    assert job["state"] == "failed" and job["attempts"] == 1, job
    assert worker.process.poll() is None  # the worker lives on


@pytest.mark.slow
def test_internal_errors_do_not_show_server_paths(embedded_stack: dict[str, Any], tiny_video: Path) -> None:
    client, settings = embedded_stack["client"], embedded_stack["settings"]
    job_id = _upload(client, tiny_video)
    (settings.job_dir(job_id) / "data").write_text("a file where the frames stage wants its folder")
    embedded_stack["start_worker"]()
    job, _ = wait_job(lambda: client.get(f"/api/jobs/{job_id}").json(), finished, timeout_s=120)
    assert job["state"] == "failed" and job["error"]["stage"] == "frames", job
    assert "internal error" in job["error"]["message"]
    shown = json.dumps(job)
    assert str(settings.root) not in shown and os.sep + "tmp" not in shown, shown


@pytest.fixture
def redis_stack(redis_db: str, tmp_path: Path) -> Iterator[dict[str, Any]]:
    yield from _queue_stack(tmp_path, redis_db)


@pytest.fixture(params=["embedded", pytest.param("redis", marks=pytest.mark.redis)])
def any_stack(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[dict[str, Any]]:
    """Both brokers: the embedded filesystem one and Redis."""
    if request.param == "redis":
        yield from _queue_stack(tmp_path, request.getfixturevalue("redis_db"))
    else:
        yield from _queue_stack(tmp_path, None)


def _wait_worker(client: TestClient, count: int = 1, timeout_s: float = 60) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        health = client.get("/api/health").json()
        if health["workers_alive"] >= count:
            return health
        time.sleep(0.3)
    raise TimeoutError(f"no worker came up: {health}")


def _upload(client: TestClient | httpx.Client, video: Path, **fields: str) -> str:
    response = client.post("/api/jobs", files={"file": ("orbit.mp4", video.read_bytes(), "video/mp4")},
                           data={**QUICK_JOB, **fields})
    assert response.status_code == 201, response.text
    return response.json()["id"]


@pytest.mark.redis
@pytest.mark.slow
def test_redis_worker_video_to_glb(redis_stack: dict[str, Any], tiny_video: Path) -> None:
    client = redis_stack["client"]
    redis_stack["start_worker"]()
    health = _wait_worker(client)
    assert health["status"] == "ok" and health["broker"]["url"].startswith("redis://")
    job_id = _upload(client, tiny_video)
    job, seen = wait_job(lambda: client.get(f"/api/jobs/{job_id}").json(), finished, poll_s=0.1)
    assert job["state"] == "succeeded", job["error"]
    assert_monotonic_progress(seen, list(STAGE_NAMES))
    assert all(s["runs"] == 1 for s in job["stages"]) and job["attempts"] == 1
    response = client.get(job["artifacts"]["mesh.glb"])
    assert response.status_code == 200
    assert_valid_glb(response.content)


@pytest.mark.slow
def test_killed_worker_job_resumes_on_a_new_worker(any_stack: dict[str, Any], tiny_video: Path) -> None:
    """SIGKILL the worker (and its pool process) during training; a new worker finishes the job, skipping
    the stages that had finished. (The embedded broker loses the message of a killed worker outright and
    Redis holds it until the visibility timeout: the store's stale heartbeat is what brings the job back.)"""
    client, settings = any_stack["client"], any_stack["settings"]
    first = any_stack["start_worker"]()
    _wait_worker(client)
    job_id = _upload(client, tiny_video)
    get = lambda: client.get(f"/api/jobs/{job_id}").json()  # noqa: E731
    job, _ = wait_job(get, lambda j: (j["stage"] == "train" and j["stages"][3]["progress"] > 0) or finished(j),
                      poll_s=0.1)
    assert job["state"] == "running", job
    before = completed_stages(settings.job_dir(job_id))
    assert set(before) == {"frames", "poses", "scene"}
    first.kill()

    time.sleep(1.0)
    assert get()["state"] == "running"  # nobody knows yet: the record waits for its heartbeat to go stale
    any_stack["start_worker"]()
    job, _ = wait_job(get, finished)
    assert job["state"] == "succeeded", job["error"]
    assert job["attempts"] == 2
    runs = {s["name"]: s["runs"] for s in job["stages"]}
    assert runs == {"frames": 1, "poses": 1, "scene": 1, "train": 2, "mesh": 1, "export": 1}, runs
    after = completed_stages(settings.job_dir(job_id))
    for name in ("frames", "poses", "scene"):  # the finished stages' markers are the very same
        assert after[name]["finished_at"] == before[name]["finished_at"]
    response = client.get(job["artifacts"]["mesh.glb"])
    assert_valid_glb(response.content)
