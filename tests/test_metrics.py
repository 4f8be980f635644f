"""Mesh metrics against figures computed independently on meshes with known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
import typer
from typer.testing import CliRunner

from neudf_core import synthetic
from neudf_core.metrics import (
    boundary_loops,
    evaluate,
    evaluate_files,
    load_mesh,
    unit_sphere_normalisation,
)

CONTRACT_KEYS = {"chamfer", "fscore", "normal_consistency", "boundary_loops_pred", "boundary_loops_gt"}


def unit_sheet(n: int = 16, x_max: float = 1.0) -> trimesh.Trimesh:
    """The square [0, x_max] x [0, 1] in the plane z = 0, as an n x n grid of quads."""
    u, v = np.meshgrid(np.linspace(0, x_max, n + 1), np.linspace(0, 1, n + 1))
    vertices = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], -1)
    idx = np.arange(u.size).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(vertices, faces, process=False)


def test_identical_meshes_score_perfectly():
    gt = synthetic.procedural_mesh("bowl")
    result = evaluate(gt.copy(), gt, n_samples=20_000)
    assert CONTRACT_KEYS <= set(result)
    assert result["chamfer"] < 1e-6
    assert result["fscore"] == 1.0
    assert result["normal_consistency"] > 0.999
    assert result["boundary_loops_pred"] == result["boundary_loops_gt"] == 1
    json.dumps(result)  # plain JSON types, as `neudf eval --json` prints them


def test_sheet_shifted_along_its_normal_gives_the_offset():
    # GT's unit sphere: centre (0.5, 0.5, 0), radius sqrt(0.5) -> scale sqrt(2). Two parallel sheets
    # offset by d are d apart everywhere, both ways: the Chamfer distance is d * sqrt(2), exactly.
    gt = unit_sheet()
    for offset in (0.003, 0.02):
        pred = unit_sheet()
        pred.apply_translation([0, 0, offset])
        result = evaluate(pred, gt, n_samples=20_000, fscore_threshold=0.01)
        assert result["scale"] == pytest.approx(math.sqrt(2))
        assert result["chamfer"] == pytest.approx(offset * math.sqrt(2), rel=1e-4)
        assert result["chamfer_pred_to_gt"] == pytest.approx(result["chamfer_gt_to_pred"], rel=1e-4)
        assert result["fscore"] == (1.0 if offset * math.sqrt(2) < 0.01 else 0.0)
        assert result["normal_consistency"] > 0.999  # parallel, either orientation
    flipped = unit_sheet()
    flipped.faces = flipped.faces[:, ::-1]
    assert evaluate(flipped, gt, n_samples=5_000)["normal_consistency"] > 0.999  # sign-agnostic


def test_half_a_sheet_matches_the_expected_mean_distance():
    # Prediction: the left half of GT. Predicted points lie on GT (0); GT points on the right half are
    # x - 0.5 from it, uniform on [0, 0.5]: mean 0.25 over half the samples = 0.125 (times the scale).
    gt = unit_sheet()
    half = unit_sheet(x_max=0.5)
    result = evaluate(half, gt, n_samples=40_000)
    assert result["chamfer_pred_to_gt"] < 1e-6
    expected = 0.125 * math.sqrt(2)
    assert result["chamfer_gt_to_pred"] == pytest.approx(expected, rel=0.02)  # sampling error ~0.5%
    assert result["chamfer"] == pytest.approx(expected / 2, rel=0.02)
    assert result["fscore"] == pytest.approx(2 * 1.0 * 0.51 / 1.51, abs=0.02)  # recall: left half (+ 0.01 band)


def test_metrics_are_taken_in_the_ground_truths_unit_sphere():
    gt = unit_sheet()
    pred = unit_sheet()
    pred.apply_translation([0, 0, 0.01])
    base = evaluate(pred, gt, n_samples=5_000)
    # moving and scaling both meshes together changes nothing
    transform = trimesh.transformations.compose_matrix(scale=[7.0] * 3, angles=[0.3, -0.2, 1.0],
                                                       translate=[5.0, -3.0, 2.0])
    moved = evaluate(pred.copy().apply_transform(transform), gt.copy().apply_transform(transform), n_samples=5_000)
    for key in ("chamfer", "fscore", "normal_consistency"):
        assert moved[key] == pytest.approx(base[key], rel=1e-3, abs=1e-6)
    centre, scale = unit_sphere_normalisation(gt)
    assert np.allclose(centre, [0.5, 0.5, 0.0]) and scale == pytest.approx(math.sqrt(2))


def test_boundary_loops_count_closed_loops_of_boundary_edges():
    assert boundary_loops(unit_sheet()) == 1
    assert boundary_loops(trimesh.creation.icosphere(2)) == 0
    assert boundary_loops(synthetic.procedural_mesh("sheet_with_hole")) == 2
    assert boundary_loops(synthetic.procedural_mesh("two_sheets")) == 2
    assert boundary_loops(synthetic.procedural_mesh("bowl")) == 1
    # vertices split along UV seams (as OBJ files have them) are merged by position first
    sheet = unit_sheet(4)
    split = trimesh.Trimesh(sheet.vertices[sheet.faces].reshape(-1, 3), np.arange(3 * len(sheet.faces)).reshape(-1, 3),
                            process=False)
    assert boundary_loops(split) == 1
    # a hole that touches the rim at one vertex is a notch of the rim: one opening, not two
    sheet = unit_sheet(4)
    rim_vertex = 2  # (x, y) = (0.5, 0): on the edge y = 0
    notch = [i for i, f in enumerate(sheet.faces)
             if rim_vertex in f and all(np.isin(sheet.vertices[v, 1], [0.25]) for v in f if v != rim_vertex)]
    assert len(notch) == 1
    pinched = trimesh.Trimesh(sheet.vertices, np.delete(sheet.faces, notch, axis=0), process=False)
    assert boundary_loops(pinched) == 1
    inside = (sheet.vertices[:, :2] > 0).all(1) & (sheet.vertices[:, :2] < 1).all(1)
    interior = [i for i, f in enumerate(sheet.faces) if inside[f].all()]
    holed = trimesh.Trimesh(sheet.vertices, np.delete(sheet.faces, interior[:1], axis=0), process=False)
    assert boundary_loops(holed) == 2
    # two loops touching at one vertex are two loops
    bowtie = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]],
                             [[0, 1, 2], [0, 3, 4]], process=False)
    assert boundary_loops(bowtie) == 2


def test_evaluate_files_reads_formats_and_refuses_bad_files(tmp_path):
    gt = synthetic.procedural_mesh("sheet_with_hole")
    gt.export(tmp_path / "gt.obj")
    pred = gt.copy()
    pred.apply_translation([0, 0.01, 0])
    pred.export(tmp_path / "pred.ply")
    result = evaluate_files(tmp_path / "pred.ply", tmp_path / "gt.obj", n_samples=5_000)
    assert result["boundary_loops_gt"] == result["boundary_loops_pred"] == 2
    centre, scale = unit_sphere_normalisation(gt)
    assert result["chamfer"] == pytest.approx(0.01 * scale, rel=1e-3)

    with pytest.raises(FileNotFoundError, match="not found"):
        evaluate_files(tmp_path / "missing.ply", tmp_path / "gt.obj")
    (tmp_path / "garbage.ply").write_bytes(b"this is not a mesh")
    with pytest.raises(ValueError, match="garbage.ply"):
        load_mesh(tmp_path / "garbage.ply")
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(tmp_path / "points.ply")
    with pytest.raises(ValueError, match="no triangles"):
        load_mesh(tmp_path / "points.ply")
    degenerate = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="no triangles with area"):
        evaluate(degenerate, gt)


def test_eval_command_prints_the_contracts_json(tmp_path):
    from neudf_core.cli import register

    app = typer.Typer()
    register(app)
    gt = unit_sheet()
    gt.export(tmp_path / "gt.ply")
    pred = unit_sheet()
    pred.apply_translation([0, 0, 0.005])
    pred.export(tmp_path / "pred.glb")
    result = CliRunner().invoke(app, ["eval", str(tmp_path / "pred.glb"), str(tmp_path / "gt.ply"), "--json"])
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout)
    assert CONTRACT_KEYS <= set(printed)
    assert printed["chamfer"] == pytest.approx(0.005 * math.sqrt(2), rel=1e-3)
    missing = CliRunner().invoke(app, ["eval", str(tmp_path / "nope.ply"), str(tmp_path / "gt.ply")])
    assert missing.exit_code != 0 and "not found" in missing.output and "Traceback" not in missing.output
