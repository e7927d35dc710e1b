"""The paper's sliding-window sampler (Sec. "Sliding Window Sampling", eqs. 6-9).

Our reading of eqs. 6-9 (the supplementary material with the "technical details"
is not available), for one ray with sorted samples ``t_1..t_S`` and weights ``w``:

1. Scores (eq. 9): ``W_i = beta * exp(-delta_i) + (1 - beta) * w_i`` with
   ``delta_i = t_{i+1} - t_i`` in ray-parameter units (metres of camera depth for
   z-normalised rays; the last sample reuses the previous gap). The ``exp(-delta)``
   term favours densely sampled stretches (where earlier passes put samples), the
   weight term favours rendering contributions.
2. Smoothing (eq. 9): ``SW = W * G``, a box kernel ``G = [1/tau] * tau`` in sample-index
   space, "same" size output with edge-replicate padding (so the ray ends are not
   penalised; for even ``tau`` the window at ``i`` covers ``i - (tau-1)//2 .. i + tau//2``,
   like ``conv1d(padding="same")``).
3. Interval (eq. 8, "the window marches on until a discontinuity"): take the argmax
   ``k`` of ``SW``; normalise ``SW`` per ray as ``(SW - median) / (max - median)`` and grow
   the run of consecutive samples around ``k`` whose normalised score is
   ``>= run_threshold``; the run is widened to at least the window span at ``k``. Then
   ``[t_n, t_f] = [t_left, t_right]`` of that run (the sample positions themselves).
   The median (not the min) is the reference level because after a few passes most
   samples sit in a dense stretch around the surface, where ``exp(-delta) ~ 1`` lifts
   the score of empty samples well above the sparse ones; measured from the min, that
   whole stretch would qualify and the interval would stop shrinking.
   A ray whose weights sum below ``min_mass`` (nothing rendered there yet, e.g. an
   untrained field) or whose smoothed score is flat (max - median <= 1e-4 max) gets its
   whole sampled range: there is no surface to search for.
4. Samples (eq. 8 + eq. 6): ``round(frac_pdf * n)`` samples by inverse CDF of the weights
   (:func:`~fmapping.sampling.stratified.sample_pdf`), the rest stratified in ``[t_n, t_f]``;
   the union is sorted. Union with the previous samples (``X_{k+1} = ... U X_k``) is left
   to the caller (:func:`~fmapping.sampling.stratified.merge_samples`).

The paper's init schedule is a stratified pass of 32, then three sliding-window
passes of 64 samples with ``tau = 3, 4, 5``. Everything is vectorised over rays.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from .stratified import sample_pdf, stratified


def _gaps(t: Tensor) -> Tensor:
    d = t[:, 1:] - t[:, :-1]
    if d.shape[1] == 0:
        return torch.zeros_like(t)
    return torch.cat([d, d[:, -1:]], -1)


def sliding_window_scores(t: Tensor, weights: Tensor, window: int, beta: float = 0.5) -> Tensor:
    """Box-filtered scores ``(beta exp(-delta) + (1-beta) w) * G_tau`` (N, S); see module docstring."""
    if t.shape != weights.shape or t.dim() != 2:
        raise ValueError(f"t {tuple(t.shape)} and weights {tuple(weights.shape)} must both be (N, S)")
    if window < 1:
        raise ValueError(f"sliding window size must be >= 1, got {window}")
    t, w = t.detach(), weights.detach()
    score = beta * torch.exp(-_gaps(t)) + (1.0 - beta) * w
    left = (window - 1) // 2
    x = F.pad(score[:, None, :], (left, window - 1 - left), mode="replicate")
    kernel = torch.full((1, 1, window), 1.0 / window, dtype=score.dtype, device=score.device)
    return F.conv1d(x, kernel)[:, 0, :]


def sliding_window_interval(t: Tensor, weights: Tensor, window: int, beta: float = 0.5,
                            run_threshold: float = 0.5, min_mass: float = 1e-3) -> tuple[Tensor, Tensor]:
    """The interval ``[t_n, t_f]`` (each (N,)) around the best smoothed score; see module docstring."""
    if not 0.0 < run_threshold <= 1.0:
        raise ValueError(f"run_threshold must be in (0, 1], got {run_threshold}")
    t = t.detach()
    sw = sliding_window_scores(t, weights, window, beta)
    nr, s = sw.shape
    k = sw.argmax(-1, keepdim=True)  # (N, 1)
    base, hi = sw.median(-1, keepdim=True).values, sw.amax(-1, keepdim=True)
    span = hi - base
    flat = span <= 1e-4 * hi.abs().clamp_min(1e-12)  # no information (rounding-level variation)
    flat = flat | (weights.detach().sum(-1, keepdim=True) < min_mass)  # nothing rendered on this ray yet
    q = ((sw - base) / span.clamp_min(1e-30) >= run_threshold) | flat
    idx = torch.arange(s, device=t.device).expand(nr, s)
    last_false_left = torch.where(~q, idx, torch.full_like(idx, -1)).cummax(-1).values
    first_false_right = torch.where(~q, idx, torch.full_like(idx, s)).flip(-1).cummin(-1).values.flip(-1)
    left = last_false_left.gather(1, k) + 1
    right = first_false_right.gather(1, k) - 1
    left = torch.minimum(left, k - (window - 1) // 2).clamp_min(0)
    right = torch.maximum(right, k + window // 2).clamp_max(s - 1)
    return t.gather(1, left)[:, 0], t.gather(1, right)[:, 0]


def sliding_window_sample(t: Tensor, weights: Tensor, n: int, window: int, beta: float = 0.5,
                          frac_pdf: float = 0.4, generator: Optional[torch.Generator] = None,
                          run_threshold: float = 0.5, min_mass: float = 1e-3) -> Tensor:
    """``n`` new samples per ray: ``round(frac_pdf n)`` by inverse CDF of ``weights``, the rest
    stratified in the sliding-window interval. Sorted, detached, (N, n)."""
    if n < 1:
        raise ValueError(f"number of samples must be >= 1, got {n}")
    if not 0.0 <= frac_pdf <= 1.0:
        raise ValueError(f"frac_pdf must be in [0, 1], got {frac_pdf}")
    n_pdf = int(round(frac_pdf * n))
    n_sw = n - n_pdf
    parts = []
    if n_pdf > 0:
        parts.append(sample_pdf(t, weights, n_pdf, generator=generator))
    if n_sw > 0:
        tn, tf = sliding_window_interval(t, weights, window, beta, run_threshold, min_mass)
        parts.append(stratified(tn, tf, n_sw, perturb=True, generator=generator))
    return torch.sort(torch.cat(parts, -1), -1).values
