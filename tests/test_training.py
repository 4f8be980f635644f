"""Training, datasets and the `neudf train` command on small synthetic scenes the tests render themselves."""

import json

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

from neudf_core import synthetic, trainer
from neudf_core.cli import register
from neudf_core.config import RETIRED, load_config, load_saved_config
from neudf_core.dataset import DatasetError, load_dataset
from neudf_core.model import NeUDFModel, RenderState
from neudf_core.trainer import (RunError, learning_rate, load_model, point_surface_scale, sharpness_floor,
                               signed_phase, surface_anchors, train, zero_region_started)


@pytest.fixture(scope="module")
def sheet_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    return synthetic.write_neus_dataset(out, synthetic.procedural_mesh("wavy_sheet"), n_views=24, size=48)


def _metrics(run):
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_quick_preset_learns_the_scene(sheet_scene, tmp_path):
    run = tmp_path / "run"
    # The quick preset with fewer rays and samples, so that the test takes about a minute on 2 cores.
    overrides = {"data": {"white_background": True}, "log": {"log_every": 10},
                 "optim": {"rays": 128}, "sampler": {"n_coarse": 24, "n_importance": 16}}
    result = train(sheet_scene, run, preset="quick", iters=120, overrides=overrides)
    rows = _metrics(run)
    assert [r["iter"] for r in rows] == list(range(10, 121, 10))
    first, last = rows[0], np.mean([r["psnr"] for r in rows[-2:]])
    assert rows[-1]["loss"] < 0.7 * first["loss"]
    assert last > first["psnr"] + 3.0, (first["psnr"], last)
    assert result["iters"] == 120
    for key in ("iter", "loss", "psnr", "elapsed_s"):
        assert key in rows[-1]
    assert sorted(p.name for p in (run / "validation").glob("*.png"))
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["preset"] == "quick" and cfg["optim"]["iters"] == 120


def test_training_resumes_from_its_last_checkpoint(sheet_scene, tmp_path):
    run = tmp_path / "run"
    overrides = {"data": {"white_background": True}, "log": {"log_every": 2, "ckpt_every": 4}}
    train(sheet_scene, run, preset="quick", iters=4, overrides=overrides)
    reports = []
    train(sheet_scene, run, preset="quick", iters=6, overrides=overrides,
          progress=lambda f, m="", **i: reports.append(i["iter"]))
    assert reports == [5, 6]  # picked up at 4, not from scratch
    model = load_model(run)
    import torch

    psi = model.udf(torch.zeros(8, 3))
    assert psi.shape == (8,) and bool((psi >= 0).all())
    with pytest.raises(RunError, match="another configuration"):
        train(sheet_scene, run, preset="quick", iters=8, overrides={"renderer": {"weight": "neus_abs"}})


def test_baseline_weights_train_through_the_same_path(sheet_scene, tmp_path):
    for weight in ("neus_abs", "neus_sdf"):
        result = train(sheet_scene, tmp_path / weight, preset="quick", iters=2,
                       overrides={"renderer": {"weight": weight}, "data": {"white_background": True}})
        assert result["iters"] == 2
    import torch

    sdf_model = load_model(tmp_path / "neus_sdf")
    assert float(sdf_model.udf(torch.zeros(1, 3)).detach()) < 0  # signed: the initial sphere's inside is negative


def test_dataset_reports_what_is_wrong(sheet_scene, tmp_path):
    data = load_dataset(sheet_scene, max_size=24, use_masks=True)
    assert data.images.shape == (24, 24, 24, 3) and data.masks.shape == (24, 24, 24)
    with pytest.raises(DatasetError, match="does not exist"):
        load_dataset(tmp_path / "nowhere")
    (tmp_path / "image").mkdir()
    with pytest.raises(DatasetError, match="no images"):
        load_dataset(tmp_path)
    (tmp_path / "image" / "000.png").write_bytes((sheet_scene / "image" / "000.png").read_bytes())
    with pytest.raises(DatasetError, match="cameras_sphere.npz"):
        load_dataset(tmp_path)
    np.savez(tmp_path / "cameras_sphere.npz", world_mat_1=np.eye(4))
    with pytest.raises(DatasetError, match="image index 0"):
        load_dataset(tmp_path)


