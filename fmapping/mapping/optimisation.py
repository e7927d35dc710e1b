"""The optimisation step: a random ray batch of the window, batch rendering, loss assembly
and the Adam step (:class:`OptimisationStep`, mixed into :class:`fmapping.mapping.Mapper`).

Every iteration samples ``rays_per_iter`` random pixels of the window, renders
them (coarse stratified pass without gradients, then ``n_fine`` importance or
sliding-window samples; only coarse samples that matter are re-evaluated with
gradients, see :func:`fmapping.mapping.batch_render.render_batch`) and minimises

* the photometric loss (L2 or Huber) against the pixel colours, black background;
* the warping loss (:func:`fmapping.losses.warping_loss`): the expected depth
  ``sum w t / acc`` of each ray, lifted to 3-D and projected into ``warp_views``
  random window views, 3x3 patches compared (mean over the valid views);
* the per-sample photo-consistency loss ``sum_i w_i (c_i - mean_i c_i)`` where
  ``c_i`` is the colour disagreement of sample ``i`` across ``pc_views`` other views
  (a plane-sweep cost along the ray, :func:`fmapping.losses.sample_consistency_cost`).
  It pulls the rendering weight to where the views agree and removes the density
  "screens" in front of surfaces that the warping loss alone leaves (measured on
  synthetic rooms: completion ratio 83 -> 97 % on seed 0, 88 -> 97 % on seed 1);
* optional TV / L1 regularisers of the field and, with ``use_depth``, an L1 depth loss.
"""
from __future__ import annotations

import time
from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from fmapping.cancel import check_stop
from fmapping.geometry import se3_exp
from fmapping.losses import (distortion_loss, expected_depth_l1, gaussian_blur, photometric_loss,
                             sample_consistency_cost, sparse_depth_loss, warping_loss)
from fmapping.mapping.batch_render import render_batch
from fmapping.mapping.exposure import undo_exposure
from fmapping.mapping.window_schedule import WindowStats
from fmapping.runtime import release_free_memory


