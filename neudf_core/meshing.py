"""Meshes from neural distance fields: open surfaces from a UDF, closed ones from an SDF.

A UDF has no sign, so marching cubes at 0 does not apply. Two ways around it, behind one function
(:func:`extract_mesh`):

- ``"meshudf"`` (Guillard et al. 2022): marching cubes on *pseudo-signs*. In each grid cell near the
  surface a corner is "+" when its UDF gradient agrees with the cell's reference gradient and "-" when it
  points the other way (the surface lies between); cells whose gradients point at each other across a
  sign change (a ridge of the UDF, not a surface) are rejected; faces whose vertices' UDF exceeds the
  threshold are dropped. Keeps thin open sheets as they are, vertices on the zero level.
- ``"spsr"`` (the NeUDF paper's "masked Poisson"): points near the surface are moved onto the zero
  level set along the gradient, their unsigned normals oriented over a neighbourhood graph, screened
  Poisson (open3d) makes a watertight surface per connected piece, and the faces where the UDF is not
  near zero (the lids Poisson invents over openings) or the density is low are deleted.
- ``"mc"``: plain marching cubes of a signed field at ``level`` (the NeuS-SDF baseline).

A learned UDF is not an exact distance: it bottoms out above zero (softplus output) and its gradient is
weak and noisy in a band around the surface. meshudf therefore widens MeshUDF's near-surface band by the
threshold, estimates the floor from its vertices and undoes it before placing them, and gives corners
with a weak gradient the gradient found half a voxel away (a cell-independent rule, so neighbouring cells
agree on their pseudo-signs); pinholes that remain where the field is off are closed (``fill_holes``).
Tests fit this on analytic UDFs, on a noisy floored one, and on an MLP fitted to a bowl.

With the dataset's cameras, :func:`mesh_run` then drops the faces too few of them see
(:func:`cull_unseen`): an unsigned field is free wherever no image constrains it.

All three evaluate the field sparsely: a coarse pass over blocks of 8^3 cells discards empty space (a
distance field cannot drop by more than the distance travelled, see CULL_SAFETY), then only the kept
blocks are evaluated at full resolution, in chunks, so memory stays bounded at resolution 512.

Marching cubes is our own, vectorised over cells. Its table is not copied from anywhere: it is generated
from first principles (walk the iso-contour around the cube's faces, fan-triangulate each loop), and the
face ambiguities are resolved per cell with the asymptotic decider, which is invariant to flipping all
signs -- a property pseudo-signs need, since each cell picks its own reference. (skimage's
marching_cubes would need one call per cell for per-cell signs.)
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

from neudf_core.dataset import Cameras, load_cameras
from neudf_core.metrics import split_pinched_vertices
from neudf_core.numerics import flush_denormals
from neudf_core.progress import ProgressFn, null_progress, sub_progress

log = logging.getLogger(__name__)

Method = Literal["meshudf", "spsr", "mc"]
FieldFn = Callable[[torch.Tensor], torch.Tensor]
GradFn = Callable[[torch.Tensor], torch.Tensor]
ColorFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
Bounds = tuple[Sequence[float], Sequence[float]]

UNIT_BOUNDS: Bounds = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
BLOCK = 8  # cells per block side in the coarse empty-space pass
# A learned UDF is only roughly 1-Lipschitz (the eikonal loss is soft): the coarse pass keeps a block
# when its centre value is below CULL_SAFETY x the block's half diagonal (+ 2 voxels).
CULL_SAFETY = 2.0
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


@dataclass(frozen=True)
class Grid:
    """A regular grid of cubic voxels covering ``bounds``; cells are padded up to whole blocks."""

    lo: np.ndarray  # (3,) float64, the first grid point
    voxel: float
    cells: np.ndarray  # (3,) int, cells per axis that lie inside the requested bounds
    blocks: np.ndarray  # (3,) int, blocks per axis (cells padded to blocks * BLOCK)

    @property
    def point_dims(self) -> np.ndarray:
        """Grid points per axis of the padded grid (the linear index space of points and edges)."""
        return self.blocks * BLOCK + 1

    def point_id(self, idx: np.ndarray) -> np.ndarray:
        d = self.point_dims.astype(np.int64)
        idx = idx.astype(np.int64)
        return (idx[..., 0] * d[1] + idx[..., 1]) * d[2] + idx[..., 2]

    def point_index(self, pid: np.ndarray) -> np.ndarray:
        d = self.point_dims.astype(np.int64)
        return np.stack([pid // (d[1] * d[2]), (pid // d[2]) % d[1], pid % d[2]], -1)

    def position(self, idx: np.ndarray) -> np.ndarray:
        return self.lo + idx * self.voxel


def make_grid(bounds: Bounds, resolution: int) -> Grid:
    """Cubic voxels: ``resolution`` cells along the longest side of ``bounds``."""
    lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
        raise ValueError(f"bounds must be ((x0, y0, z0), (x1, y1, z1)) with x1 > x0 etc., got {bounds}")
    if resolution < 8:
        raise ValueError(f"resolution must be at least 8, got {resolution}")
    voxel = float((hi - lo).max() / resolution)
    cells = np.maximum(np.ceil((hi - lo) / voxel - 1e-9).astype(int), 1)
    return Grid(lo, voxel, cells, -(-cells // BLOCK))


# --------------------------------------------------------------------------- field evaluation


def _as_points(points: np.ndarray, device: torch.device | str) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(points, dtype=np.float32), device=device)


def evaluate_field(
    fn: FieldFn,
    points: np.ndarray,
    *,
    chunk: int = 65536,
    device: torch.device | str = "cpu",
    progress: ProgressFn = null_progress,
) -> np.ndarray:
    """``fn`` at ``points`` (N, 3), in chunks under ``torch.no_grad``; float32 (N,)."""
    out = np.empty(len(points), np.float32)
    with torch.no_grad():
        for start in range(0, len(points), chunk):
            x = _as_points(points[start : start + chunk], device)
            out[start : start + len(x)] = fn(x).reshape(-1).float().cpu().numpy()
            progress(min(start + chunk, len(points)) / max(len(points), 1), "evaluating the field")
    return out


def _autograd(fn: FieldFn, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(values, gradients), the gradients None when ``fn``'s output carries no autograd graph."""
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        y = fn(x).reshape(-1)
        if not y.requires_grad:
            return y, None
        return y.detach(), torch.autograd.grad(y.sum(), x)[0]