def _mask_hits(data, points, shift):
    hits = []
    for i in range(data.n_images):
        K, c2w = data.intrinsics[i].numpy(), data.c2w[i].numpy()
        uv = ((points - c2w[:3, 3]) @ c2w[:3, :3]) @ K.T
        uv = uv[:, :2] / uv[:, 2:] + shift
        x, y = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (x >= 0) & (x < data.width) & (y >= 0) & (y < data.height)
        hits.append(data.masks[i].numpy()[y[ok], x[ok]].mean())
    return float(np.mean(hits))


def test_dataset_cameras_match_the_renderer(sheet_scene):
    # Project the ground-truth surface with the loaded cameras: it lands inside the masks (misses are
    # grazing views of the thin sheet), and half a pixel either way fits worse (pixel centres agree).
    import trimesh

    data = load_dataset(sheet_scene, use_masks=True)
    points = trimesh.load(sheet_scene / "mesh_gt.ply").triangles_center
    exact = _mask_hits(data, points, 0.0)
    assert exact > 0.9
    assert exact > max(_mask_hits(data, points, 0.5), _mask_hits(data, points, -0.5)) + 0.02


def test_cameras_alone_are_the_datasets_cameras(sheet_scene):
    from neudf_core.dataset import load_cameras

    cameras, data = load_cameras(sheet_scene), load_dataset(sheet_scene)
    assert (cameras.width, cameras.height) == (data.width, data.height) and len(cameras) == data.n_images
    assert np.allclose(cameras.c2w, data.c2w.numpy(), atol=1e-5)
    assert np.allclose(cameras.intrinsics, data.intrinsics.numpy(), atol=1e-3)


def test_mesh_with_uvs_but_a_placeholder_texture_is_rendered_with_the_procedural_one():
    # An OBJ with UVs and no texture file (the DiffAvatar garments) loads with a one-colour 2x2 image:
    # rendered as is it would be a blank a photometric method cannot see.
    import trimesh
    from PIL import Image

    mesh = synthetic.procedural_mesh("sheet")
    uv = (mesh.vertices[:, [0, 2]] - mesh.vertices[:, [0, 2]].min(0)) / np.ptp(mesh.vertices[:, [0, 2]], 0)
    blank = trimesh.visual.material.SimpleMaterial(image=Image.new("RGBA", (2, 2), (102, 102, 102, 255)))
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, material=blank)
    camera = synthetic.sphere_cameras(5, 3.0, 64, 64)[0]  # high above the sheet, which lies in y = 0
    image, mask = synthetic.render(mesh, [camera], "white")
    albedo_spread = image[0][mask[0]].astype(float).std(axis=0)
    assert mask[0].sum() > 100 and albedo_spread.max() > 30  # colours vary over the sheet, not one grey

    striped = np.zeros((16, 16, 3), np.uint8)
    striped[:, ::2] = 255
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, material=trimesh.visual.material.SimpleMaterial(
        image=Image.fromarray(striped)))
    image, mask = synthetic.render(mesh, [camera], "white")
    values = image[0][mask[0]]
    assert set(np.unique(values.max(axis=1) < 20)) == {True, False}  # a real texture is used as it is


def test_presets_are_data_and_unknown_ones_are_refused():
    quick = load_config("quick")
    paper = load_config("paper")
    assert paper.optim.iters == 400_000 and paper.optim.rays == 512
    assert paper.sampler.n_coarse == 64 and paper.sampler.n_importance == 64 and paper.sampler.n_rounds == 2
    assert paper.field.d_hidden == 256 and paper.field.n_layers == 8 and paper.renderer.sharpness_init == 0.05
    assert quick.optim.iters < paper.optim.iters
    with pytest.raises(ValueError, match="unknown preset"):
        load_config("turbo")
    with pytest.raises(ValueError):
        load_config("quick", {"renderer": {"weight": "volsdf"}})


def test_a_run_saved_with_retired_options_still_loads():
    saved = json.loads(load_config("quick").model_dump_json())
    for block, retired in RETIRED.items():
        saved[block].update(retired)  # what config.json held before these options went
    assert load_saved_config(json.dumps(saved)) == load_config("quick")
    saved["renderer"]["normal_reg_k"] = 0  # a value the code no longer has: refused, not ignored
    with pytest.raises(ValueError, match="normal_reg_k"):
        load_saved_config(json.dumps(saved))


