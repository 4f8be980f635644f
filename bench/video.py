"""What the defaults make of a real phone video: ``neudf reconstruct``'s code path, minutes per stage, and a
picture of the mesh from three sides (plain above, in its vertex colours below).

A real video has no ground truth, so the figures are what a person would look at: faces, boundary loops,
the mesh's extent, and how much of it lies on the floor the scene stage found (a shadow or a floor drawn
as surface shows up there; an object standing on the floor touches it with its foot only).

    .venv/bin/python bench/video.py                       # ../shared/data/video/beer.mp4, the defaults
    .venv/bin/python bench/video.py clip.mp4 --minutes 5  # another video, another budget
    .venv/bin/python bench/video.py --preset P --tag T    # a variant on the default job's capture

Writes bench/results/video_<name>_<device>[_<tag>].json and docs/images/video_<name>[_<tag>].png.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.capture import printer, reuse_capture  # noqa: E402
from neudf_core import synthetic  # noqa: E402
from neudf_core.dataset import read_floor  # noqa: E402
from neudf_core.device import resolve_device  # noqa: E402
from neudf_core.metrics import boundary_loops, load_mesh  # noqa: E402
from worker.pipeline import JobOptions, run_pipeline  # noqa: E402

VIDEO = ROOT.parent / "shared" / "data" / "video" / "beer.mp4"
RESULTS = ROOT / "bench" / "results"
PICTURES = ROOT / "docs" / "images"
STAGES = ("frames", "poses", "scene", "train", "mesh", "export")
FLOOR_BAND = 0.05  # unit sphere: faces this close above the floor cut count as lying on it


def floor_figures(mesh, floor_y: float | None) -> dict[str, Any]:
    """Share of the mesh's area within FLOOR_BAND above the floor cut, and how wide that part spreads."""
    if floor_y is None:
        return {"floor_y": None}
    centres = mesh.triangles_center
    low = centres[:, 1] < floor_y + FLOOR_BAND
    area = mesh.area_faces
    spread = float(np.ptp(centres[low][:, [0, 2]], axis=0).max()) if low.any() else 0.0
    return {"floor_y": floor_y, "area_share_on_floor": round(float(area[low].sum() / area.sum()), 4),
            "width_on_floor": round(spread, 3)}


def picture(path: Path, mesh, size: int = 300) -> None:
    """Three views round the mesh (unit sphere, y up): plain grey above, vertex colours below."""
    from PIL import Image

    eyes = [np.array([2.6 * np.sin(a), 1.0, 2.6 * np.cos(a)]) for a in (0.0, 2 * np.pi / 3, 4 * np.pi / 3)]
    cams = [synthetic.Camera(synthetic.intrinsics(size, size, 40.0), synthetic.look_at(e, np.zeros(3)), size, size)
            for e in eyes]
    plain = mesh.copy()
    plain.visual = synthetic.trimesh.visual.ColorVisuals(plain, vertex_colors=[200, 200, 205, 255])
    grey, _ = synthetic.render(plain, cams, "white")
    rows = [np.concatenate(list(grey), axis=1)]
    if mesh.visual.kind == "vertex":
        colour, _ = synthetic.render(mesh, cams, "white", lit=False)
        rows.append(np.concatenate(list(colour), axis=1))
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("video", nargs="?", type=Path, default=VIDEO)
    parser.add_argument("--minutes", type=float, help="Training budget (default: the job default).")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--preset", help="Training preset (default: the device's).")
    parser.add_argument("--tag", help="Name of a variant: its own job folder and JSON, the default job's capture.")
    parser.add_argument("--work", type=Path, default=Path("/tmp/neudf-bench-video"), help="Job folders.")
    args = parser.parse_args()
    if not args.video.is_file():
        raise SystemExit(f"no such video: {args.video}")

    device = resolve_device(args.device)
    name = args.video.stem
    variant = [args.tag] if args.tag else []
    job = args.work / "_".join([name, device] + variant)
    if args.tag:
        reuse_capture(args.work / f"{name}_{device}", job)
    chosen = {k: v for k, v in (("minutes", args.minutes), ("preset", args.preset)) if v is not None}
    options = JobOptions(**chosen)
    t0 = time.perf_counter()
    metrics = run_pipeline(args.video, job, options, printer(name, every_s=30), device=device)
    wall = time.perf_counter() - t0
    stages = {s: json.loads((job / "stages" / f"{s}.json").read_text()) for s in STAGES}
    mesh = load_mesh(job / "mesh" / "mesh.ply")
    image = PICTURES / f"video_{'_'.join([name] + variant)}.png"
    picture(image, mesh)
    lo, hi = mesh.bounds
    row = {
        "video": name, "device": device, "options": options.model_dump(exclude_none=True),
        "faces": int(len(mesh.faces)), "boundary_loops": boundary_loops(mesh),
        "extent": [round(float(v), 3) for v in hi - lo], "lowest_y": round(float(lo[1]), 3),
        **floor_figures(mesh, read_floor(job / "data")),
        "minutes": {s: round(rec["seconds"] / 60, 2) for s, rec in stages.items()},
        "minutes_total": round(sum(rec["seconds"] for rec in stages.values()) / 60, 2),
        "wall_minutes_this_run": round(wall / 60, 2),
        "frames_registered": metrics.get("frames_registered"), "frames_total": metrics.get("frames_total"),
        "train": {k: stages["train"]["metrics"].get(k) for k in ("iters", "train_psnr", "stopped_by", "images")},
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / f"video_{job.name}.json"
    out.write_text(json.dumps(row, indent=2))
    m = row["minutes"]
    print("| video | faces | loops | on the floor (area share, width) | min: " + " / ".join(STAGES) + " | total min |")
    print("|---|---|---|---|---|---|")
    on_floor = (f"{row['area_share_on_floor']:.3f}, {row['width_on_floor']:.2f}" if row["floor_y"] is not None
                else "no floor found")
    print(f"| {name} | {row['faces']} | {row['boundary_loops']} | {on_floor} | "
          f"{' / '.join(f'{m[s]:.1f}' for s in STAGES)} | {row['minutes_total']:.1f} |")
    print(f"wrote {out} and {image}")


if __name__ == "__main__":
    main()
