"""Meshes from neural distance fields: open surfaces from a UDF, closed ones from an SDF.

A UDF has no sign, so marching cubes at 0 does not apply. Two ways around it, behind one function
(:func:`extract_mesh`), and plain marching cubes for a signed field:

- ``"meshudf"`` (Guillard et al. 2022, :mod:`.meshudf`): marching cubes on per-cell *pseudo-signs* from
  the UDF's gradients. Keeps thin open sheets as they are, vertices on the zero level; pinholes that
  remain where the field is off are closed (``fill_holes``).
- ``"spsr"`` (the NeUDF paper's "masked Poisson", :mod:`.spsr`): points moved onto the zero level set,
  screened Poisson per connected piece, then the faces where the UDF is not near zero are deleted.
- ``"mc"``: plain marching cubes of a signed field at ``level`` (the NeuS-SDF baseline).

All three evaluate the field sparsely (:mod:`.grid`) and share one marching cubes that takes per-cell
signs (:mod:`.marching_cubes`); :mod:`.cleanup` merges, orients and trims the result and drops what no
camera sees. Meshing a trained run folder is :func:`neudf_core.extract.mesh_run`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Literal

import numpy as np
import torch
import trimesh

from neudf_core.meshing.cleanup import (
    NothingSeenError, clean_mesh, cull_unseen, drop_small_components, fill_small_holes, orient_faces,
    orient_normals, views_seeing,
)
from neudf_core.meshing.grid import (
    UNIT_BOUNDS, Bounds, FieldFn, GradFn, Grid, NoSurfaceError, SparseGrid, as_points, cell_corners,
    evaluate_field, evaluate_gradient, make_grid, no_surface, sample_sparse,
)
from neudf_core.meshing.marching_cubes import marching_cubes
from neudf_core.meshing.meshudf import _meshudf, probe_weak_gradients, pseudo_signs
from neudf_core.meshing.spsr import _spsr
from neudf_core.progress import ProgressFn, null_progress, sub_progress

__all__ = [
    "UNIT_BOUNDS", "Bounds", "ColorFn", "FieldFn", "GradFn", "Grid", "Method", "NoSurfaceError", "NothingSeenError",
    "SparseGrid", "cell_corners", "color_vertices", "cull_unseen", "default_threshold", "drop_small_components",
    "evaluate_field", "evaluate_gradient", "extract_mesh", "fill_small_holes", "make_grid", "marching_cubes",
    "orient_faces", "orient_normals", "probe_weak_gradients", "pseudo_signs", "sample_sparse",
    "views_seeing",
]

log = logging.getLogger(__name__)

Method = Literal["meshudf", "spsr", "mc"]
# Holes up to this share of the box's side in perimeter are closed: 0.25 in the unit sphere's box, a round hole
# 0.08 across. The holes a learned field left in a garment's cloth measured up to 0.23 (pants on video); the
# smallest openings of the five garments measure 0.78 (GT's sphere), a thin learned pants' legs 0.59.
FILL_HOLES_SHARE = 0.125
# Holes up to this share of the box's side can be closed where the field covers them (its median across the
# hole at most the meshing threshold) and the mesh does not: tears in cloth few cameras see, which culling
# cut (polo, pants on video). Off by default: where the field lids an opening that culling opened (two on the
# poncho on video) it closes the opening again (docs/experiments.md).
FILL_COVERED_SHARE = 0.0
# Slits up to this share of the box's side in perimeter and SLIT_WIDTH_SHARE in width (twice the vector area over
# the perimeter) are closed: tears the field left in cloth few cameras see. Pants' crotch on video: 0.28-0.60
# long, 0.006-0.016 wide in the unit sphere; the narrowest opening of a garment on video, a pants' leg, 0.07;
# a poncho's side opening wraps round and reads 0.026 wide, but is 2.9 long.
FILL_SLIT_SHARE = 0.5
SLIT_WIDTH_SHARE = 0.01
ColorFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def _mc(sparse: SparseGrid, level: float, bounds: Bounds) -> trimesh.Trimesh:
    cells, vals = cell_corners(sparse)
    vals = vals - level
    crossing = (vals.min(1) < 0) & (vals.max(1) >= 0)
    if not crossing.any():
        raise no_surface(f"the field does not cross level {level}", sparse, bounds)
    # for an SDF (negative inside) the faces come out facing the outside
    vertices, faces, _ = marching_cubes(sparse.grid, cells[crossing], vals[crossing])
    return clean_mesh(vertices, faces, tol=1e-6 * sparse.grid.voxel)


def default_threshold(method: Method, voxel: float) -> float | None:
    """The UDF level under which a face counts as on the surface, when the caller gives none.

    meshudf: 1 voxel (its vertices lie on the zero level by construction; the mask only trims boundary
    faces and the ghost sheets MeshUDF puts at non-zero UDF minima). spsr: 2 voxels (Poisson smooths
    the surface off the zero level by up to about a voxel at our depth; its lids are far off). mc: none.
    """
    return {"meshudf": 1.0 * voxel, "spsr": 2.0 * voxel, "mc": None}[method]


def extract_mesh(
    udf_fn: FieldFn,
    *,
    method: Method = "meshudf",
    resolution: int = 256,
    bounds: Bounds = UNIT_BOUNDS,
    threshold: float | None = None,
    grad_fn: GradFn | None = None,
    chunk: int = 65536,
    min_component_faces: int = 32,
    min_component_fraction: float = 0.01,
    fill_holes: float | None = None,
    fill_covered: float | None = None,
    fill_slits: float | None = None,
    level: float = 0.0,
    device: torch.device | str = "cpu",
    progress: ProgressFn = null_progress,
) -> trimesh.Trimesh:
    """A mesh of the zero level set of ``udf_fn`` (or of its ``level`` set for ``method="mc"``).

    ``udf_fn`` maps (N, 3) float32 points on ``device`` to (N,) values; it is called under no_grad in
    chunks of ``chunk`` points. Gradients (meshudf, spsr) come from ``grad_fn`` when given, else from
    autograd through ``udf_fn`` (exact, about two forward passes), else -- for a callable autograd cannot
    see through -- from central differences (see :func:`evaluate_gradient`). ``resolution`` cells span
    the longest side of ``bounds``. ``threshold``: the UDF value that counts as surface, see
    :func:`default_threshold` (logged and stored in ``mesh.metadata["meshing"]``; mc takes none). Connected
    pieces smaller than max(min_component_faces, min_component_fraction x faces) are dropped. Holes with
    a perimeter up to ``fill_holes`` are closed (holes where the field is off; default: the larger of
    :data:`FILL_HOLES_SHARE` of the longest side of ``bounds`` and 8 voxels; 0 keeps every hole), and
    holes up to ``fill_covered`` that the field covers and the mesh does not (default
    :data:`FILL_COVERED_SHARE` of the longest side, 0: none; see :func:`fill_small_holes`), and slits up
    to ``fill_slits`` long and :data:`SLIT_WIDTH_SHARE` of the longest side wide (default
    :data:`FILL_SLIT_SHARE` of it; 0: none). The mesh
    is in the coordinates of the queried points. Raises :class:`NoSurfaceError` (a ValueError) when the
    field has no surface in bounds.
    """
    if method not in ("meshudf", "spsr", "mc"):
        raise ValueError(f"unknown meshing method {method!r}: use meshudf, spsr or mc")
    grid = make_grid(bounds, resolution)
    if method == "mc" and threshold is not None:
        raise ValueError("threshold applies to the UDF methods (meshudf, spsr); mc extracts the level set")
    if threshold is None:
        threshold = default_threshold(method, grid.voxel)
        source = "default"
    else:
        if threshold <= 0:
            raise ValueError(f"threshold must be positive, got {threshold}")
        source = "given"
    log.info(
        "meshing with %s at resolution %d (voxel %.4g), threshold %s (%s)", method, resolution, grid.voxel,
        "n/a" if threshold is None else f"{threshold:.4g}", source,
    )
    progress(0.0, f"sampling the field ({method}, {resolution}^3)")
    sparse = sample_sparse(
        udf_fn, grid, level=level if method == "mc" else 0.0, chunk=chunk, device=device,
        progress=sub_progress(progress, 0.0, 0.4),
    )
    if len(sparse.blocks) == 0:
        raise NoSurfaceError(
            f"no surface in bounds {tuple(map(tuple, bounds))}: the field stays far from "
            f"{'level ' + str(level) if method == 'mc' else 'zero'} everywhere on the coarse grid"
        )
    stage = sub_progress(progress, 0.4, 0.95)
    if method == "meshudf":
        mesh = _meshudf(udf_fn, grad_fn, sparse, threshold, bounds, chunk, device, stage)
    elif method == "spsr":
        mesh = _spsr(udf_fn, grad_fn, sparse, threshold, bounds, chunk, device, stage)
    else:
        mesh = _mc(sparse, level, bounds)
    slit_width = None
    if method != "mc":
        side = float(np.max(np.subtract(bounds[1], bounds[0])))
        if fill_holes is None:
            fill_holes = max(FILL_HOLES_SHARE * side, 8 * grid.voxel)
        if fill_covered is None:
            fill_covered = FILL_COVERED_SHARE * side
        if fill_slits is None:
            fill_slits = FILL_SLIT_SHARE * side
        slit_width = SLIT_WIDTH_SHARE * side
        mesh = fill_small_holes(mesh, fill_holes, field_perimeter=fill_covered, field_level=threshold,
                                field=lambda p: evaluate_field(udf_fn, p, chunk=chunk, device=device),
                                slit_perimeter=fill_slits, slit_width=slit_width)
    mesh = drop_small_components(mesh, min_component_faces, min_component_fraction)
    if len(mesh.faces) == 0:
        raise NoSurfaceError("no surface left after dropping small components: every piece was below "
                         f"max({min_component_faces} faces, {min_component_fraction:.0%} of faces)")
    mesh.metadata["meshing"] = {
        "method": method, "resolution": resolution, "voxel": grid.voxel, "threshold": threshold,
        "threshold_source": source, "level": level if method == "mc" else None, "fill_holes": fill_holes,
        "fill_covered": fill_covered if method != "mc" else None,
        "fill_slits": fill_slits if method != "mc" else None, "slit_width": slit_width,
        "bounds": [list(map(float, bounds[0])), list(map(float, bounds[1]))],
    }
    log.info("mesh: %d vertices, %d faces", len(mesh.vertices), len(mesh.faces))
    progress(1.0, f"mesh: {len(mesh.faces)} faces")
    return mesh


def color_vertices(
    mesh: trimesh.Trimesh,
    color_fn: ColorFn,
    *,
    chunk: int = 65536,
    device: torch.device | str = "cpu",
    progress: ProgressFn = null_progress,
) -> trimesh.Trimesh:
    """Set vertex colours from ``color_fn(points, normals, view_dirs) -> rgb in 0..1`` (torch, (N, 3)).

    Each vertex is seen head-on: the view direction (camera to point, as rays have it) is the negated
    vertex normal. Modifies and returns ``mesh``.
    """
    points = np.asarray(mesh.vertices, np.float32)
    normals = np.asarray(mesh.vertex_normals, np.float32)
    rgb = np.empty((len(points), 3), np.float32)
    with torch.no_grad():
        for start in range(0, len(points), chunk):
            x = as_points(points[start : start + chunk], device)
            n = as_points(normals[start : start + chunk], device)
            rgb[start : start + len(x)] = color_fn(x, n, -n).reshape(-1, 3).float().cpu().numpy()
            progress(min(start + chunk, len(points)) / max(len(points), 1), "colouring vertices")
    rgba = np.concatenate([np.clip(rgb, 0, 1) * 255, np.full((len(rgb), 1), 255.0)], 1)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba.round().astype(np.uint8))
    return mesh
