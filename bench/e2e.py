"""Benchmark of record: what a user gets from a phone video of a garment, with the defaults.

Each garment of ../shared/data/meshes is rendered as a handheld walk-around phone video (portrait 720x1280,
8 s at 30 fps, H.264), hanging above a textured floor in a textured room with boxes standing about, its
shadow on the floor (cached in --work). Then the same code path as ``neudf reconstruct``
(``worker.pipeline.run_pipeline``) with default options, on this machine's default device. The mesh is
moved into the ground truth's frame by the similarity that maps the estimated cameras onto the true ones,
and compared with the garment (CONTRACT's convention: Chamfer and F-score at 0.01 in GT's unit sphere,
boundary loops against GT's). Prints a table, writes JSON under bench/results/ and, per garment, a picture
of the ground truth beside the result from the same camera.

    .venv/bin/python bench/e2e.py                                  # the five garments, the defaults
    .venv/bin/python bench/e2e.py --meshes tshirt --weight neus_sdf   # the closed-surface baseline, same capture
    .venv/bin/python bench/e2e.py --render-only                    # cache the videos, train nothing
    .venv/bin/python bench/e2e.py --capture-only                   # videos and their capture, train nothing
    .venv/bin/python bench/e2e.py --meshes bowl flag --out bench/results/e2e_held_out_cpu.json  # held-out shapes

Besides the garments, ``--meshes`` takes the held-out shapes ``bowl`` (a hemisphere open at the top, one
opening), ``flag`` (a wavy sheet standing upright) and ``holed_sheet`` (a flat sheet with a round hole):
open surfaces that no default was tuned on, written as OBJ files into --work and filmed the same way.

``--weight neus_sdf`` (or a ``--tag``) reuses the capture (frames, poses, scene) of the NeUDF job of the same
garment when it is in --work, so every variant sees the same cameras.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.capture import printer, reuse_capture  # noqa: E402
from neudf_core import synthetic  # noqa: E402
from neudf_core.metrics import evaluate, load_mesh  # noqa: E402
from neudf_core.device import resolve_device  # noqa: E402
from neudf_core.files import atomic_write  # noqa: E402
from worker.capture.evaluate import align_cameras, load_dataset_cameras, pose_errors  # noqa: E402
from neudf_core.progress import Cancelled  # noqa: E402
from worker.pipeline import JobOptions, run_pipeline  # noqa: E402

MESH_DIR = ROOT.parent / "shared" / "data" / "meshes"
RESULTS = ROOT / "bench" / "results"
PICTURES = ROOT / "docs" / "images"
WIDTH, HEIGHT, FPS, SECONDS = 720, 1280, 30, 8


HELD_OUT = ("bowl", "flag", "holed_sheet")


def held_out_shape(name: str, work: Path) -> Path:
    """Write a held-out open surface as OBJ (no texture: the renderer paints a procedural one) and return it."""
    if name == "bowl":
        mesh = synthetic.procedural_mesh("bowl", subdivisions=64)
    elif name == "flag":  # the wavy sheet turned upright, as a flag or a curtain hangs
        mesh = synthetic.procedural_mesh("wavy_sheet", subdivisions=64)
        mesh.apply_transform(synthetic.trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0]))
    elif name == "holed_sheet":
        mesh = synthetic.procedural_mesh("sheet_with_hole", subdivisions=64)
        mesh.apply_transform(synthetic.trimesh.transformations.rotation_matrix(0.3, [1.0, 0.0, 0.0]))
    else:
        raise ValueError(name)
    path = work / "shapes" / f"{name}.obj"
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)
    return path


def garments(names: list[str] | None, work: Path) -> list[Path]:
    found = sorted(MESH_DIR.glob("*.obj"))
    if names:
        found = [p for p in found if p.stem in names] + [held_out_shape(n, work) for n in names if n in HELD_OUT]
        missing = set(names) - {p.stem for p in found}
        if missing:
            raise SystemExit(f"no such garment in {MESH_DIR} nor held-out shape ({', '.join(HELD_OUT)}): "
                             f"{', '.join(sorted(missing))}")
    return found


def load_garment(path: Path):
    """The garment, texture kept, moved into its unit sphere (fills 0.8 of it): the frame the video is shot in."""
    import trimesh

    mesh = trimesh.load(path, process=False, force="mesh")
    mesh.apply_transform(np.linalg.inv(synthetic.unit_sphere_transform(mesh)))
    return mesh


def render_video(path: Path, garment, seed: int, chunk: int = 8) -> np.ndarray:
    """Render and encode the walk-around in chunks (bounded memory); returns the true c2w (N, 4, 4)."""
    import av

    room = synthetic.room_scene(garment, seed=seed)
    cameras = synthetic.handheld_orbit(FPS * SECONDS, width=WIDTH, height=HEIGHT, seed=seed)
    t0 = time.perf_counter()
    with atomic_write(path) as tmp, av.open(str(tmp), mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=Fraction(FPS))
        stream.width, stream.height, stream.pix_fmt = WIDTH, HEIGHT, "yuv420p"
        stream.options = {"crf": "20", "preset": "medium"}  # about what a phone's encoder leaves
        for start in range(0, len(cameras), chunk):
            images, _ = synthetic.render_room(room, cameras[start:start + chunk], seed=seed)
            for image in images:
                for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                    container.mux(packet)
            done = min(start + chunk, len(cameras))
            print(f"  rendered {done}/{len(cameras)} frames, {time.perf_counter() - t0:.0f} s", flush=True)
        for packet in stream.encode():
            container.mux(packet)
    return np.stack([c.c2w for c in cameras])


def cached_video(work: Path, mesh_path: Path, seed: int) -> tuple[Path, np.ndarray]:
    video, cams = work / "videos" / f"{mesh_path.stem}.mp4", work / "videos" / f"{mesh_path.stem}_c2w.npy"
    if not (video.is_file() and cams.is_file()):
        video.parent.mkdir(parents=True, exist_ok=True)
        print(f"rendering {mesh_path.stem}: {FPS * SECONDS} frames {WIDTH}x{HEIGHT} -> {video}", flush=True)
        np.save(cams, render_video(video, load_garment(mesh_path), seed))
    return video, np.load(cams)


def camera_similarity(job: Path, true_c2w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(s, R, t) taking the job's unit sphere onto the true world (x -> s R x + t), by its estimated cameras
    against the true ones of the same frames; also both camera sets."""
    _, est = load_dataset_cameras(job / "data")
    entries = json.loads((job / "data" / "frames.json").read_text())
    truth = true_c2w[[e["frame_index"] for e in entries]]
    s, R, t = align_cameras(est, truth)
    return s, R, t, est, truth


