"""The FMapping mapper: init stage + on-the-fly sliding-window optimisation of a neural field.

Conventions are those of :mod:`fmapping.geometry` (metres, OpenCV camera axes,
camera-to-world poses, left-multiplied se(3) corrections ``c2w = exp(xi) @ c2w0``)
and :mod:`fmapping.camera` (z-normalised ray directions: ray parameter == depth).

Stages (paper, Sec. "System overview"):

* **Init**: the first ``init_frames`` frames are optimised jointly with the
  field over four sampling rounds ``init_rounds`` = (sliding-window size, samples
  per ray); window size 0 is plain stratified sampling. Frame 0 is fixed; the
  other init poses get se(3) corrections when ``optimize_init_poses``. The colour
  decoder is frozen afterwards.
* **On the fly**: an active window of ``window_size`` frames = up to
  ``n_global_keyframes`` global keyframes (half chosen for overlap with the
  recent frames, half at random for coverage) + the most recent local frames.
  Every ``new_frames_per_window`` new frames, ``iters_per_window`` iterations
  run; the oldest local frames leave the window (every ``keyframe_every``-th
  frame becomes a global keyframe).
* **Finish**: pending frames form a last window; then ``final_global_iters``
  iterations over windows of overlapping keyframes refine the whole map.

Every iteration samples ``rays_per_iter`` random pixels of the window, renders
them (coarse stratified pass without gradients, then ``n_fine`` importance or
sliding-window samples; only coarse samples that matter are re-evaluated with
gradients, see :meth:`Mapper._render_batch`) and minimises

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

All randomness comes from one ``torch.Generator`` saved in the state.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field as dc_field
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.cancel import StopFn, check_stop
from fmapping.device import pick_device
from fmapping.field import FieldConfig, build_field
from fmapping.geometry import nearest_rotation, se3_exp, se3_inverse
from fmapping.losses import (distortion_loss, expected_depth_l1, photometric_loss, sample_consistency_cost,
                             sparse_depth_loss, warping_loss)
from fmapping.render import alpha_to_weights, composite, raw_to_alpha, render_rays, sample_deltas
from fmapping.sampling import ray_aabb, sample_pdf, stratified
from fmapping.sampling.sliding_window import sliding_window_sample
from fmapping.sparse_points import SparsePointsConfig, TrackTriangulator, aabb_from_points, seen_depth_box

STATE_VERSION = 1


@dataclass
class MapperConfig:
    """Mapper settings (YAML-overridable through :func:`fmapping.config.load_config`).

    Defaults follow the paper where it is specific (15 init frames, rounds 32 / 64 / 64 / 64
    with sliding windows 3 / 4 / 5, window of 20 frames, 20 iterations every 5 frames, Adam
    lr 0.02 / 0.001, decoder frozen after init) and were measured on synthetic rooms where it
    is not (GT poses, RGB only, 200 frames at 320x240, bench/mapping.py): 1024 rays x (32
    coarse + 16 importance) samples, warping weight 2 over 8 random window views with the
    mean over the valid views (``warp_keep`` 1; keeping only the best half favours the
    small-baseline views, which barely see depth errors - on the 15 init frames both gave the
    same depth error), per-sample photo-consistency weight 4. In the init rounds
    the "samples per ray" are the coarse stratified samples plus ``samples - n_coarse``
    sliding-window samples.
    """

    field: FieldConfig = dc_field(default_factory=FieldConfig)
    # --- init stage
    init_frames: int = 15
    init_rounds: tuple = ((0, 32), (3, 64), (4, 64), (5, 64))  # (sliding window size (0 = stratified), samples per ray)
    init_iters_per_round: int = 75
    optimize_init_poses: bool = True  # frame 0 fixed; se(3) corrections for the others
    freeze_decoder_after_init: bool = True
    # --- on-the-fly stage
    window_size: int = 20
    new_frames_per_window: int = 5
    iters_per_window: int = 20
    n_global_keyframes: int = 10
    keyframe_every: int = 5
    # --- rays and samples
    rays_per_iter: int = 1024
    n_coarse: int = 32  # stratified samples (evaluated without gradient, density only)
    n_fine: int = 16  # importance / sliding-window samples added to them
    sampler: str = "pdf"  # on-the-fly fine samples: "pdf" | "sliding_window" | "stratified"
    sw_window: int = 5
    color_threshold: float = 0.01  # colour evaluated only where weight > this x the ray's max weight
    active_threshold: float = 1e-3  # coarse samples re-evaluated with gradient only above this x max opacity (0: all)
    # --- optimiser
    lr_grid: float = 0.02
    lr_decoder: float = 0.001
    lr_pose: float = 0.001
    # --- losses
    photo_loss: str = "l2"
    huber_delta: float = 0.1
    warp_weight: float = 2.0
    warp_radius: int = 1
    warp_dilations: tuple = (1.0,)
    warp_keep: float = 1.0
    warp_views: int = 8  # target views per iteration (random subset of the window; 0 = all)
    warp_depth: str = "expected"  # depth for warping: "expected" (sum w t / acc) | "far" (unreached mass at the ray's far bound)
    pc_weight: float = 4.0  # per-sample photo-consistency loss sum_i w_i (cost_i - mean cost) (plane-sweep cost volume)
    pc_rays: int = 512  # rays (of rays_per_iter) that get the per-sample cost
    pc_views: int = 4  # other window views the per-sample cost is computed in
    pc_radius: int = 0  # patch radius of the per-sample cost
    tv_weight: float = 0.0
    l1_weight: float = 0.0
    distortion_weight: float = 0.0  # mip-NeRF 360 distortion loss on the colour rays (compact termination, no fog)
    use_depth: bool = False
    depth_weight: float = 0.5
    # --- sparse points: KLT tracks triangulated with the given poses (fmapping.sparse_points)
    sparse: SparsePointsConfig = dc_field(default_factory=SparsePointsConfig)
    sparse_depth_weight: float = 1.0  # weight of the sparse depth term (0: off); pulls rays onto triangulated points
    sparse_rays: int = 256  # rays per iteration through triangulated points
    sparse_fill_weight: float = 0.0  # weight (x the points') of depth filled in between a frame's points (0: off)
    # --- per-frame affine colour (auto exposure / white balance): rendered = (1 + a) * colour + b per channel
    exposure: bool = True
    lr_exposure: float = 0.001
    exposure_reg: float = 0.01  # pull of (a, b) towards 0 (no change)
    # --- scene bounds
    near: float = 0.1
    far: float = 6.0
    bbox: Optional[tuple] = None  # ((xmin, ymin, zmin), (xmax, ymax, zmax)); given: fixed, no growth
    bbox_margin: float = 0.1
    bounds: str = "points"  # box without `bbox`: "points" (triangulated, grows with them) | "frusta" (near..far)
    bounds_grow: float = 0.05  # re-fit the box when the points leave it by more than this share of its extent
    # --- closing refinement
    final_global_iters: int = 300
    seed: int = 0
    device: str = "auto"

    def validate(self) -> None:
        if self.init_frames < 1:
            raise ValueError(f"MapperConfig.init_frames must be >= 1, got {self.init_frames}")
        if self.window_size < 2 or not 0 <= self.n_global_keyframes < self.window_size:
            raise ValueError(f"MapperConfig: need window_size >= 2 and 0 <= n_global_keyframes < window_size, "
                             f"got {self.window_size}, {self.n_global_keyframes}")
        if self.new_frames_per_window < 1 or self.new_frames_per_window > self.window_size - self.n_global_keyframes:
            raise ValueError("MapperConfig.new_frames_per_window must be in 1..window_size - n_global_keyframes")
        if self.sampler not in ("pdf", "sliding_window", "stratified"):
            raise ValueError(f"MapperConfig.sampler must be pdf, sliding_window or stratified, got {self.sampler!r}")
        if self.bounds not in ("points", "frusta"):
            raise ValueError(f"MapperConfig.bounds must be 'points' or 'frusta', got {self.bounds!r}")
        if min(self.sparse_depth_weight, self.sparse_rays, self.sparse_fill_weight, self.lr_exposure, self.exposure_reg,
               self.distortion_weight) < 0:
            raise ValueError("MapperConfig: sparse_depth_weight, sparse_rays, sparse_fill_weight, lr_exposure, exposure_reg "
                             "and distortion_weight must be >= 0")
        self.sparse.validate()
        if self.warp_depth not in ("far", "expected"):
            raise ValueError(f"MapperConfig.warp_depth must be 'far' or 'expected', got {self.warp_depth!r}")
        if not 0 < self.near < self.far:
            raise ValueError(f"MapperConfig: need 0 < near < far, got near={self.near}, far={self.far}")
        if self.rays_per_iter < 1 or self.n_coarse < 2:
            raise ValueError("MapperConfig: rays_per_iter must be >= 1 and n_coarse >= 2")
        for r in self.init_rounds:
            if len(r) != 2 or r[0] < 0 or r[1] < 2:
                raise ValueError(f"MapperConfig.init_rounds entries are (window >= 0, samples >= 2), got {r!r}")


@dataclass
class WindowStats:
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

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def aabb_from_poses(c2w: np.ndarray, camera: PinholeCamera, near: float, far: float, margin: float = 0.1) -> np.ndarray:
    """Bounding box (2, 3) of the view frusta (near..far) of the cameras ``c2w`` (N, 4, 4)."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    w, h = camera.width, camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]], np.float64)
    d = np.stack([(corners[:, 0] - camera.cx) / camera.fx, (corners[:, 1] - camera.cy) / camera.fy, np.ones(4)], -1)
    pts = np.concatenate([d * near, d * far])  # (8, 3) camera frame
    world = np.einsum("nij,kj->nki", c2w[:, :3, :3], pts) + c2w[:, None, :3, 3]
    allp = np.concatenate([world.reshape(-1, 3), c2w[:, :3, 3]])
    return np.stack([allp.min(0) - margin, allp.max(0) + margin])


