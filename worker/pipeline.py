"""One job: frames -> poses -> scene -> train -> mesh -> export, each stage a plain function on the job folder.

A stage reads files of the job folder and writes files into it. When it returns, a marker
``stages/<name>.json`` records it finished (with its seconds and figures); a stage whose marker and
outputs are both present is skipped, so a job that was interrupted resumes after its last finished stage
(training itself also resumes from its last checkpoint). When a stage has to run again, the stages after
it are cleared, since their inputs changed.

The capture stages (frames, poses, scene) live in :mod:`worker.capture`, training and meshing in
:mod:`neudf_core`, the export stage in :mod:`worker.export`; this module only strings them together.
The same ``run_pipeline`` runs from the CLI (``neudf reconstruct``), from a Celery task and from tests.
Progress goes to one callback: the overall fraction (stages weighted by their usual share of the time),
a message, and ``stage``, ``stage_progress``, ``event`` ("start", "progress", "done", "skipped") plus the
stage's own figures (loss, psnr, eta_s ...). A callback that raises ``Cancelled`` stops the job there.
Errors leave as ``StageError(stage, message)``.

Job folder::

    input/video.<ext>        the upload, never modified
    data/                    the NeuS dataset (image/, cameras_sphere.npz, frames.json, capture.json, cameras.png)
    run/                     training (config.json, checkpoints/, metrics.jsonl, validation/)
    mesh/mesh.ply            the extracted mesh
    export/                  mesh.glb, mesh.obj (+ mesh.mtl, mesh.png), mesh.usdz, mesh.ply, preview.png, loss.png,
                             frames.png, metrics.json
    stages/<name>.json       finished-stage markers
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from neudf_core.decimate import DEFAULT_FACES, MIN_FACES
from neudf_core.files import write_json_atomic
from neudf_core.progress import Cancelled, ProgressFn, null_progress, sub_progress
from neudf_core.texture import DEFAULT_TEXTURE_SIZE, MAX_TEXTURE_SIZE, MIN_TEXTURE_SIZE
from worker.errors import StageError

__all__ = ["JobOptions", "STAGES", "STAGE_NAMES", "run_pipeline", "artifact_files", "completed_stages", "StageError",
           "Cancelled"]


# The download's files (worker.export writes them; named here, where the service reads the artifact list).
EXPORT_FILES = ("mesh.glb", "mesh.obj", "mesh.mtl", "mesh.png", "mesh.usdz", "mesh.ply")

# A job with no budget of its own ends within DEFAULT_JOB_MINUTES of its start on a 2-core CPU: training takes
# what the capture left, less what meshing and export need (0.9-1.2 minutes measured), between MIN_ and
# DEFAULT_TRAIN_MINUTES. The poses stage of a 10 s video took 4.8-6.7 minutes on the last machines measured,
# SIFT and matching most of it: such a job trained 10.5-12 minutes and ended after 18.6-18.9. Machines vary
# by up to 2x; a slow capture shortens training, not the user's wait, down to MIN_TRAIN_MINUTES.
DEFAULT_JOB_MINUTES = 19.0
DEFAULT_TRAIN_MINUTES = 12.0
MIN_TRAIN_MINUTES = 5.0
AFTER_TRAIN_MINUTES = 1.5
CAPTURE_STAGES = ("frames", "poses", "scene")


class JobOptions(BaseModel):
    """What a user may choose for one job. Unset fields take each stage's own default."""

    model_config = ConfigDict(extra="forbid")

    preset: str | None = Field(None, description="Training preset (default: the device's, quick on a CPU, gpu on "
                               "CUDA); also fast, paper.")
    minutes: float | None = Field(None, gt=0, le=24 * 60, description="Training budget in minutes (default: "
                                  f"what the capture left of {DEFAULT_JOB_MINUTES:g} minutes end to end, "
                                  f"{MIN_TRAIN_MINUTES:g}-{DEFAULT_TRAIN_MINUTES:g}); training stops when it is "
                                  "spent or at iters.")
    weight: Literal["neudf", "neus_sdf", "neus_abs"] = Field(
        "neudf", description="Rendering weight: neudf (open surfaces), or a baseline: neus_sdf (closed surfaces), "
        "neus_abs (NeuS on |f|).")
    frames: int | None = Field(None, ge=8, le=300, description="Frames to pick from the video.")
    iters: int | None = Field(None, ge=1, le=2_000_000, description="Training iterations (default: the preset's).")
    max_size: int | None = Field(None, ge=64, le=1600, description="Longest side of the frames given to SIFT.")
    mesh_method: Literal["meshudf", "spsr", "mc"] | None = Field(None, description="Open-surface extraction method.")
    mesh_resolution: int | None = Field(None, ge=16, le=512, description="Grid resolution of mesh extraction.")
    mesh_threshold: float | None = Field(None, gt=0, le=1, description="UDF level (unit-sphere units) under which "
                                         "a face counts as surface; default about a voxel.")
    mesh_min_faces: int | None = Field(None, ge=1, le=1_000_000, description="Connected pieces with fewer faces are "
                                       "dropped as noise (default 32).")
    mesh_min_seen: float | None = Field(None, ge=0, le=1, description="Share of the video's cameras that must see a "
                                        "face for it to stay (default 0.15): sheets fewer views see are the "
                                        "field's guesses. 0 keeps every face.")
    mesh_lid_spread: float | None = Field(None, ge=0, le=3, description="Cut seen patches whose colour the frames "
                                          "scatter about by more than this (median L1 over RGB in 0..1; "
                                          "default 0.2) as lids over openings. 0 keeps them.")
    faces: int = Field(DEFAULT_FACES, ge=0, le=5_000_000, description="Faces of the downloaded mesh (quadric "
                       "decimation, open boundaries kept); 0 keeps every face.")
    texture_size: int = Field(DEFAULT_TEXTURE_SIZE, ge=0, le=MAX_TEXTURE_SIZE, description="Side of the texture baked from the "
                              "frames, px; 0: vertex colours only.")

    @field_validator("preset")
    @classmethod
    def _known_preset(cls, value: str | None) -> str | None:
        from neudf_core.config import available_presets

        presets = available_presets()
        if value is not None and value not in presets:
            raise ValueError(f"unknown preset {value!r}; available: {', '.join(presets)}")
        return value

    @field_validator("faces", "texture_size")
    @classmethod
    def _zero_or_enough(cls, value: int, info: ValidationInfo) -> int:
        """0 switches decimation or the texture off; a small non-zero value is a mistake, not a choice."""
        least, why = _LEAST[info.field_name]
        if 0 < value < least:
            raise ValueError(f"{why} (at least {least}); 0 turns it off")
        return value


