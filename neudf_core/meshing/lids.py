"""Lids: surface the cameras see but disagree about the colour of, cut out of the mesh.

A learned field can close an opening (a neck, a sleeve's end, a bowl's rim) with a thin lid painted like
what lies behind it: through the opening each camera sees another part of the inside, and at the
resolution training sees, a lid coloured with their blur explains every frame about as well. A real
surface looks the same from every camera that sees it (its texture, up to shading); a lid does not. So each
vertex's colour is read in every frame whose camera sees it, and where those colours scatter far from their
median over a patch of the mesh, the patch is a lid and is cut out: the opening shows again.

Misplaced cloth scatters too: where the field carves a print into a crease a little off the true cloth,
the frames disagree at the mesh. They agree a step in front of or behind it, at the cloth; through a lid
they agree only on the inside, an opening's depth away. So each vertex is also asked at points just off
it along its normal, and the least scatter counts.

Thin streaks of scatter (a texture's edge under a pixel of pose or mesh error) are not lids: the patches
are opened morphologically (shrunk and grown back by a few face rings) before they count, and small ones
are kept, as are patches that reach the mesh's boundary (see :func:`lid_faces`).
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components

from neudf_core.dataset import Cameras, cameras_sphere_px
from neudf_core.meshing.cleanup import project, sightings

log = logging.getLogger(__name__)

# The unit sphere's diameter in the frames colours are read from: coarse enough that a pixel or two of pose
# or mesh error reads the same texture, fine enough that a neck's inside is many pixels.
SAMPLE_SPHERE_PX = 240
# Scatter of a vertex: the median over its cameras of the L1 distance (RGB in 0..1) of their colour from
# the median colour. Cloth on video reads 0.01-0.05 (median 0.03); lids over a polo's neck and sleeves 0.2-0.5.
SPREAD_LID = 0.2
# A lid's patch grows from the faces above SPREAD_LID into neighbours above this (its rim, seen at an angle).
SPREAD_RIM = 0.1
MIN_VIEWS = 3  # fewer cameras than this: no verdict
# Where the field places real cloth a little off (a print carved into creases), the frames disagree at the
# mesh but agree at a point just in front of or behind it; through a lid they agree only on the inside, an
# opening's depth away. So a vertex's scatter is the least over points within this distance along its normal
# (unit sphere), tried at DEPTH_STEPS depths each way.
NEAR_DEPTH = 0.04
DEPTH_STEPS = 4
OPEN_WIDTH = 0.016  # streaks narrower than about twice this (unit sphere) are not lids
MIN_LID_AREA = 0.002  # smallest lid (unit sphere units squared; a sleeve's end is 0.01-0.03)


def read_frames(paths: Sequence[Path], scale: float) -> list[np.ndarray]:
    """The frames as (H, W, 3) float32 in 0..1, scaled down by ``scale`` (<= 1)."""
    out = []
    for path in paths:
        with Image.open(path) as image:
            image = image.convert("RGB")
            if scale < 1.0:
                size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
                image = image.resize(size, Image.BILINEAR)
            out.append(np.asarray(image, np.float32) / 255.0)
    return out


def colour_spread(mesh: trimesh.Trimesh, cameras: Cameras, frames: Sequence[Path], tol: float,
                  near: float = NEAR_DEPTH, sweep: Callable[[np.ndarray], np.ndarray] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, how far the frames that see it scatter about its colour (see :data:`SPREAD_LID`): at the
    vertex, and the least at points near it (below); NaN where fewer than :data:`MIN_VIEWS` cameras see
    it. ``frames``: one image per camera, full size.

    Each side of the surface (by the vertex normal) has its own median colour: cloth may be printed outside
    and plain inside, and a camera looking up through a hem sees the inside of the same sheet. The vertices
    ``sweep(spread)`` picks (a boolean mask; default: scatter above :data:`SPREAD_RIM`) are asked again at
    points up to ``near`` in front of and behind them along their normal, and the least scatter counts (see
    :data:`NEAR_DEPTH`).
    """
    if len(frames) != len(cameras):
        raise ValueError(f"{len(frames)} frames for {len(cameras)} cameras")
    vertices, normals = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    scale = min(1.0, SAMPLE_SPHERE_PX / cameras_sphere_px(cameras.intrinsics, cameras.c2w))
    images = read_frames(frames, scale)
    n = len(vertices)
    colours = np.zeros((len(cameras), n, 3), np.uint8)  # 0..255 keeps 200 views x 100k vertices small
    side = np.zeros((len(cameras), n), np.int8)  # +1 / -1: the camera is in front of / behind the vertex; 0: unseen
    for i, (seen, pixels) in enumerate(sightings(vertices, np.asarray(mesh.faces), cameras, tol)):
        colours[i, seen] = _colour_at(images[i], pixels[seen], cameras)
        facing = np.einsum("ij,ij->i", cameras.c2w[i, :3, 3] - vertices[seen], normals[seen]) >= 0
        side[i, seen] = np.where(facing, 1, -1)
    spread = _scatter(colours, side)
    spread[(side != 0).sum(axis=0) < MIN_VIEWS] = np.nan
    at_vertex = spread.copy()
    with np.errstate(invalid="ignore"):  # NaN compares False: no verdict stays none
        ask = np.nonzero(sweep(spread) if sweep is not None else spread > SPREAD_RIM)[0]
    if near <= 0 or len(ask) == 0:
        return at_vertex, spread
    shifted = np.zeros((len(cameras), len(ask), 3), np.uint8)
    for depth in np.linspace(-near, near, 2 * DEPTH_STEPS + 1):
        if depth == 0.0:
            continue
        points = vertices[ask] + depth * normals[ask]
        for i in range(len(cameras)):
            seen = side[i, ask] != 0
            pixels, _ = project(points[seen], cameras.intrinsics[i], cameras.c2w[i])
            shifted[i, seen] = _colour_at(images[i], pixels, cameras)
        spread[ask] = np.fmin(spread[ask], _scatter(shifted, side[:, ask]))
    return at_vertex, spread


