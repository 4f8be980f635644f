"""Capture stage 1, frames: a phone video becomes ~200 sharp, evenly spread, upright 8-bit sRGB frames.

The video is decoded once with PyAV. Its frames are split into ``n_frames`` equal windows of time and the
sharpest frame of each window (variance of the Laplacian of a small grey copy) is kept, so the chosen
frames cover the whole walk-around and skip motion blur. Kept frames are turned upright from the video's
rotation metadata (phones store portrait video as landscape plus a display matrix), HDR frames (PQ or HLG,
10-bit) are tone-mapped to 8-bit sRGB instead of being squashed into a washed-out picture, and the result is
downscaled to ``max_size`` on its longest side.

Writes ``DATA/image/000.png ...`` and ``DATA/frames.json`` (one entry per image, CONTRACT.md), plus the
video's description and this stage's seconds into ``DATA/capture.json``. ``frames.json`` is written last:
its presence with all its files is what :func:`is_done` checks.

Bad input raises :class:`~worker.errors.StageError` naming the problem: not a video, an empty, truncated or
corrupt file, a resolution or duration beyond :class:`VideoLimits`, too few usable frames.
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
from PIL import Image
from pydantic import BaseModel, ConfigDict, Field

from neudf_core.files import write_json_atomic
from neudf_core.progress import ProgressFn, null_progress
from worker.capture.records import read_frames_json, update_capture_json
from worker.errors import StageError

__all__ = [
    "STAGE",
    "VideoLimits",
    "VideoInfo",
    "probe_video",
    "extract_frames",
    "is_done",
    "options_record",
]

STAGE = "frames"

# Sharpness is measured on a grey copy at most this long, so the figure does not depend on the video's
# resolution and decoding 1000 4K frames stays cheap.
_ANALYSIS_SIZE = 640
# A frame this flat (a black or single-colour frame; the Laplacian variance of a real scene is in the
# hundreds) is not usable for poses or training.
DEFAULT_MIN_SHARPNESS = 2.0


class VideoLimits(BaseModel):
    """What the pipeline accepts. The service builds one from its settings; the CLI uses the defaults."""

    model_config = ConfigDict(extra="forbid")

    max_seconds: float = Field(1800.0, gt=0, description="Longest accepted video, in seconds.")
    max_pixels: int = Field(8192 * 8192, gt=0, description="Largest accepted frame, width x height.")
    max_side: int = Field(16384, gt=0, description="Longest accepted frame side, in pixels.")
    min_side: int = Field(32, gt=0, description="Shortest accepted frame side, in pixels.")
    min_frames: int = Field(8, ge=1, description="Fewest (usable) frames a video must have.")


class VideoInfo(BaseModel):
    """What :func:`probe_video` learns from a file without decoding more than its first frame."""

    path: str
    codec: str
    width: int = Field(description="Width as displayed (after the rotation metadata).")
    height: int = Field(description="Height as displayed.")
    coded_width: int
    coded_height: int
    rotation: int = Field(description="Counter-clockwise degrees the frames are turned for display (0/90/180/270).")
    fps: float
    seconds: float
    frames: int = Field(description="Frames according to the container (estimated from duration x rate if absent).")
    pix_fmt: str
    bit_depth: int
    hdr: str | None = Field(description="'pq' or 'hlg' for HDR transfer functions, None for SDR.")
    file_bytes: int


def options_record(video: str | Path, n_frames: int, max_size: int, min_sharpness: float) -> dict[str, Any]:
    """What decides this stage's output: kept in capture.json so a resumed capture can tell it changed."""
    video = Path(video).resolve()
    size = video.stat().st_size if video.is_file() else None
    return {"video": str(video), "video_bytes": size, "n_frames": n_frames, "max_size": max_size,
            "min_sharpness": min_sharpness}


def is_done(data_dir: str | Path) -> bool:
    """True when frames.json exists and names exactly the images in DATA/image."""
    data_dir = Path(data_dir)
    try:
        entries = read_frames_json(data_dir)
    except (OSError, ValueError):
        return False
    files = sorted(p.name for p in (data_dir / "image").glob("*.png"))
    return bool(entries) and files == [e["file"] for e in entries]