# The least non-zero value of an option where 0 means "off", and why.
_LEAST = {"faces": (MIN_FACES, "a mesh of so few faces shows nothing"),
          "texture_size": (MIN_TEXTURE_SIZE, "a texture that small shows nothing")}


@dataclass
class JobContext:
    job_dir: Path
    video: Path
    options: JobOptions
    device: str

    @property
    def preset(self) -> str:
        from neudf_core.config import default_preset

        return self.options.preset or default_preset(self.device)

    @property
    def train_minutes(self) -> float | None:
        """The training budget: the user's; unless iterations were asked for, what the capture stages (their
        records' seconds) left of :data:`DEFAULT_JOB_MINUTES`, within the default's bounds."""
        if self.options.minutes is not None or self.options.iters is not None:
            return self.options.minutes
        spent = 0.0
        for name in CAPTURE_STAGES:
            marker = _marker(self.job_dir, name)
            if marker.is_file():
                spent += float(json.loads(marker.read_text()).get("seconds") or 0.0) / 60.0
        left = DEFAULT_JOB_MINUTES - AFTER_TRAIN_MINUTES - spent
        return round(min(DEFAULT_TRAIN_MINUTES, max(MIN_TRAIN_MINUTES, left)), 2)

    @property
    def frames(self) -> int:
        from worker.capture.frames import DEFAULT_FRAMES

        return self.options.frames or DEFAULT_FRAMES

    @property
    def data_dir(self) -> Path:
        return self.job_dir / "data"

    @property
    def run_dir(self) -> Path:
        return self.job_dir / "run"

    @property
    def mesh_file(self) -> Path:
        return self.job_dir / "mesh" / "mesh.ply"

    @property
    def export_dir(self) -> Path:
        return self.job_dir / "export"


