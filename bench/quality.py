"""Benchmark: NeUDF against naive NeuS-on-|f| and NeuS-SDF on open garments, at the same budget.

For each ground-truth mesh (../shared/data/meshes by default: tshirt.obj and pants.obj with their
textures, diffavatar_*.obj with the renderer's procedural texture) it renders a synthetic NeuS-layout
scene, trains the three rendering weights with the same preset, iterations and overrides, meshes each
(masked screened Poisson, the paper's meshing, for the two unsigned fields by default; marching cubes at
level 0 for NeuS-SDF) and compares the mesh with
the ground truth in GT's unit sphere (neudf_core.metrics.evaluate). Prints one table and writes JSON
under bench/results/.

Images are rendered at --size and trained at that size (the preset's downscaling is overridden): at
96 px a pixel is 2% of the object and every method's error is about one pixel, which hides the
differences the paper is about.

    .venv/bin/python bench/quality.py --jobs 2                               # CPU: quick, 4000 iterations, 192 px
    .venv/bin/python bench/quality.py --preset fast --device cuda --views 64 --size 256 --iters 20000
    .venv/bin/python bench/quality.py --meshes diffavatar_tshirt --iters 5   # a smoke run
    # after a change that touches NeUDF only: train it alone, take the baselines' rows from the last table
    # (a variant that is not in the preset: --set renderer.sharpness_floor_end=1600)
    .venv/bin/python bench/quality.py --jobs 2 --methods neudf --rows-from bench/results/quality_quick_4000.json
    # where two methods are within a single run's spread: several seeds, a mean per mesh
    .venv/bin/python bench/quality.py --jobs 2 --meshes pants tshirt --methods neudf neus_sdf --seeds 0 1 2
    # a table trained in parts (other meshes, methods or seeds per report): join the reports, train nothing
    .venv/bin/python bench/quality.py --methods --rows-from A.json B.json --out joined.json
"""

from __future__ import annotations

import argparse
import ctypes
import json
import math
import platform
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neudf_core import synthetic  # noqa: E402
from neudf_core.config import deep_merge, load_config  # noqa: E402
from neudf_core.extract import mesh_run  # noqa: E402
from neudf_core.meshing.lids import SPREAD_LID  # noqa: E402
from neudf_core.metrics import boundary_loops, evaluate  # noqa: E402
from neudf_core.numerics import flush_denormals  # noqa: E402
from neudf_core.trainer import fit_schedule_to_iters, train  # noqa: E402

MESH_DIR = ROOT.parent / "shared" / "data" / "meshes"
# weight -> (label, meshing method): NeuS on |f| learns an unsigned field, so it is meshed like NeUDF
METHODS = {"neudf": ("NeUDF", "udf"), "neus_abs": ("NeuS |f|", "udf"), "neus_sdf": ("NeuS-SDF", "mc")}


def find_meshes(names: list[str] | None) -> list[Path]:
    """The GT meshes: names (with or without .obj) in MESH_DIR, or paths; all .obj files by default."""
    if not names:
        found = sorted(MESH_DIR.glob("*.obj"))
        if not found:
            raise SystemExit(f"no meshes in {MESH_DIR}; pass --meshes PATH ...")
        return found
    paths = []
    for name in names:
        path = Path(name)
        if not path.is_file():
            path = MESH_DIR / (name if name.endswith(".obj") else f"{name}.obj")
        if not path.is_file():
            raise SystemExit(f"mesh not found: {name} (looked in {MESH_DIR})")
        paths.append(path)
    return paths