def test_learning_rate_warms_up_then_decays_to_the_end_factor():
    cfg = load_config("paper").optim
    assert learning_rate(0, cfg) < learning_rate(2_500, cfg) < learning_rate(4_999, cfg) <= cfg.lr
    assert abs(learning_rate(cfg.iters, cfg) - cfg.lr * cfg.lr_end_factor) < 1e-12


def _cli():
    app = typer.Typer()
    register(app)
    return app


def test_train_command_writes_the_contracts_run_folder(sheet_scene, tmp_path):
    run = tmp_path / "run"
    result = CliRunner().invoke(_cli(), ["train", str(sheet_scene), "--out", str(run), "--iters", "3",
                                         "--white-background"])
    assert result.exit_code == 0, result.output
    assert (run / "config.json").is_file() and list((run / "checkpoints").glob("*.pt"))
    assert (run / "metrics.jsonl").is_file() and list((run / "validation").glob("*.png"))


def test_train_command_fails_cleanly_on_bad_input(tmp_path):
    result = CliRunner().invoke(_cli(), ["train", str(tmp_path / "missing"), "--out", str(tmp_path / "r")])
    assert result.exit_code != 0
    assert "does not exist" in result.output and "Traceback" not in result.output
    result = CliRunner().invoke(_cli(), ["train", str(tmp_path), "--out", str(tmp_path / "r"), "--preset", "turbo"])
    assert result.exit_code != 0 and "unknown preset" in result.output


def test_help_explains_every_option():
    result = CliRunner().invoke(_cli(), ["train", "--help"])
    assert result.exit_code == 0
    for option in ("--out", "--preset", "--iters", "--device"):
        assert option in result.output


def test_fast_preset_learns_the_scene(sheet_scene, tmp_path):
    run = tmp_path / "run"
    # The same reduced sampling as the quick test; each CPU step is dearer (hash-grid gathers).
    overrides = {"data": {"white_background": True}, "log": {"log_every": 10},
                 "optim": {"rays": 128}, "sampler": {"n_coarse": 24, "n_importance": 16}}
    train(sheet_scene, run, preset="fast", iters=120, overrides=overrides)
    rows = _metrics(run)
    last = np.mean([r["psnr"] for r in rows[-2:]])
    assert rows[-1]["loss"] < 0.7 * rows[0]["loss"]
    assert last > rows[0]["psnr"] + 3.0, (rows[0]["psnr"], last)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["field"]["encoding"] == "hashgrid" and cfg["field"]["gradient"] == "finite_difference"


def test_zero_region_term_is_on_in_quick_only_and_trains(sheet_scene, tmp_path):
    # the paper has no such term; fast has not been measured with it
    assert [load_config(p).loss.zero_region_weight for p in ("paper", "fast")] == [0, 0]
    assert load_config("quick").loss.zero_region_weight > 0
    result = train(sheet_scene, tmp_path / "run", preset="quick", iters=3, overrides={"data": {"white_background": True}})
    assert result["iters"] == 3 and np.isfinite(result["loss"])


def test_zero_region_term_waits_for_its_share_of_training(sheet_scene, tmp_path, monkeypatch):
    # started as a sphere (h < 0 inside), the field is penalised for that inside only from the share on
    assert zero_region_started(0, 0.0, 20)
    assert [zero_region_started(step, 0.3, 1000) for step in (299, 300)] == [False, True]
    # ... and, held back at all, not before 100 iterations: a run of seconds keeps its shell
    assert [zero_region_started(step, 0.3, 200) for step in (60, 99, 100)] == [False, False, True]
    assert not zero_region_started(22, 0.3, 23)
    monkeypatch.setattr(trainer, "ZERO_REGION_MIN_WAIT", 0)  # a run of 8 iterations shows the share alone
    overrides = {"data": {"white_background": True}, "log": {"log_every": 1}, "optim": {"rays": 64},
                 "field": {"init_radius": 0.5}, "loss": {"zero_region_from": 0.5}}
    train(sheet_scene, tmp_path / "run", preset="quick", iters=8, overrides=overrides)
    rows = _metrics(tmp_path / "run")
    extra = [r["loss"] - r["color_loss"] - 0.1 * r["eikonal"] for r in rows]
    assert [r["iter"] for r in rows] == list(range(1, 9))
    assert max(abs(e) for e in extra[:4]) < 1e-5, extra
    assert min(extra[4:]) > 1e-3, extra