# -- the stages: thin adapters over the functions that do the work -------------------------------------
def _frames(ctx: JobContext, progress: ProgressFn) -> dict[str, Any]:
    from worker.capture.frames import extract_frames

    kwargs: dict[str, Any] = {}
    if ctx.options.frames is not None:
        kwargs["n_frames"] = ctx.options.frames
    if ctx.options.max_size is not None:
        kwargs["max_size"] = ctx.options.max_size
    extract_frames(ctx.video, ctx.data_dir, progress=progress, **kwargs)
    from worker.export import write_frames_montage

    write_frames_montage(ctx.data_dir / "image", ctx.export_dir / "frames.png")
    return {"frames_selected": len(list((ctx.data_dir / "image").glob("*.png")))}


def _poses(ctx: JobContext, progress: ProgressFn) -> dict[str, Any]:
    from worker.capture.poses import estimate_poses

    figures = estimate_poses(ctx.data_dir, progress=progress)
    keep = ("frames_total", "frames_registered", "reprojection_error_px", "points", "warnings")
    return {k: figures[k] for k in keep if k in figures} if isinstance(figures, dict) else {}


def _scene(ctx: JobContext, progress: ProgressFn) -> dict[str, Any]:
    from worker.capture.scene import write_scene

    write_scene(ctx.data_dir, progress=progress)
    capture_file = ctx.data_dir / "capture.json"
    if capture_file.is_file():
        capture = json.loads(capture_file.read_text())
        return {k: capture[k] for k in ("frames_total", "frames_registered", "reprojection_error_px") if k in capture}
    return {}


def _train(ctx: JobContext, progress: ProgressFn) -> dict[str, Any]:
    from neudf_core.trainer import train

    minutes = ctx.train_minutes
    overrides = {"renderer": {"weight": ctx.options.weight}} if ctx.options.weight != "neudf" else None
    result = train(ctx.data_dir, ctx.run_dir, preset=ctx.preset, iters=ctx.options.iters, minutes=minutes,
                   device=ctx.device, progress=progress, overrides=overrides)
    keep = ("iters", "psnr", "loss", "iters_per_s", "images", "preset", "device", "stopped_by", "minutes", "train_s",
            "surface_points", "sight_points", "start")
    return {f"train_{k}" if k in ("loss", "psnr") else k: result[k] for k in keep if result.get(k) is not None}