def _colour_at(image: np.ndarray, pixels: np.ndarray, cameras: Cameras) -> np.ndarray:
    """The colours (0..255) of a scaled frame at full-size ``pixels`` (N, 2), the nearest pixel, clipped."""
    h, w = image.shape[:2]
    u = np.clip(np.nan_to_num(pixels[:, 0] * w / cameras.width).astype(np.int64), 0, w - 1)
    v = np.clip(np.nan_to_num(pixels[:, 1] * h / cameras.height).astype(np.int64), 0, h - 1)
    return np.round(image[v, u] * 255.0).astype(np.uint8)


def _scatter(colours: np.ndarray, side: np.ndarray) -> np.ndarray:
    """Per vertex, the median over the cameras that see it of the L1 distance of their colour ((C, N, 3),
    0..255) from the median colour of the cameras on the same side (``side`` (C, N): +1, -1, 0 unseen)."""
    n = colours.shape[1]
    spread = np.full(n, np.nan)
    chunk = 20000  # float copies of that many vertices at a time
    for start in range(0, n, chunk):
        part = colours[:, start:start + chunk].astype(np.float32) / 255.0
        sides = side[:, start:start + chunk, None]
        deviation = np.full(part.shape[:2], np.nan, np.float32)
        with warnings.catch_warnings():  # a side no camera sees is all NaN: no median there, as meant
            warnings.simplefilter("ignore", RuntimeWarning)
            for s in (1, -1):
                own = np.where(sides == s, part, np.nan)
                dev = np.abs(own - np.nanmedian(own, axis=0)).sum(axis=2)
                deviation = np.where(sides[..., 0] == s, dev, deviation)
            spread[start:start + chunk] = np.nanmedian(deviation, axis=0)
    return spread


def _face_graph(mesh: trimesh.Trimesh) -> csr_matrix:
    pairs = mesh.face_adjacency
    n = len(mesh.faces)
    rows, cols = np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]]
    return coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()


def _grow(graph: csr_matrix, mask: np.ndarray, rings: int) -> np.ndarray:
    for _ in range(rings):
        mask = mask | (graph @ mask.astype(np.float64) > 0)
    return mask


