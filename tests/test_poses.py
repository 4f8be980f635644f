"""The poses stage (``worker.capture.poses``): frames that share nothing fail to register, the pairs a video
is matched on, pose jumps."""

from __future__ import annotations

import numpy as np
import pytest

from neudf_core import synthetic
from tests.builders import encode_video, noise_frames
from worker.capture.frames import extract_frames
from worker.capture.poses import PoseOptions, estimate_poses, image_pairs, jump_indices
from worker.errors import StageError


def test_unrelated_frames_fail_to_register(tmp_path):
    video = encode_video(tmp_path / "noise.mp4", noise_frames(12, 160, 120, seed=5))
    extract_frames(video, tmp_path / "data", n_frames=12)
    with pytest.raises(StageError) as exc:
        estimate_poses(tmp_path / "data", options=PoseOptions(min_registered=4))
    assert exc.value.stage == "poses" and exc.value.kind == "registration"
    assert "12 frames" in exc.value.message or "of 12 frames" in exc.value.message


def test_image_pairs_sequential_with_loop_closure():
    assert len(image_pairs(10)) == 45  # small sets: exhaustive
    pairs = set(image_pairs(200))
    assert (0, 1) in pairs and (0, 10) in pairs and (0, 11) not in pairs
    assert (0, 16) in pairs and (0, 128) in pairs  # doubling distances
    assert (0, 199) in pairs and (5, 195) in pairs  # the end of the walk-around meets its start
    assert len(pairs) < 200 * 199 / 2 / 5


def test_pose_jumps_find_a_mirrored_stretch_of_video():
    c2w = np.stack([c.c2w for c in synthetic.orbit_cameras(60, 3.0)])
    w2c, centres = np.transpose(c2w[:, :3, :3], (0, 2, 1)), c2w[:, :3, 3].copy()
    assert jump_indices(w2c, centres) == []
    mirror = np.diag([-1.0, 1.0, 1.0])  # frames 20..39 registered mirrored through the x = 0 plane
    centres[20:40] = centres[20:40] @ mirror
    w2c[20:40] = mirror @ w2c[20:40] @ mirror
    assert jump_indices(w2c, centres) == [19, 39]
