"""Capture stage 3, scene: find the filmed object, normalise it into the unit sphere, write the NeUDF dataset.

From the pinhole model of the poses stage:

1. The object is where the cameras look: the point nearest to all optical axes (least squares, re-weighted
   so a few frames aimed elsewhere do not pull it). The sparse points near that point (closer than
   ``near_fraction`` of the median camera distance) are the object and its immediate surroundings; the
   middle of their robust bounding box refines the centre and their spread gives the object's radius.
   A floor under the object (a dense level of points below it, spreading wider than the object and going
   on past the column under it) is left out of both, and its height goes into DATA/region.json: training
   leaves what lies under it to the background model, so neither the floor nor the object's shadow on it
   becomes surface.
2. The world is turned upright, so the mesh comes out upright (y up, as glTF expects): people hold a
   phone level while tilting it, so "up" is the direction perpendicular to all cameras' right vectors, on
   the side of their mean up vector; +z points towards the first frame.
3. ``scale_mat`` maps the unit sphere onto a sphere of radius object_radius / ``object_fill`` about the
   centre, so the object sits inside the unit sphere with a margin while the cameras stay outside (the
   radius shrinks, with a warning, when a camera came closer than that).

Writes, for the registered frames only and in their order: DATA/image/*.png (renumbered, undistorted),
DATA/frames.json (kept consistent with image/), DATA/cameras_sphere.npz (``world_mat_i`` = K [R | t] 4x4
from the upright world to pixels, ``scale_mat_i`` 4x4 from the unit sphere to that world) and
DATA/cameras.png, a picture of the camera path and sparse points for the web page; besides them
DATA/region.json (the floor), DATA/object_points.npy (the sparse points inside the unit sphere and above
the floor, for training's optional point prior) and DATA/object_point_views.npy (for each of them, frames
that saw it). Pixel centres sit at integer + 0.5 (COLMAP's
and the synthetic renderer's convention). Figures go into ``capture.json`` under ``scene``, written last.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from pydantic import BaseModel, ConfigDict, Field

from neudf_core.dataset import OBJECT_POINT_VIEWS_FILE, OBJECT_POINTS_FILE, REGION_FILE, VIEWS_PER_POINT
from neudf_core.files import atomic_write, link_or_copy, write_json_atomic
from neudf_core.progress import ProgressFn, null_progress
from worker.capture.poses import colmap_dir, undistorted_dir
from worker.capture.records import update_capture_json
from worker.errors import StageError

__all__ = ["STAGE", "SceneOptions", "SceneCameras", "write_scene", "is_done", "load_model", "axes_point",
           "up_direction", "upright_rotation"]

STAGE = "scene"
# A level of sparse points this many times denser than a typical level above it needs no wider reach than the
# object's to count as the floor (a floor against a smooth bowl: 7224 points in its bin, 2 in a typical one).
FLOOR_DENSITY = 20.0


class SceneOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    object_fill: float = Field(0.7, gt=0, lt=1, description="Object radius as a share of the unit sphere's.")
    near_fraction: float = Field(0.5, gt=0, lt=1, description="Points this close to the centre (share of the "
                                 "median camera distance) belong to the object.")
    object_percentile: float = Field(98.0, gt=50, le=100, description="Percentile of the object points' "
                                     "distances taken as the object's radius (robust to stray points).")
    camera_clearance: float = Field(1.1, ge=1, description="Cameras at least this many unit radii from the centre.")
    min_object_points: int = Field(20, ge=1, description="Fewer near points: use the axes point and camera "
                                   "distances alone.")
    max_point_error_px: float = Field(2.0, gt=0, description="Sparse points with a larger reprojection error are ignored.")
    min_track_length: int = Field(3, ge=2, description="Sparse points seen in fewer frames are ignored: two-view "
                                  "points off the object's silhouette float in the air around it.")
    floor_band: float = Field(0.015, gt=0, lt=0.2, description="Half the thickness of the floor's level of sparse "
                              "points, as a share of the median camera distance.")
    plot_points: int = Field(6000, ge=0, description="Most sparse points drawn in cameras.png.")


class SceneCameras(BaseModel):
    """Registered cameras of the pinhole model, in image-name order (numpy arrays inside)."""

    model_config = ConfigDict(arbitrary_types_allowed=True)

    names: list[str]
    K: np.ndarray  # (3, 3), shared
    width: int
    height: int
    R: np.ndarray  # (N, 3, 3) world to camera
    t: np.ndarray  # (N, 3)
    points: np.ndarray  # (M, 3) sparse points (filtered)
    colors: np.ndarray  # (M, 3) uint8
    views: np.ndarray  # (M, VIEWS_PER_POINT) int32: indices (into names) of frames that saw each point, -1 after

    @property
    def centers(self) -> np.ndarray:
        return -np.einsum("nji,nj->ni", self.R, self.t)

    @property
    def axes(self) -> np.ndarray:
        """Unit optical axes (camera +z) in world."""
        return self.R[:, 2, :]

    @property
    def rights(self) -> np.ndarray:
        """Unit right vectors (camera +x) in world."""
        return self.R[:, 0, :]

    @property
    def ups(self) -> np.ndarray:
        """Unit up vectors (camera -y, OpenCV) in world."""
        return -self.R[:, 1, :]


def load_model(model_dir: str | Path, max_point_error_px: float = 2.0, min_track_length: int = 3) -> SceneCameras:
    """Read a pinhole COLMAP model (one shared camera) into arrays, images sorted by name."""
    rec = pycolmap.Reconstruction(str(model_dir))
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise StageError(STAGE, "the camera model holds no posed frames", "registration")
    cam = rec.cameras[images[0].camera_id]
    fx, fy, cx, cy = (float(v) for v in cam.params[:4])
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    R = np.stack([im.cam_from_world().rotation.matrix() for im in images])
    t = np.stack([np.asarray(im.cam_from_world().translation) for im in images])
    index = {im.image_id: i for i, im in enumerate(images)}
    kept = [p for p in rec.points3D.values() if p.error <= max_point_error_px
            and p.track.length() >= min_track_length]
    points = np.array([p.xyz for p in kept]).reshape(-1, 3)
    colors = np.array([p.color for p in kept], dtype=np.uint8).reshape(-1, 3)
    views = np.stack([_track_views(p.track, index) for p in kept]) if kept else np.zeros((0, VIEWS_PER_POINT), np.int32)
    return SceneCameras(names=[im.name for im in images], K=K, width=cam.width, height=cam.height, R=R, t=t,
                        points=points, colors=colors, views=views)


def _track_views(track: Any, index: dict[int, int]) -> np.ndarray:
    """Up to VIEWS_PER_POINT frames of a point's track, spread over it (first to last), -1 after."""
    seen = sorted({index[e.image_id] for e in track.elements if e.image_id in index})
    picked = [seen[i] for i in np.linspace(0, len(seen) - 1, min(len(seen), VIEWS_PER_POINT)).round().astype(int)]
    return np.array(picked + [-1] * (VIEWS_PER_POINT - len(picked)), dtype=np.int32)