def test_sharpness_floor_rises_geometrically_for_the_neudf_weight_only():
    cfg = load_config("quick", {"renderer": {"sharpness_init": 20.0, "sharpness_floor_end": 500.0}}).renderer
    assert sharpness_floor(0, cfg, 1000) == pytest.approx(20.0)
    assert sharpness_floor(500, cfg, 1000) == pytest.approx(100.0)  # the geometric mean of 20 and 500
    assert sharpness_floor(1000, cfg, 1000) == pytest.approx(500.0)
    assert sharpness_floor(5000, cfg, 1000) == pytest.approx(500.0)  # past the schedule it stays at the end
    assert sharpness_floor(500, cfg.model_copy(update={"sharpness_floor_end": 0.0}), 1000) == 0.0
    assert sharpness_floor(500, cfg.model_copy(update={"weight": "neus_sdf"}), 1000) == 0.0


def test_training_renders_with_r_at_or_above_its_floor(sheet_scene, tmp_path):
    overrides = {"data": {"white_background": True}, "log": {"log_every": 5},
                 "renderer": {"sharpness_init": 20.0, "sharpness_floor_end": 2000.0}}
    train(sheet_scene, tmp_path / "run", preset="quick", iters=20, overrides=overrides)
    cfg = load_config("quick", overrides)
    for row in _metrics(tmp_path / "run"):
        # a row averages the r its 5 steps rendered with; the floor only rises, so its first step bounds it
        assert row["sharpness"] >= sharpness_floor(row["iter"] - 5, cfg.renderer, 20) * (1 - 1e-5), row
    assert _metrics(tmp_path / "run")[-1]["sharpness"] > 500.0  # r starts at 20; 20 Adam steps cannot reach 500


@pytest.mark.parametrize("mode", ["clamp", "lift"])
def test_only_a_lifted_r_learns_while_the_floor_bounds_it(sheet_scene, tmp_path, mode):
    """Clamped, r is the floor and its gradient is 0 while the learned value lies below; lifted, the learned
    value itself is kept at or above the floor and the images' gradient reaches it."""
    cfg = load_config("quick", {"data": {"white_background": True}, "optim": {"iters": 20},
                                "renderer": {"sharpness_init": 20.0, "sharpness_floor_end": 2000.0,
                                             "sharpness_floor_mode": mode}})
    fit = trainer.Trainer(load_dataset(sheet_scene, max_size=24), tmp_path / "run", cfg, "cpu")
    for _ in range(5):
        fit.train_step()
    grad = fit.model.sharpness.v.grad
    learned = float(fit.model.sharpness())
    if mode == "lift":
        assert learned >= sharpness_floor(5, cfg.renderer, 20) * (1 - 1e-5)
        assert grad is not None and float(grad.abs()) > 0
    else:
        assert learned < sharpness_floor(4, cfg.renderer, 20)  # 5 warm-up steps of Adam leave it near 20
        assert grad is None or float(grad.abs()) == 0


def test_a_signed_start_renders_h_exactly_as_the_neus_sdf_baseline_renders_its_field():
    """In its signed share of training NeUDF renders h (the field before |.|) with NeuS's weight and the
    signed gradient, as the NeuS-SDF baseline renders the same network; after it, NeUDF's weight on |h|."""
    torch.manual_seed(0)
    cfg = load_config("quick", {"data": {"white_background": True}, "field": {"init_radius": 0.5},
                                "renderer": {"signed_until": 0.5}})
    unsigned = NeUDFModel(cfg)
    baseline = NeUDFModel(cfg.model_copy(update={"renderer": cfg.renderer.model_copy(update={"weight": "neus_sdf"})}))
    baseline.load_state_dict(unsigned.state_dict())
    rays_o = torch.tensor([[0.0, 0.0, -2.0], [0.3, -0.2, -2.0], [0.0, 0.9, -2.0]])
    rays_d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [-0.1, 0.1, 1.0], [0.0, -0.3, 1.0]]), dim=-1)
    state = RenderState(cos_anneal=0.5)
    signed = unsigned.render(rays_o, rays_d, RenderState(cos_anneal=0.5, signed=True))
    reference = baseline.render(rays_o, rays_d, state)
    torch.testing.assert_close(signed["weights"], reference["weights"])
    torch.testing.assert_close(signed["color"], reference["color"])
    assert (signed["raw"] < 0).any()  # the rays enter the sphere the field starts as
    opened = unsigned.render(rays_o, rays_d, state)
    assert (opened["weights"] - reference["weights"]).abs().max() > 1e-2


