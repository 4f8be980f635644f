"""Abuse of the running service, probed over 127.0.0.1 as an outsider would: `neudf serve` with tokens on.

Each probe must be answered with a 4xx or 503 and a JSON reason, the server must keep answering
/api/health within a second throughout, and no file may be left outside a live job. The page (Gradio)
gets the same scrutiny as the API: tokens, the files its inputs name, the files it hands out.
"""

from __future__ import annotations

import hashlib
import os
import signal
import sqlite3
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest

from tests.helpers import QUICK_JOB, ServeProcess, finished, wait_job

ALICE = {"Authorization": "Bearer alice-token"}
BOB = {"Authorization": "Bearer bob-token"}
FILE_META = {"_type": "gradio.FileData"}


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServeProcess]:
    """`neudf serve` with two tokens, a 1 MB upload limit, a Gradio folder of its own and no worker (no job runs)."""
    base = tmp_path_factory.mktemp("guarded")
    server = ServeProcess(base / "data", base / "serve.log", worker=False, NEUDF_AUTH_TOKENS="alice-token,bob-token",
                          NEUDF_MAX_UPLOAD_MB="1", GRADIO_TEMP_DIR=str(base / "gradio"))
    server.gradio_dir = base / "gradio"  # type: ignore[attr-defined]
    try:
        server.wait_ready()
        yield server
    finally:
        server.stop()


def upload(client: httpx.Client, video: Path, headers: dict[str, str] | None = None, **fields: str) -> httpx.Response:
    return client.post("/api/jobs", files={"file": ("orbit.mp4", video.read_bytes(), "video/mp4")}, data=fields,
                       headers=headers)


def assert_json_refusal(response: httpx.Response, *statuses: int) -> dict[str, Any]:
    assert response.status_code in statuses, (response.status_code, response.text[:300])
    assert response.headers["content-type"].startswith("application/json"), response.headers
    body = response.json()
    assert isinstance(body["detail"], str) and body["detail"], body
    return body


@contextmanager
def write_lock(db: Path) -> Iterator[None]:
    """Hold the job store's write lock, as a long writer would."""
    conn = sqlite3.connect(db, timeout=5, isolation_level=None)
    try:
        conn.execute("BEGIN IMMEDIATE")
        yield
    finally:
        conn.execute("ROLLBACK")
        conn.close()


class HealthWatch:
    """Polls /api/health in a thread; every answer's status and seconds."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.samples: list[tuple[float, int | str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=5) as client:
            while not self._stop.is_set():
                t0 = time.monotonic()
                try:
                    response = client.get("/api/health")
                    status: int | str = response.status_code if response.json().get("status") else "no status"
                except (httpx.HTTPError, ValueError) as exc:
                    status = type(exc).__name__
                self.samples.append((time.monotonic() - t0, status))
                self._stop.wait(0.2)

    def __enter__(self) -> HealthWatch:
        self._thread.start()
        return self

    def __exit__(self, *_: Any) -> None:
        self._stop.set()
        self._thread.join(10)

    def assert_answered(self) -> None:
        assert len(self.samples) >= 5, self.samples
        slow = [s for s in self.samples if s[0] >= 1.0 or s[1] not in (200, 503)]
        assert not slow, f"/api/health was slow or failed: {slow}"


def page_call(client: httpx.Client, path: str, headers: dict[str, str] | None = None) -> httpx.Response:
    """Ask the page's submit handler to take a server file, the way an API client of Gradio would."""
    data = [{"path": path, "meta": FILE_META}, "quick", None, None, None, None, None, None, None, None, None]
    return client.post("/gradio_api/call/submit", json={"data": data}, headers=headers)


def release_fifo(fifo: Path) -> None:
    """Open the FIFO's write end and close it, so a reader blocked on it (a server without the fix) goes on."""
    try:
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    except OSError:
        pass


def leftovers(server: ServeProcess) -> list[str]:
    """Files outside a live job: job folders without a record, staged uploads, files in the page's upload folder."""
    db = sqlite3.connect(server.data_dir / "jobs.db")
    live = {row[0] for row in db.execute("SELECT id FROM jobs")}
    db.close()
    jobs = server.data_dir / "jobs"
    orphans = [str(p) for p in jobs.glob("*") if p.name not in live] if jobs.is_dir() else []
    staged = [str(p) for p in (server.data_dir / "uploads").rglob("*") if p.is_file()]
    page = [str(p) for p in server.gradio_dir.rglob("*") if p.is_file()]  # type: ignore[attr-defined]
    return orphans + staged + page


