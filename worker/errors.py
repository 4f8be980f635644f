"""The one error a pipeline stage raises for a problem the user can act on.

A stage that cannot go on raises :class:`StageError` with the stage's name and a message written for the
person who uploaded the video ("only 12 of 200 frames registered: film slower, with more texture"), never a
traceback. ``kind`` is a short machine-readable code the service maps to an HTTP status (``not_video`` is
415, the rest 422) and tests assert on.
"""

from __future__ import annotations

__all__ = ["StageError"]


class StageError(Exception):
    """A stage failed for a reason the user can understand (bad input, a capture that cannot be posed).

    Attributes:
        stage: the stage that failed ("frames", "poses", "scene", ...).
        message: one user-facing sentence naming the problem.
        kind: a short code for the problem (``not_video``, ``empty``, ``truncated``, ``too_few_frames``,
            ``resolution``, ``duration``, ``registration``, ...); ``error`` when nothing more specific fits.
    """

    def __init__(self, stage: str, message: str, kind: str = "error") -> None:
        super().__init__(f"{stage}: {message}")
        self.stage = stage
        self.message = message
        self.kind = kind

    def __reduce__(self):  # keep stage/message/kind when pickled across processes (Celery, pools)
        return (type(self), (self.stage, self.message, self.kind))
