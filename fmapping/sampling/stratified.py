"""Ray/AABB clipping, stratified sampling and inverse-CDF (importance) sampling.

All functions work on batches of rays and return ray parameters ``t`` (N, S),
sorted along the last axis. With the z-normalised ray directions of
:mod:`fmapping.camera`, ``t`` is the camera z-depth. Randomness only comes from
the optional ``generator`` (else torch's default generator).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor


def _rand(shape, like: Tensor, generator: Optional[torch.Generator]) -> Tensor:
    if generator is not None and generator.device != like.device:
        return torch.rand(shape, generator=generator, dtype=like.dtype, device=generator.device).to(like.device)
    return torch.rand(shape, generator=generator, dtype=like.dtype, device=like.device)


def ray_aabb(origins: Tensor, dirs: Tensor, aabb: Tensor, near_min: float = 0.05) -> tuple[Tensor, Tensor, Tensor]:
    """Slab-method intersection of rays ``o + t d`` (N, 3) with a box ``aabb`` (2, 3).

    Returns ``near`` (N,), ``far`` (N,) and ``hit`` (N,) bool. ``near`` is clamped to
    ``near_min`` (so rays starting inside the box begin at ``near_min``); ``hit`` means
    ``far > near``. Rays that miss get ``near = far = near_min``. Directions may have
    zero components (treated as parallel to that slab).
    """
    aabb = aabb.to(device=origins.device, dtype=origins.dtype)
    eps = 1e-12
    d = torch.where(dirs.abs() < eps, torch.where(dirs < 0, -eps, eps) * torch.ones_like(dirs), dirs)
    inv = 1.0 / d
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    tmin = torch.minimum(t0, t1).amax(-1)
    tmax = torch.maximum(t0, t1).amin(-1)
    near = tmin.clamp_min(near_min)
    hit = tmax > near
    nm = torch.full_like(near, near_min)
    return torch.where(hit, near, nm), torch.where(hit, tmax, nm), hit


def stratified(near: Tensor, far: Tensor, n: int, perturb: bool = True,
               generator: Optional[torch.Generator] = None) -> Tensor:
    """``n`` samples per ray, one in each of ``n`` equal bins of ``[near, far]`` (N,).

    ``perturb``: uniform position inside each bin; else the bin centres. Sorted.
    """
    if n < 1:
        raise ValueError(f"number of samples must be >= 1, got {n}")
    if near.shape != far.shape or near.dim() != 1:
        raise ValueError(f"near {tuple(near.shape)} and far {tuple(far.shape)} must both be (N,)")
    i = torch.arange(n, dtype=near.dtype, device=near.device)
    u = _rand((near.shape[0], n), near, generator) if perturb else torch.full((near.shape[0], n), 0.5,
                                                                                dtype=near.dtype, device=near.device)
    frac = (i + u) / n
    return near[:, None] + (far - near)[:, None] * frac


def sample_pdf(t: Tensor, weights: Tensor, n: int, deterministic: bool = False,
               generator: Optional[torch.Generator] = None) -> Tensor:
    """Inverse-CDF sampling of ``n`` new ``t`` per ray from the piecewise-constant pdf of ``weights``.

    Sample ``i`` owns the bin between the midpoints to its neighbours (the first and
    last bins end at ``t_0`` and ``t_{S-1}``, so new samples stay in ``[t_0, t_{S-1}]``),
    with probability proportional to ``weights_i + 1e-5 * max(sum w, 1e-3) * width_i / range``
    (a small floor that is uniform in ``t``: empty rays sample uniformly over the range).
    ``u`` is stratified over [0, 1) (one per ``1/n`` slice, at the slice centre when ``deterministic``),
    so the output is sorted.
    Inputs are detached (no gradient).
    """
    if t.shape != weights.shape or t.dim() != 2:
        raise ValueError(f"t {tuple(t.shape)} and weights {tuple(weights.shape)} must both be (N, S)")
    if n < 1:
        raise ValueError(f"number of samples must be >= 1, got {n}")
    t = t.detach()
    w = weights.detach().clamp_min(0)
    nr, s = t.shape
    if s == 1:
        return t.expand(nr, n).clone()
    mid = 0.5 * (t[:, 1:] + t[:, :-1])
    edges = torch.cat([t[:, :1], mid, t[:, -1:]], -1)  # (N, S+1)
    width = edges[:, 1:] - edges[:, :-1]
    floor = width / (edges[:, -1:] - edges[:, :1]).clamp_min(1e-12)  # uniform-in-t density
    w = w + 1e-5 * w.sum(-1, keepdim=True).clamp_min(1e-3) * floor + 1e-20  # never all zero (degenerate rays)
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)  # (N, S+1)
    cdf[:, -1] = 1.0
    i = torch.arange(n, dtype=t.dtype, device=t.device)
    jitter = torch.full((nr, n), 0.5, dtype=t.dtype, device=t.device) if deterministic else _rand((nr, n), t, generator)
    u = ((i + jitter) / n).contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(0, s - 1)  # u lies in bin `below`: cdf[below] <= u < cdf[below + 1]
    above = below + 1
    c0, c1 = cdf.gather(1, below), cdf.gather(1, above)
    e0, e1 = edges.gather(1, below), edges.gather(1, above)
    denom = (c1 - c0)
    frac = torch.where(denom > 1e-12, (u - c0) / denom.clamp_min(1e-12), torch.zeros_like(u)).clamp(0, 1)
    out = e0 + frac * (e1 - e0)
    return torch.sort(out, -1).values


def merge_samples(*ts: Tensor) -> Tensor:
    """Sorted union of several (N, S_k) sample sets (the paper's ``X_{k+1} = new U X_k``)."""
    return torch.sort(torch.cat(ts, -1), -1).values
