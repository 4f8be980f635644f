"""Capture stage 2, poses: pycolmap structure from motion on the chosen frames.

Steps, each reported through ``progress``:

1. SIFT features (pycolmap, CPU), one camera shared by all frames (one phone, one zoom) with a distortion
   model (OPENCV by default), the SIFT image size capped. Extraction runs in batches so progress moves
   and a cancel takes effect between batches.
2. Matching on an explicit list of image pairs. A small set (fewer than ``exhaustive_below`` frames) is
   matched exhaustively. A video is matched with each frame's ``overlap`` successors in time first; the far
   pairs (successors at power-of-two distances, as COLMAP's quadratic overlap, all pairs among
   ~``loop_keyframes`` frames spread over the video, and the first frames against the last, to close a
   walk-around's loop; COLMAP's own loop detection needs a vocabulary tree file we do not ship) are matched
   only where the neighbours in time cannot hold the video, and survive only with ``far_min_inliers``
   inliers and a general (non-planar) geometry.
3. Mapping, the largest model kept. A video is mapped globally (pycolmap's GLOMAP: rotation averaging,
   global positioning, bundle adjustment and retriangulation, on at most ``global_max_tracks`` tracks): a
   200-frame walk-around's mapping took 75 s where COLMAP's incremental mapper took 368 s, the cameras as
   close to the truth (``PoseOptions.mapper``).
   Fewer frames, matched all against all, go to the incremental mapper, which reports each registered
   frame.
   A video's consecutive frames must move smoothly. When the mapping from neighbours in time makes no
   model, registers too few frames or jumps between consecutive frames (:func:`jump_indices`), the far
   pairs are matched and the video mapped again with them. On repeated texture (floor tiles, a room's
   walls) a far pair can be wrong and flip a stretch of the video to a mirrored pose with a small
   reprojection error (seen on the real beer.mp4 and on the poncho and polo videos of bench/e2e.py, when
   they were mapped with their far pairs first); where the poses then jump, every far pair is dropped and
   the video mapped incrementally from neighbours in time, rejecting a wrong pair frame by frame where a
   global solve must average it in. Jumps that remain are reported as a warning.
4. Undistortion to a pinhole camera, because NeuS's ``world_mat`` is a pinhole projection. When the
   estimated distortion moves no pixel by more than ``undistort_threshold_px`` the frames are used as they
   are (no resampling blur) and the camera is rewritten as PINHOLE; otherwise pycolmap's
   ``undistort_images`` resamples them.

Writes ``DATA/colmap/`` (database.db, sparse/<k>/, with far pairs sparse_far/<k>/ and after a jump there
sparse_sequential_incremental/<k>/,
undistorted/{images,sparse}/, frames_all.json and poses.json, the marker written last) and merges
frames_total, frames_registered, reprojection_error_px, points and the seconds of each step into
``DATA/capture.json``. Raises StageError when too few frames register.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar, Literal, NamedTuple

import numpy as np
import pycolmap
from pydantic import BaseModel, ConfigDict, Field

from neudf_core.files import link_or_copy, write_json_atomic
from neudf_core.progress import Cancelled, ProgressFn, null_progress, sub_progress
from worker.capture.records import read_frames_json, update_capture_json
from worker.errors import StageError

__all__ = ["STAGE", "PoseOptions", "estimate_poses", "is_done", "image_pairs", "pose_jumps", "jump_indices",
           "colmap_dir", "undistorted_dir"]

STAGE = "poses"


class PoseOptions(BaseModel):
    """Knobs of the pycolmap stage; the defaults suit a phone walk-around of 100-300 frames."""

    model_config = ConfigDict(extra="forbid")
    # How the stage runs, not what it computes: a resumed capture does not redo poses for a change in these.
    RUN_ONLY: ClassVar[frozenset[str]] = frozenset({"num_threads", "colmap_log", "extract_batch", "match_batch"})

    camera_model: Literal["OPENCV", "SIMPLE_RADIAL", "RADIAL", "PINHOLE", "SIMPLE_PINHOLE"] = Field(
        "OPENCV", description="COLMAP camera model shared by all frames (with distortion unless *PINHOLE).")
    sift_max_image_size: int = Field(1024, ge=64, description="Longest side SIFT sees.")
    sift_max_features: int = Field(2048, ge=100, description="Most SIFT features per image: matching costs the "
                                   "square of it, mapping grows with the points it makes.")
    exhaustive_below: int = Field(60, ge=0, description="Match all pairs when there are fewer frames than this.")
    overlap: int = Field(6, ge=1, description="Sequential matching: successors each frame is matched with.")
    loop_keyframes: int = Field(25, ge=0, description="Frames spread over the video matched all-against-all.")
    doubling: bool = Field(True, description="Also match each frame with frames at doubling distances in time.")
    far_min_inliers: int = Field(
        60, ge=15, description="Pairs farther apart in time than `overlap` are kept only with this many inliers "
        "and a general (non-planar) two-view geometry: repeated texture (floor tiles) fakes such pairs.")
    max_jump_factor: float = Field(
        10.0, gt=1, description="A step between consecutive frames this many times the median step (position) "
        "or 45 degrees and this many median rotations is a pose jump; jumps call in the far pairs, and where those "
        "jump, drop them for the incremental mapper.")
    mapper: Literal["auto", "global", "incremental"] = Field(
        "auto", description="global: rotation averaging, then all positions and bundle adjustment at once (GLOMAP "
        "in pycolmap), several times faster on a video; incremental: COLMAP's frame-by-frame mapper, which "
        "reports each registered frame and can be cancelled mid-way; auto: global for a video (at least "
        "`exhaustive_below` frames), incremental for fewer frames, whose all-pairs matching lets repeated "
        "texture join stretches of the orbit at wrong angles in a global solve.")
    global_max_tracks: int = Field(
        2500, ge=100, description="Global mapper: the most feature tracks used for positioning and bundle "
        "adjustment (its retriangulation then adds the others back as points); fewer tracks, faster mapping.")
    ba_global_ratio: float = Field(
        1.4, gt=1, description="Incremental mapper: bundle-adjust the whole model each time it has grown by this "
        "factor (COLMAP: 1.1); between, each new frame gets a local adjustment. Global adjustments dominate "
        "its mapping of a 200-frame video.")
    min_registered_fraction: float = Field(0.4, ge=0, le=1, description="Below this share of frames: failure.")
    good_registered_fraction: float = Field(0.8, ge=0, le=1, description="Below this share: a warning.")
    min_registered: int = Field(8, ge=2, description="Fewest registered frames, whatever the share.")
    undistort_threshold_px: float = Field(
        1.0, ge=0, description="Largest distortion displacement (px) still treated as a pinhole camera.")
    extract_batch: int = Field(16, ge=1, description="Images per SIFT call (progress and cancel granularity).")
    match_batch: int = Field(256, ge=1, description="Pairs per matching call.")
    num_threads: int = Field(
        -1, ge=-1, description="Threads for pycolmap (-1: all cores). Threads make a run vary a little even with "
        "the seed fixed; 1 keeps repeated runs closer.")
    seed: int = Field(0, description="Random seed of the mapper's RANSAC, for repeatable runs.")
    colmap_log: bool = Field(False, description="Let pycolmap log its INFO lines (thousands) to stderr.")


def colmap_dir(data_dir: str | Path) -> Path:
    return Path(data_dir) / "colmap"


def undistorted_dir(data_dir: str | Path) -> Path:
    """Where the pinhole model (sparse/) and its images (images/) live for the scene stage."""
    return colmap_dir(data_dir) / "undistorted"


def is_done(data_dir: str | Path) -> bool:
    """True when the stage finished: its marker, the pinhole model and its images exist."""
    und = undistorted_dir(data_dir)
    return (
        (colmap_dir(data_dir) / "poses.json").is_file()
        and (und / "sparse" / "images.bin").is_file()
        and (und / "images").is_dir()
    )


# -- pairs ---------------------------------------------------------------------------------------------
def image_pairs(n: int, *, exhaustive_below: int = 60, overlap: int = 10, loop_keyframes: int = 25,
                doubling: bool = True) -> list[tuple[int, int]]:
    """Index pairs (i < j) to match among ``n`` frames of a video, in a stable order."""
    if n < exhaustive_below:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        for d in range(1, overlap + 1):  # neighbours in time
            if i + d < n:
                pairs.add((i, i + d))
        d = 2 ** math.ceil(math.log2(overlap + 1))
        while doubling and i + d < n:  # farther frames at doubling distances: bridges over a blurry stretch
            pairs.add((i, i + d))
            d *= 2
    n_keys = min(loop_keyframes, max(2, n // 4))  # short videos: fewer keyframes, not a near-exhaustive set
    if loop_keyframes > 1:  # a walk-around ends where it began: let keyframes find each other
        keys = sorted(set(np.linspace(0, n - 1, n_keys).round().astype(int).tolist()))
        pairs.update((a, b) for k, a in enumerate(keys) for b in keys[k + 1:])
        for a in range(min(overlap, n)):
            for b in range(max(n - overlap, a + 1), n):
                pairs.add((a, b))
    return sorted(pairs)


@contextlib.contextmanager
def _colmap_log_level(verbose: bool) -> Iterator[None]:
    """pycolmap logs every image and pair at INFO: keep warnings only, unless asked (the setting is global)."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = previous if verbose else max(previous, int(pycolmap.logging.WARNING))
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