def axes_point(centers: np.ndarray, axes: np.ndarray, iterations: int = 5) -> np.ndarray:
    """The point nearest to all lines ``centers + s * axes`` in least squares, Cauchy re-weighted.

    Minimises sum_i w_i |(I - d_i d_i^T)(x - c_i)|^2; frames whose axis passes far from the current estimate
    get less weight, so a glance away from the object does not move it.
    """
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    weights = np.ones(len(centers))
    x = centers.mean(axis=0)
    for _ in range(iterations):
        A = np.einsum("n,nij->ij", weights, projectors)
        b = np.einsum("n,nij,nj->i", weights, projectors, centers)
        eig = np.linalg.eigvalsh(A)
        if eig[0] < 1e-6 * max(eig[-1], 1e-12):  # all axes (nearly) parallel: no crossing point
            raise np.linalg.LinAlgError("optical axes are parallel")
        x = np.linalg.solve(A, b)
        residual = np.linalg.norm(np.einsum("nij,nj->ni", projectors, x - centers), axis=1)
        scale = max(np.median(residual), 1e-9)
        weights = 1.0 / (1.0 + (residual / (2 * scale)) ** 2)
    return x


def up_direction(rights: np.ndarray, ups: np.ndarray) -> np.ndarray:
    """World up from camera axes: perpendicular to every camera's right vector, on the side of their ups.

    People hold a phone level (little roll) but tilt it up and down as they walk round, so the right
    vectors are horizontal while the up vectors lean; up is the direction least along all right vectors.
    When the right vectors do not span the horizontal plane (a short arc), fall back to the mean up vector
    made perpendicular to the dominant right vector.
    """
    mean_up = ups.mean(axis=0)
    mean_up = mean_up / max(np.linalg.norm(mean_up), 1e-12)
    eigvals, eigvecs = np.linalg.eigh(rights.T @ rights / len(rights))
    if eigvals[1] > 0.05:
        up = eigvecs[:, 0]
    else:
        right = eigvecs[:, 2]
        up = mean_up - np.dot(mean_up, right) * right
    up = up / max(np.linalg.norm(up), 1e-12)
    return up if np.dot(up, mean_up) >= 0 else -up


