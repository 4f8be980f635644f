"""Normal regularisation (paper Sec. 3.3, Eq. 9).

The UDF has a cusp on its zero set: the gradient flips direction across the surface and is unstable
near it, while the colour network needs a steady normal. The paper replaces the normal at sample i by a
weighted mean of the gradients at the K previous samples on the ray,

    n(p_i) = sum_k w_{i-k} grad Psi(p_{i-k}) / sum_k w_{i-k},   w_{i-k} = ||p_i - p_{i-k}||^2,

so farther (and therefore off-cusp) samples count more. The first sample of a ray has no predecessor
and keeps its own gradient.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def regularised_normals(points: Tensor, gradients: Tensor, k_neighbours: int = 5) -> Tensor:
    """points, gradients: (R, S, 3) in ray order. Returns the regularised normals, (R, S, 3)."""
    if k_neighbours <= 0:
        return gradients
    numerator = torch.zeros_like(gradients)
    denominator = torch.zeros_like(gradients[..., :1])
    n_samples = points.shape[1]
    for k in range(1, min(k_neighbours, n_samples - 1) + 1):
        # Shift by k along the ray, with zeros where sample i has no (i - k)-th predecessor.
        w = F.pad((points[:, k:] - points[:, :-k]).pow(2).sum(dim=-1, keepdim=True), (0, 0, k, 0))
        numerator = numerator + w * F.pad(gradients[:, :-k], (0, 0, k, 0))
        denominator = denominator + w
    has_history = denominator > 0
    return torch.where(has_history, numerator / denominator.clamp_min(1e-12), gradients)
