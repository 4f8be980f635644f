"""Where a video job's mesh misses its garment: horizontal sections of the learned field against the truth.

For jobs that ``bench/e2e.py`` left in --work, and heights in the ground truth's unit sphere (y up): a
picture per job with one panel per height, the field's value before its output activation (h: red
positive, blue negative, dark where the field's surface is, |h| < 0.004) with the true garment's section
drawn in green; and a table of completeness by height (the mean distance from GT's surface to the mesh,
and the share of it farther than 0.05), in four bands of equal GT area. Read together they say whether GT
is missing from the field or only from the mesh, and what stands in its place.

    .venv/bin/python bench/e2e_sections.py diffavatar_poncho_neudf diffavatar_poncho_neus_sdf --heights -0.6
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.e2e import PICTURES, RESULTS, aligned_mesh, camera_similarity, garments, load_garment  # noqa: E402
from neudf_core.metrics import directed_distances, unit_sphere_normalisation  # noqa: E402
from neudf_core.trainer import load_model  # noqa: E402

SIDE = 400  # pixels across GT's unit sphere in a panel
SCALE_H = 0.15  # |h| (GT's units) at full colour
SURFACE_H = 0.004  # |h| drawn as surface


def garment_of(job: Path) -> str:
    """The garment a job folder was made from: its name up to the weight (``<garment>_<weight>[_variant]``)."""
    for weight in ("_neudf", "_neus_sdf", "_neus_abs"):
        if weight in job.name:
            return job.name.split(weight)[0]
    raise SystemExit(f"{job} is not a bench/e2e.py job folder (<garment>_<weight>...)")


def section(model, to_job, y: float, gt_points: np.ndarray, scale: float) -> tuple[np.ndarray, float]:
    """One panel (SIDE x SIDE x 3, uint8): h over the plane at height y, GT's points within a hair of it;
    and the lowest h on the plane (GT's units)."""
    u = np.linspace(-1.0, 1.0, SIDE)
    x, z = np.meshgrid(u, u)
    plane = np.stack([x.ravel(), np.full(x.size, y), z.ravel()], 1)
    with torch.no_grad():
        _, h, _ = model.udf_net.forward_with_raw(torch.tensor(to_job(plane), dtype=torch.float32))
    h = h.numpy().reshape(SIDE, SIDE) * scale
    v = np.clip(h / SCALE_H, -1.0, 1.0)
    image = np.stack([np.where(v < 0, 1 + v, 1.0), 1 - np.abs(v), np.where(v > 0, 1 - v, 1.0)], -1)
    image[np.abs(h) < SURFACE_H] = 0.3
    near = gt_points[np.abs(gt_points[:, 1] - y) < 0.004]
    cols, rows = [((near[:, k] + 1) / 2 * (SIDE - 1)).round().astype(int) for k in (0, 2)]
    image[rows, cols] = (0.0, 0.7, 0.0)
    return (image * 255).astype(np.uint8), float(h.min())


def study(job: Path, work: Path, heights: list[float]) -> dict:
    import trimesh
    from PIL import Image

    name = garment_of(job)
    gt = load_garment(garments([name], work)[0])
    true_c2w = np.load(work / "videos" / f"{name}_c2w.npy")
    pred, _ = aligned_mesh(job, true_c2w)
    _, gt_side, unit = directed_distances(pred, gt)
    centre, _ = unit_sphere_normalisation(gt)
    s, R, t, _, _ = camera_similarity(job, true_c2w)
    model = load_model(job / "run")

    def to_job(p: np.ndarray) -> np.ndarray:  # GT's unit sphere -> the true world -> the job's unit sphere
        return ((p / unit + centre - t) @ R) / s

    unit_gt = gt.copy()
    unit_gt.apply_translation(-centre)
    unit_gt.apply_scale(unit)
    dense, _ = trimesh.sample.sample_surface(unit_gt, 400_000, seed=0)
    panels, lowest = zip(*(section(model, to_job, y, dense, s * unit) for y in heights))
    picture = PICTURES / f"sections_{job.name}.png"
    Image.fromarray(np.concatenate(panels, 1)).save(picture)

    y, d = gt_side["point"][:, 1], gt_side["distance"]
    edges = np.quantile(y, np.linspace(0.0, 1.0, 5))
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (y >= lo) & (y <= hi)
        bands.append({"y": [round(float(lo), 3), round(float(hi), 3)],
                      "completeness": float(d[inside].mean()), "farther_than_0.05": float(np.mean(d[inside] > 0.05))})
    return {"job": job.name, "heights": heights, "lowest_h": [round(v, 4) for v in lowest],
            "picture": str(picture.relative_to(ROOT)), "bands": bands}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("jobs", nargs="+", help="Job folder names under --work/jobs (e.g. diffavatar_poncho_neudf).")
    parser.add_argument("--heights", nargs="+", type=float, default=[-0.75, -0.6, -0.4],
                        help="Heights of the sections in GT's unit sphere (y up).")
    parser.add_argument("--work", type=Path, default=Path("/tmp/neudf-bench-e2e"), help="bench/e2e.py's --work.")
    parser.add_argument("--out", type=Path, default=RESULTS / "e2e_sections.json")
    args = parser.parse_args()
    rows = []
    for name in args.jobs:
        job = args.work / "jobs" / name
        if not (job / "run" / "config.json").is_file() or not (job / "mesh" / "mesh.ply").is_file():
            raise SystemExit(f"{job} holds no trained and meshed job: run bench/e2e.py for it first")
        rows.append(study(job, args.work, args.heights))
    print("| job | completeness x1e-3 by height band, low to high (share farther than 0.05) | lowest h per section |")
    print("|---|---|---|")
    for row in rows:
        cells = " / ".join(f"{b['completeness'] * 1e3:.1f} ({b['farther_than_0.05']:.2f})" for b in row["bands"])
        print(f"| {row['job']} | {cells} | {' / '.join(f'{v:.3f}' for v in row['lowest_h'])} |")
    previous = json.loads(args.out.read_text())["rows"] if args.out.is_file() else []
    rows = [r for r in previous if r["job"] not in {row["job"] for row in rows}] + rows
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M:%S"), "rows": rows}, indent=2))
    print(f"wrote {args.out}; pictures in {PICTURES.relative_to(ROOT)}/sections_<job>.png")


if __name__ == "__main__":
    main()
