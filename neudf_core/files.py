"""Files written whole, and files placed without a second copy: the small file chores every layer shares.

A reader (the service handing out an artifact, a resumed job checking a stage's outputs) must see a file
whole or not at all: :func:`atomic_write` gives the writer a temporary name beside the target and moves
it into place (``os.replace``, atomic on one file system) only once the writer is done.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["atomic_write", "write_json_atomic", "link_or_copy"]


@contextlib.contextmanager
def atomic_write(path: str | Path, tmp: str | Path | None = None) -> Iterator[Path]:
    """Yield a temporary path to write instead of ``path``; it replaces ``path`` when the block ends.

    The temporary file is ``tmp`` if given, else ``<stem>.tmp<suffix>`` beside ``path`` (the suffix kept,
    so writers that pick their format from it, np.savez and matplotlib, write the right one). Pass ``tmp``
    when a reader globs for the suffix (``*.png``) and must not find a half-written file. If the block
    raises, the temporary file is removed and ``path`` stays as it was.
    """
    path = Path(path)
    tmp = Path(tmp) if tmp is not None else path.with_name(f"{path.stem}.tmp{path.suffix}")
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def write_json_atomic(path: str | Path, value: Any) -> None:
    """Write ``value`` as indented JSON, whole or not at all (its folder is made if missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(value, indent=2))


def link_or_copy(src: str | Path, dst: str | Path) -> None:
    """Hard-link ``src`` to ``dst`` (same file system: no second copy of 200 frames), else copy it."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
