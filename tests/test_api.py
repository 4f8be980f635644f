"""The REST API: bad input is refused with a reason and leaves nothing behind; the embedded default
(`neudf serve`: filesystem broker, SQLite, a local Celery worker) turns a video into a GLB."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.helpers import QUICK_JOB, assert_monotonic_progress, assert_valid_glb, finished, wait_job
from worker.pipeline import STAGE_NAMES, JobOptions
from worker.store import JobStore


# -- without a worker: in-process app, real SQLite store and filesystem broker ----------------------------
@pytest.fixture
def make_client(tmp_path: Path) -> Iterator[Callable[..., tuple[TestClient, Settings]]]:
    clients: list[TestClient] = []

    def make(**overrides: Any) -> tuple[TestClient, Settings]:
        settings = Settings(data_dir=tmp_path / f"data{len(clients)}", **overrides)
        client = TestClient(create_app(settings))
        client.__enter__()
        clients.append(client)
        return client, settings

    yield make
    for client in clients:
        client.__exit__(None, None, None)


def assert_nothing_left(settings: Settings) -> None:
    """No record, no job folder, no staging file."""
    assert JobStore(settings.resolved_database_url).list()[1] == 0
    assert not any(settings.jobs_dir.glob("*")) if settings.jobs_dir.exists() else True
    assert not any(settings.uploads_dir.glob("*"))


def upload(client: httpx.Client | TestClient, data: bytes | Path, name: str = "clip.mp4",
           headers: dict[str, str] | None = None, **fields: str) -> httpx.Response:
    content = data.read_bytes() if isinstance(data, Path) else data
    return client.post("/api/jobs", files={"file": (name, content, "video/mp4")}, data=fields, headers=headers)


def test_not_a_video_is_415_and_leaves_nothing(make_client: Callable, tmp_path: Path) -> None:
    client, settings = make_client()
    response = upload(client, b"this is a text file, not a video\n" * 100, name="notes.mp4")
    assert response.status_code == 415
    assert "video" in response.json()["detail"].lower()
    assert_nothing_left(settings)


def test_empty_file_is_400(make_client: Callable) -> None:
    client, settings = make_client()
    response = upload(client, b"")
    assert response.status_code == 400
    assert "empty" in response.json()["detail"]
    assert_nothing_left(settings)


def test_oversized_upload_is_413(make_client: Callable, tiny_video: Path) -> None:
    client, settings = make_client(max_upload_mb=0.01)  # 10 KiB; the video is ~40 KB
    response = upload(client, tiny_video)
    assert response.status_code == 413
    assert "limit" in response.json()["detail"]
    assert_nothing_left(settings)


def test_oversized_upload_without_length_is_cut_off(make_client: Callable, tiny_video: Path) -> None:
    """A chunked upload (no Content-Length) is counted while streaming and stopped at the limit."""
    client, settings = make_client(max_upload_mb=0.01)
    boundary = "neudfboundary"
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"v.mp4\"\r\n"
            f"Content-Type: video/mp4\r\n\r\n").encode() + tiny_video.read_bytes() + f"\r\n--{boundary}--\r\n".encode()

    def chunks() -> Iterator[bytes]:
        for i in range(0, len(body), 4096):
            yield body[i:i + 4096]

    response = client.post("/api/jobs", content=chunks(),
                           headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert response.status_code == 413
    assert_nothing_left(settings)


def test_bad_options_and_missing_file_are_422(make_client: Callable, tiny_video: Path) -> None:
    client, settings = make_client()
    for fields, word in (({"iters": "-3"}, "iters"), ({"preset": "nope"}, "preset"), ({"colour": "red"}, "colour"),
                         ({"frames": "many"}, "frames"), ({"mesh_min_seen": "1.5"}, "mesh_min_seen")):
        response = upload(client, tiny_video, **fields)
        assert response.status_code == 422, fields
        assert word in response.json()["detail"]
    response = client.post("/api/jobs", data={"preset": "quick"}, files={"other": ("x.txt", b"x")})
    assert response.status_code == 422
    assert "file" in response.json()["detail"]
    response = client.post("/api/jobs", json={"file": "x"})
    assert response.status_code == 415
    assert_nothing_left(settings)


def test_unknown_job_is_404(make_client: Callable) -> None:
    client, _ = make_client()
    missing = "0" * 32
    for method, path in (("get", f"/api/jobs/{missing}"), ("post", f"/api/jobs/{missing}/cancel"),
                         ("delete", f"/api/jobs/{missing}"), ("get", f"/api/jobs/{missing}/artifacts/mesh.glb"),
                         ("get", "/api/jobs/not-an-id")):
        response = client.request(method, path)
        assert response.status_code == 404, path
        assert "no job" in response.json()["detail"]


def test_accepted_job_lifecycle_without_worker(make_client: Callable, tiny_video: Path) -> None:
    """Queued jobs: listing newest first with paging, artifact path tricks, cancel, 409s, delete."""
    client, settings = make_client()
    ids = []
    for i in range(3):
        response = upload(client, tiny_video, name=f"clip{i}.mp4", iters="5")
        assert response.status_code == 201, response.text
        job = response.json()
        assert job["state"] == "queued" and job["options"]["iters"] == 5 and job["options"].get("preset") is None
        assert [s["name"] for s in job["stages"]] == list(STAGE_NAMES)
        ids.append(job["id"])
    # The upload of an accepted job is kept, byte for byte.
    kept = list((settings.job_dir(ids[0]) / "input").glob("video.*"))
    assert len(kept) == 1 and kept[0].read_bytes() == tiny_video.read_bytes()

    page = client.get("/api/jobs", params={"limit": 2}).json()
    assert page["total"] == 3 and [j["id"] for j in page["items"]] == [ids[2], ids[1]]
    page = client.get("/api/jobs", params={"limit": 2, "offset": 2}).json()
    assert [j["id"] for j in page["items"]] == [ids[0]]
    assert client.get("/api/jobs", params={"limit": 0}).status_code == 422

    job_id = ids[0]
    for trick in ("../../jobs.db", "..%2F..%2Fjobs.db", "../input/video.mp4", "%2e%2e/jobs.db", ".hidden",
                  "mesh.glb/../../../jobs.db", "a\\..\\b"):
        response = client.get(f"/api/jobs/{job_id}/artifacts/{trick}")
        # A client may normalise the dots away before sending (then the router answers 404); what arrives
        # with them gets a 400 with a reason. Never a file.
        assert response.status_code in (400, 404), trick
        assert response.headers["content-type"].startswith("application/json") and response.json()["detail"], trick
    response = client.get(f"/api/jobs/{job_id}/artifacts/..%2F..%2Fjobs.db")
    assert response.status_code == 400 and "invalid artifact name" in response.json()["detail"]
    response = client.get(f"/api/jobs/{job_id}/artifacts/mesh.glb")
    assert response.status_code == 404 and "none yet" in response.json()["detail"]

    assert client.delete(f"/api/jobs/{job_id}").status_code == 409  # queued: not finished
    response = client.post(f"/api/jobs/{job_id}/cancel")
    assert response.status_code == 200 and response.json()["state"] == "cancelled"
    response = client.post(f"/api/jobs/{job_id}/cancel")
    assert response.status_code == 409 and "already cancelled" in response.json()["detail"]
    assert client.delete(f"/api/jobs/{job_id}").status_code == 204
    assert client.get(f"/api/jobs/{job_id}").status_code == 404
    assert not settings.job_dir(job_id).exists()
    assert client.get("/api/jobs").json()["total"] == 2


def test_tokens_keep_jobs_apart(make_client: Callable, tiny_video: Path) -> None:
    client, _ = make_client(auth_tokens="alice-token,bob-token")
    alice = {"Authorization": "Bearer alice-token"}
    bob = {"Authorization": "Bearer bob-token"}
    assert upload(client, tiny_video).status_code == 401
    assert client.get("/api/jobs", headers={"Authorization": "Bearer guess"}).status_code == 401
    response = upload(client, tiny_video, headers=alice)
    assert response.status_code == 201
    job_id = response.json()["id"]
    assert client.get(f"/api/jobs/{job_id}", headers=alice).status_code == 200
    assert client.get(f"/api/jobs/{job_id}", headers=bob).status_code == 404
    assert client.post(f"/api/jobs/{job_id}/cancel", headers=bob).status_code == 404
    assert client.get("/api/jobs", headers=bob).json()["total"] == 0
    assert client.get("/api/jobs", headers=alice).json()["total"] == 1
    # health stays open for probes, without what is where (no worker here: degraded)
    assert client.get("/api/health").json() == {"status": "degraded"}


def test_health_without_worker_is_degraded(make_client: Callable) -> None:
    client, _ = make_client()
    response = client.get("/api/health")
    assert response.status_code == 503
    health = response.json()
    assert health["status"] == "degraded" and health["workers_alive"] == 0
    assert health["broker"]["reachable"] and health["database"]["reachable"]
    assert any("worker" in r for r in health["reasons"])
    assert client.get("/api/live").json() == {"status": "ok"}


def test_options_that_could_exhaust_the_machine_are_refused(make_client: Callable, tiny_video: Path) -> None:
    client, settings = make_client()
    for fields in ({"frames": "2000"}, {"max_size": "8192"}, {"mesh_resolution": "2048"}):
        response = upload(client, tiny_video, **fields)
        assert response.status_code == 422, fields
        assert next(iter(fields)) in response.json()["detail"]
    assert_nothing_left(settings)


def test_unfinished_jobs_per_token_are_capped(make_client: Callable, tiny_video: Path) -> None:
    client, _ = make_client(auth_tokens="alice-token,bob-token", max_unfinished_jobs=2)
    alice = {"Authorization": "Bearer alice-token"}
    ids = [upload(client, tiny_video, headers=alice).json()["id"] for _ in range(2)]
    response = upload(client, tiny_video, headers=alice)
    assert response.status_code == 429 and "at most 2" in response.json()["detail"]
    assert int(response.headers["retry-after"]) > 0
    assert upload(client, tiny_video, headers={"Authorization": "Bearer bob-token"}).status_code == 201
    assert client.post(f"/api/jobs/{ids[0]}/cancel", headers=alice).status_code == 200
    assert upload(client, tiny_video, headers=alice).status_code == 201


def test_upload_needs_free_disk(make_client: Callable, tiny_video: Path) -> None:
    client, settings = make_client(min_free_disk_mb=2**40)
    response = upload(client, tiny_video)
    assert response.status_code == 507 and "disk" in response.json()["detail"]
    assert_nothing_left(settings)


def test_owner_keys_depend_on_the_deployment_secret(make_client: Callable, tiny_video: Path) -> None:
    """Owner keys are keyed by a secret of the deployment; jobs stored under the old unsalted key stay their token's."""
    import hashlib

    alice = {"Authorization": "Bearer alice-token"}
    keys = []
    for _ in range(2):
        client, settings = make_client(auth_tokens="alice-token")
        assert upload(client, tiny_video, headers=alice).status_code == 201
        keys.append(JobStore(settings.resolved_database_url).list()[0][0].owner)
    legacy = hashlib.sha256(b"alice-token").hexdigest()[:32]
    assert keys[0] != keys[1] and legacy not in keys
    client, settings = make_client(auth_tokens="alice-token")
    store = JobStore(settings.resolved_database_url)
    store.create(job_id="a" * 32, owner=legacy, stages=list(STAGE_NAMES), options={}, input_name="old.mp4",
                 input_bytes=1)
    jobs = client.get("/api/jobs", headers=alice).json()
    assert [j["id"] for j in jobs["items"]] == ["a" * 32]
    assert store.get("a" * 32).owner not in (legacy, None)


