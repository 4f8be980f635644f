"""A capture's cameras against known ones (tests and benchmarks of synthetic videos): alignment and errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from neudf_core.dataset import decompose_projection

__all__ = ["load_dataset_cameras", "align_cameras", "pose_errors"]


def load_dataset_cameras(data_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics (N, 3, 3) and camera-to-world (N, 4, 4, OpenCV axes) in unit-sphere coordinates.

    Reads cameras_sphere.npz as a NeuS loader does: P_i = world_mat_i @ scale_mat_i, split into K and [R | t]
    by the training loader's own decomposition (``neudf_core.dataset.decompose_projection``).
    """
    with np.load(Path(data_dir) / "cameras_sphere.npz") as arrays:
        n = sum(1 for k in arrays.files if k.startswith("world_mat_"))
        Ks, c2ws = zip(*(decompose_projection(arrays[f"world_mat_{i}"] @ arrays[f"scale_mat_{i}"]) for i in range(n)))
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