def test_a_signed_start_has_its_share_of_training_then_hands_over_to_neudf(sheet_scene, tmp_path):
    cfg = load_config("quick", {"renderer": {"signed_until": 0.4}}).renderer
    assert [signed_phase(step, cfg, 100) for step in (0, 39, 40, 99)] == [True, True, False, False]
    assert sharpness_floor(39, cfg, 100) == 0.0  # the signed share learns its s, as the baseline does
    assert sharpness_floor(40, cfg, 100) == sharpness_floor(40, cfg.model_copy(update={"signed_until": 0.0}), 100)
    assert not signed_phase(0, cfg.model_copy(update={"weight": "neus_sdf"}), 100)  # the baseline is signed anyway
    with pytest.raises(ValueError, match="output abs"):
        load_config("paper", {"renderer": {"signed_until": 0.4}})  # Softplus keeps no sign of h
    overrides = {"data": {"white_background": True}, "log": {"log_every": 1}, "optim": {"rays": 64},
                 "renderer": {"signed_until": 0.5, "sharpness_floor_end": 2000.0}}
    result = train(sheet_scene, tmp_path / "run", preset="quick", iters=8, overrides=overrides)
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert result["start"] == "sphere" and saved["field"]["init_radius"] == 0.5
    rows = _metrics(tmp_path / "run")
    # row i holds step i - 1: steps 0-3 signed (learned s from 20, no zero-region term), then NeUDF's floor
    zero_region = [r["loss"] - r["color_loss"] - 0.1 * r["eikonal"] for r in rows]
    assert max(abs(z) for z in zero_region[:4]) < 1e-5, zero_region
    assert min(zero_region[4:]) > 1e-4, zero_region  # the sphere's inside, h < 0, is penalised from then on
    assert all(r["sharpness"] < 25.0 for r in rows[:4]), rows
    assert all(r["sharpness"] >= sharpness_floor(r["iter"] - 1, load_config("quick", overrides).renderer, 8) * (1 - 1e-5)
               for r in rows[4:]), rows
    assert rows[-1]["sharpness"] > 100.0


_DENORMALS = """
import torch
{setup}
torch.set_num_threads(2)
x = torch.full((1 << 20,), 1e-20)
print(int(((x * 1e-20) != 0).sum()))  # 1e-40 is a float32 denormal unless flushed
"""


def _denormals_left(setup: str) -> int:
    import subprocess
    import sys

    code = _DENORMALS.format(setup=setup)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return int(out.stdout.split()[-1])


def test_training_flushes_denormals_on_every_compute_thread(sheet_scene, tmp_path):
    """exp(-r d) underflows into denormals away from the surface, and a CPU computing with them made late
    steps 2.5x slower; train() flushes them in its thread and in the compute threads it starts."""
    import torch

    if not torch.set_flush_denormal(False):  # a CPU without the mode: nothing to check
        pytest.skip("this CPU has no flush-to-zero mode")
    assert _denormals_left("") > 0  # the default mode keeps them, so the check below can fail
    trained = (f"from neudf_core.trainer import train\n"
               f"train({str(sheet_scene)!r}, {str(tmp_path / 'run')!r}, preset='quick', iters=2, "
               f"overrides={{'data': {{'white_background': True}}}})")
    assert _denormals_left(trained) == 0


def test_near_points_cover_the_object_and_leave_the_rest_of_the_view(sheet_scene):
    """Sparse points of the object, projected and grown by the prior's radius, cover the object's mask in every
    view and leave most of the rest of the image, where the prior then says: no object here."""
    import trimesh

    data = load_dataset(sheet_scene, use_masks=True)
    surface = trimesh.load(sheet_scene / "mesh_gt.ply")
    points, _ = trimesh.sample.sample_surface_even(surface, 400, seed=0)
    data.find_near_points(torch.from_numpy(np.asarray(points)).float(), radius=0.06)
    mask = data.masks > 0.5
    assert data.near_points.shape == mask.shape
    assert float(data.near_points[mask].float().mean()) > 0.95
    assert float(data.near_points[~mask].float().mean()) < 0.3
    batch = data.sample_rays(64, 0, torch.Generator().manual_seed(0))
    assert set(batch["near_points"].unique().tolist()) <= {0.0, 1.0}


