"""Paper-faithful tracking path: render-and-compare through the neural field.

For each frame, an se(3) correction ``xi`` of the predicted pose
(``c2w = se3_exp(xi) @ c2w_pred``, left-multiplied as in :mod:`fmapping.geometry`)
is optimised with Adam on the photometric error between the frame and colours
volume-rendered through the map at sampled pixels (iMAP / NICE-SLAM style). The
gradient flows through the field to the ray origins and directions. Slow on a
CPU (every iteration renders rays); kept for comparison with the direct path.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from fmapping.geometry import orthonormalize, se3_exp
from fmapping.tracking.direct_align import select_pixels, to_gray
from fmapping.tracking.mapview import MapView


@dataclass
class RenderCompareConfig:
    iterations: int = 30
    pixels: int = 512  # rays per iteration
    lr: float = 2e-3
    huber_delta: float = 0.1
    high_gradient: bool = True  # sample among high-gradient pixels (else uniformly)
    min_acc: float = 0.5  # ignore rays that hit nothing
    seed: int = 0


@dataclass
class RenderCompareResult:
    c2w: np.ndarray
    loss: float
    iterations: int
    ms: float


class RenderCompareTracker:
    def __init__(self, view: MapView, cfg: Optional[RenderCompareConfig] = None):
        self.view = view
        self.cfg = cfg or RenderCompareConfig()
        self._gen = torch.Generator().manual_seed(self.cfg.seed)

    def track(self, rgb: np.ndarray, c2w_init: np.ndarray) -> RenderCompareResult:
        t0 = time.perf_counter()
        cam = self.view.camera
        c = self.cfg
        img = torch.as_tensor(np.asarray(rgb, np.float32) / 255.0)
        if c.high_gradient:
            cand = torch.as_tensor(select_pixels(to_gray(rgb), c.pixels * 4, 0.01), dtype=torch.float32)
        else:
            cand = cam.pixel_grid()
        if len(cand) == 0:
            cand = cam.pixel_grid()
        base = torch.as_tensor(np.asarray(c2w_init, np.float64), dtype=torch.float32)
        xi = torch.zeros(6, requires_grad=True)
        opt = torch.optim.Adam([xi], lr=c.lr)
        loss_v = float("nan")
        for _ in range(c.iterations):
            idx = torch.randint(len(cand), (min(c.pixels, len(cand)),), generator=self._gen)
            uv = cand[idx]
            target = img[uv[:, 1].long(), uv[:, 0].long()]
            pose = se3_exp(xi) @ base
            o, d = cam.rays(pose, uv)
            out, ok = self.view.render(o, d)
            m = (ok & (out.acc.detach() > c.min_acc)).float()
            err = torch.nn.functional.huber_loss(out.rgb, target, reduction="none", delta=c.huber_delta).sum(-1)
            loss = (err * m).sum() / m.sum().clamp_min(1.0)
            opt.zero_grad()
            loss.backward()
            opt.step()
            loss_v = float(loss.detach())
        with torch.no_grad():
            c2w = (se3_exp(xi.detach().double()) @ base.double()).numpy()
        return RenderCompareResult(orthonormalize(c2w), loss_v, c.iterations, (time.perf_counter() - t0) * 1000)