def test_openapi_lists_the_routes(make_client: Callable) -> None:
    client, _ = make_client()
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/api/jobs", "/api/jobs/{job_id}", "/api/jobs/{job_id}/artifacts/{name}", "/api/jobs/{job_id}/cancel",
            "/api/health", "/api/live"} <= set(paths)
    assert "multipart/form-data" in paths["/api/jobs"]["post"]["requestBody"]["content"]
    assert client.get("/docs").status_code == 200


def test_openapi_form_lists_every_job_option(make_client: Callable) -> None:
    """The upload form in the API docs comes from JobOptions: a new option shows there by itself."""
    client, _ = make_client()
    body = client.get("/openapi.json").json()["paths"]["/api/jobs"]["post"]["requestBody"]
    form = body["content"]["multipart/form-data"]["schema"]
    assert set(form["properties"]) == {"file"} | set(JobOptions.model_fields)
    assert form["required"] == ["file"] and form["properties"]["file"]["format"] == "binary"
    faces = form["properties"]["faces"]
    assert faces["type"] == "integer" and faces["default"] == JobOptions.model_fields["faces"].default
    assert form["properties"]["mesh_method"]["enum"] == ["meshudf", "spsr", "mc"]  # an optional one, without null


# -- the embedded default, end to end ------------------------------------------------------------------------
@pytest.mark.slow
def test_embedded_video_to_glb(embedded_server: Any, tiny_video: Path) -> None:
    with httpx.Client(base_url=embedded_server.url, timeout=30) as client:
        response = client.get("/api/health")
        health = response.json()
        assert response.status_code == 200 and health["status"] == "ok" and health["broker"]["embedded"], health
        response = upload(client, tiny_video, **QUICK_JOB)
        assert response.status_code == 201, response.text
        job_id = response.json()["id"]
        job, seen = wait_job(lambda: client.get(f"/api/jobs/{job_id}").json(), finished, poll_s=0.1)
        assert job["state"] == "succeeded", job["error"]
        assert_monotonic_progress(seen, list(STAGE_NAMES))
        assert job["progress"] == 1.0 and job["error"] is None
        assert all(s["state"] == "done" and s["runs"] == 1 and s["seconds"] is not None for s in job["stages"])
        assert job["metrics"]["frames_registered"] >= 8 and job["metrics"]["mesh_faces"] > 0
        assert "mesh_faces_unseen" not in job["metrics"]  # mesh_min_seen 0: meshed without the cameras
        for name in ("mesh.glb", "mesh.obj", "mesh.mtl", "mesh.png", "mesh.usdz", "mesh.ply", "preview.png",
                     "loss.png", "frames.png", "cameras.png", "metrics.json"):
            assert name in job["artifacts"], name
        glb = client.get(job["artifacts"]["mesh.glb"])
        assert glb.status_code == 200 and glb.headers["content-type"] == "model/gltf-binary"
        assert_valid_glb(glb.content)
        png = client.get(job["artifacts"]["loss.png"])
        assert png.status_code == 200 and png.content[:4] == b"\x89PNG"

        response = client.post(f"/api/jobs/{job_id}/cancel")
        assert response.status_code == 409 and "succeeded" in response.json()["detail"]
        assert client.delete(f"/api/jobs/{job_id}").status_code == 204
        assert not (embedded_server.data_dir / "jobs" / job_id).exists()


@pytest.mark.slow
def test_embedded_cancel_while_training(embedded_server: Any, tiny_video: Path) -> None:
    """A cancel flag set during training stops the job at its next progress report."""
    with httpx.Client(base_url=embedded_server.url, timeout=30) as client:
        response = upload(client, tiny_video, **{**QUICK_JOB, "iters": "5000"})
        assert response.status_code == 201
        job_id = response.json()["id"]
        wait_job(lambda: client.get(f"/api/jobs/{job_id}").json(),
                 lambda j: j["stage"] == "train" and j["stages"][3]["progress"] > 0 or finished(j), poll_s=0.2)
        response = client.post(f"/api/jobs/{job_id}/cancel")
        assert response.status_code == 200 and response.json()["cancel_requested"]
        job, _ = wait_job(lambda: client.get(f"/api/jobs/{job_id}").json(), finished, timeout_s=60)
        assert job["state"] == "cancelled" and job["stage"] == "train"
        train = job["stages"][3]
        assert train["state"] == "cancelled" and train["progress"] < 0.5
        assert [s["state"] for s in job["stages"][4:]] == ["pending", "pending"]
        assert client.delete(f"/api/jobs/{job_id}").status_code == 204