def _mesh(ctx: JobContext, progress: ProgressFn) -> dict[str, Any]:
    from neudf_core.extract import mesh_run
    from neudf_core.meshing import NoSurfaceError, NothingSeenError

    kwargs: dict[str, Any] = {}
    if ctx.options.mesh_method is not None:
        kwargs["method"] = ctx.options.mesh_method
    if ctx.options.mesh_resolution is not None:
        kwargs["resolution"] = ctx.options.mesh_resolution
    if ctx.options.mesh_threshold is not None:
        kwargs["threshold"] = ctx.options.mesh_threshold
    if ctx.options.mesh_min_seen is not None:
        kwargs["min_seen_fraction"] = ctx.options.mesh_min_seen
    if ctx.options.mesh_lid_spread is not None:
        kwargs["lid_spread"] = ctx.options.mesh_lid_spread
    ctx.mesh_file.parent.mkdir(parents=True, exist_ok=True)
    try:
        if ctx.options.mesh_min_faces is not None:
            # the user's count is the whole rule: no extra share-of-the-mesh cut on top of it
            kwargs.update(min_component_faces=ctx.options.mesh_min_faces, min_component_fraction=0.0)
        # the video's cameras decide what is surface: sheets few of them see are the field's guesses
        cull = ctx.options.mesh_min_seen != 0
        mesh = mesh_run(ctx.run_dir, ctx.mesh_file, device=ctx.device, progress=progress,
                        views=ctx.data_dir if cull else None, **kwargs)
    except NoSurfaceError as exc:
        raise StageError("mesh", f"{exc}. Train longer (more minutes) or raise mesh_threshold.") from exc
    except NothingSeenError as exc:
        raise StageError("mesh", f"{exc}. Train longer or lower mesh_min_seen (0 keeps every face).") from exc
    except ValueError as exc:  # a method that does not fit the field, ...
        raise StageError("mesh", str(exc)) from exc
    info = mesh.metadata.get("meshing", {})
    keys = ("method", "resolution", "threshold", "faces_unseen", "faces_lids", "faces_on_floor", "faces_floor_skirt",
            "faces_outside")
    return {f"mesh_{k}": info[k] for k in keys if k in info}


def _export(ctx: JobContext, progress: ProgressFn) -> dict[str, Any]:
    from worker.export import export_job

    return export_job(ctx.mesh_file, ctx.data_dir, ctx.run_dir, ctx.export_dir, faces=ctx.options.faces,
                      texture_size=ctx.options.texture_size, progress=progress)


@dataclass(frozen=True)
class Stage:
    name: str
    weight: float  # share of a typical job's time, for the overall progress
    run: Callable[[JobContext, ProgressFn], dict[str, Any]]
    outputs: Callable[[JobContext], list[Path]]
    # Folders that belong to this stage alone: cleared when an earlier stage had to run again.
    owns: Callable[[JobContext], list[Path]] = field(default=lambda ctx: [])
    # The options its outputs depend on: a finished stage run with other values is run again, from scratch
    # unless only ``resumable`` ones changed (more iterations continue a run).
    keys: tuple[str, ...] = ()
    resumable: tuple[str, ...] = ()
    # Seconds this stage is expected to take on a 2-core CPU (bench/e2e.py's minutes per stage): the job's
    # ETA before the stage has measured its own speed.
    expect_s: Callable[[JobContext], float] = field(default=lambda ctx: 10.0)

    def options_used(self, ctx: JobContext) -> dict[str, Any]:
        # the preset a job trains with is the device's when the user named none
        return {k: ctx.preset if k == "preset" else getattr(ctx.options, k) for k in self.keys}


STAGES: tuple[Stage, ...] = (
    Stage("frames", 0.04, _frames, lambda c: [c.data_dir / "image", c.data_dir / "frames.json"],
          keys=("frames", "max_size"), expect_s=lambda c: 0.15 * c.frames),
    # SIFT, matching and global mapping of 720x1280 frames: 4.8-6.2 min for 200 on a 2-core CPU left to itself.
    Stage("poses", 0.16, _poses, lambda c: [c.data_dir / "colmap" / "poses.json"],
          expect_s=lambda c: 1.8 * c.frames),
    Stage("scene", 0.02, _scene, lambda c: [c.data_dir / "cameras_sphere.npz"]),
    # Not cleared when train itself runs again: the trainer resumes from its checkpoint (or goes on to more
    # iterations of the same configuration).
    Stage("train", 0.65, _train, lambda c: [c.run_dir / "config.json", c.run_dir / "metrics.jsonl"],
          owns=lambda c: [c.run_dir], keys=("preset", "weight", "iters", "minutes"), resumable=("iters", "minutes"),
          expect_s=lambda c: 60.0 * c.train_minutes if c.train_minutes else 0.25 * (c.options.iters or 4000)),
    Stage("mesh", 0.10, _mesh, lambda c: [c.mesh_file], owns=lambda c: [c.mesh_file.parent],
          keys=("mesh_method", "mesh_resolution", "mesh_threshold", "mesh_min_faces", "mesh_min_seen",
                "mesh_lid_spread"),
          expect_s=lambda c: 45.0),
    # The bake projects every frame onto the texture: about a third of a second per frame on a 2-core CPU.
    Stage("export", 0.05, _export, lambda c: [c.export_dir / "mesh.glb", c.export_dir / "metrics.json"],
          keys=("faces", "texture_size"), expect_s=lambda c: 15.0 + (0.35 * c.frames if c.options.texture_size else 0),
          owns=lambda c: [c.export_dir / n for n in (*EXPORT_FILES, "preview.png", "loss.png", "metrics.json")]),
)
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)