# -- the steps -------------------------------------------------------------------------------------------
def _extract(db: Path, image_dir: Path, names: list[str], opts: PoseOptions, progress: ProgressFn) -> None:
    reader = pycolmap.ImageReaderOptions(camera_model=opts.camera_model)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = opts.sift_max_image_size
    extraction.num_threads = opts.num_threads
    extraction.sift.max_num_features = opts.sift_max_features
    for start in range(0, len(names), opts.extract_batch):
        batch = names[start:start + opts.extract_batch]
        progress(start / len(names), f"SIFT features {start}/{len(names)}")
        pycolmap.extract_features(db, image_dir, image_names=batch, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        if reader.existing_camera_id < 0:  # one camera for the whole video: later batches reuse the first's
            with contextlib.closing(pycolmap.Database.open(str(db))) as database:
                reader.existing_camera_id = database.read_all_cameras()[0].camera_id
    progress(1.0, f"SIFT features {len(names)}/{len(names)}")


def _match(db: Path, work: Path, names: list[str], pairs: list[tuple[int, int]], opts: PoseOptions,
           progress: ProgressFn) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.num_threads
    pair_file = work / "pairs.txt"
    for start in range(0, len(pairs), opts.match_batch):
        progress(start / len(pairs), f"matching pairs {start}/{len(pairs)}")
        chunk = pairs[start:start + opts.match_batch]
        pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in chunk))
        pycolmap.match_image_pairs(db, matching_options=matching,
                                   pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pair_file)),
                                   device=pycolmap.Device.cpu)
    pair_file.unlink(missing_ok=True)
    progress(1.0, f"matched {len(pairs)} pairs")


