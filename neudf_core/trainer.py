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
from neudf_core.config import RendererConfig, TrainConfig, default_preset, load_config, load_saved_config
from neudf_core.dataset import (FLOOR_SHADOW_BAND, Dataset, image_paths, load_dataset, read_floor,
                                read_object_point_views, read_object_points)
from neudf_core.files import atomic_write
from neudf_core.model import NeUDFModel, RenderState
from neudf_core.numerics import flush_denormals
from neudf_core.progress import ProgressFn, null_progress
from neudf_core.sampler import sight_lines

log = logging.getLogger(__name__)

KEEP_CHECKPOINTS = 2
# A run with a time budget and no iteration count stops on time alone.
BUDGET_MAX_ITERS = 1_000_000
MIN_PRIOR_POINTS = 50  # fewer sparse points of the object outline nothing: no point prior
# A sparse point anchors the surface when this many others lie within this radius (unit sphere): a garment's
# points have a dozen (median), the floor's scatter above the cut and a smooth bowl's few points none.
ANCHOR_NEIGHBOURS, ANCHOR_RADIUS = 5, 0.05
# An unsigned field with no anchors starts as a sphere shell that shrinks onto the object (as NeuS-SDF starts),
# the zero-region term held back for this share of training: grown from the centre with nothing to pull it
# out, a smooth object's surface lost every ray to the surroundings model.
SPHERE_START_RADIUS, SPHERE_START_ZERO_REGION_FROM = 0.5, 0.3
# A held-back zero-region term also waits this many iterations: shrinking takes steps, not a share of them, and
# a run of a few dozen iterations (a budget of seconds) would otherwise lift the whole shell off zero.
ZERO_REGION_MIN_WAIT = 100
# What may change when a run is resumed with another --iters: the schedule, not the model.
_SCHEDULE_FIELDS = {"optim": True, "log": True, "renderer": {"cos_anneal_iters"}}


class RunError(ValueError):
    """A run folder that cannot be used (missing, or holding another configuration)."""


# -- schedules: pure functions of the step ----------------------------------------------------------
def learning_rate(step: int, cfg_optim, total: int | None = None) -> float:
    """Linear warm-up to lr, then cosine decay to lr * lr_end_factor at the last iteration (``total``,
    default the configured iterations; a run with a time budget passes the iterations it expects to reach)."""
    lr, warm = cfg_optim.lr, cfg_optim.warmup_iters
    total = cfg_optim.iters if total is None else total
    if warm > 0 and step < warm:
        return lr * (step + 1) / warm
    progress = min(1.0, (step - warm) / max(1, total - warm))
    end = cfg_optim.lr_end_factor
    return lr * (end + (1.0 - end) * 0.5 * (1.0 + math.cos(math.pi * progress)))


def cos_anneal_ratio(step: int, anneal_iters: int) -> float:
    return 1.0 if anneal_iters <= 0 else min(1.0, step / anneal_iters)


def point_surface_scale(step: int, until: float, total: int) -> float:
    """The point-surface term's share of its weight at ``step``: 1 at the start, 0 from ``until`` of training."""
    return max(0.0, 1.0 - step / max(until * total, 1.0))


def zero_region_started(step: int, share: float, total: int) -> bool:
    """Whether the zero-region term acts at ``step``: from ``share`` of training, and when held back at all, not
    before ZERO_REGION_MIN_WAIT iterations."""
    if share <= 0:
        return True
    return step >= max(share * total, ZERO_REGION_MIN_WAIT)


def signed_phase(step: int, cfg_renderer: RendererConfig, total: int) -> bool:
    """Whether NeUDF's field is still rendered as a signed distance at ``step`` (``renderer.signed_until``)."""
    return cfg_renderer.weight == "neudf" and step < cfg_renderer.signed_until * total