def aligned_mesh(job: Path, true_c2w: np.ndarray, mesh: Any = None) -> tuple[Any, dict[str, float]]:
    """The job's mesh (or ``mesh``, in the job's unit sphere) moved into the true world by the camera
    similarity, and how far the estimated cameras are from the true ones after it."""
    mesh = load_mesh(job / "mesh" / "mesh.ply") if mesh is None else mesh.copy()
    s, R, t, est, truth = camera_similarity(job, true_c2w)
    mesh.vertices = s * np.asarray(mesh.vertices) @ R.T + t
    errors = pose_errors(est, truth)
    orbit = float(np.median(np.linalg.norm(truth[:, :3, 3], axis=1)))
    Ks, _ = load_dataset_cameras(job / "data")  # undistorted frames at the video's size
    true_f = synthetic.handheld_orbit(1, width=WIDTH, height=HEIGHT)[0].K[0, 0]
    return mesh, {"rotation_deg_median": round(float(np.median(errors["rotation_deg"])), 4),
                  "centre_rms_of_orbit": round(float(np.sqrt(np.mean(errors["centre_err"] ** 2))) / orbit, 5),
                  "focal_error": round(float(np.median(Ks[:, 0, 0])) / true_f - 1.0, 4)}


def picture(path: Path, gt, pred, size: int = 320) -> None:
    """Ground truth (left) and the result (right), rendered from the same camera on white."""
    from PIL import Image

    cam = synthetic.Camera(synthetic.intrinsics(size, size, 40.0),
                           synthetic.look_at(np.array([1.6, 0.9, 2.6]), np.zeros(3)), size, size)
    panels = []
    for mesh in (gt, pred):
        plain = mesh.copy()
        plain.visual = synthetic.trimesh.visual.ColorVisuals(plain, vertex_colors=[200, 200, 205, 255])
        image, _ = synthetic.render(plain, [cam], "white")
        panels.append(image[0])
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(panels, axis=1)).save(path)


