"""The FMapping mapper: init stage + on-the-fly sliding-window optimisation of a neural field.

Conventions are those of :mod:`fmapping.geometry` (metres, OpenCV camera axes,
camera-to-world poses, left-multiplied se(3) corrections ``c2w = exp(xi) @ c2w0``)
and :mod:`fmapping.camera` (z-normalised ray directions: ray parameter == depth).

Stages: :mod:`fmapping.mapping.window_schedule`; the iteration and its losses:
:mod:`fmapping.mapping.optimisation`; the box: :mod:`fmapping.mapping.scene_box`.

All randomness comes from one ``torch.Generator`` saved in the state.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.cancel import StopFn
from fmapping.device import pick_device
from fmapping.field import build_field
from fmapping.geometry import nearest_rotation, se3_exp, se3_inverse
from fmapping.mapping.batch_render import render_batch
from fmapping.mapping.config import MapperConfig
from fmapping.mapping.exposure import fit_colour_gain, undo_exposure
from fmapping.mapping.optimisation import OptimisationStep
from fmapping.mapping.scene_box import aabb_from_depth, aabb_from_poses, points_box
from fmapping.mapping.state_io import MapperStateIO
from fmapping.mapping.image_store import ImageStore
from fmapping.mapping.window_schedule import WindowSchedule, WindowStats
from fmapping.sparse_points import TrackTriangulator


class Mapper(WindowSchedule, OptimisationStep, MapperStateIO):
    """Incremental neural-field mapper. The stages: :mod:`fmapping.mapping.window_schedule`.

    ``should_stop()``, when given, is asked before every optimisation iteration; True raises
    :class:`fmapping.cancel.Cancelled` and leaves the update half-done (a service stopping on a
    signal must not wait for a long update; it resumes from a checkpoint taken between updates)."""

    def __init__(self, cfg: MapperConfig, camera: PinholeCamera, aabb=None, device=None,
                 should_stop: StopFn = None):
        cfg.validate()
        if camera.dist is not None:
            raise ValueError("Mapper: camera must be undistorted (dist=None); undistort the images first")
        self.cfg = cfg
        self.camera = camera
        self.device = pick_device(device if device is not None else cfg.device)
        box = aabb if aabb is not None else cfg.bbox
        self._aabb_given: Optional[Tensor] = None
        if box is not None:
            b = torch.as_tensor(np.asarray(box, np.float64), dtype=torch.float32).reshape(2, 3)
            if not torch.isfinite(b).all() or not (b[1] > b[0]).all():
                raise ValueError(f"Mapper: bounding box must be finite with min < max, got {b.tolist()}")
            self._aabb_given = b
        self.aabb: Optional[Tensor] = None
        self.field = None
        self._opt: Optional[torch.optim.Optimizer] = None
        self._coarse = None  # the factor lines' coarse companions (cfg.coarse_nodes; fmapping.mapping.coarse)
        self._pose_corr: Optional[torch.nn.Parameter] = None
        self._gen = torch.Generator().manual_seed(int(cfg.seed))
        # frames
        # uint8 (H, W, 3) of the window frames (raw) and keyframes (compressed beyond the window)
        self._images = ImageStore(codec=cfg.keyframe_codec, quality=cfg.keyframe_jpeg_quality)
        self._depths: dict[int, Tensor] = {}
        self._poses: dict[int, Tensor] = {}  # float64 (4, 4) c2w of every frame seen (refined at init)
        self._timestamps: dict[int, float] = {}
        self._frame_no: dict[int, int] = {}  # the caller's frame number of a frame id (when it differs)
        self._guessed: set[int] = set()  # frames whose pose was guessed (c2w None)
        self._next_id = 0
        self._init_ids: list[int] = []
        self._pending: list[int] = []
        self._local: list[int] = []
        self._keyframes: list[int] = []
        self._window: list[int] = []
        self.initialized = False
        self._stats: list[WindowStats] = []
        self._iterations = 0
        self._finished = False
        self._should_stop = should_stop
        need_points = (cfg.bounds == "points" and self._aabb_given is None) or cfg.sparse_depth_weight > 0
        self._sparse: Optional[TrackTriangulator] = TrackTriangulator(camera, cfg.sparse) if need_points else None
        self._exposure: dict[int, torch.nn.Parameter] = {}  # frame id -> (a_r, a_g, a_b, b_r, b_g, b_b)
        # frame id -> se(3) correction (camera side) of its pose in the current update (cfg.refine_poses)
        self._pose_delta: dict[int, torch.nn.Parameter] = {}
        self._box_refits = 0
        # the box is the frusta's near..far guess (no points yet at the init): the first points box replaces it
        self._box_provisional = False

    # ================================================================= public API
    def add_frame(self, rgb: np.ndarray, c2w: Optional[np.ndarray], timestamp: float = 0.0,
                  depth: Optional[np.ndarray] = None, defer: bool = False,
                  frame_no: Optional[int] = None) -> Optional[WindowStats]:
        """Add the next frame; run the init stage or a window update when due and return its stats.

        ``defer`` (a caller behind the stream, catching up): a window update waits until up to a whole
        local window (``window_size - n_global_keyframes``) of new frames are pending, instead of
        ``new_frames_per_window``: fewer updates over more frames each.
        ``frame_no``: the frame's number in the caller's stream (default: the order added). Keyframes are
        spaced ``keyframe_every`` stream frames apart, so a caller that skips frames keeps as many."""
        if frame_no is not None and self._next_id > 0 and frame_no <= self.frame_number(self._next_id - 1):
            raise ValueError(f"Mapper.add_frame: frame number {frame_no} does not follow "
                             f"{self.frame_number(self._next_id - 1)}")
        img, pose, dep = self._validate_frame(rgb, c2w, depth)
        fid = self._next_id
        if pose is None:
            pose = self._guess_pose()
            self._guessed.add(fid)
        self._next_id += 1
        self._images[fid] = img
        if dep is not None:
            self._depths[fid] = dep
        self._poses[fid] = pose
        self._timestamps[fid] = float(timestamp)
        if frame_no is not None and frame_no != fid:
            self._frame_no[fid] = int(frame_no)
        self._finished = False
        if self._sparse is not None and fid not in self._guessed:  # a guessed pose would triangulate garbage
            self._sparse.add(fid, img.numpy(), pose.numpy())
        if self.cfg.exposure:
            self._new_frame_param(self._exposure, "exposure", fid)
        if self.cfg.refine_poses:
            self._new_frame_param(self._pose_delta, "pose_refine", fid)
        if not self.initialized:
            self._init_ids.append(fid)
            if len(self._init_ids) >= self.cfg.init_frames:
                return self._run_init()
            return None
        self._pending.append(fid)
        due = self.cfg.window_size - self.cfg.n_global_keyframes if defer else self.cfg.new_frames_per_window
        if len(self._pending) >= due:
            return self._run_window()
        return None

    def frame_number(self, fid: int) -> int:
        """The caller's frame number of frame id ``fid`` (``frame_no`` of :meth:`add_frame`, else ``fid``)."""
        return self._frame_no.get(fid, fid)

    def finish(self, extra_iters: int = 0) -> Optional[WindowStats]:
        """Flush pending frames (init or a last window), then the closing global refinement
        (``final_global_iters`` plus ``extra_iters``: e.g. ``owed_iters_factor`` times the window
        iterations a caller that fell behind the stream skipped, see ``services.mapper.core``)."""
        last = None
        if not self.initialized and self._init_ids:
            last = self._run_init()
        if self._pending:
            last = self._run_window()
        iters = self.cfg.final_global_iters + max(0, int(extra_iters))
        if self.initialized and iters > 0 and not self._finished:
            last = self._run_final(iters)
        self._finished = True
        return last

    def window_due(self) -> bool:
        """Would :meth:`finish` run a last window first (frames pending after the init)?"""
        return self.initialized and bool(self._pending)

    def refine(self, iters: Optional[int] = None) -> Optional[WindowStats]:
        """The closing global refinement over all keyframes now (``iters``, default
        ``final_global_iters``), without ending the run: later frames go on as before. Pending frames
        get their window first. None before the map is initialised."""
        if not self.initialized:
            return None
        if self._pending:
            self._run_window()
        n = self.cfg.final_global_iters if iters is None else int(iters)
        return self._run_final(n) if n > 0 else None

    def set_poses(self, poses: dict) -> int:
        """Replace the poses of frames already added (``{frame id: c2w}``), e.g. with a tracker's
        bundle-adjusted ones; later iterations train on them. Every pose is checked first, so a bad
        one changes nothing. Unknown frame ids are ignored; returns how many poses were replaced."""
        checked = {int(i): _checked_pose(c2w, f"set_poses: frame {i}") for i, c2w in poses.items()
                   if int(i) in self._poses}
        self._poses.update(checked)
        if self._sparse is not None:
            self._sparse.set_poses({i: p.numpy() for i, p in checked.items()})
        return len(checked)

    def frame_poses(self) -> dict[int, np.ndarray]:
        return {i: p.numpy().copy() for i, p in sorted(self._poses.items())}

    def frame_timestamps(self) -> dict[int, float]:
        return dict(sorted(self._timestamps.items()))

    def keyframe_ids(self) -> list[int]:
        return list(self._keyframes)

    def view_ids(self) -> list[int]:
        """The views the map is exported from: the keyframes and the local window's frames (the newest
        ones, not keyframes yet, whose images the mapper still holds), in frame order. Keyframes alone
        leave out what the camera saw last: up to a whole local window of frames, a sixth of the path
        when a mapper behind the stream took every sixth frame."""
        return sorted(set(self._keyframes) | set(self._local))

    def window_ids(self) -> list[int]:
        return list(self._window)

    def keyframe_image(self, fid: int) -> np.ndarray:
        return self._images[fid].numpy().copy()

    def num_parameters(self) -> int:
        return 0 if self.field is None else int(self.field.num_parameters())

    @torch.no_grad()
    def render(self, c2w, camera: Optional[PinholeCamera] = None, chunk: int = 2048,
               samples: Optional[tuple[int, int]] = None, frame: Optional[int] = None) -> dict:
        """Render a full image (deterministic samples, black background) as numpy float32:
        ``rgb`` (H, W, 3) in [0, 1]; ``depth`` (H, W) = ``sum w t`` (not normalised, as
        :class:`fmapping.render.RenderOutput`); ``depth_normalized`` = ``depth / acc`` (the camera z
        of the expected surface, 0 where ``acc`` < 1e-6); ``acc`` (H, W) accumulated opacity. With
        ``frame``, the colour is as that frame's camera saw it (its exposure, :meth:`exposure`)."""
        if self.field is None:
            raise RuntimeError("Mapper.render: the map is not initialised yet")
        cam = camera or self.camera
        pose = torch.as_tensor(np.asarray(c2w, np.float64), dtype=torch.float32, device=self.device)
        if pose.shape != (4, 4) or not torch.isfinite(pose).all():
            raise ValueError(f"Mapper.render: pose must be a finite 4x4 matrix, got shape {tuple(pose.shape)}")
        uv = cam.pixel_grid(device=self.device)
        origins, dirs = cam.rays(pose, uv)
        n_c, n_f = samples if samples is not None else (self.cfg.n_coarse, self.cfg.n_fine)
        rgb, dep, acc = [], [], []
        for s in range(0, len(uv), chunk):
            out, _ = render_batch(self.field, self.aabb, self.cfg, origins[s:s + chunk], dirs[s:s + chunk], "pdf",
                                  n_c, n_f, grad=False)
            rgb.append(out.rgb)
            dep.append(out.depth)
            acc.append(out.acc)
        h, w = cam.height, cam.width
        acc_t, dep_t = torch.cat(acc), torch.cat(dep)
        rgb_t = torch.cat(rgb)
        if frame is not None:
            gain, offset = self.exposure(frame)
            rgb_t = rgb_t * torch.as_tensor(gain, device=rgb_t.device) + torch.as_tensor(offset, device=rgb_t.device)
        dn = torch.where(acc_t > 1e-6, dep_t / acc_t.clamp_min(1e-6), torch.zeros_like(acc_t))
        return {
            "rgb": rgb_t.reshape(h, w, 3).clamp(0, 1).cpu().numpy(),
            "depth": dep_t.reshape(h, w).cpu().numpy(),
            "depth_normalized": dn.reshape(h, w).cpu().numpy(),
            "acc": acc_t.reshape(h, w).cpu().numpy(),
        }

    def stats(self) -> dict:
        win = [s for s in self._stats if s.kind == "window"]
        secs = [s.seconds for s in win]
        return {
            "parameters": self.num_parameters(),
            "frames": self._next_id,
            "keyframes": len(self._keyframes),
            "iterations": self._iterations,
            "windows": [s.to_dict() for s in self._stats],
            "window_seconds_min": min(secs) if secs else None,
            "window_seconds_median": float(np.median(secs)) if secs else None,
            "window_seconds_mean": float(np.mean(secs)) if secs else None,
            "init_seconds": sum(s.seconds for s in self._stats if s.kind == "init"),
            "final_seconds": sum(s.seconds for s in self._stats if s.kind == "final"),
            "total_seconds": sum(s.seconds for s in self._stats),
            "rays_per_iter": self.cfg.rays_per_iter,
            "aabb": None if self.aabb is None else self.aabb.detach().cpu().tolist(),
            "box_refits": self._box_refits,
            "sparse_points": 0 if self._sparse is None else int(len(self._sparse.points)),
            "samples_per_ray": self.cfg.n_coarse + self.cfg.n_fine,
        }

    # ================================================================ validation
    def _validate_frame(self, rgb, c2w, depth):
        cam = self.camera
        if not isinstance(rgb, np.ndarray):
            raise ValueError(f"add_frame: rgb must be a numpy array, got {type(rgb).__name__}")
        if rgb.shape != (cam.height, cam.width, 3):
            raise ValueError(f"add_frame: rgb must have shape ({cam.height}, {cam.width}, 3) to match the camera, "
                             f"got {rgb.shape}")
        if rgb.dtype == np.uint8:
            img = torch.from_numpy(np.ascontiguousarray(rgb)).clone()
        elif np.issubdtype(rgb.dtype, np.floating):
            if not np.isfinite(rgb).all() or rgb.min() < 0 or rgb.max() > 1:
                raise ValueError("add_frame: float rgb must be finite and in [0, 1]")
            img = torch.from_numpy(np.round(rgb * 255).astype(np.uint8))
        else:
            raise ValueError(f"add_frame: rgb dtype must be uint8 or float in [0, 1], got {rgb.dtype}")
        pose = None
        if c2w is None:
            if self.initialized or not self.cfg.optimize_init_poses:
                raise ValueError("add_frame: c2w is required (a pose may be omitted only during init "
                                 "with optimize_init_poses=True)")
        else:
            pose = _checked_pose(c2w, "add_frame: c2w")
        dep = None
        if depth is not None and self.cfg.use_depth:
            d = np.asarray(depth)
            if d.shape != (cam.height, cam.width):
                raise ValueError(f"add_frame: depth must have shape ({cam.height}, {cam.width}), got {d.shape}")
            d = np.where(np.isfinite(d), d, 0).astype(np.float32)
            dep = torch.from_numpy(d)
        return img, pose, dep

    def _guess_pose(self) -> Tensor:
        """Constant-velocity guess from the last two poses (identity for the first frame)."""
        n = self._next_id
        if n == 0:
            return torch.eye(4, dtype=torch.float64)
        if n == 1:
            return self._poses[0].clone()
        a, b = self._poses[n - 2], self._poses[n - 1]
        return b @ se3_inverse(a) @ b

    # ================================================================ per-frame parameters
    def _new_frame_param(self, params: dict, group: str, fid: int) -> None:
        """A zero (6,) parameter of frame ``fid`` in ``params`` (its exposure or pose correction; frame 0's
        stays fixed), joining the optimiser's ``group`` when there is one."""
        p = torch.nn.Parameter(torch.zeros(6, dtype=torch.float32, device=self.device), requires_grad=fid > 0)
        params[fid] = p
        if self._opt is not None and p.requires_grad:
            for g in self._opt.param_groups:
                if g.get("name") == group:
                    g["params"].append(p)

    @torch.no_grad()
    def _fold_pose_deltas(self, ids: list[int]) -> None:
        """Move the update's pose corrections of frames ``ids`` into their poses and zero them (Adam's
        moments stay: the next update goes on from where this one left)."""
        for i in ids:
            d = self._pose_delta.get(i)
            if d is None or not d.requires_grad or not bool(d.any()):
                continue
            p = self._poses[i] @ se3_exp(d.detach().double().cpu())
            p[:3, :3] = nearest_rotation(p[:3, :3])
            self._poses[i] = p
            d.zero_()

    # ================================================================ exposure
    @torch.no_grad()
    def _start_exposures(self, ids: list[int], grid: tuple[int, int] = (40, 30)) -> None:
        """Where frames ``ids`` (entering their first window update) start their colour estimate: the
        previous frame's, with the gains re-fitted (:func:`fit_colour_gain`) to their pixels against the
        previous frame's colours, exposure undone, at the same surface points: a ``grid`` of pixels lifted to
        the map's rendered depth and projected into the previous frame. The map gives only the
        correspondence: its colours are untrained where the camera has just arrived."""
        if not self.cfg.exposure or self.field is None or self.cfg.exposure_start == "none":
            return
        cam = self.camera
        us = ((torch.arange(grid[0], dtype=torch.float32) + 0.5) * cam.width / grid[0]).floor()
        vs = ((torch.arange(grid[1], dtype=torch.float32) + 0.5) * cam.height / grid[1]).floor()
        gv, gu = torch.meshgrid(vs.clamp_max(cam.height - 1), us.clamp_max(cam.width - 1), indexing="ij")
        pu, pv = gu.reshape(-1).long(), gv.reshape(-1).long()
        uv = torch.stack([pu, pv], -1).to(torch.float32)
        for i in sorted(ids):
            p, prev = self._exposure.get(i), self._exposure.get(i - 1)
            if p is None or not p.requires_grad or prev is None:
                continue
            start = prev.detach().clone()
            p.copy_(start)
            if (i - 1) not in self._images:
                continue
            c2w = self._poses[i].to(torch.float32)
            origins, dirs = cam.rays(c2w, uv)
            out, (_, _, hit) = render_batch(self.field, self.aabb, self.cfg, origins.to(self.device),
                                            dirs.to(self.device), "pdf", self.cfg.n_coarse, self.cfg.n_fine,
                                            grad=False, color=False)
            acc = out.acc.cpu()
            pts = (origins + dirs * (out.depth.cpu() / acc.clamp_min(1e-6))[:, None]).double().numpy()
            uv_r, z_r = cam.world_to_pixels(self._poses[i - 1].numpy(), pts)
            ru, rv = np.round(uv_r[:, 0]).astype(np.int64), np.round(uv_r[:, 1]).astype(np.int64)
            ok = (hit.cpu() & (acc > 0.9)).numpy() & (z_r > self.cfg.near) & (ru >= 0) & (ru < cam.width) \
                & (rv >= 0) & (rv < cam.height)
            ok_t = torch.from_numpy(ok)
            obs = self._images[i][pv[ok_t], pu[ok_t]].to(torch.float32) / 255.0
            ref = self._images[i - 1][torch.from_numpy(rv[ok]), torch.from_numpy(ru[ok])].to(torch.float32) / 255.0
            e = start.cpu()
            fit = fit_colour_gain(obs, undo_exposure(ref, e), e[3:])  # against the previous frame's scene colours
            if fit is not None:
                p.copy_(fit.to(p))

    def _exposure_of(self, ids: list[int]) -> Optional[Tensor]:
        """(V, 6) per-frame colour parameters of frames ``ids`` (differentiable), None when off."""
        if not self.cfg.exposure:
            return None
        return torch.stack([self._exposure[i] for i in ids])

    def exposure(self, fid: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``fid``'s estimated colour gain and offset: observed = gain * scene colour + offset."""
        if not self.cfg.exposure or fid not in self._exposure:
            return np.ones(3, np.float32), np.zeros(3, np.float32)
        e = self._exposure[fid].detach().cpu().numpy()
        return 1.0 + e[:3], e[3:].copy()

    # ================================================================ set-up
    def _build(self) -> None:
        """Decide the bounding box and create field + optimiser (at init, or on load)."""
        cfg = self.cfg
        if self._aabb_given is not None:
            box = self._aabb_given
        else:
            ids = self._init_ids
            poses = np.stack([self._poses[i].numpy() for i in ids])
            b = None
            if cfg.use_depth and any(i in self._depths for i in ids):
                b = aabb_from_depth(poses, [self._depths[i].numpy() if i in self._depths else None for i in ids],
                                    self.camera, cfg.bbox_margin)
            if b is None and cfg.bounds == "points":
                self._sparse.flush()
                b = points_box(self._sparse, self._poses, self.camera, cfg.bbox_margin)
            if b is None:
                b = aabb_from_poses(poses, self.camera, cfg.near, cfg.far, cfg.bbox_margin)
                self._box_provisional = cfg.bounds == "points" and self._sparse is not None
            box = torch.as_tensor(b, dtype=torch.float32)
        self.aabb = box.to(self.device)
        self.field = build_field(cfg.field, self.aabb.cpu()).to(self.device)  # seeded by cfg.field.seed
        if cfg.optimize_init_poses:
            self._pose_corr = torch.nn.Parameter(
                torch.zeros(cfg.init_frames, 6, dtype=torch.float32, device=self.device))
        self._make_optimizer()

    def _grow_box(self) -> None:
        """Re-fit the box to the triangulated points when they leave it (the camera explores): the box
        only grows, the field is resampled onto it (:meth:`fmapping.field.Field.refit_box`). A box that was
        only the frusta's guess (the init had no points: a camera turning on the spot) is replaced by the
        first points box, smaller or not."""
        cfg = self.cfg
        if self._aabb_given is not None or cfg.bounds != "points" or self._sparse is None:
            return
        b = points_box(self._sparse, self._poses, self.camera, cfg.bbox_margin)
        if b is None:
            return
        cur = self.aabb.detach().cpu().numpy().astype(np.float64)
        if self._box_provisional:
            new = np.stack([np.maximum(cur[0], b[0]), np.minimum(cur[1], b[1])])  # within the guess
            if not (new[1] > new[0]).all():
                return
            self._box_provisional = False
        else:
            slack = cfg.bounds_grow * (cur[1] - cur[0])
            if not ((cur[0] - b[0] > slack).any() or (b[1] - cur[1] > slack).any()):
                return
            new = np.stack([np.minimum(cur[0], b[0]), np.maximum(cur[1], b[1])])
        try:
            self.field.refit_box(new)
        except NotImplementedError:
            return
        self.aabb = self.field.aabb.detach().clone()
        for p in self.field.grid_parameters():  # Adam's moments belonged to the old node positions
            self._opt.state.pop(p, None)
        for c in (self._coarse.params() if self._coarse is not None else []):
            self._opt.state.pop(c, None)
        self._box_refits += 1


def _checked_pose(c2w, what: str) -> Tensor:
    """float64 (4, 4) tensor of a rigid camera-to-world pose; ValueError naming ``what`` otherwise."""
    p = np.asarray(c2w, dtype=np.float64)
    if p.shape != (4, 4):
        raise ValueError(f"{what} must be 4x4, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{what} contains NaN or Inf")
    r = p[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(r) - 1) > 1e-3 \
            or np.abs(p[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise ValueError(f"{what} is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return torch.from_numpy(p.copy())