def parse_setting(text: str) -> dict[str, Any]:
    """``block.key=value`` (value as JSON, else a string) -> {"block": {"key": value}}."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected block.key=value, got {text!r}")
    try:
        value: Any = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    for part in reversed(key.split(".")):
        value = {part: value}
    return value


def overrides_for(weight: str, args: argparse.Namespace, seed: int = 0) -> dict[str, Any]:
    overrides: dict[str, Any] = {}
    for setting in args.set:
        overrides = deep_merge(overrides, setting)
    overrides = deep_merge(overrides, {"renderer": {"weight": weight}, "data": {"max_size": args.max_size},
                                       "seed": seed})
    if args.background == "white":
        overrides["data"]["white_background"] = True
    return overrides


def resolved_config(weight: str, args: argparse.Namespace) -> dict[str, Any]:
    """The training configuration a method gets in this run, as its run folder's config.json records it."""
    cfg = fit_schedule_to_iters(load_config(args.preset, overrides_for(weight, args)), args.iters or None)
    return json.loads(cfg.model_dump_json())


def run_one(data: Path, run_dir: Path, weight: str, args: argparse.Namespace, gt: trimesh.Trimesh,
            seed: int = 0) -> dict[str, Any]:
    """Train one rendering weight, mesh it and evaluate it. Failures are recorded, not raised."""
    label, method = METHODS[weight]
    if method == "udf":
        method = args.udf_mesh_method
    overrides = overrides_for(weight, args, seed)
    row: dict[str, Any] = {"weight": weight, "label": label, "seed": seed, "mesh_method": method,
                           "boundary_loops_gt": boundary_loops(gt)}
    t0 = time.perf_counter()
    result = train(data, run_dir, preset=args.preset, iters=args.iters or None, device=args.device,
                   overrides=overrides)
    row.update(train_s=round(time.perf_counter() - t0, 1), iters=result["iters"], psnr=result.get("psnr"),
               train_config=json.loads((run_dir / "config.json").read_text()))
    t1 = time.perf_counter()
    try:
        pred = mesh_run(run_dir, run_dir / "mesh.ply", method=method, resolution=args.resolution, device=args.device,
                        views=data if args.min_seen > 0 else None, min_seen_fraction=args.min_seen,
                        lid_spread=args.lid_spread)
    except ValueError as exc:  # e.g. no surface yet after a tiny budget: a result, not a crash
        row.update(error=str(exc), chamfer=None, fscore=None, boundary_loops_pred=None)
        return row
    row["mesh_s"] = round(time.perf_counter() - t1, 1)
    metrics = evaluate(pred, gt, n_samples=args.samples)
    row.update(metrics)
    info = pred.metadata.get("meshing", {})
    row.update(faces=len(pred.faces), mesh_threshold=info.get("threshold"), min_seen=args.min_seen,
               faces_unseen=info.get("faces_unseen"), lid_spread=args.lid_spread, faces_lids=info.get("faces_lids"))
    return row


Job = tuple[str, Path, Path, str, int]  # mesh name, dataset, run folder, weight, seed


def _run_job(job: Job, args: argparse.Namespace, started: float) -> dict[str, Any]:
    mesh, data, run_dir, weight, seed = job
    print(f"[{time.time() - started:7.0f}s] {mesh}: {METHODS[weight][0]}, seed {seed}", flush=True)
    gt = trimesh.load(data / "mesh_gt.ply", process=False)
    try:
        return {"mesh": mesh, **run_one(data, run_dir, weight, args, gt, seed)}
    except Exception as exc:  # noqa: BLE001 -- one failed training must not lose the other rows
        print(f"{mesh}: {METHODS[weight][0]}, seed {seed} failed: {exc}", flush=True)
        return {"mesh": mesh, "weight": weight, "label": METHODS[weight][0], "seed": seed,
                "boundary_loops_gt": boundary_loops(gt), "error": f"{type(exc).__name__}: {exc}",
                "chamfer": None, "fscore": None, "boundary_loops_pred": None}


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _init_worker(threads: int) -> None:
    flush_denormals()  # before the thread pool starts, so its threads take the mode
    torch.set_num_threads(threads)
    # Killing the bench (kill PID, not Ctrl-C, which reaches the whole process group) would otherwise leave
    # its workers training on, half the CPU each, into folders a rerun then shares with them.
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def run_all(jobs: list[Job], args: argparse.Namespace, started: float) -> list[dict[str, Any]]:
    """Run the trainings, --jobs at a time. On a small CPU two one-thread processes train about 1.5x faster
    in all than one two-thread process (a small MLP does not keep two threads busy); rows keep job order."""
    if args.jobs <= 1:
        return [_run_job(job, args, started) for job in jobs]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    threads = max(1, torch.get_num_threads() // args.jobs)
    # spawn: a forked child of a process that already ran torch's thread pool can hang
    with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_init_worker, initargs=(threads,)) as pool:
        return list(pool.map(_run_job, jobs, [args] * len(jobs), [started] * len(jobs)))


