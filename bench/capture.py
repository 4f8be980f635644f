"""Benchmark: the capture pipeline (frames -> pycolmap poses -> unit sphere) on a synthetic or a real video.

Synthetic (default): a walk-around of a UV-textured garment from ../shared/data/meshes inside a textured
backdrop, rendered with the synthetic-scene renderer at 1080p and encoded as H.264 (cached in the work
folder: rendering 200 1080p frames takes a while on 2 cores), then ``run_capture`` on it. Reports seconds
per stage, registered frames, reprojection error and, against the true cameras after a similarity
alignment, rotation and camera-centre errors, the focal length error and whether the garment lands inside
the unit sphere with the cameras outside. Real (``--video``): the same without the truth.

Prints a table and writes JSON under bench/results/.

    .venv/bin/python bench/capture.py                                   # 200 frames, 1920x1080, tshirt.obj
    .venv/bin/python bench/capture.py --video ../shared/data/video/beer.mp4
    .venv/bin/python bench/capture.py --width 640 --height 360 --frames 60   # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import time
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neudf_core import synthetic  # noqa: E402
from neudf_core.files import atomic_write  # noqa: E402
from worker.capture.evaluate import load_dataset_cameras, pose_errors  # noqa: E402
from worker.capture.poses import PoseOptions  # noqa: E402
from worker.capture.run import run_capture  # noqa: E402

DEFAULT_MESH = ROOT.parent / "shared" / "data" / "meshes" / "tshirt.obj"
RESULTS = ROOT / "bench" / "results"
ORBIT_RADIUS = 3.0


def load_garment(path: Path):
    """The garment, UV texture kept, moved into its unit sphere (fills 0.8 of it)."""
    import trimesh

    mesh = trimesh.load(path, process=False, force="mesh")
    mesh.apply_transform(np.linalg.inv(synthetic.unit_sphere_transform(mesh)))
    return mesh


def render_video(path: Path, mesh_path: Path, n: int, width: int, height: int, fov_deg: float, chunk: int = 8) -> np.ndarray:
    """Render and encode the walk-around (streamed in chunks to bound memory); returns the true c2w (N, 4, 4)."""
    import av

    from tests.builders import backdrop_sphere, render_scene

    garment = load_garment(mesh_path)
    # The backdrop's texture grows with the frame so its blobs stay a few to a few tens of pixels wide.
    scale = max(1, round(width / 640))
    backdrop = backdrop_sphere(texture_size=(1024 * scale, 512 * scale), n_blobs=3000 * scale * scale,
                               blob_px=(3, 16))
    cameras = synthetic.orbit_cameras(n, ORBIT_RADIUS, width=width, height=height, fov_deg=fov_deg)
    t0 = time.perf_counter()
    with atomic_write(path) as tmp, av.open(str(tmp), mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=Fraction(30))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"crf": "18", "preset": "medium"}  # about what a phone's encoder leaves
        for start in range(0, n, chunk):
            for image in render_scene(garment, backdrop, cameras[start:start + chunk], supersample=1):
                for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                    container.mux(packet)
            done = min(start + chunk, n)
            elapsed = time.perf_counter() - t0
            print(f"  rendered {done}/{n} frames, {elapsed:.0f} s, eta {elapsed / done * (n - done):.0f} s", flush=True)
        for packet in stream.encode():
            container.mux(packet)
    return np.stack([c.c2w for c in cameras])


def printer(label: str = "", every_s: float = 10.0) -> Any:
    """A progress function that prints a line per stage and at most one every ``every_s`` seconds within it."""
    last = [0.0, ""]
    prefix = f"[{label}] " if label else ""

    def report(fraction: float, message: str = "", **info: Any) -> None:
        stage = info.get("stage", "")
        if time.perf_counter() - last[0] > every_s or stage != last[1]:
            print(f"  {prefix}{fraction * 100:5.1f}%  {message}", flush=True)
            last[0], last[1] = time.perf_counter(), stage

    return report


def reuse_capture(source: Path, job: Path) -> None:
    """Give ``job`` the finished capture of ``source`` (same video), so a baseline trains on the same cameras."""
    if (job / "stages" / "scene.json").is_file() or not (source / "stages" / "scene.json").is_file():
        return
    shutil.copytree(source / "data", job / "data", dirs_exist_ok=True)
    (job / "stages").mkdir(parents=True, exist_ok=True)
    for stage in ("frames", "poses", "scene"):
        shutil.copy2(source / "stages" / f"{stage}.json", job / "stages" / f"{stage}.json")


def truth_figures(data: Path, true_c2w: np.ndarray, mesh_path: Path, K_true: np.ndarray) -> dict[str, Any]:
    K, c2w = load_dataset_cameras(data)
    # The frames were downscaled to --max-size: the true focal length in their pixels scales with them.
    capture = json.loads((data / "capture.json").read_text())
    K_true = K_true * capture["image_size"][0] / capture["video"]["width"]
    entries = json.loads((data / "frames.json").read_text())
    truth = true_c2w[[e["frame_index"] for e in entries]]
    err = pose_errors(c2w, truth)
    garment = load_garment(mesh_path)
    vertices = (garment.vertices - err["translation"]) @ err["rotation"] / err["scale"]
    up = err["rotation"] @ np.array([0.0, 1.0, 0.0])
    return {
        "rotation_err_deg_median": float(np.median(err["rotation_deg"])),
        "rotation_err_deg_max": float(err["rotation_deg"].max()),
        "centre_err_pct_radius_rms": float(np.sqrt(np.mean(err["centre_err"] ** 2)) / ORBIT_RADIUS * 100),
        "centre_err_pct_radius_max": float(err["centre_err"].max() / ORBIT_RADIUS * 100),
        "focal_err_pct": float((K[:, 0, 0].mean() / K_true[0, 0] - 1) * 100),
        "up_err_deg": float(np.degrees(np.arccos(np.clip(up[1], -1, 1)))),
        "object_max_radius_unit": float(np.linalg.norm(vertices, axis=1).max()),
        "camera_min_radius_unit": float(np.linalg.norm(c2w[:, :3, 3], axis=1).min()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--video", type=Path, help="A real video instead of the synthetic one.")
    parser.add_argument("--mesh", type=Path, default=DEFAULT_MESH, help="Garment for the synthetic video.")
    parser.add_argument("--frames", type=int, default=200, help="Frames in the synthetic video.")
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--fov", type=float, default=50.0, help="Horizontal field of view, degrees.")
    parser.add_argument("--pick", type=int, default=200, help="Frames the capture picks (--frames of neudf capture).")
    parser.add_argument("--max-size", type=int, default=1600)
    parser.add_argument("--camera-model", default="OPENCV")
    parser.add_argument("--work", type=Path, default=Path("/tmp/neudf-bench-capture"), help="Videos and datasets.")
    parser.add_argument("--name", help="Result name (default: synthetic_<H>p or the video's stem).")
    parser.add_argument("--render-only", action="store_true",
                        help="Render and encode the synthetic video into --work, then stop (to capture it later unloaded).")
    parser.add_argument("--evaluate-only", action="store_true",
                        help="Do not capture again: report the figures of the dataset already in --work.")
    args = parser.parse_args()

    args.work.mkdir(parents=True, exist_ok=True)
    truth: dict[str, Any] | None = None
    render_s = None
    if args.video:
        video, name = args.video, args.name or args.video.stem
    else:
        name = args.name or f"synthetic_{args.mesh.stem}_{args.height}p_{args.frames}"
        video = args.work / f"{name}.mp4"
        cams_file = args.work / f"{name}_c2w.npy"
        if not (video.is_file() and cams_file.is_file()):
            print(f"rendering {args.frames} frames {args.width}x{args.height} of {args.mesh.name} -> {video}")
            t = time.perf_counter()
            np.save(cams_file, render_video(video, args.mesh, args.frames, args.width, args.height, args.fov))
            render_s = time.perf_counter() - t
        truth = {"c2w": np.load(cams_file), "K": synthetic.intrinsics(args.width, args.height, args.fov)}
        if args.render_only:
            print(f"rendered {video}" + (f" in {render_s:.0f} s" if render_s is not None else " (cached)"))
            return

    data = args.work / f"data_{name}"
    print(f"capture {video} -> {data}")
    load_before = os.getloadavg()  # a shared machine: other work slows every stage
    t = time.perf_counter()
    if args.evaluate_only:
        record = json.loads((data / "capture.json").read_text())
        wall = sum(record["seconds"].values())
    else:
        record = run_capture(video, data, n_frames=args.pick, max_size=args.max_size, resume=False,
                             pose_options=PoseOptions(camera_model=args.camera_model), progress=printer())
        wall = time.perf_counter() - t

    result: dict[str, Any] = {
        "name": name, "video": str(video), "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "loadavg_1min_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)]},
        "options": {"pick": args.pick, "max_size": args.max_size, "camera_model": args.camera_model},
        "video_info": {k: record["video"][k] for k in ("width", "height", "frames", "seconds", "codec")},
        "seconds": record["seconds"], "wall_s": round(wall, 1),
        "frames_total": record["frames_total"], "frames_registered": record["frames_registered"],
        "reprojection_error_px": record["reprojection_error_px"], "points": record["points"],
        "camera": record["camera"], "undistorted": record.get("undistorted"),
        "matching": {k: record.get(k) for k in ("pairs_matched", "far_pairs_matched", "far_pairs_dropped", "sequential_only",
                                                 "pose_jumps", "models")},
        "warnings": record.get("warnings", []),
        "scene": record.get("scene"),
    }
    if render_s is not None:
        result["render_s"] = round(render_s, 1)
    if truth is not None:
        result["truth"] = truth_figures(data, truth["c2w"], args.mesh, truth["K"])

    rows = [(f"{stage} (s)", f"{secs:.1f}") for stage, secs in record["seconds"].items()]
    rows += [("total (s)", f"{wall:.1f}"),
             ("frames registered", f"{record['frames_registered']}/{record['frames_total']}"),
             ("reprojection error (px)", f"{record['reprojection_error_px']:.3f}"),
             ("sparse points", str(record["points"])),
             ("pose jumps (after remapping)", str(record.get("pose_jumps"))),
             ("mapped from neighbours in time only", str(record.get("sequential_only")))]
    if truth is not None:
        tf = result["truth"]
        rows += [("rotation error median / max (deg)", f"{tf['rotation_err_deg_median']:.3f} / {tf['rotation_err_deg_max']:.3f}"),
                 ("centre error RMS / max (% radius)", f"{tf['centre_err_pct_radius_rms']:.3f} / {tf['centre_err_pct_radius_max']:.3f}"),
                 ("focal length error (%)", f"{tf['focal_err_pct']:+.2f}"),
                 ("up direction error (deg)", f"{tf['up_err_deg']:.2f}"),
                 ("garment max radius (unit sphere)", f"{tf['object_max_radius_unit']:.3f}"),
                 ("nearest camera radius (unit sphere)", f"{tf['camera_min_radius_unit']:.3f}")]
    width = max(len(r[0]) for r in rows)
    print(f"\ncapture benchmark: {name} ({result['video_info']['width']}x{result['video_info']['height']}, "
          f"{result['video_info']['frames']} frames, {os.cpu_count()} CPUs)")
    for key, value in rows:
        print(f"  {key:<{width}}  {value}")
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / f"capture_{name}.json"
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
