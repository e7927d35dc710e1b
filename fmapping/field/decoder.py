"""Small decoders shared by the fields: positional encoding and the colour MLP.

The colour MLP is the paper's "two-layer MLP with 48 channels in the hidden
layer": ``features [+ PE(viewdir)] -> Linear(hidden) -> ReLU -> Linear(3) -> sigmoid``.
"""
from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def pe_dim(in_dim: int, freqs: int) -> int:
    """Width of :func:`positional_encoding` output."""
    return in_dim * (1 + 2 * freqs)


def positional_encoding(x: Tensor, freqs: int) -> Tensor:
    """``[x, sin(2^k pi x), cos(2^k pi x)]`` for ``k = 0..freqs-1`` along the last axis."""
    if freqs == 0:
        return x
    scales = (2.0 ** torch.arange(freqs, dtype=x.dtype, device=x.device)) * math.pi
    xs = (x[..., None, :] * scales[:, None]).flatten(-2)  # (..., freqs*D)
    return torch.cat([x, torch.sin(xs), torch.cos(xs)], -1)


def init_linear(layer: nn.Linear, generator: torch.Generator) -> nn.Linear:
    """PyTorch's default Linear init (U(-1/sqrt(fan_in), 1/sqrt(fan_in))) from a local generator."""
    bound = 1.0 / math.sqrt(layer.in_features)
    with torch.no_grad():
        w = (torch.rand(layer.weight.shape, generator=generator) * 2 - 1) * bound
        layer.weight.copy_(w.to(layer.weight.device))
        if layer.bias is not None:
            b = (torch.rand(layer.bias.shape, generator=generator) * 2 - 1) * bound
            layer.bias.copy_(b.to(layer.bias.device))
    return layer


def linear(in_f: int, out_f: int, generator: torch.Generator, bias: bool = True, device=None) -> nn.Linear:
    return init_linear(nn.Linear(in_f, out_f, bias=bias, device=device), generator)


class ColorDecoder(nn.Module):
    """``features (M, in_features) [+ viewdirs (M, 3)] -> rgb (M, 3)`` in [0, 1]."""

    def __init__(self, in_features: int, hidden: int, generator: torch.Generator, view_dependent: bool = False,
                 view_pe_freqs: int = 2, device=None) -> None:
        super().__init__()
        self.in_features = in_features
        self.hidden = hidden
        self.view_dependent = view_dependent
        self.view_pe_freqs = view_pe_freqs
        d_in = in_features + (pe_dim(3, view_pe_freqs) if view_dependent else 0)
        self.d_in = d_in
        self.fc1 = linear(d_in, hidden, generator, device=device)
        self.fc2 = linear(hidden, 3, generator, device=device)

    def forward(self, feat: Tensor, viewdirs: Optional[Tensor] = None, basis: Optional[Tensor] = None) -> Tensor:
        """``basis`` (in_features, K): when given, ``feat`` (M, K) is first mapped by the linear
        basis ``feat @ basis.T``; the product is folded into the first layer (``W1 @ basis``,
        a tiny matrix) so the big batch sees one matmul instead of two."""
        w1 = self.fc1.weight
        w_feat = w1[:, :self.in_features]
        if basis is not None:
            w_feat = w_feat @ basis
        h = F.linear(feat, w_feat, self.fc1.bias)
        if self.view_dependent:
            if viewdirs is None:
                raise ValueError("this field is view dependent: color() needs viewdirs (M, 3)")
            vd = viewdirs.to(feat.dtype)
            vd = vd / vd.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            h = h + F.linear(positional_encoding(vd, self.view_pe_freqs), w1[:, self.in_features:])
        return torch.sigmoid(self.fc2(torch.relu(h)))

    def flops(self) -> int:
        """Multiply-adds * 2 per point (activations ignored)."""
        return 2 * (self.d_in * self.hidden + self.hidden * 3)
