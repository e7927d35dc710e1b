"""CP-factorized radiance field (TensoRF CP decomposition; the FMapping default).

Density:    ``raw(x) = sum_r  lx_r(x) * ly_r(y) * lz_r(z)``  (``density_components`` rank-one terms)
Appearance: ``f(x)_r = ax_r(x) * ay_r(y) * az_r(z)``  (``appearance_components``), then
            ``rgb = MLP(B f(x) [, PE(viewdir)])`` with a linear basis ``B`` (no bias, width
            ``app_features``) and the 2-layer colour MLP of :mod:`.decoder`.

Each line factor holds ``resolution`` nodes spanning the box (see :mod:`.base`),
linearly interpolated with ``grid_sample`` on a stacked ``(3, C, R, 1)`` tensor
(one image per axis): on CPU this measured ~1.5x faster (forward + backward) than a
gather + lerp with an ``index_put_`` backward, and ~2x faster than plain indexing.
With the defaults (128 nodes, 16 + 24 components, 27 basis, 48 hidden) the field
has (16+24)*3*128 = 15360 grid + 648 basis + 1491 MLP = 17499 parameters.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .base import Field, FieldConfig, as_aabb, make_generator, randn_param, start_raw, tv_1d
from .decoder import ColorDecoder, linear


def sample_lines(lines: Tensor, u: Tensor) -> Tensor:
    """Linear interpolation of stacked axis lines.

    ``lines`` (3, C, R, 1): line ``a`` holds R nodes over normalised coordinate
    ``u[:, a] in [-1, 1]`` (align_corners=True; clamped at the ends).
    ``u`` (N, 3). Returns (3, C, N): per axis, per component, per point.
    """
    ut = u.t()
    grid = torch.stack([torch.zeros_like(ut), ut], -1).unsqueeze(2)  # (3, N, 1, 2): (x=0, y=u_a)
    out = F.grid_sample(lines, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.squeeze(-1)


def node_coords(old: Tensor, new: Tensor, r: int) -> Tensor:
    """(3, R): where each of box ``new``'s ``r`` nodes per axis lies in box ``old``'s normalised
    coordinates ([-1, 1] inside ``old``)."""
    k = torch.linspace(0.0, 1.0, r, dtype=new.dtype, device=new.device)
    x = new[0, :, None] + (new[1] - new[0])[:, None] * k  # (3, R) world position of every new node
    return 2.0 * (x - old[0, :, None]) / (old[1] - old[0])[:, None] - 1.0


def resample_lines(lines: Tensor, old: Tensor, new: Tensor) -> Tensor:
    """Lines (3, C, R, 1) over box ``old`` (2, 3) resampled onto ``new``'s nodes; zero where a node
    lies outside ``old`` (empty space in the CP product: one zero factor empties the term)."""
    u = node_coords(old.to(lines.dtype), new.to(lines.dtype), lines.shape[2])
    grid = torch.stack([torch.zeros_like(u), u], -1).unsqueeze(2)  # (3, R, 1, 2)
    out = F.grid_sample(lines, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return torch.where((u.abs() <= 1.0 + 1e-6)[:, None, :, None], out, torch.zeros_like(out))



class _AxisProduct(torch.autograd.Function):
    """``s[0] * s[1] * s[2]`` for ``s`` (3, C, N), with a backward that writes the three
    partial gradients straight into one (3, C, N) buffer (autograd's version builds them
    separately and then stacks them: an extra full-size copy)."""

    @staticmethod
    def forward(ctx, s: Tensor) -> Tensor:
        p01 = s[0] * s[1]
        ctx.save_for_backward(s, p01)
        return p01 * s[2]

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        s, p01 = ctx.saved_tensors
        gs = torch.empty_like(s)
        g2 = g * s[2]
        torch.mul(g2, s[1], out=gs[0])
        torch.mul(g2, s[0], out=gs[1])
        torch.mul(g, p01, out=gs[2])
        return gs


def axis_product(s: Tensor) -> Tensor:
    """Product over the leading axis of a (3, C, N) tensor -> (C, N) (differentiable)."""
    return _AxisProduct.apply(s)


class CPField(Field):
    """CP-decomposed density and appearance lines + linear basis + small colour MLP."""

    def __init__(self, cfg: FieldConfig, aabb) -> None:
        super().__init__(cfg, aabb)
        g = make_generator(cfg.seed)
        dev = self.aabb.device
        R, cd, ca = cfg.resolution, cfg.density_components, cfg.appearance_components
        self.density_lines = randn_param((3, cd, R, 1), cfg.init_scale, dev, g)
        self.app_lines = randn_param((3, ca, R, 1), cfg.init_scale, dev, g)
        raw = start_raw(cfg, self.aabb)
        if raw > 0:  # every rank-one term at raw / cd: each of its three lines at the cube root (plus the noise)
            with torch.no_grad():
                self.density_lines.add_((raw / cd) ** (1.0 / 3.0))
        self.basis = linear(ca, cfg.app_features, g, bias=False, device=dev)
        self.decoder = ColorDecoder(cfg.app_features, cfg.hidden, g, cfg.view_dependent, cfg.view_pe_freqs, dev)

    def density_raw(self, xyz: Tensor) -> Tensor:
        self._check_points(xyz)
        u, uc = self.normalize_clamped(xyz)
        raw = axis_product(sample_lines(self.density_lines, uc)).sum(0)
        return self._mask_outside(raw, u)

    def app_features(self, xyz: Tensor) -> Tensor:
        """(N, 3) -> (N, appearance_components) CP appearance features (before the basis)."""
        uc = self.normalize_clamped(xyz)[1]
        return axis_product(sample_lines(self.app_lines, uc)).t()

    def color(self, xyz: Tensor, viewdirs: Optional[Tensor] = None) -> Tensor:
        self._check_points(xyz)
        return self.decoder(self.app_features(xyz), viewdirs, basis=self.basis.weight)

    def refit_box(self, aabb) -> None:
        """Move the field onto a new box (grown as the camera explores), keeping what it holds: the
        factor lines are resampled at the new nodes (zero outside the old box: empty space)."""
        new = as_aabb(aabb, device=self.aabb.device, dtype=self.aabb.dtype)
        with torch.no_grad():
            for p in (self.density_lines, self.app_lines):
                p.copy_(resample_lines(p.detach(), self.aabb, new))
            self.aabb.copy_(new)

    def grid_parameters(self) -> list[nn.Parameter]:
        return [self.density_lines, self.app_lines]

    def decoder_parameters(self) -> list[nn.Parameter]:
        return [self.basis.weight, *self.decoder.parameters()]

    def regularizer(self, kind: str = "tv") -> Tensor:
        """``tv``: mean squared node difference along the density and appearance lines;
        ``l1``: mean absolute value of the density lines."""
        self._check_reg_kind(kind)
        if kind == "tv":
            return tv_1d(self.density_lines.squeeze(-1)) + tv_1d(self.app_lines.squeeze(-1))
        return self.density_lines.abs().mean()

    def flops_per_point(self) -> int:
        """Per point: each line lookup is 2 MACs per channel (lerp); the 3-way product is
        2 MACs; the density sum 1; basis ``Ca*P``; plus the colour MLP. Times 2 for FLOPs."""
        cfg = self.cfg
        cd, ca = cfg.density_components, cfg.appearance_components
        dens = cd * (3 * 2 + 2 + 1)
        app = ca * (3 * 2 + 2) + ca * cfg.app_features
        return 2 * (dens + app) + self.decoder.flops()

