"""Export stage: the mesh a user downloads, preview pictures and the job's figures in metrics.json.

The mesh stage's mesh is decimated to the job's ``faces`` (:mod:`neudf_core.decimate`) and, unless
``texture_size`` is 0, textured from the job's frames (:mod:`neudf_core.texture`). Files: ``mesh.glb``
(textured, or vertex colours without a texture), ``mesh.obj`` with ``mesh.mtl`` and ``mesh.png`` beside it
(the texture), ``mesh.usdz`` (iOS AR Quick Look, in metres) and ``mesh.ply`` (the decimated mesh with its
vertex colours, one side).

Pictures: ``preview.png`` (the downloaded mesh ray-cast from four sides), ``loss.png`` (loss and PSNR
against iteration from the run's metrics.jsonl) and ``frames.png`` (the chosen frames, written as soon as
the frames stage ends so the page can show them early).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from PIL import Image

from neudf_core.decimate import DEFAULT_FACES, decimate
from neudf_core.export import USDZ_METRES_PER_UNIT, export_mesh
from neudf_core.files import write_json_atomic
from neudf_core.progress import ProgressFn, null_progress, sub_progress
from neudf_core.texture import DEFAULT_TEXTURE_SIZE, bake_texture


def write_frames_montage(image_dir: Path, out: Path, *, max_frames: int = 24, thumb: int = 160) -> Path | None:
    """A grid of up to ``max_frames`` of the chosen frames, evenly spread over them."""
    files = sorted(image_dir.glob("*.png"))
    if not files:
        return None
    picks = [files[int(i)] for i in np.linspace(0, len(files) - 1, min(max_frames, len(files))).round()]
    thumbs = []
    for path in picks:
        with Image.open(path) as im:
            im = im.convert("RGB")
            im.thumbnail((thumb, thumb))
            thumbs.append(im.copy())
    cols = min(6, len(thumbs))
    rows = math.ceil(len(thumbs) / cols)
    w = max(t.width for t in thumbs)
    h = max(t.height for t in thumbs)
    sheet = Image.new("RGB", (cols * w + (cols + 1) * 4, rows * h + (rows + 1) * 4), "white")
    for i, t in enumerate(thumbs):
        r, c = divmod(i, cols)
        sheet.paste(t, (4 + c * (w + 4), 4 + r * (h + 4)))
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out


def read_metrics_log(path: Path) -> list[dict[str, Any]]:
    """The rows of a metrics.jsonl; a half-written last line (a run still going) is skipped."""
    rows = []
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def write_loss_curve(metrics_jsonl: Path, out: Path) -> Path | None:
    rows = [r for r in read_metrics_log(metrics_jsonl) if "iter" in r and "loss" in r]
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")  # no display in a worker
    import matplotlib.pyplot as plt

    iters = [r["iter"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=100)
    ax.plot(iters, [r["loss"] for r in rows], color="tab:blue", marker="." if len(rows) < 30 else None)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss", color="tab:blue")
    ax.set_yscale("log" if min(r["loss"] for r in rows) > 0 else "linear")
    if all("psnr" in r for r in rows):
        ax2 = ax.twinx()
        ax2.plot(iters, [r["psnr"] for r in rows], color="tab:orange", marker="." if len(rows) < 30 else None)
        ax2.set_ylabel("PSNR (dB)", color="tab:orange")
    ax.set_title("training")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def write_preview(mesh: trimesh.Trimesh, out: Path, *, size: int = 256, views: int = 4) -> Path | None:
    """Ray-cast the mesh with its texture or vertex colours from ``views`` directions around it, side by side."""
    if len(mesh.faces) == 0:
        return None
    from neudf_core.synthetic import Camera, intrinsics, look_at, render

    centre = mesh.bounds.mean(axis=0)
    radius = float(np.linalg.norm(mesh.vertices - centre, axis=1).max()) or 1.0
    fov = 40.0
    distance = radius / math.sin(math.radians(fov / 2)) * 1.1
    K = intrinsics(size, size, fov)
    cams = []
    for i in range(views):
        azimuth = 2 * math.pi * i / views + math.pi / 8
        eye = centre + distance * np.array([math.sin(azimuth) * 0.9, 0.35, math.cos(azimuth) * 0.9])
        cams.append(Camera(K.copy(), look_at(eye, centre), size, size))
    coloured = mesh.visual.kind in ("vertex", "texture")
    scene = mesh if coloured else trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    images, _ = render(scene, cams, background="white")
    panel = np.concatenate(list(images), axis=1)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(panel).save(out)
    return out


def mesh_figures(mesh: trimesh.Trimesh) -> dict[str, Any]:
    edges = mesh.edges_sorted
    if len(edges):
        _, counts = np.unique(edges, axis=0, return_counts=True)
        boundary_edges = int((counts == 1).sum())
    else:
        boundary_edges = 0
    return {
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "boundary_edges": boundary_edges,
        "area": round(float(mesh.area), 6),
        "watertight": bool(mesh.is_watertight),
        "has_vertex_colors": mesh.visual.kind == "vertex",
    }


def _write_download(mesh: trimesh.Trimesh, textured: trimesh.Trimesh | None, out_dir: Path) -> dict[str, int]:
    """The download's files; returns their sizes in bytes. (The pipeline removes an earlier run's files, e.g. the
    OBJ's texture when a job is exported again without one.)"""
    shown = textured if textured is not None else mesh
    for name in ("mesh.glb", "mesh.obj", "mesh.usdz"):
        export_mesh(shown, out_dir / name)
    export_mesh(mesh, out_dir / "mesh.ply")
    return {path.name: path.stat().st_size for path in sorted(out_dir.glob("mesh.*"))}


