"""The capture pipeline: phone video -> frames -> pycolmap poses -> normalised NeuS-layout dataset.

``run_capture`` runs the three stages of :mod:`worker.capture` on one data folder, each reporting into its
share of one progress callback, and skips a stage whose outputs are already complete (``is_done``) and
were made with the same options (recorded in capture.json), so an interrupted capture resumes where it
stopped. Once a stage runs, the ones after it run too: their inputs changed. ``neudf capture`` (worker/cli.py)
calls it; the job pipeline (worker/pipeline.py) runs its stages one by one.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neudf_core.progress import ProgressFn, null_progress, sub_progress
from worker.capture import frames, poses, scene
from worker.capture.frames import VideoLimits
from worker.capture.poses import PoseOptions
from worker.capture.scene import SceneOptions

__all__ = ["CaptureStage", "CAPTURE_STAGES", "run_capture"]


@dataclass(frozen=True)
class CaptureStage:
    name: str
    weight: float  # share of a typical capture's time, for the overall progress
    is_done: Callable[[Path], bool]


# Weights from the 200-frame runs in stack_notes.md: decoding ~6%, pycolmap ~92%, normalising ~2%.
CAPTURE_STAGES = (
    CaptureStage("frames", 0.06, frames.is_done),
    CaptureStage("poses", 0.92, poses.is_done),
    CaptureStage("scene", 0.02, scene.is_done),
)


def _deciding(options: Any) -> Any:
    """An options record without the knobs that change only how a stage runs (PoseOptions.RUN_ONLY)."""
    if not isinstance(options, dict):
        return options
    return {k: v for k, v in options.items() if k not in PoseOptions.RUN_ONLY}


def run_capture(
    video: str | Path,
    data_dir: str | Path,
    *,
    n_frames: int = 200,
    max_size: int = 1600,
    limits: VideoLimits | None = None,
    pose_options: PoseOptions | None = None,
    scene_options: SceneOptions | None = None,
    resume: bool = True,
    progress: ProgressFn = null_progress,
) -> dict[str, Any]:
    """Turn ``video`` into a NeuS-layout dataset in ``data_dir``; returns the content of capture.json.

    With ``resume`` a stage whose outputs are complete is skipped (reported with ``skipped=True``). Raises
    StageError for input or captures the pipeline cannot use, Cancelled when the callback asks to stop.
    """
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    pose_options, scene_options = pose_options or PoseOptions(), scene_options or SceneOptions()
    # A finished stage is reused only if it ran with the same options (a new --frames redoes everything).
    wanted = {
        "frames": ("frames_options", frames.options_record(video, n_frames, max_size, frames.DEFAULT_MIN_SHARPNESS)),
        "poses": ("pose_options", pose_options.model_dump()),
        "scene": ("scene_options", scene_options.model_dump()),
    }
    recorded = _read_json(data_dir / "capture.json")
    runners: dict[str, Callable[[ProgressFn], Any]] = {
        "frames": lambda p: frames.extract_frames(video, data_dir, n_frames=n_frames, max_size=max_size,
                                                  limits=limits, progress=p),
        "poses": lambda p: poses.estimate_poses(data_dir, options=pose_options, progress=p),
        "scene": lambda p: scene.write_scene(data_dir, options=scene_options, progress=p),
    }
    total = sum(s.weight for s in CAPTURE_STAGES)
    start, must_run = 0.0, not resume
    for stage in CAPTURE_STAGES:
        end = start + stage.weight / total
        key, options = wanted[stage.name]
        if not must_run and stage.is_done(data_dir) and _deciding(recorded.get(key)) == _deciding(options):
            progress(end, f"{stage.name}: done earlier", stage=stage.name, skipped=True)
            start = end
            continue
        must_run = True
        overall = sub_progress(progress, start, end)

        def report(fraction: float, message: str = "", _name: str = stage.name, _p: ProgressFn = overall,
                   **info: Any) -> None:
            _p(fraction, f"{_name}: {message}" if message else _name, stage=_name, **info)

        report(0.0, "started")
        runners[stage.name](report)
        start = end
    progress(1.0, "capture done")
    return json.loads((data_dir / "capture.json").read_text())


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