def upright_rotation(up: np.ndarray, toward: np.ndarray) -> np.ndarray:
    """Rotation (rows x, y, z) taking ``up`` to +y and ``toward`` (made horizontal) to +z."""
    y = up / np.linalg.norm(up)
    z = toward - np.dot(toward, y) * y
    if np.linalg.norm(z) < 1e-6:  # first camera straight above: any horizontal direction
        z = np.cross(y, [1.0, 0.0, 0.0] if abs(y[0]) < 0.9 else [0.0, 0.0, 1.0])
    z = z / np.linalg.norm(z)
    x = np.cross(y, z)
    return np.stack([x, y, z])


def floor_height(heights: np.ndarray, spread: np.ndarray, band: float, min_points: int) -> tuple[float | None, str]:
    """The floor under the object: a dense level of sparse points below the centre that spreads wider than
    the object does. ``heights``: the heights above the centre (upright) of the points in the column under
    and around the object, ``spread``: their horizontal distance from it, ``band``: half the floor level's
    thickness. Returns the floor's top (None when there is no such level) and what was found, in words.
    """
    below = heights < -band
    if below.sum() < min_points:
        return None, f"{int(below.sum())} sparse points below the object"
    edges = np.arange(heights[below].min(), 0.0, band)
    if len(edges) < 2:
        return None, "the points below the object lie in one thin level"
    counts, edges = np.histogram(heights[below], bins=edges)
    peak = int(np.argmax(counts))
    level = float(edges[peak] + band / 2)
    on = np.abs(heights - level) < band
    above = heights > level + band
    # A floor is a level much denser than the object's own levels above it; an object rich in features (a
    # labelled can) may hold most of the points, so the floor is compared with levels, not with all points.
    higher = counts[peak + 1:]
    typical = float(np.median(higher[higher > 0])) if (higher > 0).any() else 0.0
    found = (f"{int(on.sum())} of {len(heights)} points on the densest level below ({counts[peak]} in its bin, "
             f"{typical:.0f} in a typical bin above), {int(above.sum())} above it")
    if on.sum() < min_points or counts[peak] < 1.5 * typical or above.sum() < min_points:
        return None, found
    # A floor reaches beyond the object's footprint; a hem or a can's bottom rim does not. Where the object
    # gives few points (a smooth bowl), stray points in the column spread as far as the floor can (the column
    # bounds both), so a level many times denser than any above it is a floor if it reaches as far.
    reach_on, reach_above = np.percentile(spread[on], 80), np.percentile(spread[above], 80)
    found += f", reaching {reach_on / max(reach_above, 1e-12):.2f}x as far out as the object"
    overwhelming = counts[peak] >= FLOOR_DENSITY * max(typical, 1.0)
    if reach_on < (1.0 if overwhelming else 1.2) * reach_above:
        return None, found
    return level + band, found


