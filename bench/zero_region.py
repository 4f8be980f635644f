"""Benchmark: NeUDF with and without the zero-region penalty (loss.zero_region_weight, not in the paper).

For each garment it renders the same synthetic scene as bench/quality.py, trains NeUDF with the quick
preset for each penalty weight, meshes each field with both UDF methods (meshudf and masked SPSR) and
compares with the ground truth. Prints a table and writes JSON under bench/results/.

    .venv/bin/python bench/zero_region.py --meshes tshirt pants --weights 0 10     # CPU, about 20 min
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from quality import find_meshes  # noqa: E402  (bench/ is on the path when run as a script)

from neudf_core import synthetic  # noqa: E402
from neudf_core.extract import mesh_run  # noqa: E402
from neudf_core.metrics import evaluate  # noqa: E402
from neudf_core.trainer import train  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--meshes", nargs="*", default=["tshirt", "pants"])
    ap.add_argument("--weights", nargs="+", type=float, default=[0.0, 10.0])
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "zero_region.json")
    args = ap.parse_args()

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in find_meshes(args.meshes):
            source = trimesh.load(path, process=False, force="mesh")
            data = synthetic.write_neus_dataset(Path(tmp) / path.stem, source, n_views=args.views, size=args.size)
            gt = trimesh.load(data / "mesh_gt.ply", process=False)
            for weight in args.weights:
                run = Path(tmp) / f"{path.stem}_{weight:g}"
                overrides = {"data": {"white_background": True, "max_size": 0},
                             "loss": {"zero_region_weight": weight}}
                result = train(data, run, preset="quick", iters=args.iters, overrides=overrides)
                row = {"mesh": path.stem, "weight": weight, "psnr": result["psnr"]}
                for method in ("meshudf", "spsr"):
                    mesh = mesh_run(run, run / f"{method}.ply", method=method, resolution=args.resolution)
                    metrics = evaluate(mesh, gt, n_samples=100_000)
                    row[method] = {k: metrics[k] for k in ("chamfer", "fscore", "boundary_loops_pred")}
                row["boundary_loops_gt"] = metrics["boundary_loops_gt"]
                rows.append(row)
                print(f"[{time.strftime('%H:%M:%S')}] {path.stem} weight {weight:g} done", flush=True)

    print(f"\n{'mesh':<12}{'weight':>7}{'PSNR':>7}{'meshudf CD x1e-3':>18}{'loops':>7}{'SPSR CD x1e-3':>15}{'loops':>7}{'GT':>4}")
    for r in rows:
        print(f"{r['mesh']:<12}{r['weight']:>7g}{r['psnr']:>7.2f}{r['meshudf']['chamfer'] * 1e3:>18.2f}"
              f"{r['meshudf']['boundary_loops_pred']:>7}{r['spsr']['chamfer'] * 1e3:>15.2f}"
              f"{r['spsr']['boundary_loops_pred']:>7}{r['boundary_loops_gt']:>4}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
