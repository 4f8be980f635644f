"""The capture as a whole (``worker.capture.run`` and ``worker.capture.evaluate``) on a video the tests make.

The main fixture renders a walk-around of a textured wavy sheet inside a textured backdrop sphere (the
backdrop gives SIFT texture with parallax, as a room does), encodes it as H.264 MP4 with PyAV, runs
``neudf capture`` on it once (real PyAV, real pycolmap) and the tests read the result: the contract files,
the poses against the truth, the unit sphere, resuming and cancelling.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from neudf_core import synthetic
from neudf_core.progress import Cancelled
from tests.builders import ORBIT_RADIUS, backdrop_sphere, encode_video, noise_frames, render_scene, textured_sheet
from tests.helpers import worker_cli_app
from worker.capture import frames as frames_stage
from worker.capture import poses as poses_stage
from worker.capture.evaluate import load_dataset_cameras, pose_errors
from worker.capture.records import read_frames_json
from worker.capture.run import run_capture
from worker.errors import StageError


# -- the main capture: a 60-frame walk-around through `neudf capture` ---------------------------------------
N_ORBIT = 60
NOISE_AT, N_NOISE = 30, 3  # a thumb over the lens: frames with nothing in common with the rest


@pytest.fixture(scope="module")
def orbit(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("orbit")
    sheet = textured_sheet()
    cameras = synthetic.orbit_cameras(N_ORBIT, ORBIT_RADIUS, width=320, height=240, fov_deg=50.0)
    images = render_scene(sheet, backdrop_sphere(), cameras)
    images = np.concatenate([images[:NOISE_AT], noise_frames(N_NOISE, 320, 240, seed=7), images[NOISE_AT:]])
    encode_video(root / "orbit.mp4", images)
    # Video frame -> true camera (None for the noise frames).
    camera_of_frame = list(range(NOISE_AT)) + [None] * N_NOISE + list(range(NOISE_AT, N_ORBIT))
    return {"video": root / "orbit.mp4", "cameras": cameras, "mesh": sheet, "root": root,
            "camera_of_frame": camera_of_frame}


@pytest.fixture(scope="module")
def captured(orbit) -> dict:
    from typer.testing import CliRunner

    data = orbit["root"] / "data"
    n_video = N_ORBIT + N_NOISE
    # One pycolmap thread, and a video encoded on one thread (encode_video): with more threads either one
    # varies from run to run, and the poses with it.
    result = CliRunner().invoke(worker_cli_app(), ["capture", str(orbit["video"]), "--out", str(data),
                                                "--frames", str(n_video), "--threads", "1"])
    assert result.exit_code == 0, result.output
    capture = json.loads((data / "capture.json").read_text())
    K, c2w = load_dataset_cameras(data)
    entries = json.loads((data / "frames.json").read_text())
    cams = [orbit["camera_of_frame"][e["frame_index"]] for e in entries]
    assert None not in cams, "a noise frame registered"
    truth = np.stack([orbit["cameras"][i].c2w for i in cams])
    return {"data": data, "capture": capture, "K": K, "c2w": c2w, "entries": entries, "truth": truth,
            "errors": pose_errors(c2w, truth), "output": result.output}


@pytest.mark.slow
def test_capture_writes_the_contract_files(captured):
    data, capture = captured["data"], captured["capture"]
    for name in ("cameras_sphere.npz", "frames.json", "capture.json", "cameras.png"):
        assert (data / name).is_file(), name
    images = sorted(p.name for p in (data / "image").glob("*.png"))
    assert images == [e["file"] for e in captured["entries"]]  # frames.json follows image/, in order
    assert set(captured["entries"][0]) == {"file", "frame_index", "time_s", "sharpness"}
    indices = [e["frame_index"] for e in captured["entries"]]
    assert indices == sorted(indices)
    assert len(captured["c2w"]) == len(images) == capture["frames_registered"]
    for key in ("frames_total", "frames_registered", "reprojection_error_px", "seconds", "points"):
        assert key in capture, key
    assert {"frames", "features", "matching", "mapping", "scene"} <= set(capture["seconds"])
    assert capture["frames_total"] == N_ORBIT + N_NOISE
    assert Image.open(data / "cameras.png").size[0] >= 400
    assert "frames registered" in captured["output"]


@pytest.mark.slow
def test_most_frames_register_and_unregistered_ones_are_dropped(captured):
    capture = captured["capture"]
    assert capture["frames_registered"] >= 0.9 * N_ORBIT
    assert capture["frames_registered"] <= N_ORBIT  # the noise frames are not posed...
    indices = {e["frame_index"] for e in captured["entries"]}
    assert not indices & set(range(NOISE_AT, NOISE_AT + N_NOISE))  # ...nor kept in image/ and frames.json
    assert capture["reprojection_error_px"] < 1.0
    assert capture["pose_jumps"] == 0
    n = capture["frames_total"]
    assert capture["pairs_matched"] < n * (n - 1) / 2  # a video is matched sequentially, not all pairs
    assert capture["far_pairs_matched"] == 0 and capture["sequential_only"]  # a smooth orbit needs no far pair
    assert capture["mapper"] == "global"  # and mapped at once


@pytest.mark.slow
def test_cameras_agree_with_the_truth_up_to_a_similarity(captured):
    errors = captured["errors"]
    assert np.median(errors["rotation_deg"]) < 0.5
    # In some runs a single frame comes out 1.1-2.0 degrees off while the median stays at 0.1-0.3; where it
    # could be seen it was the orbit's last frame, which has neighbours on one side only.
    assert np.quantile(errors["rotation_deg"], 0.95) < 1.0
    assert errors["rotation_deg"].max() < 3.0
    rms_centre = np.sqrt(np.mean(errors["centre_err"] ** 2))
    # 2%, not 1%: one run in the whole suite gave 1.4% (0.041), others stay well under 1%
    assert rms_centre < 0.02 * ORBIT_RADIUS
    true_focal = synthetic.intrinsics(320, 240, 50.0)[0, 0]
    # Focal length and distortion trade off on this small orbit, and pycolmap's answer differs between machines
    # even on one thread: under 5% long on earlier ones, 5.2% on another (k1 0.04 taking up part of it).
    assert abs(captured["K"][:, 0, 0].mean() / true_focal - 1) < 0.08


@pytest.mark.slow
@pytest.mark.parametrize("jumping", [1, 2])
def test_a_sequence_that_jumps_calls_in_the_far_pairs_and_drops_them_if_they_jump(captured, orbit, tmp_path,
                                                                                  monkeypatch, jumping):
    import shutil

    import pycolmap

    data = tmp_path / "data"  # the capture's registered frames, posed again
    shutil.copytree(captured["data"] / "image", data / "image")
    shutil.copy(captured["data"] / "frames.json", data / "frames.json")
    real_jumps, calls = poses_stage.pose_jumps, []

    def first_mappings_jump(model, factor=10.0):  # as a blurry stretch, then a wrong far pair, would make them
        calls.append(model.num_reg_images())
        return [("000.png", "001.png")] if len(calls) <= jumping else real_jumps(model, factor)

    monkeypatch.setattr(poses_stage, "pose_jumps", first_mappings_jump)
    figures = poses_stage.estimate_poses(data, options=poses_stage.PoseOptions(num_threads=1))
    assert len(calls) == jumping + 1  # neighbours alone, with the far pairs, and without them incrementally
    assert figures["far_pairs_matched"] > 0 and figures["pose_jumps"] == 0
    record = json.loads((data / "colmap" / "poses.json").read_text())
    if jumping == 1:  # the far pairs held: they stay in the model
        assert figures["mapper"] == "global" and not figures["sequential_only"]
        assert record["model_dir"].startswith("sparse_far")
    else:
        assert figures["mapper"] == "incremental" and figures["sequential_only"]
        assert figures["far_pairs_dropped"] > 0
        assert record["model_dir"].startswith("sparse_sequential_incremental")
    model = pycolmap.Reconstruction(str(data / "colmap" / record["model_dir"]))
    posed = {im.name: np.linalg.inv(np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]]))
             for im in model.images.values() if im.has_pose}
    assert len(posed) >= 0.9 * len(captured["entries"])
    keep = [i for i, e in enumerate(captured["entries"]) if e["file"] in posed]
    est = np.stack([posed[captured["entries"][i]["file"]] for i in keep])
    errors = pose_errors(est, captured["truth"][keep])
    assert np.median(errors["rotation_deg"]) < 0.5
    assert np.sqrt(np.mean(errors["centre_err"] ** 2)) < 0.02 * ORBIT_RADIUS


@pytest.mark.slow
def test_a_model_from_neighbours_in_time_is_kept_when_the_far_pairs_make_none(captured, tmp_path, monkeypatch):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(captured["data"] / "image", data / "image")
    shutil.copy(captured["data"] / "frames.json", data / "frames.json")
    real_map, real_jumps, calls = poses_stage._map, poses_stage.pose_jumps, []

    def far_mapping_fails(db, image_dir, out, *args, **kwargs):
        if out.name == poses_stage.FAR_MODELS:  # as a wrong far pair can leave no model at all
            raise poses_stage.StageError("poses", "no model", "registration")
        return real_map(db, image_dir, out, *args, **kwargs)

    def first_mapping_jumps(model, factor=10.0):
        calls.append(model.num_reg_images())
        return [("000.png", "001.png")] if len(calls) == 1 else real_jumps(model, factor)

    monkeypatch.setattr(poses_stage, "_map", far_mapping_fails)
    monkeypatch.setattr(poses_stage, "pose_jumps", first_mapping_jumps)
    figures = poses_stage.estimate_poses(data, options=poses_stage.PoseOptions(num_threads=1))
    assert figures["far_pairs_matched"] > 0 and figures["sequential_only"]
    assert figures["frames_registered"] == calls[0] >= 0.9 * len(captured["entries"])
    record = json.loads((data / "colmap" / "poses.json").read_text())
    assert record["model_dir"].startswith("sparse/")
    assert any("jump" in w for w in figures.get("warnings", []))  # the first mapping's (made-up) jump is reported


def test_alignment_undoes_a_similarity_and_is_not_tilted_by_centre_noise():
    truth = np.stack([c.c2w for c in synthetic.orbit_cameras(40, ORBIT_RADIUS, elevation_deg=(0.0, 0.0))])
    from scipy.spatial.transform import Rotation

    R0 = Rotation.from_rotvec(np.radians(70.0) * np.array([0.3, -1.0, 0.5]) / np.linalg.norm([0.3, -1.0, 0.5])).as_matrix()
    s0, t0 = 0.37, np.array([1.0, -2.0, 0.5])
    est = truth.copy()  # the truth seen in another frame: est = similarity^-1(truth)
    est[:, :3, :3] = R0.T @ truth[:, :3, :3]
    est[:, :3, 3] = (truth[:, :3, 3] - t0) @ R0 / s0
    exact = pose_errors(est, truth)
    assert np.allclose(exact["rotation"], R0, atol=1e-9) and exact["scale"] == pytest.approx(s0)
    assert exact["rotation_deg"].max() < 1e-5 and exact["centre_err"].max() < 1e-9
    # Centres off by up to 1% of the radius, out of the orbit's plane, up on one half and down on the other: a fit to the centres
    # alone would tilt every camera; the orientations hold the rotation.
    rng = np.random.default_rng(0)
    noisy = est.copy()
    lift = np.where(np.arange(40) < 20, 1.0, -1.0) * 0.01 * ORBIT_RADIUS / s0 * rng.uniform(0.5, 1.0, 40)
    noisy[:, :3, 3] += lift[:, None] * (R0.T @ np.array([0.0, 1.0, 0.0]))
    errors = pose_errors(noisy, truth)
    assert errors["rotation_deg"].max() < 0.2  # centres alone: about 0.6 degrees
    assert np.sqrt(np.mean(errors["centre_err"] ** 2)) < 0.01 * ORBIT_RADIUS


@pytest.mark.slow
def test_object_inside_the_unit_sphere_and_cameras_outside(captured, orbit):
    errors = captured["errors"]
    # Truth -> the dataset's unit sphere: the inverse of the similarity that aligned estimate to truth.
    vertices = (orbit["mesh"].vertices - errors["translation"]) @ errors["rotation"] / errors["scale"]
    radii = np.linalg.norm(vertices, axis=1)
    assert radii.max() < 1.0
    assert radii.max() > 0.4  # and fills a fair part of it
    assert np.linalg.norm(captured["c2w"][:, :3, 3], axis=1).min() > 1.0


@pytest.mark.slow
def test_world_is_upright(captured):
    # The dataset's +y (up), carried into the truth frame, is the truth's up (+y: the orbit's axis).
    up = captured["errors"]["rotation"] @ np.array([0.0, 1.0, 0.0])
    assert np.degrees(np.arccos(np.clip(up[1], -1, 1))) < 5.0


@pytest.mark.slow
def test_finished_capture_resumes_without_work(captured, orbit):
    npz = captured["data"] / "cameras_sphere.npz"
    before = npz.stat().st_mtime_ns
    reports = []
    # the fixture ran pycolmap on one thread, this asks for all cores: how it runs is no reason to redo poses
    run_capture(orbit["video"], captured["data"], n_frames=N_ORBIT + N_NOISE,
                progress=lambda f, m="", **info: reports.append(info))
    assert [r["stage"] for r in reports if r.get("skipped")] == ["frames", "poses", "scene"]
    assert npz.stat().st_mtime_ns == before


def test_cancel_stops_the_capture_and_a_rerun_resumes_after_the_last_finished_stage(small_videos, tmp_path):
    data = tmp_path / "data"

    def cancel_during_sift(fraction: float, message: str = "", **info) -> None:
        if info.get("stage") == "poses" and "SIFT features 16/" in message:
            raise Cancelled()

    with pytest.raises(Cancelled):
        run_capture(small_videos["ok"], data, n_frames=24, progress=cancel_during_sift)
    assert frames_stage.is_done(data) and not poses_stage.is_done(data)
    reports: list[dict] = []
    with pytest.raises(StageError) as exc:  # noise frames never register; what matters is what ran
        run_capture(small_videos["ok"], data, n_frames=24, progress=lambda f, m="", **info: reports.append(info))
    assert exc.value.stage == "poses" and exc.value.kind == "registration"
    assert [r["stage"] for r in reports if r.get("skipped")] == ["frames"]
    reports.clear()  # other options: nothing is reused
    with pytest.raises(StageError):
        run_capture(small_videos["ok"], data, n_frames=20, progress=lambda f, m="", **info: reports.append(info))
    assert not [r for r in reports if r.get("skipped")]
    assert len(read_frames_json(data)) == 20
