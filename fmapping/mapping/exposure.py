"""Per-frame affine colour (auto exposure / white balance): where a new frame's estimate starts.

The mapper models what frame ``i`` observes as ``(1 + a) * c + b`` per channel, ``c`` the field's
colour (frame 0 fixes the gauge: a = b = 0), and optimises the six numbers ``(a, b)`` with the map
at a small learning rate. A frame that started at "no change" could move only about 0.02 per
window update, while a camera's auto exposure moves its gain by tens of percent over a few
seconds; until the estimate caught up, the optimiser explained the colour change with geometry
(synthetic wide room seed 1, exposure change alone: completion ratio 82.7 -> 69.8 %). So a frame starts
from the previous frame's estimate with its gains re-fitted (:func:`fit_colour_gain`) to its pixels against
the previous frame's colours at the same surface points (``Mapper._start_exposures``): 69.8 -> 80.9 % on
that room, 82.7 % without any exposure change.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor


def undo_exposure(observed: Tensor, expo: Tensor) -> Tensor:
    """Scene colours ``(observed - b) / (1 + a)`` of colours (..., 3) seen with the colour numbers ``expo``
    (..., 6) = (a, b) (broadcast against ``observed``; gains below 0.1 are clamped)."""
    return (observed - expo[..., 3:]) / (1 + expo[..., :3]).clamp_min(0.1)


def fit_colour_gain(observed: Tensor, rendered: Tensor, offset: Tensor, min_points: int = 64, clip: float = 3.0,
                    rounds: int = 3, gain_range: tuple[float, float] = (0.25, 4.0)) -> Optional[Tensor]:
    """Per-channel gain ``g`` of ``observed ~ g * rendered + offset`` (``offset`` (3,) held), by least squares
    through the origin; returns ``(g - 1, offset)`` as the mapper's six colour numbers, or None when it
    cannot be trusted.

    observed, rendered (N, 3) colours in 0..1 of the same N pixels. Only the gain is fitted: with the
    offset free too, the low-contrast views of real rooms confound the two (the rendered colours' own
    errors flatten the slope and the offset takes up the rest: gain errors of 0.2 on the synthetic wide
    room seed 1), while a camera's auto exposure and white balance are gains. The fit is repeated
    ``rounds`` times without the pixels whose residual (norm over the channels) exceeds the median by
    ``clip`` x its robust spread (1.4826 x MAD), so parts of the view the map renders wrongly (not yet
    mapped, occluded) do not bias it. None with fewer than ``min_points`` pixels, non-finite input, or a
    gain outside ``gain_range``."""
    if observed.shape != rendered.shape or observed.ndim != 2 or observed.shape[-1] != 3:
        raise ValueError(f"fit_colour_gain: need two (N, 3) colour arrays, got {tuple(observed.shape)} "
                         f"and {tuple(rendered.shape)}")
    off = offset.detach().double().reshape(3).cpu()
    obs, ren = observed.double().cpu() - off, rendered.double().cpu()
    finite = torch.isfinite(obs).all(-1) & torch.isfinite(ren).all(-1)
    obs, ren = obs[finite], ren[finite]
    keep = torch.ones(len(obs), dtype=torch.bool)
    gain = None
    for _ in range(max(1, rounds)):
        if int(keep.sum()) < min_points:
            return None
        o, r = obs[keep], ren[keep]
        gain = (r * o).sum(0) / (r * r).sum(0).clamp_min(1e-12)
        res = (obs - gain * ren).norm(dim=-1)
        med = res[keep].median()
        keep = res <= med + clip * 1.4826 * (res[keep] - med).abs().median().clamp_min(1e-4)
    if not bool(torch.isfinite(gain).all()) or bool((gain < gain_range[0]).any() or (gain > gain_range[1]).any()):
        return None
    return torch.cat([gain - 1.0, off]).to(torch.float32)
