"""The scene stage (``worker.capture.scene``): the object's centre and the world's up from the cameras, the
floor under the object left out of the object region."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scipy.spatial import cKDTree

from neudf_core import synthetic
from neudf_core.dataset import VIEWS_PER_POINT
from tests.builders import encode_video, textured_sheet
from worker.capture.evaluate import align_cameras, load_dataset_cameras, pose_errors
from worker.capture.poses import PoseOptions
from worker.capture.run import run_capture
from worker.capture.scene import (SceneCameras, SceneOptions, _object_sphere, axes_point, floor_height, up_direction,
                                  upright_rotation)


@pytest.mark.slow
def test_object_region_leaves_a_textured_floor_out(tmp_path):
    """A sheet hanging above a textured floor in a furnished room, filmed by hand: the scene stage finds the
    floor, and the region training calls object (the unit sphere above region.json's floor) holds the whole
    sheet and none of the floor, though the floor reaches into the sphere."""
    room = synthetic.room_scene(textured_sheet(), floor_y=-0.7)
    cameras = synthetic.handheld_orbit(48, width=360, height=640, seed=3)  # smaller: too few floor features
    images, _ = synthetic.render_room(room, cameras)
    video = encode_video(tmp_path / "room.mp4", images)
    data = tmp_path / "data"
    # 48 small frames are too few to tell fx from fy: OPENCV's two focal lengths came out 520 and 287 px on
    # one run (poses 46 degrees off), 462 and 429 on another (1.7 degrees off, the sparse floor a tenth of
    # the sphere below the true one). The renders have square pixels, so one focal length. The scene stage is
    # what is tested here: a capture whose poses are still off is made again, at most twice.
    options = PoseOptions(num_threads=1, camera_model="SIMPLE_RADIAL")
    for _ in range(3):
        shutil.rmtree(data, ignore_errors=True)
        run_capture(video, data, n_frames=48, pose_options=options)
        _, c2w = load_dataset_cameras(data)
        entries = json.loads((data / "frames.json").read_text())
        truth = np.stack([cameras[e["frame_index"]].c2w for e in entries])
        off_deg = float(np.median(pose_errors(c2w, truth)["rotation_deg"]))
        if off_deg < 0.5:
            break
    assert off_deg < 0.5 and len(entries) >= 40, (off_deg, len(entries))
    floor_y = json.loads((data / "region.json").read_text())["floor_y"]
    record = json.loads((data / "capture.json").read_text())
    assert record["mapper"] == "incremental"  # 48 frames, matched all against all
    scene = record.get("scene", {})
    assert floor_y is not None, (record.get("frames_registered"), scene.get("floor_search"), scene.get("up"))

    s, R, t = align_cameras(c2w, truth)
    to_data = lambda p: (p - t) @ R / s  # noqa: E731  (true world -> the dataset's unit sphere)
    grid = np.stack(np.meshgrid(np.linspace(-2, 2, 81), np.linspace(-2, 2, 81)), -1).reshape(-1, 2)
    floor = to_data(np.stack([grid[:, 0], np.full(len(grid), room.floor_y), grid[:, 1]], -1))
    floor = floor[np.linalg.norm(floor, axis=1) < 1.0]
    assert len(floor) > 100  # the floor does reach into the sphere ...
    assert floor[:, 1].max() <= floor_y + 0.02  # ... and lies under the cut
    sheet = to_data(room.parts[0].vertices)
    assert np.linalg.norm(sheet, axis=1).max() < 1.0 and sheet[:, 1].min() > floor_y + 0.02

    # The sparse points training looks for the object at: inside the sphere, above the floor, on the sheet.
    points = np.load(data / "object_points.npy")
    assert len(points) >= 50 and np.linalg.norm(points, axis=1).max() < 1.0 and points[:, 1].min() > floor_y
    gap, _ = cKDTree(sheet).query(points)
    assert np.mean(gap < 0.05) > 0.8

    # Row for row, frames that saw each point (its track): the point lies in front of each and in its frame.
    views = np.load(data / "object_point_views.npy")
    assert views.shape == (len(points), VIEWS_PER_POINT) and (views[:, :3] >= 0).all()
    K, _ = load_dataset_cameras(data)
    rows, cols = np.nonzero(views >= 0)
    w2c = np.linalg.inv(c2w[views[rows, cols]])
    in_cam = np.einsum("nij,nj->ni", w2c[:, :3, :3], points[rows]) + w2c[:, :3, 3]
    pixels = np.einsum("nij,nj->ni", K[views[rows, cols]], in_cam)
    pixels = pixels[:, :2] / pixels[:, 2:]
    width, height = scene["image_size"]
    assert (in_cam[:, 2] > 0).all()
    assert np.mean((pixels >= 0).all(1) & (pixels[:, 0] < width) & (pixels[:, 1] < height)) > 0.99


def test_axes_point_and_upright_rotation():
    target = np.array([0.3, -0.2, 0.1])
    cams = synthetic.orbit_cameras(30, 2.5, target=target)
    c2w = np.stack([c.c2w for c in cams])
    rng = np.random.default_rng(0)
    axes = c2w[:, :3, 2]
    axes[:3] = rng.normal(size=(3, 3))  # three frames look elsewhere
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    assert np.linalg.norm(axes_point(c2w[:, :3, 3], axes) - target) < 0.02
    up = up_direction(c2w[:, :3, 0], -c2w[:, :3, 1])  # the cameras tilt between -20 and 40 degrees
    assert np.allclose(up, [0, 1, 0], atol=1e-6)
    rotation = upright_rotation(np.array([0.0, 0.0, 2.0]), c2w[0, :3, 3] - target)
    assert np.allclose(rotation @ rotation.T, np.eye(3))
    assert np.allclose(rotation @ np.array([0.0, 0.0, 1.0]), [0, 1, 0], atol=1e-6)


def test_floor_under_an_object_poor_in_features_is_found():
    """A smooth bowl gives few sparse points; strays in the column under it (clutter, the room) spread as far
    as the floor's points can, since the column bounds both, so the floor is told by its density alone."""
    rng = np.random.default_rng(1)
    band = 0.02
    disc = lambda n: np.sqrt(rng.uniform(0.0, 1.0, n))  # noqa: E731  uniform over the column's cross-section
    bowl_h, bowl_r = rng.uniform(-0.3, 0.2, 40), rng.uniform(0.0, 0.4, 40)
    stray_h, stray_r = rng.uniform(-0.7, 0.9, 150), disc(150)
    floor_h, floor_r = rng.normal(-0.8, 0.004, 5000), disc(5000)
    level, found = floor_height(np.concatenate([bowl_h, stray_h, floor_h]),
                                np.concatenate([bowl_r, stray_r, floor_r]), band, 20)
    assert level is not None and abs(level - (-0.8 + band)) < band, found
    faint = floor_height(np.concatenate([bowl_h, stray_h, floor_h[:25]]),
                         np.concatenate([bowl_r, stray_r, floor_r[:25]]), band, 20)
    assert faint[0] is None, faint[1]  # a level only a few times denser must also reach wider


def test_floor_under_an_object_rich_in_features_is_found_and_a_rim_is_not():
    """A labelled can holds most of the sparse points, spread over its height; the tiled floor around its
    foot is a thin level, fewer points than the can but much denser than any of the can's own levels, and
    wider. A can without a floor has a bottom rim, not a floor."""
    rng = np.random.default_rng(0)
    n_can = 8000
    angle = rng.uniform(0, 2 * np.pi, n_can)
    can_h = rng.uniform(-0.5, 0.5, n_can)
    can_r = np.full(n_can, 0.2)
    ring_r = 0.2 * np.sqrt(rng.uniform(0.0, 1.0, 400))  # the bottom, seen a little from above
    floor_r = rng.uniform(0.25, 0.9, 800)
    band = 0.02
    heights = np.concatenate([can_h, np.full(400, -0.5), rng.normal(-0.55, 0.004, 800)])
    spread = np.concatenate([can_r, ring_r, floor_r])
    level, found = floor_height(heights, spread, band, 20)
    assert level is not None and abs(level - (-0.55 + band)) < band, found
    without = heights[: n_can + 400], spread[: n_can + 400]
    assert floor_height(*without, band, 20)[0] is None


def test_a_flat_objects_own_level_is_not_a_floor_unless_the_level_goes_on_past_it():
    """A wavy sheet floating in a room gives its sparse points in a few levels, the lowest one dense and as wide
    as the sheet: within the column under the object it looks like a floor. A floor goes on past that column
    (cameras see it behind the object); the sheet's level stops at its edge."""
    rng = np.random.default_rng(2)
    c2w = np.stack([c.c2w for c in synthetic.orbit_cameras(24, radius=3.0)])
    R = np.transpose(c2w[:, :3, :3], (0, 2, 1))
    t = -np.einsum("nij,nj->ni", R, c2w[:, :3, 3])

    def cylinder(n, h, r_lo, r_hi):  # points at heights h, spread uniformly over the ring r_lo..r_hi
        angle, r = rng.uniform(0, 2 * np.pi, n), np.sqrt(rng.uniform(r_lo ** 2, r_hi ** 2, n))
        return np.stack([r * np.cos(angle), h, r * np.sin(angle)], -1)

    above = cylinder(200, rng.uniform(-0.05, 0.5, 200), 0.0, 0.3)
    level = cylinder(300, rng.normal(-0.3, 0.003, 300), 0.0, 0.6)
    onward = cylinder(200, rng.normal(-0.3, 0.003, 200), 1.6, 2.9)  # inside the cameras' ring (radius 3)

    def floor_of(points):  # the floor's height in the world (None: no floor) and what the search found
        cams = SceneCameras(names=[f"{i}" for i in range(len(R))], K=np.eye(3), width=100, height=100, R=R, t=t,
                            points=points, colors=np.zeros((len(points), 3), np.uint8),
                            views=np.zeros((len(points), VIEWS_PER_POINT), np.int32))
        centre, _, _, floor, found, _ = _object_sphere(cams, SceneOptions(), np.array([0.0, 1.0, 0.0]))
        return (None if floor is None else floor + centre[1]), found

    floor, found = floor_of(np.concatenate([above, level]))
    assert floor is None and "0 continuing it past the column" in found, found
    floor, found = floor_of(np.concatenate([above, level, onward]))
    band = SceneOptions().floor_band * 3.0
    assert floor is not None and abs(floor - (-0.3 + band)) < band, found
