"""The `neudf` entry point (``pyproject.toml``: ``neudf = "web.cli:main"``).

It lives in the top layer because `neudf serve` is where the app is assembled: the service's FastAPI app
with this layer's page mounted onto it. The service never imports the page; this module hands
``web.page.mount_page`` to the service's command line (``service.cli.build_app``), which holds every other
command.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fastapi import FastAPI

__all__ = ["main"]


def mount_page(app: FastAPI) -> None:
    """``web.page.mount_page``, imported when `neudf serve` runs: gradio stays out of the other commands."""
    from web.page import mount_page as mount

    mount(app)


def main() -> None:
    from service.cli import build_app

    build_app(mount_page)(prog_name="neudf")


if __name__ == "__main__":
    sys.exit(main())
