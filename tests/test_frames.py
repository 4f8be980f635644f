"""The frames stage (``worker.capture.frames``): probing and rejecting input, picking sharp frames spread over
time, rotation metadata, HDR to SDR."""

from __future__ import annotations

import av
import numpy as np
import pytest
from PIL import Image

from tests.builders import encode_video, noise_frames
from worker.capture import frames as frames_stage
from worker.capture.frames import VideoLimits, extract_frames, probe_video
from worker.capture.records import read_frames_json
from worker.errors import StageError


# -- rejected input ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "limits", "kind", "words"),
    [
        ("notes", None, "not_video", "not a video"),
        ("empty", None, "empty", "empty"),
        ("ok_cut", None, "truncated", "truncated"),
        ("faststart_cut", None, "truncated", "truncated"),
        ("few", None, "too_few_frames", "too few frames"),
        ("still", None, "not_video", "still image"),
        ("ok", VideoLimits(max_side=48), "resolution", "resolution 64x48"),
        ("ok", VideoLimits(max_pixels=1000), "resolution", "resolution 64x48"),
        ("ok", VideoLimits(max_seconds=0.5), "duration", "duration"),
    ],
)
def test_bad_input_is_rejected_naming_the_problem(small_videos, tmp_path, name, limits, kind, words):
    with pytest.raises(StageError) as probed:
        probe_video(small_videos[name], limits)
    with pytest.raises(StageError) as extracted:
        extract_frames(small_videos[name], tmp_path / "data", limits=limits)
    for exc in (probed.value, extracted.value):
        assert exc.stage == "frames"
        assert exc.kind == kind
        assert words in exc.message


def test_video_without_usable_frames_is_rejected(small_videos, tmp_path):
    probe_video(small_videos["black"])  # a fine file...
    with pytest.raises(StageError) as exc:
        extract_frames(small_videos["black"], tmp_path / "data")  # ...with nothing to see
    assert exc.value.kind == "too_few_frames"
    assert "usable" in exc.value.message


def test_probe_describes_a_good_video(small_videos, tmp_path):
    info = probe_video(small_videos["ok"])
    assert (info.width, info.height, info.frames, info.codec) == (64, 48, 24, "h264")
    assert info.seconds == pytest.approx(1.0, abs=0.05)
    # Matroska has no frame count in its header: the probe counts packets.
    mkv = probe_video(encode_video(tmp_path / "clip.mkv", noise_frames(24)))
    assert (mkv.frames, mkv.width) == (24, 64)
    extract_frames(tmp_path / "clip.mkv", tmp_path / "data", n_frames=12)
    assert len(read_frames_json(tmp_path / "data")) == 12


def test_frames_are_spread_over_time_and_sharpest_in_their_window(tmp_path):
    # 40 frames, every other one blurred: picking 20 must take the sharp one of each pair.
    sharp = noise_frames(40, 96, 64, seed=3)
    blurred = np.stack([np.asarray(Image.fromarray(f).resize((12, 8)).resize((96, 64), Image.BILINEAR)) for f in sharp])
    images = np.where((np.arange(40) % 2 == 0)[:, None, None, None], blurred, sharp)
    video = encode_video(tmp_path / "mixed.mp4", images)
    summary = extract_frames(video, tmp_path / "data", n_frames=20, max_size=48)
    entries = read_frames_json(tmp_path / "data")
    assert summary["frames_selected"] == 20
    assert [e["frame_index"] for e in entries] == list(range(1, 40, 2))
    assert entries[1]["time_s"] == pytest.approx(3 / 24, abs=1e-3)
    assert Image.open(tmp_path / "data" / "image" / "000.png").size == (48, 32)  # longest side max_size
    assert frames_stage.is_done(tmp_path / "data")


# -- rotation metadata and HDR -----------------------------------------------------------------------------------
def _pattern(width: int = 96, height: int = 64) -> np.ndarray:
    """An asymmetric picture: smooth colour ramps (they survive 4:2:0) and a bright top-left block."""
    u, v = np.meshgrid(np.linspace(0, 1, width), np.linspace(0, 1, height))
    image = np.stack([u, v, 0.5 + 0.3 * np.sin(6 * u) * np.cos(4 * v)], -1)
    image[: height // 4, : width // 4] = [1.0, 1.0, 1.0]
    return (image * 255).round().astype(np.uint8)


@pytest.mark.parametrize("rotation", [90, -90, 180])
def test_rotation_metadata_turns_frames_upright(tmp_path, rotation):
    source = _pattern()
    video = encode_video(tmp_path / "rot.mp4", np.repeat(source[None], 12, axis=0), rotation=rotation)
    info = probe_video(video)
    assert info.rotation == rotation % 360
    assert (info.width, info.height) == ((64, 96) if rotation % 180 else (96, 64))
    extract_frames(video, tmp_path / "data", n_frames=8)
    frame = np.asarray(Image.open(tmp_path / "data" / "image" / "000.png")).astype(float)
    upright = np.rot90(source, rotation // 90).astype(float)  # counter-clockwise, as the display matrix says
    assert frame.shape == upright.shape
    assert np.abs(frame - upright).mean() < 6
    assert np.abs(frame - np.rot90(upright, 2)).mean() > 30  # and not turned the wrong way


def _srgb_to_pq_bt2020(image: np.ndarray) -> np.ndarray:
    """An SDR picture as an HDR10 signal: sRGB -> linear BT.709 -> BT.2020 -> 203-nit white -> PQ, 16 bit."""
    x = image / 255.0
    linear = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    to2020 = np.linalg.inv(frames_stage._BT2020_TO_BT709)
    nits = np.clip(linear @ to2020.T, 0, None) * 203.0
    m1, m2, c1, c2, c3 = 2610 / 16384, 2523 / 4096 * 128, 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
    y = (nits / 10000.0) ** m1
    pq = ((c1 + c2 * y) / (1 + c3 * y)) ** m2
    return (pq * 65535).round().astype(np.uint16)


def test_hdr_pq_video_comes_out_as_sdr_not_washed_out(tmp_path):
    source = _pattern()
    hdr = _srgb_to_pq_bt2020(source.astype(float))
    color = {"color_trc": 16, "color_primaries": 9, "colorspace": 9, "color_range": 1}
    video = encode_video(tmp_path / "hdr.mp4", np.repeat(hdr[None], 12, axis=0), codec="libx265",
                         pix_fmt="yuv420p10le", crf=12, color=color, input_format="rgb48le")
    info = probe_video(video)
    assert (info.hdr, info.bit_depth) == ("pq", 10)
    extract_frames(video, tmp_path / "data", n_frames=8)
    ours = np.asarray(Image.open(tmp_path / "data" / "image" / "000.png")).astype(float)
    with av.open(str(video)) as container:  # what a plain 8-bit conversion gives
        naive = next(container.decode(video=0)).to_ndarray(format="rgb24").astype(float)
    error, naive_error = np.abs(ours - source).mean(), np.abs(naive - source).mean()
    assert error < 8
    assert naive_error > 3 * error
