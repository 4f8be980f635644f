"""The download: decimation that keeps open boundaries, and GLB, OBJ + MTL + PNG, USDZ and PLY that load back
with their UVs and texture; the export stage on a small textured job folder."""

from __future__ import annotations

import json
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from neudf_core.decimate import decimate
from neudf_core.export import USDZ_METRES_PER_UNIT, export_mesh
from neudf_core.metrics import boundary_loops, evaluate
from neudf_core.texture import bake_texture
from tests.builders import holed_wavy_sheet, textured_sheet_dataset
from worker.export import export_job


def test_decimation_to_a_fifth_keeps_boundaries_and_chamfer():
    """A reconstruction-like sheet (jagged rim and hole, a smooth error of ~1 % of the unit sphere) against the
    smooth truth: a fifth of the faces moves Chamfer by under 2 % and keeps both boundary loops."""
    truth = holed_wavy_sheet(384)
    dense = holed_wavy_sheet(128)
    x, z = dense.vertices[:, 0], dense.vertices[:, 2]
    dense.vertices[:, 1] += 0.01 * np.sin(3.0 * x + 1.0) * np.cos(2.0 * z)
    dense.visual.vertex_colors = np.tile([200, 30, 30, 255], (len(dense.vertices), 1)).astype(np.uint8)
    small = decimate(dense, len(dense.faces) // 5)
    assert len(small.faces) <= len(dense.faces) // 5 + 10
    assert small.metadata["decimation"] == {"faces_before": len(dense.faces), "faces_after": len(small.faces)}
    before, after = evaluate(dense, truth, n_samples=50_000), evaluate(small, truth, n_samples=50_000)
    assert abs(after["chamfer"] - before["chamfer"]) < 0.02 * before["chamfer"], (before["chamfer"], after["chamfer"])
    assert boundary_loops(small) == boundary_loops(dense) == 2
    assert (np.asarray(small.visual.vertex_colors)[:, :3] == [200, 30, 30]).all()  # colours carried over


def test_a_mesh_under_the_target_is_left_as_it_is():
    mesh = holed_wavy_sheet(16)
    assert decimate(mesh, len(mesh.faces)) is mesh and decimate(mesh, 0) is mesh


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> tuple[Path, trimesh.Trimesh, trimesh.Trimesh]:
    data, sheet = textured_sheet_dataset(tmp_path_factory.mktemp("sheet") / "data", n_views=16, size=96)
    textured, _ = bake_texture(sheet, data, 256)
    return data, sheet, textured


def _same_texture(image, textured: trimesh.Trimesh, tol: float) -> None:
    original = np.asarray(textured.visual.material.baseColorTexture.convert("RGB"), np.float64)
    loaded = np.asarray(image.convert("RGB"), np.float64)
    assert loaded.shape == original.shape and np.abs(loaded - original).mean() < tol


def test_glb_obj_and_usdz_load_back_with_uvs_and_texture(baked, tmp_path):
    _, _, textured = baked
    glb = trimesh.load(export_mesh(textured, tmp_path / "mesh.glb"), force="mesh", process=False)
    assert glb.visual.kind == "texture" and glb.visual.uv.shape == (len(glb.vertices), 2)
    assert glb.visual.material.doubleSided is True
    _same_texture(glb.visual.material.baseColorTexture, textured, tol=3.0)  # JPEG inside the GLB
    assert len(glb.faces) == len(textured.faces)

    export_mesh(textured, tmp_path / "mesh.obj")
    assert {p.name for p in tmp_path.glob("mesh.*")} >= {"mesh.obj", "mesh.mtl", "mesh.png"}
    assert "map_Kd mesh.png" in (tmp_path / "mesh.mtl").read_text()
    obj = trimesh.load(tmp_path / "mesh.obj", force="mesh", process=False)
    assert obj.visual.kind == "texture" and len(obj.visual.uv) == len(obj.vertices)
    _same_texture(obj.visual.material.image, textured, tol=0.5)  # PNG: lossless
    uv_at = {tuple(v.round(6)): tuple(t.round(5)) for v, t in zip(textured.vertices, textured.visual.uv)}
    assert all(uv_at.get(tuple(v.round(6))) is not None for v in obj.vertices[:50])

    from pxr import Usd, UsdGeom, UsdShade

    usdz = export_mesh(textured, tmp_path / "mesh.usdz")
    assert any(name.endswith(".jpg") for name in zipfile.ZipFile(usdz).namelist())
    stage = Usd.Stage.Open(str(usdz))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    mesh = UsdGeom.Mesh(stage.GetDefaultPrim().GetChild("Mesh"))
    points = np.asarray(mesh.GetPointsAttr().Get())
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get()
    assert len(points) == len(st) == len(textured.vertices)
    assert np.allclose(np.ptp(points, axis=0), np.ptp(textured.vertices, axis=0) * USDZ_METRES_PER_UNIT, atol=1e-5)
    assert points[:, 1].min() == pytest.approx(0.0, abs=1e-6)  # standing on the floor
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    shaders = {UsdShade.Shader(p).GetIdAttr().Get() for p in material.GetPrim().GetChildren()}
    assert {"UsdPreviewSurface", "UsdUVTexture", "UsdPrimvarReader_float2"} <= shaders


def _gltf_validator() -> list[str] | None:
    """``node`` with the npm package gltf-validator (e.g. ``npm i gltf-validator`` in the folder named by
    NEUDF_GLTF_VALIDATOR_DIR, default /tmp/gv), or None."""
    import os

    folder = Path(os.environ.get("NEUDF_GLTF_VALIDATOR_DIR", "/tmp/gv"))
    node = shutil.which("node")
    if node is None or not (folder / "node_modules" / "gltf-validator").is_dir():
        return None
    script = ("const v=require('gltf-validator');const b=require('fs').readFileSync(process.argv[1]);"
              "v.validateBytes(new Uint8Array(b)).then(r=>console.log(JSON.stringify(r.issues)))")
    return [node, "-e", script]


def test_glb_passes_the_khronos_validator(baked, tmp_path):
    command = _gltf_validator()
    if command is None:
        pytest.skip("gltf-validator (npm) is not installed")
    _, _, textured = baked
    path = export_mesh(textured, tmp_path / "mesh.glb")
    import os

    folder = os.environ.get("NEUDF_GLTF_VALIDATOR_DIR", "/tmp/gv")
    result = subprocess.run([*command, str(path)], capture_output=True, text=True, timeout=120, cwd=folder,
                            env={**os.environ, "NODE_PATH": str(Path(folder) / "node_modules")})
    issues = json.loads(result.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


def test_export_stage_writes_the_download(baked, tmp_path):
    data, sheet, _ = baked
    mesh_file = tmp_path / "mesh" / "mesh.ply"
    mesh_file.parent.mkdir()
    sheet.export(mesh_file)
    out = tmp_path / "export"
    figures = export_job(mesh_file, data, tmp_path / "run", out, faces=100, texture_size=128)
    names = {p.name for p in out.iterdir()}
    assert {"mesh.glb", "mesh.obj", "mesh.mtl", "mesh.png", "mesh.usdz", "mesh.ply", "preview.png",
            "metrics.json"} <= names
    assert figures["mesh_faces"] <= 110 < figures["mesh_faces_before"] and figures["texture_size"] == 128
    summary = json.loads((out / "metrics.json").read_text())["download"]
    assert summary["usdz_metres_per_unit"] == USDZ_METRES_PER_UNIT and summary["texture"]["texture_size"] == 128
    assert summary["bytes"]["mesh.glb"] == (out / "mesh.glb").stat().st_size
    ply = trimesh.load(out / "mesh.ply", process=False)
    assert ply.visual.kind == "vertex" and len(ply.faces) == figures["mesh_faces"]  # one side, vertex colours
    glb = trimesh.load(out / "mesh.glb", force="mesh", process=False)
    assert glb.visual.kind == "texture" and len(glb.faces) == 2 * figures["mesh_faces"]  # front and back

    plain = export_job(mesh_file, data, tmp_path / "run", tmp_path / "plain", faces=0, texture_size=0)
    assert plain["texture_size"] == 0 and plain["mesh_faces"] == len(sheet.faces)
    assert not (tmp_path / "plain" / "mesh.png").exists()
    plain_glb = trimesh.load(tmp_path / "plain" / "mesh.glb", force="mesh", process=False, skip_materials=True)
    assert plain_glb.visual.kind == "vertex" and getattr(plain_glb.visual, "uv", None) is None