def aabb_from_depth(c2w: np.ndarray, depths: list, camera: PinholeCamera, margin: float = 0.1,
                    stride: int = 8) -> Optional[np.ndarray]:
    """Bounding box (2, 3) of the back-projected valid depth of frames (robust 0.5/99.5 percentiles)."""
    pts = []
    uv = camera.pixel_grid(dtype=torch.float64).numpy().reshape(camera.height, camera.width, 2)[::stride, ::stride]
    for pose, dep in zip(c2w, depths):
        if dep is None:
            continue
        z = np.asarray(dep, np.float64)[::stride, ::stride]
        ok = np.isfinite(z) & (z > 0)
        if not ok.any():
            continue
        p = np.stack([(uv[..., 0][ok] - camera.cx) / camera.fx * z[ok], (uv[..., 1][ok] - camera.cy) / camera.fy * z[ok], z[ok]], -1)
        pts.append(p @ pose[:3, :3].T + pose[:3, 3])
        pts.append(pose[None, :3, 3])
    if not pts:
        return None
    allp = np.concatenate(pts)
    return np.stack([np.percentile(allp, 0.5, 0) - margin, np.percentile(allp, 99.5, 0) + margin])


class Mapper:
    """Incremental neural-field mapper. See the module docstring for the stages.

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
        self._pose_corr: Optional[torch.nn.Parameter] = None
        self._gen = torch.Generator().manual_seed(int(cfg.seed))
        # frames
        self._images: dict[int, Tensor] = {}  # uint8 (H, W, 3), kept for window / keyframes
        self._depths: dict[int, Tensor] = {}
        self._poses: dict[int, Tensor] = {}  # float64 (4, 4) c2w of every frame seen (refined at init)
        self._timestamps: dict[int, float] = {}
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
        self._box_refits = 0

    # ================================================================= public API
    def add_frame(self, rgb: np.ndarray, c2w: Optional[np.ndarray], timestamp: float = 0.0,
                  depth: Optional[np.ndarray] = None) -> Optional[WindowStats]:
        """Add the next frame; run the init stage or a window update when due and return its stats."""
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
        self._finished = False
        if self._sparse is not None and fid not in self._guessed:  # a guessed pose would triangulate garbage
            self._sparse.add(fid, img.numpy(), pose.numpy())
        if self.cfg.exposure:
            self._new_exposure(fid)
        if not self.initialized:
            self._init_ids.append(fid)
            if len(self._init_ids) >= self.cfg.init_frames:
                return self._run_init()
            return None
        self._pending.append(fid)
        if len(self._pending) >= self.cfg.new_frames_per_window:
            return self._run_window()
        return None

    def finish(self) -> Optional[WindowStats]:
        """Flush pending frames (init or a last window), then the closing global refinement."""
        last = None
        if not self.initialized and self._init_ids:
            last = self._run_init()
        if self._pending:
            last = self._run_window()
        if self.initialized and self.cfg.final_global_iters > 0 and not self._finished:
            last = self._run_final()
        self._finished = True
        return last

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
        o, d = cam.rays(pose, uv)
        n_c, n_f = samples if samples is not None else (self.cfg.n_coarse, self.cfg.n_fine)
        rgb, dep, acc = [], [], []
        for s in range(0, len(uv), chunk):
            out, _ = self._render_batch(o[s:s + chunk], d[s:s + chunk], "pdf", n_c, n_f, grad=False)
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

    # ================================================================ exposure
    def _new_exposure(self, fid: int) -> None:
        p = torch.nn.Parameter(torch.zeros(6, dtype=torch.float32, device=self.device), requires_grad=fid > 0)
        self._exposure[fid] = p
        if self._opt is not None and p.requires_grad:
            for g in self._opt.param_groups:
                if g.get("name") == "exposure":
                    g["params"].append(p)

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
                b = self._points_box()
            if b is None:
                b = aabb_from_poses(poses, self.camera, cfg.near, cfg.far, cfg.bbox_margin)
            box = torch.as_tensor(b, dtype=torch.float32)
        self.aabb = box.to(self.device)
        self.field = build_field(cfg.field, self.aabb.cpu()).to(self.device)  # seeded by cfg.field.seed
        if cfg.optimize_init_poses:
            self._pose_corr = torch.nn.Parameter(torch.zeros(cfg.init_frames, 6, dtype=torch.float32, device=self.device))
        self._make_optimizer()

    def _make_optimizer(self) -> None:
        cfg = self.cfg
        # one "grid" group per (params, lr multiplier) of the field (cp / vm / mlp: one, x1)
        groups = [{"params": list(ps), "lr": cfg.lr_grid * scale, "name": "grid"}
                  for ps, scale in self.field.grid_param_groups()]
        groups.append({"params": list(self.field.decoder_parameters()), "lr": cfg.lr_decoder, "name": "decoder"})
        if self._pose_corr is not None:
            groups.append({"params": [self._pose_corr], "lr": cfg.lr_pose, "name": "pose"})
        if cfg.exposure:  # frame 0 fixes the colour gauge; frames after the build join the group as they come
            groups.append({"params": [p for i, p in sorted(self._exposure.items()) if p.requires_grad],
                           "lr": cfg.lr_exposure, "name": "exposure"})
        groups = [g for g in groups if g["params"] or g["name"] == "exposure"]
        self._opt = torch.optim.Adam(groups, betas=(0.9, 0.99))

    def _set_lr(self, name: str, lr: float) -> None:
        for g in self._opt.param_groups:
            if g.get("name") == name:
                g["lr"] = lr

    def _freeze_decoder(self) -> None:
        for p in self.field.decoder_parameters():
            p.requires_grad_(False)
        for g in self._opt.param_groups:
            if g.get("name") in ("decoder", "pose"):
                g["lr"] = 0.0
        if self._pose_corr is not None:
            self._pose_corr.requires_grad_(False)

    # ================================================================ rendering core
    def _near_far(self, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        tn, tf, hit = ray_aabb(o, d, self.aabb, near_min=self.cfg.near)
        tf = tf.clamp_max(self.cfg.far)
        ok = hit & (tf > tn + 1e-3)
        tf = torch.where(ok, tf, tn + 1e-2)
        return tn, tf, ok

    def _render_batch(self, o: Tensor, d: Tensor, mode: str, n_coarse: int, n_fine: int, grad: bool = True,
                      sw_window: int = 0, color: bool = True):
        """Sample and render rays (background black).

        ``mode`` "stratified": ``n_coarse`` stratified samples, all rendered. "pdf" /
        "sliding_window": a coarse stratified pass without gradient, then ``n_fine``
        importance / sliding-window samples; the union is rendered. With ``grad`` and
        ``active_threshold`` > 0, only *active* coarse samples are re-evaluated with gradient:
        those not hidden (transmittance > 1e-4) and with opacity above ``active_threshold`` x
        the ray's largest coarse opacity (all of them on rays that are still empty); the others
        keep their exact no-grad density, so the forward render is unchanged and only
        negligible gradients are skipped.
        """
        cfg = self.cfg
        tn, tf, ok = self._near_far(o, d)
        gen = self._gen if grad else None
        t = stratified(tn, tf, n_coarse, perturb=grad, generator=gen)
        if mode == "stratified" or n_fine <= 0:
            with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
                out = render_rays(self.field, o, d, t, background=0.0, color_weight_threshold=cfg.color_threshold)
            return out, (tn, tf, ok)
        field = self.field
        dnorm = d.norm(dim=-1)
        n = o.shape[0]
        with torch.no_grad():
            xyz_c = o[:, None, :] + t[..., None] * d[:, None, :]
            raw_c = field.density_raw(xyz_c.reshape(-1, 3)).view(n, n_coarse)
            alpha_c = raw_to_alpha(raw_c, sample_deltas(t, dnorm), field.cfg.alpha_mode, field.cfg.density_shift)
            w = alpha_to_weights(alpha_c)
            if mode == "sliding_window":
                t_new = sliding_window_sample(t, w, n_fine, window=max(sw_window, 1), generator=gen)
            else:
                t_new = sample_pdf(t, w, n_fine, deterministic=not grad, generator=gen)
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
            ri, si = active.nonzero(as_tuple=True)
            xyz = o[ri] + t_all[ri, si, None] * d[ri]
            raw_act = field.density_raw(xyz)
            raw = raw_known.index_put((ri, si), raw_act)
            alpha = raw_to_alpha(raw, sample_deltas(t_all, dnorm), field.cfg.alpha_mode, field.cfg.density_shift)
            out = composite(alpha, t_all, None, None)
            if not color:  # depth-only rays (the sparse depth term)
                return out, (tn, tf, ok)
            wd = out.weights.detach()
            mask = wd > cfg.color_threshold * wd.amax(-1, keepdim=True)
            cr, cs = mask.nonzero(as_tuple=True)
            rgb = torch.zeros(n, 3, dtype=alpha.dtype, device=alpha.device)
            if cr.numel() > 0:
                c = field.color(o[cr] + t_all[cr, cs, None] * d[cr])
                rgb = rgb.index_add(0, cr, out.weights[cr, cs, None] * c)
            out.rgb = rgb
        return out, (tn, tf, ok)

    # ================================================================ optimisation
    def _frame_c2w(self, ids: list[int]) -> Tensor:
        """float32 (V, 4, 4) poses of frames ``ids`` on the device, with init corrections (differentiable)."""
        base = torch.stack([self._poses[i] for i in ids]).to(self.device, torch.float32)
        if self._pose_corr is None or not self._pose_corr.requires_grad:
            return base
        nc = self._pose_corr.shape[0]
        rows = torch.tensor([self._init_ids.index(i) if i in self._init_ids[1:nc] else -1 for i in ids],
                            device=self.device)
        table = torch.cat([torch.zeros(1, 6, device=self.device), self._pose_corr[1:],
                           torch.zeros(1, 6, device=self.device)])  # row 0: frame 0 fixed; last row: no correction
        corr = table[torch.where(rows < 0, torch.full_like(rows, table.shape[0] - 1), rows)]
        return se3_exp(corr) @ base

    def _images_f(self, ids: list[int]) -> Tensor:
        return torch.stack([self._images[i] for i in ids]).to(self.device, torch.float32) / 255.0

    @torch.no_grad()
    def _scene_images(self, ids: list[int], imgs: Tensor) -> Tensor:
        """``imgs`` with each frame's current exposure undone (observed = (1 + a) c + b)."""
        expo = self._exposure_of(ids)
        if expo is None:
            return imgs
        e = expo.detach()
        return (imgs - e[:, None, None, 3:]) / (1 + e[:, None, None, :3]).clamp_min(0.1)

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
        f, uv, z, w = (np.concatenate(x) for x in zip(*rows))
        dev = self.device
        return (torch.as_tensor(f, device=dev), torch.as_tensor(uv, dtype=torch.float32, device=dev),
                torch.as_tensor(z, dtype=torch.float32, device=dev), torch.as_tensor(w, dtype=torch.float32, device=dev))

    def _step(self, ids: list[int], imgs: Tensor, mode: str, n_coarse: int, n_fine: int, sw_window: int = 0,
              scene_imgs: Optional[Tensor] = None, sparse: Optional[tuple] = None) -> dict:
        """One optimisation iteration over the window ``ids`` (images ``imgs``, float (V, H, W, 3)).
        ``scene_imgs``: the images with each frame's exposure undone (for the losses that compare
        views with each other); ``sparse``: the window's triangulated points (:meth:`_sparse_batch`)."""
        cfg, cam = self.cfg, self.camera
        scene_imgs = imgs if scene_imgs is None else scene_imgs
        n = cfg.rays_per_iter
        v = len(ids)
        g = self._gen
        fi = torch.randint(v, (n,), generator=g).to(self.device)
        u = torch.randint(cam.width, (n,), generator=g).to(self.device)
        vv = torch.randint(cam.height, (n,), generator=g).to(self.device)
        uv = torch.stack([u, vv], -1).to(torch.float32)
        c2w = self._frame_c2w(ids)
        o, d = cam.rays(c2w[fi], uv)
        target = imgs[fi, vv, u]
        out, (tn, tf, ok) = self._render_batch(o, d, mode, n_coarse, n_fine, grad=True, sw_window=sw_window)
        okf = ok.to(torch.float32)
        expo = self._exposure_of(ids)
        pred = out.rgb if expo is None else out.rgb * (1 + expo[fi, :3]) + expo[fi, 3:]
        photo = photometric_loss(pred, target, cfg.photo_loss, cfg.huber_delta, weight=okf)
        loss = photo
        if cfg.distortion_weight > 0 and bool(ok.any()):
            loss = loss + cfg.distortion_weight * distortion_loss(out.weights[ok], out.t[ok], tn[ok], tf[ok])
        warp = torch.zeros((), device=self.device)
        if cfg.warp_weight > 0 and v > 1:
            if cfg.warp_depth == "far":
                depth = out.depth + (1 - out.acc) * tf
            else:
                depth = out.depth / out.acc.clamp_min(1e-3)
            if 0 < cfg.warp_views < v:  # a random subset of the window as target views (cost ~ views)
                sub = torch.randperm(v, generator=g)[:cfg.warp_views].to(self.device)
                pos = torch.full((v,), -1, dtype=torch.long, device=self.device)
                pos[sub] = torch.arange(len(sub), device=self.device)
                w_imgs, w_c2w, w_src = scene_imgs[sub], c2w[sub], pos[fi]
            else:
                w_imgs, w_c2w, w_src = scene_imgs, c2w, fi
            for dil in cfg.warp_dilations:
                ref = _pixel_patches(scene_imgs, fi, u, vv, cfg.warp_radius, int(round(float(dil))))
                res = warping_loss(o, d, depth, uv, w_src, w_imgs, w_c2w, cam, radius=cfg.warp_radius,
                                   dilation=float(dil), keep=cfg.warp_keep, min_z=cfg.near, ray_weight=okf,
                                   ref_colors=ref)
                warp = warp + res.loss / len(cfg.warp_dilations)
            loss = loss + cfg.warp_weight * warp
        pc = torch.zeros((), device=self.device)
        if cfg.pc_weight > 0 and v > 1:
            pc = self._pc_loss(out, o, d, fi, u, vv, scene_imgs, c2w)
            loss = loss + cfg.pc_weight * pc
        sp = torch.zeros((), device=self.device)
        if sparse is not None and cfg.sparse_depth_weight > 0 and cfg.sparse_rays > 0:
            s_frame, s_uv, s_z, s_w = sparse
            pick = torch.randint(len(s_z), (min(cfg.sparse_rays, len(s_z)),), generator=g).to(self.device)
            so, sd = cam.rays(c2w[s_frame[pick]], s_uv[pick])
            s_out, (_, s_tf, s_ok) = self._render_batch(so, sd, mode, n_coarse, n_fine, grad=True, sw_window=sw_window,
                                                        color=False)
            sp = sparse_depth_loss(s_out.weights, s_out.t, s_out.acc, s_tf, s_z[pick], s_w[pick] * s_ok)
            loss = loss + cfg.sparse_depth_weight * sp
        if expo is not None and cfg.exposure_reg > 0:
            loss = loss + cfg.exposure_reg * expo.pow(2).mean()
        if cfg.use_depth and self._depths:
            dts = [self._depths.get(i) for i in ids]
            if all(x is not None for x in dts):
                dgt = torch.stack(dts).to(self.device)[fi, vv, u]
                loss = loss + cfg.depth_weight * expected_depth_l1(out.weights, out.t, out.acc, tf, dgt)
        if cfg.tv_weight > 0:
            loss = loss + cfg.tv_weight * self.field.regularizer("tv")
        if cfg.l1_weight > 0:
            loss = loss + cfg.l1_weight * self.field.regularizer("l1")
        self._opt.zero_grad(set_to_none=True)
        loss.backward()
        self._opt.step()
        self._iterations += 1
        return {"loss": float(loss.detach()), "photo": float(photo.detach()), "warp": float(warp.detach()),
                "pc": float(pc.detach()), "sparse": float(sp.detach()), "samples": int(out.t.shape[-1]) if hasattr(out, "t") and out.t is not None else n_coarse + n_fine}

    def _pc_loss(self, out, o: Tensor, d: Tensor, fi: Tensor, u: Tensor, vv: Tensor, imgs: Tensor,
                 c2w: Tensor) -> Tensor:
        """Per-sample photo-consistency: rendering weights are pulled to samples whose colour agrees
        across views (cost below the ray's mean cost) and pushed from the others."""
        cfg = self.cfg
        v = imgs.shape[0]
        m = min(cfg.pc_rays, o.shape[0])
        k = min(cfg.pc_views, v)
        views = torch.randperm(v, generator=self._gen)[:k].to(self.device)
        pos = torch.full((v,), -1, dtype=torch.long, device=self.device)
        pos[views] = torch.arange(k, device=self.device)
        src = pos[fi[:m]]
        t = out.t[:m].detach()
        pts = o[:m, None].detach() + d[:m, None].detach() * t[..., None]
        ref = _pixel_patches(imgs, fi[:m], u[:m], vv[:m], cfg.pc_radius, 1)
        cost, nval = sample_consistency_cost(pts, ref, src, imgs[views], c2w[views].detach(), self.camera,
                                             radius=cfg.pc_radius, keep=1.0, min_z=cfg.near)
        valid = (nval > 0).to(cost.dtype)
        cbar = (cost * valid).sum(-1, keepdim=True) / valid.sum(-1, keepdim=True).clamp_min(1)
        w = out.weights[:m]
        return ((w * (cost - cbar) * valid).sum(-1)).mean()

    def _run_iters(self, kind: str, ids: list[int], iters: int, mode: str, n_coarse: int, n_fine: int,
                   sw_window: int = 0, t0: Optional[float] = None) -> WindowStats:
        t0 = time.perf_counter() if t0 is None else t0
        imgs = self._images_f(ids)
        sparse = self._sparse_batch(ids)
        scene_imgs = self._scene_images(ids, imgs)  # the exposures move slowly: undone once per update
        logs = []
        for _ in range(iters):
            check_stop(self._should_stop, f"{kind} update (after {len(logs)} of {iters} iterations)")
            logs.append(self._step(ids, imgs, mode, n_coarse, n_fine, sw_window, scene_imgs, sparse))
        st = WindowStats(
            index=len(self._stats), kind=kind, seconds=time.perf_counter() - t0, iterations=iters,
            loss=float(np.mean([x["loss"] for x in logs[-5:]])) if logs else float("nan"),
            photo_loss=float(np.mean([x["photo"] for x in logs[-5:]])) if logs else float("nan"),
            warp_loss=float(np.mean([x["warp"] for x in logs[-5:]])) if logs else float("nan"),
            pc_loss=float(np.mean([x["pc"] for x in logs[-5:]])) if logs else float("nan"),
            rays=self.cfg.rays_per_iter * iters,
            samples_per_ray=logs[-1]["samples"] if logs else 0, frames=list(ids),
        )
        return st

    def _run_init(self) -> WindowStats:
        cfg = self.cfg
        t0 = time.perf_counter()
        self._build()
        ids = list(self._init_ids)
        st = None
        total = {"iters": 0, "loss": [], "photo": [], "warp": []}
        for r, (window, samples) in enumerate(cfg.init_rounds):
            # exposures start after the first round: from an empty map, a colour offset would explain the images
            self._set_lr("exposure", cfg.lr_exposure if r > 0 else 0.0)
            if window == 0:
                s = self._run_iters("init", ids, cfg.init_iters_per_round, "stratified", samples, 0)
            else:  # the round's samples = the coarse stratified ones + (samples - n_coarse) sliding-window ones
                s = self._run_iters("init", ids, cfg.init_iters_per_round, "sliding_window", cfg.n_coarse,
                                    max(1, samples - cfg.n_coarse), sw_window=window)
            total["iters"] += s.iterations
            total["loss"].append(s.loss)
            total["photo"].append(s.photo_loss)
            total["warp"].append(s.warp_loss)
            st = s
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
            if len(ids) - ids.index(i) > n_local and (i - self._keyframes[-1]) >= cfg.keyframe_every:
                self._keyframes.append(i)
        self._local = ids[-n_local:]
        for i in ids:
            self._drop_image_if_unused(i)
        self._window = ids
        stats = WindowStats(index=len(self._stats), kind="init", seconds=time.perf_counter() - t0,
                            iterations=total["iters"], loss=total["loss"][-1], photo_loss=total["photo"][-1],
                            warp_loss=total["warp"][-1], rays=cfg.rays_per_iter * total["iters"],
                            samples_per_ray=st.samples_per_ray if st else 0, frames=ids,
                            pc_loss=st.pc_loss if st else 0.0)
        self._stats.append(stats)
        return stats

    def _drop_image_if_unused(self, fid: int) -> None:
        if fid not in self._local and fid not in self._keyframes and fid not in self._pending:
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
            last_kf = self._keyframes[-1] if self._keyframes else -10 ** 9
            if old - last_kf >= cfg.keyframe_every:
                self._keyframes.append(old)
            self._drop_image_if_unused(old)
        self._grow_box()
        glob = self._select_global(self._local, cfg.n_global_keyframes)
        ids = glob + list(self._local)
        self._window = ids
        st = self._run_iters("window", ids, cfg.iters_per_window, cfg.sampler, cfg.n_coarse, cfg.n_fine,
                             sw_window=cfg.sw_window, t0=t0)
        self._stats.append(st)
        return st

    def _points_box(self) -> Optional[np.ndarray]:
        """The box of the triangulated points and camera centres, widened to hold what each camera saw out
        to the depth of its own points (:func:`fmapping.sparse_points.seen_depth_box`), plus the margin."""
        ids = [i for i in self._sparse.frame_ids if i in self._poses]
        if not ids:
            return None
        poses = np.stack([self._poses[i].numpy() for i in ids])
        b = aabb_from_points(self._sparse.points, poses[:, :3, 3], margin=self.cfg.bbox_margin)
        seen = seen_depth_box(poses, [self._sparse.frame_depths(i)[1] for i in ids], self.camera)
        if b is None or seen is None:
            return b
        pad = np.maximum(self.cfg.bbox_margin, 0.05 * (seen[1] - seen[0]))
        return np.stack([np.minimum(b[0], seen[0] - pad), np.maximum(b[1], seen[1] + pad)])

    def _grow_box(self) -> None:
        """Re-fit the box to the triangulated points when they leave it (the camera explores): the box
        only grows, the field is resampled onto it (:meth:`fmapping.field.Field.refit_box`)."""
        cfg = self.cfg
        if self._aabb_given is not None or cfg.bounds != "points" or self._sparse is None:
            return
        b = self._points_box()
        if b is None:
            return
        cur = self.aabb.detach().cpu().numpy().astype(np.float64)
        slack = cfg.bounds_grow * (cur[1] - cur[0])
        if not ((cur[0] - b[0] > slack).any() or (b[1] - cur[1] > slack).any()):
            return
        try:
            self.field.refit_box(np.stack([np.minimum(cur[0], b[0]), np.maximum(cur[1], b[1])]))
        except NotImplementedError:
            return
        self.aabb = self.field.aabb.detach().clone()
        for p in self.field.grid_parameters():  # Adam's moments belonged to the old node positions
            self._opt.state.pop(p, None)
        self._box_refits += 1

    def _run_final(self) -> WindowStats:
        cfg = self.cfg
        t0 = time.perf_counter()
        pool = sorted(set(self._keyframes) | set(self._local))
        logs = []
        done = 0
        chunk = max(1, cfg.iters_per_window)
        while done < cfg.final_global_iters:
            k = min(chunk, cfg.final_global_iters - done)
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
        vv, uu = torch.meshgrid(vs, us, indexing="ij")
        uv = torch.stack([uu.reshape(-1), vv.reshape(-1)], -1).to(self.device)
        pts = []
        for i in ids:
            c2w = self._poses[i].to(self.device, torch.float32)
            o, d = cam.rays(c2w, uv)
            out, (tn, tf, ok) = self._render_batch(o, d, "pdf", 16, 8, grad=False)
            dep = torch.where(out.acc > 0.5, out.depth / out.acc.clamp_min(1e-6), 0.5 * (tn + tf))
            pts.append(o + d * dep[:, None])
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

    # ================================================================ state
    def state_dict(self) -> dict:
        """Everything needed to resume exactly (tensors and plain python only)."""
        return {
            "version": STATE_VERSION,
            "config": plain_tree(dataclasses.asdict(self.cfg)),
            "camera": self.camera.to_dict(),
            "aabb": None if self.aabb is None else self.aabb.detach().cpu().clone(),
            "aabb_given": None if self._aabb_given is None else self._aabb_given.clone(),
            "field": None if self.field is None else {k: v.detach().cpu().clone() for k, v in self.field.state_dict().items()},
            "optimizer": None if self._opt is None else _cpu_tree(self._opt.state_dict()),
            "pose_corr": None if self._pose_corr is None else self._pose_corr.detach().cpu().clone(),
            "images": {int(i): im.clone() for i, im in self._images.items()},
            "depths": {int(i): dp.clone() for i, dp in self._depths.items()},
            "poses": {int(i): p.clone() for i, p in self._poses.items()},
            "timestamps": {int(i): float(t) for i, t in self._timestamps.items()},
            "guessed": sorted(self._guessed),
            "next_id": self._next_id,
            "init_ids": list(self._init_ids),
            "pending": list(self._pending),
            "local": list(self._local),
            "keyframes": list(self._keyframes),
            "window": list(self._window),
            "initialized": self.initialized,
            "finished": self._finished,
            "iterations": self._iterations,
            "stats": [s.to_dict() for s in self._stats],
            "rng": self._gen.get_state().clone(),
            "exposure": {int(i): p.detach().cpu().clone() for i, p in self._exposure.items()},
            "sparse": None if self._sparse is None else self._sparse.state_dict(),
            "box_refits": self._box_refits,
        }

    def load_state_dict(self, d: dict) -> None:
        """Restore a :meth:`state_dict` (the camera must match; the config of this mapper is kept)."""
        if not isinstance(d, dict) or d.get("version") != STATE_VERSION:
            raise ValueError(f"Mapper.load_state_dict: not a mapper state of version {STATE_VERSION}")
        cam = PinholeCamera.from_dict(d["camera"])
        if cam != self.camera:
            raise ValueError(f"Mapper.load_state_dict: camera differs ({cam} vs {self.camera})")
        self._aabb_given = None if d["aabb_given"] is None else d["aabb_given"].clone()
        self._images = {int(i): im.clone() for i, im in d["images"].items()}
        self._depths = {int(i): dp.clone() for i, dp in d["depths"].items()}
        self._poses = {int(i): p.clone().to(torch.float64) for i, p in d["poses"].items()}
        self._timestamps = {int(i): float(t) for i, t in d["timestamps"].items()}
        self._guessed = set(d["guessed"])
        self._next_id = int(d["next_id"])
        self._init_ids = list(d["init_ids"])
        self._pending = list(d["pending"])
        self._local = list(d["local"])
        self._keyframes = list(d["keyframes"])
        self._window = list(d["window"])
        self.initialized = bool(d["initialized"])
        self._finished = bool(d["finished"])
        self._iterations = int(d["iterations"])
        self._stats = [WindowStats(**s) for s in d["stats"]]
        self._gen.set_state(d["rng"].clone())
        self._box_refits = int(d.get("box_refits", 0))
        if self._sparse is not None and d.get("sparse") is not None:
            self._sparse.load_state_dict(d["sparse"])
        self._exposure = {}
        for i, e in sorted(d.get("exposure", {}).items()):
            self._exposure[int(i)] = torch.nn.Parameter(e.clone().to(self.device), requires_grad=int(i) > 0)
        self.field, self._opt, self._pose_corr, self.aabb = None, None, None, None
        if d["field"] is not None:
            self._aabb_given, given = d["aabb"].clone(), self._aabb_given
            self._build()
            self._aabb_given = given
            self.field.load_state_dict(d["field"])
            if self._pose_corr is not None and d["pose_corr"] is not None:
                with torch.no_grad():
                    self._pose_corr.copy_(d["pose_corr"].to(self.device))
            if self.initialized:
                if self.cfg.freeze_decoder_after_init:
                    self._freeze_decoder()
                elif self._pose_corr is not None:
                    self._pose_corr.requires_grad_(False)
            self._opt.load_state_dict(d["optimizer"])


