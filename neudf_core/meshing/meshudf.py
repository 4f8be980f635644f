"""MeshUDF (Guillard et al. 2022): marching cubes on per-cell pseudo-signs of an unsigned field.

In each grid cell near the surface a corner is "+" when its UDF gradient agrees with the cell's reference
gradient and "-" when it points the other way (the surface lies between); cells whose gradients point at
each other across a sign change (a ridge of the UDF, not a surface) are rejected; faces whose vertices'
UDF exceeds the threshold are dropped. Keeps thin open sheets as they are, vertices on the zero level.

A learned UDF is not an exact distance: it bottoms out above zero (softplus output) and its gradient is
weak and noisy in a band around the surface. So the near-surface band is widened by the threshold, the
floor is estimated from the vertices and undone before placing them, and corners with a weak gradient
take the gradient found half a voxel away (a cell-independent rule, so neighbouring cells agree on their
pseudo-signs).
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import trimesh

from neudf_core.meshing.cleanup import clean_mesh, orient_faces
from neudf_core.meshing.grid import (
    CORNERS, EDGES, Bounds, FieldFn, GradFn, SparseGrid, cell_corners, evaluate_field, evaluate_gradient, no_surface,
)
from neudf_core.meshing.marching_cubes import marching_cubes
from neudf_core.progress import ProgressFn, sub_progress

log = logging.getLogger(__name__)

# MeshUDF's near-surface test, in voxels: a plane through a cell gives at most mean 0.87 and max sqrt(3).
NEAR_MEAN_VOXELS = 1.05
NEAR_MAX_VOXELS = 1.74
# A sign change between corners a -> b is believed when the gradients point away from each other along
# the edge (the surface lies between them); a cell where a normalised gradient points *towards* the
# other corner by more than this (cos 60 deg) is rejected: a ridge of the UDF, not a surface. 0.1 let
# the noise of a learned-like test field reject cells on edges nearly parallel to the surface.
FACING_TOLERANCE = 0.5
TIE_BREAK = np.array([0.267, 0.535, 0.802])  # a generic direction, for corners on the surface
TRUSTED_GRAD = 0.3  # gradient norm (x the median) from which a corner votes in the gradient test
WEAK_GRAD = 0.1  # gradient norm (x the median) under which a corner's own direction is not used
# TIE_BREAK and two directions orthogonal to it (Gram-Schmidt): at least one is a fair way off any plane
PROBE_DIRECTIONS = np.linalg.qr(np.array([TIE_BREAK, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).T)[0].T
PROBE_DIRECTIONS *= np.sign(PROBE_DIRECTIONS[0] @ TIE_BREAK)


def probe_weak_gradients(
    udf_fn: FieldFn, grad_fn: GradFn | None, points: np.ndarray, grads: np.ndarray, voxel: float,
    chunk: int, device: torch.device | str,
) -> tuple[np.ndarray, np.ndarray]:
    """Replace the gradients of grid points that sit in the UDF's flat band by a probe's.

    Near its zero level a learned UDF flattens out (softplus floor, smoothed cusp): there the gradient is
    weak and its direction noise, so two cells sharing such a corner can give it contradicting
    pseudo-signs, which leaves a pinhole. Such a point
    is as good as on the surface, so we treat it as nudged half a voxel along a fixed generic direction:
    it takes the gradient found there, which says on which side of the surface the nudge went. The rule
    depends on the point alone, so every cell agrees. If the probe is weak too (the direction runs along
    the surface), two more orthogonal directions are tried. Returns (gradients, which points were probed).
    """
    norm = np.linalg.norm(grads, axis=1)
    strong = WEAK_GRAD * float(np.median(norm[np.isfinite(norm)])) if np.isfinite(norm).any() else 0.0
    weak = ~(norm >= strong)  # also NaN
    probed = weak.copy()
    grads = grads.copy()
    todo = np.nonzero(weak)[0]
    for direction in PROBE_DIRECTIONS:
        if len(todo) == 0:
            break
        probe = evaluate_gradient(udf_fn, points[todo] + 0.5 * voxel * direction, grad_fn=grad_fn,
                                  step=voxel / 4, chunk=chunk, device=device)
        ok = np.linalg.norm(probe, axis=1) >= strong
        grads[todo[ok]] = probe[ok]
        todo = todo[~ok]
    if len(todo):
        grads[todo] = 0.0  # still nothing: pseudo_signs falls back to the fixed tie-break
    log.info("meshudf: %d of %d corner gradients weak (< %.2f x median), probed", int(weak.sum()), len(norm),
             WEAK_GRAD)
    return grads, probed


def pseudo_signs(
    vals: np.ndarray, grads: np.ndarray, voxel: float, trusted: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """MeshUDF's per-cell signs: (M, 8) +-1 and (M,) whether the cell passes the gradient test.

    ``vals`` (M, 8) UDF and ``grads`` (M, 8, 3) gradients at each cell's corners. A corner is "+" when its
    gradient agrees with the cell's reference gradient (that of the corner farthest from the surface,
    the least affected by the cusp at the zero level) and "-" when it points the other way.

    A corner with no gradient (an analytic field sampled exactly on its zero level: a plane on a grid
    plane) is treated as nudged along -TIE_BREAK: it sits on the reference side iff the reference
    gradient faces away from TIE_BREAK, so of the two cells sharing that plane exactly one makes faces.
    (Widening this to corners with merely weak gradients, as a learned UDF has near its floor, made
    hundreds of holes in a test bowl wherever the surface normal is nearly perpendicular to TIE_BREAK.)
    """
    norm = np.linalg.norm(grads, axis=-1)
    g = grads / np.maximum(norm, 1e-12)[..., None]
    unreliable = ~(norm > 1e-6 * np.median(norm))  # also catches NaN
    far = np.where(unreliable, -np.inf, vals)
    rows = np.arange(len(vals))
    ref = g[rows, far.argmax(1)]
    sign = np.where(np.einsum("mkc,mc->mk", g, ref) >= 0, 1.0, -1.0)
    tie = np.where(ref @ TIE_BREAK < 0, 1.0, -1.0)
    sign = np.where(unreliable, tie[:, None], sign)
    # A sign change a -> b is believed unless a gradient points clearly towards the other corner (a
    # ridge of the UDF between two surfaces, not a surface). Only strong gradients vote: in the band
    # where a learned UDF flattens out at its floor, the gradient's direction is noise.
    strong = norm >= TRUSTED_GRAD * np.median(norm)
    trusted = strong if trusted is None else strong & trusted
    facing = np.isfinite(far[rows, far.argmax(1)])  # a cell with no reliable corner has no reference
    for a, b, ax in EDGES:
        change = sign[:, a] != sign[:, b]
        bad = (trusted[:, a] & (g[:, a, ax] > FACING_TOLERANCE)) | (trusted[:, b] & (g[:, b, ax] < -FACING_TOLERANCE))
        facing &= ~(change & bad)
    return sign, facing


def _meshudf(
    udf_fn: FieldFn, grad_fn: GradFn | None, sparse: SparseGrid, threshold: float, bounds: Bounds,
    chunk: int, device: torch.device | str, progress: ProgressFn,
) -> trimesh.Trimesh:
    grid, h = sparse.grid, sparse.grid.voxel
    cells, vals = cell_corners(sparse)
    lowest = float(sparse.values.min())
    if lowest >= threshold:
        raise no_surface(f"the UDF never drops below threshold {threshold:.4g}", sparse, bounds)
    # MeshUDF's band (mean < 1.05, max <= 1.74 voxel), widened by the threshold: a learned UDF bottoms
    # out above 0 and the floor varies, and a cell left out is a hole (the unwidened test left hundreds
    # in a test bowl with a floor of 0.6 voxel).
    near = (
        (vals.min(1) <= threshold)
        & (vals.mean(1) < NEAR_MEAN_VOXELS * h + threshold)
        & (vals.max(1) <= NEAR_MAX_VOXELS * h + threshold)
    )
    cells, vals = cells[near], vals[near].astype(np.float64)
    if len(cells) == 0:
        raise no_surface("no grid cell lies within a voxel of the UDF's zero level", sparse, bounds)
    pids = grid.point_id(cells[:, None, :] + CORNERS[None])  # (M, 8)
    unique, inverse = np.unique(pids, return_inverse=True)
    points = grid.position(grid.point_index(unique))
    grads = evaluate_gradient(
        udf_fn, points, grad_fn=grad_fn, step=h / 4, chunk=chunk, device=device,
        progress=sub_progress(progress, 0.0, 0.65),
    )
    grads, probed = probe_weak_gradients(udf_fn, grad_fn, points, grads, h, chunk, device)
    sign, facing = pseudo_signs(
        vals, grads[inverse.reshape(-1)].reshape(-1, 8, 3), h, ~probed[inverse.reshape(-1)].reshape(-1, 8)
    )
    log.info(
        "meshudf: %d near-surface cells, %d rejected by the gradient test", len(cells), int((~facing).sum())
    )
    cells, vals, sign = cells[facing], vals[facing], sign[facing]
    vertices, faces, _ = marching_cubes(grid, cells, sign * vals, sign > 0)
    if len(faces) == 0:
        raise no_surface("no pseudo-sign change in any near-surface cell", sparse, bounds)
    vertex_udf = evaluate_field(udf_fn, vertices, chunk=chunk, device=device)
    # A learned UDF does not reach 0: it bottoms out at a floor (the softplus output) and behaves like
    # sqrt(d^2 + floor^2) near the surface, which pulls interpolated vertices towards edge midpoints.
    # The vertices' median UDF estimates the floor (capped by the lowest grid value); undo it and place
    # the vertices again. An exact UDF gives a floor of ~0 and keeps its vertices.
    floor = min(float(np.median(vertex_udf)), lowest)
    log.info("meshudf: UDF floor %.4g = %.2f voxel", floor, floor / h)
    if floor > 0.01 * h:
        distance = np.sqrt(np.maximum(vals**2 - floor**2, 0.0))
        vertices, faces, _ = marching_cubes(grid, cells, sign * distance, sign > 0)
        vertex_udf = evaluate_field(udf_fn, vertices, chunk=chunk, device=device)  # the vertices moved
    progress(0.8, "marching cubes")
    # the paper's mask, on our vertices: a face survives when all its corners are near the zero level
    keep = (vertex_udf[faces] <= threshold).all(1)
    log.info("meshudf: %d of %d faces within threshold %.4g", int(keep.sum()), len(faces), threshold)
    if not keep.any():
        raise no_surface(f"no face has UDF <= threshold {threshold:.4g} at its vertices", sparse, bounds)
    mesh = clean_mesh(vertices, faces[keep], tol=1e-6 * h)
    return orient_faces(mesh)
