"""Mesh quality against a ground truth, in the paper's convention (`neudf eval`).

Both meshes are moved by the transform that puts GT in the unit sphere (centre = midpoint of GT's
axis-aligned bounding box, scale = 1 / the largest distance of a GT vertex from that centre). Each mesh is
sampled densely (area-weighted, ``n_samples`` points) and every sample's distance to the *other mesh's
surface* is exact point-to-triangle distance (open3d's RaycastingScene, a BVH), not the distance to the
other mesh's samples, which would add the sampling spacing to every figure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

DEFAULT_SAMPLES = 100_000
DEFAULT_FSCORE_THRESHOLD = 0.01  # in GT's unit sphere (radius 1)


def _merged_faces(mesh: trimesh.Trimesh) -> np.ndarray:
    """Faces re-indexed so that vertices at the same position are one (OBJ/GLB split them at UV seams)."""
    vertices = np.asarray(mesh.vertices, np.float64)
    if len(vertices) == 0:
        return np.zeros((0, 3), np.int64)
    tol = 1e-7 * max(float(np.ptp(vertices, axis=0).max()), 1e-12)
    _, inverse = np.unique(np.round(vertices / tol).astype(np.int64), axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[np.asarray(mesh.faces, np.int64)]
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return faces[ok]


def split_pinched_vertices(faces: np.ndarray) -> np.ndarray:
    """Give each fan of faces around a vertex its own vertex id (a "pinched" vertex joins several).

    Corners of faces ("wedges") at the same vertex are joined when their faces share an edge through
    that vertex; each group of joined wedges becomes one vertex. A boundary that touches itself at one
    vertex then reads as the one opening it is, as a half-edge structure would trace it.
    """
    n_faces = len(faces)
    wedge_a = np.arange(3 * n_faces)
    wedge_b = (wedge_a // 3) * 3 + (wedge_a % 3 + 1) % 3  # edge k of face f runs from corner k to k + 1
    a, b = faces.reshape(-1), faces.reshape(-1)[wedge_b]
    _, group = np.unique(np.sort(np.stack([a, b], -1), axis=1), axis=0, return_inverse=True)
    group = group.reshape(-1)
    order = np.argsort(group, kind="stable")
    first = np.empty(group.max() + 1, np.int64)
    first[group[order[::-1]]] = order[::-1]  # the first half-edge of each edge group
    ref = first[group]
    other = ref != wedge_a
    i, r = wedge_a[other], ref[other]
    same = a[i] == a[r]  # same direction (inconsistent winding) or opposite
    join_a = np.where(same, wedge_a[r], wedge_b[r])  # the wedge of r at vertex a[i]
    join_b = np.where(same, wedge_b[r], wedge_a[r])  # the wedge of r at vertex b[i]
    rows = np.concatenate([wedge_a[i], wedge_b[i]])
    cols = np.concatenate([join_a, join_b])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_faces, 3 * n_faces))
    _, labels = connected_components(graph, directed=False)
    return labels.reshape(-1, 3)


def boundary_loops(mesh: trimesh.Trimesh) -> int:
    """Closed loops of boundary edges (edges used by exactly one face); 0 for a watertight mesh.

    Vertices are merged by position first (OBJ and GLB files split them at UV seams), then pinched
    vertices are split per fan of faces, so a loop that touches itself or another at one vertex (common
    on the jagged rim of a mesh cut out of a distance field) is traced as a half-edge structure would;
    two faces meeting only at a vertex still have two loops. Counted as the cycle rank of the
    boundary-edge graph (edges - vertices + pieces).
    """
    faces = _merged_faces(mesh)
    if len(faces) == 0:
        return 0
    faces = split_pinched_vertices(faces)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    if len(boundary) == 0:
        return 0
    vertices, local = np.unique(boundary, return_inverse=True)
    local = local.reshape(-1, 2)
    n = len(vertices)
    graph = coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(n, n))
    pieces, _ = connected_components(graph, directed=False)
    return int(len(boundary) - n + pieces)


def unit_sphere_normalisation(gt: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """(centre, scale) with x -> (x - centre) * scale putting GT in the unit sphere (the contract's rule)."""
    vertices = np.asarray(gt.vertices, np.float64)
    centre = (vertices.min(0) + vertices.max(0)) / 2
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    if not radius > 0:
        raise ValueError("the ground-truth mesh has no extent (all vertices coincide)")
    return centre, 1.0 / radius


def _check(mesh: trimesh.Trimesh, name: str) -> None:
    if len(mesh.faces) == 0 or not float(mesh.area) > 0:
        raise ValueError(f"the {name} mesh has no triangles with area")


def _sample(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    points, face_index = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points), np.asarray(mesh.face_normals)[face_index]


def closest_on_surface(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance from each point to ``mesh``'s surface, and the normal of the nearest triangle."""
    import open3d as o3d  # heavy import, only needed here

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    query = o3d.core.Tensor(points.astype(np.float32))
    result = scene.compute_closest_points(query)
    distance = np.linalg.norm(result["points"].numpy().astype(np.float64) - points, axis=1)
    return distance, result["primitive_normals"].numpy().astype(np.float64)


def directed_distances(
    pred: trimesh.Trimesh, gt: trimesh.Trimesh, *, n_samples: int = DEFAULT_SAMPLES, seed: int = 0,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """Samples of each mesh and their distances to the other, in GT's unit sphere: (pred side, GT side, scale).

    Each side holds ``point`` (n, 3), ``normal`` (the sample's triangle), ``distance`` (to the other
    mesh's surface) and ``normal_there`` (of the nearest triangle on the other mesh). The pred side's
    distances are accuracy (how far the prediction strays from GT), the GT side's completeness.
    """
    _check(pred, "predicted")
    _check(gt, "ground-truth")
    centre, scale = unit_sphere_normalisation(gt)
    pred_n, gt_n = pred.copy(), gt.copy()
    for mesh in (pred_n, gt_n):
        mesh.apply_translation(-centre)
        mesh.apply_scale(scale)
    sides = []
    for mesh, other, sample_seed in ((pred_n, gt_n, seed), (gt_n, pred_n, seed + 1)):
        points, normals = _sample(mesh, n_samples, sample_seed)
        distance, normal_there = closest_on_surface(other, points)
        sides.append({"point": points, "normal": normals, "distance": distance, "normal_there": normal_there})
    return sides[0], sides[1], scale


def evaluate(
    pred: trimesh.Trimesh,
    gt: trimesh.Trimesh,
    *,
    n_samples: int = DEFAULT_SAMPLES,
    fscore_threshold: float = DEFAULT_FSCORE_THRESHOLD,
    seed: int = 0,
) -> dict:
    """Chamfer, F-score, normal consistency and boundary loops of ``pred`` against ``gt``.

    Keys: ``chamfer`` (mean of the two directed mean distances, GT unit sphere),
    ``fscore`` (at ``fscore_threshold``, same units), ``normal_consistency`` (mean |cos| between a
    sample's normal and the nearest triangle's on the other mesh, both ways; sign-agnostic since an open
    surface has no inside), ``boundary_loops_pred``, ``boundary_loops_gt``; plus the directed terms,
    precision, recall, the threshold, the sample count and the scale applied.
    """
    pred_side, gt_side, scale = directed_distances(pred, gt, n_samples=n_samples, seed=seed)
    d_pred, pred_normals, n_at_gt = pred_side["distance"], pred_side["normal"], pred_side["normal_there"]
    d_gt, gt_normals, n_at_pred = gt_side["distance"], gt_side["normal"], gt_side["normal_there"]
    precision = float(np.mean(d_pred < fscore_threshold))
    recall = float(np.mean(d_gt < fscore_threshold))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    cos_pred = np.abs(np.sum(pred_normals * n_at_gt, axis=1))
    cos_gt = np.abs(np.sum(gt_normals * n_at_pred, axis=1))
    return {
        "chamfer": float((d_pred.mean() + d_gt.mean()) / 2),
        "fscore": float(fscore),
        "normal_consistency": float((cos_pred.mean() + cos_gt.mean()) / 2),
        "boundary_loops_pred": boundary_loops(pred),
        "boundary_loops_gt": boundary_loops(gt),
        "chamfer_pred_to_gt": float(d_pred.mean()),
        "chamfer_gt_to_pred": float(d_gt.mean()),
        "precision": precision,
        "recall": recall,
        "fscore_threshold": float(fscore_threshold),
        "n_samples": int(n_samples),
        "scale": float(scale),
    }


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """A triangle mesh from any format trimesh reads (scenes are flattened); clear errors otherwise."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds for bad files; the caller needs one message
        raise ValueError(f"cannot read mesh {path}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path} holds no triangles")
    return mesh


def evaluate_files(
    pred_path: str | Path,
    gt_path: str | Path,
    *,
    n_samples: int = DEFAULT_SAMPLES,
    fscore_threshold: float = DEFAULT_FSCORE_THRESHOLD,
) -> dict:
    """:func:`evaluate` on two mesh files (.glb, .ply, .obj, ...)."""
    pred = load_mesh(pred_path)
    gt = load_mesh(gt_path)
    return evaluate(pred, gt, n_samples=n_samples, fscore_threshold=fscore_threshold)
