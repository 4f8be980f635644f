"""Diagnostic: where a mesh's Chamfer distance to GT comes from, and what dropping its far faces would leave.

Splits both directed terms of the Chamfer distance (`neudf eval`'s convention: GT's unit sphere, exact
point-to-triangle distances) into distance bands: the share of samples in each band, the part of the
directed mean they contribute and their median position. Then an oracle bound: the Chamfer distance after
dropping every predicted face whose centre lies farther than t from GT. No method can see GT, so this
is not a result; it says how much removing stray sheets (lids over openings, say) could gain at best,
and how much is left in the surface that does cover GT.

    .venv/bin/python bench/error_bands.py /tmp/q/pants/neudf/mesh.ply /tmp/q/pants/data/mesh_gt.ply
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neudf_core.metrics import closest_on_surface, directed_distances, evaluate, load_mesh  # noqa: E402
from neudf_core.metrics import unit_sphere_normalisation  # noqa: E402

BANDS = (0.0, 0.005, 0.01, 0.02, 0.05, np.inf)


def band_rows(points: np.ndarray, distance: np.ndarray) -> list[dict]:
    rows = []
    for lo, hi in zip(BANDS[:-1], BANDS[1:]):
        inside = (distance >= lo) & (distance < hi)
        rows.append({
            "band": [lo, None if np.isinf(hi) else hi],
            "share": float(inside.mean()),
            "contribution": float(distance[inside].sum() / len(distance)),
            "median_point": np.median(points[inside], axis=0).round(3).tolist() if inside.any() else None,
        })
    return rows


def drop_far_faces(pred, gt, limit: float):
    """``pred`` without the faces whose centre is farther than ``limit`` from GT (GT's unit sphere)."""
    centre, scale = unit_sphere_normalisation(gt)
    gt_n = gt.copy()
    gt_n.apply_translation(-centre)
    gt_n.apply_scale(scale)
    distance, _ = closest_on_surface(gt_n, (np.asarray(pred.triangles_center) - centre) * scale)
    keep = np.flatnonzero(distance <= limit)
    return pred.submesh([keep], append=True) if len(keep) else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mesh", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("--drop", type=float, nargs="*", default=[0.05, 0.03, 0.02],
                    help="oracle bound: drop predicted faces farther than each of these from GT")
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--out", type=Path, default=None, help="also write the figures as JSON")
    args = ap.parse_args()

    pred, gt = load_mesh(args.mesh), load_mesh(args.gt)
    pred_side, gt_side, _ = directed_distances(pred, gt, n_samples=args.samples)
    report = {"mesh": str(args.mesh), "gt": str(args.gt), "samples": args.samples, "bands": {}, "drop": []}
    for name, side in (("accuracy (mesh -> GT)", pred_side), ("completeness (GT -> mesh)", gt_side)):
        rows = band_rows(side["point"], side["distance"])
        report["bands"][name] = rows
        print(f"{name}: mean {side['distance'].mean() * 1e3:.2f} x1e-3")
        print(f"  {'band':>14}{'share':>8}{'x1e-3':>8}  median point")
        for r in rows:
            lo, hi = r["band"]
            label = f"{lo:g}-{hi:g}" if hi is not None else f">= {lo:g}"
            print(f"  {label:>14}{r['share']:>8.3f}{r['contribution'] * 1e3:>8.2f}  {r['median_point']}")
    base = evaluate(pred, gt, n_samples=args.samples)
    print(f"\n{'drop faces farther than':>24}{'Chamfer':>9}{'acc.':>8}{'compl.':>8}{'F':>7}")
    print(f"{'(none)':>24}{base['chamfer'] * 1e3:>9.2f}{base['chamfer_pred_to_gt'] * 1e3:>8.2f}"
          f"{base['chamfer_gt_to_pred'] * 1e3:>8.2f}{base['fscore']:>7.3f}")
    for limit in args.drop:
        kept = drop_far_faces(pred, gt, limit)
        if kept is None:
            print(f"{limit:>24g}  no face left")
            continue
        m = evaluate(kept, gt, n_samples=args.samples)
        report["drop"].append({"limit": limit, **{k: m[k] for k in ("chamfer", "chamfer_pred_to_gt",
                                                                      "chamfer_gt_to_pred", "fscore")}})
        print(f"{limit:>24g}{m['chamfer'] * 1e3:>9.2f}{m['chamfer_pred_to_gt'] * 1e3:>8.2f}"
              f"{m['chamfer_gt_to_pred'] * 1e3:>8.2f}{m['fscore']:>7.3f}")
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
