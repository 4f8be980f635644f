"""The capture pipeline: phone video -> frames -> pycolmap poses -> normalised NeuS-layout dataset.

``run_capture`` runs the three stages of :mod:`worker.stages` on one data folder, each reporting into its
share of one progress callback, and skips a stage whose outputs are already complete (``is_done``) and
were made with the same options (recorded in capture.json), so an interrupted capture resumes where it
stopped. Once a stage runs, the ones after it run too: their inputs changed. ``neudf capture`` (worker/cli.py) and the job pipeline call it, or its stages one by one.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from neudf_core.progress import ProgressFn, null_progress, sub_progress
from worker.stages import frames, poses, scene
from worker.stages.frames import VideoLimits
from worker.stages.poses import PoseOptions
from worker.stages.scene import SceneOptions

__all__ = ["CaptureStage", "CAPTURE_STAGES", "run_capture", "load_dataset_cameras", "align_cameras", "pose_errors"]


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


# -- checks against known cameras (tests, benchmarks) ---------------------------------------------------------
def load_dataset_cameras(data_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics (N, 3, 3) and camera-to-world (N, 4, 4, OpenCV axes) in unit-sphere coordinates.

    Reads cameras_sphere.npz as a NeuS loader does: P_i = world_mat_i @ scale_mat_i, split by an RQ
    decomposition into K and [R | t].
    """
    with np.load(Path(data_dir) / "cameras_sphere.npz") as arrays:
        n = sum(1 for k in arrays.files if k.startswith("world_mat_"))
        Ks, c2ws = [], []
        for i in range(n):
            P = (arrays[f"world_mat_{i}"] @ arrays[f"scale_mat_{i}"])[:3, :4]
            K, R, c = cv2.decomposeProjectionMatrix(P)[:3]
            K = K / K[2, 2]
            c2w = np.eye(4)
            c2w[:3, :3] = R.T
            c2w[:3, 3] = (c[:3] / c[3]).ravel()
            Ks.append(K)
            c2ws.append(c2w)
    return np.stack(Ks), np.stack(c2ws)


def align_cameras(est_c2w: np.ndarray, true_c2w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) taking estimated cameras (N, 4, 4) onto the true ones.

    Umeyama on the centres alone leaves the rotation poorly fixed when the centres are nearly coplanar (an
    orbit): a centre error of 1% of the radius out of the plane tilts it by about half a degree, and that
    tilt then shows up as rotation error in every camera. So R fits the centres (normalised to unit RMS
    spread) and the cameras' orientations together; s and t then fit the centres given R.
    """
    src, dst = est_c2w[:, :3, 3], true_c2w[:, :3, 3]
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    spread = max(float(np.sqrt((xs**2).sum(axis=1).mean() * (xd**2).sum(axis=1).mean())), 1e-12)
    # maximise sum_i <R x_i, y_i> / spread + sum_i tr(true_i^T R est_i): one SVD of the summed correlations
    H = xd.T @ xs / spread + np.einsum("nij,nkj->ik", true_c2w[:, :3, :3], est_c2w[:, :3, :3])
    U, _, Vt = np.linalg.svd(H / len(src))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # a reflection is not a rotation
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.einsum("ni,ni->", xd, xs @ R.T) / max((xs**2).sum(), 1e-12))
    return s, R, mu_d - s * R @ mu_s


def pose_errors(est_c2w: np.ndarray, true_c2w: np.ndarray) -> dict[str, Any]:
    """Errors of estimated cameras against the truth after the best similarity alignment (see align_cameras).

    Returns the alignment and per-camera errors: rotation (degrees) and centre distance (truth units).
    """
    s, R, t = align_cameras(est_c2w, true_c2w)
    centres = s * est_c2w[:, :3, 3] @ R.T + t
    centre_err = np.linalg.norm(centres - true_c2w[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", R @ est_c2w[:, :3, :3], true_c2w[:, :3, :3])  # (R est)^T true
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    rot_err = np.degrees(np.arccos(cos))
    return {"scale": s, "rotation": R, "translation": t, "rotation_deg": rot_err, "centre_err": centre_err}
