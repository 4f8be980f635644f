"""Masked screened Poisson (the NeUDF paper's meshing) of an unsigned field.

Points near the surface are moved onto the zero level set along the gradient, their unsigned normals
oriented over a neighbourhood graph, screened Poisson (open3d) makes a watertight surface per connected
piece, and the faces where the UDF is not near zero (the lids Poisson invents over openings) or the
density is low are deleted.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch
import trimesh

from neudf_core.meshing.cleanup import clean_mesh, orient_normals
from neudf_core.meshing.grid import (
    CORNERS, Bounds, FieldFn, GradFn, SparseGrid, cell_corners, evaluate_field, evaluate_gradient, no_surface,
)
from neudf_core.progress import ProgressFn, sub_progress

log = logging.getLogger(__name__)


def _spsr(
    udf_fn: FieldFn, grad_fn: GradFn | None, sparse: SparseGrid, threshold: float, bounds: Bounds,
    chunk: int, device: torch.device | str, progress: ProgressFn, *,
    projection_steps: int = 4, density_quantile: float = 0.01, seed: int = 0,
) -> trimesh.Trimesh:
    import open3d as o3d  # heavy import, only this method needs it

    grid, h = sparse.grid, sparse.grid.voxel
    cells, vals = cell_corners(sparse)
    # cells the surface passes through or touches; a learned UDF bottoms out at a floor above 0
    floor = float(sparse.values.min())
    if floor >= threshold / 2:
        raise no_surface(f"the UDF never drops below threshold / 2 = {threshold / 2:.4g}", sparse, bounds)
    near = vals.min(1) <= floor + h
    if not near.any():
        raise no_surface("no grid cell lies within a voxel of the UDF's zero level", sparse, bounds)
    # samples: the near cells' corners plus one random point in each (a denser, less regular cloud)
    corners = np.unique(grid.point_id(cells[near][:, None, :] + CORNERS[None]).reshape(-1))
    rng = np.random.default_rng(seed)
    points = np.concatenate([
        grid.position(grid.point_index(corners).astype(np.float64)),
        grid.position(cells[near] + rng.random((int(near.sum()), 3))),
    ])
    normals = None
    for step in range(projection_steps):
        sub = sub_progress(progress, 0.5 * step / projection_steps, 0.5 * (step + 1) / projection_steps)
        u, g = evaluate_gradient(udf_fn, points, grad_fn=grad_fn, step=h / 4, chunk=chunk, device=device,
                                 progress=sub, return_values=True)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        if normals is None:
            # off-surface gradients are reliable; at the surface they flip (the cusp)
            normals = g / np.maximum(norm, 1e-12)
            has_normal = norm[:, 0] > 1e-8 * np.median(norm)  # a sample exactly on the surface has none
        # p <- p - u g/|g| for a distance field; a learned UDF flattens out near its floor (|g| < 1,
        # like sqrt(d^2 + floor^2)), where u g is the better step: it does not overshoot the surface
        points = points - u[:, None] * g / np.maximum(norm, 1.0)
    u = evaluate_field(udf_fn, points, chunk=chunk, device=device)
    on = (u <= threshold / 2) & has_normal
    points, normals = points[on], normals[on]
    log.info("spsr: %d points on the zero level set (udf <= %.3g)", len(points), threshold / 2)
    if len(points) < 100:
        raise no_surface(f"only {len(points)} points reached the zero level set", sparse, bounds)
    # UDF gradients are unsigned: propagate one orientation over the neighbourhood graph. Samples from
    # both sides of a sheet land on the same spots, so orient one per half voxel and let every sample
    # take the side of its nearest oriented one.
    from scipy.spatial import cKDTree

    _, first = np.unique(np.floor((points - grid.lo) / (h / 2)).astype(np.int64), axis=0, return_index=True)
    oriented, piece = orient_normals(points[first], normals[first])
    _, nearest = cKDTree(points[first]).query(points, workers=-1)
    normals = np.where((np.sum(normals * oriented[nearest], axis=1) < 0)[:, None], -normals, normals)
    piece = piece[nearest]
    # Separate pieces (two parallel sheets) get independent orientation signs, and screened Poisson
    # puts its iso-level at the mean indicator over all samples: two sheets facing the same way would
    # both shift off their samples. One Poisson solve per piece keeps each iso-level its own.
    sizes = np.bincount(piece)
    pieces = [p for p in np.argsort(-sizes) if sizes[p] >= 100]
    if not pieces:
        raise no_surface("the surface samples are scattered specks (< 100 points each)", sparse, bounds)
    progress(0.6, "screened Poisson")
    all_vertices, all_faces, all_densities, depths = [], [], [], []
    offset = 0
    for p in pieces:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[piece == p]))
        pcd.normals = o3d.utility.Vector3dVector(normals[piece == p].astype(np.float64))
        # average per half voxel: the normals agree now, so averaging no longer cancels them
        pcd = pcd.voxel_down_sample(h / 2)
        pcd.normalize_normals()
        extent = float(np.ptp(np.asarray(pcd.points), axis=0).max())
        depth = int(np.clip(math.ceil(math.log2(1.1 * max(extent, h) / h)), 5, 11))
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            poisson, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pcd, depth=depth, scale=1.1, linear_fit=False
            )
        dens = np.asarray(dens)
        # low density: the solver's guess far from any sample (quantile per piece: densities scale
        # with the piece's sampling)
        dense = dens >= np.quantile(dens, density_quantile) if len(dens) else dens.astype(bool)
        all_vertices.append(np.asarray(poisson.vertices))
        all_faces.append(np.asarray(poisson.triangles) + offset)
        all_densities.append(dense)
        depths.append(depth)
        offset += len(poisson.vertices)
    vertices, faces = np.concatenate(all_vertices), np.concatenate(all_faces)
    dense = np.concatenate(all_densities)
    log.info("spsr: %d oriented points in %d pieces, Poisson depth %s", len(points), len(pieces), depths)
    progress(0.85, "masking the Poisson surface")
    vertex_udf = evaluate_field(udf_fn, vertices, chunk=chunk, device=device)
    centroid_udf = evaluate_field(udf_fn, vertices[faces].mean(1), chunk=chunk, device=device)
    keep = (vertex_udf[faces] <= threshold).all(1) & (centroid_udf <= threshold) & dense[faces].all(1)
    log.info(
        "spsr: %d of %d Poisson faces kept (udf <= %.4g, density above its %.0f%% quantile)",
        int(keep.sum()), len(faces), threshold, 100 * density_quantile,
    )
    if not keep.any():
        raise no_surface(f"no Poisson face has UDF <= threshold {threshold:.4g}", sparse, bounds)
    return clean_mesh(vertices, faces[keep], tol=1e-6 * h)