def lid_faces(mesh: trimesh.Trimesh, spread: np.ndarray, rings: int, lid: float = SPREAD_LID,
              rim: float = SPREAD_RIM, min_area: float = MIN_LID_AREA, rim_spread: np.ndarray | None = None
              ) -> np.ndarray:
    """Which faces are lids: faces whose vertices' mean ``spread`` exceeds ``lid``, less streaks narrower than
    2 ``rings`` face rings (shrunk away and not grown back), grown into neighbours whose ``rim_spread``
    (default ``spread``) exceeds ``rim``, in connected patches of at least ``min_area`` that stay ``rings``
    or more from the mesh's boundary."""
    graph = _face_graph(mesh)

    def per_face(values: np.ndarray) -> np.ndarray:
        return np.nan_to_num(values)[mesh.faces].mean(axis=1)  # unseen: no verdict, not a lid

    # A lid closes an opening: surface all around it. A patch reaching the mesh's boundary is not one: at a
    # hem the frames mix the surroundings into the colours read, and beside a hole the field left (a held-out
    # bowl's bottom) the surface is off, so the frames disagree there too, and cutting it only widens the hole.
    border = np.zeros(len(mesh.faces), bool)
    border[mesh.edges_face[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]] = True
    near_border = _grow(graph, border, rings)
    high = (per_face(spread) > lid) & ~near_border
    core = ~_grow(graph, ~high, rings)
    patch = _grow(graph, core, rings) & high
    above_rim = per_face(spread if rim_spread is None else rim_spread) > rim
    while True:
        grown = patch | (_grow(graph, patch, 1) & above_rim)
        if grown.sum() == patch.sum():
            break
        patch = grown
    return _patches(graph, patch, mesh.area_faces, min_area, avoid=near_border)


def _patches(graph: csr_matrix, mask: np.ndarray, area: np.ndarray, min_area: float,
             avoid: np.ndarray | None = None) -> np.ndarray:
    """``mask`` less its connected patches smaller than ``min_area`` or touching ``avoid``."""
    idx = np.nonzero(mask)[0]
    if len(idx) == 0:
        return mask
    _, labels = connected_components(graph[idx][:, idx], directed=False)
    keep = np.bincount(labels, weights=area[idx]) >= min_area
    if avoid is not None:
        keep &= np.bincount(labels, weights=avoid[idx], minlength=len(keep)) == 0
    out = np.zeros(len(mask), bool)
    out[idx[keep[labels]]] = True
    return out


def open_lids(mesh: trimesh.Trimesh, cameras: Cameras, frames: Sequence[Path], tol: float, voxel: float,
              lid: float = SPREAD_LID) -> trimesh.Trimesh:
    """``mesh`` less its lids (:func:`lid_faces` of :func:`colour_spread`); ``voxel`` sizes the streaks
    that do not count (:data:`OPEN_WIDTH`); ``lid`` <= 0 keeps everything. Records ``faces_lids``."""
    if lid <= 0 or len(mesh.faces) == 0:
        return mesh
    rings = max(1, math.ceil(OPEN_WIDTH / voxel))

    def lids(spread: np.ndarray, rim_spread: np.ndarray | None = None) -> np.ndarray:
        return lid_faces(mesh, spread, rings, lid=lid, rim=min(SPREAD_RIM, lid), rim_spread=rim_spread)

    def on_lids(spread: np.ndarray) -> np.ndarray:  # only a lid's vertices can change the verdict
        mask = np.zeros(len(mesh.vertices), bool)
        mask[mesh.faces[lids(spread)].ravel()] = True
        return mask

    # whether a patch is a lid: no depth near it explains the frames; how far it reaches: where they
    # disagree at the mesh (a lid's rim, where the inside lies close behind it, too)
    at_vertex, least = colour_spread(mesh, cameras, frames, tol, sweep=on_lids)
    cut = lids(least, rim_spread=at_vertex)
    info = mesh.metadata.get("meshing", {})
    log.info("cut %d faces of lids (the frames disagree on their colour)", int(cut.sum()))
    if cut.any():
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[~cut], process=False)
        mesh.remove_unreferenced_vertices()
    mesh.metadata["meshing"] = {**info, "faces_lids": int(cut.sum())}
    return mesh