# Two-view configurations of a general 3-D scene (the database stores them as plain ints).
_GENERAL_GEOMETRY = {int(pycolmap.TwoViewGeometryConfiguration.CALIBRATED),
                     int(pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED)}


def _drop_far_pairs(db: Path, names: list[str], pairs: list[tuple[int, int]], overlap: int,
                    min_inliers: int | None) -> int:
    """Remove the verified geometry of far-apart pairs: weak ones (``min_inliers``) or, with None, all.

    Far pairs close loops, but on repeated texture (tiles, bricks) a wrong pair passes RANSAC as a
    homography-like geometry and flips a stretch of the video to a mirrored pose. Neighbours in time are
    kept whatever they look like.
    """
    dropped = 0
    with contextlib.closing(pycolmap.Database.open(str(db))) as database:
        ids = {im.name: im.image_id for im in database.read_all_images()}
        for i, j in pairs:
            if j - i <= overlap:
                continue
            a, b = ids[names[i]], ids[names[j]]
            if not database.exists_two_view_geometry(a, b):
                continue
            geometry = database.read_two_view_geometry(a, b)
            inliers = len(geometry.inlier_matches)
            if inliers == 0:
                continue
            if min_inliers is None or inliers < min_inliers or int(geometry.config) not in _GENERAL_GEOMETRY:
                database.delete_two_view_geometry(a, b)
                dropped += 1
    return dropped


