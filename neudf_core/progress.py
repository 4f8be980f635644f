"""Progress reporting shared by every long-running function of the project.

A long function takes a ``progress`` callable and calls it with the fraction of its own work done
(0..1), a short human message and named figures (loss, psnr, eta_s, ...). The CLI draws a progress bar
from it, the worker writes it into the job record. A caller that wants to stop the work raises
:class:`Cancelled` from inside the callback; the work stops at its next report and cleans up.
"""

from __future__ import annotations

from typing import Any, Protocol


class ProgressFn(Protocol):
    def __call__(self, fraction: float, message: str = "", **info: Any) -> None: ...


class Cancelled(Exception):
    """Raised from a progress callback to stop the running work."""


def null_progress(fraction: float, message: str = "", **info: Any) -> None:
    """The default callback: report nothing."""


def sub_progress(progress: ProgressFn, start: float, end: float) -> ProgressFn:
    """Map a sub-step's 0..1 onto [start, end] of the caller's progress."""

    def report(fraction: float, message: str = "", **info: Any) -> None:
        fraction = min(max(fraction, 0.0), 1.0)
        progress(start + (end - start) * fraction, message, **info)

    return report
