"""The sampling grid and the field on it: regular voxels, chunked evaluation of values and gradients,
and the sparse grid that evaluates only the blocks a surface may pass through.

A coarse pass over blocks of 8^3 cells discards empty space (a distance field cannot drop by more than
the distance travelled, see CULL_SAFETY); only the kept blocks are evaluated at full resolution, in
chunks, so memory stays bounded at resolution 512.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from neudf_core.progress import ProgressFn, null_progress, sub_progress

log = logging.getLogger(__name__)

FieldFn = Callable[[torch.Tensor], torch.Tensor]
GradFn = Callable[[torch.Tensor], torch.Tensor]
Bounds = tuple[Sequence[float], Sequence[float]]

UNIT_BOUNDS: Bounds = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
BLOCK = 8  # cells per block side in the coarse empty-space pass
# A learned UDF is only roughly 1-Lipschitz (the eikonal loss is soft): the coarse pass keeps a block
# when its centre value is below CULL_SAFETY x the block's half diagonal (+ 2 voxels).
CULL_SAFETY = 2.0


class NoSurfaceError(ValueError):
    """The field has no surface to mesh in the bounds (untrained, or the threshold is too tight)."""


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


def as_points(points: np.ndarray, device: torch.device | str) -> torch.Tensor:
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
            x = as_points(points[start : start + chunk], device)
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
        x = as_points(points[start : start + chunk], device)
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


def no_surface(what: str, sparse: SparseGrid, bounds: Bounds) -> NoSurfaceError:
    """The error for a field without a surface in ``bounds``, with the lowest value the grid saw."""
    lowest = float(sparse.values.min()) if sparse.values.size else float("nan")
    return NoSurfaceError(
        f"no surface in bounds {tuple(map(tuple, bounds))}: {what}"
        + (f" (lowest field value on the grid {lowest:.4g})" if sparse.values.size else "")
    )


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
