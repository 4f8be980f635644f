"""Fixtures shared by the test modules: a tiny synthetic video, small bad and good videos, one `neudf serve`,
the tests' own Redis database. Helpers the tests import live in tests/helpers.py and tests/builders.py."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import REDIS_URL, ServeProcess


@pytest.fixture(scope="session")
def tiny_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 frames at 240x180: a walk-around of a textured wavy sheet inside a textured backdrop sphere.

    The capture tests' scene (the backdrop gives SIFT texture with parallax, as a room does), rendered
    without supersampling to keep it to seconds; at this size pycolmap poses all 30 frames, while 160x120
    leaves most of them unregistered.
    """
    from neudf_core.synthetic import orbit_cameras
    from tests.builders import ORBIT_RADIUS, backdrop_sphere, encode_video, render_scene, textured_sheet

    cameras = orbit_cameras(30, ORBIT_RADIUS, width=240, height=180, fov_deg=50.0)
    images = render_scene(textured_sheet(), backdrop_sphere(rings=32), cameras, supersample=1)
    path = tmp_path_factory.mktemp("video") / "orbit.mp4"
    encode_video(path, images)
    return path


@pytest.fixture(scope="session")
def embedded_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServeProcess]:
    """One `neudf serve` with the embedded defaults (filesystem broker, SQLite), shared by the tests."""
    data = tmp_path_factory.mktemp("serve")
    server = ServeProcess(data / "data", data / "serve.log")
    try:
        server.wait_ready()
        yield server
    finally:
        server.stop()


@pytest.fixture
def redis_db() -> Iterator[str]:
    """The Redis URL of the tests' own database, flushed before and after; skip when Redis is down."""
    import redis

    client = redis.Redis.from_url(REDIS_URL, socket_connect_timeout=2)
    try:
        client.ping()
    except redis.ConnectionError:
        pytest.skip("no Redis server at 127.0.0.1:6379")
    client.flushdb()
    yield REDIS_URL
    client.flushdb()
    client.close()


@pytest.fixture(scope="session")
def small_videos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Small videos good and bad (and files that are no videos), by name."""
    import numpy as np
    from PIL import Image

    from tests.builders import encode_video, noise_frames

    root = tmp_path_factory.mktemp("small")
    videos = {
        "ok": encode_video(root / "ok.mp4", noise_frames(24)),
        "few": encode_video(root / "few.mp4", noise_frames(4)),
        "black": encode_video(root / "black.mp4", np.zeros((24, 48, 64, 3), np.uint8)),
        "faststart": encode_video(root / "faststart.mp4", noise_frames(24), faststart=True),
    }
    (root / "notes.txt").write_text("these are not the frames you are looking for\n" * 20)
    (root / "empty.mp4").write_bytes(b"")
    Image.fromarray(noise_frames(1)[0]).save(root / "still.png")
    for name in ("ok", "faststart"):  # the first half of each: a moov-at-end file and a faststart file
        data = videos[name].read_bytes()
        (root / f"{name}_cut.mp4").write_bytes(data[: len(data) // 2])
    videos.update({p.stem: p for p in (root / "notes.txt", root / "empty.mp4", root / "still.png",
                                       root / "ok_cut.mp4", root / "faststart_cut.mp4")})
    return videos
