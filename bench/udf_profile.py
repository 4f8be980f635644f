"""Diagnostic: how a trained UDF behaves across the ground-truth surface.

Samples points on GT, steps along GT's normals by fixed offsets and prints Psi's quantiles at each
offset. A UDF that touches zero on the surface and grows on both sides is healthy; Psi ~ 0 over a range
of offsets on one side is a zero *region* (see loss.zero_region_weight); a minimum above zero or away
from offset 0 is a surface that is shifted or not reached. Run folders come from `neudf train` or from
bench/quality.py --work-dir (<work>/<mesh>/<method>, GT in <work>/<mesh>/data/mesh_gt.ply).

Then it renders rays that arrive along -normal from 1.2 away and compares two depths behind the GT surface
(positive = past it): where the rendering weight of the first wall is centred (where the images see the
surface) and where Psi along the same ray is lowest (where meshing puts it). A field that renders the
wall in the right place while its minimum sits deeper has grown a low valley behind the seen side.

    .venv/bin/python bench/udf_profile.py /tmp/q4/tshirt/neudf /tmp/q4/tshirt/data/mesh_gt.ply

With --mesh (the run's mesh.ply) it also prints where the mesh sits against GT: the median offset along
GT's normals of the mesh's points within 0.04 of GT, in GT's unit sphere as `neudf eval` scales it
(negative: inside, against GT's normals; garments whose normals mostly point outwards read as expected).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neudf_core.metrics import unit_sphere_normalisation  # noqa: E402
from neudf_core.model import RenderState  # noqa: E402
from neudf_core.trainer import load_model, sharpness_floor  # noqa: E402

OFFSETS = (-0.06, -0.04, -0.03, -0.02, -0.01, -0.005, 0.0, 0.005, 0.01, 0.02, 0.03, 0.04, 0.06)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="training run folder")
    ap.add_argument("gt", type=Path, help="GT mesh in the run's unit-sphere coordinates")
    ap.add_argument("--samples", type=int, default=5000)
    ap.add_argument("--mesh", type=Path, default=None, help="a mesh of the run to place against GT")
    args = ap.parse_args()

    model = load_model(args.run)
    gt = trimesh.load(args.gt, process=False)
    points, faces = trimesh.sample.sample_surface(gt, args.samples, seed=0)
    normals = gt.face_normals[faces]
    print(f"{'offset':>8}{'Psi q10':>10}{'median':>10}{'q90':>10}")
    for offset in OFFSETS:
        with torch.no_grad():
            psi = model.udf(torch.tensor(points + offset * normals, dtype=torch.float32)).numpy()
        q10, q50, q90 = np.quantile(psi, [0.1, 0.5, 0.9])
        print(f"{offset:>+8.3f}{q10:>10.4f}{q50:>10.4f}{q90:>10.4f}")
    weight_depth, min_depth = rendered_against_minimum(model, points[:300], normals[:300])
    print(f"rays along -normal: first-wall weight median {np.median(weight_depth):+.4f}, "
          f"Psi minimum {np.median(min_depth):+.4f} behind the GT surface (medians over {len(weight_depth)} rays)")
    if args.mesh is not None:
        offset, share = mesh_offset(trimesh.load(args.mesh, force="mesh"), gt)
        print(f"mesh: median offset {offset:+.4f} along GT's normals (GT's unit sphere; "
              f"{share:.0%} of its points within 0.04 of GT)")


def mesh_offset(mesh: trimesh.Trimesh, gt: trimesh.Trimesh, n: int = 100_000, near: float = 0.04) -> tuple[float, float]:
    """Median signed offset along GT's normals of the mesh's points near GT, in GT's unit sphere."""
    import open3d as o3d

    centre, scale = unit_sphere_normalisation(gt)
    points, _ = trimesh.sample.sample_surface(mesh, n, seed=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(gt.vertices, np.float32)), o3d.core.Tensor(np.asarray(gt.faces, np.uint32)))
    hit = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    delta = (points - hit["points"].numpy()) * scale
    signed = np.sum(delta * hit["primitive_normals"].numpy(), axis=1)
    close = np.linalg.norm(delta, axis=1) < near
    return float(np.median(signed[close])), float(close.mean())


@torch.no_grad()
def rendered_against_minimum(model, points: np.ndarray, normals: np.ndarray, start: float = 1.2,
                             window: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """Per ray: the median depth of the weight within ``window`` of the GT surface, and Psi's argmin there."""
    cfg = model.cfg
    state = RenderState(sharpness_floor=sharpness_floor(cfg.optim.iters, cfg.renderer, cfg.optim.iters))
    o = torch.tensor(points + start * normals, dtype=torch.float32)
    out = model.render(o, torch.tensor(-normals, dtype=torch.float32), state, torch.ones(3))
    depth = out["mid_z"].numpy() - start
    w = out["weights"].numpy() * (np.abs(depth) < window)
    cdf = np.cumsum(w, 1) / np.maximum(w.sum(1, keepdims=True), 1e-12)
    weight_depth = depth[np.arange(len(depth)), np.argmax(cdf >= 0.5, axis=1)]
    ts = np.linspace(-window, window, 65)
    along = points[:, None] - ts[None, :, None] * normals[:, None]
    psi = model.udf(torch.tensor(along.reshape(-1, 3), dtype=torch.float32)).numpy().reshape(len(points), -1)
    return weight_depth, ts[np.abs(psi).argmin(1)]  # abs: the NeuS-SDF baseline's field is signed


if __name__ == "__main__":
    main()