# -- probing ---------------------------------------------------------------------------------------------
def _looks_like_video_container(path: Path) -> bool:
    """Magic bytes of the usual video containers: a file that has them but does not open is damaged."""
    with open(path, "rb") as fh:
        head = fh.read(12)
    return (
        head[4:8] in (b"ftyp", b"moov", b"mdat", b"wide", b"free")  # MP4 / MOV
        or head[:4] == b"\x1a\x45\xdf\xa3"  # Matroska / WebM
        or (head[:4] == b"RIFF" and head[8:12] == b"AVI ")
    )


def _open(path: Path) -> av.container.InputContainer:
    try:
        return av.open(str(path), metadata_errors="ignore")
    except (av.FFmpegError, UnicodeDecodeError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        if _looks_like_video_container(path):
            raise StageError(STAGE, f"the video file is truncated or corrupt ({reason})", "truncated") from exc
        raise StageError(STAGE, f"not a video file ({reason})", "not_video") from exc


# Demuxers FFmpeg opens that are not videos a phone makes: text shown as ANSI art, single pictures.
_NOT_VIDEO_FORMATS = {"tty": "text", "bin": "text", "xbin": "text", "idf": "text", "adf": "text"}


def _video_stream(container: av.container.InputContainer) -> av.video.stream.VideoStream:
    fmt = container.format.name
    if fmt in _NOT_VIDEO_FORMATS:
        raise StageError(STAGE, "not a video file (it reads as text)", "not_video")
    if fmt == "image2" or fmt.endswith("_pipe"):
        raise StageError(STAGE, "not a video file (it is a still image)", "not_video")
    # A music file's cover art is a one-picture "video" stream: not what the user meant.
    streams = [s for s in container.streams.video if not (s.disposition & av.stream.Disposition.attached_pic)]
    if not streams:
        raise StageError(STAGE, "not a video file (it has no video stream)", "not_video")
    return streams[0]


def _duration(container: av.container.InputContainer, stream: av.video.stream.VideoStream) -> float:
    if stream.duration and stream.time_base:
        return float(stream.duration * stream.time_base)
    if container.duration:
        return container.duration / av.time_base
    return 0.0


def _rotation(frame: av.VideoFrame, stream: av.video.stream.VideoStream) -> int:
    """Counter-clockwise degrees (a multiple of 90) that turn a decoded frame upright."""
    degrees = float(frame.rotation or 0)  # the display matrix, counter-clockwise
    if not degrees and "rotate" in stream.metadata:  # older muxers: a tag, clockwise
        try:
            degrees = -float(stream.metadata["rotate"])
        except ValueError:
            degrees = 0.0
    return int(round(degrees / 90.0)) % 4 * 90


def _hdr_kind(frame: av.VideoFrame) -> str | None:
    trc = int(frame.color_trc or 0)
    return {16: "pq", 18: "hlg"}.get(trc)  # AVCOL_TRC_SMPTE2084, AVCOL_TRC_ARIB_STD_B67


def _first_frame(container: av.container.InputContainer, stream: av.video.stream.VideoStream) -> av.VideoFrame:
    try:
        for frame in container.decode(stream):
            return frame
    except av.FFmpegError as exc:
        raise StageError(STAGE, f"the video is corrupt: its first frame does not decode ({exc})", "corrupt") from exc
    raise StageError(STAGE, "the video has no decodable frames", "too_few_frames")


def _count_packets(path: Path) -> int:
    """Frames of a stream whose container does not say, by demuxing (no decoding: cheap)."""
    with _open(path) as container:
        stream = _video_stream(container)
        return sum(1 for packet in container.demux(stream) if packet.size)


def _index_says_truncated(stream: av.video.stream.VideoStream, file_bytes: int) -> bool:
    """MP4/MOV indexes give every sample's byte offset: samples past the end of the file mean truncation."""
    try:
        entries = stream.index_entries
        if not len(entries):
            return False
        last = entries[len(entries) - 1]
        return last.pos > 0 and last.pos + last.size > file_bytes
    except (AttributeError, av.FFmpegError):
        return False


def probe_video(path: str | Path, limits: VideoLimits | None = None) -> VideoInfo:
    """Check cheaply that ``path`` is a video the pipeline can use; StageError saying why not.

    Opens the container, reads its header and decodes the first frame only (for the rotation and colour
    tags and as proof that it decodes). Checks resolution, duration and frame count against ``limits``.
    """
    limits = limits or VideoLimits()
    path = Path(path)
    if not path.is_file():
        raise StageError(STAGE, f"no such file: {path.name}", "missing")
    file_bytes = path.stat().st_size
    if file_bytes == 0:
        raise StageError(STAGE, "the file is empty", "empty")
    with _open(path) as container:
        stream = _video_stream(container)
        ctx = stream.codec_context
        coded_w, coded_h = int(ctx.width or 0), int(ctx.height or 0)
        if coded_w <= 0 or coded_h <= 0:
            raise StageError(STAGE, "the video stream has no frame size: the file is corrupt", "corrupt")
        if max(coded_w, coded_h) > limits.max_side or coded_w * coded_h > limits.max_pixels:
            raise StageError(
                STAGE,
                f"resolution {coded_w}x{coded_h} is beyond the limit "
                f"({limits.max_side} px a side, {limits.max_pixels / 1e6:.1f} megapixels)",
                "resolution",
            )
        if min(coded_w, coded_h) < limits.min_side:
            raise StageError(
                STAGE, f"resolution {coded_w}x{coded_h} is too small (at least {limits.min_side} px a side)",
                "resolution",
            )
        seconds = _duration(container, stream)
        fps = float(stream.average_rate or stream.guessed_rate or 0.0)
        frames = int(stream.frames or 0)
        if _index_says_truncated(stream, file_bytes):
            raise StageError(STAGE, "the video file is truncated (its index points past the end of the file)",
                             "truncated")
        first = _first_frame(container, stream)
        rotation = _rotation(first, stream)
        codec, pix_fmt, hdr = ctx.name, first.format.name, _hdr_kind(first)
        bit_depth = max((c.bits for c in first.format.components), default=8)
    if frames == 0:  # no count in the header (Matroska, WebM, raw streams): count the packets
        frames = _count_packets(path)
        seconds = seconds or (frames / fps if fps else 0.0)
    if seconds > limits.max_seconds:
        raise StageError(
            STAGE, f"duration {seconds:.0f} s is beyond the limit of {limits.max_seconds:.0f} s", "duration"
        )
    if frames < limits.min_frames:
        raise StageError(
            STAGE, f"too few frames: the video has {frames}, at least {limits.min_frames} are needed",
            "too_few_frames",
        )
    width, height = (coded_h, coded_w) if rotation in (90, 270) else (coded_w, coded_h)
    return VideoInfo(
        path=str(path), codec=codec, width=width, height=height, coded_width=coded_w, coded_height=coded_h,
        rotation=rotation, fps=fps, seconds=seconds, frames=frames, pix_fmt=pix_fmt, bit_depth=bit_depth,
        hdr=hdr, file_bytes=file_bytes,
    )


# -- colour: YUV (SDR or HDR) to 8-bit sRGB ---------------------------------------------------------------
# AVColorSpace of a frame -> the swscale matrix that reads its YUV.
_SWS_MATRIX = {1: 1, 4: 4, 5: 5, 6: 5, 7: 7, 9: 9, 10: 9}
# Linear BT.2020 RGB to linear BT.709 RGB (ITU-R BT.2087).
_BT2020_TO_BT709 = np.array(
    [[1.6605, -0.5876, -0.0728], [-0.1246, 1.1329, -0.0083], [-0.0182, -0.1006, 1.1187]]
)
_SDR_WHITE_NITS = 203.0  # ITU-R BT.2408: HDR reference white, mapped to SDR white


def _yuv_matrix(frame: av.VideoFrame) -> int:
    spc = int(frame.colorspace or 2)
    if spc in _SWS_MATRIX:
        return _SWS_MATRIX[spc]
    return 1 if frame.height >= 720 else 5  # untagged: HD is BT.709, SD is BT.601 (as players assume)


def _yuv_range(frame: av.VideoFrame) -> int:
    rng = int(frame.color_range or 0)
    if rng in (1, 2):
        return rng
    return 2 if frame.format.name.startswith("yuvj") else 1  # untagged YUV is limited (MPEG) range


def _pq_to_nits(e: np.ndarray) -> np.ndarray:
    """SMPTE ST 2084 EOTF: PQ signal in 0..1 to absolute luminance in cd/m^2."""
    m1, m2 = 2610 / 16384, 2523 / 4096 * 128
    c1, c2, c3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
    p = np.power(np.clip(e, 0, 1), 1 / m2)
    return 10000.0 * np.power(np.maximum(p - c1, 0) / (c2 - c3 * p), 1 / m1)


def _hlg_to_nits(e: np.ndarray, peak: float = 1000.0) -> np.ndarray:
    """ITU-R BT.2100 HLG: inverse OETF then the OOTF of a ``peak``-nit display (gamma 1.2 at 1000 nits)."""
    a, b, c = 0.17883277, 0.28466892, 0.55991073
    e = np.clip(e, 0, 1)
    scene = np.where(e <= 0.5, e * e / 3, (np.exp((e - c) / a) + b) / 12)
    luma = scene @ np.array([0.2627, 0.6780, 0.0593])
    gamma = 1.2 + 0.42 * math.log10(peak / 1000.0)
    return peak * np.power(np.maximum(luma, 1e-6), gamma - 1)[..., None] * scene


def _srgb_encode(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _tone_map(rgb: np.ndarray, knee: float = 0.8) -> np.ndarray:
    """Compress values above ``knee`` (1 = SDR white) smoothly into [knee, 1); keep hue by scaling max(R,G,B)."""
    peak = rgb.max(axis=-1, keepdims=True)
    over = np.maximum(peak - knee, 0)
    mapped = np.where(peak > knee, knee + (1 - knee) * (1 - np.exp(-over / (1 - knee))), peak)
    return rgb * (mapped / np.maximum(peak, 1e-9))


def frame_to_rgb8(frame: av.VideoFrame, width: int, height: int) -> np.ndarray:
    """The frame as 8-bit sRGB (H, W, 3) at ``width`` x ``height`` (coded orientation), HDR tone-mapped."""
    kwargs = dict(width=width, height=height, src_colorspace=_yuv_matrix(frame), src_color_range=_yuv_range(frame),
                  dst_color_range=2, interpolation="AREA")
    hdr = _hdr_kind(frame)
    if hdr is None:
        return frame.reformat(format="rgb24", **kwargs).to_ndarray()
    # HDR: read the non-linear BT.2020 RGB at 16 bits, linearise, convert the gamut, tone-map, encode sRGB.
    signal = frame.reformat(format="rgb48le", **kwargs).to_ndarray().astype(np.float64) / 65535.0
    nits = _pq_to_nits(signal) if hdr == "pq" else _hlg_to_nits(signal)
    linear709 = (nits / _SDR_WHITE_NITS) @ _BT2020_TO_BT709.T
    rgb = _srgb_encode(_tone_map(np.maximum(linear709, 0)))
    return (rgb * 255 + 0.5).astype(np.uint8)


# -- extraction ----------------------------------------------------------------------------------------------
def _sharpness(frame: av.VideoFrame) -> float:
    scale = min(1.0, _ANALYSIS_SIZE / max(frame.width, frame.height))
    w, h = max(8, round(frame.width * scale)), max(8, round(frame.height * scale))
    grey = frame.to_ndarray(format="gray", width=w, height=h, interpolation="AREA")
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _output_size(coded_w: int, coded_h: int, max_size: int) -> tuple[int, int]:
    scale = min(1.0, max_size / max(coded_w, coded_h))
    return max(1, round(coded_w * scale)), max(1, round(coded_h * scale))


@dataclass
class _Candidate:
    window: int
    index: int
    time_s: float
    sharpness: float
    frame: av.VideoFrame


def _clear_outputs(data_dir: Path) -> None:
    """A new extraction invalidates everything that was computed from the old frames."""
    for name in ("image", "colmap"):
        shutil.rmtree(data_dir / name, ignore_errors=True)
    for name in ("frames.json", "capture.json", "cameras_sphere.npz", "cameras.png"):
        (data_dir / name).unlink(missing_ok=True)


DEFAULT_FRAMES = 200  # enough views for poses and training, few enough for minutes of SIFT


def extract_frames(
    video: str | Path,
    data_dir: str | Path,
    *,
    n_frames: int = DEFAULT_FRAMES,
    max_size: int = 1600,
    limits: VideoLimits | None = None,
    min_sharpness: float = DEFAULT_MIN_SHARPNESS,
    progress: ProgressFn = null_progress,
) -> dict[str, Any]:
    """Pick up to ``n_frames`` sharp frames spread evenly over the video; write DATA/image and frames.json.

    Returns a summary: frames decoded, frames written, their mean sharpness, the video's description and
    the seconds taken. Raises StageError for input the pipeline cannot use.
    """
    if n_frames < 1:
        raise ValueError("n_frames must be at least 1")
    t0 = time.perf_counter()
    limits = limits or VideoLimits()
    info = probe_video(video, limits)
    data_dir = Path(data_dir)
    _clear_outputs(data_dir)
    image_dir = data_dir / "image"
    image_dir.mkdir(parents=True, exist_ok=True)

    n_windows = max(1, min(n_frames, info.frames)) if info.frames else n_frames
    quarter_turns = info.rotation // 90
    # Scale in the coded orientation, then turn: the longest side is the same either way.
    out_w, out_h = _output_size(info.coded_width, info.coded_height, max_size)
    digits = max(3, len(str(n_windows - 1)))
    entries: list[dict[str, Any]] = []

    def window_of(index: int, t: float) -> int:
        if info.frames:  # the container's count (MP4/MOV) or the packets counted by probe_video
            w = index * n_windows // info.frames
        else:
            w = int(t / info.seconds * n_windows) if info.seconds else index
        return min(max(w, 0), n_windows - 1)

    def keep(c: _Candidate) -> None:
        if c.sharpness < min_sharpness:  # the best of its window is blank: no frame from this window
            return
        rgb = np.ascontiguousarray(np.rot90(frame_to_rgb8(c.frame, out_w, out_h), quarter_turns))
        name = f"{len(entries):0{digits}d}.png"
        Image.fromarray(rgb).save(image_dir / name, compress_level=3)
        entries.append({"file": name, "frame_index": c.index, "time_s": round(c.time_s, 4),
                        "sharpness": round(c.sharpness, 3)})

    decoded, last_time, start_time = 0, 0.0, None
    best: _Candidate | None = None
    decode_error: str | None = None
    with _open(Path(video)) as container:
        stream = _video_stream(container)
        stream.thread_type = "AUTO"
        try:
            for index, frame in enumerate(container.decode(stream)):
                t = float(frame.time) if frame.time is not None else index / (info.fps or 30.0)
                start_time = t if start_time is None else start_time
                t -= start_time
                decoded, last_time = index + 1, t
                window = window_of(index, t)
                if best is not None and window != best.window:
                    keep(best)
                    best = None
                if not frame.is_corrupt:  # concealed decoding errors: smeared blocks, never a candidate
                    sharp = _sharpness(frame)
                    if best is None or sharp > best.sharpness:
                        best = _Candidate(window, index, t, sharp, frame)
                if index % 10 == 0:
                    total = info.frames or max(1, round(info.seconds * info.fps))
                    progress(min(index / total, 0.99), f"decoding frame {index + 1}/{total}",
                             decoded=index + 1, selected=len(entries))
        except av.FFmpegError as exc:  # a damaged stream: judged below by how much of it decoded
            decode_error = str(exc)
        if best is not None:
            keep(best)

    expected = info.frames or round(info.seconds * info.fps)
    if (expected and decoded < 0.9 * expected) or (decode_error and decoded < expected):
        shutil.rmtree(image_dir, ignore_errors=True)
        why = f" ({decode_error})" if decode_error else ""
        raise StageError(
            STAGE,
            f"the video is truncated or corrupt: only {decoded} of {expected} frames "
            f"({last_time:.1f} of {info.seconds:.1f} s) decode{why}",
            "truncated",
        )
    needed = min(limits.min_frames, n_frames)
    if len(entries) < needed:
        shutil.rmtree(image_dir, ignore_errors=True)
        raise StageError(
            STAGE,
            f"too few usable frames: {len(entries)} sharp, decodable frames in {decoded} decoded, "
            f"at least {needed} are needed",
            "too_few_frames",
        )
    seconds = time.perf_counter() - t0
    summary = {
        "frames_decoded": decoded,
        "frames_selected": len(entries),
        "sharpness_mean": round(float(np.mean([e["sharpness"] for e in entries])), 3),
        "image_size": [int(out_h if quarter_turns % 2 else out_w), int(out_w if quarter_turns % 2 else out_h)],
        "video": info.model_dump(),
    }
    update_capture_json(data_dir, seconds={"frames": seconds}, frames_selected=len(entries),
                        frames_decoded=decoded, image_size=summary["image_size"], video=summary["video"],
                        frames_options=options_record(video, n_frames, max_size, min_sharpness))
    write_json_atomic(data_dir / "frames.json", entries)  # last: marks the stage complete
    progress(1.0, f"{len(entries)} frames chosen from {decoded}", selected=len(entries), decoded=decoded)
    return {**summary, "seconds": round(seconds, 3)}
