"""The records the capture stages share: ``DATA/capture.json`` (what each stage found and took) and
``DATA/frames.json`` (one entry per image, CONTRACT.md). Both are written whole (``write_json_atomic``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from neudf_core.files import write_json_atomic

__all__ = ["update_capture_json", "read_frames_json"]


def update_capture_json(data_dir: str | Path, seconds: dict[str, float] | None = None, drop: tuple[str, ...] = (),
                        **fields: Any) -> dict:
    """Merge ``fields`` (and per-stage ``seconds``) into ``DATA/capture.json``, removing the keys in ``drop``."""
    path = Path(data_dir) / "capture.json"
    record: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {}
    for key in drop:
        record.pop(key, None)
    record.update(fields)
    if seconds:
        record["seconds"] = {**record.get("seconds", {}), **{k: round(v, 3) for k, v in seconds.items()}}
    write_json_atomic(path, record)
    return record


def read_frames_json(data_dir: str | Path) -> list[dict[str, Any]]:
    """The entries of ``DATA/frames.json`` (one per image, in image order)."""
    return json.loads((Path(data_dir) / "frames.json").read_text())
