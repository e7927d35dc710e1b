"""Samplers along rays: ray/AABB, stratified, inverse-CDF, and the sliding-window sampler."""
from __future__ import annotations

from .sliding_window import sliding_window_interval, sliding_window_sample, sliding_window_scores
from .stratified import merge_samples, ray_aabb, sample_pdf, stratified

__all__ = [
    "ray_aabb", "stratified", "sample_pdf", "merge_samples",
    "sliding_window_scores", "sliding_window_interval", "sliding_window_sample",
]
