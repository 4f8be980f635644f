"""A job as `neudf reconstruct` runs it: the training budget in minutes, its ETA, and the defaults by device."""

from __future__ import annotations

import json

import pytest

from neudf_core.config import available_presets, default_preset
from neudf_core.trainer import BUDGET_MAX_ITERS
from worker.pipeline import (AFTER_TRAIN_MINUTES, DEFAULT_JOB_MINUTES, DEFAULT_TRAIN_MINUTES, MIN_TRAIN_MINUTES,
                             JobContext, JobOptions, run_pipeline)

# The plumbing options of tests/conftest.py's QUICK_JOB, without its iteration count: the budget alone stops.
TINY = {"frames": 30, "mesh_resolution": 64, "mesh_threshold": 0.25, "mesh_min_faces": 1, "mesh_min_seen": 0.0,
        "texture_size": 256}


def test_defaults_follow_the_device(tmp_path):
    assert default_preset("cpu") == "quick"
    assert default_preset("cuda") == default_preset("cuda:1") == "gpu"
    assert {"quick", "gpu"} <= set(available_presets())

    def context(device, **options):
        return JobContext(tmp_path, tmp_path / "v.mp4", JobOptions(**options), device)

    assert context("cpu").preset == "quick" and context("cuda:0").preset == "gpu"
    assert context("cuda:0", preset="quick").preset == "quick"  # a named preset wins over the device's
    # With nothing set a job trains for the default budget; iterations alone mean no budget.
    assert context("cpu").train_minutes == DEFAULT_TRAIN_MINUTES
    assert context("cpu", iters=50).train_minutes is None
    assert context("cpu", iters=50, minutes=2).train_minutes == 2
    # ...what a slow capture left of the job's minutes, within bounds; a budget of the user's stays as it is
    (tmp_path / "stages").mkdir()
    for name, minutes in (("frames", 0.5), ("poses", 11.0), ("scene", 0.1)):
        (tmp_path / "stages" / f"{name}.json").write_text(json.dumps({"seconds": 60 * minutes}))
    assert context("cpu").train_minutes == pytest.approx(DEFAULT_JOB_MINUTES - AFTER_TRAIN_MINUTES - 11.6)
    assert context("cpu", minutes=9).train_minutes == 9
    (tmp_path / "stages" / "poses.json").write_text(json.dumps({"seconds": 60 * 16.0}))
    assert context("cpu").train_minutes == MIN_TRAIN_MINUTES


def test_job_minutes_bound_training_and_the_metrics_say_so(tiny_video, tmp_path):
    job = tmp_path / "job"
    minutes = 0.05  # 3 s of training: a few dozen quick iterations on 2 cores
    reports = []
    metrics = run_pipeline(tiny_video, job, JobOptions(minutes=minutes, **TINY),
                           lambda f, m="", **info: reports.append((f, m, info)), device="cpu")

    train = json.loads((job / "stages" / "train.json").read_text())
    assert train["metrics"]["stopped_by"] == "budget"
    assert train["metrics"]["minutes"] == minutes
    assert train["metrics"]["preset"] == "quick"
    assert train["metrics"]["train_s"] >= minutes * 60
    assert 0 < train["metrics"]["iters"] < BUDGET_MAX_ITERS
    assert (job / "export" / "mesh.glb").is_file() and metrics["mesh_faces"] > 0, metrics

    # The job announced its plan first, with the budget as the training stage's share of the ETA ...
    plans = {info["stage"]: info["eta_s"] for _, _, info in reports if info.get("event") == "plan"}
    assert list(plans) == ["frames", "poses", "scene", "train", "mesh", "export"]
    assert plans["train"] == pytest.approx(minutes * 60)
    # ... and every progress report carries the time left for the whole job, which ends at zero.
    etas = [info["job_eta_s"] for _, _, info in reports if "job_eta_s" in info]
    assert etas and all(e >= 0 for e in etas) and etas[-1] == pytest.approx(0, abs=1e-6)
    in_training = [info for _, _, info in reports if info.get("stage") == "train" and "job_eta_s" in info]
    assert in_training and all(i["job_eta_s"] >= i["eta_s"] for i in in_training)
