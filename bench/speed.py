"""Benchmark: `paper` against `fast` at the same ray batch on the same scene.

For each preset: training rays/s, peak memory, and the Chamfer distance of the mesh over wall-clock
training time (the clock stops while we mesh and measure). The target is the Chamfer `paper` reaches at
the end of its budget; the table gives the time each preset needs to reach it. Each preset trains in
its own process so that peak memory is its own. Prints a table and writes JSON under bench/results/.

    .venv/bin/python bench/speed.py --paper-budget-s 1200 --paper-iters 150 --paper-eval-every-s 400 \
        --fast-budget-s 300 --fast-eval-every-s 20                                        # CPU, about 25 min

On a 2-core CPU `paper` (8x256 MLP, 128 samples, double backward) manages ~0.15 iterations/s and has no
surface yet after 150 iterations; the table then says there is no target rather than inventing one.
The comparison the bench is for needs a GPU:

    .venv/bin/python bench/speed.py --device cuda --views 200 --size 800 --paper-budget-s 600 --fast-budget-s 600
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import sys
import tempfile
import time
from pathlib import Path

import torch
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neudf_core import synthetic  # noqa: E402
from neudf_core.config import load_config  # noqa: E402
from neudf_core.dataset import load_dataset  # noqa: E402
from neudf_core.meshing import UNIT_BOUNDS, extract_mesh  # noqa: E402
from neudf_core.metrics import evaluate  # noqa: E402
from neudf_core.trainer import Trainer, fit_schedule_to_iters  # noqa: E402

DEFAULT_MESH = ROOT.parent / "shared" / "data" / "meshes" / "diffavatar_tshirt.obj"


def chamfer_now(model, gt: trimesh.Trimesh, resolution: int, device: str) -> float | None:
    """The Chamfer distance of the model's mesh to GT now; None while the field has no surface."""
    model.eval()
    try:
        mesh = extract_mesh(model.udf, method="meshudf", resolution=resolution, bounds=UNIT_BOUNDS,
                            grad_fn=lambda x: model.udf_and_grad(x)[1], device=device)
        value = evaluate(mesh, gt, n_samples=20_000)["chamfer"]
    except ValueError:  # no surface yet
        value = None
    model.train()
    return value


def run_preset(preset: str, data_dir: str, gt_path: str, args: dict, queue) -> None:
    """Train one preset for its budget, measuring Chamfer every ``eval_every_s`` of training time."""
    torch.set_num_threads(args["threads"]) if args["threads"] else None
    overrides = {"data": {"white_background": True, "max_size": args["max_size"]}, "optim": {"rays": args["rays"]}}
    cfg = load_config(preset, overrides)
    if args.get(f"{preset}_iters"):
        cfg = fit_schedule_to_iters(cfg, args[f"{preset}_iters"])
    data = load_dataset(data_dir, cfg.data.max_size)
    gt = trimesh.load(gt_path)
    device = args["device"]
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(data, Path(tmp), cfg, device)
        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        budget = args[f"{preset}_budget_s"]
        every = args[f"{preset}_eval_every_s"] or args["eval_every_s"]
        curve, trained_s, iters, next_eval = [], 0.0, 0, every
        while trained_s < budget and trainer.step < cfg.optim.iters:
            t0 = time.perf_counter()
            trainer.train_step()
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            trained_s += time.perf_counter() - t0
            iters += 1
            if trained_s >= next_eval or trained_s >= budget:
                curve.append({"train_s": round(trained_s, 1), "iter": trainer.step,
                              "chamfer": chamfer_now(trainer.model, gt, args["resolution"], device)})
                print(f"[{preset}] {curve[-1]}", flush=True)
                next_eval += every
        if not curve or curve[-1]["iter"] != trainer.step:  # the schedule ended before the budget
            curve.append({"train_s": round(trained_s, 1), "iter": trainer.step,
                          "chamfer": chamfer_now(trainer.model, gt, args["resolution"], device)})
            print(f"[{preset}] {curve[-1]}", flush=True)
    peak = (torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda")
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    queue.put({"preset": preset, "iters": iters, "train_s": round(trained_s, 1),
               "rays_per_s": round(iters * args["rays"] / trained_s, 1), "peak_mem_mib": round(peak, 1),
               "curve": curve})


def time_to(curve: list[dict], target: float | None) -> float | None:
    """Training seconds until the Chamfer first reaches ``target`` (None: never, or no target)."""
    if target is None:
        return None
    return next((p["train_s"] for p in curve if p["chamfer"] is not None and p["chamfer"] <= target), None)


def summarise(rows: dict[str, dict]) -> dict:
    """Target (paper's final Chamfer), each preset's time to it, and fast's speed-up; prints the table.

    When paper has no surface at the end of its budget there is no target and no speed-up to claim.
    """
    target = rows["paper"]["curve"][-1]["chamfer"]
    if target is None:
        print(f"\nno target: paper has no surface after {rows['paper']['train_s']} s of training")
    else:
        print(f"\ntarget: paper's Chamfer after {rows['paper']['train_s']} s = {target:.5f}")
    print(f"{'preset':<8}{'iters':>8}{'rays/s':>10}{'peak MiB':>10}{'final CD':>12}{'time to target s':>18}")
    for name, row in rows.items():
        row["time_to_target_s"] = time_to(row["curve"], target)
        final = row["curve"][-1]["chamfer"]
        print(f"{name:<8}{row['iters']:>8}{row['rays_per_s']:>10.1f}{row['peak_mem_mib']:>10.1f}"
              f"{'no surface' if final is None else f'{final:.5f}':>12}{str(row['time_to_target_s']):>18}")
    paper_t, fast_t = rows["paper"]["time_to_target_s"], rows["fast"]["time_to_target_s"]
    speedup = paper_t / fast_t if paper_t and fast_t else None
    print(f"speed-up to paper's Chamfer: {'n/a' if speedup is None else f'{speedup:.1f}x'}")
    return {"target_chamfer": target, "speedup": speedup}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", default=str(DEFAULT_MESH))
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--max-size", type=int, default=0, help="train on images downsized to this (0 = as rendered)")
    ap.add_argument("--rays", type=int, default=512, help="the same ray batch for both presets")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--paper-budget-s", type=float, default=1200.0)
    ap.add_argument("--fast-budget-s", type=float, default=600.0)
    ap.add_argument("--paper-iters", type=int, default=None, help="schedule length for paper (default 400k)")
    ap.add_argument("--fast-iters", type=int, default=None, help="schedule length for fast (default: preset)")
    ap.add_argument("--eval-every-s", type=float, default=60.0, help="training seconds between two Chamfer checks")
    ap.add_argument("--paper-eval-every-s", type=float, default=None, help="for paper (default: --eval-every-s)")
    ap.add_argument("--fast-eval-every-s", type=float, default=None, help="for fast (default: --eval-every-s)")
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "speed.json")
    args = ap.parse_args()

    mesh = trimesh.load(args.mesh, process=False, force="mesh")
    ctx = mp.get_context("spawn")
    with tempfile.TemporaryDirectory() as tmp:
        data = synthetic.write_neus_dataset(Path(tmp) / "data", mesh, n_views=args.views, size=args.size)
        shared = {k: v for k, v in vars(args).items() if k != "out"}
        rows = {}
        for preset in ("paper", "fast"):
            queue = ctx.Queue()
            proc = ctx.Process(target=run_preset, args=(preset, str(data), str(data / "mesh_gt.ply"), shared, queue))
            proc.start()
            rows[preset] = queue.get()
            proc.join()

    summary = summarise(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, **summary, "runs": rows},
                                   indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
