"""Training loop: Adam with warm-up and cosine decay, resumable checkpoints, metrics and validation renders.

A run folder holds config.json (the resolved configuration), checkpoints/ckpt_<iter>.pt,
metrics.jsonl (one JSON object per logged step) and validation/<iter>.png.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from neudf_core import losses
from neudf_core.config import RendererConfig, TrainConfig, load_config
from neudf_core.dataset import Dataset, load_dataset
from neudf_core.model import NeUDFModel, RenderState
from neudf_core.numerics import flush_denormals
from neudf_core.progress import ProgressFn, null_progress

log = logging.getLogger(__name__)

KEEP_CHECKPOINTS = 2
# What may change when a run is resumed with another --iters: the schedule, not the model.
_SCHEDULE_FIELDS = {"optim": True, "log": True, "renderer": {"cos_anneal_iters"}, "sampler": {"importance_start_iter"}}


class RunError(ValueError):
    """A run folder that cannot be used (missing, or holding another configuration)."""


# -- schedules: pure functions of the step ----------------------------------------------------------
def learning_rate(step: int, cfg_optim) -> float:
    """Linear warm-up to lr, then cosine decay to lr * lr_end_factor at the last iteration."""
    lr, warm, total = cfg_optim.lr, cfg_optim.warmup_iters, cfg_optim.iters
    if warm > 0 and step < warm:
        return lr * (step + 1) / warm
    progress = min(1.0, (step - warm) / max(1, total - warm))
    end = cfg_optim.lr_end_factor
    return lr * (end + (1.0 - end) * 0.5 * (1.0 + math.cos(math.pi * progress)))


def cos_anneal_ratio(step: int, anneal_iters: int) -> float:
    return 1.0 if anneal_iters <= 0 else min(1.0, step / anneal_iters)


def sharpness_floor(step: int, cfg_renderer: RendererConfig, total: int) -> float:
    """The floor on NeUDF's r at ``step``: geometric from sharpness_init to sharpness_floor_end; 0 when off.

    The NeuS baselines keep their learned s: their logistic weight is symmetric about the surface, so a
    small s blurs it without moving it."""
    start, end = cfg_renderer.sharpness_init, cfg_renderer.sharpness_floor_end
    if end <= 0 or cfg_renderer.weight != "neudf":
        return 0.0
    progress = min(1.0, step / max(total, 1))
    return float(start * (end / start) ** progress)


def fit_schedule_to_iters(cfg: TrainConfig, iters: int | None) -> TrainConfig:
    """Set the iteration count; when it is shorter than the preset's, warm-up, annealing and the start of
    importance sampling shrink in proportion, so a short run still runs the whole schedule."""
    if iters is None or iters == cfg.optim.iters:
        return cfg
    if iters <= 0:
        raise ValueError(f"--iters must be positive, got {iters}")
    data = cfg.model_dump()
    ratio = min(1.0, iters / cfg.optim.iters)
    data["optim"]["iters"] = iters
    data["optim"]["warmup_iters"] = int(cfg.optim.warmup_iters * ratio)
    data["renderer"]["cos_anneal_iters"] = int(cfg.renderer.cos_anneal_iters * ratio)
    data["sampler"]["importance_start_iter"] = int(cfg.sampler.importance_start_iter * ratio)
    for key in ("val_every", "ckpt_every"):
        data["log"][key] = max(1, min(data["log"][key], iters))
    return TrainConfig.model_validate(data)


# -- the run folder ------------------------------------------------------------------------------------
def _checkpoints(run_dir: Path) -> list[Path]:
    return sorted((run_dir / "checkpoints").glob("ckpt_*.pt"))


def load_model(run_dir: str | Path, device: str = "cpu") -> NeUDFModel:
    """The trained model of a run folder (its latest checkpoint), in eval mode."""
    run_dir = Path(run_dir)
    cfg_file = run_dir / "config.json"
    if not cfg_file.is_file():
        raise RunError(f"{run_dir} is not a training run (no config.json)")
    ckpts = _checkpoints(run_dir)
    if not ckpts:
        raise RunError(f"{run_dir} has no checkpoint yet (checkpoints/ckpt_*.pt)")
    cfg = TrainConfig.model_validate_json(cfg_file.read_text())
    model = NeUDFModel(cfg).to(device)
    state = torch.load(ckpts[-1], map_location=device, weights_only=False)
    model.load_state_dict(state["model"])
    model.eval()
    return model


class Trainer:
    def __init__(self, data: Dataset, run_dir: Path, cfg: TrainConfig, device: str):
        self.data, self.run_dir, self.cfg, self.device = data.to(device), run_dir, cfg, device
        torch.manual_seed(cfg.seed)
        self.model = NeUDFModel(cfg).to(device)
        self.optimizer = torch.optim.Adam(self._param_groups(), lr=cfg.optim.lr)
        self.step = 0
        self.generator = torch.Generator().manual_seed(cfg.seed)
        bg = 1.0 if cfg.data.white_background else 0.0
        self.bg_color = torch.full((1, 3), bg, device=device)

    def _param_groups(self) -> list[dict]:
        """Hash tables learn with their own rate (Instant NGP uses a far larger one than for MLPs)."""
        tables = [p for n, p in self.model.named_parameters() if n.endswith("encoding.table")]
        others = [p for n, p in self.model.named_parameters() if not n.endswith("encoding.table")]
        groups = [{"params": others, "lr_scale": 1.0}]
        if tables:
            scale = (self.cfg.optim.lr_encoding or self.cfg.optim.lr) / self.cfg.optim.lr
            groups.append({"params": tables, "lr_scale": scale, "eps": 1e-15})
        return groups

    # -- persistence --------------------------------------------------------------------------------
    def save(self) -> Path:
        folder = self.run_dir / "checkpoints"
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"ckpt_{self.step:07d}.pt"
        tmp = path.with_suffix(".tmp")
        torch.save({"iter": self.step, "model": self.model.state_dict(),
                    "optimizer": self.optimizer.state_dict(), "rng": self.generator.get_state()}, tmp)
        tmp.replace(path)  # a reader never sees half a checkpoint
        for old in _checkpoints(self.run_dir)[:-KEEP_CHECKPOINTS]:
            old.unlink(missing_ok=True)
        return path

    def resume(self) -> bool:
        ckpts = _checkpoints(self.run_dir)
        if not ckpts:
            return False
        state = torch.load(ckpts[-1], map_location=self.device, weights_only=False)
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["rng"])
        self.step = state["iter"]
        log.info("resumed %s at iteration %d", self.run_dir, self.step)
        return True

    # -- one step -----------------------------------------------------------------------------------
    def render_state(self, training: bool) -> RenderState:
        cfg = self.cfg
        return RenderState(
            cos_anneal=cos_anneal_ratio(self.step, cfg.renderer.cos_anneal_iters) if training else 1.0,
            perturb=training,
            importance=self.step >= cfg.sampler.importance_start_iter,
            with_grad=training,
            sharpness_floor=sharpness_floor(self.step, cfg.renderer, cfg.optim.iters),
        )

    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        lr = learning_rate(self.step, cfg.optim)
        for group in self.optimizer.param_groups:
            group["lr"] = lr * group["lr_scale"]
        batch = self.data.sample_rays(cfg.optim.rays, cfg.optim.images_per_batch, self.generator)
        amp = cfg.optim.amp and self.device.startswith("cuda")
        with torch.autocast("cuda" if amp else "cpu", dtype=torch.bfloat16, enabled=amp):
            out = self.model.render(batch["rays_o"], batch["rays_d"], self.render_state(True), self.bg_color)
        out["color"] = out["color"].float()
        color_loss = losses.color_l1(out["color"], batch["color"])
        eik_valid = self._relaxed_sphere(batch, out)
        if cfg.loss.eikonal_min_udf > 0:
            eik_valid = eik_valid * (out["psi"].detach() > cfg.loss.eikonal_min_udf).float()
        eik = losses.eikonal(out["gradients"], eik_valid)
        loss = color_loss + cfg.loss.eikonal_weight * eik
        if cfg.loss.mask_weight > 0 and "mask" in batch:
            loss = loss + cfg.loss.mask_weight * losses.mask_bce(out["weight_sum"], batch["mask"])
        if cfg.loss.zero_region_weight > 0 and not self.model.signed:
            loss = loss + cfg.loss.zero_region_weight * losses.zero_region(
                out["raw"], out["inside"], cfg.loss.zero_region_margin)
        if cfg.loss.normal_smooth_weight > 0:
            loss = loss + cfg.loss.normal_smooth_weight * losses.normal_smoothness(out["gradients"], out["inside"])
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.step += 1
        return {"loss": float(loss.detach()), "color_loss": float(color_loss.detach()), "eikonal": float(eik.detach()),
                "psnr": losses.psnr(out["color"], batch["color"]), "sharpness": float(out["sharpness"]),
                "weight_sum": float(out["weight_sum"].detach().mean()), "lr": lr}

    @staticmethod
    def _relaxed_sphere(batch: dict, out: dict) -> torch.Tensor:
        """Eikonal samples: those within |x| < 1.2 (NeuS's relaxed sphere), so the field near the
        boundary of the unit sphere is regular too."""
        pts = batch["rays_o"][:, None] + batch["rays_d"][:, None] * out["mid_z"][..., None]
        return (pts.norm(dim=-1) < 1.2).float()

    # -- validation ---------------------------------------------------------------------------------
    @torch.no_grad()
    def validate(self, index: int = 0, chunk: int = 1024) -> Path:
        """Render one training view: [rendered | observed | normals] side by side, as PNG."""
        self.model.eval()
        rays_o, rays_d, (h, w) = self.data.image_rays(index, self.cfg.log.val_size)
        colors, normals = [], []
        for i in range(0, len(rays_o), chunk):
            out = self.model.render(rays_o[i:i + chunk], rays_d[i:i + chunk], self.render_state(False), self.bg_color)
            colors.append(out["color"])
            n = torch.nn.functional.normalize((out["normals"] * out["weights"][..., None]).sum(1), dim=-1)
            normals.append(n * 0.5 + 0.5)
        self.model.train()
        pred = torch.cat(colors).reshape(h, w, 3)
        normal = torch.cat(normals).reshape(h, w, 3)
        gt = self.data.images[index].permute(2, 0, 1)[None]
        gt = torch.nn.functional.interpolate(gt, size=(h, w), mode="area")[0].permute(1, 2, 0)
        panel = torch.cat([pred, gt, normal], dim=1).clamp(0, 1).cpu().numpy()
        folder = self.run_dir / "validation"
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{self.step:07d}.png"
        Image.fromarray((panel * 255).round().astype(np.uint8)).save(path)
        return path

    # -- the loop -----------------------------------------------------------------------------------
    def fit(self, progress: ProgressFn = null_progress) -> dict[str, Any]:
        cfg = self.cfg
        total = cfg.optim.iters
        metrics_file = self.run_dir / "metrics.jsonl"
        start_step, t0 = self.step, time.perf_counter()
        window: list[dict[str, float]] = []
        last: dict[str, Any] = {}
        while self.step < total:
            stats = self.train_step()
            window.append(stats)
            elapsed = time.perf_counter() - t0
            done = self.step - start_step
            eta = elapsed / done * (total - self.step)
            progress(self.step / total, f"iteration {self.step}/{total}", iter=self.step, loss=stats["loss"],
                     psnr=stats["psnr"], r=stats["sharpness"], s=cfg.sampler.s0, eta_s=eta)
            if self.step % cfg.log.log_every == 0 or self.step == total:
                last = {k: float(np.mean([w[k] for w in window])) for k in window[0]}
                last.update(iter=self.step, elapsed_s=round(elapsed, 3),
                            rays_per_s=round(done * cfg.optim.rays / max(elapsed, 1e-9), 1))
                with metrics_file.open("a") as fh:
                    fh.write(json.dumps(last) + "\n")
                log.info("iter %d loss %.4f psnr %.2f r %.3g", self.step, last["loss"], last["psnr"],
                         last["sharpness"])
                window = []
            if self.step % cfg.log.ckpt_every == 0 or self.step == total:
                self.save()
            if self.step % cfg.log.val_every == 0 or self.step == total:
                self.validate(index=(self.step // max(cfg.log.val_every, 1)) % self.data.n_images)
        elapsed = time.perf_counter() - t0
        return {"iters": self.step, "seconds": round(elapsed, 2), "run_dir": str(self.run_dir),
                "psnr": last.get("psnr"), "loss": last.get("loss"), "sharpness": last.get("sharpness"),
                "iters_per_s": round((self.step - start_step) / max(elapsed, 1e-9), 3)}


def _check_device(device: str) -> str:
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but this machine has no CUDA device (use --device cpu)")
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise ValueError(f"unknown device {device!r}; use cpu or cuda")
    return device


def train(
    data_dir: str | Path,
    run_dir: str | Path,
    *,
    preset: str = "quick",
    iters: int | None = None,
    device: str = "cpu",
    progress: ProgressFn = null_progress,
    overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train NeUDF on a NeuS-layout dataset into ``run_dir``; resumes from the run's last checkpoint."""
    device = _check_device(device)
    flush_denormals()
    run_dir = Path(run_dir)
    cfg = fit_schedule_to_iters(load_config(preset, overrides), iters)
    cfg_file = run_dir / "config.json"
    if cfg_file.is_file() and _checkpoints(run_dir):
        stored = TrainConfig.model_validate_json(cfg_file.read_text())
        if stored.model_dump(exclude=_SCHEDULE_FIELDS) != cfg.model_dump(exclude=_SCHEDULE_FIELDS):
            raise RunError(f"{run_dir} holds a run with another configuration (preset {stored.preset!r}); "
                           "pick a new --out folder or the same options to resume it")
    data = load_dataset(data_dir, cfg.data.max_size, cfg.data.use_masks)
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg_file.write_text(cfg.model_dump_json(indent=2))
    trainer = Trainer(data, run_dir, cfg, device)
    trainer.resume()
    result = trainer.fit(progress)
    result.update(preset=cfg.preset, images=data.n_images, image_size=[data.width, data.height])
    return result
