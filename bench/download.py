"""The download of a finished job: bake time, file sizes, decimation's effect, texture against vertex colours.

On a job folder (data/ and mesh/mesh.ply; only read, everything is written under --out):

- the export stage as a job runs it (decimation to --faces, a --texture-size bake from every frame): seconds
  (wall and CPU), faces before and after, the size of each file;
- texture against vertex colours at frames held out of the bake (every --hold-every-th frame): PSNR over
  the pixels the mesh covers, of the textured mesh and of the same mesh with its vertex colours, both shown
  unlit (a texture and the colour field hold the light they were filmed under);
- decimation to --fraction of the faces: Chamfer to the mesh before and boundary loops before and after; with
  --truth (a garment of the e2e bench and its true cameras, CONTRACT's convention) also the change of the
  job's Chamfer to the garment.

    .venv/bin/python bench/download.py /tmp/neudf-bench-e2e/jobs/pants_neudf_i2000 \\
        --truth ../shared/data/meshes/pants.obj /tmp/neudf-bench-e2e/videos/pants_c2w.npy

Prints a table and writes JSON under bench/results/.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neudf_core import synthetic  # noqa: E402
from neudf_core.dataset import load_cameras  # noqa: E402
from neudf_core.decimate import DEFAULT_FACES, decimate  # noqa: E402
from neudf_core.metrics import boundary_loops, evaluate, load_mesh  # noqa: E402
from neudf_core.texture import DEFAULT_TEXTURE_SIZE, bake_texture, load_views  # noqa: E402
from worker.export import export_job  # noqa: E402

RESULTS = ROOT / "bench" / "results"


def timed_export(job: Path, out: Path, faces: int, texture_size: int) -> dict:
    start, cpu = time.perf_counter(), time.process_time()
    figures = export_job(job / "mesh" / "mesh.ply", job / "data", job / "run", out, faces=faces,
                         texture_size=texture_size)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    summary = json.loads((out / "metrics.json").read_text())["download"]
    return {"export_wall_s": round(wall, 1), "export_cpu_s": round(cpu, 1), "bake_s": figures.get("texture_s"),
            "faces_before": summary["faces_before"], "faces": summary["faces"],
            "mb": {name: round(size / 2**20, 2) for name, size in summary["bytes"].items()}}


def _frame(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), np.float64)


def held_out_psnr(mesh, data: Path, texture_size: int, every: int, scale: float) -> dict:
    """PSNR of textured and vertex-coloured renders at frames held out of the bake, over the mesh's pixels."""
    n = len(load_cameras(data))
    held = list(range(every // 2, n, every))
    textured, figures = bake_texture(mesh, data, texture_size, frames=[i for i in range(n) if i not in held])
    cams, views = load_cameras(data), load_views(data)
    w, h = round(cams.width * scale), round(cams.height * scale)
    errors = {"texture": [], "vertex_colours": []}
    for i in held:
        camera = synthetic.Camera(np.diag([w / cams.width, h / cams.height, 1.0]) @ cams.intrinsics[i], cams.c2w[i],
                                  w, h)
        target = _frame(views.paths[i])
        if scale != 1.0:
            from PIL import Image

            target = np.asarray(Image.fromarray(target.astype(np.uint8)).resize((w, h), Image.BILINEAR), np.float64)
        for name, shown in (("texture", textured), ("vertex_colours", mesh)):
            image, mask = synthetic.render(shown, [camera], "white", lit=False)
            errors[name].append(((image[0].astype(np.float64) - target) ** 2)[mask[0]])
    psnr = {k: round(float(10 * np.log10(255.0**2 / np.concatenate(v).mean())), 2) for k, v in errors.items()}
    return {"held_out_frames": len(held), "bake_frames": figures["frames"], "bake_s": figures["seconds"],
            "psnr_texture": psnr["texture"], "psnr_vertex_colours": psnr["vertex_colours"],
            "psnr_gain_db": round(psnr["texture"] - psnr["vertex_colours"], 2)}


def decimation_figures(mesh, fraction: float, job: Path, truth: tuple[Path, Path] | None) -> dict:
    small = decimate(mesh, int(len(mesh.faces) * fraction))
    out = {"faces": len(mesh.faces), "faces_decimated": len(small.faces),
           "loops": boundary_loops(mesh), "loops_decimated": boundary_loops(small),
           "chamfer_to_undecimated": round(evaluate(small, mesh, n_samples=100_000)["chamfer"], 6)}
    if truth is not None:
        from bench.e2e import aligned_mesh, load_garment  # the e2e bench's garment and alignment

        garment = load_garment(truth[0])
        before, after = (evaluate(aligned_mesh(job, np.load(truth[1]), m)[0], garment)["chamfer"] for m in (mesh, small))
        out.update(chamfer_gt=round(before, 6), chamfer_gt_decimated=round(after, 6),
                   chamfer_change=round((after - before) / before, 4))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("job", type=Path, help="a finished job folder (data/, mesh/mesh.ply)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/neudf-bench-download"))
    parser.add_argument("--faces", type=int, default=DEFAULT_FACES)
    parser.add_argument("--texture-size", type=int, default=DEFAULT_TEXTURE_SIZE)
    parser.add_argument("--hold-every", type=int, default=10, help="every n-th frame is held out of the PSNR bake")
    parser.add_argument("--render-scale", type=float, default=0.5, help="held-out frames compared at this scale")
    parser.add_argument("--fraction", type=float, default=0.2, help="decimation share for the Chamfer figures")
    parser.add_argument("--truth", nargs=2, type=Path, metavar=("GARMENT", "C2W_NPY"))
    args = parser.parse_args()
    out = args.out / args.job.name
    shutil.rmtree(out, ignore_errors=True)
    result = {"job": str(args.job), "texture_size": args.texture_size, "target_faces": args.faces,
              "frames": len(load_cameras(args.job / "data")),
              "frame_size": f"{load_cameras(args.job / 'data').width}x{load_cameras(args.job / 'data').height}"}
    result["export"] = timed_export(args.job, out, args.faces, args.texture_size)
    mesh = decimate(load_mesh(args.job / "mesh" / "mesh.ply"), args.faces)
    result["held_out"] = held_out_psnr(mesh, args.job / "data", args.texture_size, args.hold_every,
                                       args.render_scale)
    result["decimation"] = decimation_figures(load_mesh(args.job / "mesh" / "mesh.ply"), args.fraction, args.job,
                                              tuple(args.truth) if args.truth else None)
    for section, figures in result.items():
        print(f"{section:>10}: {figures}")
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"download_{args.job.name}.json"
    path.write_text(json.dumps(result, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