def _object_sphere(cams: SceneCameras, opts: SceneOptions, up: np.ndarray
                   ) -> tuple[np.ndarray, float, int, float | None, str, list[str]]:
    """Centre and radius (COLMAP units) of the object, the number of sparse points used, the height of the
    floor above the centre (along ``up``; None when there is none), what the floor search found, and
    warnings."""
    centers, warnings = cams.centers, []
    try:
        focus = axes_point(centers, cams.axes)
    except np.linalg.LinAlgError:
        # A video that never turns around anything: take the middle of what the cameras saw.
        warnings.append("the cameras do not look at a common point: the scene centre is a guess")
        focus = np.median(cams.points, axis=0) if len(cams.points) else centers.mean(axis=0)
    distance = float(np.median(np.linalg.norm(centers - focus, axis=1)))
    offsets = cams.points - focus
    heights = offsets @ up
    spread = np.linalg.norm(offsets - heights[:, None] * up, axis=1)
    reach = opts.near_fraction * distance
    near_mask = np.linalg.norm(offsets, axis=1) < reach
    if near_mask.sum() < opts.min_object_points:
        warnings.append(f"only {int(near_mask.sum())} sparse points near the centre: the object's size is a guess")
        return focus, 0.3 * distance, int(near_mask.sum()), None, "too few points to look for one", warnings
    # The floor is looked for in the column under the object, deeper than the near ball reaches: a ball clips a
    # floor at its edge to a small disc, which looks like the object's own bottom.
    column = (spread < reach) & (heights < reach) & (heights > -2 * reach)
    band = opts.floor_band * distance
    floor, floor_search = floor_height(heights[column], spread[column], band, opts.min_object_points)
    if floor is not None:
        # A floor goes on past the object's column; a flat object's own level (a sheet, a leaf) stops with it.
        onward = (np.abs(heights - (floor - band)) < band) & (spread >= reach) & (spread < 2 * reach)
        floor_search += f", {int(onward.sum())} continuing it past the column"
        if onward.sum() < opts.min_object_points:
            floor = None
    if floor is not None:
        near_mask &= heights > floor
    near = cams.points[near_mask]
    lo, hi = np.percentile(near, [100 - opts.object_percentile, opts.object_percentile], axis=0)
    centre = (lo + hi) / 2
    radius = float(np.percentile(np.linalg.norm(near - centre, axis=1), opts.object_percentile))
    if floor is not None:
        floor -= float((centre - focus) @ up)
    return centre, radius, len(near), floor, floor_search, warnings


def is_done(data_dir: str | Path) -> bool:
    """True when the dataset is complete: one camera per image, the picture and the scene record."""
    data_dir = Path(data_dir)
    npz, png = data_dir / "cameras_sphere.npz", data_dir / "cameras.png"
    if not (npz.is_file() and png.is_file() and (data_dir / "capture.json").is_file()):
        return False
    try:
        if "scene" not in json.loads((data_dir / "capture.json").read_text()):
            return False
        with np.load(npz) as arrays:
            n_cams = sum(1 for k in arrays.files if k.startswith("world_mat_") and not k.endswith("_inv"))
    except (OSError, ValueError):
        return False
    return n_cams > 0 and n_cams == len(list((data_dir / "image").glob("*.png")))


def _write_images(data_dir: Path, cams: SceneCameras, progress: ProgressFn) -> list[dict[str, Any]]:
    """Replace DATA/image by the registered, undistorted frames renumbered 000.png...; frames.json to match."""
    source = undistorted_dir(data_dir) / "images"
    frames_all = {f["file"]: f for f in json.loads((colmap_dir(data_dir) / "frames_all.json").read_text())}
    staging, old, final = data_dir / "image.new", data_dir / "image.old", data_dir / "image"
    for leftover in (staging, old):
        shutil.rmtree(leftover, ignore_errors=True)
    staging.mkdir()
    digits = max(3, len(str(len(cams.names) - 1)))
    entries = []
    for i, name in enumerate(cams.names):
        new = f"{i:0{digits}d}.png"
        link_or_copy(source / name, staging / new)
        entries.append({**frames_all[name], "file": new})
        if i % 20 == 0:
            progress(0.2 + 0.5 * i / len(cams.names), f"writing frame {i + 1}/{len(cams.names)}")
    if final.exists():
        final.rename(old)
    staging.rename(final)
    shutil.rmtree(old, ignore_errors=True)
    write_json_atomic(data_dir / "frames.json", entries)
    return entries


