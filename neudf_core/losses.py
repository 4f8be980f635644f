"""Loss terms (paper Sec. 3.4: L = L_c + alpha L_e + beta L_m), the zero-region penalty and the sparse-point
priors."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def color_l1(pred: Tensor, target: Tensor) -> Tensor:
    """L_c: mean absolute error of rendered against observed colours."""
    return (pred - target).abs().mean()


def eikonal(gradients: Tensor, valid: Tensor) -> Tensor:
    """L_e: (|grad Psi| - 1)^2 averaged over valid samples (inside a relaxed sphere)."""
    err = (gradients.norm(dim=-1) - 1.0).pow(2)
    return (err * valid).sum() / valid.sum().clamp_min(1.0)


def mask_bce(weight_sum: Tensor, mask: Tensor) -> Tensor:
    """L_m: binary cross-entropy between accumulated opacity and the object mask."""
    return F.binary_cross_entropy(weight_sum.clamp(1e-3, 1.0 - 1e-3), mask)


def zero_region(raw: Tensor, valid: Tensor, margin: float) -> Tensor:
    """Penalty on a UDF that is zero over a volume instead of on a surface (not in the paper).

    ``raw`` is h, the field before its output activation (Psi = Softplus_beta(h) or |h|). With Softplus,
    where h is well below 0 Psi ~ 0 and its gradient is ~0 too, so the eikonal term cannot lift the region
    again; a true UDF needs h below ~-margin only within a hair of its zero set (h = -0.03 is Psi = 5e-4 at
    beta = 100). With |h|, h < 0 is a second, sign-flipped copy of the field: left free it grows an SDF-like
    inside whose sign changes are surfaces of their own. relu(-h - margin) acts on both.
    """
    return (torch.relu(-raw.float() - margin) * valid).sum() / valid.sum().clamp_min(1.0)


def opacity_off_points(weight_sum: Tensor, near_points: Tensor) -> Tensor:
    """The object's opacity on rays that pass no sparse point of the object, averaged over all rays (not in
    the paper). Without masks, nothing else stops the object's field from drawing the room on a screen
    inside the sphere; a sparse point is a feature seen from several views, which a screen cannot make."""
    return (weight_sum * (1.0 - near_points)).mean()


def udf_at_points(psi: Tensor) -> Tensor:
    """Mean Psi at sparse points of the object (not in the paper; Geo-NeuS supervises an SDF so). A point
    triangulated from several views lies on the surface; L1, so a stray point pulls less than a square would."""
    return psi.float().abs().mean()


def surface_in_sight(psi: Tensor, valid: Tensor, margin: float) -> Tensor:
    """Surface on the lines of sight to anchors (not in the paper): relu(margin - Psi) summed along each line
    (B, n), averaged over the ``valid`` lines (B,). A frame that saw a sparse point saw nothing in front of
    it; a UDF can meet the point with a sheet behind the one the frame sees, and this rules that out."""
    along = torch.relu(margin - psi.float().abs()).sum(-1)
    return (along * valid).sum() / valid.sum().clamp_min(1)


def psnr(pred: Tensor, target: Tensor) -> float:
    mse = (pred.detach() - target).pow(2).mean().clamp_min(1e-10)
    return float(-10.0 * torch.log10(mse))