def pose_jumps(model: pycolmap.Reconstruction, factor: float = 10.0) -> list[tuple[str, str]]:
    """Consecutive registered frames (by name, i.e. in time) whose poses are too far apart for a video."""
    images = sorted((im for im in model.images.values() if im.has_pose), key=lambda im: im.name)
    if len(images) < 4:
        return []
    w2c = np.stack([im.cam_from_world().rotation.matrix() for im in images])
    centres = np.stack([np.asarray(im.projection_center()).reshape(3) for im in images])
    return [(images[k].name, images[k + 1].name) for k in jump_indices(w2c, centres, factor)]


def jump_indices(w2c: np.ndarray, centres: np.ndarray, factor: float = 10.0) -> list[int]:
    """Indices k where the step from camera k to k+1 is a jump, not a phone's smooth motion.

    A step many times the median step, or a turn of more than 45 degrees that is also many median turns,
    means one side was registered wrongly (on repeated texture, often mirrored).
    """
    moves = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    turns = np.degrees(np.arccos(np.clip((np.einsum("nij,nij->n", w2c[1:], w2c[:-1]) - 1) / 2, -1, 1)))
    big_move = moves > factor * max(float(np.median(moves)), 1e-12)
    big_turn = (turns > 45) & (turns > factor * max(float(np.median(turns)), 1e-6))
    return [int(k) for k in np.flatnonzero(big_move | big_turn)]


def _map(db: Path, image_dir: Path, sparse: Path, n_images: int, opts: PoseOptions,
         progress: ProgressFn) -> tuple[pycolmap.Reconstruction, Path, int]:
    """The largest model the chosen mapper makes, its folder and how many models it made."""
    sparse.mkdir(parents=True, exist_ok=True)
    if _mapper(opts, n_images) == "global":
        models = _map_global(db, image_dir, sparse, n_images, opts, progress)
    else:
        models = _map_incremental(db, image_dir, sparse, n_images, opts, progress)
    if not models:
        raise StageError(
            STAGE,
            f"no camera poses could be found for the {n_images} frames: they share too few features. "
            "Film slowly all around a textured object, with the object in view and good light.",
            "registration",
        )
    key = max(models, key=lambda k: models[k].num_reg_images())
    return models[key], sparse / str(key), len(models)


def _mapper(opts: PoseOptions, n_images: int) -> str:
    if opts.mapper == "auto":
        return "global" if n_images >= opts.exhaustive_below else "incremental"
    return opts.mapper


def _map_global(db: Path, image_dir: Path, sparse: Path, n_images: int, opts: PoseOptions,
                progress: ProgressFn) -> dict[int, pycolmap.Reconstruction]:
    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = opts.num_threads
    options.random_seed = opts.seed
    # Three rounds of bundle adjustment (the default) also bring a video's focal length, which starts as
    # 1.2 times the long side, to the truth (1536 -> 938 px on a test video; one round stopped at 1464).
    # Estimating it first from the pairs' fundamental matrices (pycolmap.calibrate_view_graph) made a
    # 63-frame test orbit jump where it maps right without.
    options.mapper.keep_max_num_tracks = opts.global_max_tracks
    # CPU solvers either way (pycolmap's wheels carry no CUDA); asking for the GPU only adds a warning.
    options.mapper.global_positioning.use_gpu = False
    options.mapper.bundle_adjustment.ceres.use_gpu = False
    # One call without a per-frame callback or a cancellation token: progress moves and a cancel takes
    # effect before and after it (about a minute for 200 frames on 2 cores).
    progress(0.0, f"mapping {n_images} frames at once")
    models = pycolmap.global_mapping(db, image_dir, sparse, options=options)
    registered = max((m.num_reg_images() for m in models.values()), default=0)
    progress(1.0, f"registered {registered}/{n_images} frames", registered=registered)
    return models


