"""Dense voxel-grid baseline: trilinear density + features -> the same colour MLP.

A ``grid_resolution^3`` density grid and a ``grid_features``-channel feature grid
(stored ``(1, C, Rz, Ry, Rx)`` for ``grid_sample``), nodes on the box as in
:mod:`.base`. The features feed the 2-layer colour MLP of :mod:`.decoder` directly
(no extra basis). The default 64 nodes per axis keep memory sane:
(1 + 8) * 64^3 = 2.36 M grid parameters (128 nodes would be 18.9 M).

Density start and learning rate (why the grid differs from the factor fields). The
shared activation ``softplus(raw + density_shift)`` with ``density_shift = -10`` suits
products of small factors: a CP density ``sum_r lx*ly*lz`` grows *cubically* in the
number of Adam steps and crosses the shift within tens of steps at lr 0.02. A voxel's
raw value grows only linearly, by at most lr per step, and only ~7 % of the voxels get
a gradient in an iteration (measured on the quick mapping scene), so from raw ~ 0 it
needs thousands of iterations to reach a visible density (raw ~ +10) and an opaque one (~ +50): the
mapper's budget is a few hundred, and the map stayed empty (quick bench: 0 points, 7.4 dB).
So, as DVGO (an activation shift set by an initial opacity) and Plenoxels (a density lr
far above the feature lr) do:

* the density grid starts at ``log(expm1(grid_init_density)) - density_shift`` (plus
  the usual small noise): density ``grid_init_density`` = 0.003 /m, still clear (5 m
  absorb 1.5 %; per 6 cm sample an opacity of 2e-4, between DVGO's coarse 1e-6 and fine
  1e-2), but ~4 raw units above the factor fields' start, where the softplus slope is
  0.003 instead of 4.5e-5. For small values this is also ``logit(grid_init_density)``,
  so in occupancy mode each sample starts at opacity ~ ``grid_init_density``;
* the density grid's learning rate is ``grid_density_lr_scale`` (30) x the mapper's grid
  lr (:meth:`grid_param_groups`); the features keep the grid lr.

On the quick scene (15 init frames, 100 init iterations) the rendered depth of the
training views is within 5 cm on 56 % of the pixels after init with both changes, 44 %
with a multiplier of 10 instead of 30, 10 % with the multiplier 10 alone, 1 % with
neither. Quick mapping bench (``bench/mapping.py --quick --variants cp,grid``): the grid
went from 0 points / 7.4 dB to a 65.5 % completion ratio, 3.6 cm accuracy, 12.9 cm
completion and 29.6 dB held-out PSNR (CP in the same run: 55.1 %, 2.7 cm, 14.7 cm, 19.0 dB).
"""
from __future__ import annotations

import math
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


def initial_raw(cfg: FieldConfig) -> float:
    """Pre-activation at which ``softplus(raw + density_shift) == grid_init_density``."""
    return math.log(math.expm1(cfg.grid_init_density)) - cfg.density_shift


class GridField(Field):
    """Dense density + feature voxel grid (baseline)."""

    def __init__(self, cfg: FieldConfig, aabb) -> None:
        super().__init__(cfg, aabb)
        g = make_generator(cfg.seed)
        dev = self.aabb.device
        R, nf = cfg.grid_resolution, cfg.grid_features
        # density starts clear but close to the active range (see the module docstring);
        # features random like the factor fields
        self.density_grid = randn_param((1, 1, R, R, R), cfg.init_scale * 0.1, dev, g)
        with torch.no_grad():
            self.density_grid.add_(initial_raw(cfg))
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

    def grid_param_groups(self) -> list[tuple[list[nn.Parameter], float]]:
        """Density grid at ``grid_density_lr_scale`` x the grid lr, features at 1x."""
        return [([self.density_grid], float(self.cfg.grid_density_lr_scale)), ([self.feature_grid], 1.0)]

    def regularizer(self, kind: str = "tv") -> Tensor:
        """``tv``: mean squared neighbour differences along x, y, z of both grids;
        ``l1``: mean absolute density pre-activation (pulls voxels below the initial density)."""
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
