"""Command-line commands of the worker layer: ``neudf capture``.

service/cli.py builds the one ``neudf`` app from this module's :func:`register` and those of the other
layers. Bad input ends with a one-line reason on stderr and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

__all__ = ["register", "capture"]


def _fail(message: str, code: int) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code)


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
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from worker.capture import run_capture
    from worker.errors import StageError
    from worker.stages.poses import PoseOptions

    if not video.is_file():
        raise _fail(f"no such video: {video}", 2)
    try:
        pose_options = PoseOptions(camera_model=camera_model.upper(), num_threads=threads)
    except ValidationError:
        raise _fail(f"unknown camera model {camera_model!r}: use OPENCV, SIMPLE_RADIAL, RADIAL or PINHOLE", 2) from None

    console = Console(stderr=True)
    columns = (TextColumn("[bold]{task.fields[stage]:<6}"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn(),
               TimeRemainingColumn(), TextColumn("{task.description}"))
    try:
        with Progress(*columns, console=console, transient=False) as bar:
            task = bar.add_task("", total=1.0, stage="")

            def report(fraction: float, message: str = "", **info: Any) -> None:
                text = message.split(": ", 1)[-1] if info.get("stage") else message
                bar.update(task, completed=min(max(fraction, 0.0), 1.0), description=text[:70],
                           stage=info.get("stage", ""))

            record = run_capture(video, out, n_frames=frames, max_size=max_size, pose_options=pose_options,
                                 resume=not fresh, progress=report)
    except StageError as exc:
        raise _fail(f"{exc.stage}: {exc.message}", 1) from None
    except KeyboardInterrupt:
        raise _fail(f"interrupted; run the same command again to resume in {out}", 130) from None
    seconds = sum(record.get("seconds", {}).values())
    typer.echo(
        f"{out}: {record['frames_registered']}/{record['frames_total']} frames registered, "
        f"reprojection error {record['reprojection_error_px']:.2f} px, {record.get('points', 0)} points, "
        f"{seconds:.0f} s"
    )
    for warning in record.get("warnings", []) + record.get("scene", {}).get("warnings", []):
        typer.echo(f"warning: {warning}", err=True)


def register(app: typer.Typer) -> None:
    """Add the worker layer's commands to ``app``."""
    app.command("capture")(capture)