class OptimisationStep:
    """The optimiser and the iterations of :class:`fmapping.mapping.Mapper` (a mixin: it works on the
    mapper's frames, field, exposures and random generator)."""

    def _make_optimizer(self) -> None:
        cfg = self.cfg
        # one "grid" group per (params, lr multiplier) of the field (cp / vm / mlp: one, x1)
        groups = [{"params": list(ps), "lr": cfg.lr_grid * scale, "name": "grid", "lr_scale": scale}
                  for ps, scale in self.field.grid_param_groups()]
        groups.append({"params": list(self.field.decoder_parameters()), "lr": cfg.lr_decoder, "name": "decoder"})
        if self._pose_corr is not None:
            groups.append({"params": [self._pose_corr], "lr": cfg.lr_pose, "name": "pose"})
        if cfg.exposure:  # frame 0 fixes the colour gauge; frames after the build join the group as they come
            groups.append({"params": [p for i, p in sorted(self._exposure.items()) if p.requires_grad],
                           "lr": cfg.lr_exposure, "name": "exposure"})
        if cfg.refine_poses:  # frame 0 fixes the gauge; frames join as they come, like the exposures
            groups.append({"params": [p for i, p in sorted(self._pose_delta.items()) if p.requires_grad],
                           "lr": cfg.lr_pose_refine, "name": "pose_refine"})
        self._coarse = None
        if cfg.coarse_nodes > 0:
            from fmapping.mapping.coarse import CoarseLines, is_line
            names = {"both": ("density_lines", "app_lines"), "density": ("density_lines",),
                     "appearance": ("app_lines",)}[cfg.coarse_lines]
            lines = [getattr(self.field, n) for n in names if is_line(getattr(self.field, n, torch.empty(0)))]
            if lines:
                self._coarse = CoarseLines(lines, cfg.coarse_nodes)
                groups.append({"params": self._coarse.params(), "lr": cfg.lr_grid * cfg.coarse_lr_scale,
                               "name": "grid", "lr_scale": cfg.coarse_lr_scale})
        groups = [g for g in groups if g["params"] or g["name"] in ("exposure", "pose_refine")]
        self._opt = torch.optim.Adam(groups, betas=(0.9, 0.99))

    def _set_lr(self, name: str, lr: float) -> None:
        """The learning rate of the groups called ``name``, each at ``lr`` x its own multiplier (``lr_scale``:
        the field's grid groups, e.g. the VM planes; 1 elsewhere)."""
        for g in self._opt.param_groups:
            if g.get("name") == name:
                g["lr"] = lr * g.get("lr_scale", 1.0)

    def _freeze_decoder(self) -> None:
        for p in self.field.decoder_parameters():
            p.requires_grad_(False)
        for g in self._opt.param_groups:
            if g.get("name") in ("decoder", "pose"):
                g["lr"] = 0.0
        if self._pose_corr is not None:
            self._pose_corr.requires_grad_(False)

    def _frame_c2w(self, ids: list[int]) -> Tensor:
        """float32 (V, 4, 4) poses of frames ``ids`` on the device, with the init's corrections or, after the
        init, the update's (``refine_poses``; differentiable)."""
        base = torch.stack([self._poses[i] for i in ids]).to(self.device, torch.float32)
        if self.initialized and self.cfg.refine_poses:
            return base @ se3_exp(torch.stack([self._pose_delta[i] for i in ids]))
        if self._pose_corr is None or not self._pose_corr.requires_grad:
            return base
        nc = self._pose_corr.shape[0]
        rows = torch.tensor([self._init_ids.index(i) if i in self._init_ids[1:nc] else -1 for i in ids],
                            device=self.device)
        table = torch.cat([torch.zeros(1, 6, device=self.device), self._pose_corr[1:],
                           torch.zeros(1, 6, device=self.device)])  # row 0: frame 0 fixed; last row: no correction
        corr = table[torch.where(rows < 0, torch.full_like(rows, table.shape[0] - 1), rows)]
        return se3_exp(corr) @ base

    def _window_images(self, ids: list[int]) -> Tensor:
        """The images of frames ``ids`` as stored, uint8 (V, H, W, 3) on the device: a quarter of float32's
        memory for the whole update; :meth:`_step` converts the pixels it draws."""
        return torch.stack([self._images[i] for i in ids]).to(self.device)

    @torch.no_grad()
    def _scene_images(self, ids: list[int], imgs: Tensor) -> Tensor:
        """float (V, H, W, 3) in 0..1: ``imgs`` (uint8, :meth:`_window_images`) with each frame's current
        exposure undone (observed = (1 + a) c + b), smoothed by ``consistency_blur``: the images the losses
        that compare views with each other see. Made one view at a time, so that the conversion's and the
        blur's temporaries are one image's, not the window's (they set the update's memory peak otherwise)."""
        expo = self._exposure_of(ids)
        out = torch.empty(imgs.shape, dtype=torch.float32, device=self.device)
        for k in range(len(ids)):
            img = imgs[k].to(torch.float32).div_(255.0)
            if expo is not None:
                img = undo_exposure(img, expo[k].detach())
            out[k] = gaussian_blur(img[None], self.cfg.consistency_blur)[0]
        return out

    def _sparse_batch(self, ids: list[int]) -> Optional[tuple]:
        """The triangulated points seen by frames ``ids``: (window index, pixel, depth, weight) tensors."""
        if self._sparse is None or self.cfg.sparse_depth_weight <= 0:
            return None
        rows = []
        fill = self.cfg.sparse_fill_weight
        for k, i in enumerate(ids):
            uv, z, w = self._sparse.frame_depths(i)
            if len(z):
                rows.append((np.full(len(z), k), uv, z, w))
            if fill > 0:
                uv, z, w = self._sparse.frame_fill(i)
                if len(z):
                    rows.append((np.full(len(z), k), uv, z, fill * w))
        if not rows:
            return None
        view, uv, z, w = (np.concatenate(x) for x in zip(*rows))
        dev = self.device
        return (torch.as_tensor(view, device=dev), torch.as_tensor(uv, dtype=torch.float32, device=dev),
                torch.as_tensor(z, dtype=torch.float32, device=dev),
                torch.as_tensor(w, dtype=torch.float32, device=dev))

    def _step(self, ids: list[int], imgs: Tensor, mode: str, n_coarse: int, n_fine: int, sw_window: int,
              scene_imgs: Tensor, sparse: Optional[tuple] = None, n_rays: Optional[int] = None) -> dict:
        """One optimisation iteration over the window ``ids`` (images ``imgs``, uint8 (V, H, W, 3)).
        ``scene_imgs``: the images with each frame's exposure undone (for the losses that compare
        views with each other; :meth:`_scene_images`, made once per update); ``sparse``: the window's
        triangulated points (:meth:`_sparse_batch`); ``n_rays``: rays of the batch (default ``rays_per_iter``)."""
        cfg, cam = self.cfg, self.camera
        n_rays = cfg.rays_per_iter if n_rays is None else n_rays
        n_views = len(ids)
        gen = self._gen
        # each ray: a random pixel (pix_u, pix_v) of a random window view (its index into ids: ray_view)
        ray_view = torch.randint(n_views, (n_rays,), generator=gen).to(self.device)
        pix_u = torch.randint(cam.width, (n_rays,), generator=gen).to(self.device)
        pix_v = torch.randint(cam.height, (n_rays,), generator=gen).to(self.device)
        uv = torch.stack([pix_u, pix_v], -1).to(torch.float32)
        c2w = self._frame_c2w(ids)
        origins, dirs = cam.rays(c2w[ray_view], uv)
        target = imgs[ray_view, pix_v, pix_u].to(torch.float32) / 255.0
        out, (t_near, t_far, hit) = render_batch(self.field, self.aabb, cfg, origins, dirs, mode, n_coarse, n_fine,
                                                 grad=True, sw_window=sw_window, generator=gen)
        hit_weight = hit.to(torch.float32)  # rays that miss the box count for nothing
        expo = self._exposure_of(ids)
        pred = out.rgb if expo is None else out.rgb * (1 + expo[ray_view, :3]) + expo[ray_view, 3:]
        photo = photometric_loss(pred, target, cfg.photo_loss, cfg.huber_delta, weight=hit_weight)
        loss = photo
        if cfg.distortion_weight > 0 and bool(hit.any()):
            loss = loss + cfg.distortion_weight * distortion_loss(out.weights[hit], out.t[hit], t_near[hit],
                                                                  t_far[hit])
        warp = torch.zeros((), device=self.device)
        if cfg.warp_weight > 0 and n_views > 1:
            if cfg.warp_depth == "far":
                depth = out.depth + (1 - out.acc) * t_far
            else:
                depth = out.depth / out.acc.clamp_min(1e-3)
            if 0 < cfg.warp_views < n_views:  # a random subset of the window as target views (cost ~ views)
                sub = torch.randperm(n_views, generator=gen)[:cfg.warp_views].to(self.device)
                pos = torch.full((n_views,), -1, dtype=torch.long, device=self.device)
                pos[sub] = torch.arange(len(sub), device=self.device)
                w_views, w_c2w, w_src = sub, c2w[sub], pos[ray_view]  # the images read in place, not copied
            else:
                w_views, w_c2w, w_src = None, c2w, ray_view
            for dil in cfg.warp_dilations:
                ref = _pixel_patches(scene_imgs, ray_view, pix_u, pix_v, cfg.warp_radius, int(round(float(dil))))
                res = warping_loss(origins, dirs, depth, uv, w_src, scene_imgs, w_c2w, cam, radius=cfg.warp_radius,
                                   dilation=float(dil), keep=cfg.warp_keep, min_z=cfg.near, ray_weight=hit_weight,
                                   ref_colors=ref, max_angle_deg=cfg.consistency_max_angle, views=w_views)
                warp = warp + res.loss / len(cfg.warp_dilations)
            loss = loss + cfg.warp_weight * warp
        pc = torch.zeros((), device=self.device)
        if cfg.pc_weight > 0 and n_views > 1:
            pc = self._pc_loss(out, origins, dirs, ray_view, pix_u, pix_v, scene_imgs, c2w)
            loss = loss + cfg.pc_weight * pc
        sparse_loss = torch.zeros((), device=self.device)
        if sparse is not None and cfg.sparse_depth_weight > 0 and cfg.sparse_rays > 0:
            s_frame, s_uv, s_z, s_w = sparse
            pick = torch.randint(len(s_z), (min(cfg.sparse_rays, len(s_z)),), generator=gen).to(self.device)
            s_origins, s_dirs = cam.rays(c2w[s_frame[pick]], s_uv[pick])
            s_out, (_, s_t_far, s_hit) = render_batch(self.field, self.aabb, cfg, s_origins, s_dirs, mode, n_coarse,
                                                      n_fine, grad=True, sw_window=sw_window, color=False,
                                                      generator=gen)
            sparse_loss = sparse_depth_loss(s_out.weights, s_out.t, s_out.acc, s_t_far, s_z[pick], s_w[pick] * s_hit,
                                            cap=cfg.sparse_cap)
            loss = loss + cfg.sparse_depth_weight * sparse_loss
        if expo is not None and cfg.exposure_reg > 0:
            loss = loss + cfg.exposure_reg * expo.pow(2).mean()
        if cfg.use_depth and self._depths:
            window_depths = [self._depths.get(i) for i in ids]
            if all(x is not None for x in window_depths):
                depth_gt = torch.stack(window_depths).to(self.device)[ray_view, pix_v, pix_u]
                loss = loss + cfg.depth_weight * expected_depth_l1(out.weights, out.t, out.acc, t_far, depth_gt)
        if cfg.tv_weight > 0:
            loss = loss + cfg.tv_weight * self.field.regularizer("tv")
        if cfg.l1_weight > 0:
            loss = loss + cfg.l1_weight * self.field.regularizer("l1")
        self._opt.zero_grad(set_to_none=True)
        loss.backward()
        if self._coarse is not None:
            self._coarse.set_grads()
        self._opt.step()
        if self._coarse is not None:
            self._coarse.fold()
        self._iterations += 1
        return {"loss": float(loss.detach()), "photo": float(photo.detach()), "warp": float(warp.detach()),
                "pc": float(pc.detach()), "sparse": float(sparse_loss.detach()),
                "samples": int(out.t.shape[-1]) if hasattr(out, "t") and out.t is not None else n_coarse + n_fine}

    def _pc_loss(self, out, origins: Tensor, dirs: Tensor, ray_view: Tensor, pix_u: Tensor, pix_v: Tensor,
                 imgs: Tensor, c2w: Tensor) -> Tensor:
        """Per-sample photo-consistency: rendering weights are pulled to samples whose colour agrees
        across views (cost below the ray's mean cost) and pushed from the others. The rays are
        ``origins + t dirs`` through pixels (``pix_u``, ``pix_v``) of window views ``ray_view``."""
        cfg = self.cfg
        n_views = imgs.shape[0]
        m = min(cfg.pc_rays, origins.shape[0])
        k = min(cfg.pc_views, n_views)
        views = torch.randperm(n_views, generator=self._gen)[:k].to(self.device)
        pos = torch.full((n_views,), -1, dtype=torch.long, device=self.device)
        pos[views] = torch.arange(k, device=self.device)
        src = pos[ray_view[:m]]
        t = out.t[:m].detach()
        pts = origins[:m, None].detach() + dirs[:m, None].detach() * t[..., None]
        ref = _pixel_patches(imgs, ray_view[:m], pix_u[:m], pix_v[:m], cfg.pc_radius, 1)
        cost, nval = sample_consistency_cost(pts, ref, src, imgs, c2w[views].detach(), self.camera,
                                             radius=cfg.pc_radius, keep=cfg.pc_keep, min_z=cfg.near,
                                             ray_dirs=dirs[:m].detach(), max_angle_deg=cfg.consistency_max_angle,
                                             views=views)
        valid = (nval > 0).to(cost.dtype)
        cbar = (cost * valid).sum(-1, keepdim=True) / valid.sum(-1, keepdim=True).clamp_min(1)
        w = out.weights[:m]
        return ((w * (cost - cbar) * valid).sum(-1)).mean()

    def _run_iters(self, kind: str, ids: list[int], iters: int, mode: str, n_coarse: int, n_fine: int,
                   sw_window: int = 0, t0: Optional[float] = None, n_rays: Optional[int] = None,
                   grid_lrs: Optional[Sequence[float]] = None) -> WindowStats:
        """``iters`` iterations over the frames ``ids``; ``grid_lrs``: the grid's lr for each of them
        (default: the optimiser's as it is)."""
        t0 = time.perf_counter() if t0 is None else t0
        n_rays = self.cfg.rays_per_iter if n_rays is None else n_rays
        imgs = self._window_images(ids)
        sparse = self._sparse_batch(ids)
        scene_imgs = self._scene_images(ids, imgs)  # the exposures move slowly: undone once per update
        logs = []
        for it in range(iters):
            check_stop(self._should_stop, f"{kind} update (after {len(logs)} of {iters} iterations)")
            if grid_lrs is not None:
                self._set_lr("grid", grid_lrs[it])
            logs.append(self._step(ids, imgs, mode, n_coarse, n_fine, sw_window, scene_imgs, sparse, n_rays))
        del imgs, sparse, scene_imgs
        if self.initialized and self.cfg.refine_poses:
            self._fold_pose_deltas(ids)
        release_free_memory()  # the update's temporaries are gone: their pages go back (fmapping.runtime)
        st = WindowStats(
            index=len(self._stats), kind=kind, seconds=time.perf_counter() - t0, iterations=iters,
            loss=float(np.mean([x["loss"] for x in logs[-5:]])) if logs else float("nan"),
            photo_loss=float(np.mean([x["photo"] for x in logs[-5:]])) if logs else float("nan"),
            warp_loss=float(np.mean([x["warp"] for x in logs[-5:]])) if logs else float("nan"),
            pc_loss=float(np.mean([x["pc"] for x in logs[-5:]])) if logs else float("nan"),
            sparse_loss=float(np.mean([x["sparse"] for x in logs[-5:]])) if logs else float("nan"),
            rays=n_rays * iters,
            samples_per_ray=logs[-1]["samples"] if logs else 0, frames=list(ids),
        )
        return st


def _pixel_patches(imgs: Tensor, frame: Tensor, u: Tensor, v: Tensor, radius: int, step: int = 1) -> Tensor:
    """(2r+1)^2 patches (N, P, C) around integer pixels (u, v) of images ``frame`` (border-clamped),
    in the order of :func:`fmapping.losses.patch_offsets`."""
    _, h, w, _ = imgs.shape
    offsets = torch.arange(-radius, radius + 1, device=imgs.device) * step
    dv, du = torch.meshgrid(offsets, offsets, indexing="ij")
    cols = (u[:, None] + du.reshape(-1)).clamp(0, w - 1)
    rows = (v[:, None] + dv.reshape(-1)).clamp(0, h - 1)
    return imgs[frame[:, None], rows, cols]