def _map_incremental(db: Path, image_dir: Path, sparse: Path, n_images: int, opts: PoseOptions,
                     progress: ProgressFn) -> dict[int, pycolmap.Reconstruction]:
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = opts.num_threads
    options.random_seed = opts.seed
    options.ba_global_frames_ratio = opts.ba_global_ratio
    options.ba_global_points_ratio = opts.ba_global_ratio
    token = pycolmap.CancellationToken()
    registered = 0
    cancelled: list[Cancelled] = []

    def on_image() -> None:
        nonlocal registered
        registered += 1
        try:
            progress(min(registered / n_images, 1.0), f"registered {registered}/{n_images} frames",
                     registered=registered)
        except Cancelled as exc:  # stop pycolmap cleanly, re-raise once it has returned
            cancelled.append(exc)
            token.cancel()

    try:
        models = pycolmap.incremental_mapping(db, image_dir, sparse, options=options,
                                              next_image_callback=on_image, cancellation_token=token)
    except InterruptedError:
        if cancelled:
            raise cancelled[0] from None
        raise
    if cancelled:
        raise cancelled[0]
    return models


FAR_MODELS = "sparse_far"  # the models mapped with the far pairs too


class Mapping(NamedTuple):
    """A mapping's outcome: the largest model, its folder, how many models, the mapper that made it, its jumps
    between consecutive frames and how many far pairs were dropped on the way."""

    model: pycolmap.Reconstruction
    model_dir: Path
    n_models: int
    mapper: str
    jumps: list[tuple[str, str]]
    far_dropped: int = 0


def _sequence_broken(mapping: Mapping | None, n_images: int, opts: PoseOptions) -> str | None:
    """Why a mapping from neighbours in time alone needs the far pairs, or None when it holds."""
    if mapping is None:
        return "no model from neighbours in time"
    if mapping.jumps:
        return f"poses jump between {len(mapping.jumps)} pairs of frames"
    registered = mapping.model.num_reg_images()
    if registered < opts.good_registered_fraction * n_images:
        return f"only {registered} of {n_images} frames registered from neighbours in time"
    return None


def _map_with_far_pairs(db: Path, image_dir: Path, work: Path, names: list[str], far: list[tuple[int, int]],
                        mapper: str, opts: PoseOptions, progress: ProgressFn) -> Mapping:
    """Map again with the far pairs (matched); if one of them then makes the poses jump, drop them all and map
    incrementally from neighbours in time, which rejects a wrong pair frame by frame where a global solve
    must average it in."""
    model, model_dir, n_models = _map(db, image_dir, work / FAR_MODELS, len(names), opts,
                                      sub_progress(progress, 0.0, 0.5))
    jumps, dropped = pose_jumps(model, opts.max_jump_factor), 0
    if jumps and mapper != "incremental":
        dropped = _drop_far_pairs(db, names, far, opts.overlap, None)
        mapper = "incremental"
        model, model_dir, n_models = _map(db, image_dir, work / "sparse_sequential_incremental", len(names),
                                          opts.model_copy(update={"mapper": mapper}), sub_progress(progress, 0.5, 1.0))
        jumps = pose_jumps(model, opts.max_jump_factor)
    return Mapping(model, model_dir, n_models, mapper, jumps, dropped)


def _better_mapping(first: Mapping | None, second: Mapping | None) -> Mapping | None:
    """Which to keep of the mapping from neighbours in time (``first``) and the one after the far pairs
    (``second``; None: no model): the far pairs' unless it registers fewer frames without jumping less, so a
    partial model from neighbours in time is not lost to a worse one."""
    if first is None or second is None:
        return second or first
    fewer = second.model.num_reg_images() < first.model.num_reg_images()
    return first if fewer and len(second.jumps) >= len(first.jumps) else second