def sharpness_floor(step: int, cfg_renderer: RendererConfig, total: int) -> float:
    """The floor on NeUDF's r at ``step``: geometric from sharpness_init to sharpness_floor_end; 0 when off.

    The NeuS baselines, and NeUDF's signed start, keep their learned s: their logistic weight is symmetric
    about the surface, so a small s blurs it without moving it."""
    start, end = cfg_renderer.sharpness_init, cfg_renderer.sharpness_floor_end
    if end <= 0 or cfg_renderer.weight != "neudf" or signed_phase(step, cfg_renderer, total):
        return 0.0
    progress = min(1.0, step / max(total, 1))
    return float(start * (end / start) ** progress)


def fit_schedule_to_iters(cfg: TrainConfig, iters: int | None) -> TrainConfig:
    """Set the iteration count; when it is shorter than the preset's, warm-up and annealing shrink in
    proportion, so a short run still runs the whole schedule."""
    if iters is None or iters == cfg.optim.iters:
        return cfg
    if iters <= 0:
        raise ValueError(f"--iters must be positive, got {iters}")
    data = cfg.model_dump()
    ratio = min(1.0, iters / cfg.optim.iters)
    data["optim"]["iters"] = iters
    data["optim"]["warmup_iters"] = int(cfg.optim.warmup_iters * ratio)
    data["renderer"]["cos_anneal_iters"] = int(cfg.renderer.cos_anneal_iters * ratio)
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
    cfg = load_saved_config(cfg_file.read_text())
    model = NeUDFModel(cfg).to(device)
    state = torch.load(ckpts[-1], map_location=device, weights_only=False)
    model.load_state_dict(state["model"])
    model.eval()
    return model