def test_point_prior_clears_what_no_sparse_point_backs(sheet_scene, tmp_path):
    """With the sparse points of one half of the sheet only, the prior leaves the object's opacity on the
    other half lower than training without it does, from the same start."""
    import shutil

    import trimesh

    data_dir = tmp_path / "data"
    shutil.copytree(sheet_scene, data_dir)
    vertices = trimesh.load(sheet_scene / "mesh_gt.ply").vertices
    half = vertices[vertices[:, 0] < 0].astype(np.float32)
    np.save(data_dir / "object_points.npy", half)
    data = load_dataset(data_dir, use_masks=True)
    data.find_near_points(torch.from_numpy(half), radius=0.06)
    idx = torch.nonzero((data.masks > 0.5) & ~data.near_points)[::7]  # the sheet no point backs
    rays_o, rays_d = data.rays(idx[:, 0], idx[:, 1], idx[:, 2])
    base = {"data": {"white_background": True}, "optim": {"rays": 128, "object_rays": 0.9},
            "sampler": {"n_coarse": 24, "n_importance": 16}}
    opacity = {}
    for weight in (0.0, 1.0):
        run = tmp_path / f"run_{weight}"
        train(data_dir, run, preset="quick", iters=80, overrides={**base, "loss": {"point_prior_weight": weight}})
        model = load_model(run)
        with torch.no_grad():
            out = model.render(rays_o, rays_d, RenderState(cos_anneal=1.0), None)
        opacity[weight] = float(out["weight_sum"].mean())
    assert opacity[1.0] < opacity[0.0] - 0.1, opacity


def test_a_capture_without_anchors_starts_from_a_sphere(sheet_scene, tmp_path):
    """A capture whose sparse points anchor nothing (lone points, as on a smooth bowl) starts the unsigned
    field as a sphere shell with the zero-region term held back; one with anchors (the sheet's vertices), or
    data with no sparse points at all (clean renders), starts from a point; a start named in the options is
    kept."""
    import shutil

    import trimesh

    vertices = np.asarray(trimesh.load(sheet_scene / "mesh_gt.ply").vertices, dtype=np.float32)
    lone = np.stack(np.meshgrid(*[np.linspace(-0.6, 0.6, 5)] * 3), -1).reshape(-1, 3).astype(np.float32)
    assert surface_anchors(lone, None).sum() == 0 and len(lone) >= 50
    base = {"data": {"white_background": True}, "optim": {"rays": 32},
            "sampler": {"n_coarse": 8, "n_importance": 8}}
    starts = {}
    for name, points, field in (("lone", lone, {}), ("anchored", vertices, {}), ("none", None, {}),
                                ("named", lone, {"init_radius": 0.0})):
        data_dir = tmp_path / name
        shutil.copytree(sheet_scene, data_dir)
        if points is not None:
            np.save(data_dir / "object_points.npy", points)
        result = train(data_dir, tmp_path / f"run_{name}", preset="quick", iters=1, overrides={**base, "field": field})
        cfg = json.loads((tmp_path / f"run_{name}" / "config.json").read_text())
        starts[name] = (result["start"], cfg["field"]["init_radius"], cfg["loss"]["zero_region_from"])
    assert starts == {"lone": ("sphere", 0.5, 0.3), "anchored": ("point", 0.0, 0.0), "none": ("point", 0.0, 0.0),
                      "named": ("point", 0.0, 0.0)}, starts
    load_model(tmp_path / "run_lone")  # the saved configuration rebuilds the model it trained
    # a run saved before the start was resolved (init_radius null) resumes with the start it had: a point
    saved = tmp_path / "run_lone" / "config.json"
    cfg = json.loads(saved.read_text())
    cfg["field"]["init_radius"], cfg["loss"]["zero_region_from"] = None, 0.0
    saved.write_text(json.dumps(cfg))
    resumed = train(tmp_path / "lone", tmp_path / "run_lone", preset="quick", iters=2, overrides={**base, "field": {}})
    assert resumed["iters"] == 2 and resumed["start"] == "point"
    assert json.loads(saved.read_text())["field"]["init_radius"] == 0.0


