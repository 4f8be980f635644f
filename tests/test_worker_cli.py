"""The worker layer's commands (``worker/cli.py``): `neudf capture` and `neudf reconstruct` refuse bad input with a
one-line reason and an exit code, never a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from tests.helpers import ROOT, worker_cli_app


def test_cli_rejects_bad_input_with_one_line(small_videos):
    result = CliRunner().invoke(worker_cli_app(), ["capture", str(small_videos["notes"]), "--out", "unused"])
    assert result.exit_code != 0
    assert "Traceback" not in result.output
    error_lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(error_lines) == 1 and "not a video" in error_lines[0]


def test_reconstruct_refuses_bad_input_in_one_line(tmp_path: Path) -> None:
    """`neudf reconstruct` (the pipeline without a service): bad input is a one-line reason and exit code 2."""
    not_video = tmp_path / "notes.mp4"
    not_video.write_text("not a video\n")
    for args, words in ((["reconstruct", str(tmp_path / "missing.mp4"), "--out", "m.glb"], "no such video"),
                        (["reconstruct", str(not_video), "--out", "m.glb"], "not a video"),
                        (["reconstruct", str(not_video), "--out", "m.stl"], "--out must end in")):
        result = subprocess.run([sys.executable, "-m", "web.cli", *args], cwd=tmp_path, capture_output=True,
                                text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert result.returncode == 2, result.stderr
        assert words in result.stderr and "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "m.work").exists()  # nothing started for a refused video
