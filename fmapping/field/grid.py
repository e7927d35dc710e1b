"""Dense voxel-grid baseline: trilinear density + features -> the same colour MLP.

A ``grid_resolution^3`` density grid and a ``grid_features``-channel feature grid
(stored ``(1, C, Rz, Ry, Rx)`` for ``grid_sample``), nodes on the box as in
:mod:`.base`. The features feed the 2-layer colour MLP of :mod:`.decoder` directly
(no extra basis). The default 64 nodes per axis keep memory sane:
(1 + 8) * 64^3 = 2.36 M grid parameters (128 nodes would be 18.9 M).
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .base import Field, FieldConfig, make_generator, randn_param, tv_1d
from .decoder import ColorDecoder


def sample_volume(vol: Tensor, u: Tensor) -> Tensor:
    """Trilinear interpolation of ``vol`` (1, C, Rz, Ry, Rx) at ``u`` (N, 3) in [-1, 1] -> (C, N)."""
    grid = u.view(1, -1, 1, 1, 3)
    out = F.grid_sample(vol, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.view(vol.shape[1], -1)


class GridField(Field):
    """Dense density + feature voxel grid (baseline)."""

    def __init__(self, cfg: FieldConfig, aabb) -> None:
        super().__init__(cfg, aabb)
        g = make_generator(cfg.seed)
        dev = self.aabb.device
        R, nf = cfg.grid_resolution, cfg.grid_features
        # density starts near 0 (clear after the shift); features random like the factor fields
        self.density_grid = randn_param((1, 1, R, R, R), cfg.init_scale * 0.1, dev, g)
        self.feature_grid = randn_param((1, nf, R, R, R), cfg.init_scale, dev, g)
        self.decoder = ColorDecoder(nf, cfg.hidden, g, cfg.view_dependent, cfg.view_pe_freqs, dev)

    def density_raw(self, xyz: Tensor) -> Tensor:
        self._check_points(xyz)
        u, uc = self.normalize_clamped(xyz)
        raw = sample_volume(self.density_grid, uc)[0]
        return self._mask_outside(raw, u)

    def color(self, xyz: Tensor, viewdirs: Optional[Tensor] = None) -> Tensor:
        self._check_points(xyz)
        uc = self.normalize_clamped(xyz)[1]
        return self.decoder(sample_volume(self.feature_grid, uc).t(), viewdirs)

    def grid_parameters(self) -> list[nn.Parameter]:
        return [self.density_grid, self.feature_grid]

    def decoder_parameters(self) -> list[nn.Parameter]:
        return list(self.decoder.parameters())

    def regularizer(self, kind: str = "tv") -> Tensor:
        """``tv``: mean squared neighbour differences along x, y, z of both grids;
        ``l1``: mean absolute density."""
        self._check_reg_kind(kind)
        if kind == "tv":
            tv = self._zero()
            for vol in (self.density_grid, self.feature_grid):
                for dim in (-1, -2, -3):
                    tv = tv + tv_1d(vol.transpose(dim, -1))
            return tv
        return self.density_grid.abs().mean()

    def flops_per_point(self) -> int:
        """Trilinear lookup = 8 MACs per channel (density + features) plus the colour MLP, x2."""
        return 2 * 8 * (1 + self.cfg.grid_features) + self.decoder.flops()