def _central_differences(fn: FieldFn, x: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        plus = torch.stack([fn(x + o).reshape(-1) for o in offsets], -1)
        minus = torch.stack([fn(x - o).reshape(-1) for o in offsets], -1)
        return (plus - minus) / (2 * offsets[0, 0])


def evaluate_gradient(
    fn: FieldFn,
    points: np.ndarray,
    *,
    grad_fn: GradFn | None = None,
    step: float = 1e-3,
    chunk: int = 65536,
    device: torch.device | str = "cpu",
    progress: ProgressFn = null_progress,
    return_values: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The field's gradient at ``points`` (N, 3), float32; with ``return_values``, (values, gradients).

    ``grad_fn`` when given (a model's own analytic gradient). Otherwise autograd through ``fn``: exact for
    the field the network represents, about the cost of two forward passes, where central differences cost
    six and average opposite gradients to nothing within ``step`` of the zero level set (the UDF's cusp).
    Central differences with ``step`` only when ``fn`` is not differentiable (its output carries no graph).
    """
    out = np.empty((len(points), 3), np.float32)
    values = np.empty(len(points), np.float32) if return_values else None
    offsets = torch.eye(3, device=device) * step
    use_fd = False
    for start in range(0, len(points), chunk):
        x = _as_points(points[start : start + chunk], device)
        g = y = None
        if grad_fn is not None:
            with torch.enable_grad():
                g = grad_fn(x)
        elif not use_fd:
            y, g = _autograd(fn, x)
            if g is None:
                use_fd = True
                log.info("field is not differentiable by autograd: central differences, step %.2g", step)
        if return_values:
            if y is None:
                with torch.no_grad():
                    y = fn(x)
            values[start : start + len(x)] = y.detach().reshape(-1).float().cpu().numpy()
        if g is None:
            g = _central_differences(fn, x, offsets)
        g = g.detach().reshape(-1, 3)
        bad = ~torch.isfinite(g).all(-1)
        if bad.any():  # autograd gives NaN where e.g. a norm is differentiated at 0: fall back there
            g = g.clone()
            g[bad] = _central_differences(fn, x[bad], offsets).to(g.dtype)
        out[start : start + len(x)] = g.float().cpu().numpy()
        progress(min(start + chunk, len(points)) / max(len(points), 1), "evaluating gradients")
    return (values, out) if return_values else out


# --------------------------------------------------------------------------- sparse grid


@dataclass
class SparseGrid:
    """The field sampled at full resolution inside the blocks that may hold surface."""

    grid: Grid
    blocks: np.ndarray  # (K, 3) block indices
    values: np.ndarray  # (K, B+1, B+1, B+1) field values at the blocks' grid points


def sample_sparse(
    fn: FieldFn,
    grid: Grid,
    *,
    level: float = 0.0,
    chunk: int = 65536,
    device: torch.device | str = "cpu",
    progress: ProgressFn = null_progress,
) -> SparseGrid:
    """Evaluate ``fn`` on the full-resolution grid, skipping blocks that cannot reach ``level``."""
    nb = grid.blocks
    bidx = np.stack(np.meshgrid(*[np.arange(n) for n in nb], indexing="ij"), -1).reshape(-1, 3)
    centres = grid.position((bidx + 0.5) * BLOCK)
    coarse = evaluate_field(fn, centres, chunk=chunk, device=device, progress=sub_progress(progress, 0, 0.1))
    half_diag = math.sqrt(3) * BLOCK * grid.voxel / 2
    keep = np.abs(coarse - level) <= CULL_SAFETY * half_diag + 2 * grid.voxel
    bidx = bidx[keep]
    log.info("sparse grid: %d of %d blocks of %d^3 cells may hold surface", len(bidx), len(keep), BLOCK)
    if len(bidx) == 0:
        return SparseGrid(grid, bidx, np.zeros((0, BLOCK + 1, BLOCK + 1, BLOCK + 1), np.float32))
    local = np.stack(np.meshgrid(*[np.arange(BLOCK + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pids = grid.point_id(bidx[:, None, :] * BLOCK + local[None])  # (K, (B+1)^3)
    unique, inverse = np.unique(pids, return_inverse=True)  # shared block faces are evaluated once
    vals = evaluate_field(
        fn, grid.position(grid.point_index(unique)), chunk=chunk, device=device,
        progress=sub_progress(progress, 0.1, 1.0),
    )
    return SparseGrid(grid, bidx, vals[inverse.reshape(-1)].reshape(len(bidx), BLOCK + 1, BLOCK + 1, BLOCK + 1))


# corner i of a cell sits at offset (bit0, bit1, bit2) = (x, y, z)
CORNERS = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)])
# edge = (corner a, corner b, axis) with b = a + unit step along axis
EDGES = [(a, a | (1 << ax), ax) for ax in range(3) for a in range(8) if not (a >> ax) & 1]


def cell_corners(sparse: SparseGrid) -> tuple[np.ndarray, np.ndarray]:
    """All cells of the sparse grid inside the bounds: (M, 3) cell indices and (M, 8) corner values."""
    v = sparse.values
    corner_vals = np.stack(
        [v[:, x : x + BLOCK, y : y + BLOCK, z : z + BLOCK] for x, y, z in CORNERS], -1
    ).reshape(-1, 8)
    local = np.stack(np.meshgrid(*[np.arange(BLOCK)] * 3, indexing="ij"), -1).reshape(-1, 3)
    cells = (sparse.blocks[:, None, :] * BLOCK + local[None]).reshape(-1, 3)
    inside = np.all(cells < sparse.grid.cells, axis=1)
    return cells[inside], corner_vals[inside]


# --------------------------------------------------------------------------- marching cubes


def _cube_faces() -> list[tuple[list[int], np.ndarray]]:
    """The 6 faces as (4 corners in cyclic order, outward normal)."""
    faces = []
    for ax in range(3):
        u, v = [a for a in range(3) if a != ax]
        for side in (0, 1):
            ring = [(0, 0), (1, 0), (1, 1), (0, 1)]
            corners = [(side << ax) | (cu << u) | (cv << v) for cu, cv in ring]
            normal = np.zeros(3)
            normal[ax] = 1.0 if side else -1.0
            faces.append((corners, normal))
    return faces


CUBE_FACES = _cube_faces()
_EDGE_OF = {frozenset((a, b)): i for i, (a, b, _) in enumerate(EDGES)}
_EDGE_MID = np.array([(CORNERS[a] + CORNERS[b]) / 2 for a, b, _ in EDGES], float)


@functools.lru_cache(maxsize=None)
def triangle_table(key: int) -> np.ndarray:
    """Triangles (T, 3) of local edge indices for one cell configuration.

    ``key = case + 256 * face_bits``: bit i of ``case`` says corner i is positive; bit f of
    ``face_bits`` says that on cube face f, if ambiguous (diagonal signs), the positive corners connect.
    The iso-contour is traced on each face (positive side on the left seen from outside), the segments
    are chained into loops and each loop is fan-triangulated; triangle normals point to the positive side.
    """
    case, face_bits = key & 255, key >> 8
    positive = [(case >> i) & 1 == 1 for i in range(8)]
    succ: dict[int, int] = {}
    for f, (ring, normal) in enumerate(CUBE_FACES):
        edges = [_EDGE_OF[frozenset((ring[k], ring[(k + 1) % 4]))] for k in range(4)]
        crossing = [k for k in range(4) if positive[ring[k]] != positive[ring[(k + 1) % 4]]]
        segments: list[tuple[int, int, int, bool]] = []  # (edge, edge, corner on one side, its side +?)
        if len(crossing) == 2:
            k0, k1 = crossing
            corner = next(c for c in ring if positive[c])
            segments.append((edges[k0], edges[k1], corner, True))
        elif len(crossing) == 4:
            connected = (face_bits >> f) & 1 == 1
            for k in range(4):  # cut off each corner of the sign that does not connect
                if positive[ring[k]] != connected:
                    segments.append((edges[(k - 1) % 4], edges[k], ring[k], positive[ring[k]]))
        for ea, eb, corner, corner_positive in segments:
            pa, pb = _EDGE_MID[ea], _EDGE_MID[eb]
            left = np.dot(np.cross(pb - pa, CORNERS[corner] - pa), normal) > 0
            if left != corner_positive:
                ea, eb = eb, ea
            succ[ea] = eb
    triangles = []
    while succ:
        start, loop = next(iter(succ)), []
        edge = start
        while True:
            loop.append(edge)
            edge = succ.pop(edge)
            if edge == start:
                break
        for i in range(1, len(loop) - 1):
            triangles.append((loop[0], loop[i], loop[i + 1]))
    return np.array(triangles, np.int64).reshape(-1, 3)


def marching_cubes(
    grid: Grid, cells: np.ndarray, values: np.ndarray, positive: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised marching cubes over selected cells.

    ``cells`` (M, 3) cell indices, ``values`` (M, 8) corner values, ``positive`` (M, 8) the corners'
    sides (default ``values >= 0``; given explicitly where a value is 0 but its side is known). Signs
    are per cell, so pseudo-signs may differ between neighbours. Returns vertices (V, 3), faces (F, 3) and, per face,
    the row of ``cells`` it came from. Vertices are shared through global edge ids, so a surface crossing
    cells whose signs agree comes out connected.
    """
    if positive is None:
        positive = values >= 0
    case = (positive.astype(np.int64) << np.arange(8)).sum(1)
    face_bits = np.zeros(len(values), np.int64)
    for f, (ring, _) in enumerate(CUBE_FACES):
        fv, fp = values[:, ring], positive[:, ring]
        ambiguous = (fp[:, 0] == fp[:, 2]) & (fp[:, 1] == fp[:, 3]) & (fp[:, 0] != fp[:, 1])
        # asymptotic decider: the bilinear interpolant's value at its saddle point
        num = fv[:, 0] * fv[:, 2] - fv[:, 1] * fv[:, 3]
        den = fv[:, 0] + fv[:, 2] - fv[:, 1] - fv[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            connected = ambiguous & (num / np.where(den == 0, 1.0, den) >= 0)
        face_bits |= connected.astype(np.int64) << f
    key = case + 256 * face_bits
    order = np.argsort(key, kind="stable")
    keys, starts = np.unique(key[order], return_index=True)
    ends = np.append(starts[1:], len(order))
    edge_a = np.array([a for a, _, _ in EDGES])
    edge_b = np.array([b for _, b, _ in EDGES])
    edge_axis = np.array([ax for _, _, ax in EDGES])
    tri_edges, tri_t, tri_cell = [], [], []
    for k, s, e in zip(keys, starts, ends):
        table = triangle_table(int(k))
        if len(table) == 0:
            continue
        rows = order[s:e]
        a, b = edge_a[table], edge_b[table]  # (T, 3)
        ids = 3 * grid.point_id(cells[rows][:, None, None, :] + CORNERS[a][None]) + edge_axis[table][None]
        va, vb = values[rows][:, a], values[rows][:, b]
        tri_edges.append(ids.reshape(-1, 3))
        with np.errstate(divide="ignore", invalid="ignore"):
            tri_t.append(np.nan_to_num(va / (va - vb), nan=0.5).reshape(-1, 3))
        tri_cell.append(np.repeat(rows, len(table)))
    if not tri_edges:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    edges = np.concatenate(tri_edges)
    t = np.concatenate(tri_t)
    unique, first, faces = np.unique(edges.reshape(-1), return_index=True, return_inverse=True)
    t = np.clip(t.reshape(-1)[first], 0.0, 1.0)
    start = grid.point_index(unique // 3).astype(np.float64)
    start[np.arange(len(unique)), unique % 3] += t
    return grid.position(start), faces.reshape(-1, 3), np.concatenate(tri_cell)


# --------------------------------------------------------------------------- mesh clean-up


def _clean(vertices: np.ndarray, faces: np.ndarray, tol: float) -> trimesh.Trimesh:
    """Merge coincident vertices, drop degenerate and duplicate faces."""
    key = np.round(vertices / tol).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    vertices, faces = vertices[first], inverse.reshape(-1)[faces]
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[ok]
    _, unique_rows = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    faces = faces[np.sort(unique_rows)]
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


def _face_pairs(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of faces sharing a manifold edge, and whether each pair's winding agrees."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    manifold = counts[inverse] == 2
    idx = np.nonzero(manifold)[0]
    idx = idx[np.argsort(inverse[idx], kind="stable")]
    first, second = idx[0::2], idx[1::2]
    pairs = np.stack([owner[first], owner[second]], -1)
    # consistent winding traverses a shared edge in opposite directions
    agree = directed[first, 0] == directed[second, 1]
    return pairs, agree


def _tree_parity(parent: np.ndarray, flip: np.ndarray) -> np.ndarray:
    """XOR of ``flip`` along each node's path to its root (roots are their own parent; flip[root] = 0).

    Pointer jumping: log2(depth) vectorised rounds instead of a Python walk over the tree.
    """
    parent, flip = parent.copy(), flip.copy()
    while True:
        grand = parent[parent]
        if np.array_equal(grand, parent):
            return flip
        flip = flip ^ flip[parent]
        parent = grand


def _spanning_parents(graph, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A breadth-first spanning forest of the symmetric ``graph``: (parent, roots, piece label) per node."""
    _, labels = connected_components(graph, directed=False)
    roots = np.unique(labels, return_index=True)[1]
    # one search from a virtual node (index n) linked to one node of every piece
    coo = graph.tocoo()
    src = np.concatenate([coo.row, np.full(len(roots), n)])
    dst = np.concatenate([coo.col, roots])
    full = coo_matrix((np.ones(len(src)), (src, dst)), shape=(n + 1, n + 1)).tocsr()
    _, pred = breadth_first_order(full, n, directed=True, return_predecessors=True)
    parent = pred[:n].astype(np.int64)
    parent[roots] = roots
    return parent, roots, labels


def orient_normals(points: np.ndarray, normals: np.ndarray, k: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Flip unsigned normals into a consistent orientation per connected piece (Hoppe et al. 1992).

    Returns the normals and, per point, the label of its piece of the neighbourhood graph: pieces are
    oriented independently, each by an arbitrary sign.

    Minimum spanning tree of the k-nearest-neighbour graph weighted by 1 - |cos|, then each normal takes
    its tree parent's side. open3d's orient_normals_consistent_tangent_plane does the same but builds a
    Delaunay graph with qhull first, which fails on flat input (a planar sheet).
    """
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial import cKDTree

    n = len(points)
    _, nbr = cKDTree(points).query(points, k=min(k + 1, n), workers=-1)
    rows = np.repeat(np.arange(n), nbr.shape[1] - 1)
    cols = nbr[:, 1:].reshape(-1)
    weight = 1.0 - np.abs(np.sum(normals[rows] * normals[cols], axis=1)) + 1e-6
    mst = minimum_spanning_tree(coo_matrix((weight, (rows, cols)), shape=(n, n))).tocoo()
    sym = coo_matrix(
        (np.ones(2 * len(mst.row)), (np.concatenate([mst.row, mst.col]), np.concatenate([mst.col, mst.row]))),
        shape=(n, n),
    ).tocsr()
    parent, roots, labels = _spanning_parents(sym, n)
    flip = np.sum(normals * normals[parent], axis=1) < 0
    flip[roots] = False
    return np.where(_tree_parity(parent, flip)[:, None], -normals, normals), labels


def orient_faces(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Make the winding consistent across each connected piece (a spanning tree over shared edges).

    trimesh.repair.fix_winding does the same through networkx, about 100x slower at 10^5 faces.
    A non-orientable piece keeps the tree's choice.
    """
    faces = mesh.faces.copy()
    n = len(faces)
    if n == 0:
        return mesh
    pairs, agree = _face_pairs(faces)
    adjacency = coo_matrix(
        (np.ones(2 * len(pairs)), (np.concatenate([pairs[:, 0], pairs[:, 1]]),
                                   np.concatenate([pairs[:, 1], pairs[:, 0]]))),
        shape=(n, n),
    ).tocsr()
    parent, roots, _ = _spanning_parents(adjacency, n)
    # does a face's winding disagree with its tree parent's? look the pair up by a sorted key
    pair_key = np.sort(pairs, axis=1) @ np.array([n, 1], np.int64)
    order = np.argsort(pair_key)
    child_key = np.sort(np.stack([np.arange(n), parent], -1), axis=1) @ np.array([n, 1], np.int64)
    flip = np.zeros(n, bool)
    if len(order):
        pos = np.clip(np.searchsorted(pair_key[order], child_key), 0, len(order) - 1)
        flip = (pair_key[order][pos] == child_key) & ~agree[order][pos]
    flip[roots] = False
    flip = _tree_parity(parent, flip)
    faces[flip] = faces[flip][:, ::-1]
    return trimesh.Trimesh(mesh.vertices, faces, process=False)


def fill_small_holes(mesh: trimesh.Trimesh, max_perimeter: float) -> trimesh.Trimesh:
    """Close boundary loops no longer than ``max_perimeter`` with a fan around their centroid.

    Where a learned UDF is off by more than a voxel, neighbouring cells can disagree on a pseudo-sign
    and leave a pinhole of a few voxels (an MLP fitted to a bowl: 1 at resolution 256, ~60 at 512);
    a real opening of a garment is far longer. Loops are traced per fan of faces (a pinhole touching
    another at a vertex is two loops). Expects consistent winding: each boundary edge a -> b of a face
    gets the triangle (b, a, centre).
    """
    if max_perimeter <= 0 or len(mesh.faces) == 0:
        return mesh
    faces = np.asarray(mesh.faces)
    wedges = split_pinched_vertices(faces)  # per-fan vertex ids
    vertex_of = np.empty(wedges.max() + 1, np.int64)
    vertex_of[wedges.reshape(-1)] = faces.reshape(-1)
    directed = np.concatenate([wedges[:, [0, 1]], wedges[:, [1, 2]], wedges[:, [2, 0]]])
    _, inverse, counts = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inverse.reshape(-1)] == 1]
    if len(boundary) == 0:
        return mesh
    ids, local = np.unique(boundary, return_inverse=True)
    local = local.reshape(-1, 2)
    n = len(ids)
    graph = coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    edge_label = labels[local[:, 0]]
    n_edges, n_ids = np.bincount(edge_label), np.bincount(labels)
    ends = vertex_of[boundary]  # back to the mesh's vertices
    lengths = np.linalg.norm(mesh.vertices[ends[:, 0]] - mesh.vertices[ends[:, 1]], axis=1)
    perimeter = np.bincount(edge_label, weights=lengths)
    small = (perimeter <= max_perimeter) & (n_edges == n_ids)  # a simple loop
    if not small.any():
        return mesh
    holes = np.nonzero(small)[0]
    centre_of = np.full(len(n_edges), -1)
    centre_of[holes] = len(mesh.vertices) + np.arange(len(holes))
    sums = np.zeros((len(n_edges), 3))
    np.add.at(sums, labels, mesh.vertices[vertex_of[ids]])
    centres = sums[holes] / n_ids[holes, None]
    fill = small[edge_label]
    new_faces = np.stack([ends[fill, 1], ends[fill, 0], centre_of[edge_label[fill]]], -1)
    log.info("filled %d pinholes with perimeters up to %.3g", len(holes), max_perimeter)
    return trimesh.Trimesh(np.vstack([mesh.vertices, centres]), np.vstack([faces, new_faces]), process=False)


def drop_small_components(
    mesh: trimesh.Trimesh, min_faces: int, min_fraction: float
) -> trimesh.Trimesh:
    """Keep connected pieces (through shared edges) with at least max(min_faces, min_fraction x F) faces."""
    n = len(mesh.faces)
    if n == 0:
        return mesh
    pairs, _ = _face_pairs(mesh.faces)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    keep = sizes[labels] >= max(min_faces, min_fraction * n)
    dropped = int(np.sum(sizes < max(min_faces, min_fraction * n)))
    if dropped:
        log.info("dropped %d small components (%d faces)", dropped, int(n - keep.sum()))
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    out.remove_unreferenced_vertices()
    return out


def views_seeing(vertices: np.ndarray, faces: np.ndarray, cameras: Cameras, tol: float) -> np.ndarray:
    """How many cameras see each vertex: it lies in front of the camera and inside its image, and the
    ray from the camera's centre meets no face more than ``tol`` before it."""
    import open3d as o3d  # heavy import, only visibility needs it

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    counts = np.zeros(len(vertices), np.int64)
    for K, c2w in zip(cameras.intrinsics, cameras.c2w):
        centre = c2w[:3, 3]
        offset = vertices - centre
        in_camera = offset @ c2w[:3, :3]  # R^T (x - c) for each row
        z = in_camera[:, 2]
        pixels = in_camera @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = pixels[:, 0] / z, pixels[:, 1] / z
        in_view = (z > 1e-9) & (u >= 0) & (u <= cameras.width) & (v >= 0) & (v <= cameras.height)
        dist = np.linalg.norm(offset, axis=1)
        rays = np.concatenate([np.broadcast_to(centre, offset.shape), offset / np.maximum(dist, 1e-12)[:, None]], 1)
        hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        counts += in_view & (hit >= dist - tol)
    return counts


def cull_unseen(mesh: trimesh.Trimesh, cameras: Cameras, min_fraction: float, tol: float) -> trimesh.Trimesh:
    """Drop the faces that fewer than ``min_fraction`` of the cameras see (all three vertices).

    An unsigned field is only constrained where the images see it; where none does (the inside of a
    tube, behind a wall) it may close over or grow sheets no view can refute. A face the cameras keep
    seeing is a surface the images chose.
    """
    need = max(1, math.ceil(min_fraction * len(cameras)))
    counts = views_seeing(np.asarray(mesh.vertices), np.asarray(mesh.faces), cameras, tol)
    keep = (counts[mesh.faces] >= need).all(1)
    log.info("visibility: %d of %d faces seen by >= %d of %d views", int(keep.sum()), len(keep), need, len(cameras))
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    out.remove_unreferenced_vertices()
    return out


# --------------------------------------------------------------------------- the methods


def _no_surface(what: str, sparse: SparseGrid, bounds: Bounds) -> ValueError:
    lowest = float(sparse.values.min()) if sparse.values.size else float("nan")
    return ValueError(
        f"no surface in bounds {tuple(map(tuple, bounds))}: {what}"
        + (f" (lowest field value on the grid {lowest:.4g})" if sparse.values.size else "")
    )


def probe_weak_gradients(
    udf_fn: FieldFn, grad_fn: GradFn | None, points: np.ndarray, grads: np.ndarray, voxel: float,
    chunk: int, device: torch.device | str,
) -> tuple[np.ndarray, np.ndarray]:
    """Replace the gradients of grid points that sit in the UDF's flat band by a probe's.

    Near its zero level a learned UDF flattens out (softplus floor, smoothed cusp): there the gradient is
    weak and its direction noise, so two cells sharing such a corner can give it contradicting
    pseudo-signs, which leaves a pinhole (seen in a noisy test bowl and an MLP fitted to it). Such a point
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
        raise _no_surface(f"the UDF never drops below threshold {threshold:.4g}", sparse, bounds)
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
        raise _no_surface("no grid cell lies within a voxel of the UDF's zero level", sparse, bounds)
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
        raise _no_surface("no pseudo-sign change in any near-surface cell", sparse, bounds)
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
        vertex_udf = evaluate_field(udf_fn, vertices, chunk=chunk, device=device)
    progress(0.8, "marching cubes")
    # the paper's mask, on our vertices: a face survives when all its corners are near the zero level
    vertex_udf = evaluate_field(udf_fn, vertices, chunk=chunk, device=device)
    keep = (vertex_udf[faces] <= threshold).all(1)
    log.info("meshudf: %d of %d faces within threshold %.4g", int(keep.sum()), len(faces), threshold)
    if not keep.any():
        raise _no_surface(f"no face has UDF <= threshold {threshold:.4g} at its vertices", sparse, bounds)
    mesh = _clean(vertices, faces[keep], tol=1e-6 * h)
    return orient_faces(mesh)


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
        raise _no_surface(f"the UDF never drops below threshold / 2 = {threshold / 2:.4g}", sparse, bounds)
    near = vals.min(1) <= floor + h
    if not near.any():
        raise _no_surface("no grid cell lies within a voxel of the UDF's zero level", sparse, bounds)
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
        raise _no_surface(f"only {len(points)} points reached the zero level set", sparse, bounds)
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
        raise _no_surface("the surface samples are scattered specks (< 100 points each)", sparse, bounds)
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
        raise _no_surface(f"no Poisson face has UDF <= threshold {threshold:.4g}", sparse, bounds)
    return _clean(vertices, faces[keep], tol=1e-6 * h)


def _mc(sparse: SparseGrid, level: float, bounds: Bounds) -> trimesh.Trimesh:
    cells, vals = cell_corners(sparse)
    vals = vals - level
    crossing = (vals.min(1) < 0) & (vals.max(1) >= 0)
    if not crossing.any():
        raise _no_surface(f"the field does not cross level {level}", sparse, bounds)
    # for an SDF (negative inside) the faces come out facing the outside
    vertices, faces, _ = marching_cubes(sparse.grid, cells[crossing], vals[crossing])
    return _clean(vertices, faces, tol=1e-6 * sparse.grid.voxel)


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
    a perimeter up to ``fill_holes`` are closed (pinholes where the field is off; default: the larger of
    3% of the longest side of ``bounds`` and 8 voxels; 0 keeps every hole). The mesh is
    in the coordinates of the queried points. Raises ValueError when the field has no surface in bounds.
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
        raise ValueError(
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
    if method != "mc":
        if fill_holes is None:
            fill_holes = max(0.03 * float(np.max(np.subtract(bounds[1], bounds[0]))), 8 * grid.voxel)
        mesh = fill_small_holes(mesh, fill_holes)
    mesh = drop_small_components(mesh, min_component_faces, min_component_fraction)
    if len(mesh.faces) == 0:
        raise ValueError("no surface left after dropping small components: every piece was below "
                         f"max({min_component_faces} faces, {min_component_fraction:.0%} of faces)")
    mesh.metadata["meshing"] = {
        "method": method, "resolution": resolution, "voxel": grid.voxel, "threshold": threshold,
        "threshold_source": source, "level": level if method == "mc" else None, "fill_holes": fill_holes,
        "bounds": [list(map(float, bounds[0])), list(map(float, bounds[1]))],
    }
    log.info("mesh: %d vertices, %d faces", len(mesh.vertices), len(mesh.faces))
    progress(1.0, f"mesh: {len(mesh.faces)} faces")
    return mesh


# --------------------------------------------------------------------------- colour and the whole run


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
            x = _as_points(points[start : start + chunk], device)
            n = _as_points(normals[start : start + chunk], device)
            rgb[start : start + len(x)] = color_fn(x, n, -n).reshape(-1, 3).float().cpu().numpy()
            progress(min(start + chunk, len(points)) / max(len(points), 1), "colouring vertices")
    rgba = np.concatenate([np.clip(rgb, 0, 1) * 255, np.full((len(rgb), 1), 255.0)], 1)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba.round().astype(np.uint8))
    return mesh


def _above(mesh: trimesh.Trimesh, floor_y: float) -> trimesh.Trimesh:
    """The faces wholly above height ``floor_y``."""
    keep = mesh.vertices[mesh.faces][:, :, 1].min(axis=1) > floor_y
    if keep.all():
        return mesh
    info = mesh.metadata.get("meshing", {})
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    mesh.metadata["meshing"] = {**info, "floor_y": floor_y, "faces_below_floor": int((~keep).sum())}
    return mesh


def mesh_run(
    run_dir: str | Path,
    out_path: str | Path,
    *,
    method: Method | None = None,
    resolution: int = 256,
    threshold: float | None = None,
    min_component_faces: int = 32,
    min_component_fraction: float = 0.01,
    views: str | Path | None = None,
    min_seen_fraction: float = 0.15,
    device: str = "cpu",
    progress: ProgressFn = null_progress,
) -> trimesh.Trimesh:
    """Mesh a trained run: UDF in the unit sphere's bounding box, vertex colours, exported to ``out_path``.

    The suffix of ``out_path`` picks the format (.glb, .ply, .obj); raises ValueError for others before
    the long work starts, for a method that does not fit the field (mc for NeuS-SDF runs, meshudf or spsr
    for unsigned ones), and when the field has no surface yet. Options as :func:`extract_mesh`.
    ``views``: the run's dataset folder; faces that fewer than ``min_seen_fraction`` of its cameras see
    are dropped (:func:`cull_unseen`; 0.15 is 8 of 48 views, where culling a tube's and a pants' inner
    sheets stopped gaining).
    """
    from neudf_core.export import SUFFIXES, export_mesh
    from neudf_core.trainer import load_model

    if Path(out_path).suffix.lower() not in SUFFIXES:
        raise ValueError(f"unknown mesh format {Path(out_path).suffix!r}: use one of {', '.join(SUFFIXES)}")
    flush_denormals()
    model = load_model(run_dir, device)
    model.eval()
    signed = bool(getattr(model, "signed", False))
    method = method or ("mc" if signed else "meshudf")
    cameras = load_cameras(views) if views is not None else None  # bad folders fail before the long work
    if signed and method != "mc":
        raise ValueError(f"{run_dir} learned a signed field (the NeuS-SDF baseline): mesh it with method mc")
    if not signed and method == "mc":
        raise ValueError(f"{run_dir} learned an unsigned field: mc needs a sign, use meshudf or spsr")

    def grad_fn(x: torch.Tensor) -> torch.Tensor:
        return model.udf_and_grad(x)[1]

    mesh = extract_mesh(
        model.udf, method=method, resolution=resolution, bounds=UNIT_BOUNDS, threshold=threshold,
        grad_fn=grad_fn, min_component_faces=min_component_faces, min_component_fraction=min_component_fraction,
        device=device, progress=sub_progress(progress, 0.0, 0.85),
    )
    floor_y = model.cfg.data.floor_y
    if floor_y is not None:  # training rendered nothing of the object below the floor: what is there is a guess
        mesh = _above(mesh, floor_y)
    if cameras is not None:
        progress(0.85, "dropping what no camera sees")
        info = mesh.metadata["meshing"]
        faces_before = len(mesh.faces)
        mesh = cull_unseen(mesh, cameras, min_seen_fraction, tol=2.0 * info["voxel"])
        mesh = drop_small_components(mesh, min_component_faces, min_component_fraction)
        if len(mesh.faces) == 0:
            raise ValueError(f"no face is seen by {min_seen_fraction:.0%} of the {len(cameras)} cameras in {views}")
        mesh.metadata["meshing"] = {**info, "views": str(views), "cameras": len(cameras),
                                    "min_seen_fraction": min_seen_fraction,
                                    "faces_unseen": faces_before - len(mesh.faces)}
    color_vertices(mesh, model.color, device=device, progress=sub_progress(progress, 0.9, 0.98))
    export_mesh(mesh, out_path)
    progress(1.0, f"wrote {out_path}")
    return mesh