def export_job(mesh_file: Path, data_dir: Path, run_dir: Path, out_dir: Path, *, faces: int = DEFAULT_FACES,
               texture_size: int = DEFAULT_TEXTURE_SIZE, progress: ProgressFn = null_progress) -> dict[str, Any]:
    """Decimate to ``faces`` (0: keep all), bake a ``texture_size`` px texture from ``data_dir``'s frames (0: vertex
    colours only), write the download (mesh.glb, .obj, .mtl, .png, .usdz, .ply), preview.png, loss.png and
    metrics.json."""
    out_dir.mkdir(parents=True, exist_ok=True)
    dense = trimesh.load(mesh_file, process=False, force="mesh")
    progress(0.02, f"decimating {len(dense.faces)} faces to {faces}" if faces else "keeping every face")
    mesh = decimate(dense, faces)
    textured, texture = None, {}
    if texture_size > 0:
        textured, texture = bake_texture(mesh, data_dir, texture_size, progress=sub_progress(progress, 0.05, 0.8))
    progress(0.8, "writing GLB, OBJ, USDZ and PLY")
    sizes = _write_download(mesh, textured, out_dir)
    progress(0.88, "rendering the preview")
    write_preview(textured if textured is not None else mesh, out_dir / "preview.png")
    progress(0.95, "plotting the loss curve")
    write_loss_curve(run_dir / "metrics.jsonl", out_dir / "loss.png")
    if not (out_dir / "frames.png").is_file():
        write_frames_montage(data_dir / "image", out_dir / "frames.png")
    download = {"faces_before": int(len(dense.faces)), "faces": int(len(mesh.faces)), "texture": texture or None,
                "usdz_metres_per_unit": USDZ_METRES_PER_UNIT, "bytes": sizes}
    summary: dict[str, Any] = {"mesh": mesh_figures(mesh), "download": download}
    capture_file = data_dir / "capture.json"
    if capture_file.is_file():
        summary["capture"] = json.loads(capture_file.read_text())
    rows = read_metrics_log(run_dir / "metrics.jsonl")
    if rows:
        summary["train"] = rows[-1]
    write_json_atomic(out_dir / "metrics.json", summary)
    progress(1.0, "exported")
    figures = {f"mesh_{k}": v for k, v in mesh_figures(mesh).items()}
    figures.update(mesh_faces_before=int(len(dense.faces)), texture_size=texture_size if textured is not None else 0,
                   glb_mb=round(sizes["mesh.glb"] / 2**20, 3), usdz_mb=round(sizes["mesh.usdz"] / 2**20, 3))
    if texture:
        figures.update(texture_s=texture["seconds"], texture_seen=texture["seen"])
    return figures
