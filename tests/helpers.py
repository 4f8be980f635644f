"""What the service and queue tests share: job options, real servers and workers as processes, polling.

Nothing here is mocked: `neudf serve` and `neudf worker` run as child processes (each in its own process
group, so a test can SIGKILL a whole worker), the broker is the embedded filesystem one or the real Redis
at 127.0.0.1:6379 (database 13 only, flushed before and after), the store is SQLite or PostgreSQL.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import pytest

if TYPE_CHECKING:
    import typer

    from worker.store import JobStore

ROOT = Path(__file__).resolve().parents[1]
REDIS_URL = "redis://127.0.0.1:6379/13"  # a database of its own: the tests flush only this one
POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
ARTIFACTS = Path(__file__).parent / "artifacts"

# Options that keep a whole job to seconds on 2 CPU cores. Ten iterations of the quick preset leave the
# UDF's minimum around 0.1 (unit sphere), above the default meshing threshold of about a voxel, and what
# meshes is a few dozen faces near that minimum: hence the explicit threshold and no small-piece filter.
# No culling by the cameras either (mesh_min_seen 0): those fragments lie anywhere, and in one full run of
# four on 2026-12-03 no camera saw any of them ("no face is seen by 5% of the 17 cameras").
# (A real surface needs hundreds of iterations; these tests check the plumbing, not the quality.)
# A small texture keeps the export stage's bake to a second.
QUICK_JOB = {"preset": "quick", "iters": "10", "frames": "30", "mesh_resolution": "64", "mesh_threshold": "0.25",
             "mesh_min_faces": "1", "mesh_min_seen": "0", "texture_size": "256"}
# Fast liveness: a killed worker's job is queued again after a few seconds.
FAST_LIVENESS = {"NEUDF_HEARTBEAT_S": "1", "NEUDF_STALE_AFTER_S": "5", "NEUDF_PROGRESS_INTERVAL_S": "0.2"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def neudf_env(data_dir: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NEUDF_")}
    env.update(FAST_LIVENESS)
    env.update({"NEUDF_DATA_DIR": str(data_dir), "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "2"})
    env.update(extra)
    return env


def _stop_group(process: subprocess.Popen, wait_s: float = 20) -> None:
    """SIGTERM to the leader (a warm shutdown stops its own children), then SIGKILL to what is left."""
    if process.poll() is None:
        try:
            process.terminate()
            process.wait(wait_s)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass
    try:
        os.killpg(process.pid, signal.SIGKILL)  # pool children that outlived their parent
    except ProcessLookupError:
        pass


class WorkerProcess:
    """`neudf worker` as a child process group."""

    def __init__(self, env: dict[str, str], log: Path) -> None:
        self.log = log
        with open(log, "ab") as fh:
            self.process = subprocess.Popen([sys.executable, "-m", "worker.cli", "worker"], cwd=ROOT, env=env,
                                            stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)

    def kill(self) -> None:
        """SIGKILL the worker and its pool process at once, as a crashed machine would."""
        os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait(10)

    def stop(self) -> None:
        _stop_group(self.process)


class ServeProcess:
    """`neudf serve` (API + page + embedded worker, unless ``worker=False``) as a child process group."""

    def __init__(self, data_dir: Path, log: Path, *, worker: bool = True, port: int | None = None, **env: str) -> None:
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.data_dir = data_dir
        self.worker = worker
        command = [sys.executable, "-m", "web.cli", "serve", "--port", str(self.port), "--data-dir", str(data_dir)]
        with open(log, "ab") as fh:
            self.process = subprocess.Popen(command + ([] if worker else ["--no-worker"]), cwd=ROOT,
                                            env=neudf_env(data_dir, **env), stdout=fh, stderr=subprocess.STDOUT,
                                            start_new_session=True)
        self.log = log

    def log_tails(self, chars: int = 3000) -> str:
        """The ends of the server's and its worker's logs, for a failing test's message."""
        tails = []
        for path in (self.log, self.data_dir / "worker.log"):
            text = path.read_text(errors="replace")[-chars:] if path.is_file() else "(none)"
            tails.append(f"--- {path.name}:\n{text}")
        return "\n".join(tails)

    def wait_ready(self, timeout_s: float = 120) -> None:
        """Until the API answers and, with a worker, health says ok (it has reported in)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"neudf serve exited: {self.log.read_text()[-3000:]}")
            try:
                response = httpx.get(f"{self.url}/api/health", timeout=5)
                if not self.worker or response.json()["status"] == "ok":
                    return
            except (httpx.HTTPError, ValueError, KeyError):
                pass
            time.sleep(0.5)
        raise TimeoutError(f"neudf serve not ready: {self.log.read_text()[-3000:]}")

    def stop(self) -> None:
        _stop_group(self.process)


def wait_job(get: Callable[[], dict[str, Any]], until: Callable[[dict[str, Any]], bool], timeout_s: float = 300,
             poll_s: float = 0.25) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Poll a job until ``until(job)``; returns the last job and every snapshot seen."""
    seen: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = get()
        seen.append(job)
        if until(job):
            return job, seen
        time.sleep(poll_s)
    raise TimeoutError(f"job never reached the condition; last: {seen[-1] if seen else None}")