def _mean(values: list[float]) -> float:
    return sum(values) / len(values)


def _cell(rows: list[dict[str, Any]]) -> str:
    """Chamfer, F-score and boundary loops of one method: one run, or the mean of several seeds."""
    if not rows:
        return f"{'-':>28}"
    ok = [r for r in rows if not r.get("error")]
    if not ok:
        no_surface = all(str(r["error"]).startswith("no surface") for r in rows)
        return f"{'no surface' if no_surface else 'failed (error in JSON)':>28}"
    loops = f"{ok[0]['boundary_loops_pred']}" if len(ok) == 1 else "-"
    failed = "" if len(ok) == len(rows) else f" ({len(rows) - len(ok)} failed)"
    return (f"{_mean([r['chamfer'] for r in ok]) * 1e3:>14.2f}{_mean([r['fscore'] for r in ok]):>7.3f}"
            f"{loops:>7}{failed}")


def print_table(rows: list[dict[str, Any]], weights: list[str]) -> None:
    """One line per mesh and seed; with several seeds a mean line per mesh, and the means over meshes."""
    labels = [METHODS[w][0] for w in weights]
    head = f"{'mesh':<22}{'seed':>5}{'GT loops':>9}  " + "".join(f"{lab:>28}" for lab in labels)
    sub = f"{'':<22}{'':>5}{'':>9}  " + "".join(f"{'CD x1e-3   F   loops':>28}" for _ in labels)
    print(head)
    print(sub)
    per_mesh: dict[str, dict[str, float]] = {w: {} for w in weights}  # weight -> mesh -> mean Chamfer
    for mesh in dict.fromkeys(r["mesh"] for r in rows):
        of_mesh = [r for r in rows if r["mesh"] == mesh]
        gt_loops = of_mesh[0]["boundary_loops_gt"]
        seeds = sorted({r.get("seed", 0) for r in of_mesh})
        for seed in seeds:
            cells = [_cell([r for r in of_mesh if r["weight"] == w and r.get("seed", 0) == seed]) for w in weights]
            print(f"{mesh:<22}{seed:>5}{gt_loops!s:>9}  " + "".join(cells))
        if len(seeds) > 1:
            print(f"{mesh:<22}{'mean':>5}{'':>9}  " + "".join(_cell([r for r in of_mesh if r["weight"] == w])
                                                            for w in weights))
        for w in weights:
            values = [r["chamfer"] for r in of_mesh if r["weight"] == w and not r.get("error")]
            if values:
                per_mesh[w][mesh] = _mean(values)
    for w, lab in zip(weights, labels):
        if per_mesh[w]:
            print(f"mean Chamfer {lab}: {_mean(list(per_mesh[w].values())) * 1e3:.2f} x1e-3 over "
                  f"{len(per_mesh[w])} meshes")


# Settings that only NeUDF's weight reads (the baselines' logistic weight has its own CDF and keeps its
# learned s): a baseline row trained with other values of these is still the same training.
NEUDF_ONLY = {"renderer.varsigma", "renderer.sharpness_floor_end", "renderer.receding_opacity"}
# Settings the signed baseline never reads: its field has no output activation (f is h itself) and no
# zero-region term.
UNSIGNED_ONLY = {"field.output", "loss.zero_region_weight", "loss.zero_region_margin"}

