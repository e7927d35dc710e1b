"""The window schedule: the init stage, the active window (global keyframes chosen for overlap +
recent local frames), which frames leave and enter it, and the closing refinement
(:class:`WindowSchedule`, mixed into :class:`fmapping.mapping.Mapper`).

Stages (paper, Sec. "System overview"):

* **Init**: the first ``init_frames`` frames are optimised jointly with the
  field over four sampling rounds ``init_rounds`` = (sliding-window size, samples
  per ray); window size 0 is plain stratified sampling. Each round runs
  ``init_iters_per_round`` iterations of ``init_rays_per_iter`` rays; the grid's
  learning rate falls geometrically from ``init_lr_grid`` to ``lr_grid`` over the
  whole init (:func:`init_grid_lrs`), from a field that starts as a fog
  (``field.init_opacity``). Frame 0 is fixed; the other init poses get se(3)
  corrections when ``optimize_init_poses``. The colour decoder is frozen afterwards.
* **On the fly**: an active window of ``window_size`` frames = up to
  ``n_global_keyframes`` global keyframes (half chosen for overlap with the
  recent frames, half at random for coverage) + the most recent local frames.
  Every ``new_frames_per_window`` new frames, ``iters_per_window`` iterations
  run; the oldest local frames leave the window (every ``keyframe_every``-th
  frame becomes a global keyframe).
* **Finish**: pending frames form a last window; then ``final_global_iters``
  iterations over windows of overlapping keyframes refine the whole map.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from fmapping.geometry import nearest_rotation, se3_inverse
from fmapping.mapping.batch_render import render_batch


@dataclass
class WindowStats:
    """What one update (init, window or final) did: its frames, iterations, time and last losses."""

    index: int
    kind: str  # "init" | "window" | "final"
    seconds: float
    iterations: int
    loss: float
    photo_loss: float
    warp_loss: float
    rays: int
    samples_per_ray: int
    frames: list
    pc_loss: float = 0.0
    sparse_loss: float = 0.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


class WindowSchedule:
    """Which frames :class:`fmapping.mapping.Mapper` optimises when (a mixin: it works on the mapper's
    frame lists ``_init_ids``, ``_pending``, ``_local``, ``_keyframes`` and ``_window``)."""

    def _run_init(self) -> WindowStats:
        cfg = self.cfg
        t0 = time.perf_counter()
        self._build()
        ids = list(self._init_ids)
        st = None
        total = {"iters": 0, "loss": [], "photo": [], "warp": []}
        n = cfg.init_iters_per_round
        lrs = init_grid_lrs(cfg.init_lr_grid, cfg.lr_grid, n * len(cfg.init_rounds))
        for r, (window, samples) in enumerate(cfg.init_rounds):
            # exposures start after the first round: from an empty map, a colour offset would explain the images
            self._set_lr("exposure", cfg.lr_exposure if r > 0 else 0.0)
            kw = dict(n_rays=cfg.init_rays_per_iter, grid_lrs=lrs[r * n:(r + 1) * n])
            if window == 0:
                s = self._run_iters("init", ids, n, "stratified", samples, 0, **kw)
            else:  # the round's samples = the coarse stratified ones + (samples - n_coarse) sliding-window ones
                s = self._run_iters("init", ids, n, "sliding_window", cfg.n_coarse, max(1, samples - cfg.n_coarse),
                                    sw_window=window, **kw)
            total["iters"] += s.iterations
            total["loss"].append(s.loss)
            total["photo"].append(s.photo_loss)
            total["warp"].append(s.warp_loss)
            st = s
        self._set_lr("grid", cfg.lr_grid)
        # bake the pose corrections and freeze the decoder
        if self._pose_corr is not None:
            with torch.no_grad():
                refined = self._frame_c2w(ids)
            self._pose_corr.requires_grad_(False)
            for k, i in enumerate(ids):
                if k > 0:
                    self._poses[i] = torch.as_tensor(
                        _orthonormalize(refined[k].double().cpu()), dtype=torch.float64)
            with torch.no_grad():
                self._pose_corr.zero_()
        if cfg.freeze_decoder_after_init:
            self._freeze_decoder()
        elif self._pose_corr is not None:
            for g in self._opt.param_groups:
                if g.get("name") == "pose":
                    g["lr"] = 0.0
        self.initialized = True
        n_local = cfg.window_size - cfg.n_global_keyframes
        self._keyframes = [ids[0]]
        for i in ids[1:]:
            if len(ids) - ids.index(i) > n_local and self._frames_apart(self._keyframes[-1], i) >= cfg.keyframe_every:
                self._keyframes.append(i)
        self._local = ids[-n_local:]
        for i in ids:
            self._drop_image_if_unused(i)
        self._window = ids
        stats = WindowStats(index=len(self._stats), kind="init", seconds=time.perf_counter() - t0,
                            iterations=total["iters"], loss=total["loss"][-1], photo_loss=total["photo"][-1],
                            warp_loss=total["warp"][-1], rays=cfg.init_rays_per_iter * total["iters"],
                            samples_per_ray=st.samples_per_ray if st else 0, frames=ids,
                            pc_loss=st.pc_loss if st else 0.0, sparse_loss=st.sparse_loss if st else 0.0)
        self._stats.append(stats)
        return stats

    def _frames_apart(self, a: int, b: int) -> int:
        """Stream frames between frame ids ``a`` and ``b`` (:meth:`Mapper.frame_number`)."""
        return self.frame_number(b) - self.frame_number(a)

    def _drop_image_if_unused(self, fid: int) -> None:
        """A frame out of the working set (local window, pending): a keyframe's image is kept compressed,
        any other's goes."""
        if fid in self._local or fid in self._pending:
            return
        if fid in self._keyframes:
            self._images.compress(fid)
        else:
            self._images.pop(fid, None)
            self._depths.pop(fid, None)

    def _run_window(self) -> WindowStats:
        cfg = self.cfg
        t0 = time.perf_counter()
        n_local = cfg.window_size - cfg.n_global_keyframes
        new = list(self._pending)
        self._pending = []
        self._local.extend(new)
        while len(self._local) > n_local:
            old = self._local.pop(0)
            if not self._keyframes or self._frames_apart(self._keyframes[-1], old) >= cfg.keyframe_every:
                self._keyframes.append(old)
            self._drop_image_if_unused(old)
        self._grow_box()
        self._start_exposures(new)
        global_ids = self._select_global(self._local, cfg.n_global_keyframes)
        ids = global_ids + list(self._local)
        self._window = ids
        st = self._run_iters("window", ids, cfg.iters_per_window, cfg.sampler, cfg.n_coarse, cfg.n_fine,
                             sw_window=cfg.sw_window, t0=t0)
        self._stats.append(st)
        return st

    def _run_final(self, iters: Optional[int] = None) -> WindowStats:
        cfg = self.cfg
        total = cfg.final_global_iters if iters is None else int(iters)
        t0 = time.perf_counter()
        pool = sorted(set(self._keyframes) | set(self._local))
        logs = []
        done = 0
        chunk = max(1, cfg.iters_per_window)
        while done < total:
            k = min(chunk, total - done)
            anchor = pool[int(torch.randint(len(pool), (1,), generator=self._gen))]
            others = [i for i in pool if i != anchor]
            ids = [anchor] + self._select_global([anchor], min(cfg.window_size - 1, len(others)), pool=others,
                                                 random_share=0.25)
            logs.append(self._run_iters("final", ids, k, cfg.sampler, cfg.n_coarse, cfg.n_fine, cfg.sw_window))
            done += k
        st = WindowStats(index=len(self._stats), kind="final", seconds=time.perf_counter() - t0,
                         iterations=done, loss=logs[-1].loss, photo_loss=logs[-1].photo_loss,
                         warp_loss=logs[-1].warp_loss, rays=cfg.rays_per_iter * done,
                         samples_per_ray=logs[-1].samples_per_ray, frames=pool, pc_loss=logs[-1].pc_loss)
        self._stats.append(st)
        return st

    # ================================================================ keyframe selection
    @torch.no_grad()
    def _probe_points(self, ids: list[int], grid: tuple[int, int] = (8, 6)) -> Tensor:
        """World points of a coarse pixel grid of frames ``ids`` at their rendered depth (far bound where empty)."""
        cam = self.camera
        us = (torch.arange(grid[0], dtype=torch.float32) + 0.5) * cam.width / grid[0] - 0.5
        vs = (torch.arange(grid[1], dtype=torch.float32) + 0.5) * cam.height / grid[1] - 0.5
        grid_v, grid_u = torch.meshgrid(vs, us, indexing="ij")
        uv = torch.stack([grid_u.reshape(-1), grid_v.reshape(-1)], -1).to(self.device)
        pts = []
        for i in ids:
            c2w = self._poses[i].to(self.device, torch.float32)
            origins, dirs = cam.rays(c2w, uv)
            out, (t_near, t_far, _) = render_batch(self.field, self.aabb, self.cfg, origins, dirs, "pdf", 16, 8,
                                                   grad=False)
            dep = torch.where(out.acc > 0.5, out.depth / out.acc.clamp_min(1e-6), 0.5 * (t_near + t_far))
            pts.append(origins + dirs * dep[:, None])
        return torch.cat(pts)

    @torch.no_grad()
    def _overlap(self, pts: Tensor, cands: list[int]) -> Tensor:
        """Fraction of ``pts`` inside the view of each candidate frame (no occlusion test)."""
        if not cands:
            return torch.zeros(0)
        c2w = torch.stack([self._poses[i] for i in cands]).to(self.device, torch.float32)
        w2c = se3_inverse(c2w)
        cp = torch.einsum("vij,nj->vni", w2c[:, :3, :3], pts) + w2c[:, None, :3, 3]
        uv, z = self.camera.project(cp)
        vis = (z > self.cfg.near) & self.camera.in_image(uv)
        return vis.float().mean(-1).cpu()

    def _select_global(self, anchor: list[int], k: int, pool: Optional[list[int]] = None,
                       random_share: float = 0.5) -> list[int]:
        """``k`` frames from ``pool`` (default: global keyframes outside ``anchor``): the best-overlapping
        share (1 - random_share) with the anchor frames' rendered surface, the rest at random."""
        if pool is None:
            pool = [i for i in self._keyframes if i not in anchor]
        if k <= 0 or not pool:
            return []
        if len(pool) <= k:
            return list(pool)
        pts = self._probe_points(anchor[-self.cfg.new_frames_per_window:])
        ov = self._overlap(pts, pool)
        n_best = k - int(round(k * random_share))
        order = torch.argsort(ov, descending=True).tolist()
        chosen = [pool[j] for j in order[:n_best]]
        rest = [pool[j] for j in order[n_best:]]
        perm = torch.randperm(len(rest), generator=self._gen).tolist()
        chosen += [rest[j] for j in perm[:k - n_best]]
        return sorted(chosen)


def init_grid_lrs(start: float, end: float, n: int) -> list[float]:
    """The grid's learning rate at each of the init's ``n`` iterations: geometric from ``start`` to ``end``."""
    if n <= 1:
        return [float(end)] * n
    return [float(start * (end / start) ** (i / (n - 1))) for i in range(n)]


def _orthonormalize(p: Tensor) -> Tensor:
    out = p.clone()
    out[:3, :3] = nearest_rotation(p[:3, :3])
    return out
