"""The networks of NeUDF: the unsigned distance field Psi, the colour field, the NeRF++ background.

Shapes follow the paper's supplement (Sec. "Network Architecture"): Psi is an 8x256 MLP on positionally
encoded points with a skip into layer 4, weight normalisation and Softplus(beta=100) on the hidden layers
*and* on the output, so Psi >= 0 everywhere. The colour network sees the point, the encoded view
direction, the (regularised) normal and Psi's feature vector; without the view direction when asked
(``color.view_dependent``), so that a lid over an opening cannot paint the inside's parallax on itself.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm as _weight_norm


class PositionalEncoding(nn.Module):
    """NeRF/NeuS encoding: [x, sin(2^k x), cos(2^k x) for k < n_freqs]."""

    def __init__(self, n_freqs: int, d_in: int = 3):
        super().__init__()
        self.register_buffer("freqs", 2.0 ** torch.arange(n_freqs, dtype=torch.float32), persistent=False)
        self.d_out = d_in * (1 + 2 * n_freqs)

    def forward(self, x: Tensor) -> Tensor:
        if len(self.freqs) == 0:
            return x
        scaled = x[..., None, :] * self.freqs[:, None]  # (..., F, d)
        enc = torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-1).flatten(-2)
        return torch.cat([x, enc], dim=-1)


class HashGridEncoding(nn.Module):
    """Multiresolution hash encoding (Mueller et al., Instant NGP), in plain PyTorch.

    Level l has resolution floor(base * b^l) cells per axis over [-bound, bound]^3; coarse levels whose
    grid fits in the table are stored densely, finer ones hashed with the Instant-NGP primes. Features
    of the 8 cell corners are blended trilinearly. Output: (N, 3 + n_levels * n_features), the raw
    point first so a geometric initialisation of the next layer still applies.
    """

    _PRIMES = (1, 2654435761, 805459861)

    def __init__(self, n_levels: int = 16, n_features: int = 2, log2_table: int = 19, base_res: int = 16,
                 max_res: int = 2048, bound: float = 1.0):
        super().__init__()
        growth = math.exp((math.log(max_res) - math.log(base_res)) / max(n_levels - 1, 1))
        res = [int(math.floor(base_res * growth**level)) for level in range(n_levels)]
        size = 2**log2_table
        self.bound, self.table_size, self.n_features = bound, size, n_features
        self.register_buffer("res", torch.tensor(res, dtype=torch.long), persistent=False)
        self.register_buffer("dense", torch.tensor([(r + 1) ** 3 <= size for r in res]), persistent=False)
        self.register_buffer("offsets", torch.arange(n_levels, dtype=torch.long) * size, persistent=False)
        corners = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.long)
        self.register_buffer("corners", corners, persistent=False)
        self.register_buffer("primes", torch.tensor(self._PRIMES, dtype=torch.long), persistent=False)
        # Small initial features: the field starts as what the MLP makes of the raw point alone.
        self.table = nn.Parameter(torch.empty(n_levels * size, n_features).uniform_(-1e-4, 1e-4))
        self.d_out = 3 + n_levels * n_features

    def forward(self, x: Tensor) -> Tensor:
        u = ((x + self.bound) / (2 * self.bound)).clamp(0.0, 1.0)
        pos = u[:, None, :] * self.res[None, :, None].float()  # (N, L, 3)
        cell = pos.floor().long().clamp_max(self.res[None, :, None] - 1)
        frac = pos - cell.float()
        corner = cell[:, :, None, :] + self.corners[None, None]  # (N, L, 8, 3)
        stride = (self.res + 1)[None, :, None]
        dense_idx = corner[..., 0] + corner[..., 1] * stride + corner[..., 2] * stride * stride
        hashed = corner * self.primes
        hash_idx = (hashed[..., 0] ^ hashed[..., 1] ^ hashed[..., 2]) % self.table_size
        idx = torch.where(self.dense[None, :, None], dense_idx, hash_idx) + self.offsets[None, :, None]
        feats = self.table[idx]  # (N, L, 8, F)
        w = torch.where(self.corners[None, None].bool(), frac[:, :, None, :], 1.0 - frac[:, :, None, :]).prod(-1)
        out = (w[..., None] * feats).sum(2).flatten(1)
        return torch.cat([x, out], dim=-1)


def _linear(d_in: int, d_out: int, use_weight_norm: bool) -> nn.Linear:
    layer = nn.Linear(d_in, d_out)
    return _weight_norm(layer) if use_weight_norm else layer


class UDFNetwork(nn.Module):
    """Psi: R^3 -> R_{>=0} (or R for the NeuS-SDF baseline) plus a feature vector.

    Initialisation: IDR's geometric init makes the pre-activation output |x| - radius. With radius 0 the
    unsigned field starts as the UDF of a point (the origin), a valid distance field with unit gradient
    everywhere. For ``signed=True`` it is the SDF of a sphere of that radius, as NeuS starts from.
    """

    def __init__(
        self,
        d_hidden: int = 256,
        n_layers: int = 8,
        skip_in: tuple[int, ...] = (4,),
        n_freqs: int = 6,
        d_feature: int = 256,
        init_radius: float = 0.5,
        use_weight_norm: bool = True,
        signed: bool = False,
        encoding: nn.Module | None = None,
        output: Literal["softplus", "abs"] = "softplus",
    ):
        super().__init__()
        self.encoding = encoding if encoding is not None else PositionalEncoding(n_freqs)
        self.signed = signed
        self.output = output
        self.skip_in = set(skip_in)
        self.d_feature = d_feature
        dims = [self.encoding.d_out] + [d_hidden] * n_layers + [1 + d_feature]
        d_in = dims[0]
        layers = []
        for i in range(len(dims) - 1):
            out_dim = dims[i + 1] - d_in if (i + 1) in self.skip_in else dims[i + 1]
            layer = nn.Linear(dims[i], out_dim)
            self._geometric_init(layer, i, len(dims) - 2, d_in, out_dim, init_radius)
            layers.append(_weight_norm(layer) if use_weight_norm else layer)
        self.layers = nn.ModuleList(layers)
        self.activation = nn.Softplus(beta=100.0)

    def _geometric_init(self, layer: nn.Linear, i: int, last: int, d_in: int, out_dim: int, radius: float) -> None:
        """IDR / SAL geometric initialisation: the network starts as the SDF of a sphere."""
        with torch.no_grad():
            if i == last:
                nn.init.normal_(layer.weight, mean=math.sqrt(math.pi) / math.sqrt(layer.in_features), std=1e-4)
                nn.init.constant_(layer.bias, -radius)
            elif i == 0:
                # Only the raw coordinates feed the first layer at init; the encoding starts silent.
                nn.init.constant_(layer.bias, 0.0)
                nn.init.constant_(layer.weight[:, 3:], 0.0)
                nn.init.normal_(layer.weight[:, :3], 0.0, math.sqrt(2) / math.sqrt(out_dim))
            elif i in self.skip_in:
                nn.init.constant_(layer.bias, 0.0)
                nn.init.normal_(layer.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))
                if d_in > 3:
                    nn.init.constant_(layer.weight[:, -(d_in - 3):], 0.0)
            else:
                nn.init.constant_(layer.bias, 0.0)
                nn.init.normal_(layer.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Returns (psi (N,), feature (N, d_feature))."""
        psi, _, feature = self.forward_with_raw(x)
        return psi, feature

    def forward_with_raw(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(psi, h, feature): h is the last layer's value before the output activation (psi = h if signed)."""
        inputs = self.encoding(x)
        h = inputs
        for i, layer in enumerate(self.layers):
            if i in self.skip_in:
                h = torch.cat([h, inputs], dim=-1) / math.sqrt(2)
            h = layer(h)
            if i < len(self.layers) - 1:
                h = self.activation(h)
        raw = h[:, 0]
        value = raw
        if not self.signed:
            # Psi >= 0: the paper's Softplus on the output, or |h|
            value = raw.abs() if self.output == "abs" else self.activation(raw)
        return value, raw, h[:, 1:]


class ColorNetwork(nn.Module):
    """c(x, v, n, feature) -> RGB in (0, 1); c(x, n, feature) when ``view_dependent`` is False."""

    def __init__(self, d_feature: int = 256, d_hidden: int = 256, n_layers: int = 4, n_freqs_view: int = 4,
                 use_weight_norm: bool = True, view_dependent: bool = True):
        super().__init__()
        self.view_encoding = PositionalEncoding(n_freqs_view) if view_dependent else None
        d_view = self.view_encoding.d_out if self.view_encoding is not None else 0
        dims = [3 + d_view + 3 + d_feature] + [d_hidden] * n_layers + [3]
        self.layers = nn.ModuleList(_linear(a, b, use_weight_norm) for a, b in zip(dims[:-1], dims[1:]))

    def forward(self, x: Tensor, view_dirs: Tensor, normals: Tensor, features: Tensor) -> Tensor:
        views = [self.view_encoding(view_dirs)] if self.view_encoding is not None else []
        h = torch.cat([x, *views, normals, features], dim=-1)
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < len(self.layers) - 1:
                h = torch.relu(h)
        return torch.sigmoid(h)


class BackgroundNeRF(nn.Module):
    """NeRF++'s outside model: density and colour of points beyond the unit sphere, in inverted-sphere
    coordinates (x/|x|, 1/|x|) so that infinity is a finite place."""

    def __init__(self, d_hidden: int = 256, n_layers: int = 8, n_freqs: int = 10, n_freqs_view: int = 4,
                 skip_in: tuple[int, ...] = (4,), view_dependent: bool = True):
        super().__init__()
        self.encoding = PositionalEncoding(n_freqs, d_in=4)
        self.view_encoding = PositionalEncoding(n_freqs_view) if view_dependent else None
        self.skip_in = set(skip_in)
        d_in = self.encoding.d_out
        layers = []
        for i in range(n_layers):
            d = d_in if i == 0 else d_hidden + (d_in if i in self.skip_in else 0)
            layers.append(nn.Linear(d, d_hidden))
        self.layers = nn.ModuleList(layers)
        self.density = nn.Linear(d_hidden, 1)
        self.feature = nn.Linear(d_hidden, d_hidden)
        d_view = self.view_encoding.d_out if self.view_encoding is not None else 0
        self.rgb = nn.Sequential(nn.Linear(d_hidden + d_view, d_hidden // 2), nn.ReLU(),
                                 nn.Linear(d_hidden // 2, 3))

    def forward(self, x: Tensor, view_dirs: Tensor) -> tuple[Tensor, Tensor]:
        """x: points outside the unit sphere (N, 3). Returns (sigma (N,), rgb (N, 3))."""
        dist = x.norm(dim=-1, keepdim=True).clamp_min(1.0)
        inputs = self.encoding(torch.cat([x / dist, 1.0 / dist], dim=-1))
        h = inputs
        for i, layer in enumerate(self.layers):
            if i in self.skip_in:
                h = torch.cat([inputs, h], dim=-1)
            h = torch.relu(layer(h))
        sigma = torch.relu(self.density(h)[:, 0])
        views = [self.view_encoding(view_dirs)] if self.view_encoding is not None else []
        rgb = torch.sigmoid(self.rgb(torch.cat([self.feature(h), *views], dim=-1)))
        return sigma, rgb


class FloorTexture(nn.Module):
    """The colour of the floor plane inside the unit sphere as a function of the point's (x, z): a texture,
    seen the same from every view, so shadows and floor patterns stay put on the floor."""

    def __init__(self, d_hidden: int = 64, n_layers: int = 3, n_freqs: int = 8):
        super().__init__()
        self.encoding = PositionalEncoding(n_freqs, d_in=2)
        dims = [self.encoding.d_out] + [d_hidden] * n_layers
        layers: list[nn.Module] = []
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(d_in, d_out), nn.ReLU()]
        self.net = nn.Sequential(*layers, nn.Linear(dims[-1], 3))

    def forward(self, xz: Tensor) -> Tensor:
        """xz: (N, 2) floor coordinates. Returns rgb (N, 3) in 0..1."""
        return torch.sigmoid(self.net(self.encoding(xz)))


class Sharpness(nn.Module):
    """One learnable scalar: r for the NeUDF weight, s for the NeuS baselines.

    Parameterised as exp(10 v), as NeuS does, so Adam's roughly constant step in v grows it geometrically.
    """

    def __init__(self, init_value: float):
        super().__init__()
        self.v = nn.Parameter(torch.tensor(math.log(init_value) / 10.0))

    def forward(self) -> Tensor:
        return torch.exp(10.0 * self.v)

    @torch.no_grad()
    def lift_to(self, floor: float) -> None:
        """Raise the value to ``floor`` where it is below; above it the learned value stands."""
        self.v.clamp_(min=math.log(floor) / 10.0)
