"""VM-factorized radiance field (TensoRF vector-matrix decomposition).

For the three axis pairs ``(x,y)|z``, ``(x,z)|y``, ``(y,z)|x`` a plane ``P_a`` (C, R, R)
and a line ``L_a`` (C, R) give, per component, ``P_a(u_i, u_j) * L_a(u_k)``.

Density:    ``raw(x) = sum_a sum_r P_a,r * L_a,r``  (``vm_density_components`` per pair)
Appearance: the ``3 * vm_appearance_components`` products, concatenated, -> linear basis
            (no bias, ``app_features``) -> the 2-layer colour MLP of :mod:`.decoder`.

Component counts are deliberately small (defaults 4 density / 8 appearance per pair):
planes cost ``R^2`` each, so 128 nodes give 12*3*128^2 ~ 0.59 M grid parameters,
already ~35x the CP field. Plane sampling is bilinear ``grid_sample`` on a stacked
``(3, C, R, R)`` tensor (plane ``a``: width axis = first coordinate of the pair,
height axis = second), lines as in :mod:`.cp`.

Plane learning rate. A line node is shared by every point with that coordinate, but a
plane node only by the points on one line through the box: each plane node gets a
gradient in far fewer iterations (the dense grid's problem, see :mod:`.grid`, one
dimension milder). With TensoRF's single lr (0.02) the planes hardly leave their random
init within the mapper's budget, so the density is carried by the lines (extrusions of
plane noise) and the quick bench's VM map was sparse: 23.6 % completion ratio, 6.0 cm
accuracy, 24.5 cm completion, 14.8 dB held-out PSNR (CP: 55.1 %, 2.7 cm, 14.7 cm, 19.0 dB).
The planes therefore train at ``vm_plane_lr_scale`` (10) x the grid lr, the lines at 1x
(``bench/mapping.py --quick``, seed 0: x5 gave 56.7 %, 4.3 cm, 12.7 cm, 22.7 dB; x10
63.5 %, 3.2 cm, 10.5 cm, 26.1 dB). TensoRF's density L1 (weight 2.4e-4 here, = its 8e-5
on per-axis means) made it worse (x5 + L1: 40.6 %, 8.9 cm). ``vm_plane_lr_scale = 1``
restores the single parameter group.

Box changes (:meth:`VMField.refit_box`, the mapper's box growing with its points) resample planes and lines at
the new nodes, as CP does with its lines. Before 2026-12-05 a VM field could not change its box, so a VM map kept
the box of its first 15 frames: 7-Scenes dev (GT poses, RGB only) 34.9 % completion ratio, 62.3 % with the growth.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .base import Field, FieldConfig, as_aabb, make_generator, randn_param, start_raw, tv_1d
from .cp import node_coords, resample_lines, sample_lines
from .decoder import ColorDecoder, linear

#: (width axis, height axis) of each plane and the axis of its line.
MAT_MODES = ((0, 1), (0, 2), (1, 2))
VEC_MODES = (2, 1, 0)


def sample_planes(planes: Tensor, u: Tensor) -> Tensor:
    """Bilinear interpolation of the three stacked planes at points ``u`` (N, 3) -> (3, C, N)."""
    grid = torch.stack([u[:, list(m)] for m in MAT_MODES], 0).unsqueeze(2)  # (3, N, 1, 2)
    out = F.grid_sample(planes, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.squeeze(-1)


def resample_planes(planes: Tensor, old: Tensor, new: Tensor) -> Tensor:
    """Planes (3, C, R, R) over box ``old`` (2, 3) resampled onto ``new``'s nodes (plane ``a`` spans the
    axes ``MAT_MODES[a]``: width = first, height = second); zero where a node lies outside ``old``."""
    u = node_coords(old.to(planes.dtype), new.to(planes.dtype), planes.shape[-1])  # (3, R) per axis
    grids, inside = [], []
    for i, j in MAT_MODES:
        uh, uw = torch.meshgrid(u[j], u[i], indexing="ij")  # (R rows = height axis j, R cols = width axis i)
        grids.append(torch.stack([uw, uh], -1))
        inside.append((uw.abs() <= 1.0 + 1e-6) & (uh.abs() <= 1.0 + 1e-6))
    out = F.grid_sample(planes, torch.stack(grids), mode="bilinear", padding_mode="zeros", align_corners=True)
    return torch.where(torch.stack(inside)[:, None], out, torch.zeros_like(out))


class VMField(Field):
    """TensoRF-VM density/appearance planes and lines + linear basis + colour MLP."""

    def __init__(self, cfg: FieldConfig, aabb) -> None:
        super().__init__(cfg, aabb)
        g = make_generator(cfg.seed)
        dev = self.aabb.device
        R, cd, ca = cfg.resolution, cfg.vm_density_components, cfg.vm_appearance_components
        self.density_planes = randn_param((3, cd, R, R), cfg.init_scale, dev, g)
        self.density_lines = randn_param((3, cd, R, 1), cfg.init_scale, dev, g)
        self.app_planes = randn_param((3, ca, R, R), cfg.init_scale, dev, g)
        self.app_lines = randn_param((3, ca, R, 1), cfg.init_scale, dev, g)
        raw = start_raw(cfg, self.aabb)
        if raw > 0:  # every plane x line term at raw / (3 cd): plane and line at its square root (plus the noise)
            with torch.no_grad():
                for p in (self.density_planes, self.density_lines):
                    p.add_((raw / (3 * cd)) ** 0.5)
        self.basis = linear(3 * ca, cfg.app_features, g, bias=False, device=dev)
        self.decoder = ColorDecoder(cfg.app_features, cfg.hidden, g, cfg.view_dependent, cfg.view_pe_freqs, dev)

    def _lines_u(self, u: Tensor) -> Tensor:
        # sample_lines reads u[:, a] for line a; reorder so line a reads its VEC_MODES axis.
        return u[:, list(VEC_MODES)]

    def density_raw(self, xyz: Tensor) -> Tensor:
        self._check_points(xyz)
        u, uc = self.normalize_clamped(xyz)
        p = sample_planes(self.density_planes, uc)
        lines = sample_lines(self.density_lines, self._lines_u(uc))
        raw = (p * lines).sum((0, 1))
        return self._mask_outside(raw, u)

    def app_features(self, xyz: Tensor) -> Tensor:
        """(N, 3) -> (N, 3 * vm_appearance_components), pair-major."""
        uc = self.normalize_clamped(xyz)[1]
        p = sample_planes(self.app_planes, uc)
        lines = sample_lines(self.app_lines, self._lines_u(uc))
        return (p * lines).flatten(0, 1).t()

    def color(self, xyz: Tensor, viewdirs: Optional[Tensor] = None) -> Tensor:
        self._check_points(xyz)
        return self.decoder(self.app_features(xyz), viewdirs, basis=self.basis.weight)

    def refit_box(self, aabb) -> None:
        """Move the field onto a new box keeping what it holds: planes and lines are resampled at the new
        nodes, zero where a node lies outside the old box (one zero factor empties a plane x line term)."""
        new = as_aabb(aabb, device=self.aabb.device, dtype=self.aabb.dtype)
        old = self.aabb
        with torch.no_grad():
            for p in (self.density_lines, self.app_lines):  # line a runs along axis VEC_MODES[a]
                p.copy_(resample_lines(p.detach(), old[:, list(VEC_MODES)], new[:, list(VEC_MODES)]))
            for p in (self.density_planes, self.app_planes):
                p.copy_(resample_planes(p.detach(), old, new))
            self.aabb.copy_(new)

    def grid_parameters(self) -> list[nn.Parameter]:
        return [self.density_planes, self.density_lines, self.app_planes, self.app_lines]

    def decoder_parameters(self) -> list[nn.Parameter]:
        return [self.basis.weight, *self.decoder.parameters()]

    def grid_param_groups(self) -> list[tuple[list[nn.Parameter], float]]:
        """One group at 1x (default), or planes at ``vm_plane_lr_scale`` x and lines at 1x."""
        scale = float(self.cfg.vm_plane_lr_scale)
        if scale == 1.0:
            return [(self.grid_parameters(), 1.0)]
        return [([self.density_planes, self.app_planes], scale), ([self.density_lines, self.app_lines], 1.0)]

    def regularizer(self, kind: str = "tv") -> Tensor:
        """``tv``: mean squared neighbour differences on planes (both directions) and lines;
        ``l1``: mean absolute value of the density planes and lines."""
        self._check_reg_kind(kind)
        if kind == "tv":
            tv = self._zero()
            for planes, lines in ((self.density_planes, self.density_lines), (self.app_planes, self.app_lines)):
                tv = tv + tv_1d(planes) + tv_1d(planes.transpose(-1, -2)) + tv_1d(lines.squeeze(-1))
            return tv
        return self.density_planes.abs().mean() + self.density_lines.abs().mean()

    def flops_per_point(self) -> int:
        """Per component and pair: bilinear lookup 4 MACs + line lookup 2 + product 1;
        density sum 1; basis ``3*Ca*P``; plus the colour MLP. Times 2 for FLOPs."""
        cfg = self.cfg
        cd, ca = cfg.vm_density_components, cfg.vm_appearance_components
        dens = 3 * cd * (4 + 2 + 1 + 1)
        app = 3 * ca * (4 + 2 + 1) + 3 * ca * cfg.app_features
        return 2 * (dens + app) + self.decoder.flops()
