# Our own table, not skimage's or open3d's: those take one sign per grid point, MeshUDF's pseudo-signs differ per cube.
"""Marching cubes, vectorised over cells, with per-cell signs.

The table is generated from first principles (walk the iso-contour around the cube's faces,
fan-triangulate each loop), and the face ambiguities are resolved per cell with the asymptotic decider,
which is invariant to flipping all signs: pseudo-signs need that, since each cell picks its own reference.
"""

from __future__ import annotations

import functools

import numpy as np

from neudf_core.meshing.grid import CORNERS, EDGES, Grid


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