# Settings that must agree for rows of two runs to sit in one table.
_COMPARABLE = ("preset", "iters", "views", "size", "max_size", "udf_mesh_method", "background", "resolution", "samples",
               "lid_spread")
# What a report made before an option existed ran with.
_BEFORE_OPTION = {"lid_spread": 0.0}


def _report_rows(path: Path, args: argparse.Namespace, meshes: list[str]) -> list[dict[str, Any]]:
    """The rows of one earlier report for the methods not run now, after checking its settings match."""
    report = json.loads(path.read_text())
    old = report["config"]
    differ = [k for k in _COMPARABLE if old.get(k, _BEFORE_OPTION.get(k)) != getattr(args, k)]
    if differ:
        raise SystemExit(f"{path} was made with other settings ({', '.join(f'{k}={old.get(k)}' for k in differ)}); "
                         "its rows cannot share a table with this run")
    # a row already reused keeps naming the report that trained it
    return [dict(r, reused_from=r.get("reused_from", str(path))) for r in report["rows"]
            if r["weight"] not in args.methods and r["mesh"] in meshes]


def reused_rows(paths: list[Path], args: argparse.Namespace, meshes: list[str]) -> list[dict[str, Any]]:
    """Rows of the methods not run now, from earlier reports made with the same settings (one report per
    part of a table that took several sessions to train; a method, mesh and seed may come from one only)."""
    rows: list[dict[str, Any]] = []
    for path in paths:
        for r in _report_rows(path, args, meshes):
            twin = next((o for o in rows if (o["mesh"], o["weight"], o.get("seed", 0))
                         == (r["mesh"], r["weight"], r.get("seed", 0))), None)
            if twin is not None:
                raise SystemExit(f"{r['mesh']}/{r['label']}, seed {r.get('seed', 0)} is in both "
                                 f"{twin['reused_from']} and {r['reused_from']}; pass one of them")
            rows.append(r)
    for r in rows:
        if "train_config" not in r:
            print(f"note: {r['reused_from']} does not record its training configuration; {r['mesh']}/{r['label']} "
                  "is reused on the report's settings alone")
            continue
        now = resolved_config(r["weight"], args)
        ignored = NEUDF_ONLY if r["weight"] != "neudf" else set()
        if r["weight"] == "neus_sdf":
            ignored = ignored | UNSIGNED_ONLY
        changed = sorted(f"{block}.{k}" for block, v in now.items() if isinstance(v, dict)
                         for k in v if r["train_config"].get(block, {}).get(k) != v[k]
                         and f"{block}.{k}" not in ignored)
        if changed:
            print(f"note: {r['mesh']}/{r['label']} was trained with other values of {', '.join(changed)}")
            r["config_changed_since"] = changed
    missing = [(m, w) for m in meshes for w in METHODS if w not in args.methods
               and not any(r["mesh"] == m and r["weight"] == w for r in rows)]
    if missing:
        raise SystemExit(f"{', '.join(map(str, paths))} have no rows for {missing}")
    return rows