def test_point_surface_term_pulls_the_field_to_zero_at_sparse_points(sheet_scene, tmp_path):
    """Sparse points of the sheet (half its vertices) given to the point-surface term: after the same short
    training from the same start, Psi is lower at those points and at the sheet's other vertices than
    without the term, so the surface is drawn towards where features were triangulated."""
    import shutil

    import trimesh

    data_dir = tmp_path / "data"
    shutil.copytree(sheet_scene, data_dir)
    vertices = np.asarray(trimesh.load(sheet_scene / "mesh_gt.ply").vertices, dtype=np.float32)
    np.save(data_dir / "object_points.npy", vertices[::2])
    base = {"data": {"white_background": True}, "optim": {"rays": 128},
            "sampler": {"n_coarse": 24, "n_importance": 16}}
    at_points, elsewhere = {}, {}
    for weight in (0.0, 1.0):
        run = tmp_path / f"run_{weight}"
        loss = {"point_surface_weight": weight, "point_surface_until": 1.0}
        result = train(data_dir, run, preset="quick", iters=60, overrides={**base, "loss": loss})
        anchors = int(surface_anchors(vertices[::2], None).sum())  # the sheet's rim has fewer neighbours
        assert result.get("surface_points") == (None if weight == 0 else anchors) and anchors > 0.8 * len(
            vertices[::2]), result
        model = load_model(run)
        with torch.no_grad():
            at_points[weight] = float(model.udf(torch.from_numpy(vertices[::2])).abs().mean())
            elsewhere[weight] = float(model.udf(torch.from_numpy(vertices[1::2])).abs().mean())
    assert at_points[1.0] < 0.5 * at_points[0.0], at_points
    assert elsewhere[1.0] < 0.5 * elsewhere[0.0], elsewhere


def test_line_of_sight_term_clears_surface_off_the_lines_to_seen_points(sheet_scene, tmp_path):
    """Each anchor with the images that saw it (DATA/object_point_views.npy, here every camera): after the
    same short training, the field has less surface on the lines from those cameras to the anchors (those
    the term keeps) with the line-of-sight term than without it. The views are read row for row with the
    anchors, and a file that does not match the points is refused with its name."""
    import shutil

    import trimesh

    from neudf_core.losses import surface_in_sight
    from neudf_core.sampler import sight_lines
    from neudf_core.trainer import clear_sight_views, load_model

    data_dir = tmp_path / "data"
    shutil.copytree(sheet_scene, data_dir)
    anchors = np.asarray(trimesh.load(sheet_scene / "mesh_gt.ply").vertices, dtype=np.float32)[::2]
    np.save(data_dir / "object_points.npy", anchors)
    n_images = len(list((data_dir / "image").glob("*.png")))
    views = np.stack([np.random.default_rng(i).permutation(n_images)[:8] for i in range(len(anchors))])
    np.save(data_dir / "object_point_views.npy", views.astype(np.int32))
    base = {"data": {"white_background": True}, "optim": {"rays": 64},
            "sampler": {"n_coarse": 16, "n_importance": 16}}
    c2w = load_dataset(data_dir).c2w
    # measured on the lines the term trains on: a frame that sees the sheet too obliquely is left out
    kept = clear_sight_views(torch.from_numpy(anchors), torch.from_numpy(views).long(), c2w[:, :3, 3], 0.01, 0.03)
    rows, cols = (kept >= 0).nonzero(as_tuple=True)
    lines, valid = sight_lines(torch.from_numpy(anchors)[rows], c2w[kept[rows, cols], :3, 3], gap=0.03, n=64)
    in_sight = {}
    for weight in (0.0, 10.0):
        run = tmp_path / f"run_{weight}"
        loss = {"point_surface_weight": 1.0, "point_surface_until": 1.0, "point_sight_weight": weight}
        result = train(data_dir, run, preset="quick", iters=60, overrides={**base, "loss": loss})
        if weight == 0:
            assert "sight_points" not in result
        else:  # a sheet seen from all round: some anchors' eight frames all see it too obliquely to keep
            assert 0.9 * result["surface_points"] <= result["sight_points"] <= result["surface_points"], result
        with torch.no_grad():
            psi = load_model(run).udf(lines.reshape(-1, 3)).reshape(lines.shape[:2])
        in_sight[weight] = float(surface_in_sight(psi, valid, 0.01))
    assert in_sight[10.0] < 0.5 * in_sight[0.0], in_sight

    unfiltered = train(data_dir, tmp_path / "run_every_view", preset="quick", iters=2, overrides={**base, "loss": {
        "point_surface_weight": 1.0, "point_sight_weight": 1.0, "point_sight_clear": False}})
    assert unfiltered["sight_points"] == unfiltered["surface_points"], unfiltered

    np.save(data_dir / "object_point_views.npy", views[:-1].astype(np.int32))
    with pytest.raises(DatasetError, match="object_point_views.npy"):
        train(data_dir, tmp_path / "run_bad", preset="quick", iters=2,
              overrides={**base, "loss": {"point_surface_weight": 1.0, "point_sight_weight": 1.0}})


