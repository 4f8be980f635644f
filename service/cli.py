"""`neudf serve`, and the one `neudf` typer app of every layer's commands.

:func:`build_app` adds ``neudf_core.cli.register`` (train, mesh, eval), ``worker.cli.register`` (capture,
reconstruct, worker) and `neudf serve` below. The page is not this layer's: the entry point that may import
both (``web.cli:main``) hands its ``mount_page`` in, and `neudf serve` mounts it onto the app it assembles.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:  # the commands import what they need when they run: `neudf --help` stays fast
    from fastapi import FastAPI

__all__ = ["build_app", "serve_command"]

PageMount = Callable[["FastAPI"], None]


def serve_command(mount_page: PageMount | None) -> Callable[..., None]:
    """The `neudf serve` command; ``mount_page(app)`` adds the web page to the app it serves."""

    def serve(
        host: Annotated[str | None, typer.Option(help="Address to listen on (NEUDF_HOST, default 127.0.0.1).")] = None,
        port: Annotated[int | None, typer.Option(help="Port (NEUDF_PORT, default 8000).")] = None,
        data_dir: Annotated[Path | None, typer.Option(help="Where jobs, the database and the queue live (NEUDF_DATA_DIR, default ./neudf-data).")] = None,
        worker: Annotated[bool, typer.Option("--worker/--no-worker", help="Start a local worker with the API.")] = True,
    ) -> None:
        """Start the API, the web page and a local worker (no Redis and no GPU needed)."""
        import uvicorn

        from service.app import create_app
        from service.settings import Settings
        from worker.cli import load_settings

        settings = load_settings(Settings, host=host, port=port, data_dir=data_dir, embedded_worker=worker)
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
        app = create_app(settings)
        if mount_page is not None:
            mount_page(app)
        typer.echo(f"neudf: page http://{settings.host}:{settings.port}/  API docs http://{settings.host}:{settings.port}/docs"
                   f"  data {settings.root}", err=True)
        uvicorn.run(app, host=settings.host, port=settings.port, log_level="info")

    return serve


def build_app(mount_page: PageMount | None = None) -> typer.Typer:
    """The `neudf` app: every layer's commands; `neudf serve` with the page when ``mount_page`` is given."""
    import neudf_core.cli
    import worker.cli

    app = typer.Typer(name="neudf", help="NeUDF: phone video in, open-surface mesh out.", no_args_is_help=True,
                      pretty_exceptions_enable=False, add_completion=False)
    neudf_core.cli.register(app)
    worker.cli.register(app)
    app.command("serve")(serve_command(mount_page))
    return app
