"""The `neudf` command: serve, worker and reconstruct here, plus the commands of the other layers.

``main()`` builds one typer app from ``neudf_core.cli.register`` (train, mesh, eval),
``worker.cli.register`` (capture) and ``register`` below.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:  # the commands import what they need when they run: `neudf --help` stays fast
    from service.settings import Settings
    from worker.pipeline import JobOptions

MESH_SUFFIXES = (".glb", ".ply", ".obj")


def _fail(message: str, code: int = 2) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code)


def _settings(**overrides: Any) -> Settings:
    from pydantic import ValidationError

    from service.settings import Settings

    try:
        return Settings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        first = exc.errors()[0]
        raise _fail(f"bad setting {'.'.join(map(str, first['loc']))}: {first['msg']}") from None


def serve(
    host: Annotated[str | None, typer.Option(help="Address to listen on (NEUDF_HOST, default 127.0.0.1).")] = None,
    port: Annotated[int | None, typer.Option(help="Port (NEUDF_PORT, default 8000).")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="Where jobs, the database and the queue live (NEUDF_DATA_DIR, default ./neudf-data).")] = None,
    worker: Annotated[bool, typer.Option("--worker/--no-worker", help="Start a local worker with the API.")] = True,
) -> None:
    """Start the API, the web page and a local worker (no Redis and no GPU needed)."""
    import uvicorn

    from service.app import create_app

    settings = _settings(host=host, port=port, data_dir=data_dir, embedded_worker=worker)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    app = create_app(settings)
    typer.echo(f"neudf: page http://{settings.host}:{settings.port}/  API docs http://{settings.host}:{settings.port}/docs"
               f"  data {settings.root}", err=True)
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="info")


def worker(
    concurrency: Annotated[int | None, typer.Option(help="Jobs at once (NEUDF_WORKER_CONCURRENCY; one per GPU).")] = None,
    loglevel: Annotated[str, typer.Option(help="Celery log level.")] = "INFO",
) -> None:
    """Start a Celery worker that runs jobs from the broker in NEUDF_BROKER_URL (scaled deployments)."""
    import socket

    from worker.celery_app import create_celery, run_worker

    settings = _settings(worker_concurrency=concurrency)
    app = create_celery(settings)
    # A unique node name per process, so several workers on one host stay apart in the store.
    run_worker(app, loglevel=loglevel, hostname=f"neudf-{os.getpid()}@{socket.gethostname()}")


def reconstruct(
    video: Annotated[Path, typer.Argument(help="The video (MP4, MOV, ...).")],
    out: Annotated[Path, typer.Option("--out", help="The mesh to write: .glb, .ply or .obj.")],
    preset: Annotated[str | None, typer.Option(help="Training preset: quick, fast, gpu or paper (default: quick on "
                                                    "a CPU, gpu on CUDA).")] = None,
    minutes: Annotated[float | None, typer.Option(help="Training budget in minutes (default 10 unless --iters is given); "
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
) -> None:
    """Run the whole pipeline on a video without a service: frames, poses, training, mesh, export."""
    from pydantic import ValidationError

    from worker.pipeline import JobOptions, StageError, run_pipeline

    if not video.is_file():
        raise _fail(f"no such video: {video}")
    if out.suffix.lower() not in MESH_SUFFIXES:
        raise _fail(f"--out must end in {', '.join(MESH_SUFFIXES)}, got {out.name}")
    from worker.stages.frames import probe_video

    try:
        probe_video(video)
    except StageError as exc:
        raise _fail(f"{video.name}: {exc.message}") from None
    try:
        options = JobOptions(preset=preset, minutes=minutes, iters=iters, weight=weight, frames=frames, mesh_resolution=mesh_resolution,
                             mesh_method=mesh_method, mesh_threshold=mesh_threshold,
                             mesh_min_faces=mesh_min_faces, mesh_min_seen=mesh_min_seen)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise _fail(f"{'.'.join(map(str, first['loc']))}: {first['msg']}") from None
    if device == "auto":
        import torch

        device = "cuda" if torch.cuda.is_available() else "cpu"
    work = work_dir or out.with_name(out.stem + ".work")
    job_dir = work.resolve()
    input_dir = job_dir / "input"
    input_dir.mkdir(parents=True, exist_ok=True)
    staged = input_dir / f"video{video.suffix.lower() or '.bin'}"
    if not staged.exists() or staged.stat().st_size != video.stat().st_size:
        shutil.copyfile(video, staged)
    try:
        _run_with_bar(run_pipeline, staged, job_dir, options, device)
    except StageError as exc:
        raise _fail(f"{exc.stage}: {exc.message}", code=1) from None
    except KeyboardInterrupt:
        raise _fail(f"interrupted; run the same command again to resume from {work}", code=130) from None
    _write_mesh(job_dir / "export", out)
    typer.echo(f"wrote {out} (stage outputs in {work})", err=True)


def _run_with_bar(run_pipeline: Callable[..., Any], video: Path, job_dir: Path, options: JobOptions,
                  device: str) -> None:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    # The job's own ETA (the running stage's estimate plus the expected time of the later stages), not
    # rich's extrapolation of the overall fraction, which the stages' uneven weights would skew.
    columns = (TextColumn("[bold]{task.fields[stage]:<7}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
               TimeElapsedColumn(), TextColumn("ETA {task.fields[eta]}"), TextColumn("{task.description}"))
    with Progress(*columns, transient=False) as bar:
        task = bar.add_task("", total=1.0, stage="start", eta="-")

        def report(fraction: float, message: str = "", **info: Any) -> None:
            if info.get("event") == "plan":
                return
            eta = info.get("job_eta_s")
            bar.update(task, completed=fraction, description=message[:60], stage=info.get("stage", ""),
                       eta=f"{int(eta) // 60}:{int(eta) % 60:02d}" if eta is not None else "-")

        run_pipeline(video, job_dir, options, report, device=device)


def _write_mesh(export_dir: Path, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    suffix = out.suffix.lower()
    if suffix in (".glb", ".ply"):
        shutil.copyfile(export_dir / f"mesh{suffix}", out)
        return
    import trimesh

    trimesh.load(export_dir / "mesh.ply", process=False, force="mesh").export(out)


def register(app: typer.Typer) -> None:
    app.command()(serve)
    app.command()(worker)
    app.command()(reconstruct)


def build_app() -> typer.Typer:
    import neudf_core.cli
    import worker.cli

    app = typer.Typer(name="neudf", help="NeUDF: phone video in, open-surface mesh out.", no_args_is_help=True,
                      pretty_exceptions_enable=False, add_completion=False)
    neudf_core.cli.register(app)
    worker.cli.register(app)
    register(app)
    return app


def main() -> None:
    build_app()()


if __name__ == "__main__":
    sys.exit(main())
