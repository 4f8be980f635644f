"""Benchmark: train the `quick` preset on a synthetic open surface on this machine.

Renders a NeuS-layout scene from a garment in ../shared/data/meshes (or a procedural sheet), trains
NeUDF with the `quick` preset, meshes the result and compares it with the ground truth. Prints a table
and writes JSON under bench/results/.

    .venv/bin/python bench/train_quick.py --mesh ../shared/data/meshes/diffavatar_poncho.obj
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neudf_core import synthetic  # noqa: E402
from neudf_core.extract import mesh_run  # noqa: E402
from neudf_core.metrics import evaluate  # noqa: E402
from neudf_core.trainer import train  # noqa: E402

DEFAULT_MESH = ROOT.parent / "shared" / "data" / "meshes" / "diffavatar_poncho.obj"


def load_scene_mesh(spec: str) -> tuple[str, trimesh.Trimesh]:
    path = Path(spec)
    if path.is_file():
        return path.stem, trimesh.load(path, process=False, force="mesh")
    return spec, synthetic.procedural_mesh(spec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", default=str(DEFAULT_MESH) if DEFAULT_MESH.is_file() else "wavy_sheet",
                    help="mesh file, or a procedural kind (wavy_sheet, bowl, sheet_with_hole, two_sheets)")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--iters", type=int, default=None, help="default: the preset's")
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--resolution", type=int, default=128, help="meshing grid")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "train_quick.json")
    args = ap.parse_args()

    name, mesh = load_scene_mesh(args.mesh)
    with tempfile.TemporaryDirectory() as tmp:
        data = synthetic.write_neus_dataset(Path(tmp) / "data", mesh, n_views=args.views, size=args.size,
                                            background="white")
        t0 = time.perf_counter()
        result = train(data, Path(tmp) / "run", preset=args.preset, iters=args.iters, device=args.device,
                       overrides={"data": {"white_background": True}})
        train_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        pred = mesh_run(Path(tmp) / "run", Path(tmp) / "mesh.ply", resolution=args.resolution, device=args.device)
        mesh_s = time.perf_counter() - t1
        metrics = evaluate(pred, trimesh.load(data / "mesh_gt.ply"))

    row = {
        "mesh": name, "preset": args.preset, "device": args.device, "views": args.views, "size": args.size,
        "iters": result["iters"], "iters_per_s": round(result["iters"] / train_s, 3), "final_psnr": result["psnr"],
        "train_s": round(train_s, 1), "mesh_s": round(mesh_s, 1), "chamfer": metrics["chamfer"],
        "fscore": metrics["fscore"], "boundary_loops_pred": metrics["boundary_loops_pred"],
        "boundary_loops_gt": metrics["boundary_loops_gt"], "torch_threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
    }
    print(f"{'mesh':<22}{'iters':>7}{'it/s':>8}{'PSNR':>8}{'train s':>9}{'mesh s':>8}{'chamfer':>10}{'F':>7}{'loops':>8}")
    print(f"{row['mesh']:<22}{row['iters']:>7}{row['iters_per_s']:>8.2f}{row['final_psnr']:>8.2f}{row['train_s']:>9.1f}"
          f"{row['mesh_s']:>8.1f}{row['chamfer']:>10.4f}{row['fscore']:>7.3f}"
          f"{row['boundary_loops_pred']:>4}/{row['boundary_loops_gt']:<3}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(row, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
