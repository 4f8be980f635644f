"""Are a video job's anchors met by the surface its cameras see, or by a sheet hidden behind it?

For each anchor (the sparse points the point-surface term uses) and one of the frames that saw it
(DATA/object_point_views.npy), the line of sight from that camera to ``--gap`` short of the anchor is
sampled in the trained field; an anchor counts as hidden when Psi falls below ``--eps`` somewhere on it.
Prints the share of hidden anchors by quarter of their height (low to high) and writes JSON.

    .venv/bin/python bench/e2e_sight.py diffavatar_poncho_neudf diffavatar_poncho_neus_sdf
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

from bench.e2e import RESULTS  # noqa: E402
from bench.e2e_sections import garment_of  # noqa: E402
from neudf_core.dataset import load_dataset, read_floor, read_object_point_views, read_object_points  # noqa: E402
from neudf_core.sampler import sight_lines  # noqa: E402
from neudf_core.trainer import load_model, surface_anchors  # noqa: E402


def hidden_share(job: Path, gap: float, eps: float, samples: int) -> dict:
    # every variant of a garment trains on the capture of its NeUDF job (bench/e2e.py)
    data_dir = job.parent / f"{garment_of(job)}_neudf" / "data"
    points = read_object_points(data_dir)
    c2w = load_dataset(data_dir).c2w
    views = read_object_point_views(data_dir, len(points), len(c2w))
    if views is None:
        raise SystemExit(f"{data_dir} has no object_point_views.npy: capture it again with today's scene stage")
    kept = surface_anchors(points, read_floor(data_dir)) & (views[:, 0] >= 0)
    anchors, views = points[kept], views[kept]
    rng = np.random.default_rng(0)
    view = views[np.arange(len(views)), rng.integers((views >= 0).sum(1))]
    torch.manual_seed(0)
    lines, valid = sight_lines(torch.from_numpy(anchors), c2w[torch.from_numpy(view).long(), :3, 3], gap, samples)
    with torch.no_grad():
        psi = load_model(job / "run").udf(lines.reshape(-1, 3)).abs().reshape(lines.shape[:2])
    hidden = ((psi < eps).any(1) & valid).numpy()
    edges = np.quantile(anchors[:, 1], np.linspace(0, 1, 5))
    bands = [float(hidden[(anchors[:, 1] >= lo) & (anchors[:, 1] <= hi)].mean()) for lo, hi in zip(edges[:-1], edges[1:])]
    return {"job": job.name, "anchors": int(len(anchors)), "hidden": float(hidden.mean()), "by_height": bands}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("jobs", nargs="+", help="Job folder names under --work/jobs.")
    parser.add_argument("--work", type=Path, default=Path("/tmp/neudf-bench-e2e"), help="bench/e2e.py's --work.")
    parser.add_argument("--gap", type=float, default=0.03, help="How far short of the anchor a line stops.")
    parser.add_argument("--eps", type=float, default=0.005, help="Psi under this on a line is surface.")
    parser.add_argument("--samples", type=int, default=200, help="Points on each line.")
    parser.add_argument("--out", type=Path, default=RESULTS / "e2e_sight.json")
    args = parser.parse_args()
    rows = [hidden_share(args.work / "jobs" / name, args.gap, args.eps, args.samples) for name in args.jobs]
    print("| job | anchors | hidden | by height, low to high |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {r['job']} | {r['anchors']} | {r['hidden']:.2f} | {' / '.join(f'{b:.2f}' for b in r['by_height'])} |")
    args.out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M:%S"), "gap": args.gap, "eps": args.eps,
                                    "rows": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
