"""iMAP-like baseline: one coordinate MLP for density and colour.

``u = normalised position in [-1, 1]^3 -> PE (pe_freqs octaves) -> mlp_layers x
Linear(mlp_width) + ReLU -> {density head (1), colour head (3, sigmoid)}``; the
colour head also sees PE(viewdir) when ``view_dependent``. With the defaults
(6 octaves, 4 x 128) it has 55 k parameters; iMAP's own width of 256 would give ~0.2 M.

``density_raw`` and ``color`` each run the trunk (colour is evaluated on a subset of
samples by the renderer), so the trunk cost is paid once for all samples plus once
for the coloured ones. All parameters are in ``decoder_parameters`` (there is no grid).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor, nn

from .base import Field, FieldConfig, make_generator
from .decoder import linear, pe_dim, positional_encoding


class MLPField(Field):
    """Positional-encoding MLP (iMAP-like) baseline."""

    def __init__(self, cfg: FieldConfig, aabb) -> None:
        super().__init__(cfg, aabb)
        g = make_generator(cfg.seed)
        dev = self.aabb.device
        d_in = pe_dim(3, cfg.pe_freqs)
        dims = [d_in] + [cfg.mlp_width] * cfg.mlp_layers
        self.trunk = nn.ModuleList(linear(a, b, g, device=dev) for a, b in zip(dims[:-1], dims[1:]))
        self.density_head = linear(cfg.mlp_width, 1, g, device=dev)
        d_view = pe_dim(3, cfg.view_pe_freqs) if cfg.view_dependent else 0
        self.color_head = linear(cfg.mlp_width + d_view, 3, g, device=dev)
        with torch.no_grad():  # start clear: raw ~ 0 everywhere (the shift makes it empty)
            self.density_head.weight.mul_(0.01)
            self.density_head.bias.zero_()

    def _trunk(self, u: Tensor) -> Tensor:
        h = positional_encoding(u, self.cfg.pe_freqs)
        for layer in self.trunk:
            h = torch.relu(layer(h))
        return h

    def density_raw(self, xyz: Tensor) -> Tensor:
        self._check_points(xyz)
        u, uc = self.normalize_clamped(xyz)
        raw = self.density_head(self._trunk(uc))[:, 0]
        return self._mask_outside(raw, u)

    def color(self, xyz: Tensor, viewdirs: Optional[Tensor] = None) -> Tensor:
        self._check_points(xyz)
        h = self._trunk(self.normalize_clamped(xyz)[1])
        if self.cfg.view_dependent:
            if viewdirs is None:
                raise ValueError("this field is view dependent: color() needs viewdirs (M, 3)")
            vd = viewdirs.to(h.dtype)
            vd = vd / vd.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            h = torch.cat([h, positional_encoding(vd, self.cfg.view_pe_freqs)], -1)
        return torch.sigmoid(self.color_head(h))

    def grid_parameters(self) -> list[nn.Parameter]:
        return []

    def decoder_parameters(self) -> list[nn.Parameter]:
        return list(self.parameters())

    def regularizer(self, kind: str = "tv") -> Tensor:
        """No spatial factors: both kinds are 0."""
        self._check_reg_kind(kind)
        return self._zero()

    def flops_per_point(self) -> int:
        """Trunk + both heads (the trunk counted once), x2 for FLOPs."""
        cfg = self.cfg
        d_in = pe_dim(3, cfg.pe_freqs)
        macs = d_in * cfg.mlp_width + (cfg.mlp_layers - 1) * cfg.mlp_width ** 2
        macs += cfg.mlp_width * 1 + self.color_head.in_features * 3
        return 2 * macs
