"""Mesh clean-up: merge and orient, close pinholes, drop specks, and drop what no camera sees."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

from neudf_core.dataset import Cameras
from neudf_core.metrics import split_pinched_vertices

log = logging.getLogger(__name__)


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, tol: float) -> trimesh.Trimesh:
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


def fill_small_holes(mesh: trimesh.Trimesh, max_perimeter: float, *, field: Callable[[np.ndarray], np.ndarray] |
                     None = None, field_perimeter: float = 0.0, field_level: float = 0.0,
                     slit_perimeter: float = 0.0, slit_width: float = 0.0) -> trimesh.Trimesh:
    """Close boundary loops no longer than ``max_perimeter`` with a fan around their centroid; also slits:
    loops up to ``slit_perimeter`` whose width, twice their vector area over their perimeter (a round
    hole's radius, a slit's width or less), is at most ``slit_width``; with a ``field`` (the UDF, points to
    values), also the loops up to ``field_perimeter`` that the field covers and the mesh does not: the
    field's median over points across the fan at most ``field_level``, and no vertex of the mesh nearer the
    loop's centroid than half the distance to the loop's nearest vertex.

    Where a learned UDF is off by more than a voxel, neighbouring cells can disagree on a pseudo-sign
    and leave a pinhole of a few voxels (more of them at finer resolutions); a real opening of a
    garment is far longer. Larger holes where the field still says "surface" are the same flaw; an
    opening has no surface across it, so the field there is about its radius. (The outer edge of a flat
    sheet has the field across its fan too, and the sheet itself: the mesh test keeps it.) A tear where
    the field did not close the cloth (a pants' crotch few cameras see) is long but narrow: its two edges
    lie close together, so its vector area is small; a garment's opening is a wide ring. Loops are
    traced per fan of faces (a pinhole touching another at a vertex is two loops). Expects consistent
    winding: each boundary edge a -> b of a face gets the triangle (b, a, centre).
    """
    reach = max(max_perimeter, slit_perimeter if slit_width > 0 else 0.0, field_perimeter if field is not None else 0.0)
    if reach <= 0 or len(mesh.faces) == 0:
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
    simple = n_edges == n_ids
    sums = np.zeros((len(n_edges), 3))
    np.add.at(sums, labels, mesh.vertices[vertex_of[ids]])
    centres_all = sums / np.maximum(n_ids, 1)[:, None]
    by_size = (perimeter <= max_perimeter) & simple
    small = by_size.copy()
    if slit_width > 0:
        area = np.cross(mesh.vertices[ends[:, 0]], mesh.vertices[ends[:, 1]]) / 2  # per directed edge
        vector_area = np.stack([np.bincount(edge_label, weights=area[:, k]) for k in range(3)], 1)
        width = 2 * np.linalg.norm(vector_area, axis=1) / np.maximum(perimeter, 1e-12)
        small |= simple & (perimeter <= slit_perimeter) & (width <= slit_width)
    if field is not None:
        candidates = np.nonzero(simple & ~small & (perimeter <= field_perimeter))[0]
        small[candidates[_covered(field, np.asarray(mesh.vertices), vertex_of[ids], labels, centres_all,
                                  candidates, field_level)]] = True
    if not small.any():
        return mesh
    holes = np.nonzero(small)[0]
    centre_of = np.full(len(n_edges), -1)
    centre_of[holes] = len(mesh.vertices) + np.arange(len(holes))
    centres = centres_all[holes]
    fill = small[edge_label]
    new_faces = np.stack([ends[fill, 1], ends[fill, 0], centre_of[edge_label[fill]]], -1)
    log.info("filled %d holes (%d up to perimeter %.3g, the rest slits or covered by the field)", len(holes),
             int(by_size.sum()), max_perimeter)
    return trimesh.Trimesh(np.vstack([mesh.vertices, centres]), np.vstack([faces, new_faces]), process=False)


# Where across a hole's fan the field is read: the centre and these fractions of the way to each rim vertex.
FAN_FRACTIONS = (0.25, 0.5, 0.75)


def _covered(field: Callable[[np.ndarray], np.ndarray], vertices: np.ndarray, rim_ids: np.ndarray,
             labels: np.ndarray, centres: np.ndarray, loops: np.ndarray, level: float) -> np.ndarray:
    """Which of ``loops`` (rim vertices ``rim_ids`` by label) the field covers and the mesh does not."""
    if len(loops) == 0:
        return np.zeros(0, bool)
    points, owner, open_ = [], [], []
    for i, loop in enumerate(loops):
        centre, ring = centres[loop], vertices[rim_ids[labels == loop]]
        to_rim = float(np.min(np.sum((ring - centre) ** 2, axis=1)))
        open_.append(float(np.min(np.sum((vertices - centre) ** 2, axis=1))) >= 0.25 * to_rim)
        across = [centre[None]] + [centre + f * (ring - centre) for f in FAN_FRACTIONS]
        points.append(np.concatenate(across))
        owner.append(np.full(sum(len(a) for a in across), i))
    values, owner = field(np.concatenate(points)), np.concatenate(owner)
    return np.array([open_[i] and np.median(values[owner == i]) <= level for i in range(len(loops))])


def _piece_labels(faces: np.ndarray) -> np.ndarray:
    """The connected piece (through shared edges) of each face."""
    n = len(faces)
    pairs, _ = _face_pairs(faces)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def drop_small_components(
    mesh: trimesh.Trimesh, min_faces: int, min_fraction: float
) -> trimesh.Trimesh:
    """Keep connected pieces (through shared edges) with at least max(min_faces, min_fraction x F) faces."""
    n = len(mesh.faces)
    if n == 0:
        return mesh
    labels = _piece_labels(mesh.faces)
    sizes = np.bincount(labels)
    keep = sizes[labels] >= max(min_faces, min_fraction * n)
    dropped = int(np.sum(sizes < max(min_faces, min_fraction * n)))
    if dropped:
        log.info("dropped %d small components (%d faces)", dropped, int(n - keep.sum()))
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    out.remove_unreferenced_vertices()
    return out


def keep_above(mesh: trimesh.Trimesh, floor_y: float) -> trimesh.Trimesh:
    """The faces wholly above height ``floor_y``."""
    keep = mesh.vertices[mesh.faces][:, :, 1].min(axis=1) > floor_y
    if keep.all():
        return mesh
    info = mesh.metadata.get("meshing", {})
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    mesh.metadata["meshing"] = {**info, "floor_y": floor_y, "faces_below_floor": int((~keep).sum())}
    return mesh


def keep_in_sphere(mesh: trimesh.Trimesh, rim: float) -> trimesh.Trimesh:
    """Cut the faces that reach outside the unit sphere and drop the pieces, the largest excepted, that lie
    wholly beyond radius ``rim``.

    Training renders the object only inside the unit sphere (the surroundings model owns the rest of each
    ray), so surface outside it is unseen guesswork. The capture scales the object to well inside the
    sphere; a separate piece out at its rim is the room caught at the edge of the rendered volume (a field
    that starts as a sphere shell can leave one where clutter stands)."""
    if len(mesh.faces) == 0:
        return mesh
    info = mesh.metadata.get("meshing", {})
    radius = np.linalg.norm(mesh.vertices, axis=1)
    inside = radius[mesh.faces].max(axis=1) <= 1.0
    labels = _piece_labels(mesh.faces)
    nearest = np.full(labels.max() + 1, np.inf)
    np.minimum.at(nearest, labels, radius[mesh.faces].min(axis=1))
    at_rim = nearest > rim
    at_rim[np.bincount(labels).argmax()] = False
    keep = inside & ~at_rim[labels]
    if keep.all():
        return mesh
    log.info("dropped %d faces outside the unit sphere or at its rim", int((~keep).sum()))
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    mesh.metadata["meshing"] = {**info, "faces_outside": int((~keep).sum())}
    return mesh


def drop_floor_pieces(mesh: trimesh.Trimesh, floor_y: float, band: float, touch: float) -> trimesh.Trimesh:
    """Drop pieces that rest on the floor cut (lowest point within ``touch`` of ``floor_y``) and stay low
    (highest point within ``band`` of it), the largest piece excepted.

    Training leaves what lies under the cut to the surroundings model, which is sampled only beyond the
    unit sphere; the floor inside the sphere and the object's shadow on it can then be drawn by a thin
    sheet just above the cut. An object standing on the floor rises far above the band, and the largest
    piece is kept whatever its height (a flat object lying on the floor).
    """
    if len(mesh.faces) == 0:
        return mesh
    labels = _piece_labels(mesh.faces)
    face_y = mesh.vertices[mesh.faces][:, :, 1]
    n_pieces = labels.max() + 1
    low = np.full(n_pieces, np.inf)
    high = np.full(n_pieces, -np.inf)
    np.minimum.at(low, labels, face_y.min(axis=1))
    np.maximum.at(high, labels, face_y.max(axis=1))
    on_floor = (low <= floor_y + touch) & (high <= floor_y + band)
    on_floor[np.bincount(labels).argmax()] = False
    if not on_floor.any():
        return mesh
    info = mesh.metadata.get("meshing", {})
    keep = ~on_floor[labels]
    log.info("dropped %d pieces lying on the floor (%d faces)", int(on_floor.sum()), int((~keep).sum()))
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    mesh.metadata["meshing"] = {**info, "faces_on_floor": int((~keep).sum())}
    return mesh


def trim_floor_skirt(
    mesh: trimesh.Trimesh, floor_y: float, band: float, above: float, margin: float
) -> trimesh.Trimesh:
    """Drop the faces lying within ``band`` above the floor cut outside the object's own footprint.

    An object standing on the floor casts a shadow there, and training may draw it as a skirt of surface
    fused to the object's foot (one piece, so :func:`drop_floor_pieces` keeps it). The footprint is the
    convex hull, seen from above, of the vertices from ``band`` to ``band + above`` over the cut, grown by
    ``margin``: what the object is just above the floor. Nothing is trimmed when no vertex lies in that
    slab (an object lying flat on the floor, or one hanging above it), or when that would drop half the
    faces or more. A foot that flares out within ``band`` of the floor is trimmed as a shadow would be.
    """
    from scipy.spatial import ConvexHull, QhullError

    if len(mesh.faces) == 0:
        return mesh
    face_y = mesh.vertices[mesh.faces][:, :, 1]
    low = face_y.max(axis=1) < floor_y + band
    height = mesh.vertices[:, 1]
    slab = mesh.vertices[(height >= floor_y + band) & (height < floor_y + band + above)]
    if not low.any() or len(slab) < 3:
        return mesh
    try:
        hull = ConvexHull(slab[:, [0, 2]])
    except QhullError:  # the slab's vertices lie on a line seen from above
        return mesh
    xz = mesh.triangles_center[low][:, [0, 2]]
    outside = (xz @ hull.equations[:, :2].T + hull.equations[:, 2]).max(axis=1) > margin
    if not outside.any() or outside.sum() > len(mesh.faces) / 2:  # a skirt is a fringe, not most of the object
        return mesh
    keep = np.ones(len(mesh.faces), bool)
    keep[np.nonzero(low)[0][outside]] = False
    info = mesh.metadata.get("meshing", {})
    log.info("trimmed %d faces spreading on the floor beyond the object's footprint", int((~keep).sum()))
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    mesh.metadata["meshing"] = {**info, "faces_floor_skirt": int((~keep).sum())}
    return mesh


# --------------------------------------------------------------------------- visibility


class NothingSeenError(ValueError):
    """Culling by the cameras left no face: too few of them see what the field made."""


def sightings(vertices: np.ndarray, faces: np.ndarray, cameras: Cameras, tol: float
              ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Per camera: which vertices it sees (in front of it, inside its image, and the ray from its centre
    meets no face more than ``tol`` before them) and where they land in its image ((N, 2) pixels)."""
    import open3d as o3d  # heavy import, only visibility needs it

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    for K, c2w in zip(cameras.intrinsics, cameras.c2w):
        centre = c2w[:3, 3]
        pixels, z = project(vertices, K, c2w)
        u, v = pixels[:, 0], pixels[:, 1]
        in_view = (z > 1e-9) & (u >= 0) & (u <= cameras.width) & (v >= 0) & (v <= cameras.height)
        offset = vertices - centre
        dist = np.linalg.norm(offset, axis=1)
        rays = np.concatenate([np.broadcast_to(centre, offset.shape), offset / np.maximum(dist, 1e-12)[:, None]], 1)
        hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        yield in_view & (hit >= dist - tol), pixels


def project(points: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where world ``points`` (N, 3) land in a camera's image ((N, 2) pixels) and their depth along its axis."""
    in_camera = (points - c2w[:3, 3]) @ c2w[:3, :3]  # R^T (x - c) for each row
    z = in_camera[:, 2]
    pixels = in_camera @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return pixels[:, :2] / z[:, None], z


def views_seeing(vertices: np.ndarray, faces: np.ndarray, cameras: Cameras, tol: float) -> np.ndarray:
    """How many cameras see each vertex (see :func:`sightings`)."""
    counts = np.zeros(len(vertices), np.int64)
    for seen, _ in sightings(vertices, faces, cameras, tol):
        counts += seen
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
