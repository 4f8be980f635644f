"""Diagnostic: how a trained UDF behaves across the ground-truth surface.

Samples points on GT, steps along GT's normals by fixed offsets and prints Psi's quantiles at each
offset. A UDF that touches zero on the surface and grows on both sides is healthy; Psi ~ 0 over a range
of offsets on one side is a zero *region* (see loss.zero_region_weight); a minimum above zero or away
from offset 0 is a surface that is shifted or not reached. Run folders come from `neudf train` or from
bench/quality.py --work-dir (<work>/<mesh>/<method>, GT in <work>/<mesh>/data/mesh_gt.ply).

    .venv/bin/python bench/udf_profile.py /tmp/q4/tshirt/neudf /tmp/q4/tshirt/data/mesh_gt.ply
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neudf_core.trainer import load_model  # noqa: E402

OFFSETS = (-0.06, -0.04, -0.03, -0.02, -0.01, -0.005, 0.0, 0.005, 0.01, 0.02, 0.03, 0.04, 0.06)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="training run folder")
    ap.add_argument("gt", type=Path, help="GT mesh in the run's unit-sphere coordinates")
    ap.add_argument("--samples", type=int, default=5000)
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


if __name__ == "__main__":
    main()