def _max_distortion_px(camera: pycolmap.Camera) -> float:
    """Largest shift a pixel gets from the camera's distortion, over a grid covering the image."""
    u, v = np.meshgrid(np.linspace(0.5, camera.width - 0.5, 17), np.linspace(0.5, camera.height - 0.5, 17))
    pixels = np.stack([u.ravel(), v.ravel()], -1)
    normalized = camera.cam_from_img(pixels)
    fx, fy = camera.focal_length_x, camera.focal_length_y
    cx, cy = camera.principal_point_x, camera.principal_point_y
    pinhole = np.stack([normalized[:, 0] * fx + cx, normalized[:, 1] * fy + cy], -1)
    return float(np.abs(pinhole - pixels).max())


def _undistort(model: pycolmap.Reconstruction, model_dir: Path, image_dir: Path, out: Path,
               threshold_px: float) -> dict[str, Any]:
    shutil.rmtree(out, ignore_errors=True)
    camera = next(iter(model.cameras.values()))
    shift = _max_distortion_px(camera) if not camera.model_name.endswith("PINHOLE") else 0.0
    if shift > threshold_px:
        pycolmap.undistort_images(str(out), str(model_dir), str(image_dir), output_type="COLMAP")
        return {"undistorted": True, "max_distortion_px": round(shift, 3)}
    # Negligible distortion: the same pixels, the same focal lengths, a pinhole model.
    (out / "images").mkdir(parents=True)
    (out / "sparse").mkdir()
    for image in model.images.values():
        if image.has_pose:
            link_or_copy(image_dir / image.name, out / "images" / image.name)
    pinhole = pycolmap.Reconstruction(str(model_dir))  # a copy: the mapped model stays as it was
    for cam in pinhole.cameras.values():  # in place: images keep pointing at their camera
        params = [cam.focal_length_x, cam.focal_length_y, cam.principal_point_x, cam.principal_point_y]
        cam.model = pycolmap.CameraModelId.PINHOLE
        cam.params = params
    pinhole.write(str(out / "sparse"))
    return {"undistorted": False, "max_distortion_px": round(shift, 3)}


def estimate_poses(
    data_dir: str | Path,
    *,
    options: PoseOptions | None = None,
    progress: ProgressFn = null_progress,
) -> dict[str, Any]:
    """Pose the frames of DATA/image with pycolmap; returns the figures merged into capture.json."""
    opts = options or PoseOptions()
    with _colmap_log_level(opts.colmap_log):
        return _estimate_poses(Path(data_dir), opts, progress)


