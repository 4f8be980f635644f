"""Benchmark: NeUDF's meshes with and without the view offset, on the same trained fields.

`neudf mesh --views` and the service move a NeUDF surface that the cameras see from one side by 1/r
toward them (neudf_core.meshing.offset_toward_views): with the exp varsigma the rendering weight's mean
lies 1/r in front of the zero level, so that is where the images put the surface. This script takes the
run folders bench/quality.py leaves with --work-dir (<work>/<mesh>/data, <work>/<mesh>/neudf[_seedN]),
meshes each NeUDF run once (masked Poisson, faces seen by < --min-seen of the cameras dropped, as
quality.py does), evaluates that mesh before and after the offset, and prints one paired table. Pairs
on one field differ only by the offset, so a gain smaller than the seed-to-seed spread still shows.

    .venv/bin/python bench/view_offset.py /tmp/q                 # after bench/quality.py --work-dir /tmp/q
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neudf_core.dataset import load_cameras  # noqa: E402
from neudf_core.meshing import mesh_run, offset_toward_views, rendered_depth_bias  # noqa: E402
from neudf_core.metrics import evaluate  # noqa: E402
from neudf_core.trainer import load_model  # noqa: E402

KEYS = ("chamfer", "chamfer_pred_to_gt", "chamfer_gt_to_pred", "fscore", "normal_consistency")


def neudf_runs(work: Path) -> list[tuple[str, Path]]:
    """(mesh name, run folder) for every finished NeUDF run under a quality.py work folder."""
    runs = []
    for run in sorted(work.glob("*/neudf*")):
        if not (run / "config.json").is_file():
            continue
        cfg = json.loads((run / "config.json").read_text())
        done = run / "checkpoints" / f"ckpt_{cfg['optim']['iters']:07d}.pt"
        if cfg["renderer"]["weight"] != "neudf":
            continue
        if not done.is_file():
            print(f"skipping {run}: not trained to its {cfg['optim']['iters']} iterations yet")
            continue
        runs.append((run.parent.name, run))
    return runs


def paired_row(name: str, run: Path, args: argparse.Namespace) -> dict:
    data = run.parent / "data"
    gt = trimesh.load(data / "mesh_gt.ply", process=False)
    plain = mesh_run(run, args.scratch / f"{name}_{run.name}.ply", method="spsr", resolution=args.resolution,
                     views=data, min_seen_fraction=args.min_seen, view_offset=False)
    distance = rendered_depth_bias(load_model(run))
    if distance is None:
        raise SystemExit(f"{run}: no view offset for this renderer (it needs NeUDF's weight with the exp varsigma)")
    moved, count = offset_toward_views(plain, load_cameras(data), distance, tol=2.0 * plain.metadata["meshing"]["voxel"])
    before, after = (evaluate(m, gt, n_samples=args.samples) for m in (plain, moved))
    return {"mesh": name, "run": run.name, "view_offset": distance, "vertices_offset": count,
            "vertices": len(plain.vertices), "before": {k: before[k] for k in KEYS}, "after": {k: after[k] for k in KEYS}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path, help="a bench/quality.py --work-dir")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--min-seen", type=float, default=0.15)
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--meshes", nargs="*", default=None, help="only these meshes (default: every one found)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "view_offset.json")
    args = ap.parse_args()
    args.scratch = args.work / "view_offset_meshes"
    args.scratch.mkdir(exist_ok=True)

    runs = [(n, r) for n, r in neudf_runs(args.work) if args.meshes is None or n in args.meshes]
    if not runs:
        raise SystemExit(f"no NeUDF run folders under {args.work} (<mesh>/neudf*, from bench/quality.py --work-dir)")
    rows = []
    print(f"{'mesh':<20}{'run':<14}{'1/r':>8}{'moved':>7}{'Chamfer x1e-3':>18}{'acc.':>14}{'compl.':>14}{'F':>13}")
    for name, run in runs:
        t0 = time.perf_counter()
        row = paired_row(name, run, args)
        rows.append(row)
        b, a = row["before"], row["after"]
        print(f"{name:<20}{run.name:<14}{row['view_offset']:>8.4f}{row['vertices_offset'] / row['vertices']:>7.0%}"
              f"{b['chamfer'] * 1e3:>9.2f} ->{a['chamfer'] * 1e3:>6.2f}"
              f"{b['chamfer_pred_to_gt'] * 1e3:>7.2f} ->{a['chamfer_pred_to_gt'] * 1e3:>5.2f}"
              f"{b['chamfer_gt_to_pred'] * 1e3:>7.2f} ->{a['chamfer_gt_to_pred'] * 1e3:>5.2f}"
              f"{b['fscore']:>6.3f} ->{a['fscore']:>5.3f}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    for name in dict.fromkeys(r["mesh"] for r in rows):
        mine = [r for r in rows if r["mesh"] == name]
        mean = {k: sum(r[k]["chamfer"] for r in mine) / len(mine) * 1e3 for k in ("before", "after")}
        print(f"{name:<20}{'mean of ' + str(len(mine)):<14}{'':>15}{mean['before']:>9.2f} ->{mean['after']:>6.2f}")
    config = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    args.out.write_text(json.dumps({"config": config, "rows": rows}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