def _marker(job_dir: Path, name: str) -> Path:
    return job_dir / "stages" / f"{name}.json"


def _is_complete(stage: Stage, ctx: JobContext) -> bool:
    marker = _marker(ctx.job_dir, stage.name)
    if not marker.is_file() or not all(p.exists() for p in stage.outputs(ctx)):
        return False
    try:
        return json.loads(marker.read_text()).get("options", {}) == stage.options_used(ctx)
    except ValueError:
        return False


def _changed_beyond_resumable(stage: Stage, ctx: JobContext) -> bool:
    """Whether this stage last finished with other values of options its outputs cannot be resumed under."""
    marker = _marker(ctx.job_dir, stage.name)
    if not marker.is_file():
        return False  # never finished (or interrupted): its partial outputs are there to resume from
    try:
        before = json.loads(marker.read_text()).get("options", {})
    except ValueError:
        return True
    now = stage.options_used(ctx)
    return any(before.get(k) != now[k] for k in stage.keys if k not in stage.resumable)


def _write_marker(job_dir: Path, name: str, record: dict[str, Any]) -> None:
    write_json_atomic(_marker(job_dir, name), record)  # a marker is either whole or absent


def completed_stages(job_dir: Path) -> dict[str, dict[str, Any]]:
    """The finished-stage markers of a job folder, by stage name."""
    out = {}
    for name in STAGE_NAMES:
        marker = _marker(job_dir, name)
        if marker.is_file():
            out[name] = json.loads(marker.read_text())
    return out


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink()


def run_pipeline(video: str | Path, job_dir: str | Path, options: JobOptions | None = None,
                 progress: ProgressFn = null_progress, *, device: str = "cpu") -> dict[str, Any]:
    """Run (or resume) every stage of one job; returns the merged figures of all stages."""
    ctx = JobContext(Path(job_dir), Path(video), options or JobOptions(), device)
    ctx.job_dir.mkdir(parents=True, exist_ok=True)
    total_weight = sum(s.weight for s in STAGES)
    start = 0.0
    metrics: dict[str, Any] = {}
    must_run = False  # once a stage runs, every later stage runs too
    to_run = _stages_to_run(ctx)
    for stage in to_run:  # each stage's expected time, so the job's ETA holds from its first second
        progress(0.0, "", stage=stage.name, event="plan", eta_s=stage.expect_s(ctx))
    for stage in STAGES:
        end = start + stage.weight / total_weight
        if not must_run and _is_complete(stage, ctx):
            record = json.loads(_marker(ctx.job_dir, stage.name).read_text())
            metrics.update(record.get("metrics", {}))
            progress(end, f"{stage.name}: done earlier", stage=stage.name, stage_progress=1.0, event="skipped",
                     seconds=record.get("seconds"))
            start = end
            continue
        if not must_run:  # the first stage to run: later stages' outputs are stale
            for later in STAGES[STAGES.index(stage) + 1:]:
                _remove(_marker(ctx.job_dir, later.name))
                for path in later.owns(ctx):
                    _remove(path)
            must_run = True
        if _changed_beyond_resumable(stage, ctx):
            for path in stage.owns(ctx):
                _remove(path)
        _remove(_marker(ctx.job_dir, stage.name))
        later_s = sum(s.expect_s(ctx) for s in to_run[to_run.index(stage) + 1:])
        metrics.update(_run_stage(stage, ctx, progress, start, end, later_s))
        start = end
    return metrics