def test_abuse_battery(guarded: ServeProcess, tiny_video: Path, tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    secret = tmp_path / "secret.txt"
    secret.write_text("not for the page\n")
    with HealthWatch(guarded.url) as watch, httpx.Client(base_url=guarded.url, timeout=30) as client:
        try:
            # Server paths through the page's file input: devices, FIFOs, any file; with a token or without.
            for path in (str(fifo), "/dev/zero", str(secret), str(guarded.data_dir / "jobs.db")):
                assert_json_refusal(page_call(client, path), 401)
                body = assert_json_refusal(page_call(client, path, ALICE), 400)
                assert "uploaded through" in body["detail"]
            join = {"data": [{"path": str(fifo), "meta": FILE_META}], "fn_index": 0, "session_hash": "abc123"}
            assert_json_refusal(client.post("/gradio_api/queue/join", json=join, headers=ALICE), 400)
        finally:
            release_fifo(fifo)

        # Anonymous upload to the page: 401, nothing kept.
        response = client.post("/gradio_api/upload", files={"files": ("v.mp4", tiny_video.read_bytes(), "video/mp4")})
        assert_json_refusal(response, 401)

        # A chunked body of small fields past the limit: 413 and a short answer, not an echo of the fields.
        def flood() -> Iterator[bytes]:
            for i in range(30_000):  # ~3 MB against a 1 MB limit
                yield (f"--b\r\nContent-Disposition: form-data; name=\"f{i}\"\r\n\r\n" + "x" * 40 + "\r\n").encode()
            yield b"--b--\r\n"

        response = client.post("/api/jobs", content=flood(), headers={**ALICE, "Content-Type": "multipart/form-data; boundary=b"})
        assert_json_refusal(response, 413)
        assert len(response.content) < 1000
        many = "".join(f"--b\r\nContent-Disposition: form-data; name=\"f{i}\"\r\n\r\nx\r\n" for i in range(200)) + "--b--\r\n"
        response = client.post("/api/jobs", content=many.encode(),
                               headers={**ALICE, "Content-Type": "multipart/form-data; boundary=b"})
        assert_json_refusal(response, 413)
        assert len(response.content) < 1000

        # Malformed multipart bodies: 400 with a reason, no traceback.
        for body in (b"garbage that is not multipart at all", b"--b\r\nContent-Disposition: form-data; name=\"file\"; "
                     b"filename=\"v.mp4\"\r\n\r\nhalf a video"):
            response = client.post("/api/jobs", content=body,
                                   headers={**ALICE, "Content-Type": "multipart/form-data; boundary=b"})
            assert "Traceback" not in assert_json_refusal(response, 400)["detail"]

        # A huge offset: 422 naming the parameter.
        response = client.get("/api/jobs", params={"offset": str(2**63)}, headers=ALICE)
        assert "offset" in assert_json_refusal(response, 422)["detail"]

        # The job store's write lock held while a video arrives: 503, and the upload leaves nothing behind.
        with write_lock(guarded.data_dir / "jobs.db"):
            response = upload(client, tiny_video, ALICE)
            assert "job store" in assert_json_refusal(response, 503)["detail"]
            assert response.headers.get("retry-after")
    watch.assert_answered()
    assert leftovers(guarded) == []


def test_page_needs_a_valid_token(guarded: ServeProcess, tiny_video: Path) -> None:
    """No page route or page file answers without a valid token; /login keeps one in a cookie."""
    # Wrong tokens from an address of their own (127.0.0.3): they count towards its rate limit.
    wrong = httpx.Client(base_url=guarded.url, timeout=30, transport=httpx.HTTPTransport(local_address="127.0.0.3"),
                         headers={"Authorization": "Bearer wrong"})
    with wrong, httpx.Client(base_url=guarded.url, timeout=30) as client:
        for path in ("/", "/config", "/gradio_api/info", "/theme.css", "/gradio_api/app_id", "/gradio_api/user",
                     f"/gradio_api/file={guarded.data_dir / 'jobs.db'}", "/monitoring/x", "/assets/index.js"):
            assert_json_refusal(client.get(path), 401)
            assert_json_refusal(wrong.get(path), 401)
        response = client.get("/", headers={"Accept": "text/html"})
        assert response.status_code == 303 and response.headers["location"] == "/login"
        assert client.get("/login").status_code == 200
        assert client.post("/login", data={"token": "wrong"}).status_code == 401
        response = client.post("/login", data={"token": "alice-token"})
        assert response.status_code == 303 and "httponly" in response.headers["set-cookie"].lower()
        assert client.get("/", headers={"Accept": "text/html"}).status_code == 200  # the cookie now
        assert client.get("/config").status_code == 200


def test_page_files_follow_their_job(guarded: ServeProcess, tiny_video: Path) -> None:
    """A file the page shows is served to its job's owner only, from the job's folder: gone with the job."""
    from gradio_client import Client, handle_file

    page = Client(guarded.url, headers=ALICE, verbose=False, download_files=False, analytics_enabled=False)
    notice = page.predict(handle_file(str(tiny_video)), "quick", None, None, None, None, None, None, None, None, 256,
                          api_name="/submit")
    assert "queued" in str(notice)
    with httpx.Client(base_url=guarded.url, timeout=30, headers=ALICE) as client:
        job_id = client.get("/api/jobs").json()["items"][0]["id"]
        export = guarded.data_dir / "jobs" / job_id / "export"
        export.mkdir(parents=True)
        (export / "mesh.glb").write_bytes(b"glTF mesh of alice")
        (export / "metrics.json").write_text("{}")
        (guarded.data_dir / "jobs" / job_id / "stages").mkdir()
        (guarded.data_dir / "jobs" / job_id / "stages" / "export.json").write_text("{}")
        outputs = page.predict(api_name="/refresh")
        urls = [o["url"] for o in outputs if isinstance(o, dict) and str(o.get("path", "")).endswith("mesh.glb")]
        assert urls, outputs
        url = urls[0]
        assert_json_refusal(httpx.get(url), 401)
        assert_json_refusal(httpx.get(url, headers=BOB), 404)
        assert httpx.get(url, headers=ALICE).content == b"glTF mesh of alice"
        assert client.post(f"/api/jobs/{job_id}/cancel").status_code == 200
        assert client.delete(f"/api/jobs/{job_id}").status_code == 204
        assert_json_refusal(httpx.get(url, headers=ALICE), 404)
    assert leftovers(guarded) == []


def test_reads_do_not_wait_behind_a_writer(guarded: ServeProcess, tiny_video: Path) -> None:
    with httpx.Client(base_url=guarded.url, timeout=10, headers=ALICE) as client:
        response = upload(client, tiny_video)
        assert response.status_code == 201, response.text
        job_id = response.json()["id"]
        with write_lock(guarded.data_dir / "jobs.db"):
            assert client.get(f"/api/jobs/{job_id}").json()["state"] == "queued"
            assert client.get("/api/jobs").json()["total"] >= 1
        assert client.post(f"/api/jobs/{job_id}/cancel").status_code == 200


def test_artifacts_are_served_only_whole(guarded: ServeProcess, tiny_video: Path) -> None:
    """An export file is served once the export stage has finished; a growing log only up to its last line."""
    with httpx.Client(base_url=guarded.url, timeout=30, headers=ALICE) as client:
        response = upload(client, tiny_video)
        assert response.status_code == 201, response.text
        job_id = response.json()["id"]
        job_dir = guarded.data_dir / "jobs" / job_id
        (job_dir / "export").mkdir()
        (job_dir / "export" / "mesh.glb").write_bytes(b"glTF half a me")  # being written
        (job_dir / "run").mkdir()
        (job_dir / "run" / "metrics.jsonl").write_text('{"iter": 1}\n{"iter": 2}\n{"it')
        artifact = f"/api/jobs/{job_id}/artifacts/"
        assert_json_refusal(client.get(artifact + "mesh.glb"), 404)
        assert client.get(artifact + "metrics.jsonl").text == '{"iter": 1}\n{"iter": 2}\n'
        (job_dir / "stages").mkdir()
        (job_dir / "stages" / "export.json").write_text("{}")  # the stage's marker: its outputs are whole
        assert client.get(artifact + "mesh.glb").content == b"glTF half a me"
        assert client.post(f"/api/jobs/{job_id}/cancel").status_code == 200


def test_health_shows_internals_to_token_holders_only(guarded: ServeProcess, tiny_video: Path) -> None:
    with httpx.Client(base_url=guarded.url, timeout=30) as client:
        response = upload(client, tiny_video, BOB)
        assert response.status_code == 201
        public = client.get("/api/health")
        assert public.status_code == 503 and public.json() == {"status": "degraded"}  # no worker here
        assert_json_refusal(client.get("/api/health", headers={"Authorization": "Bearer wrong"}), 401)
        detailed = client.get("/api/health", headers=ALICE)
        assert detailed.status_code == 503
        health = detailed.json()
        assert health["database"]["reachable"] and health["workers_alive"] == 0
        assert any("worker" in r for r in health["reasons"])
        mine = client.get("/api/jobs", params={"limit": 200}, headers=ALICE).json()["items"]
        assert health["jobs"] == dict(Counter(j["state"] for j in mine))  # alice's, not bob's queued job
        assert client.get("/api/live").json() == {"status": "ok"}
        assert client.post(f"/api/jobs/{response.json()['id']}/cancel", headers=BOB).status_code == 200


def test_owner_keys_are_keyed_and_bad_tokens_rate_limited(guarded: ServeProcess, tiny_video: Path) -> None:
    with httpx.Client(base_url=guarded.url, timeout=30, headers=ALICE) as client:
        response = upload(client, tiny_video)
        job_id = response.json()["id"]
        client.post(f"/api/jobs/{job_id}/cancel")
    db = sqlite3.connect(guarded.data_dir / "jobs.db")
    (owner,) = db.execute("SELECT owner FROM jobs WHERE id = ?", (job_id,)).fetchone()
    db.close()
    assert owner and owner != hashlib.sha256(b"alice-token").hexdigest()[:32]

    # Guesses from one address (127.0.0.2) run into 429, then even a valid token waits; other addresses do not.
    transport = httpx.HTTPTransport(local_address="127.0.0.2")
    with httpx.Client(base_url=guarded.url, timeout=30, transport=transport) as guesser:
        statuses = [guesser.get("/api/jobs", headers={"Authorization": f"Bearer guess{i}"}).status_code
                    for i in range(12)]
        assert statuses[:10] == [401] * 10 and statuses[10:] == [429, 429], statuses
        response = guesser.get("/api/jobs", headers=ALICE)
        assert_json_refusal(response, 429)
        assert int(response.headers["retry-after"]) > 0
        assert guesser.post("/login", data={"token": "alice-token"}).status_code == 429
        assert_json_refusal(guesser.get("/config", headers=ALICE), 429)
    assert httpx.get(f"{guarded.url}/api/jobs", headers=ALICE).status_code == 200


def worker_mains(data: Path) -> list[psutil.Process]:
    """The `neudf worker` processes on this data folder, less their pool processes."""
    found = []
    for process in psutil.process_iter():
        try:
            if "worker" in process.cmdline() and process.environ().get("NEUDF_DATA_DIR") == str(data.resolve()):
                found.append(process)
        except psutil.Error:  # gone meanwhile, or not ours to read
            continue
    pids = {p.pid for p in found}
    return [p for p in found if p.ppid() not in pids]


@pytest.mark.slow
def test_killed_serve_leaves_no_worker_behind(tmp_path: Path, tiny_video: Path) -> None:
    """kill -9 of `neudf serve`: its worker ends too and hands back the job; the next `neudf serve` runs it to the
    end with exactly one worker, and sweeps a job folder nobody recorded."""
    data = tmp_path / "data"
    first = ServeProcess(data, tmp_path / "serve1.log")
    old: list[psutil.Process] = []
    second = None
    try:
        first.wait_ready()
        with httpx.Client(base_url=first.url, timeout=30) as client:
            health = client.get("/api/health")
            assert health.status_code == 200 and health.json()["workers_alive"] == 1
            response = upload(client, tiny_video, **QUICK_JOB)
            assert response.status_code == 201, response.text
            job_id = response.json()["id"]
            wait_job(lambda: client.get(f"/api/jobs/{job_id}").json(),
                     lambda j: j["state"] == "running" or finished(j), poll_s=0.1)
        old = psutil.Process(first.process.pid).children(recursive=True)
        assert old
        os.kill(first.process.pid, signal.SIGKILL)
        first.process.wait(10)
        _, alive = psutil.wait_procs(old, timeout=30)
        assert not alive, f"the worker outlived neudf serve: {[p.pid for p in alive]}"

        orphan = data / "jobs" / ("f" * 32)
        (orphan / "input").mkdir(parents=True)
        (orphan / "input" / "video.mp4").write_bytes(b"left by a create that never got its record")
        os.utime(orphan, (time.time() - 7200, time.time() - 7200))
        second = ServeProcess(data, tmp_path / "serve2.log")
        second.wait_ready()
        assert not orphan.exists()
        with httpx.Client(base_url=second.url, timeout=30) as client:
            job, _ = wait_job(lambda: client.get(f"/api/jobs/{job_id}").json(), finished)
            assert job["state"] == "succeeded", job["error"]
            assert {s["name"]: s["runs"] for s in job["stages"]}["export"] == 1
            assert client.get("/api/health").json()["workers_alive"] == 1
        workers = worker_mains(data)
        assert [p.ppid() for p in workers] == [second.process.pid], [(p.pid, p.ppid()) for p in workers]
    finally:
        for process in old:  # a worker a broken build left behind
            if process.is_running():
                process.kill()
        first.stop()
        if second is not None:
            second.stop()
