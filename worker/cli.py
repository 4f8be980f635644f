"""Command-line commands of the worker layer: ``neudf capture``, ``neudf reconstruct``, ``neudf worker``.

The ``neudf`` entry point (web/cli.py, through service/cli.py) builds one typer app from this module's
:func:`register` and those of the other layers; ``python -m worker.cli`` runs the core's and this layer's
commands without the service (the embedded worker of `neudf serve` starts as ``python -m worker.cli
worker``). Bad input ends with a one-line reason on stderr and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from neudf_core.cli import fail, progress_bar
from neudf_core.decimate import DEFAULT_FACES
from neudf_core.texture import DEFAULT_TEXTURE_SIZE
from worker.pipeline import DEFAULT_JOB_MINUTES, DEFAULT_TRAIN_MINUTES, MIN_TRAIN_MINUTES

if TYPE_CHECKING:  # the commands import what they need when they run: `neudf --help` stays fast
    from worker.settings import QueueSettings

__all__ = ["register", "capture", "reconstruct", "worker", "main"]

MESH_SUFFIXES = (".glb", ".ply", ".obj", ".usdz")


def capture(
    video: Annotated[Path, typer.Argument(help="The walk-around video (MP4, MOV, MKV, ...).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="The dataset folder to write (NeuS layout).")],
    frames: Annotated[int, typer.Option("--frames", min=8, max=2000, help="Frames to pick from the video.")] = 200,
    max_size: Annotated[int, typer.Option("--max-size", min=64, max=8192, help="Longest side of the frames, px.")] = 1600,
    camera_model: Annotated[str, typer.Option(help="COLMAP camera model: OPENCV, SIMPLE_RADIAL, RADIAL, PINHOLE.")] = "OPENCV",
    fresh: Annotated[bool, typer.Option("--fresh", help="Recompute every stage instead of resuming.")] = False,
    threads: Annotated[int, typer.Option("--threads", min=-1, help="pycolmap threads (-1: all cores; 1: slower, "
                                         "but repeated runs agree more closely).")] = -1,
) -> None:
    """Video -> frames, pycolmap poses, normalisation: DATA/image, cameras_sphere.npz, frames.json, capture.json, cameras.png."""
    from pydantic import ValidationError

    from worker.capture.poses import PoseOptions
    from worker.capture.run import run_capture
    from worker.errors import StageError

    if not video.is_file():
        fail(f"no such video: {video}", 2)
    try:
        pose_options = PoseOptions(camera_model=camera_model.upper(), num_threads=threads)
    except ValidationError:
        fail(f"unknown camera model {camera_model!r}: use OPENCV, SIMPLE_RADIAL, RADIAL or PINHOLE", 2)

    try:
        with progress_bar("capture") as report:
            record = run_capture(video, out, n_frames=frames, max_size=max_size, pose_options=pose_options,
                                 resume=not fresh, progress=report)
    except StageError as exc:
        fail(f"{exc.stage}: {exc.message}", 1)
    except KeyboardInterrupt:
        fail(f"interrupted; run the same command again to resume in {out}", 130)
    seconds = sum(record.get("seconds", {}).values())
    typer.echo(
        f"{out}: {record['frames_registered']}/{record['frames_total']} frames registered, "
        f"reprojection error {record['reprojection_error_px']:.2f} px, {record.get('points', 0)} points, "
        f"{seconds:.0f} s"
    )
    for warning in record.get("warnings", []) + record.get("scene", {}).get("warnings", []):
        typer.echo(f"warning: {warning}", err=True)


def reconstruct(
    video: Annotated[Path, typer.Argument(help="The video (MP4, MOV, ...).")],
    out: Annotated[Path, typer.Option("--out", help="The mesh to write: .glb, .obj (with .mtl and .png), .usdz "
                                                    "(iOS AR) or .ply (vertex colours).")],
    preset: Annotated[str | None, typer.Option(help="Training preset: quick, fast, gpu or paper (default: quick on "
                                                    "a CPU, gpu on CUDA).")] = None,
    minutes: Annotated[float | None, typer.Option(help=f"Training budget in minutes (default, unless --iters is given: "
                                                      f"what the capture left of {DEFAULT_JOB_MINUTES:g} minutes end to end, "
                                                      f"{MIN_TRAIN_MINUTES:g}-{DEFAULT_TRAIN_MINUTES:g}); "
                                                      "training stops at it or at --iters, whichever comes first.")] = None,
    iters: Annotated[int | None, typer.Option(help="Training iterations (default: as many as --minutes allows).")] = None,
    weight: Annotated[str, typer.Option(help="Weight of the volume rendering: neudf, or the closed-surface "
                                             "baselines neus_sdf and neus_abs.")] = "neudf",
    frames: Annotated[int | None, typer.Option(help="Frames to pick from the video.")] = None,
    work_dir: Annotated[Path | None, typer.Option(help="Stage outputs (kept; run again to resume). Default: OUT's name + '.work'.")] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    mesh_resolution: Annotated[int | None, typer.Option(help="Grid resolution of mesh extraction.")] = None,
    mesh_method: Annotated[str | None, typer.Option(help="meshudf, spsr or mc.")] = None,
    mesh_threshold: Annotated[float | None, typer.Option(help="UDF level under which a face counts as surface.")] = None,
    mesh_min_faces: Annotated[int | None, typer.Option(help="Connected pieces with fewer faces are dropped (default 32).")] = None,
    mesh_min_seen: Annotated[float | None, typer.Option(help="Share of the cameras that must see a face (default 0.15; 0 keeps every face).")] = None,
    mesh_lid_spread: Annotated[float | None, typer.Option(help="Cut seen patches whose colour the frames scatter about by more than this as lids over openings (default 0.2; 0 keeps them).")] = None,
    faces: Annotated[int, typer.Option(help="Faces of the mesh written (quadric decimation, open boundaries kept); "
                                            "0 keeps every face.")] = DEFAULT_FACES,
    texture_size: Annotated[int, typer.Option(help="Side of the texture baked from the frames, px; 0: vertex "
                                                   "colours only.")] = DEFAULT_TEXTURE_SIZE,
) -> None:
    """Run the whole pipeline on a video without a service: frames, poses, training, mesh, export."""
    from pydantic import ValidationError

    from neudf_core.device import resolve_device
    from worker.capture.frames import probe_video
    from worker.pipeline import JobOptions, StageError, run_pipeline

    if not video.is_file():
        fail(f"no such video: {video}")
    if out.suffix.lower() not in MESH_SUFFIXES:
        fail(f"--out must end in {', '.join(MESH_SUFFIXES)}, got {out.name}")
    try:
        probe_video(video)
    except StageError as exc:
        fail(f"{video.name}: {exc.message}")
    try:
        options = JobOptions(preset=preset, minutes=minutes, iters=iters, weight=weight, frames=frames, mesh_resolution=mesh_resolution,
                             mesh_method=mesh_method, mesh_threshold=mesh_threshold,
                             mesh_min_faces=mesh_min_faces, mesh_min_seen=mesh_min_seen,
                             mesh_lid_spread=mesh_lid_spread, faces=faces,
                             texture_size=texture_size)
    except ValidationError as exc:
        first = exc.errors()[0]
        fail(f"{'.'.join(map(str, first['loc']))}: {first['msg']}")
    device = resolve_device(device)
    work = work_dir or out.with_name(out.stem + ".work")
    job_dir = work.resolve()
    input_dir = job_dir / "input"
    input_dir.mkdir(parents=True, exist_ok=True)
    staged = input_dir / f"video{video.suffix.lower() or '.bin'}"
    if not staged.exists() or staged.stat().st_size != video.stat().st_size:
        shutil.copyfile(video, staged)
    try:
        # The bar's time left is the job's own ETA (the running stage's estimate plus the expected time of the
        # later stages), not an extrapolation of the overall fraction, which the stages' uneven weights skew.
        with progress_bar("start") as report:
            run_pipeline(staged, job_dir, options, report, device=device)
    except StageError as exc:
        fail(f"{exc.stage}: {exc.message}", 1)
    except KeyboardInterrupt:
        fail(f"interrupted; run the same command again to resume from {work}", 130)
    _write_mesh(job_dir / "export", out)
    typer.echo(f"wrote {out} (stage outputs in {work})", err=True)


def _write_mesh(export_dir: Path, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    suffix = out.suffix.lower()
    if suffix != ".obj":
        shutil.copyfile(export_dir / f"mesh{suffix}", out)
        return
    import trimesh

    from neudf_core.export import export_mesh

    # written again rather than copied: the OBJ names its .mtl and the .mtl its .png, after OUT's name
    export_mesh(trimesh.load(export_dir / "mesh.obj", process=False, force="mesh"), out)


def load_settings(cls: type[QueueSettings] | None = None, **overrides: Any) -> QueueSettings:
    """Settings of class ``cls`` (default ``QueueSettings``) from the environment and the options that were given;
    a bad value ends the command with its name and reason."""
    from pydantic import ValidationError

    from worker.settings import QueueSettings

    try:
        return (cls or QueueSettings)(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        first = exc.errors()[0]
        fail(f"bad setting {'.'.join(map(str, first['loc']))}: {first['msg']}")


def worker(
    concurrency: Annotated[int | None, typer.Option(help="Jobs at once (NEUDF_WORKER_CONCURRENCY; one per GPU).")] = None,
    loglevel: Annotated[str, typer.Option(help="Celery log level.")] = "INFO",
) -> None:
    """Start a Celery worker that runs jobs from the broker in NEUDF_BROKER_URL (scaled deployments)."""
    import socket

    from worker.celery_app import create_celery, run_worker
    from worker.tasks import register_tasks

    app = create_celery(load_settings(worker_concurrency=concurrency))
    register_tasks(app)
    # A unique node name per process, so several workers on one host stay apart in the store.
    run_worker(app, loglevel=loglevel, hostname=f"neudf-{os.getpid()}@{socket.gethostname()}")


def register(app: typer.Typer) -> None:
    """Add the worker layer's commands to ``app``."""
    app.command("capture")(capture)
    app.command()(reconstruct)
    app.command()(worker)


def main() -> None:
    """``python -m worker.cli``: the core's and the worker layer's commands (everything but `neudf serve`)."""
    import neudf_core.cli

    app = typer.Typer(name="neudf", help="NeUDF without the service: capture, reconstruct, train, mesh, eval and "
                      "the job worker.", no_args_is_help=True, pretty_exceptions_enable=False, add_completion=False)
    neudf_core.cli.register(app)
    register(app)
    app(prog_name="neudf")


if __name__ == "__main__":
    sys.exit(main())