def _stages_to_run(ctx: JobContext) -> list[Stage]:
    """The stages a run will work through: from the first one not finished with these options to the end."""
    for i, stage in enumerate(STAGES):
        if not _is_complete(stage, ctx):
            return list(STAGES[i:])
    return []


def _stage_eta(stage: Stage, ctx: JobContext, fraction: float, elapsed: float, info: dict[str, Any]) -> float:
    """Seconds left in a running stage: its own figure if it gives one, else its speed so far, else the prior."""
    if "eta_s" in info:
        return float(info["eta_s"])
    if fraction >= 1.0:
        return 0.0
    prior = max(stage.expect_s(ctx) - elapsed, 0.0)
    if fraction < 0.1 or elapsed < 5.0:
        return prior
    return elapsed * (1.0 - fraction) / fraction


def _run_stage(stage: Stage, ctx: JobContext, progress: ProgressFn, start: float, end: float,
               later_s: float = 0.0) -> dict[str, Any]:
    progress(start, f"{stage.name}: started", stage=stage.name, stage_progress=0.0, event="start",
             eta_s=stage.expect_s(ctx), job_eta_s=stage.expect_s(ctx) + later_s)
    overall = sub_progress(progress, start, end)
    t0 = time.perf_counter()

    def report(fraction: float, message: str = "", **info: Any) -> None:
        fraction = min(max(fraction, 0.0), 1.0)
        eta = _stage_eta(stage, ctx, fraction, time.perf_counter() - t0, info)
        info = {**info, "eta_s": eta, "job_eta_s": eta + later_s}
        overall(fraction, f"{stage.name}: {message}" if message else stage.name, stage=stage.name,
                stage_progress=fraction, event="progress", **info)

    try:
        figures = stage.run(ctx, report) or {}
    except (Cancelled, StageError):
        raise
    except Exception as exc:  # anything else still names its stage
        raise StageError(stage.name, f"{type(exc).__name__}: {exc}") from exc
    seconds = round(time.perf_counter() - t0, 3)
    _write_marker(ctx.job_dir, stage.name, {"finished_at": time.time(), "seconds": seconds, "metrics": figures,
                                            "options": stage.options_used(ctx)})
    progress(end, f"{stage.name}: done in {seconds:.1f} s", stage=stage.name, stage_progress=1.0, event="done",
             seconds=seconds, metrics=figures, eta_s=0.0, job_eta_s=later_s)
    return figures


# -- what a finished (or running) job can hand out ---------------------------------------------------
def _latest(folder: Path, pattern: str) -> Path | None:
    files = sorted(folder.glob(pattern)) if folder.is_dir() else []
    return files[-1] if files else None


def artifact_files(job_dir: str | Path) -> dict[str, Path]:
    """Artifact name -> file, for the files that exist now. Names are fixed: nothing else is served."""
    job = Path(job_dir)
    candidates: dict[str, Path | None] = {
        **{name: job / "export" / name for name in EXPORT_FILES},
        "preview.png": job / "export" / "preview.png",
        "loss.png": job / "export" / "loss.png",
        "frames.png": job / "export" / "frames.png",
        "metrics.json": job / "export" / "metrics.json",
        "cameras.png": job / "data" / "cameras.png",
        "capture.json": job / "data" / "capture.json",
        "frames.json": job / "data" / "frames.json",
        "metrics.jsonl": job / "run" / "metrics.jsonl",
        "validation.png": _latest(job / "run" / "validation", "*.png"),
    }
    return {name: path for name, path in candidates.items() if path is not None and path.is_file()}
