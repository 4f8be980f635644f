"""Where to put samples along a ray: coarse stratified depths, zeta_s importance sampling, outside samples.

The importance sampler is deliberately *not* the rendering weight (paper Sec. 3.2, "Importance points
sampling"): it uses classical volume rendering of tau_s = zeta_s(Psi), a logistic density of the UDF
that is symmetric about the surface, so the eikonal term sees samples on both sides of it. The weights
are max-filtered over neighbours (k = -1, 0, 1), normalised, and inverted (inverse CDF).
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor


def near_far_from_sphere(rays_o: Tensor, rays_d: Tensor, radius: float = 1.0) -> tuple[Tensor, Tensor]:
    """Depths where the ray enters and leaves the sphere; rays that miss get the chord at closest approach.

    Cameras sit outside the sphere, so ``near`` is positive.
    """
    b = (rays_o * rays_d).sum(-1)
    c = (rays_o * rays_o).sum(-1) - radius**2
    half_chord = torch.sqrt((b * b - c).clamp_min(0.0))
    mid = -b
    # A ray that grazes or misses still gets a thin section, so that the background takes over.
    half_chord = half_chord.clamp_min(1e-2)
    near = (mid - half_chord).clamp_min(1e-2)
    far = torch.maximum(mid + half_chord, near + 2e-2)
    return near, far


def stratified(near: Tensor, far: Tensor, n: int, perturb: bool) -> Tensor:
    """n depths per ray evenly spread over [near, far]; jittered within their bins when ``perturb``."""
    u = torch.linspace(0.0, 1.0, n, device=near.device)
    u = u.expand(near.shape[0], n)
    if perturb:
        u = u + (torch.rand_like(u) - 0.5) / n
        u = u.clamp(0.0, 1.0).sort(dim=-1).values
    return near[:, None] + (far - near)[:, None] * u


def sight_lines(targets: Tensor, centres: Tensor, gap: float, n: int) -> tuple[Tensor, Tensor]:
    """n jittered points (B, n, 3) on each line of sight from a camera centre to ``gap`` short of the point it
    saw, within the unit sphere; and which lines (B,) have such a stretch."""
    offset = targets - centres
    length = offset.norm(dim=-1).clamp_min(1e-9)
    dirs = offset / length[:, None]
    near, _ = near_far_from_sphere(centres, dirs)
    far = length - gap
    depths = stratified(near, torch.maximum(far, near), n, perturb=True)
    return centres[:, None] + dirs[:, None] * depths[..., None], far > near


def outside_samples(far: Tensor, n: int, perturb: bool) -> Tensor:
    """n depths beyond ``far`` spread evenly in inverse depth up to near-infinity (NeRF++)."""
    u = torch.linspace(1e-3, 1.0 - 1.0 / (n + 1), n, device=far.device).expand(far.shape[0], n)
    if perturb:
        u = (u + (torch.rand_like(u) - 0.5) / (n + 1)).clamp(1e-3, 1.0 - 1e-3)
    inv = u.sort(dim=-1, descending=True).values  # inverse depth: far -> near-infinity
    return far[:, None] / inv


def zeta(d: Tensor, s: float) -> Tensor:
    """zeta_s(d) = s e^{-s d} / (1 + e^{-s d})^2, the logistic density: positive, decreasing for d > 0."""
    return s * torch.sigmoid(s * d) * torch.sigmoid(-s * d)


def importance_weights(z: Tensor, psi: Tensor, s: float) -> Tensor:
    """w''_s per interval between consecutive depths: (R, S) depths and UDFs -> (R, S-1), rows sum to 1."""
    delta = z[:, 1:] - z[:, :-1]
    psi_mid = 0.5 * (psi[:, 1:] + psi[:, :-1])
    alpha = 1.0 - torch.exp(-zeta(psi_mid, s) * delta)
    ones = torch.ones_like(alpha[:, :1])
    w = alpha * torch.cumprod(torch.cat([ones, 1.0 - alpha + 1e-7], -1), -1)[:, :-1]
    # w'_s(t_i) = max(w_s(t_{i-1}), w_s(t_i), w_s(t_{i+1})): a surface caught by one interval widens to three.
    w = F.max_pool1d(w[:, None], kernel_size=3, stride=1, padding=1)[:, 0]
    w = w + 1e-5  # a ray that sees nothing still samples somewhere
    return w / w.sum(-1, keepdim=True)


def sample_pdf(bins: Tensor, weights: Tensor, n: int, deterministic: bool) -> Tensor:
    """Inverse-CDF sampling of n depths from piecewise-constant weights over the intervals of ``bins``."""
    cdf = torch.cumsum(weights, -1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], -1)
    if deterministic:
        u = torch.linspace(0.5 / n, 1.0 - 0.5 / n, n, device=bins.device).expand(bins.shape[0], n)
    else:
        u = torch.rand(bins.shape[0], n, device=bins.device)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True)
    below = (idx - 1).clamp(0, cdf.shape[-1] - 1)
    above = idx.clamp(0, cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = cdf.gather(-1, below), cdf.gather(-1, above)
    bin_lo, bin_hi = bins.gather(-1, below), bins.gather(-1, above)
    span = torch.where(cdf_hi - cdf_lo < 1e-5, torch.ones_like(cdf_hi), cdf_hi - cdf_lo)
    return bin_lo + (u - cdf_lo) / span * (bin_hi - bin_lo)


def hierarchical_samples(
    rays_o: Tensor,
    rays_d: Tensor,
    z: Tensor,
    udf_fn: Callable[[Tensor], Tensor],
    n_importance: int,
    n_rounds: int,
    s0: float,
    deterministic: bool,
) -> Tensor:
    """Add ``n_importance`` depths in ``n_rounds`` rounds of zeta_s sampling, s doubling each round.

    ``udf_fn`` maps (N, 3) points to (N,) UDF values; it is called without gradients.
    """
    if n_importance <= 0 or n_rounds <= 0:
        return z
    per_round = n_importance // n_rounds
    with torch.no_grad():
        psi = udf_fn((rays_o[:, None] + rays_d[:, None] * z[..., None]).reshape(-1, 3)).reshape(z.shape)
        s = s0
        for _ in range(n_rounds):
            new_z = sample_pdf(z, importance_weights(z, psi, s), per_round, deterministic)
            new_psi = udf_fn((rays_o[:, None] + rays_d[:, None] * new_z[..., None]).reshape(-1, 3))
            z, order = torch.cat([z, new_z], -1).sort(-1)
            psi = torch.cat([psi, new_psi.reshape(new_z.shape)], -1).gather(-1, order)
            s *= 2.0
    return z