def plot_cameras(path: Path, centers: np.ndarray, axes: np.ndarray, points: np.ndarray, colors: np.ndarray,
                 title: str, max_points: int = 6000, seed: int = 0) -> None:
    """Two views of the unit-sphere scene: a perspective one and one from above (x right, z down the page).

    Sparse points in their colours, the camera path coloured by time (dark = start), short ticks for the
    viewing directions and the unit sphere the object must fill.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reach = 1.15 * float(np.linalg.norm(centers, axis=1).max())
    keep = np.linalg.norm(points, axis=1) < reach
    points, colors = points[keep], colors[keep] / 255.0
    if len(points) > max_points:
        pick = np.random.default_rng(seed).choice(len(points), max_points, replace=False)
        points, colors = points[pick], colors[pick]
    time_colors = plt.cm.viridis(np.linspace(0, 1, len(centers)))
    step = max(1, len(centers) // 40)
    tips = centers + 0.12 * reach * axes

    fig = plt.figure(figsize=(11, 5.5), dpi=100)
    ax = fig.add_subplot(1, 2, 1, projection="3d")  # matplotlib's z is the world's up (y)
    if len(points):
        ax.scatter(points[:, 0], points[:, 2], points[:, 1], c=colors, s=1.5, depthshade=False, linewidths=0)
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 37), np.linspace(0, np.pi, 19))
    ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.6", linewidth=0.3)
    ax.plot(centers[:, 0], centers[:, 2], centers[:, 1], color="0.3", linewidth=0.8)
    ax.scatter(centers[:, 0], centers[:, 2], centers[:, 1], c=time_colors, s=10, depthshade=False)
    for c, tip, col in zip(centers[::step], tips[::step], time_colors[::step]):
        ax.plot([c[0], tip[0]], [c[2], tip[2]], [c[1], tip[1]], color=col, linewidth=1.0)
    ax.set_xlim(-reach, reach), ax.set_ylim(-reach, reach), ax.set_zlim(-reach, reach)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x"), ax.set_ylabel("z"), ax.set_zlabel("y (up)")
    ax.view_init(elev=30, azim=-60)

    top = fig.add_subplot(1, 2, 2)
    if len(points):
        top.scatter(points[:, 0], points[:, 2], c=colors, s=1.5, linewidths=0)
    top.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="0.5", linewidth=0.8, linestyle="--"))
    top.plot(centers[:, 0], centers[:, 2], color="0.3", linewidth=0.8)
    top.scatter(centers[:, 0], centers[:, 2], c=time_colors, s=10, zorder=3)
    for c, tip, col in zip(centers[::step], tips[::step], time_colors[::step]):
        top.plot([c[0], tip[0]], [c[2], tip[2]], color=col, linewidth=1.0)
    top.set_xlim(-reach, reach), top.set_ylim(reach, -reach)
    top.set_aspect("equal")
    top.set_xlabel("x"), top.set_ylabel("z")
    top.set_title("from above (dashed: unit sphere)", fontsize=9)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    with atomic_write(path) as tmp:  # cameras.tmp.png: the picture is handed out as soon as it exists
        fig.savefig(tmp)
    plt.close(fig)


def write_scene(
    data_dir: str | Path,
    *,
    options: SceneOptions | None = None,
    progress: ProgressFn = null_progress,
) -> dict[str, Any]:
    """Normalise the posed capture into the unit sphere and write the NeuS-layout dataset."""
    opts = options or SceneOptions()
    data_dir = Path(data_dir)
    t0 = time.perf_counter()
    model_dir = undistorted_dir(data_dir) / "sparse"
    if not (model_dir / "images.bin").is_file():
        raise StageError(STAGE, "no camera poses to normalise: run the poses stage first", "missing")
    progress(0.0, "reading the camera model")
    cams = load_model(model_dir, opts.max_point_error_px, opts.min_track_length)

    up = up_direction(cams.rights, cams.ups)
    centre, radius, n_near, floor, floor_search, warnings = _object_sphere(cams, opts, up)
    rotation = upright_rotation(up, cams.centers[0] - centre)
    # The world of the dataset: COLMAP's, moved to the object's centre and turned upright (COLMAP's units).
    centers_w = (cams.centers - centre) @ rotation.T
    sphere_radius = radius / opts.object_fill
    nearest_camera = float(np.linalg.norm(centers_w, axis=1).min())
    if sphere_radius * opts.camera_clearance > nearest_camera:
        sphere_radius = nearest_camera / opts.camera_clearance
        warnings.append("a camera came close to the object: parts of it may lie outside the reconstructed sphere")
    scale_mat = np.diag([sphere_radius, sphere_radius, sphere_radius, 1.0])
    progress(0.2, "writing frames")
    entries = _write_images(data_dir, cams, progress)

    K4 = np.eye(4)
    K4[:3, :3] = cams.K
    arrays: dict[str, np.ndarray] = {}
    for i in range(len(cams.names)):
        w2c = np.eye(4)
        w2c[:3, :3] = cams.R[i] @ rotation.T
        w2c[:3, 3] = cams.R[i] @ centre + cams.t[i]
        arrays[f"world_mat_{i}"] = K4 @ w2c
        arrays[f"scale_mat_{i}"] = scale_mat
    with atomic_write(data_dir / "cameras_sphere.npz") as tmp:  # cameras_sphere.tmp.npz
        np.savez(tmp, **arrays)

    progress(0.8, "drawing the camera path")
    unit_centers = centers_w / sphere_radius
    unit_axes = cams.axes @ rotation.T
    unit_points = (cams.points - centre) @ rotation.T / sphere_radius
    record = _read_capture(data_dir)
    title = (f"{len(cams.names)}/{record.get('frames_total', len(cams.names))} frames registered, "
             f"{record.get('reprojection_error_px', float('nan')):.2f} px, {len(cams.points)} points")
    plot_cameras(data_dir / "cameras.png", unit_centers, unit_axes, unit_points, cams.colors, title, opts.plot_points)

    camera_radii = np.linalg.norm(unit_centers, axis=1)
    scene = {
        "centre": [round(float(v), 6) for v in centre],
        "up": [round(float(v), 6) for v in rotation[1]],
        "sphere_radius": round(float(sphere_radius), 6),
        "object_radius_unit": round(float(radius / sphere_radius), 4),
        "camera_radius_unit": {"min": round(float(camera_radii.min()), 4),
                               "median": round(float(np.median(camera_radii)), 4),
                               "max": round(float(camera_radii.max()), 4)},
        "object_points": int(n_near),
        "images": len(entries),
        "image_size": [int(cams.width), int(cams.height)],
    }
    floor_unit = None if floor is None or floor / sphere_radius <= -1.0 else round(float(floor / sphere_radius), 4)
    write_json_atomic(data_dir / REGION_FILE, {"floor_y": floor_unit})
    scene["floor_y_unit"] = floor_unit
    scene["object_points_inside"] = _write_object_points(data_dir, unit_points, cams.views, floor_unit)
    under = floor is not None and floor_unit is None
    scene["floor_search"] = floor_search + (", under the unit sphere" if under else "")
    if warnings:
        scene["warnings"] = warnings
    seconds = time.perf_counter() - t0
    # Last: the "scene" record marks the stage complete.
    update_capture_json(data_dir, seconds={"scene": seconds}, scene_options=opts.model_dump(), scene=scene)
    progress(1.0, f"{len(entries)} cameras normalised", images=len(entries))
    return {**scene, "seconds": round(seconds, 3)}


def _write_object_points(data_dir: Path, unit_points: np.ndarray, views: np.ndarray, floor_y: float | None) -> int:
    """DATA/object_points.npy: the sparse points inside the unit sphere and above the floor, where training
    looks for the object; DATA/object_point_views.npy, row for row, the frames that saw them. Returns how many."""
    keep = np.linalg.norm(unit_points, axis=1) < 1.0
    if floor_y is not None:
        keep &= unit_points[:, 1] > floor_y
    with atomic_write(data_dir / OBJECT_POINT_VIEWS_FILE) as tmp:
        np.save(tmp, views[keep])
    with atomic_write(data_dir / OBJECT_POINTS_FILE) as tmp:
        np.save(tmp, unit_points[keep].astype(np.float32))
    return int(keep.sum())


def _read_capture(data_dir: Path) -> dict[str, Any]:
    path = data_dir / "capture.json"
    return json.loads(path.read_text()) if path.is_file() else {}