def finished(job: dict[str, Any]) -> bool:
    return job["state"] in ("succeeded", "failed", "cancelled")


def assert_monotonic_progress(snapshots: list[dict[str, Any]], stage_names: list[str]) -> None:
    """Overall progress never goes back, and the current stage only moves forward through the stages."""
    values = [s["progress"] for s in snapshots]
    assert all(b >= a for a, b in zip(values, values[1:])), f"progress went back: {values}"
    order = [stage_names.index(s["stage"]) for s in snapshots if s["stage"] is not None]
    assert all(b >= a for a, b in zip(order, order[1:])), f"stages went back: {order}"
    for s in snapshots:  # per stage too
        for stage in s["stages"]:
            assert 0.0 <= stage["progress"] <= 1.0
    assert len(set(values)) >= 3, f"progress hardly moved: {sorted(set(values))}"


def assert_valid_glb(data: bytes) -> Any:
    """A GLB trimesh reads back as a mesh with faces and vertex colours."""
    import io

    import trimesh

    assert data[:4] == b"glTF", "not a binary glTF"
    scene = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    mesh = scene.to_mesh() if hasattr(scene, "to_mesh") else scene
    assert len(mesh.faces) > 0
    return mesh


# -- the job store ---------------------------------------------------------------------------------------------
def postgres_schema() -> Iterator[str]:
    """A PostgreSQL URL whose tables live in a fresh schema, dropped afterwards; skip without a server."""
    import sqlalchemy as sa

    engine = sa.create_engine(POSTGRES_URL)
    schema = f"neudf_test_{uuid.uuid4().hex[:8]}"
    try:
        with engine.begin() as conn:
            conn.execute(sa.text(f"CREATE SCHEMA {schema}"))
    except sa.exc.OperationalError:
        pytest.skip("no PostgreSQL server at 127.0.0.1:5432")
    try:
        yield f"{POSTGRES_URL}?options=-csearch_path%3D{schema}"
    finally:
        with engine.begin() as conn:
            conn.execute(sa.text(f"DROP SCHEMA {schema} CASCADE"))
        engine.dispose()


def new_job(store: JobStore) -> str:
    """A queued job record (no folder, no message)."""
    from worker.pipeline import STAGE_NAMES

    job_id = uuid.uuid4().hex
    store.create(job_id=job_id, owner=None, stages=list(STAGE_NAMES), options={}, input_name="v.mp4", input_bytes=1)
    return job_id


# -- the command line -------------------------------------------------------------------------------------------
def worker_cli_app() -> typer.Typer:
    """A typer app with the worker layer's commands (capture, reconstruct, worker), for CliRunner."""
    import typer

    from worker.cli import register

    app = typer.Typer()

    @app.callback()
    def main() -> None:  # a callback keeps `capture` a subcommand, as in the real `neudf` app
        """neudf (test app)"""

    register(app)
    return app
