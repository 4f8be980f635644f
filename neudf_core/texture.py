"""A texture for the mesh a user downloads: UV atlas (xatlas) and colours projected from the input frames.

Vertex colours hold one colour per vertex, so a label's letters or a check pattern finer than the mesh
blur away, and many tools do not show them. Here the mesh gets a UV atlas and an image baked from the
frames the mesh was made from:

- **Two sides.** An open sheet has two sides that look different (a shirt's inside is not its outside).
  Each face gets a twin with reversed winding, set back by ``BACK_OFFSET`` along the vertex normal, with
  texels of its own; a face side is baked only from cameras in front of it. With a double-sided material
  the nearer of the two wins the depth test in any viewer, so each side shows its own texels.
- **Atlas.** xatlas charts the front faces once (charts of a bounded area: xatlas's parametrisation grows
  much faster than linearly with a chart's size) and packs two copies of those charts, front and back,
  into one image.
- **Projection.** Per frame: a z-buffer of the mesh (rasterised here in numpy, at most ``DEPTH_SIDE`` px),
  then every texel whose face looks at the camera is projected; it counts if it lies no deeper than the
  z-buffer's nearest depth around it (so texels at an occluding edge, where a pixel mixes two surfaces,
  are left out), and takes the frame's colour (bilinear) with weight cos^2 (viewing angle) x (f / z)^2
  (pixels per unit of surface) x the frame's sharpness.
- **Colour agreement.** A phone changes exposure and white balance along a video. Each frame's colours
  are scaled per channel by the gain that fits them best to what the frames before it gave the same texels
  (in video order a frame's neighbours come first and overlap it most), so frames blend without seams of
  brightness; the frames' own mean colour sets the overall level. The vertex colours cannot serve as the
  reference: a vertex has one colour for both sides of a sheet.
- **Holes.** Texels no frame sees take the vertex colours; the atlas is dilated ``PADDING`` texels past
  each chart's edge so that filtering and mip-maps do not pull in the empty background.

The mesh and the cameras are in the unit-sphere frame of the dataset (``neudf_core.dataset``).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from typing import TYPE_CHECKING

import cv2
import numpy as np
from PIL import Image

from neudf_core.progress import ProgressFn, null_progress

if TYPE_CHECKING:  # trimesh and the dataset (torch) load when a bake runs: the API reads only the defaults
    import trimesh

__all__ = ["DEFAULT_TEXTURE_SIZE", "MIN_TEXTURE_SIZE", "MAX_TEXTURE_SIZE", "BACK_OFFSET", "Views", "Atlas", "load_views", "unwrap", "rasterize",
           "bake_texture", "textured_mesh"]

DEFAULT_TEXTURE_SIZE = 2048
MIN_TEXTURE_SIZE, MAX_TEXTURE_SIZE = 64, 4096  # the sides a texture may have (0: no texture)
BACK_OFFSET = 1e-3  # unit-sphere units (0.25 mm at 0.5 m across): a face's back twin sits this far behind it
PADDING = 4  # texels between charts, and how far the colours are dilated past a chart's edge
DEPTH_SIDE = 800  # longest side of the z-buffer: occlusion needs the shape, not every pixel
MIN_COS = 0.1  # a face seen more edge-on than this (84 degrees) gives no colour
_UTILISATION = 0.6  # the share of an atlas xatlas fills with charts of a mesh like ours
_CHART_FACES = 200  # about this many faces per chart: xatlas parametrises such charts fast
_MIN_GAIN_TEXELS = 256  # a frame sharing fewer texels with the frames before it keeps its colours as they are


@dataclass
class Views:
    """The frames of a dataset with their cameras (unit sphere, OpenCV, pixels of the full-size images)."""

    paths: list[Path]
    intrinsics: np.ndarray  # (N, 3, 3)
    c2w: np.ndarray  # (N, 4, 4)
    width: int
    height: int
    sharpness: list[float | None]  # frames.json's, where given; measured on the frame otherwise

    def __len__(self) -> int:
        return len(self.paths)


def load_views(data_dir: str | Path) -> Views:
    """The frames and cameras of a NeuS-layout folder (the dataset module's reading of them)."""
    from neudf_core.dataset import image_paths, load_cameras

    root = Path(data_dir)
    cameras = load_cameras(root)
    paths = image_paths(root)
    given: dict[str, float] = {}
    frames_file = root / "frames.json"
    if frames_file.is_file():
        try:
            given = {e["file"]: float(e["sharpness"]) for e in json.loads(frames_file.read_text()) if "sharpness" in e}
        except (ValueError, KeyError, TypeError):
            given = {}
    sharpness = [given.get(p.name) for p in paths]
    return Views(paths, cameras.intrinsics, cameras.c2w, cameras.width, cameras.height, sharpness)


# -- the atlas ---------------------------------------------------------------------------------------------
@dataclass
class Atlas:
    """A two-sided mesh with UVs: the front faces, then their twins with reversed winding."""

    vertices: np.ndarray  # (M, 3); a back vertex is set back by BACK_OFFSET along the vertex normal
    faces: np.ndarray  # (2F, 3): face i and its twin F + i
    uv: np.ndarray  # (M, 2) in 0..1, v up (glTF and OBJ flip it for their own conventions)
    source: np.ndarray  # (M,) the vertex of the input mesh each atlas vertex copies

    @property
    def n_front(self) -> int:
        return len(self.faces) // 2

    def pieces(self) -> np.ndarray:
        """Per face, its connected piece (faces sharing an edge of the input mesh); a twin's is its own."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        front = self.source[self.faces[: self.n_front]]
        edges = np.sort(np.concatenate([front[:, [0, 1]], front[:, [1, 2]], front[:, [2, 0]]]), axis=1)
        _, edge_id = np.unique(edges, axis=0, return_inverse=True)
        faces = np.tile(np.arange(self.n_front), 3)
        n_edges = int(edge_id.max()) + 1
        incidence = coo_matrix((np.ones(len(faces)), (faces, edge_id.ravel())), shape=(self.n_front, n_edges))
        _, labels = connected_components((incidence @ incidence.T).tocsr(), directed=False)
        return np.concatenate([labels, labels + labels.max() + 1])

    def face_normals(self) -> np.ndarray:
        """Each face's unit normal by its winding (a twin's is its front face's, negated)."""
        tri = self.vertices[self.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-20)


def _xatlas_mesh(atlas, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vmap, faces, uv = atlas.get_mesh(index)
    return vmap.astype(np.int64), faces.astype(np.int64), uv.astype(np.float64)


def unwrap(mesh: trimesh.Trimesh, size: int = DEFAULT_TEXTURE_SIZE) -> Atlas:
    """Chart the faces with xatlas and pack front and back copies of the charts for a ``size`` px image."""
    import xatlas

    vertices = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    area = max(float(mesh.area), 1e-12)
    charts = xatlas.ChartOptions()
    charts.max_chart_area = area * min(1.0, _CHART_FACES / max(len(faces), 1))
    charts.max_iterations = 1
    # texels per unit fixed here: with only a resolution to meet, xatlas packs again and again to find it
    pack = xatlas.PackOptions()
    pack.texels_per_unit = math.sqrt(_UTILISATION * size * size / (2 * area))
    pack.padding = PADDING
    front = xatlas.Atlas()
    front.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    front.generate(charts, pack)
    vmap, chart_faces, uv = _xatlas_mesh(front, 0)
    if len(chart_faces) != len(faces):
        raise ValueError(f"xatlas returned {len(chart_faces)} faces for {len(faces)}")
    texel_uv = (uv * [front.width, front.height]).astype(np.float32)  # keep the charts' texel scale
    both = xatlas.Atlas()
    for _ in range(2):
        both.add_uv_mesh(texel_uv, chart_faces.astype(np.uint32))
    repack = xatlas.PackOptions()
    repack.padding = PADDING
    repack.texels_per_unit = 1.0
    both.generate(xatlas.ChartOptions(), repack)
    (map_f, faces_f, uv_f), (map_b, faces_b, uv_b) = _xatlas_mesh(both, 0), _xatlas_mesh(both, 1)
    src_f, src_b = vmap[map_f], vmap[map_b]
    normals = np.asarray(mesh.vertex_normals, np.float64)
    back = vertices[src_b] - BACK_OFFSET * normals[src_b]
    return Atlas(vertices=np.concatenate([vertices[src_f], back]),
                 faces=np.concatenate([faces_f, faces_b[:, ::-1] + len(src_f)]),
                 uv=np.concatenate([uv_f, uv_b]), source=np.concatenate([src_f, src_b]))


# -- rasterising triangles onto a pixel grid ---------------------------------------------------------------
def rasterize(points: np.ndarray, faces: np.ndarray, width: int, height: int,
              budget: int = 1 << 21) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The pixel centres (x + 0.5, y + 0.5) inside each triangle of 2-D ``points``, in chunks of at most
    about ``budget`` candidates: yields (flat pixel index y * width + x, face index, barycentrics (n, 3))."""
    tri = points[faces]  # (F, 3, 2)
    lo = np.clip(np.ceil(tri.min(axis=1) - 0.5), 0, [width, height]).astype(np.int64)
    hi = np.clip(np.floor(tri.max(axis=1) - 0.5), -1, [width - 1, height - 1]).astype(np.int64)
    span = np.maximum(hi - lo + 1, 0)
    counts = span[:, 0] * span[:, 1]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    live = np.flatnonzero((counts > 0) & (np.abs(area) > 1e-12))
    ends = np.cumsum(counts[live])
    start = 0
    while start < len(live):
        stop = max(int(np.searchsorted(ends, (ends[start - 1] if start else 0) + budget, side="right")), start + 1)
        chunk = live[start:stop]
        start = stop
        n = counts[chunk]
        face = np.repeat(chunk, n)
        within = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        x = lo[face, 0] + within % span[face, 0]
        y = lo[face, 1] + within // span[face, 0]
        px, py = x + 0.5 - a[face, 0], y + 0.5 - a[face, 1]
        eb = (px * (c[face, 1] - a[face, 1]) - py * (c[face, 0] - a[face, 0])) / area[face]
        ec = ((b[face, 0] - a[face, 0]) * py - (b[face, 1] - a[face, 1]) * px) / area[face]
        bary = np.stack([1.0 - eb - ec, eb, ec], axis=1)
        inside = (bary >= -1e-9).all(axis=1)
        yield (y * width + x)[inside], face[inside], bary[inside]


@dataclass
class Texels:
    """The texels an atlas covers: where each lies on the surface, on which face (and so which side)."""

    index: np.ndarray  # (T,) flat texel index row * size + col (row 0 at the top: v = 1)
    face: np.ndarray  # (T,) atlas face
    position: np.ndarray  # (T, 3) float32
    fallback: np.ndarray | None  # (T, 3) float32 0..1: the vertex colours there (None: the mesh has none)
    piece: np.ndarray  # (T,) the connected piece of the two-sided mesh (each side of a sheet is one)


def atlas_texels(atlas: Atlas, size: int, vertex_colors: np.ndarray | None) -> Texels:
    pixels = np.stack([atlas.uv[:, 0] * size, (1.0 - atlas.uv[:, 1]) * size], axis=1)
    parts = list(rasterize(pixels, atlas.faces, size, size))
    index = np.concatenate([p[0] for p in parts])
    face = np.concatenate([p[1] for p in parts])
    bary = np.concatenate([p[2] for p in parts])
    index, first = np.unique(index, return_index=True)  # a texel centre on a shared edge: one face
    face, bary = face[first], bary[first]
    corners = atlas.faces[face]
    position = np.einsum("nk,nkc->nc", bary, atlas.vertices[corners]).astype(np.float32)
    fallback = None
    if vertex_colors is not None:
        colors = vertex_colors[atlas.source].astype(np.float32)
        fallback = np.einsum("nk,nkc->nc", bary.astype(np.float32), colors[corners])
    return Texels(index, face, position, fallback, atlas.pieces()[face])


# -- one frame ---------------------------------------------------------------------------------------------
def _read_frame(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"cannot read frame {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (what the frames stage ranks frames by)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_32F).var())


def visible_depth(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, c2w: np.ndarray, width: int,
                  height: int) -> np.ndarray:
    """A z-buffer (camera z per pixel) of the mesh, then per pixel the nearest depth of its 3x3 neighbourhood,
    or 0 where that neighbourhood reaches the background or the image's edge: a point counts as seen where
    it is no deeper than this."""
    in_camera = (vertices - c2w[:3, 3]) @ c2w[:3, :3]
    z = in_camera[:, 2]
    front = (z[faces] > 1e-3).all(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = (in_camera @ K.T)[:, :2] / z[:, None]
    inverse = 1.0 / np.where(z > 1e-3, z, 1.0)
    zbuf = np.full(width * height, np.inf, np.float32)
    kept = faces[front]
    for pixel, face, bary in rasterize(np.nan_to_num(xy), kept, width, height):
        depth = 1.0 / (bary * inverse[kept[face]]).sum(axis=1)  # 1/z is linear across a projected triangle
        np.minimum.at(zbuf, pixel, depth.astype(np.float32))
    zbuf = zbuf.reshape(height, width)
    nearest = cv2.erode(zbuf, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0.0)
    background = cv2.dilate(np.isinf(zbuf).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    nearest[background] = 0.0
    return nearest


def _sample(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear colours (n, 3) float32 0..1 at pixel coordinates whose centres are at integer + 0.5."""
    n = len(u)
    cols = 4096
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = u - 0.5, v - 0.5
    out = cv2.remap(image, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:n].astype(np.float32) / 255.0


def _gain(observed: np.ndarray, reference: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Per channel, the ratio of the weighted means of ``reference`` and ``observed``, kept within 0.5..2.

    Means, not a least-squares fit: a frame that sees the surface blurred or a pixel off (at a slant, or
    with a pose error) has the right mean but a weaker correlation, which a fit would read as darkness."""
    num = (weight[:, None] * reference).sum(axis=0)
    den = (weight[:, None] * observed).sum(axis=0)
    gain = np.where(den > 1e-6, num / np.maximum(den, 1e-12), 1.0)
    return np.clip(gain, 0.5, 2.0).astype(np.float32)


class _Sums:
    """Per texel: the sum of weight x gain x colour, of weight x colour (the frames as they came), of weight."""

    def __init__(self, n: int) -> None:
        self.values = np.zeros((n, 7), np.float32)  # one array: one gather and one scatter per frame

    @property
    def weight(self) -> np.ndarray:
        return self.values[:, 6]

    def corrected(self, rows: np.ndarray | slice) -> np.ndarray:
        return self.values[rows, :3]

    def raw(self, rows: np.ndarray | slice) -> np.ndarray:
        return self.values[rows, 3:6]


def _frame_gain(sums: _Sums, pick: np.ndarray, color: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The gain that fits a frame's colours to what the frames before it gave the same texels (frames come in
    video order, so a frame's neighbours are there already); 1 while the overlap is small."""
    before = sums.weight[pick] > 0
    if before.sum() < _MIN_GAIN_TEXELS:
        return np.ones(3, np.float32)
    rows = sums.values[pick[before]]
    return _gain(color[before], rows[:, :3] / rows[:, 6:7], weight[before])


def _face_cos(normals: np.ndarray, centroids: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Per atlas face, the cosine between its side's normal and the direction to the camera (faces are small
    beside their distance to a camera: one value serves all of a face's texels)."""
    toward = (c2w[:3, 3] - centroids).astype(np.float32)
    return (normals * toward).sum(axis=1) / np.maximum(np.linalg.norm(toward, axis=1), 1e-9)


def _project_frame(texels: Texels, face_cos: np.ndarray, depth: np.ndarray, depth_scale: float, image: np.ndarray,
                   K: np.ndarray, c2w: np.ndarray, sharpness: float, sums: _Sums) -> tuple[int, np.ndarray]:
    """Add one frame's colours to the texels it sees; returns (texels seen, the frame's gain)."""
    pick = np.flatnonzero((face_cos > MIN_COS)[texels.face])
    cos = face_cos[texels.face[pick]]
    in_camera = (texels.position[pick] - c2w[:3, 3].astype(np.float32)) @ c2w[:3, :3].astype(np.float32)
    z = in_camera[:, 2]
    height, width = image.shape[:2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (K[0, 0] * in_camera[:, 0] + K[0, 1] * in_camera[:, 1]) / z + K[0, 2]
        v = K[1, 1] * in_camera[:, 1] / z + K[1, 2]
    ok = (z > 1e-3) & (u >= 1) & (u <= width - 1) & (v >= 1) & (v <= height - 1)
    dh, dw = depth.shape
    nearest = depth[np.minimum((np.where(ok, v, 0) * depth_scale).astype(np.int64), dh - 1),
                    np.minimum((np.where(ok, u, 0) * depth_scale).astype(np.int64), dw - 1)]
    focal = float(K[0, 0])
    # one z-buffer pixel of surface at this depth (more when seen at a slant), and room for the set-back twin
    tolerance = 2.0 * BACK_OFFSET + 1.5 * z / (focal * depth_scale) / np.maximum(cos, 0.3)
    seen = ok & (z <= nearest + tolerance)
    pick, z, cos, u, v = pick[seen], z[seen], cos[seen], u[seen], v[seen]
    if len(pick) == 0:
        return 0, np.ones(3, np.float32)
    color = _sample(image, u, v)
    weight = (cos * cos * (focal / z) ** 2 * sharpness).astype(np.float32)
    gain = _frame_gain(sums, pick, color, weight)
    add = np.empty((len(pick), 7), np.float32)
    add[:, 3:6] = weight[:, None] * color
    add[:, :3] = add[:, 3:6] * gain
    add[:, 6] = weight
    sums.values[pick] += add
    return len(pick), gain


# -- the image ---------------------------------------------------------------------------------------------
def _dilate(image: np.ndarray, filled: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow the filled texels ``steps`` texels outwards, each new one the mean of its filled neighbours."""
    kernel = np.ones((3, 3), np.float32)
    for _ in range(steps):
        weight = cv2.filter2D(filled.astype(np.float32), -1, kernel, borderType=cv2.BORDER_CONSTANT)
        total = cv2.filter2D(image * filled[..., None], -1, kernel, borderType=cv2.BORDER_CONSTANT)
        grow = (~filled) & (weight > 0)
        image[grow] = total[grow] / weight[grow][:, None]
        filled = filled | grow
    return image, filled


def _levels(piece: np.ndarray, raw: np.ndarray, corrected: np.ndarray) -> np.ndarray:
    """Per texel, the factor that gives its piece of surface the frames' own mean colour.

    The gains chain from the first frame that sees a piece, and pieces no frame sees together (the two sides
    of a sheet) chain from different frames: each piece's level is set by all the frames that saw it."""
    pieces = int(piece.max()) + 1 if len(piece) else 0
    factor = np.ones((pieces, 3), np.float32)
    for c in range(3):
        num = np.bincount(piece, raw[:, c], minlength=pieces)
        den = np.bincount(piece, corrected[:, c], minlength=pieces)
        factor[:, c] = np.where(den > 1e-9, num / np.maximum(den, 1e-9), 1.0)
    return factor[piece]


def _compose(size: int, texels: Texels, sums: _Sums) -> tuple[np.ndarray, float]:
    """The texture (size, size, 3) float32: baked colours, vertex colours where no frame saw, dilated."""
    seen = sums.weight > 0
    colors = np.zeros((len(texels.index), 3), np.float32)
    colors[seen] = sums.corrected(seen) / sums.weight[seen][:, None]
    colors[seen] *= _levels(texels.piece[seen], sums.raw(seen), sums.corrected(seen))
    if texels.fallback is not None:
        colors[~seen] = texels.fallback[~seen]
    elif seen.any():
        colors[~seen] = colors[seen].mean(axis=0)
    else:
        colors[:] = 0.5
    image = np.zeros((size * size, 3), np.float32)
    image[texels.index] = colors
    filled = np.zeros(size * size, bool)
    filled[texels.index] = True
    image, filled = _dilate(image.reshape(size, size, 3), filled.reshape(size, size), PADDING)
    image[~filled] = colors.mean(axis=0)  # between charts: no colour a mip-map level could show as a seam
    return np.clip(image, 0.0, 1.0), float(seen.mean()) if len(seen) else 0.0


def _vertex_colors(mesh: trimesh.Trimesh) -> np.ndarray | None:
    if mesh.visual.kind != "vertex":
        return None
    return np.asarray(mesh.visual.vertex_colors, np.float32)[:, :3] / 255.0


def bake_texture(mesh: trimesh.Trimesh, data_dir: str | Path, size: int = DEFAULT_TEXTURE_SIZE, *,
                 frames: Sequence[int] | None = None,
                 progress: ProgressFn = null_progress) -> tuple[trimesh.Trimesh, dict]:
    """The two-sided textured mesh of ``mesh`` (unit sphere of ``data_dir``'s cameras) and the bake's figures.

    ``frames``: the indices of the frames to project (default: all). Returns the mesh (TextureVisuals with
    a double-sided, matte PBR material) and ``{"texture_size", "texels", "seen", "frames", "seconds",
    "gain_min", "gain_max"}`` (seen: the share of texels at least one frame coloured).
    """
    if size < 8:
        raise ValueError(f"texture size must be at least 8 px, got {size}")
    if len(mesh.faces) == 0:
        raise ValueError("refusing to texture a mesh with no faces")
    start = time.perf_counter()
    views = load_views(data_dir)
    chosen = list(range(len(views))) if frames is None else [int(i) for i in frames]
    progress(0.0, "UV atlas")
    atlas = unwrap(mesh, size)
    progress(0.15, "texels")
    texels = atlas_texels(atlas, size, _vertex_colors(mesh))
    sums = _Sums(len(texels.index))
    normals = atlas.face_normals().astype(np.float32)
    centroids = atlas.vertices[atlas.faces].mean(axis=1)
    front_vertices, front_faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    depth_scale = min(1.0, DEPTH_SIDE / max(views.width, views.height))
    dw, dh = max(1, round(views.width * depth_scale)), max(1, round(views.height * depth_scale))
    gains = []
    for n, i in enumerate(chosen):
        image = _read_frame(views.paths[i])
        if image.shape[:2] != (views.height, views.width):
            raise ValueError(f"{views.paths[i].name} is {image.shape[1]}x{image.shape[0]}, the cameras are for "
                             f"{views.width}x{views.height}")
        K, c2w = views.intrinsics[i], views.c2w[i]
        K_depth = np.diag([dw / views.width, dh / views.height, 1.0]) @ K
        depth = visible_depth(front_vertices, front_faces, K_depth, c2w, dw, dh)
        sharpness = views.sharpness[i] if views.sharpness[i] is not None else _sharpness(image)
        face_cos = _face_cos(normals, centroids, c2w)
        _, gain = _project_frame(texels, face_cos, depth, dw / views.width, image, K, c2w, max(sharpness, 1e-6), sums)
        gains.append(gain)
        progress(0.15 + 0.8 * (n + 1) / len(chosen), f"projected frame {n + 1}/{len(chosen)}")
    pixels, seen = _compose(size, texels, sums)
    image = Image.fromarray((pixels * 255.0).round().astype(np.uint8))
    textured = textured_mesh(atlas, image)
    textured.metadata.update(mesh.metadata)
    gains_arr = np.array(gains) if gains else np.ones((1, 3))
    figures = {"texture_size": size, "texels": int(len(texels.index)), "seen": round(seen, 4),
               "frames": len(chosen), "seconds": round(time.perf_counter() - start, 2),
               "gain_min": round(float(gains_arr.min()), 3), "gain_max": round(float(gains_arr.max()), 3)}
    textured.metadata["texture"] = figures
    textured.metadata["texture_gains"] = gains_arr.round(4).tolist()  # per frame baked, per channel
    progress(1.0, f"baked a {size} px texture from {len(chosen)} frames")
    return textured, figures


def textured_mesh(atlas: Atlas, image: Image.Image) -> trimesh.Trimesh:
    """A trimesh of the atlas with ``image`` as the base colour of a matte, double-sided PBR material."""
    import trimesh

    material = trimesh.visual.material.PBRMaterial(
        name="neudf-texture", baseColorTexture=image, baseColorFactor=[255, 255, 255, 255], metallicFactor=0.0,
        roughnessFactor=1.0, doubleSided=True)
    visual = trimesh.visual.TextureVisuals(uv=atlas.uv, material=material)
    return trimesh.Trimesh(atlas.vertices, atlas.faces, visual=visual, process=False)
