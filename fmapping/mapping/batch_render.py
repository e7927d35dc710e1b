"""Rendering a batch of rays for the optimiser: near/far from the box, coarse pass without
gradient, fine samples, gradient only where it matters."""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from fmapping.render import alpha_to_weights, composite, raw_to_alpha, render_rays, sample_deltas
from fmapping.sampling import ray_aabb, sample_pdf, stratified
from fmapping.sampling.sliding_window import sliding_window_sample


def ray_bounds(origins: Tensor, dirs: Tensor, aabb: Tensor, near: float, far: float) -> tuple[Tensor, Tensor, Tensor]:
    """Near and far ray parameters inside the box (``near`` <= t <= ``far``) and which rays hit it
    (rays that miss get a tiny interval just past ``t_near``)."""
    t_near, t_far, in_box = ray_aabb(origins, dirs, aabb, near_min=near)
    t_far = t_far.clamp_max(far)
    hit = in_box & (t_far > t_near + 1e-3)
    t_far = torch.where(hit, t_far, t_near + 1e-2)
    return t_near, t_far, hit


def render_batch(field, aabb: Tensor, cfg, origins: Tensor, dirs: Tensor, mode: str, n_coarse: int, n_fine: int,
                 grad: bool = True, sw_window: int = 0, color: bool = True,
                 generator: Optional[torch.Generator] = None):
    """Sample and render rays (background black) through ``field`` inside ``aabb`` with the settings
    of ``cfg`` (a :class:`fmapping.mapping.MapperConfig`); returns the render and (t_near, t_far, hit).

    ``mode`` "stratified": ``n_coarse`` stratified samples, all rendered. "pdf" /
    "sliding_window": a coarse stratified pass without gradient, then ``n_fine``
    importance / sliding-window samples; the union is rendered. With ``grad`` and
    ``active_threshold`` > 0, only *active* coarse samples are re-evaluated with gradient:
    those not hidden (transmittance > 1e-4) and with opacity above ``active_threshold`` x
    the ray's largest coarse opacity (all of them on rays that are still empty); the others
    keep their exact no-grad density, so the forward render is unchanged and only
    negligible gradients are skipped. ``generator`` draws the random samples (used only with ``grad``).
    """
    t_near, t_far, hit = ray_bounds(origins, dirs, aabb, cfg.near, cfg.far)
    gen = generator if grad else None
    t = stratified(t_near, t_far, n_coarse, perturb=grad, generator=gen)
    if mode == "stratified" or n_fine <= 0:
        with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
            out = render_rays(field, origins, dirs, t, background=0.0, color_weight_threshold=cfg.color_threshold)
        return out, (t_near, t_far, hit)
    dnorm = dirs.norm(dim=-1)
    n_rays = origins.shape[0]
    with torch.no_grad():
        xyz_c = origins[:, None, :] + t[..., None] * dirs[:, None, :]
        raw_c = field.density_raw(xyz_c.reshape(-1, 3)).view(n_rays, n_coarse)
        alpha_c = raw_to_alpha(raw_c, sample_deltas(t, dnorm), field.cfg.alpha_mode, field.cfg.density_shift)
        weights_c = alpha_to_weights(alpha_c)
        if mode == "sliding_window":
            t_new = sliding_window_sample(t, weights_c, n_fine, window=max(sw_window, 1), generator=gen)
        else:
            t_new = sample_pdf(t, weights_c, n_fine, deterministic=not grad, generator=gen)
        t_all, order = torch.sort(torch.cat([t, t_new], -1), -1)
        raw_known = torch.cat([raw_c, torch.zeros_like(t_new)], -1).gather(1, order)
        if grad and cfg.active_threshold > 0:
            trans = torch.cumprod(1 - alpha_c + 1e-10, -1)
            trans = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], -1)
            amax = alpha_c.amax(-1, keepdim=True)
            act_c = ((alpha_c > cfg.active_threshold * amax) | (amax < 1e-2)) & (trans > 1e-4)
        else:
            act_c = torch.ones_like(alpha_c, dtype=torch.bool)
        active = torch.cat([act_c, torch.ones_like(t_new, dtype=torch.bool)], -1).gather(1, order)
    with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
        act_ray, act_sample = active.nonzero(as_tuple=True)
        xyz = origins[act_ray] + t_all[act_ray, act_sample, None] * dirs[act_ray]
        raw_act = field.density_raw(xyz)
        raw = raw_known.index_put((act_ray, act_sample), raw_act)
        alpha = raw_to_alpha(raw, sample_deltas(t_all, dnorm), field.cfg.alpha_mode, field.cfg.density_shift)
        out = composite(alpha, t_all, None, None)
        if not color:  # depth-only rays (the sparse depth term)
            return out, (t_near, t_far, hit)
        wd = out.weights.detach()
        mask = wd > cfg.color_threshold * wd.amax(-1, keepdim=True)
        col_ray, col_sample = mask.nonzero(as_tuple=True)
        rgb = torch.zeros(n_rays, 3, dtype=alpha.dtype, device=alpha.device)
        if col_ray.numel() > 0:
            vd = None  # a view-dependent field sees each ray's unit direction (as fmapping.render does)
            if field.cfg.view_dependent:
                vd = dirs[col_ray] / dnorm[col_ray, None].clamp_min(1e-12)
            c = field.color(origins[col_ray] + t_all[col_ray, col_sample, None] * dirs[col_ray], vd)
            rgb = rgb.index_add(0, col_ray, out.weights[col_ray, col_sample, None] * c)
        out.rgb = rgb
    return out, (t_near, t_far, hit)