def gallery(names: list[str], weight: str, path: Path, side: int = 240) -> None:
    """One picture of every garment: the ground truth above, the default job's mesh below (their pictures)."""
    from PIL import Image, ImageDraw

    columns = []
    for name in names:
        pair = np.asarray(Image.open(PICTURES / f"e2e_{name}_{weight}.png").convert("RGB"))
        half, pad = pair.shape[1] // 2, (pair.shape[1] // 2 - side) // 2
        crop = lambda a: a[pad // 2: half - pad // 2, pad: pad + side]  # noqa: E731  (less of the white margin)
        columns.append(np.concatenate([crop(pair[:, :half]), crop(pair[:, half:])], 0))
    image = Image.fromarray(np.concatenate(columns, 1))
    draw = ImageDraw.Draw(image)
    for i, name in enumerate(names):
        draw.text((i * side + 8, 4), name + (" (ground truth)" if i == 0 else ""), fill=(60, 60, 60))
    draw.text((4, image.height // 2 + 4), f"{weight}, defaults, from the video", fill=(60, 60, 60))
    image.save(path)


def run_garment(mesh_path: Path, args: argparse.Namespace, device: str) -> dict[str, Any]:
    name = mesh_path.stem
    video, true_c2w = cached_video(args.work, mesh_path, args.seed)
    job = args.work / "jobs" / "_".join([name, args.weight] + [x for x in (args.preset, args.tag) if x])
    if job.name != f"{name}_neudf":
        reuse_capture(args.work / "jobs" / f"{name}_neudf", job)
    chosen = {k: v for k, v in (("minutes", args.minutes), ("preset", args.preset)) if v is not None}
    options = JobOptions(weight=args.weight, **chosen)
    t0 = time.perf_counter()
    metrics = run_pipeline(video, job, options, printer(name, every_s=30), device=device)
    wall = time.perf_counter() - t0
    stages = {s: json.loads((job / "stages" / f"{s}.json").read_text()) for s in
              ("frames", "poses", "scene", "train", "mesh", "export")}
    gt = load_garment(mesh_path)
    pred, cameras = aligned_mesh(job, true_c2w)
    figures = evaluate(pred, gt)
    picture(PICTURES / f"e2e_{job.name}.png", gt, pred)
    return {
        "mesh": name, "weight": args.weight, "device": device,
        "train_device": stages["train"]["metrics"].get("device", device), "options": options.model_dump(exclude_none=True),
        "chamfer": figures["chamfer"], "fscore": figures["fscore"],
        "boundary_loops_pred": figures["boundary_loops_pred"], "boundary_loops_gt": figures["boundary_loops_gt"],
        "faces": int(len(pred.faces)),
        "minutes": {s: round(rec["seconds"] / 60, 2) for s, rec in stages.items()},
        "minutes_total": round(sum(rec["seconds"] for rec in stages.values()) / 60, 2),
        "wall_minutes_this_run": round(wall / 60, 2),
        "camera_error": cameras,
        "frames_registered": metrics.get("frames_registered"), "frames_total": metrics.get("frames_total"),
        "train": {k: stages["train"]["metrics"].get(k) for k in ("iters", "train_psnr", "stopped_by", "images",
                                                                    "surface_points", "sight_points", "start")},
    }


def capture_only(mesh_path: Path, args: argparse.Namespace, device: str) -> None:
    """Frames, poses and the scene of a garment's NeUDF job, so that variants can train on them later."""
    video, _ = cached_video(args.work, mesh_path, args.seed)
    show = printer(mesh_path.stem, every_s=30)

    def report(fraction: float, message: str = "", **info: Any) -> None:
        if info.get("stage") == "train" and info.get("event") == "start":
            raise Cancelled("capture done")
        show(fraction, message, **info)

    try:
        run_pipeline(video, args.work / "jobs" / f"{mesh_path.stem}_neudf", JobOptions(), report, device=device)
    except Cancelled:
        pass


def print_table(rows: list[dict[str, Any]]) -> None:
    head = "| garment | method | Chamfer x1e-3 | F-score | loops (GT) | faces | min: frames / poses / scene / train / mesh / export | total min |"
    print(head)
    print("|---" * 8 + "|")
    for r in rows:
        if "error" in r:
            print(f"| {r['mesh']} | {r['weight']} | failed: {r['error']} | | | | | |")
            continue
        m = r["minutes"]
        stages = " / ".join(f"{m[s]:.1f}" for s in ("frames", "poses", "scene", "train", "mesh", "export"))
        print(f"| {r['mesh']} | {r['weight']} | {r['chamfer'] * 1e3:.1f} | {r['fscore']:.2f} | "
              f"{r['boundary_loops_pred']} ({r['boundary_loops_gt']}) | {r['faces']} | {stages} | "
              f"{r['minutes_total']:.1f} |")
    ok = [r for r in rows if "error" not in r]
    if ok:
        print(f"mean Chamfer x1e-3: {np.mean([r['chamfer'] for r in ok]) * 1e3:.1f} over {len(ok)} garments")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="*", help="Garment names (default: every mesh in ../shared/data/meshes).")
    parser.add_argument("--weight", default="neudf", choices=["neudf", "neus_sdf", "neus_abs"])
    parser.add_argument("--minutes", type=float, help="Training budget (default: the job default).")
    parser.add_argument("--preset", help="Training preset (default: the device's).")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--seed", type=int, default=0, help="Seed of the room and the camera path.")
    parser.add_argument("--work", type=Path, default=Path("/tmp/neudf-bench-e2e"), help="Videos and job folders.")
    parser.add_argument("--out", type=Path, help="JSON report (default bench/results/e2e_<weight>_<device>.json).")
    parser.add_argument("--tag", help="Name of a variant: its own job folder, the NeUDF job's capture.")
    parser.add_argument("--render-only", action="store_true", help="Render and cache the videos, then stop.")
    parser.add_argument("--capture-only", action="store_true", help="Videos and their capture, then stop.")
    args = parser.parse_args()

    device = resolve_device(args.device)
    meshes = garments(args.meshes, args.work)
    if args.render_only:
        for path in meshes:
            cached_video(args.work, path, args.seed)
        return
    if args.capture_only:
        for path in meshes:
            capture_only(path, args, device)
        return
    out = args.out or RESULTS / f"e2e_{args.weight}_{device}{'_' + args.tag if args.tag else ''}.json"
    previous = json.loads(out.read_text())["rows"] if out.is_file() else []
    rows = [r for r in previous if r["mesh"] not in {p.stem for p in meshes}]
    for path in meshes:
        try:
            rows.append(run_garment(path, args, device))
        except Exception as exc:  # one failed garment is a row with its error, not a lost table
            rows.append({"mesh": path.stem, "weight": args.weight, "error": f"{type(exc).__name__}: {exc}"})
        rows.sort(key=lambda r: r["mesh"])
        RESULTS.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({
            "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "device": device},
            "video": {"width": WIDTH, "height": HEIGHT, "fps": FPS, "seconds": SECONDS, "seed": args.seed},
            "rows": rows}, indent=2))
        print_table(rows)
    print(f"wrote {out}")
    pictured = [r["mesh"] for r in rows if "error" not in r and r["mesh"] not in HELD_OUT
                and (PICTURES / f"e2e_{r['mesh']}_{r['weight']}.png").is_file()]
    if not (args.tag or args.preset) and pictured:  # the defaults' run on garments: the README's picture
        gallery(pictured, args.weight, PICTURES / f"e2e_garments_{args.weight}.png")


if __name__ == "__main__":
    main()