def test_lines_of_sight_that_graze_their_own_cloth_or_pass_other_cloth_are_left_out():
    """Anchors on a sheet at z = 0, and a strip of cloth above its middle at z = 0.2. A camera straight above
    the sheet's edge sees it clear; above the middle its line passes the strip; a camera low at the side
    sees the sheet so obliquely that the line's end lies within the margin of the sheet itself."""
    from neudf_core.trainer import anchor_normals, clear_sight_views

    g = torch.linspace(-0.3, 0.3, 31)
    x, y = torch.meshgrid(g, g, indexing="ij")
    sheet = torch.stack([x.ravel(), y.ravel(), torch.zeros(x.numel())], -1)
    strip = sheet[sheet[:, 0].abs() <= 0.1] + torch.tensor([0.0, 0.0, 0.2])
    points = torch.cat([sheet, strip])
    normals = anchor_normals(points)
    assert torch.allclose(normals[: len(sheet)].abs(), torch.tensor([0.0, 0.0, 1.0]).expand(len(sheet), 3), atol=1e-4)

    middle = int(((sheet[:, 0].abs() + sheet[:, 1].abs()) < 1e-6).nonzero())
    edge = int(((sheet - torch.tensor([0.3, 0.0, 0.0])).norm(dim=-1) < 1e-6).nonzero())
    centres = torch.tensor([[0.3, 0.0, 2.0], [0.0, 0.0, 2.0], [2.0, 0.0, 0.05], [0.0, 0.3, 2.0], [1.5, 0.0, 1.0]])
    views = torch.full((len(points), 4), -1, dtype=torch.long)
    views[edge, :2] = torch.tensor([0, 2])  # above the edge: clear; from the side: grazing
    # the middle from the side; from straight above and from a little aside (the line meets z = 0.2 at
    # (0, 0.03)), both over the strip; and from far aside (it meets z = 0.2 at x = 0.3, past the strip)
    views[middle] = torch.tensor([2, 1, 3, 4])
    kept = clear_sight_views(points, views, centres, margin=0.01, gap=0.03)
    assert kept[edge].tolist() == [0, -1, -1, -1]
    assert kept[middle].tolist() == [4, -1, -1, -1]


def test_point_surface_term_fades_to_nothing_at_its_share_of_training():
    assert point_surface_scale(0, 0.5, 1000) == 1.0
    assert point_surface_scale(250, 0.5, 1000) == 0.5
    assert point_surface_scale(500, 0.5, 1000) == 0.0
    assert point_surface_scale(900, 0.5, 1000) == 0.0
    assert point_surface_scale(500, 1.0, 1000) == 0.5


def test_point_surface_term_anchors_on_clusters_of_points_off_the_floor():
    """Points of the floor's texture scatter just above the floor cut, and strays stand alone; pulled to
    Psi = 0 they draw a sheet of floor or specks, so the term takes only points clear of the cut that have
    neighbours (a textured object's points)."""
    grid = np.linspace(-0.3, 0.3, 31)  # a cloth's points 0.02 apart
    cloth = np.stack([*np.meshgrid(grid, grid), np.zeros((31, 31))], -1).reshape(-1, 3)
    low_cluster = cloth * [1, 0.05, 1] + [0, -0.76, 0]   # dense, but within the band over the floor at -0.8
    strays = np.array([[0.8, 0.5, 0.1], [-0.7, -0.2, 0.5], [0.0, 0.6, -0.8]])
    points = np.concatenate([cloth, low_cluster, strays]).astype(np.float32)
    kept = points[surface_anchors(points, -0.8)]
    assert len(kept) == len(cloth) and np.allclose(kept, cloth.astype(np.float32))
    assert surface_anchors(points, None).sum() == 2 * len(cloth)
