"""Command-line commands of the core: ``neudf train``, ``neudf mesh``, ``neudf eval``; and what every layer's
commands share: :func:`fail` (a one-line reason on stderr, a non-zero exit code) and :func:`progress_bar`.

The ``neudf`` entry point (web/cli.py, through service/cli.py) builds one typer app from this module's
:func:`register` and those of the worker and service layers. Every command turns bad input into a one-line
reason on stderr and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Iterator
from datetime import timedelta
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    Progress,
    ProgressColumn,
    Task,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

from neudf_core.decimate import DEFAULT_FACES, MIN_FACES
from neudf_core.meshing.lids import SPREAD_LID
from neudf_core.progress import ProgressFn
from neudf_core.texture import DEFAULT_TEXTURE_SIZE, MAX_TEXTURE_SIZE, MIN_TEXTURE_SIZE

err_console = Console(stderr=True)


class Device(str, Enum):
    cpu = "cpu"
    cuda = "cuda"


class MeshMethod(str, Enum):
    meshudf = "meshudf"
    spsr = "spsr"
    mc = "mc"


def fail(message: str, code: int = 2) -> NoReturn:
    """Print ``error: <message>`` as one line on stderr and exit with ``code`` (2: bad input)."""
    err_console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


# Report fields that steer the bar (or are too big for it) rather than describe the work.
_NOT_FIGURES = frozenset({"stage", "stage_progress", "event", "eta_s", "job_eta_s", "metrics", "seconds", "skipped"})


class _TimeLeft(ProgressColumn):
    """The work's own estimate of the time left when it reports one (``job_eta_s``, else ``eta_s``), else rich's."""

    def __init__(self) -> None:
        super().__init__()
        self._extrapolated = TimeRemainingColumn()

    def render(self, task: Task) -> Text:
        eta = task.fields.get("eta")
        if eta is None:
            return self._extrapolated.render(task)
        return Text(str(timedelta(seconds=max(int(eta), 0))), style="progress.remaining")


@contextlib.contextmanager
def progress_bar(description: str) -> Iterator[ProgressFn]:
    """The one progress bar of the ``neudf`` commands, on stderr, driven by a :class:`ProgressFn`.

    Shows the stage being worked on (the report's ``stage``, else ``description``), the fraction done, the
    time spent and the time left (the work's own estimate when it gives one), and the message with the
    report's figures (loss, psnr, ...). Planning reports (``event="plan"``) move nothing.
    """
    columns = (TextColumn("[bold]{task.fields[stage]:<8}"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn(),
               _TimeLeft(), TextColumn("{task.fields[info]}"))
    with Progress(*columns, console=err_console, transient=False) as bar:
        task = bar.add_task(description, total=1.0, stage=description, eta=None, info="")

        def report(fraction: float, message: str = "", **info: Any) -> None:
            if info.get("event") == "plan":
                return
            stage = info.get("stage") or description
            if message.startswith(f"{stage}: "):  # the stage column names it already
                message = message[len(stage) + 2:]
            figures = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                               for k, v in info.items() if k not in _NOT_FIGURES)
            eta = info.get("job_eta_s", info.get("eta_s"))
            bar.update(task, completed=min(max(fraction, 0.0), 1.0), stage=stage, eta=eta,
                       info=escape(f"{message} {figures}".strip()[:80]))

        yield report


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn the errors a user can cause (bad paths, bad files, bad options) into a clean exit."""
    try:
        yield
    except (ValueError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        fail(str(exc) or exc.__class__.__name__)
    except KeyboardInterrupt:
        fail("interrupted", code=130)


def train_command(
    data: Annotated[Path, typer.Argument(help="dataset folder in the NeuS layout (image/, cameras_sphere.npz)")],
    out: Annotated[Path, typer.Option("--out", help="run folder: config.json, checkpoints/, metrics.jsonl, validation/")],
    preset: Annotated[str | None, typer.Option(help="quick (CPU-sized), fast, gpu, paper (the paper's settings, hours "
                                                    "on a GPU); default quick on cpu, gpu on cuda")] = None,
    minutes: Annotated[float | None, typer.Option(help="training budget in minutes; schedules end with it")] = None,
    iters: Annotated[int | None, typer.Option(help="iterations (default: the preset's, or as many as --minutes "
                                                   "allows); schedule shrinks to fit")] = None,
    device: Annotated[Device, typer.Option(help="cpu or cuda")] = Device.cpu,
    masks: Annotated[bool, typer.Option("--masks/--no-masks", help="use mask/*.png (BCE loss, no background model)")] = False,
    white_background: Annotated[bool, typer.Option(help="images have a plain white background (no NeRF++)")] = False,
    weight: Annotated[str, typer.Option(help="rendering weight: neudf, neus_abs (naive baseline), neus_sdf")] = "neudf",
) -> None:
    """Train NeUDF on a dataset; resumes when OUT already holds a run with the same options."""
    from neudf_core.trainer import train

    overrides: dict[str, Any] = {"renderer": {"weight": weight}}
    if masks:
        overrides["data"] = {"use_masks": True}
        overrides["loss"] = {"mask_weight": 0.1}
    if white_background:
        overrides.setdefault("data", {})["white_background"] = True
    with user_errors(), progress_bar("training") as report:
        result = train(data, out, preset=preset, iters=iters, minutes=minutes, device=device.value, progress=report,
                       overrides=overrides)
    typer.echo(json.dumps(result))


def mesh_command(
    run: Annotated[Path, typer.Argument(help="a run folder written by `neudf train`")],
    out: Annotated[Path, typer.Option("--out", help="mesh file: .glb, .ply, .obj or .usdz")],
    method: Annotated[MeshMethod, typer.Option(help="meshudf (sheets, default), spsr (masked Poisson), mc (signed fields)")] = MeshMethod.meshudf,
    resolution: Annotated[int, typer.Option(help="grid cells per axis over the unit sphere's box")] = 256,
    threshold: Annotated[float | None, typer.Option(help="UDF value counted as surface (default: per method)")] = None,
    views: Annotated[Path | None, typer.Option(help="the run's dataset folder: drop faces its cameras do not see")] = None,
    min_seen: Annotated[float, typer.Option(help="with --views: the share of cameras that must see a face")] = 0.15,
    lid_spread: Annotated[float, typer.Option(help="with --views: cut seen patches whose colour the frames "
                                                   "scatter about by more than this as lids over openings (0 "
                                                   "keeps them)")] = SPREAD_LID,
    faces: Annotated[int, typer.Option(help=f"faces of the mesh written (quadric decimation, open boundaries kept; "
                                            f"default {DEFAULT_FACES:,}); 0 keeps every face")] = DEFAULT_FACES,
    texture_size: Annotated[int | None, typer.Option(help=f"with --views: side of the texture baked from the frames, "
                                                          f"px (default {DEFAULT_TEXTURE_SIZE}); 0: vertex colours "
                                                          "only")] = None,
    device: Annotated[Device, typer.Option(help="cpu or cuda")] = Device.cpu,
) -> None:
    """Extract the open mesh from a trained run: vertex colours, or (with --views) a texture from the frames.

    A textured .obj comes with its .mtl and .png beside it; .usdz is for iOS AR Quick Look."""
    from neudf_core.extract import mesh_run

    if resolution < 16 or resolution > 2048:
        fail(f"--resolution must be between 16 and 2048, got {resolution}")
    if not 0.0 < min_seen <= 1.0:
        fail(f"--min-seen is a share of the cameras, in (0, 1], got {min_seen}")
    if lid_spread < 0:
        fail(f"--lid-spread is a colour distance, 0 or more, got {lid_spread}")
    if faces < 0 or 0 < faces < MIN_FACES:
        fail(f"--faces must be 0 (every face) or at least {MIN_FACES}, got {faces}")
    if texture_size is not None and texture_size > 0 and views is None:
        fail("--texture-size needs --views DATA: the texture is baked from the dataset's frames")
    if texture_size is None:
        texture_size = DEFAULT_TEXTURE_SIZE if views is not None else 0
    if not (texture_size == 0 or MIN_TEXTURE_SIZE <= texture_size <= MAX_TEXTURE_SIZE):
        fail(f"--texture-size must be 0 (vertex colours) or between {MIN_TEXTURE_SIZE} and {MAX_TEXTURE_SIZE}, "
             f"got {texture_size}")
    with user_errors(), progress_bar("meshing") as report:
        mesh = mesh_run(run, out, method=method.value, resolution=resolution, threshold=threshold, views=views,
                        min_seen_fraction=min_seen, lid_spread=lid_spread, faces=faces, texture_size=texture_size,
                        device=device.value, progress=report)
    typer.echo(json.dumps({"mesh": str(out), "vertices": len(mesh.vertices), "faces": len(mesh.faces),
                           "textured": texture_size > 0}))


def eval_command(
    pred: Annotated[Path, typer.Argument(help="predicted mesh")],
    gt: Annotated[Path, typer.Argument(help="ground-truth mesh; both are moved into GT's unit sphere")],
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
) -> None:
    """Compare two meshes: Chamfer distance, F-score, normal consistency, boundary loops."""
    from neudf_core.metrics import evaluate_files

    with user_errors():
        result = evaluate_files(pred, gt)
    if as_json:
        typer.echo(json.dumps(result))
        return
    for key, value in result.items():
        typer.echo(f"{key:>22}: {value:.6g}" if isinstance(value, float) else f"{key:>22}: {value}")


def register(app: typer.Typer) -> None:
    app.command("train")(train_command)
    app.command("mesh")(mesh_command)
    app.command("eval")(eval_command)


def main() -> None:  # pragma: no cover - the installed entry point is web.cli:main
    app = typer.Typer(add_completion=False, no_args_is_help=True)
    register(app)
    app(prog_name="neudf")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