def _json_safe(value: Any) -> Any:
    """NaN and infinities as null: strict JSON readers refuse them."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="quick", help="quick (CPU), fast or paper (GPU)")
    ap.add_argument("--iters", type=int, default=4000,
                    help="iterations per method (0: the preset's); at 2000 NeUDF's pants had not covered the "
                         "inner leg walls yet (bench/results/quality_quick_4000_pants.json)")
    ap.add_argument("--meshes", nargs="*", default=None, help="names in ../shared/data/meshes or paths (default: all)")
    ap.add_argument("--views", type=int, default=48, help="rendered views per scene")
    ap.add_argument("--size", type=int, default=192, help="image size in pixels")
    ap.add_argument("--max-size", type=int, default=0,
                    help="train on images downscaled to this longest side (0: as rendered)")
    ap.add_argument("--udf-mesh-method", choices=["meshudf", "spsr"], default="spsr",
                    help="meshing for the unsigned fields (NeUDF, NeuS |f|); NeuS-SDF always uses marching cubes")
    ap.add_argument("--background", choices=["white", "env"], default="white",
                    help="white: plain background (trained with white_background); env: NeRF++ background")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--resolution", type=int, default=256, help="meshing grid (cells over the unit box)")
    ap.add_argument("--min-seen", type=float, default=0.15,
                    help="drop mesh faces fewer than this share of the scene's cameras see, as the service does "
                         "(0: keep them); applies to the methods trained in this run")
    ap.add_argument("--lid-spread", type=float, default=SPREAD_LID,
                    help="with --min-seen: cut patches the frames disagree on the colour of above this as lids, "
                         "as the service does (0: keep them)")
    ap.add_argument("--samples", type=int, default=100_000, help="surface samples per mesh for the metrics")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0],
                    help="train every method once per seed; the table gives each seed and the mean per mesh "
                         "(single runs of one garment differed by up to 4 x1e-3 in Chamfer: "
                         "bench/results/quality_quick_seeds.json)")
    ap.add_argument("--set", type=parse_setting, action="append", default=[], metavar="BLOCK.KEY=VALUE",
                    help="a training setting on top of the preset for the methods trained now (value as JSON), "
                         "e.g. --set renderer.sharpness_floor_end=1600; repeatable")
    ap.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS))
    ap.add_argument("--work-dir", type=Path, default=None, help="keep datasets and runs here (default: temporary)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="trainings at once (CPU: 2 on 2 cores is about 1.5x faster; GPU: keep 1)")
    ap.add_argument("--rows-from", type=Path, nargs="+", default=None,
                    help="earlier reports made with the same settings: the methods not in --methods are taken "
                         "from them (marked reused_from) so that the table is whole; with --methods and no "
                         "name, nothing is trained and the reports are joined into one table")
    ap.add_argument("--out", type=Path, default=None,
                    help="JSON file (default: bench/results/quality_<preset>_<iters>.json)")
    args = ap.parse_args()
    if not args.methods and not args.rows_from:
        ap.error("--methods names no method and there is no --rows-from: nothing to train or to show")

    meshes = find_meshes(args.meshes)
    reused = reused_rows(args.rows_from, args, [p.stem for p in meshes]) if args.rows_from else []
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="neudf-quality-"))
    started = time.time()
    try:
        jobs = []
        for path in meshes if args.methods else []:
            source = trimesh.load(path, process=False, force="mesh")
            data = synthetic.write_neus_dataset(work / path.stem / "data", source, n_views=args.views,
                                                size=args.size, background=args.background)
            # seed 0 keeps the single-seed layout, so a --work-dir from before --seeds resumes
            jobs += [(path.stem, data, work / path.stem / (weight if seed == 0 else f"{weight}_seed{seed}"), weight,
                      seed) for seed in args.seeds for weight in args.methods]
        rows = run_all(jobs, args, started)
        order = {w: i for i, w in enumerate(METHODS)}
        rows = sorted(rows + reused, key=lambda r: ([p.stem for p in meshes].index(r["mesh"]), r.get("seed", 0),
                                                    order[r["weight"]]))
    finally:
        if args.work_dir is None:
            shutil.rmtree(work, ignore_errors=True)

    print()
    print_table(rows, [w for w in METHODS if any(r["weight"] == w for r in rows)])
    if reused:
        print(f"rows of {', '.join(sorted({METHODS[r['weight']][0] for r in reused}))} reused from "
              f"{', '.join(map(str, args.rows_from))}")
    out = args.out or ROOT / "bench" / "results" / f"quality_{args.preset}_{args.iters}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    report = {
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": {"device": args.device, "torch": torch.__version__, "threads": torch.get_num_threads(),
                    "jobs": args.jobs, "cpu": platform.processor() or platform.machine(),
                    "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None},
        "seconds": round(time.time() - started, 1),
        "rows": rows,
    }
    out.write_text(json.dumps(_json_safe(report), indent=2, default=str))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
