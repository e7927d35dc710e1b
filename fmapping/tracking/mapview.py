"""What the tracker needs from the map: depth at chosen pixels, and differentiable rendering of rays.

:class:`MapView` wraps a neural field (normally ``Mapper.field`` with the mapper's
bounding box and near / far) and renders rays the way the mapper does: a
deterministic stratified pass, then inverse-CDF samples from its weights, then
:func:`fmapping.render.render_rays`. Depths are camera z (z-normalised rays, see
:mod:`fmapping.camera`), normalised by the accumulated opacity; pixels whose
opacity is below ``min_acc`` have no depth (NaN).

A factorised field is only constrained where mapped frames looked: elsewhere its
factors extend structure into unseen space and it renders confident but meaningless
depth, which makes a tracker drift without any sign of trouble (the warp explains the
image because the depth is wrong). With ``seen_poses`` (the mapped frames' poses),
depth is kept only where the rendered surface point lies in one of their frusta
(:func:`seen_by`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.render import render_rays, render_weights
from fmapping.sampling import ray_aabb, sample_pdf, stratified


@dataclass
class MapViewConfig:
    n_coarse: int = 32
    n_fine: int = 16
    min_acc: float = 0.7  # opacity below which a pixel has no depth
    chunk: int = 16384
    seen_only: bool = True  # from_mapper: depth only where a mapped frame looked (see seen_by)


def seen_by(points: np.ndarray, c2ws: list, camera, near: float, far: float, margin: float = 2.0) -> np.ndarray:
    """Boolean (N,): which world points (N, 3) lie inside the viewing frustum (image with
    ``margin`` pixels, depth in [near, far]) of at least one camera-to-world pose in ``c2ws``."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    seen = np.zeros(len(pts), bool)
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    for c2w in c2ws:
        t = np.asarray(c2w, np.float64)
        pc = (pts - t[:3, 3]) @ t[:3, :3]  # world -> camera: R^T (X - t)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = fx * pc[:, 0] / z + cx, fy * pc[:, 1] / z + cy
        seen |= (z >= near) & (z <= far) & (u >= margin - 0.5) & (u <= camera.width - 0.5 - margin) \
            & (v >= margin - 0.5) & (v <= camera.height - 0.5 - margin)
        if seen.all():
            break
    return seen


class MapView:
    def __init__(self, field, aabb: Tensor, camera: PinholeCamera, near: float, far: float,
                 cfg: Optional[MapViewConfig] = None, seen_poses: Optional[list] = None):
        self.field = field
        self.aabb = torch.as_tensor(aabb, dtype=torch.float32)
        self.camera = camera
        self.near = float(near)
        self.far = float(far)
        self.cfg = cfg or MapViewConfig()
        self.seen_poses = None if seen_poses is None else [np.asarray(p, np.float64) for p in seen_poses]

    @classmethod
    def from_mapper(cls, mapper, cfg: Optional[MapViewConfig] = None) -> "MapView":
        if mapper.field is None or mapper.aabb is None:
            raise RuntimeError("MapView: the mapper has no map yet (not initialised)")
        cfg = cfg or MapViewConfig()
        seen = list(mapper.frame_poses().values()) if cfg.seen_only else None
        return cls(mapper.field, mapper.aabb, mapper.camera, mapper.cfg.near, mapper.cfg.far, cfg, seen)

    def _samples(self, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        aabb = self.aabb.to(o.device, o.dtype)
        tn, tf, hit = ray_aabb(o, d, aabb, near_min=self.near)
        tf = tf.clamp_max(self.far)
        ok = hit & (tf > tn + 1e-3)
        tf = torch.where(ok, tf, tn + 1e-2)
        with torch.no_grad():
            t = stratified(tn, tf, self.cfg.n_coarse, perturb=False)
            if self.cfg.n_fine > 0:
                w = render_weights(self.field, o.detach(), d.detach(), t).weights
                t_new = sample_pdf(t, w, self.cfg.n_fine, deterministic=True)
                t = torch.sort(torch.cat([t, t_new], -1), -1).values
        return t, ok

    def render(self, o: Tensor, d: Tensor):
        """Render rays (N, 3) -> RenderOutput (differentiable w.r.t. ``o``, ``d`` and the field) and hit mask."""
        t, ok = self._samples(o, d)
        return render_rays(self.field, o, d, t, background=0.0), ok

    @torch.no_grad()
    def depth_at(self, c2w: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Rendered depth (N,) at float pixels ``uv`` (N, 2) of a camera at ``c2w``; NaN where empty."""
        dev = self.field.device if hasattr(self.field, "device") else torch.device("cpu")
        pose = torch.as_tensor(np.asarray(c2w, np.float64), dtype=torch.float32, device=dev)
        uvt = torch.as_tensor(np.asarray(uv, np.float64), dtype=torch.float32, device=dev)
        out, pts = [], []
        for s in range(0, len(uvt), self.cfg.chunk):
            o, d = self.camera.rays(pose, uvt[s:s + self.cfg.chunk])
            t, ok = self._samples(o, d)
            r = render_weights(self.field, o, d, t)
            dep = r.depth / r.acc.clamp_min(1e-6)
            good = ok & (r.acc >= self.cfg.min_acc)
            out.append(torch.where(good, dep, torch.full_like(dep, float("nan"))))
            pts.append(o + d * dep[:, None])  # z-normalised rays: the surface point at camera depth dep
        if not out:
            return np.zeros(0)
        z = torch.cat(out).double().cpu().numpy()
        if self.seen_poses is not None:
            ok = np.flatnonzero(np.isfinite(z))
            world = torch.cat(pts).double().cpu().numpy()[ok]
            z[ok[~seen_by(world, self.seen_poses, self.camera, self.near, self.far)]] = np.nan
        return z

    def depth_fn(self, c2w: np.ndarray):
        """A callable ``uv -> depth`` for :func:`fmapping.tracking.direct_align.make_reference`."""
        pose = np.asarray(c2w, np.float64).copy()
        return lambda uv: self.depth_at(pose, uv)