class Trainer:
    def __init__(self, data: Dataset, run_dir: Path, cfg: TrainConfig, device: str,
                 surface_points: torch.Tensor | None = None, surface_views: torch.Tensor | None = None):
        self.data, self.run_dir, self.cfg, self.device = data.to(device), run_dir, cfg, device
        # the object's sparse points, where the point-surface term pulls Psi to 0 (None: the term is off)
        self.surface_points = surface_points.float().to(device) if surface_points is not None else None
        # row for row, images that saw each of them, -1 after (None: the line-of-sight term is off)
        self.surface_views = surface_views.to(device) if surface_views is not None else None
        torch.manual_seed(cfg.seed)
        self.model = NeUDFModel(cfg).to(device)
        self.optimizer = torch.optim.Adam(self._param_groups(), lr=cfg.optim.lr)
        self.step = 0
        self.total = cfg.optim.iters  # the last iteration the schedules aim at; a time budget re-plans it
        self.elapsed_s = 0.0  # training seconds over every session of this run (a budget counts them all)
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
        with atomic_write(path, tmp=path.with_suffix(".tmp")) as tmp:  # readers glob *.pt: never half a one
            torch.save({"iter": self.step, "model": self.model.state_dict(),
                        "optimizer": self.optimizer.state_dict(), "rng": self.generator.get_state(),
                        "elapsed_s": self.elapsed_s}, tmp)
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
        self.elapsed_s = float(state.get("elapsed_s", 0.0))
        log.info("resumed %s at iteration %d", self.run_dir, self.step)
        return True

    # -- one step -----------------------------------------------------------------------------------
    def render_state(self, training: bool) -> RenderState:
        cfg = self.cfg
        return RenderState(
            cos_anneal=cos_anneal_ratio(self.step, cfg.renderer.cos_anneal_iters) if training else 1.0,
            perturb=training,
            with_grad=training,
            sharpness_floor=sharpness_floor(self.step, cfg.renderer, self.total)
            if cfg.renderer.sharpness_floor_mode == "clamp" else 0.0,
            signed=signed_phase(self.step, cfg.renderer, self.total),
        )

    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        lr = learning_rate(self.step, cfg.optim, self.total)
        for group in self.optimizer.param_groups:
            group["lr"] = lr * group["lr_scale"]
        batch = self.data.sample_rays(cfg.optim.rays, cfg.optim.images_per_batch, self.generator,
                                      cfg.optim.object_rays)
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
        if "near_points" in batch and cfg.loss.point_prior_weight > 0:
            loss = loss + cfg.loss.point_prior_weight * losses.opacity_off_points(out["weight_sum"],
                                                                                  batch["near_points"])
        fade = point_surface_scale(self.step, cfg.loss.point_surface_until, self.total)
        if self.surface_points is not None and fade > 0:
            loss = loss + fade * cfg.loss.point_surface_weight * losses.udf_at_points(self._udf_at_sparse_points())
        if self.surface_views is not None and fade > 0:
            loss = loss + fade * cfg.loss.point_sight_weight * self._surface_in_sight()
        # A signed field's inside is negative by rights: the term waits for the unsigned part of training.
        zero_region_on = (zero_region_started(self.step, cfg.loss.zero_region_from, self.total)
                          and not signed_phase(self.step, cfg.renderer, self.total))
        if cfg.loss.zero_region_weight > 0 and not self.model.signed and zero_region_on:
            loss = loss + cfg.loss.zero_region_weight * losses.zero_region(
                out["raw"], out["inside"], cfg.loss.zero_region_margin)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.step += 1
        self._lift_sharpness()
        return {"loss": float(loss.detach()), "color_loss": float(color_loss.detach()), "eikonal": float(eik.detach()),
                "psnr": losses.psnr(out["color"], batch["color"]), "sharpness": float(out["sharpness"]),
                "weight_sum": float(out["weight_sum"].detach().mean()), "lr": lr}

    def _lift_sharpness(self) -> None:
        """In ``lift`` mode the floor bounds the learned r itself, so the gradient reaches r above it."""
        floor = sharpness_floor(self.step, self.cfg.renderer, self.total)
        if self.cfg.renderer.sharpness_floor_mode == "lift" and floor > 0:
            self.model.sharpness.lift_to(floor)

    def _udf_at_sparse_points(self) -> torch.Tensor:
        pick = torch.randint(len(self.surface_points), (self.cfg.loss.point_surface_batch,), generator=self.generator)
        return self.model.udf(self.surface_points[pick.to(self.device)])

    def _surface_in_sight(self) -> torch.Tensor:
        """The line-of-sight term at a batch of anchors, each seen from one of the images that saw it."""
        cfg = self.cfg.loss
        pick = torch.randint(len(self.surface_points), (cfg.point_surface_batch,), generator=self.generator)
        views = self.surface_views[pick.to(self.device)]
        seen = (views >= 0).sum(1)  # the views come first in each row, -1 after
        column = (torch.rand(len(pick), generator=self.generator).to(self.device) * seen).long().clamp_max(seen - 1)
        view = views.gather(1, column[:, None].clamp_min(0)).squeeze(1)
        points, valid = sight_lines(self.surface_points[pick.to(self.device)], self.data.c2w[view, :3, 3],
                                    cfg.point_sight_gap, cfg.point_sight_samples)
        psi = self.model.udf(points.reshape(-1, 3)).reshape(points.shape[:2])
        return losses.surface_in_sight(psi, valid & (seen > 0), cfg.point_sight_margin)

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
        # the service serves the newest *.png: never a half-written one
        with atomic_write(path, tmp=folder / f".{self.step:07d}.tmp") as tmp:
            Image.fromarray((panel * 255).round().astype(np.uint8)).save(tmp, format="PNG")
        return path

    # -- the loop -----------------------------------------------------------------------------------
    def _plan(self, budget_s: float | None, session_start: int, session_s: float) -> None:
        """Re-plan the last iteration from the speed so far, so the schedules end when the budget does."""
        if budget_s is None:
            return
        done = self.step - session_start
        if done < 5:  # the first steps are slow (allocation, caches): no speed to trust yet
            return
        remaining = max(budget_s - self.elapsed_s, 0.0)
        planned = self.step + int(remaining / (session_s / done))
        self.total = max(self.step + 1, min(self.cfg.optim.iters, planned))

    def fit(self, progress: ProgressFn = null_progress, budget_s: float | None = None) -> dict[str, Any]:
        """Train to ``cfg.optim.iters``, or until ``budget_s`` seconds of training (over all sessions) are spent."""
        cfg = self.cfg
        metrics_file = self.run_dir / "metrics.jsonl"
        start_step, t0 = self.step, time.perf_counter()
        elapsed_before = self.elapsed_s
        window: list[dict[str, float]] = []
        last: dict[str, Any] = {}
        stopped_by = "iters"
        while self.step < min(self.total, cfg.optim.iters):
            stats = self.train_step()
            window.append(stats)
            session_s = time.perf_counter() - t0
            self.elapsed_s = elapsed_before + session_s
            self._plan(budget_s, start_step, session_s)
            out_of_time = budget_s is not None and self.elapsed_s >= budget_s
            if out_of_time:
                self.total, stopped_by = self.step, "budget"
            done = self.step - start_step
            eta = (max(budget_s - self.elapsed_s, 0.0) if budget_s is not None
                   else session_s / done * (self.total - self.step))
            fraction = min(self.elapsed_s / budget_s, 1.0) if budget_s is not None else self.step / self.total
            progress(fraction, f"iteration {self.step}/{self.total}", iter=self.step, loss=stats["loss"],
                     psnr=stats["psnr"], r=stats["sharpness"], s=cfg.sampler.s0, eta_s=eta)
            final = self.step >= self.total
            if self.step % cfg.log.log_every == 0 or final:
                last = {k: float(np.mean([w[k] for w in window])) for k in window[0]}
                last.update(iter=self.step, elapsed_s=round(self.elapsed_s, 3),
                            rays_per_s=round(done * cfg.optim.rays / max(session_s, 1e-9), 1))
                with metrics_file.open("a") as fh:
                    fh.write(json.dumps(last) + "\n")
                log.info("iter %d loss %.4f psnr %.2f r %.3g", self.step, last["loss"], last["psnr"],
                         last["sharpness"])
                window = []
            if self.step % cfg.log.ckpt_every == 0 or final:
                self.save()
            if self.step % cfg.log.val_every == 0 or final:
                self.validate(index=(self.step // max(cfg.log.val_every, 1)) % self.data.n_images)
        if budget_s is not None and self.elapsed_s >= budget_s:
            stopped_by = "budget"
        session_s = time.perf_counter() - t0
        return {"iters": self.step, "seconds": round(session_s, 2), "train_s": round(self.elapsed_s, 2),
                "run_dir": str(self.run_dir), "psnr": last.get("psnr"), "loss": last.get("loss"),
                "sharpness": last.get("sharpness"), "stopped_by": stopped_by,
                "iters_per_s": round((self.step - start_step) / max(session_s, 1e-9), 3)}


def surface_anchors(points: np.ndarray, floor_y: float | None) -> np.ndarray:
    """Which sparse points (a boolean mask) the point-surface term may pull the surface onto. Left out: those
    just above the floor cut (the floor's texture and the shadow: they draw a sheet of floor) and those with
    fewer than ANCHOR_NEIGHBOURS others within ANCHOR_RADIUS (a point of a textured object has neighbours;
    the floor's scatter and strays stand alone, and a lone point would grow a speck of surface)."""
    above = points[:, 1] > floor_y + FLOOR_SHADOW_BAND if floor_y is not None else np.ones(len(points), bool)
    every = torch.from_numpy(np.ascontiguousarray(points[above], dtype=np.float32))
    # counted in blocks of rows: a capture's few thousand points, without an N x N matrix at once
    others = torch.cat([(torch.cdist(block, every) <= ANCHOR_RADIUS).sum(1) - 1 for block in every.split(1024)]
                       ) if len(every) else torch.zeros(0, dtype=torch.long)
    keep = above.copy()
    keep[above] = (others >= ANCHOR_NEIGHBOURS).numpy()
    return keep


def anchor_views(data_dir: Path, points: np.ndarray, kept: np.ndarray) -> torch.Tensor | None:
    """The images that saw each anchor (rows of ``points[kept]``), or None when the capture did not record
    them or none of the anchors has one."""
    data_dir = Path(data_dir)
    views = read_object_point_views(data_dir, len(points), len(image_paths(data_dir)))
    if views is None or not (views[kept, 0] >= 0).any():
        return None
    return torch.from_numpy(views[kept].astype(np.int64))


def anchor_normals(points: torch.Tensor, radius: float = ANCHOR_RADIUS) -> torch.Tensor:
    """Unit normals (N, 3) of the anchors: the plane through each one's neighbours within ``radius`` (zeros
    where fewer than three points give no plane)."""
    normals = []
    for block in points.split(1024):
        near = (torch.cdist(block, points) <= radius).to(points.dtype)
        count = near.sum(1)
        mean = near @ points / count[:, None]
        second = torch.einsum("bn,ni,nj->bij", near, points, points) / count[:, None, None]
        _, vectors = torch.linalg.eigh(second - mean[:, :, None] * mean[:, None, :])
        normals.append(torch.where((count >= 3)[:, None], vectors[:, :, 0], torch.zeros_like(mean)))
    return torch.cat(normals) if normals else torch.zeros_like(points)


def clear_sight_views(points: torch.Tensor, views: torch.Tensor, centres: torch.Tensor, margin: float, gap: float
                      ) -> torch.Tensor:
    """``views`` (N, V; -1 padded) without the frames whose line of sight to the anchor would hold real
    cloth within ``margin``: where the line meets the anchor's own surface so obliquely that its end, ``gap``
    short of the anchor, lies within 1.5 margins of that surface's plane; and where it passes within 2
    margins of another anchor (its own neighbours within ANCHOR_RADIUS aside), as lines to the inner side of
    one leg do at the other leg. Kept frames come first in each row, as in ``views``."""
    rows, cols = (views >= 0).nonzero(as_tuple=True)
    target, centre = points[rows], centres[views[rows, cols]]
    offset = target - centre
    length = offset.norm(dim=-1)
    direction = offset / length.clamp_min(1e-9)[:, None]
    normals = anchor_normals(points)[rows]
    oblique = ((normals * direction).sum(-1).abs() < 1.5 * margin / max(gap, 1e-9)) & (normals.norm(dim=-1) > 0)
    passing = torch.zeros_like(oblique)
    for part in torch.arange(len(rows)).split(2048):  # lines x anchors, in blocks of lines
        towards = points[None] - centre[part, None]  # (L, N, 3)
        along = (towards * direction[part, None]).sum(-1)
        across = (towards - along[..., None] * direction[part, None]).norm(dim=-1)
        own = torch.cdist(target[part], points) <= ANCHOR_RADIUS
        on_line = (along > 0) & (along < (length[part] - gap)[:, None]) & ~own
        passing[part] = ((across < 2 * margin) & on_line).any(1)
    kept = views.clone()
    kept[rows[oblique | passing], cols[oblique | passing]] = -1
    order = torch.argsort((kept < 0).to(torch.int8), dim=1, stable=True)
    return kept.gather(1, order)


def resolve_start(cfg: TrainConfig, unanchored: bool) -> TrainConfig:
    """Fix the field's start where the options leave it open (``field.init_radius`` None). The signed
    baseline, and NeUDF with a signed start (``renderer.signed_until``), start as a sphere shell, as NeuS
    does. So does an unsigned field whose capture has sparse points but none that anchor the surface
    (``unanchored``), with the zero-region term held back so that the shell first shrinks onto the object. Otherwise an unsigned field starts as the distance to a point and
    grows where its anchors (or, on clean renders, its colours) are, which keeps lids off openings that a
    shell would cover."""
    if cfg.field.init_radius is not None:
        return cfg
    signed = cfg.renderer.weight == "neus_sdf" or cfg.renderer.signed_until > 0
    shell = signed or unanchored
    update = {"field": cfg.field.model_copy(update={"init_radius": SPHERE_START_RADIUS if shell else 0.0})}
    if shell and not signed:
        update["loss"] = cfg.loss.model_copy(update={
            "zero_region_from": max(cfg.loss.zero_region_from, SPHERE_START_ZERO_REGION_FROM)})
    return cfg.model_copy(update=update)


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
    preset: str | None = None,
    iters: int | None = None,
    minutes: float | None = None,
    device: str = "cpu",
    progress: ProgressFn = null_progress,
    overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train NeUDF on a NeuS-layout dataset into ``run_dir``; resumes from the run's last checkpoint.

    ``preset``: default the device's (quick on a CPU, gpu on CUDA).
    ``minutes``: a training budget (wall clock, over every session of the run); the learning-rate and
    sharpness schedules are planned from the speed measured as it trains, so they end with the budget.
    With a budget and no ``iters`` the run stops on time alone; with both, at whichever comes first.
    """
    device = _check_device(device)
    preset = preset or default_preset(device)
    flush_denormals()
    run_dir = Path(run_dir)
    if minutes is not None and minutes <= 0:
        raise ValueError(f"--minutes must be positive, got {minutes}")
    if minutes is not None and iters is None:
        iters = BUDGET_MAX_ITERS
    cfg = fit_schedule_to_iters(load_config(preset, overrides), iters)
    floor = read_floor(data_dir)
    if floor is not None and cfg.data.floor_y is None:
        cfg = cfg.model_copy(update={"data": cfg.data.model_copy(update={"floor_y": floor})})
    uses_points = cfg.loss.point_prior_weight > 0 or cfg.loss.point_surface_weight > 0
    captured = read_object_points(data_dir) if uses_points else None
    points = captured if captured is not None and len(captured) >= MIN_PRIOR_POINTS else None
    surface_points = surface_views = None
    if points is not None and cfg.loss.point_surface_weight > 0:
        kept = surface_anchors(points, cfg.data.floor_y)
        surface_points = torch.from_numpy(points[kept]) if kept.sum() >= MIN_PRIOR_POINTS else None
        if surface_points is not None and cfg.loss.point_sight_weight > 0:
            surface_views = anchor_views(data_dir, points, kept)
    # a capture whose sparse points anchor nothing: the object is smooth or plain where the term relies on them
    unanchored = cfg.loss.point_surface_weight > 0 and captured is not None and surface_points is None
    asked, cfg = cfg, resolve_start(cfg, unanchored)
    cfg_file = run_dir / "config.json"
    if cfg_file.is_file() and _checkpoints(run_dir):
        stored = load_saved_config(cfg_file.read_text())
        if stored.field.init_radius is None and asked.field.init_radius is None:
            # saved before the start was resolved from the capture: it started as the model then chose
            # (a shell when signed, a point otherwise), and the run keeps that start
            stored, cfg = resolve_start(stored, False), resolve_start(asked, False)
        if stored.model_dump(exclude=_SCHEDULE_FIELDS) != cfg.model_dump(exclude=_SCHEDULE_FIELDS):
            raise RunError(f"{run_dir} holds a run with another configuration (preset {stored.preset!r}); "
                           "pick a new --out folder or the same options to resume it")
    data = load_dataset(data_dir, cfg.data.max_size, cfg.data.use_masks, cfg.data.sphere_px)
    if cfg.optim.object_rays > 0:
        data.find_object_pixels()
    if points is not None and cfg.loss.point_prior_weight > 0:
        data.find_near_points(torch.from_numpy(points), cfg.loss.point_prior_radius)
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg_file.write_text(cfg.model_dump_json(indent=2))
    if surface_views is not None and cfg.loss.point_sight_clear:
        surface_views = clear_sight_views(surface_points, surface_views, data.c2w[:, :3, 3],
                                          cfg.loss.point_sight_margin, cfg.loss.point_sight_gap)
    trainer = Trainer(data, run_dir, cfg, device, surface_points, surface_views)
    trainer.resume()
    result = trainer.fit(progress, budget_s=minutes * 60 if minutes is not None else None)
    result.update(preset=cfg.preset, device=device, images=data.n_images, image_size=[data.width, data.height],
                  start="point" if cfg.field.init_radius == 0 else "sphere")
    if cfg.loss.point_surface_weight > 0:  # 0: the term was on in the options but had nothing to hold
        result["surface_points"] = 0 if surface_points is None else len(surface_points)
    if cfg.loss.point_sight_weight > 0:  # anchors whose lines of sight were kept clear
        result["sight_points"] = 0 if surface_views is None else int((surface_views[:, 0] >= 0).sum())
    if minutes is not None:
        result["minutes"] = minutes
    return result