def _estimate_poses(data_dir: Path, opts: PoseOptions, progress: ProgressFn) -> dict[str, Any]:
    image_dir = data_dir / "image"
    try:
        frames = read_frames_json(data_dir)
    except (OSError, ValueError) as exc:
        raise StageError(STAGE, "no frames to pose: run the frames stage first", "missing") from exc
    names = [f["file"] for f in frames]
    work = colmap_dir(data_dir)
    shutil.rmtree(work, ignore_errors=True)  # a rerun starts clean: pycolmap appends to a database
    work.mkdir(parents=True)
    for stale in ("cameras_sphere.npz", "cameras.png"):  # the scene stage's, made from the old poses
        (data_dir / stale).unlink(missing_ok=True)
    update_capture_json(data_dir, drop=("scene", "scene_options", "warnings"))
    write_json_atomic(work / "frames_all.json", frames)  # the scene stage renumbers; keep the original list
    db = work / "database.db"
    pycolmap.set_random_seed(opts.seed)
    seconds: dict[str, float] = {}

    t = time.perf_counter()
    _extract(db, image_dir, names, opts, sub_progress(progress, 0.0, 0.3))
    seconds["features"] = time.perf_counter() - t

    t = time.perf_counter()
    pairs = image_pairs(len(names), exhaustive_below=opts.exhaustive_below, overlap=opts.overlap,
                        loop_keyframes=opts.loop_keyframes, doubling=opts.doubling)
    video = len(names) >= opts.exhaustive_below  # matched as a sequence; far pairs only where it breaks
    near = [p for p in pairs if not video or p[1] - p[0] <= opts.overlap]
    far = [p for p in pairs if video and p[1] - p[0] > opts.overlap]
    _match(db, work, names, near, opts, sub_progress(progress, 0.3, 0.45))
    seconds["matching"] = time.perf_counter() - t

    t = time.perf_counter()
    mapper = _mapper(opts, len(names))
    try:
        model, model_dir, n_models = _map(db, image_dir, work / "sparse", len(names), opts,
                                          sub_progress(progress, 0.45, 0.7))
        jumps = pose_jumps(model, opts.max_jump_factor) if video else []
        mapping: Mapping | None = Mapping(model, model_dir, n_models, mapper, jumps)
    except StageError:
        if not far:
            raise
        mapping = None
    far_matched, far_dropped = 0, 0
    broken = _sequence_broken(mapping, len(names), opts) if far else None
    far_seconds = 0.0
    if broken:  # far pairs bridge a stretch the neighbours could not hold
        progress(0.7, f"{broken}: matching far pairs too")
        far_start = time.perf_counter()
        _match(db, work, names, far, opts, sub_progress(progress, 0.7, 0.78))
        far_matched, far_dropped = len(far), _drop_far_pairs(db, names, far, opts.overlap, opts.far_min_inliers)
        far_seconds = time.perf_counter() - far_start
        try:
            with_far = _map_with_far_pairs(db, image_dir, work, names, far, mapper, opts,
                                           sub_progress(progress, 0.78, 0.95))
        except StageError:
            if mapping is None:
                raise
            with_far = None
        mapping = _better_mapping(mapping, with_far)
        far_dropped += mapping.far_dropped
    model, model_dir, n_models, mapper, jumps, _ = mapping
    seconds["matching"] += far_seconds
    seconds["mapping"] = time.perf_counter() - t - far_seconds

    total, registered = len(names), model.num_reg_images()
    needed = max(opts.min_registered, math.ceil(opts.min_registered_fraction * total))
    if registered < needed:
        raise StageError(
            STAGE,
            f"only {registered} of {total} frames could be posed (at least {needed} are needed). "
            "Film slowly all around a textured object, keeping it in view, with good light.",
            "registration",
        )
    warnings = []
    if registered < opts.good_registered_fraction * total:
        warnings.append(f"only {registered} of {total} frames registered: poses may be unreliable")
    if jumps:
        warnings.append(f"camera poses jump between {len(jumps)} pairs of consecutive frames "
                        f"({', '.join(f'{a}-{b}' for a, b in jumps[:3])}): parts of the capture may be misplaced")

    t = time.perf_counter()
    progress(0.95, "undistorting frames")
    undistortion = _undistort(model, model_dir, image_dir, undistorted_dir(data_dir), opts.undistort_threshold_px)
    seconds["undistort"] = time.perf_counter() - t

    camera = next(iter(model.cameras.values()))
    figures: dict[str, Any] = {
        "frames_total": total,
        "frames_registered": registered,
        "reprojection_error_px": round(float(model.compute_mean_reprojection_error()), 4),
        "points": model.num_points3D(),
        "mean_track_length": round(float(model.compute_mean_track_length()), 3),
        "mapper": mapper,
        "models": n_models,
        "pairs_matched": len(near) + far_matched,
        "far_pairs_matched": far_matched,
        "far_pairs_dropped": far_dropped,
        "sequential_only": video and model_dir.parent.name != FAR_MODELS,
        "pose_jumps": len(jumps),
        "camera": {"model": camera.model_name, "width": camera.width, "height": camera.height,
                   "params": [round(float(p), 6) for p in camera.params]},
        **undistortion,
    }
    if warnings:
        figures["warnings"] = warnings
    record = update_capture_json(data_dir, seconds=seconds, pose_options=opts.model_dump(), **figures)
    write_json_atomic(work / "poses.json", {"model_dir": str(model_dir.relative_to(work)), **figures,
                                            "seconds": {k: round(v, 3) for k, v in seconds.items()}})
    progress(1.0, f"registered {registered}/{total} frames, {figures['reprojection_error_px']:.2f} px",
             frames_registered=registered, frames_total=total)
    return {**figures, "seconds": record["seconds"]}