def _pixel_patches(imgs: Tensor, frame: Tensor, u: Tensor, v: Tensor, radius: int, step: int = 1) -> Tensor:
    """(2r+1)^2 patches (N, P, C) around integer pixels (u, v) of images ``frame`` (border-clamped),
    in the order of :func:`fmapping.losses.patch_offsets`."""
    _, h, w, _ = imgs.shape
    r = torch.arange(-radius, radius + 1, device=imgs.device) * step
    dv, du = torch.meshgrid(r, r, indexing="ij")
    uu = (u[:, None] + du.reshape(-1)).clamp(0, w - 1)
    vv = (v[:, None] + dv.reshape(-1)).clamp(0, h - 1)
    return imgs[frame[:, None], vv, uu]


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


def _orthonormalize(p: Tensor) -> Tensor:
    out = p.clone()
    out[:3, :3] = nearest_rotation(p[:3, :3])
    return out


def plain_tree(x):
    """Dataclass-asdict output -> plain python (tuples to lists) for weights_only loading."""
    if isinstance(x, dict):
        return {k: plain_tree(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain_tree(v) for v in x]
    return x


def _cpu_tree(x):
    if isinstance(x, Tensor):
        return x.detach().cpu().clone()
    if isinstance(x, dict):
        return {k: _cpu_tree(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_cpu_tree(v) for v in x]
    return x
