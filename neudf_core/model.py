"""NeUDF as one module: the fields, and the path of a ray batch through sampler, renderer and normals."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from neudf_core.config import TrainConfig
from neudf_core.fields import BackgroundNeRF, ColorNetwork, FloorTexture, HashGridEncoding, Sharpness, UDFNetwork
from neudf_core.normals import regularised_normals
from neudf_core.renderer import alpha_for_mode, composite, section_ends, weights_from_alpha
from neudf_core.sampler import hierarchical_samples, near_far_from_sphere, outside_samples, stratified


@dataclass
class RenderState:
    """What changes with the training step and is not a weight: annealing and sampling switches."""

    cos_anneal: float = 1.0
    perturb: bool = False
    with_grad: bool = False  # keep the graph through gradients (the eikonal term needs it)
    sharpness_floor: float = 0.0  # lower bound on r at this step (see trainer.sharpness_floor); 0 = none
    signed: bool = False  # render h, the field before |.|, as a signed distance with NeuS's weight


class NeUDFModel(nn.Module):
    def __init__(self, cfg: TrainConfig):
        super().__init__()
        self.cfg = cfg
        f, c, b = cfg.field, cfg.color, cfg.background
        self.signed = cfg.renderer.weight == "neus_sdf"
        # An unsigned field starts as the distance to the origin: unit gradient everywhere and no region
        # where the output Softplus is saturated (a solid ball's inside would be Psi = 0 with no gradient
        # to leave it). The signed baseline starts as NeuS does, from a sphere.
        radius = f.init_radius if f.init_radius is not None else (0.5 if self.signed else 0.0)
        encoding = (HashGridEncoding(f.hash_levels, f.hash_features, f.hash_log2_table, f.hash_base_res,
                                     f.hash_max_res) if f.encoding == "hashgrid" else None)
        self.udf_net = UDFNetwork(f.d_hidden, f.n_layers, f.skip_in, f.n_freqs, f.d_feature, radius,
                                  use_weight_norm=f.use_weight_norm, signed=self.signed, encoding=encoding,
                                  output=f.output)
        self.color_net = ColorNetwork(f.d_feature, c.d_hidden, c.n_layers, c.n_freqs_view,
                                      view_dependent=c.view_dependent)
        self.background = (BackgroundNeRF(b.d_hidden, b.n_layers, b.n_freqs, view_dependent=b.view_dependent)
                           if self._use_background() else None)
        self.floor = (FloorTexture(b.d_hidden, max(b.n_layers - 1, 1), b.floor_freqs)
                      if self.background is not None and b.floor else None)
        self.sharpness = Sharpness(cfg.renderer.sharpness_init)

    def _use_background(self) -> bool:
        return not self.cfg.data.use_masks and not self.cfg.data.white_background

    # -- the field as a function of space: the entry points meshing and evaluation use --------------
    def udf(self, x: Tensor) -> Tensor:
        """Psi(x) for points (N, 3) in unit-sphere coordinates; signed f for the NeuS-SDF baseline."""
        return self.udf_net(x)[0]

    def udf_and_grad(self, x: Tensor, create_graph: bool = False) -> tuple[Tensor, Tensor, Tensor]:
        """(Psi (N,), grad Psi (N, 3), feature (N, F))."""
        psi, _, grad, feature = self._field(x, create_graph)
        return psi, grad, feature

    def _field(self, x: Tensor, create_graph: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(Psi, h before the output activation, grad Psi, feature)."""
        if self.cfg.field.gradient == "finite_difference":
            return self._udf_and_fd_grad(x)
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            psi, raw, feature = self.udf_net.forward_with_raw(x)
            (grad,) = torch.autograd.grad(psi.sum(), x, create_graph=create_graph)
        return psi, raw, grad, feature

    def _udf_and_fd_grad(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Tetrahedral finite differences: 4 more evaluations and a first-order graph only (no double
        backward), which is what makes hash grids cheap to regularise."""
        eps = self.cfg.field.fd_eps
        tetra = torch.tensor([[1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0]],
                             device=x.device)
        shifted = (x[:, None, :] + eps * tetra[None]).reshape(-1, 3)
        psi_all, raw_all, feature_all = self.udf_net.forward_with_raw(torch.cat([x, shifted]))
        n = x.shape[0]
        around = psi_all[n:].reshape(n, 4)
        grad = (around[..., None] * tetra[None]).sum(1) / (4 * eps)
        return psi_all[:n], raw_all[:n], grad, feature_all[:n]

    def color(self, x: Tensor, normal: Tensor, view_dir: Tensor) -> Tensor:
        """RGB in 0..1 of points seen along ``view_dir`` with surface normal ``normal``."""
        _, feature = self.udf_net(x)
        return self.color_net(x, view_dir, normal, feature)

    # -- volume rendering ---------------------------------------------------------------------------
    def render(self, rays_o: Tensor, rays_d: Tensor, state: RenderState, bg_color: Tensor | None = None) -> dict:
        """Render a batch of rays (R, 3). Returns a flat dict of named outputs (see the keys below)."""
        cfg_s, cfg_r = self.cfg.sampler, self.cfg.renderer
        near, far = near_far_from_sphere(rays_o, rays_d)
        z = stratified(near, far, cfg_s.n_coarse, state.perturb)
        # The zeta_s sampler reads the unsigned distance, so the SDF baseline samples around |f| = 0.
        z = hierarchical_samples(rays_o, rays_d, z, lambda p: self.udf(p).abs(), cfg_s.n_importance,
                                 cfg_s.n_rounds, cfg_s.s0, deterministic=not state.perturb)
        # Sections between consecutive depths; the last one gets the coarse spacing, as in NeuS.
        dists = torch.cat([z[:, 1:] - z[:, :-1], ((far - near) / cfg_s.n_coarse)[:, None]], -1)
        mid_z = z + 0.5 * dists
        points = rays_o[:, None] + rays_d[:, None] * mid_z[..., None]
        n_rays, n_samples = mid_z.shape
        flat = points.reshape(-1, 3)
        psi, raw, grad, feature = self._field(flat, create_graph=state.with_grad)
        psi, raw, grad = psi.reshape(n_rays, n_samples), raw.reshape(n_rays, n_samples), grad.reshape(n_rays, n_samples, 3)
        if not state.with_grad:
            grad = grad.detach()
        value, mode, signed = psi, cfg_r.weight, self.signed
        if state.signed and not self.signed:
            # Psi = |h|: h and its gradient, sign(h) grad Psi, make the signed field NeuS renders.
            value, mode, signed = raw, "neus_sdf", True
            grad = torch.where(raw[..., None] < 0, -grad, grad)

        sharp = self.sharpness()
        if state.sharpness_floor > 0:
            sharp = sharp.clamp_min(state.sharpness_floor)
        if cfg_r.section == "samples":
            # The paper's literal form: the two ends of a section are consecutive samples.
            prev, nxt = value, torch.cat([value[:, 1:], value[:, -1:]], -1)
        else:
            cos = (rays_d[:, None] * grad).sum(-1)
            prev, nxt = section_ends(value, cos, dists, state.cos_anneal, signed=signed)
        alpha = alpha_for_mode(mode, prev, nxt, sharp, cfg_r.varsigma, cfg_r.receding_opacity)

        inside = (points.norm(dim=-1) < 1.0).float()
        if self.cfg.data.floor_y is not None:
            # Under the floor the scene stage found there is no object: the floor and the shadows on it are
            # left to the background model, so they cannot become surface.
            inside = inside * (points[..., 1] > self.cfg.data.floor_y).float()
        if self.background is not None:
            alpha = alpha * inside  # beyond the sphere the background model owns the ray
        weights, transmittance = weights_from_alpha(alpha)

        normals = regularised_normals(points, grad)
        view_dirs = rays_d[:, None].expand(-1, n_samples, -1).reshape(-1, 3)
        rgb = self.color_net(flat, view_dirs, normals.reshape(-1, 3), feature).reshape(n_rays, n_samples, 3)
        color = composite(weights, rgb)

        if self.background is not None:
            bg = self._render_background(rays_o, rays_d, far, state.perturb)
            if self.floor is not None and self.cfg.data.floor_y is not None:
                bg = self._floor_over_background(rays_o, rays_d, bg)
        elif bg_color is not None:
            bg = bg_color.expand_as(color)
        else:
            bg = torch.zeros_like(color)
        color = color + transmittance[:, None] * bg

        return {
            "color": color,
            "weight_sum": weights.sum(-1),
            "depth": (weights * mid_z).sum(-1),
            "weights": weights,
            "psi": psi,
            "raw": raw,
            "gradients": grad,
            "normals": normals,
            "inside": inside,
            "sharpness": sharp.detach(),
            "mid_z": mid_z,
        }

    def _floor_over_background(self, rays_o: Tensor, rays_d: Tensor, bg: Tensor) -> Tensor:
        """Rays from above going down that meet the floor plane inside the sphere end there, in the floor's
        colour; the rest keep the background's."""
        floor_y = self.cfg.data.floor_y
        down = (rays_d[:, 1] < -1e-6) & (rays_o[:, 1] > floor_y)
        t = (floor_y - rays_o[:, 1]) / torch.where(down, rays_d[:, 1], -torch.ones_like(rays_d[:, 1]))
        hit_point = rays_o + rays_d * t[:, None]
        hit = down & (hit_point.norm(dim=-1) <= 1.0)
        return torch.where(hit[:, None], self.floor(hit_point[:, [0, 2]]), bg)

    def _render_background(self, rays_o: Tensor, rays_d: Tensor, far: Tensor, perturb: bool) -> Tensor:
        z = outside_samples(far, self.cfg.background.n_samples, perturb)
        pts = rays_o[:, None] + rays_d[:, None] * z[..., None]
        view = rays_d[:, None].expand_as(pts)
        sigma, rgb = self.background(pts.reshape(-1, 3), view.reshape(-1, 3))
        # In inverted-sphere space the natural step is the change of 1/|x|; far samples get long sections.
        delta = torch.cat([z[:, 1:] - z[:, :-1], torch.full_like(z[:, :1], 1e10)], -1)
        alpha = 1.0 - torch.exp(-sigma.reshape(z.shape) * delta / z.clamp_min(1e-3))
        w, _ = weights_from_alpha(alpha)
        return composite(w, rgb.reshape(*z.shape, 3))
