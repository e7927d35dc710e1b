"""Volume rendering (paper eqs. 4-5) with density or occupancy (UNISURF) opacity.

Conventions:

* Rays are ``x(t) = o + t d`` with z-normalised directions (``|d| >= 1``, see
  :mod:`fmapping.camera`), so the ray parameter ``t`` equals the camera z-depth.
* Sample ``i`` at ``t_i`` stands for the segment ``[t_i, t_{i+1})`` of metric length
  ``delta_i = (t_{i+1} - t_i) |d|``. The last sample has no successor; its delta is the
  mean of the ray's other deltas (a finite value, so no artificial opaque wall at the
  far end; for uniform samples on ``[near, far]`` placed at the bin starts it is exactly
  ``far - t_last``). With a single sample the last delta is 0.
* Density mode: ``alpha = 1 - exp(-softplus(raw + shift) * delta)``.
  Occupancy mode (UNISURF): ``alpha = sigmoid(raw + shift)``, independent of ``delta``.
  The shift is applied in both modes so that an untrained field (raw ~ 0) starts clear.
* ``weights_i = alpha_i prod_{j<i} (1 - alpha_j)``; ``acc = sum_i weights_i``.
* ``depth = sum_i weights_i t_i`` (the paper's eq. 5, NOT normalised by ``acc``: it
  tends to 0 on empty rays); ``RenderOutput.depth_normalized`` = ``depth / acc``.
  Both are camera z-depths.
* ``rgb = sum_i weights_i c_i + (1 - acc) * background`` (no background term when
  ``background`` is None).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

Background = Union[Tensor, float, None]


@dataclass
class RenderOutput:
    rgb: Optional[Tensor]  # (N, 3); None when composite() got no colours
    depth: Tensor          # (N,)  sum_i w_i t_i (not normalised)
    acc: Tensor            # (N,)  sum_i w_i
    weights: Tensor        # (N, S)
    t: Tensor              # (N, S)

    @property
    def depth_normalized(self) -> Tensor:
        """Expected depth given the ray terminates: ``depth / acc`` (0 where acc ~ 0)."""
        return torch.where(self.acc > 1e-6, self.depth / self.acc.clamp_min(1e-6), torch.zeros_like(self.depth))


def sample_deltas(t: Tensor, dirs_norm: Optional[Tensor] = None) -> Tensor:
    """Metric segment lengths (N, S) for sorted samples ``t`` (N, S); see module docstring."""
    d = t[..., 1:] - t[..., :-1]
    if d.shape[-1] > 0:
        last = d.mean(-1, keepdim=True)
    else:
        last = torch.zeros_like(t[..., :1])
    d = torch.cat([d, last], -1)
    if dirs_norm is not None:
        d = d * dirs_norm[..., None]
    return d


def raw_to_alpha(raw: Tensor, deltas: Tensor, mode: str, shift: float) -> Tensor:
    """Opacity of each sample; ``deltas`` in metres (ignored in occupancy mode)."""
    if mode == "density":
        return 1.0 - torch.exp(-F.softplus(raw + shift) * deltas)
    if mode == "occupancy":
        return torch.sigmoid(raw + shift)
    raise ValueError(f"alpha mode must be 'density' or 'occupancy', got {mode!r}")


def alpha_to_weights(alpha: Tensor) -> Tensor:
    """``w_i = alpha_i prod_{j<i} (1 - alpha_j)`` along the last axis."""
    trans = torch.cumprod(1.0 - alpha + 1e-10, -1)
    trans = torch.cat([torch.ones_like(trans[..., :1]), trans[..., :-1]], -1)
    return alpha * trans


def _background(background: Background, like: Tensor) -> Optional[Tensor]:
    if background is None:
        return None
    bg = torch.as_tensor(background, dtype=like.dtype, device=like.device)
    if bg.dim() == 0:
        bg = bg.expand(3)
    if bg.shape not in ((3,), (like.shape[0], 3)):
        raise ValueError(f"background must be a float, (3,) or (N, 3); got shape {tuple(bg.shape)}")
    return bg


def composite(alpha: Tensor, t: Tensor, rgb: Optional[Tensor] = None, background: Background = 0.0) -> RenderOutput:
    """Alpha compositing of per-sample opacity (N, S) and colour (N, S, 3) along sorted ``t`` (N, S)."""
    if alpha.shape != t.shape:
        raise ValueError(f"alpha {tuple(alpha.shape)} and t {tuple(t.shape)} must have the same shape")
    w = alpha_to_weights(alpha)
    acc = w.sum(-1)
    depth = (w * t).sum(-1)
    out_rgb = None
    if rgb is not None:
        if rgb.shape != (*alpha.shape, 3):
            raise ValueError(f"rgb must have shape {(*alpha.shape, 3)}, got {tuple(rgb.shape)}")
        out_rgb = (w[..., None] * rgb).sum(-2)
        bg = _background(background, out_rgb)
        if bg is not None:
            out_rgb = out_rgb + (1.0 - acc)[..., None] * bg
    return RenderOutput(out_rgb, depth, acc, w, t)


def _density_pass(field, origins: Tensor, dirs: Tensor, t: Tensor) -> tuple[RenderOutput, Tensor, Tensor]:
    if t.dim() != 2:
        raise ValueError(f"t must have shape (N, S), got {tuple(t.shape)}")
    n, s = t.shape
    if origins.shape != (n, 3) or dirs.shape != (n, 3):
        raise ValueError(f"origins {tuple(origins.shape)} and dirs {tuple(dirs.shape)} "
                         f"must be ({n}, 3) for t {tuple(t.shape)}")
    dtype = field.dtype
    origins, dirs, t = origins.to(dtype), dirs.to(dtype), t.to(dtype)
    dnorm = dirs.norm(dim=-1)
    xyz = origins[:, None, :] + t[..., None] * dirs[:, None, :]  # (N, S, 3)
    raw = field.density_raw(xyz.reshape(-1, 3)).view(n, s)
    alpha = raw_to_alpha(raw, sample_deltas(t, dnorm), field.cfg.alpha_mode, field.cfg.density_shift)
    return composite(alpha, t, None, None), xyz, dnorm


def render_weights(field, origins: Tensor, dirs: Tensor, t: Tensor) -> RenderOutput:
    """Density-only pass (no colour evaluated, ``rgb`` is None): weights, depth and acc,
    e.g. for the sampling passes. Same conventions and gradients as :func:`render_rays`."""
    return _density_pass(field, origins, dirs, t)[0]


def render_rays(field, origins: Tensor, dirs: Tensor, t: Tensor, *, background: Background = 0.0,
                color_weight_threshold: Optional[float] = 1e-4, viewdirs: Optional[Tensor] = None) -> RenderOutput:
    """Render rays ``o + t d`` through ``field`` (a :class:`fmapping.field.Field`).

    ``origins``, ``dirs`` (N, 3); ``t`` (N, S) sorted. Density is evaluated on all
    samples; colour only on samples whose (detached) weight exceeds
    ``color_weight_threshold`` times the largest weight on the same ray (gather, then
    ``index_add`` into the rays). ``None`` evaluates colour everywhere.

    The threshold is *relative to the ray's max weight* on purpose: with an absolute
    threshold an untrained (clear) field or a ray into unseen space has all weights
    below it, colour is never evaluated and, with a black background, the density gets
    no gradient at all (the map can never start there). On rays with a surface
    (max weight ~ 1) it is the usual absolute test (TensoRF's ``weight > 1e-4``). The
    output differs from colouring everywhere by the skipped ``sum w c`` (each w below
    the threshold); gradients differ by terms of the same order.

    Gradients flow to the field and to ``origins``/``dirs`` through both density and
    colour. ``viewdirs`` default to the normalised ``dirs`` for a view-dependent field.
    """
    out, xyz, dnorm = _density_pass(field, origins, dirs, t)
    n, s = t.shape
    dtype = field.dtype
    dirs = dirs.to(dtype)
    w = out.weights

    if field.cfg.view_dependent and viewdirs is None:
        viewdirs = dirs / dnorm[:, None].clamp_min(1e-12)
    if color_weight_threshold is None:
        vd = None if viewdirs is None else viewdirs[:, None, :].expand(n, s, 3).reshape(-1, 3)
        c = field.color(xyz.reshape(-1, 3), vd).view(n, s, 3)
        rgb = (w[..., None] * c).sum(1)
    else:
        wd = w.detach()
        mask = wd > color_weight_threshold * wd.amax(-1, keepdim=True)
        ray_idx, samp_idx = mask.nonzero(as_tuple=True)
        rgb = torch.zeros(n, 3, dtype=dtype, device=t.device)
        if ray_idx.numel() > 0:
            vd = None if viewdirs is None else viewdirs.to(dtype)[ray_idx]
            c = field.color(xyz[ray_idx, samp_idx], vd)
            rgb = rgb.index_add(0, ray_idx, w[ray_idx, samp_idx][:, None] * c)
    bg = _background(background, rgb)
    if bg is not None:
        rgb = rgb + (1.0 - out.acc)[:, None] * bg
    out.rgb = rgb
    return out


@torch.no_grad()
def render_image(field, camera, c2w, near: float, far: float, n_samples: int, chunk: int = 32768,
                 background: Background = 0.0, n_importance: int = 0,
                 color_weight_threshold: Optional[float] = 1e-4) -> dict[str, Tensor]:
    """Render a full image (no grad, chunked) for export / evaluation.

    Each pixel ray is clipped to ``[near, far]`` and to the field box, sampled with
    ``n_samples`` deterministic stratified samples (bin centres), plus ``n_importance``
    deterministic inverse-CDF samples when > 0. Returns H x W tensors on the field's
    device: ``rgb`` (H, W, 3), ``depth`` (un-normalised, see module docstring),
    ``depth_normalized``, ``acc``.
    """
    from .sampling import ray_aabb, sample_pdf, stratified

    dev, dtype = field.device, field.dtype
    c2w_t = torch.as_tensor(np.asarray(c2w.detach().cpu() if isinstance(c2w, Tensor) else c2w), dtype=torch.float64)
    if c2w_t.shape != (4, 4):
        raise ValueError(f"c2w must be 4x4, got {tuple(c2w_t.shape)}")
    uv = camera.pixel_grid(dtype=torch.float64)
    o_all, d_all = camera.rays(c2w_t, uv)
    o_all, d_all = o_all.to(dev, dtype), d_all.to(dev, dtype)
    outs: dict[str, list[Tensor]] = {"rgb": [], "depth": [], "depth_normalized": [], "acc": []}
    for i in range(0, o_all.shape[0], chunk):
        o, d = o_all[i:i + chunk], d_all[i:i + chunk]
        bn, bf, hit = ray_aabb(o, d, field.aabb, near_min=near)
        bf = torch.minimum(bf, torch.full_like(bf, far))
        bf = torch.where(hit & (bf > bn), bf, bn)
        t = stratified(bn, bf, n_samples, perturb=False)
        if n_importance > 0:
            r0 = render_weights(field, o, d, t)
            t_new = sample_pdf(t, r0.weights, n_importance, deterministic=True)
            t = torch.sort(torch.cat([t, t_new], -1), -1).values
        r = render_rays(field, o, d, t, background=background, color_weight_threshold=color_weight_threshold)
        outs["rgb"].append(r.rgb)
        outs["depth"].append(r.depth)
        outs["depth_normalized"].append(r.depth_normalized)
        outs["acc"].append(r.acc)
    h, w = camera.height, camera.width
    return {
        "rgb": torch.cat(outs["rgb"]).view(h, w, 3),
        "depth": torch.cat(outs["depth"]).view(h, w),
        "depth_normalized": torch.cat(outs["depth_normalized"]).view(h, w),
        "acc": torch.cat(outs["acc"]).view(h, w),
    }
