"""Monocular front end: two-view bootstrap, direct tracking against keyframes, windowed bundle adjustment.

RGB-only tracking before (and independently of) the neural map:

1. **Bootstrap.** Corners of frame 0 are followed with KLT; once the tracks to a
   frame ``k`` show enough parallax, the essential matrix gives the relative pose
   (unit baseline), the inlier tracks are triangulated and the scale is fixed by
   an *anchor*: the metric baseline ``|t_k - t_0|`` from a pose source (ground
   truth: the DIM-SLAM convention of anchoring with known first poses), or else
   the convention that the median scene depth is ``unit_depth``. Frames ``1..k``
   are then aligned photometrically to frame 0 with the triangulated depth. With an
   anchor, its baseline is taken again ``late_anchor_frames`` frames in (the end of
   the mapper's init window) and the whole front end is rescaled about frame 0
   (:meth:`MonoFrontend.rescale`): a bootstrap baseline of a few frames is too short
   to hold the scale.
2. **Tracking.** Every frame is aligned by :class:`~fmapping.tracking.direct_tracker.DirectTracker`
   to the current keyframe (sparse depth at tracked corners); KLT tracks are
   carried along from frame to frame. A frame the alignment loses (motion blur, a
   blurred keyframe) gets its pose from the tracked landmarks (PnP + RANSAC) and is
   aligned again from there; if that fails too, the PnP pose stands and the frame
   becomes a keyframe. Only when PnP fails as well does the frame count as lost.
3. **Keyframes.** When the tracker asks for one, tracks with a landmark add an
   observation, tracks without one are triangulated between their first keyframe
   and the new one; then a windowed bundle adjustment (last ``window`` keyframes,
   the two oldest fixed, which also holds the scale) refines keyframe poses and
   landmarks; the new keyframe's reference holds every tracked landmark (at its
   observed pixel, with the refined depth) plus, optionally, dense depth from the
   map (``extra_depth``). New corners fill the gaps.
4. **Loops.** At each keyframe, old keyframes the camera has come back to (by the estimated
   poses) are checked on their own landmarks and image (:mod:`fmapping.tracking.loop`); a
   verified loop that contradicts the chain is closed by a pose graph over the keyframes since
   (:mod:`fmapping.tracking.posegraph`), landmarks moving with their first keyframe, then a
   bundle adjustment of those keyframes with the loop's matches as observations (the pose
   graph bends the chain; the BA makes it agree with the images again), scaled back to the
   pose graph's size; :meth:`MonoFrontend.refined_poses` then hands on every frame's pose.

With ``MonoConfig.rolling_shutter`` (the readout time as a fraction of the frame interval) the
tracked pixels are unrolled (:mod:`fmapping.tracking.rolling_shutter`) with each frame's rotation
since the previous one before PnP, triangulation and bundle adjustment; the photometric alignment
and KLT keep the image's own pixels.

Non-keyframe poses are stored relative to their keyframe, so :meth:`MonoFrontend.poses`
returns them moved with the bundle-adjusted keyframes. Poses are camera-to-world
4x4 (see :mod:`fmapping.geometry`).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import orthonormalize
from fmapping.tracking.ba import bundle_adjust
from fmapping.geometry import inv_pose, pose_distance, scale_about
from fmapping.tracking.direct_align import select_pixels, to_gray
from fmapping.tracking.features import (
    REFERENCE_WIDTH, KltConfig, at_width, detect_corners, klt_track, pnp_ransac, refine_pnp, to_u8, triangulate,
    two_view_init, two_view_known_baseline,
)
from fmapping.tracking.direct_tracker import DirectTracker, TrackerConfig, TrackResult
from fmapping.tracking.loop import LoopConfig, LoopMatch, cross_check, locate_in_keyframe, loop_candidates
from fmapping.tracking.posegraph import optimize_pose_graph
from fmapping.tracking.rolling_shutter import rotation_step, unroll


@dataclass
class MonoConfig:
    klt: KltConfig = field(default_factory=KltConfig)
    init_min_parallax_deg: float = 1.0  # median parallax of the triangulated tracks to accept the bootstrap ...
    init_min_parallax_px: float = 20.0  # ... and that parallax times the focal length (pixel noise matters);
    init_fallback_parallax_px: float = 10.0  # accepted instead once fewer than 2 x init_min_points tracks survive
    init_min_points: int = 60
    init_max_frames: int = 60  # give up the bootstrap after this many frames
    init_min_flow_px: float = 6.0  # median track length (scaled to a 320-px-wide image) before trying
    ransac_px: float = 1.0
    tri_min_parallax_deg: float = 1.0
    tri_max_reproj_px: float = 2.0
    min_ref_points: int = 40
    unit_depth: float = 2.0  # scale convention without an anchor: median scene depth of the bootstrap
    # keyframes in the bundle adjustment. Synthetic rooms (200 frames), Sim3 ATE seeds 0-4: 7 -> 0.91 / 1.61 /
    # 2.00 / 0.80 / 1.99 cm, 10 -> 0.91 / 1.49 / 1.95 / 0.80 / 1.91 cm (14: the same as 10); TUM fr1_rpy
    # SE3 3.45 -> 3.33 cm, rotation from the first GT pose 1.69 -> 1.60 deg.
    window: int = 10
    # Up to this many older keyframes that saw the window's landmarks join the BA, fixed. Measured with 10:
    # synthetic rooms (200 frames), Sim3 ATE seeds 0-4: 0.91 / 1.61 / 2.00 / 0.80 / 1.99 cm (0) -> 0.90 / 1.78 /
    # 1.91 / 0.55 / 1.88 cm; but TUM fr1_rpy (60 frames): rotation from the first GT pose 1.69 -> 2.42 deg,
    # SE3 3.45 -> 3.50 cm (3 gave the same). Off by default.
    ba_fixed_observers: int = 0
    ba: bool = True
    ba_huber_px: float = 1.5
    ba_max_nfev: int = 15
    ba_outlier_px: float = 4.0  # observations beyond this after BA are dropped
    # Add depth from ``extra_depth`` (the map) to new keyframes when given ... Off: on the synthetic
    # room (seed 0, 200 frames, with the 21 px KLT window of then) the map's depth sat ~2 % off the
    # landmarks and Sim3 ATE went 1.46 cm (off) -> 2.39 cm (on, gated as below); ungated it derailed
    # tracking (24 cm).
    dense_extra: bool = False
    dense_max_gap: float = 0.05  # ... and when, at the landmarks' pixels, its median relative gap to the
    dense_min_rendered: float = 0.5  # landmarks' depth is below this, with depth at this fraction of them
    klt_from_keyframe: bool = True  # re-track from the keyframe image (chained positions as the guess): no KLT drift
    pose_refine: str = "pnp"  # per-frame pose after direct alignment: "pnp" (reprojection of tracked landmarks) | "none"
    reinit_after: int = 3  # consecutive lost frames after which the current frame becomes a keyframe
    #                        with a constant-depth plane at the last median depth (reported as "reinit")
    pnp_min_points: int = 30
    pnp_recovery: bool = True  # a frame the direct alignment loses gets its pose from the landmarks (PnP + RANSAC)
    pnp_inlier_px: float = 2.0
    # With an anchor, its baseline sets the scale again at the first tracked frame with an anchor pose from
    # frame first + late_anchor_frames - 1 on (15: frame 14, the end of the mapper's init window, where the
    # map front end takes its scale): everything is scaled about the first camera centre then. The
    # bootstrap's baseline is a few frames long (TUM fr1_rpy: 1.3 cm at frame 4), too short to fix the
    # scale: by frame 14 the GT has moved 3.0x as far as the estimate. Given up (scale kept) after twice
    # as many frames without one. 0: the bootstrap's scale stays.
    late_anchor_frames: int = 15
    late_anchor_factor_max: float = 10.0  # a refresh changing the scale by more (or less than 1/this) is refused
    loop: LoopConfig = field(default_factory=LoopConfig)  # loop closure at keyframes (fmapping.tracking.loop)
    # Rolling shutter: readout time from the first to the last row as a fraction of the frame interval
    # (0: global shutter). Tracked pixels are unrolled (fmapping.tracking.rolling_shutter) before PnP,
    # triangulation and bundle adjustment, with each frame's rotation since the previous one. TUM fr1_rpy
    # (60 frames): its images prefer 0.85 (bench/tracking.py images_optimum: the optimum's cost 23 % below
    # the global shutter's); the front end with 0.85, median of 6 runs, best-fit rotation 1.70 -> 1.39 deg
    # but SE3 2.98 -> 3.22 cm. On global-shutter frames it costs accuracy (synthetic, 30 frames: Sim3
    # 0.23 cm at 0, 0.62 cm at 1.0). Off by default.
    rolling_shutter: float = 0.0

    def validate(self) -> None:
        if not (np.isfinite(self.rolling_shutter) and 0.0 <= self.rolling_shutter <= 1.0):
            raise ValueError(f"mono.rolling_shutter is the readout time as a fraction of the frame interval, "
                             f"0 (global shutter) to 1, got {self.rolling_shutter}")
        self.loop.validate()


def moved_poses(held: dict, refined: dict, min_m: float = 1e-3, min_deg: float = 0.05) -> dict:
    """The entries of ``refined`` ({frame: c2w}) whose frame is in ``held`` and whose pose moved from
    the held one by more than ``min_m`` metres or ``min_deg`` degrees: the poses worth handing on
    after a bundle adjustment (to a mapper, over the wire)."""
    out = {}
    for k, c2w in refined.items():
        if k in held:
            dt, dr = pose_distance(held[k], c2w)
            if dt > min_m or dr > min_deg:
                out[k] = c2w
    return out


def _parallax_deg(c2w_a: np.ndarray, c2w_b: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the rays from the two camera centres to each world point (N, 3)."""
    ra = world - c2w_a[:3, 3]
    rb = world - c2w_b[:3, 3]
    cos = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


class _Tracks:
    """KLT tracks: current pixel (``uv``, in the image; ``geo``, unrolled for a rolling shutter, the
    one geometry uses), landmark id (-1: none), first keyframe and the (unrolled) pixel there."""

    def __init__(self, uv: np.ndarray, kf: int):
        n = len(uv)
        self.uv = np.asarray(uv, np.float64).reshape(-1, 2).copy()
        self.geo = self.uv
        self.lid = np.full(n, -1, np.int64)
        self.first_kf = np.full(n, kf, np.int64)
        self.uv_first = self.uv.copy()
        self.tid = np.arange(n)

    def keep(self, mask: np.ndarray) -> None:
        self.uv, self.geo, self.lid, self.first_kf, self.uv_first, self.tid = (
            self.uv[mask], self.geo[mask], self.lid[mask], self.first_kf[mask], self.uv_first[mask], self.tid[mask])

    def add(self, uv: np.ndarray, kf: int, geo: Optional[np.ndarray] = None) -> None:
        n = len(uv)
        geo = uv if geo is None else geo
        self.uv = np.concatenate([self.uv, uv])
        self.geo = np.concatenate([self.geo, geo])
        self.lid = np.concatenate([self.lid, np.full(n, -1, np.int64)])
        self.first_kf = np.concatenate([self.first_kf, np.full(n, kf, np.int64)])
        self.uv_first = np.concatenate([self.uv_first, geo])
        start = int(self.tid.max()) + 1 if len(self.tid) else 0
        self.tid = np.concatenate([self.tid, np.arange(start, start + n)])

    def __len__(self) -> int:
        return len(self.uv)


class MonoFrontend:
    """See the module docstring. Call :meth:`bootstrap` per frame until it returns poses, then :meth:`track`."""

    def __init__(self, camera: PinholeCamera, tracker_cfg: Optional[TrackerConfig] = None,
                 cfg: Optional[MonoConfig] = None):
        self.camera = camera
        self.cfg = cfg or MonoConfig()
        self.cfg.validate()
        self.tracker = DirectTracker(camera, tracker_cfg or TrackerConfig())
        self.initialized = False
        self.failed = False
        self.init_info: dict = {}
        self.ba_stats: list = []
        self._buf: list = []  # bootstrap frames: (index, rgb)
        self._tracks: Optional[_Tracks] = None
        self._last_gray: Optional[np.ndarray] = None
        self._kf_pose: dict = {}  # keyframe index -> c2w (refined)
        self._kf_rgb: dict = {}  # window keyframes' images
        self._window: list = []  # keyframe indices in the BA window
        self._lm: list = []  # landmark world points
        self._obs: list = []  # (kf index, landmark id, u, v)
        self._rel: dict = {}  # frame index -> (keyframe index, inv(c2w_kf) @ c2w)
        self._kf_index = -1
        self._lost_run = 0
        self.reinits: list = []
        self.dense_checks: list = []  # per keyframe with extra depth: did it agree with the landmarks?
        self._first_index = 0  # the bootstrap's first frame
        self._anchor: Optional[Callable[[int], Optional[float]]] = None  # baseline source of the late anchor
        self.late_anchor: Optional[dict] = None  # {"frame", "factor"} once the scale was taken again (or refused)
        self.loops: list = []  # loop closures: {"frame", "keyframe", "inliers", "moved_m", "moved_deg", ...}
        self.loops_refused: list = []  # verified loops whose correction was too large to trust
        self._kf_images: dict = {}  # keyframe index -> grey image, for loop verification (bounded)
        self._moved_all = False  # the last keyframe's update moved every keyframe (a loop closure)
        self._step = np.zeros(3)  # the current frame's rotation since the previous one (camera frame)

    # ================================================================== bootstrap
    def bootstrap(self, index: int, rgb: np.ndarray, c2w0: np.ndarray,
                  anchor_baseline: Optional[Callable[[int], Optional[float]]] = None,
                  anchor_position: Optional[Callable[[int], Optional[np.ndarray]]] = None) -> Optional[dict]:
        """Feed frames from the start. Returns {index: c2w} of all frames so far once initialised, else None.

        ``anchor_baseline(index)`` gives the metric distance between the camera
        centres of the first frame and frame ``index`` (from a pose source), or None.
        ``anchor_position(index)`` gives the camera centre (3,) of frame ``index`` in the
        world frame of ``c2w0`` (the "first two poses known" convention), or None; it
        takes precedence: the baseline *vector* is then known and only the rotation is
        fitted to the tracks (:func:`~fmapping.tracking.features.two_view_known_baseline`).
        The essential matrix cannot tell a small translation from a rotation when the
        motion is mostly rotation (centimetres of baseline at metres of depth): its
        translation direction, hence the triangulated depth and the scale, is then
        wrong even with the right baseline length.
        """
        gray = to_u8(rgb)
        c = self.cfg
        if not self._buf:
            self._first_index = index
            self._buf.append((index, rgb))
            self._tracks = _Tracks(detect_corners(gray, c.klt), index)
            self._last_gray = gray
            self._c2w0 = orthonormalize(np.asarray(c2w0, np.float64))
            self._hist = {index: (self._tracks.tid.copy(), self._tracks.uv.copy())}
            return None
        self._buf.append((index, rgb))
        self._klt(gray)
        self._hist[index] = (self._tracks.tid.copy(), self._tracks.uv.copy())
        if len(self._buf) > c.init_max_frames or len(self._tracks) < c.init_min_points:
            self.failed = True
            return None
        tr = self._tracks
        flow = np.median(np.linalg.norm(tr.uv - tr.uv_first, axis=1))
        if flow < at_width(c.init_min_flow_px, self.camera.width):
            return None
        need_px = c.init_min_parallax_px if len(tr) >= 2 * c.init_min_points else c.init_fallback_parallax_px
        pos = anchor_position(index) if anchor_position is not None else None
        if pos is not None:
            c_a = self._c2w0[:3, :3].T @ (np.asarray(pos, np.float64).reshape(3) - self._c2w0[:3, 3])
            if np.linalg.norm(c_a) < 1e-4:
                return None
            kb = two_view_known_baseline(self.camera, tr.uv_first, tr.uv, c_a, c.ransac_px)
            if kb is None:
                return None
            c2w_k = orthonormalize(self._c2w0 @ kb[0])
            world, valid = triangulate(self.camera, self._c2w0, c2w_k, tr.uv_first, tr.uv,
                                       c.tri_min_parallax_deg, c.tri_max_reproj_px)
            valid &= kb[1]
            median_par = float(np.median(_parallax_deg(self._c2w0, c2w_k, world[valid]))) if valid.any() else 0.0
            if valid.sum() < c.init_min_points or median_par < c.init_min_parallax_deg \
                    or np.radians(median_par) * self.camera.fx < need_px:
                return None
            s, how = float(np.linalg.norm(c_a)), "anchor_position"
        else:
            tv = two_view_init(self.camera, tr.uv_first, tr.uv, c.ransac_px, c.tri_min_parallax_deg)
            if tv is None or tv.valid.sum() < c.init_min_points or tv.median_parallax_deg < c.init_min_parallax_deg:
                return None
            if np.radians(tv.median_parallax_deg) * self.camera.fx < need_px:
                return None
            base = anchor_baseline(index) if anchor_baseline is not None else None
            if base is not None and base > 1e-4:
                s, how = float(base), "anchor"  # recoverPose's translation has unit norm
            else:
                s, how = float(c.unit_depth / np.median(tv.points[tv.valid, 2])), "unit_depth"
            c2w_k = tv.c2w_b.copy()
            c2w_k[:3, 3] *= s
            c2w_k = orthonormalize(self._c2w0 @ c2w_k)
            world = (tv.points * s) @ self._c2w0[:3, :3].T + self._c2w0[:3, 3]
            valid, median_par = tv.valid, tv.median_parallax_deg
        i0 = self._buf[0][0]
        # landmarks and their two observations
        sel = np.flatnonzero(valid)
        self._kf_pose = {i0: self._c2w0.copy(), index: c2w_k}
        for j in sel:
            lid = len(self._lm)
            self._lm.append(world[j])
            tr.lid[j] = lid
            self._obs.append((i0, lid, tr.uv_first[j, 0], tr.uv_first[j, 1]))
            self._obs.append((index, lid, tr.uv[j, 0], tr.uv[j, 1]))
        self._window = [i0, index]
        self._kf_rgb = {i0: self._buf[0][1], index: rgb}
        if c.loop.enabled:
            self._kf_images = {i0: to_u8(self._buf[0][1]), index: gray}
        # photometric tracking of frames 1..k against frame 0 with the landmarks' depth
        lids = tr.lid[tr.lid >= 0]
        pts_cam0 = self._cam_points(i0, lids, tr.uv_first[tr.lid >= 0])
        self.tracker.set_reference_points(self._buf[0][1], pts_cam0, self._c2w0, i0)
        self.tracker.observe(self._c2w0)
        poses = {i0: self._c2w0.copy()}
        for fi, frgb in self._buf[1:-1]:
            poses[fi] = self.tracker.track(frgb).c2w
        r = self.tracker.track(rgb, c2w_guess=self._kf_pose[index])
        two_view_vs_photo = pose_distance(self._kf_pose[index], r.c2w)[1]
        poses[index] = self._kf_pose[index]
        if c.rolling_shutter:
            self._unroll_bootstrap(poses, i0, index)
        # multi-view bundle adjustment of the bootstrap (frame 0 fixed), then the anchor scale again
        rms = self._bootstrap_ba(poses, index, s if how == "anchor" else None, fix_last=how == "anchor_position")
        for fi in poses:
            self._rel[fi] = (i0, inv_pose(self._c2w0) @ poses[fi])
        self._rel[index] = (index, np.eye(4))
        poses[index] = self._kf_pose[index]
        self.tracker.reset_motion([poses[self._buf[-2][0]], poses[index]])
        self.init_info = {"frame": int(index), "frames": len(self._buf), "points": int(len(sel)),
                          "median_parallax_deg": median_par, "scale": s, "scale_from": how,
                          "two_view_vs_photometric_deg": two_view_vs_photo, "ba_rms_px": rms}
        self._set_reference(index, rgb, gray)
        self.initialized = True
        self._buf = []
        if how != "unit_depth" and anchor_baseline is not None and c.late_anchor_frames > 0:
            self._anchor = anchor_baseline
        return poses

    def _unroll_bootstrap(self, poses: dict, i0: int, index: int) -> None:
        """Once the bootstrap frames have poses: their tracked pixels (history, first pixels,
        observations) unrolled for the rolling shutter with each frame's rotation step."""
        ids = sorted(poses)  # each frame's step from the previous frame; the first frame takes the second's
        steps = {f: rotation_step(poses[ids[max(j - 1, 0)]], poses[ids[max(j, 1)]]) for j, f in enumerate(ids)}
        cam, r = self.camera, self.cfg.rolling_shutter
        self._hist = {f: (tids, unroll(cam, uvs, steps[f], r)) for f, (tids, uvs) in self._hist.items()}
        tr = self._tracks
        tr.uv_first = unroll(cam, tr.uv_first, steps[i0], r)
        self._step = steps[index]
        tr.geo = self._geo(tr.uv)
        obs = np.array(self._obs, np.float64)
        for f in (i0, index):
            m = obs[:, 0] == f
            obs[m, 2:4] = unroll(cam, obs[m, 2:4], steps[f], r)
        self._obs = [(int(f), int(l), float(u), float(v)) for f, l, u, v in obs]

    def _geo(self, uv: np.ndarray) -> np.ndarray:
        """Pixels of the current frame unrolled for the rolling shutter (``MonoConfig.rolling_shutter``)."""
        return unroll(self.camera, uv, self._step, self.cfg.rolling_shutter)

    def _bootstrap_ba(self, poses: dict, k_index: int, baseline: Optional[float], fix_last: bool = False) -> Optional[float]:
        """BA over up to 6 bootstrap frames (frame 0 fixed, and frame ``k_index`` with ``fix_last``;
        the scale re-anchored to ``baseline`` when given); updates poses and landmarks."""
        c = self.cfg
        tr = self._tracks
        ids = [f for f, _ in self._buf]
        sel = sorted(set([ids[0], ids[-1]] + [ids[int(j)] for j in np.linspace(0, len(ids) - 1, min(6, len(ids)))]))
        tid_to_lid = {int(t): int(l) for t, l in zip(tr.tid, tr.lid) if l >= 0}
        obs_kf, obs_pt, obs_uv = [], [], []
        lids = sorted(set(tid_to_lid.values()))
        lpos = {l: i for i, l in enumerate(lids)}
        for kpos, f in enumerate(sel):
            tids, uvs = self._hist[f]
            for t, uv in zip(tids, uvs):
                l = tid_to_lid.get(int(t))
                if l is not None:
                    obs_kf.append(kpos)
                    obs_pt.append(lpos[l])
                    obs_uv.append(uv)
        if len(lids) < 10:
            return None
        fixed = [0, len(sel) - 1] if fix_last else [0]  # sel ends with k_index (the newest frame)
        res = bundle_adjust(self.camera, [poses[f] for f in sel], fixed, np.stack([self._lm[l] for l in lids]),
                            np.array(obs_kf), np.array(obs_pt), np.array(obs_uv), c.ba_huber_px, 30)
        new = dict(zip(sel, res.poses))
        pts = res.points
        c0 = self._c2w0[:3, 3]
        if baseline is not None:
            b = np.linalg.norm(new[k_index][:3, 3] - c0)
            f = baseline / b if b > 1e-9 else 1.0
            for key in new:
                new[key][:3, 3] = c0 + f * (new[key][:3, 3] - c0)
            pts = c0 + f * (pts - c0)
        # frames not in the BA keep their pose relative to the nearest earlier BA frame
        moved = {}
        for fi in poses:
            if fi in new:
                moved[fi] = new[fi]
            else:
                prev = max(x for x in sel if x <= fi)
                moved[fi] = orthonormalize(new[prev] @ inv_pose(poses[prev]) @ poses[fi])
        poses.update(moved)
        for l, p in zip(lids, pts):
            self._lm[l] = p
        self._kf_pose[k_index] = poses[k_index]
        bad = res.residual_px > c.ba_outlier_px
        return float(np.sqrt(np.mean(res.residual_px[~bad] ** 2))) if (~bad).any() else None

    # ================================================================== tracking
    def track(self, index: int, rgb: np.ndarray,
              extra_depth: Optional[Callable[[np.ndarray], Callable]] = None) -> TrackResult:
        """Track a frame after the bootstrap. ``extra_depth(c2w)`` -> ``uv -> depth`` callable
        (e.g. rendered from the map) adds dense points to new keyframes."""
        if not self.initialized:
            raise RuntimeError("MonoFrontend.track before a successful bootstrap")
        if self._anchor is not None and index - self._first_index >= 2 * self.cfg.late_anchor_frames:
            self.settle_scale(f"no tracked frame with an anchor pose in the first {2 * self.cfg.late_anchor_frames}")
        gray = to_u8(rgb)
        res = self.tracker.track(rgb)
        if self.cfg.rolling_shutter and not res.lost:
            hist = self.tracker.motion_history  # [previous frame, this frame]
            if len(hist) == 2:
                self._step = rotation_step(hist[0], hist[1])
        self._klt(gray)
        if res.lost and self.cfg.pnp_recovery:
            res = self._recover(rgb, res)
        if res.lost:
            self._lost_run += 1
            if self._lost_run >= self.cfg.reinit_after:
                self._reinit(index, rgb, gray, res.c2w)
                res.reason += f"; re-initialised at frame {index} (constant-depth keyframe)"
                self.reinits.append(index)
                self._lost_run = 0
            return res
        self._lost_run = 0
        if self.cfg.pose_refine == "pnp":
            t0 = time.perf_counter()
            refined = self._pnp(res.c2w)
            if refined is not None:
                res.c2w = refined
                self.tracker.correct_last(refined)
            res.ms += (time.perf_counter() - t0) * 1000.0
        self._rel[index] = (self._kf_index, inv_pose(self._kf_pose[self._kf_index]) @ res.c2w)
        if res.need_keyframe:
            t0 = time.perf_counter()
            c2w = self._add_keyframe(index, rgb, gray, res.c2w)
            try:
                self._set_reference(index, rgb, gray, extra_depth)
            except ValueError:
                pass  # keep the old reference; the tracker asks again next frame
            res.c2w = c2w
            res.ms += (time.perf_counter() - t0) * 1000.0  # keyframe work counts as tracking time
        if self._anchor is not None and index - self._first_index >= self.cfg.late_anchor_frames - 1:
            res.c2w = self._late_anchor(index, res.c2w)
        return res

    def _late_anchor(self, index: int, c2w: np.ndarray) -> np.ndarray:
        """Take the anchor's baseline again at frame ``index`` (see ``MonoConfig.late_anchor_frames``):
        rescale everything about the first camera centre. Returns frame ``index``'s pose afterwards."""
        c = self.cfg
        base = self._anchor(index)
        est = float(np.linalg.norm(c2w[:3, 3] - self._c2w0[:3, 3]))
        if base is None:
            return c2w  # no anchor pose for this frame: try the next one (see track)
        if base <= 1e-4 or est <= 1e-9 or not 1 / c.late_anchor_factor_max <= base / est <= c.late_anchor_factor_max:
            self.late_anchor = {"frame": int(index), "factor": 1.0,
                                "refused": f"anchor baseline {base:.4g} against {est:.4g} estimated"}
        else:
            self.rescale(base / est)
            self.late_anchor = {"frame": int(index), "factor": base / est}
            c2w = scale_about(c2w, self._c2w0[:3, 3], base / est)
        self._anchor = None
        return c2w

    @property
    def scale_pending(self) -> bool:
        """True while the front end waits for its late anchor."""
        return self._anchor is not None

    def settle_scale(self, why: str = "the sequence ended before it") -> None:
        """Stop waiting for the late anchor: the scale stays (``late_anchor`` says why)."""
        if self._anchor is not None:
            self.late_anchor = {"frame": None, "factor": 1.0, "refused": why}
            self._anchor = None

    def rescale(self, s: float) -> None:
        """Scale the front end's world by ``s`` about the first camera centre: keyframe poses,
        landmarks, the poses of the frames relative to their keyframe, the tracker's references."""
        self._scale_part(self._c2w0[:3, 3], s)

    def _scale_part(self, c0: np.ndarray, s: float, kfs: Optional[set] = None) -> None:
        """Scale by ``s`` about ``c0`` what belongs to keyframes ``kfs`` (default: everything): their
        poses, the landmarks first seen by them, the frames stored relative to them (translations)
        and the tracker's references of them (with everything, its motion model too)."""
        first = None if kfs is None else self._first_keyframes()
        for k in list(self._kf_pose):
            if kfs is None or k in kfs:
                self._kf_pose[k] = scale_about(self._kf_pose[k], c0, s)
        for lid, p in enumerate(self._lm):
            if kfs is None or first.get(lid) in kfs:
                self._lm[lid] = c0 + s * (np.asarray(p) - c0)
        for i, (k, rel) in self._rel.items():
            if kfs is None or k in kfs:
                rel = rel.copy()
                rel[:3, 3] *= s
                self._rel[i] = (k, rel)
        self.tracker.rescale(c0, s, frames=kfs)

    # ================================================================== internals
    def _klt(self, gray: np.ndarray) -> None:
        tr = self._tracks
        if tr is not None and len(tr):
            new, ok = klt_track(self._last_gray, gray, tr.uv, self.cfg.klt)
            kf_gray = getattr(self, "_kf_gray", None)
            if self.cfg.klt_from_keyframe and kf_gray is not None and getattr(tr, "uv_kf", None) is not None:
                # refine from the keyframe image: positions no longer accumulate frame-to-frame drift
                ref, ok2 = klt_track(kf_gray, gray, tr.uv_kf, self.cfg.klt, guess=new)
                good = ok2 & (np.linalg.norm(ref - new, axis=1) < 2.0)
                new = np.where(good[:, None], ref, new)
            tr.uv = new.astype(np.float64)
            tr.geo = self._geo(tr.uv)
            if getattr(tr, "uv_kf", None) is not None:
                tr.uv_kf = tr.uv_kf[ok]
            tr.keep(ok)
        self._last_gray = gray

    def _reinit(self, index: int, rgb, gray, c2w: np.ndarray) -> None:
        from fmapping.tracking.direct_align import make_reference

        med = self.tracker.reference.median_depth if self.tracker.reference is not None else self.cfg.unit_depth
        cam = self.camera
        depth = np.full((cam.height, cam.width), med if np.isfinite(med) else self.cfg.unit_depth, np.float32)
        self._kf_pose[index] = np.asarray(c2w, np.float64).copy()
        self._kf_rgb[index] = rgb
        self._window = [index]
        tcfg = self.tracker.cfg
        ref = make_reference(rgb, depth, cam, self._kf_pose[index], tcfg.align.levels, tcfg.num_points, tcfg.min_grad,
                             index, blur=tcfg.align.blur)
        self.tracker.push_reference(ref)
        self.tracker.reset_motion([self._kf_pose[index]])
        self._kf_index = index
        self._rel[index] = (index, np.eye(4))
        tr = _Tracks(detect_corners(gray, self.cfg.klt).astype(np.float64), index)
        tr.uv_kf = tr.uv.astype(np.float32).copy()
        self._tracks = tr
        self._kf_gray = gray

    def _tracked_landmarks(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """World points and current pixels of the tracks with a landmark (None below ``pnp_min_points``)."""
        tr = self._tracks
        has = tr.lid >= 0
        if has.sum() < self.cfg.pnp_min_points:
            return None
        return np.stack([self._lm[i] for i in tr.lid[has]]), tr.geo[has]

    def _recover(self, rgb: np.ndarray, lost: TrackResult) -> TrackResult:
        """A frame the direct alignment lost: the pose from the tracked landmarks (PnP + RANSAC),
        then the direct alignment again from there. When that still fails, the PnP pose is kept
        and the frame becomes a keyframe (a fresh reference where the old one no longer fits)."""
        pose = self._pnp_ransac()
        if pose is None:
            return lost
        again = self.tracker.track(rgb, c2w_guess=pose)
        why = f"lost ({lost.reason}); re-localised on the landmarks (PnP)"
        if not again.lost:
            return dataclasses.replace(again, relocalised=True, reason=why, ms=again.ms + lost.ms)
        self.tracker.observe(pose)
        return dataclasses.replace(lost, c2w=pose, lost=False, relocalised=True, need_keyframe=True,
                                   reason=why + ", direct alignment still failing: new keyframe",
                                   ms=lost.ms + again.ms)

    def _pnp_ransac(self) -> Optional[np.ndarray]:
        """Camera-to-world pose from the KLT-tracked landmarks alone (no prior), or None when fewer
        than ``pnp_min_points`` inliers (within ``pnp_inlier_px`` per 320 pixels of image width) or
        under half of the tracked landmarks agree."""
        found = self._tracked_landmarks()
        if found is None:
            return None
        x, uv = found
        px = at_width(self.cfg.pnp_inlier_px, max(self.camera.width, REFERENCE_WIDTH))  # KLT noise grows with the size
        found = pnp_ransac(self.camera, x, uv, px)
        if found is None or found[1].sum() < max(self.cfg.pnp_min_points, 0.5 * len(x)):
            return None
        return orthonormalize(inv_pose(found[0]))

    def _pnp(self, c2w: np.ndarray) -> Optional[np.ndarray]:
        """Refine a pose on the reprojection error of the tracked landmarks (inliers of the given pose)."""
        found = self._tracked_landmarks()
        if found is None:
            return None
        x, uv = found
        w2c = inv_pose(c2w)
        y = x @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.where(y[:, 2] > 1e-6, y[:, 2], 1e-6)
        cam = self.camera
        proj = np.stack([cam.fx * y[:, 0] / z + cam.cx, cam.fy * y[:, 1] / z + cam.cy], -1)
        inl = (y[:, 2] > 1e-3) & (np.linalg.norm(proj - uv, axis=1) < self.cfg.pnp_inlier_px)
        if inl.sum() < self.cfg.pnp_min_points:
            return None
        refined = refine_pnp(cam, x[inl], uv[inl], w2c)
        if refined is None:
            return None
        out = orthonormalize(inv_pose(refined))
        dt, dr = pose_distance(out, c2w)
        scale = self.tracker.reference.median_depth if self.tracker.reference is not None else 1.0
        if dt > 0.1 * scale or dr > 5.0:
            return None  # disagrees wildly with the photometric pose: keep that one
        return out

    def _cam_points(self, kf: int, lids: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Camera-frame points at observed pixels ``uv`` with the depth of landmarks ``lids`` in keyframe ``kf``."""
        if len(lids) == 0:
            return np.zeros((0, 3))
        w2c = inv_pose(self._kf_pose[kf])
        x = np.stack([self._lm[i] for i in lids]) @ w2c[:3, :3].T + w2c[:3, 3]
        z = x[:, 2]
        ok = z > 1e-3
        uv, z = uv[ok], z[ok]
        cam = self.camera
        return np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], -1)

    def _add_keyframe(self, index: int, rgb: np.ndarray, gray: np.ndarray, c2w: np.ndarray) -> np.ndarray:
        c = self.cfg
        tr = self._tracks
        self._kf_pose[index] = np.asarray(c2w, np.float64).copy()
        self._kf_rgb[index] = rgb
        self._moved_all = False
        # observations of known landmarks
        has = tr.lid >= 0
        for j in np.flatnonzero(has):
            self._obs.append((index, int(tr.lid[j]), tr.geo[j, 0], tr.geo[j, 1]))
        # triangulate the others between their first keyframe and this one
        for kf in np.unique(tr.first_kf[~has]):
            if kf not in self._kf_pose or kf == index:
                continue
            m = np.flatnonzero((~has) & (tr.first_kf == kf))
            pts, ok = triangulate(self.camera, self._kf_pose[kf], c2w, tr.uv_first[m], tr.geo[m],
                                  c.tri_min_parallax_deg, c.tri_max_reproj_px)
            for j, p in zip(m[ok], pts[ok]):
                lid = len(self._lm)
                self._lm.append(p)
                tr.lid[j] = lid
                self._obs.append((int(kf), lid, tr.uv_first[j, 0], tr.uv_first[j, 1]))
                self._obs.append((index, lid, tr.geo[j, 0], tr.geo[j, 1]))
        self._window.append(index)
        if len(self._window) > c.window:
            old = self._window.pop(0)
            self._kf_rgb.pop(old, None)
        before = self._kf_pose[index].copy()
        if c.ba:
            self._run_ba()
        if c.loop.enabled:
            self._close_loop(index, gray)
            self._kf_images[index] = gray
            while len(self._kf_images) > c.loop.max_keyframe_images:
                self._kf_images.pop(next(iter(self._kf_images)))
        after = self._kf_pose[index]
        # move the motion model with the refined keyframe
        delta = after @ inv_pose(before)
        self.tracker.reset_motion([delta @ p for p in self.tracker.motion_history])
        return after

    def _close_loop(self, index: int, gray: np.ndarray) -> None:
        """Look for an old keyframe the camera has come back to (:mod:`fmapping.tracking.loop`); when
        one verifies and disagrees with the chain, correct the keyframes since then (:meth:`_correct_loop`)."""
        lc = self.cfg.loop
        ref = self.tracker.reference
        scale = ref.median_depth if ref is not None and np.isfinite(ref.median_depth) else self.cfg.unit_depth
        for k in loop_candidates(self._kf_pose, index, scale, lc):
            if k not in self._kf_images:
                continue
            seen = [(o[1], o[2], o[3]) for o in self._obs if o[0] == k]
            if len(seen) < lc.min_points:
                continue
            lids = np.array([o[0] for o in seen], np.int64)
            uv = np.array([o[1:] for o in seen], np.float64)
            m = locate_in_keyframe(self.camera, self._kf_images[k], uv, np.stack([self._lm[i] for i in lids]),
                                   self._kf_pose[k], gray, self._kf_pose[index], self.cfg.klt, lc)
            if m is None:
                continue
            dt, dr = pose_distance(self._kf_pose[index], m.c2w)
            rec = {"frame": int(index), "keyframe": int(k), "points": m.points, "inliers": m.inliers,
                   "moved_m": dt, "moved_deg": dr}
            if dt > lc.max_correction * scale:
                rec["why"] = f"correction {dt:.3g} > {lc.max_correction} x median depth {scale:.3g}"
                self.loops_refused.append(rec)
                continue
            if dt < lc.min_correction_m * scale and dr < lc.min_correction_deg:
                return  # the chain already agrees with the old keyframe
            if np.isfinite(lc.max_cross_deg):
                cross = self._cross_check(k, index, m, gray)
                if cross is not None:
                    rec["cross_deg"], rec["cross_dist"] = cross[0], cross[1] / scale
                if cross is None or cross[0] > lc.max_cross_deg or cross[1] > lc.max_cross_dist * scale:
                    rec["why"] = (f"measured the other way round: {cross and round(cross[0], 3)} deg, "
                                  f"{cross and round(cross[1] / scale, 4)} x median depth apart")
                    self.loops_refused.append(rec)
                    continue
            rec.update(self._correct_loop(k, index, m, lids, scale))
            self.loops.append(rec)
            return

    def _cross_check(self, old: int, index: int, m: LoopMatch, gray: np.ndarray) -> Optional[tuple]:
        """The loop ``m`` (keyframe ``index`` in the map of keyframe ``old``) measured the other way
        round, from keyframe ``index``'s own landmarks (:func:`~fmapping.tracking.loop.cross_check`)."""
        seen = [(o[1], o[2], o[3]) for o in self._obs if o[0] == index]
        if len(seen) < self.cfg.loop.min_points:
            return None
        lids = np.array([o[0] for o in seen], np.int64)
        uv = np.array([o[1:] for o in seen], np.float64)
        return cross_check(self.camera, self._kf_images[old], self._kf_pose[old], m, gray, uv,
                           np.stack([self._lm[i] for i in lids]), self._kf_pose[index], self.cfg.klt, self.cfg.loop)

    def _correct_loop(self, old: int, index: int, m: LoopMatch, old_lids: np.ndarray, scale: float) -> dict:
        """Pose graph over the keyframes from ``old`` (fixed) to ``index``: the chain's relative poses
        plus the loop edge ``old`` -> ``index`` (``m``, a :class:`~fmapping.tracking.loop.LoopMatch` on
        the landmarks ``old_lids`` of keyframe ``old``). Landmarks move with their first keyframe;
        then (``loop.loop_ba``, loops up to ``loop_ba_max_keyframes``) the loop's inliers become
        observations of keyframe ``index``, the loop's keyframes are bundle-adjusted (the first two
        fixed) and scaled back to the pose graph's size (``loop_ba_keep_scale``). The tracker's
        references move with their keyframes; non-keyframes are stored relative to their keyframe."""
        lc = self.cfg.loop
        kfs = sorted(k for k in self._kf_pose if k >= old)
        before = [self._kf_pose[k].copy() for k in kfs]
        edges = [(a, a + 1, inv_pose(before[a]) @ before[a + 1]) for a in range(len(kfs) - 1)]
        edges.append((0, len(kfs) - 1, inv_pose(before[0]) @ m.c2w))
        after, stats = optimize_pose_graph(before, edges, [0], unit=scale)
        corr = {}
        for k, b, a in zip(kfs, before, after):
            self._kf_pose[k] = orthonormalize(a)
            corr[k] = self._kf_pose[k] @ inv_pose(b)
        for lid, k in self._first_keyframes().items():
            if k in corr:
                self._lm[lid] = corr[k][:3, :3] @ self._lm[lid] + corr[k][:3, 3]
        out = {"keyframes": len(kfs), "cost_before": stats["cost_before"], "cost_after": stats["cost_after"]}
        out["ba"] = lc.loop_ba and len(kfs) <= lc.loop_ba_max_keyframes
        if out["ba"]:
            have = {int(o[1]) for o in self._obs if o[0] == index}
            for lid, (u, v) in zip(old_lids[m.index], m.uv):
                if int(lid) not in have:
                    self._obs.append((index, int(lid), float(u), float(v)))
            graph_size = self._spread_about(kfs, old)
            self._run_ba(window=kfs, max_nfev=lc.loop_ba_max_nfev)
            out["ba_scale"] = graph_size / max(self._spread_about(kfs, old), 1e-12)
            out["ba_rms_px"] = self.ba_stats[-1]["rms_after_px"] if self.ba_stats else None
        self.tracker.move_references({k: self._kf_pose[k] @ inv_pose(b) for k, b in zip(kfs, before)})
        if out["ba"] and lc.loop_ba_keep_scale:
            self._scale_keyframes(kfs, old, out["ba_scale"])
        self._moved_all = True
        return out

    def _spread_about(self, kfs: list, about: int) -> float:
        """Mean distance of the centres of keyframes ``kfs`` from keyframe ``about``'s."""
        c0 = self._kf_pose[about][:3, 3]
        return float(np.mean([np.linalg.norm(self._kf_pose[k][:3, 3] - c0) for k in kfs]))

    def _first_keyframes(self) -> dict:
        """{landmark id: the keyframe of its first remaining observation}: whose pose it moves with."""
        first: dict = {}
        for o in self._obs:
            first.setdefault(int(o[1]), int(o[0]))
        return first

    def _scale_keyframes(self, kfs: list, about: int, s: float) -> None:
        """Scale what belongs to keyframes ``kfs`` by ``s`` about keyframe ``about``'s centre (:meth:`_scale_part`)."""
        self._scale_part(self._kf_pose[about][:3, 3].copy(), s, set(kfs))

    def _run_ba(self, fixed_all_but_points: bool = False, window: Optional[list] = None,
                max_nfev: Optional[int] = None) -> None:
        """Bundle adjustment of the keyframes ``window`` (default: the BA window; the first two fixed)
        and the landmarks they observe, at most ``max_nfev`` iterations (default ``ba_max_nfev``)."""
        c = self.cfg
        win = list(self._window if window is None else window)
        if not self._obs:
            return
        obs = np.array(self._obs, dtype=np.float64)
        kf_of = obs[:, 0].astype(np.int64)
        inwin = np.isin(kf_of, win)
        extra: list = []
        keep = inwin
        if c.ba_fixed_observers > 0 and inwin.any():
            # older keyframes that saw the window's landmarks join, fixed: their observations tie the
            # window to the past (without them scale and rotation drift from window to window)
            seen = np.isin(obs[:, 1].astype(np.int64), np.unique(obs[inwin, 1].astype(np.int64)))
            older = np.unique(kf_of[seen & ~inwin])
            extra = [int(k) for k in older[::-1][: c.ba_fixed_observers] if int(k) in self._kf_pose]
            keep = inwin | (seen & np.isin(kf_of, extra))
        obs = obs[keep]
        if len(obs) == 0:
            return
        lids, inv = np.unique(obs[:, 1].astype(np.int64), return_inverse=True)
        counts = np.bincount(inv)
        keep = counts[inv] >= 2
        obs, inv = obs[keep], inv[keep]
        lids, inv = np.unique(obs[:, 1].astype(np.int64), return_inverse=True)
        if len(lids) < 10:
            return
        kf_pos = {k: i for i, k in enumerate(win + extra)}
        poses = [self._kf_pose[k] for k in win + extra]
        fixed = list(range(len(win))) if fixed_all_but_points else list(range(min(2, len(win))))
        fixed += list(range(len(win), len(win) + len(extra)))
        t0 = time.perf_counter()
        res = bundle_adjust(self.camera, poses, fixed, np.stack([self._lm[i] for i in lids]),
                            np.array([kf_pos[int(k)] for k in obs[:, 0]]), inv, obs[:, 2:4],
                            c.ba_huber_px, c.ba_max_nfev if max_nfev is None else max_nfev)
        for k, p in zip(win, res.poses[: len(win)]):
            self._kf_pose[k] = p
        for i, p in zip(lids, res.points):
            self._lm[int(i)] = p
        # drop outlying observations (in the window)
        bad = res.residual_px > c.ba_outlier_px
        if bad.any():
            badset = {(int(a), int(b)) for a, b in obs[bad][:, :2]}
            self._obs = [o for o in self._obs if (int(o[0]), int(o[1])) not in badset]
            bad_l = {b for _, b in badset}
            tr = self._tracks
            for j in np.flatnonzero(np.isin(tr.lid, list(bad_l))):
                tr.lid[j] = -1  # re-triangulate later from this keyframe on
                tr.first_kf[j] = win[-1]
                tr.uv_first[j] = tr.geo[j]
        self.ba_stats.append({"keyframes": len(win), "fixed_observers": len(extra), "points": int(len(lids)),
                              "obs": int(len(obs)),
                              "rms_before_px": float(np.sqrt(2 * res.cost_before / max(1, len(obs)))),
                              "rms_after_px": float(np.sqrt(2 * res.cost_after / max(1, len(obs)))),
                              "outliers": int(bad.sum()), "ms": (time.perf_counter() - t0) * 1000, "nfev": res.nfev})

    def _set_reference(self, index: int, rgb, gray, extra_depth=None) -> None:
        c = self.cfg
        tr = self._tracks
        has = tr.lid >= 0
        pts = self._cam_points(index, tr.lid[has], tr.uv[has])
        if extra_depth is not None and c.dense_extra:
            fn = extra_depth(self._kf_pose[index])
            if self._dense_agrees(index, fn, pts):
                dense = self._dense_points(rgb, fn)
                if len(dense):
                    pts = np.concatenate([pts, dense])
        if len(pts) < c.min_ref_points:
            raise ValueError(f"keyframe {index}: only {len(pts)} points with depth")
        self.tracker.set_reference_points(rgb, pts, self._kf_pose[index], index)
        self._kf_index = index
        # restart tracks here: live ones continue, fresh corners start at this keyframe
        newc = detect_corners(gray, c.klt, existing=tr.uv)
        if len(newc):
            tr.add(newc.astype(np.float64), index, self._geo(newc.astype(np.float64)))
        tr.uv_kf = tr.uv.astype(np.float32).copy()
        self._kf_gray = gray

    def _dense_agrees(self, index: int, depth_fn, pts: np.ndarray, max_check: int = 300) -> bool:
        """Does ``depth_fn`` (e.g. the map) agree with the landmarks ``pts`` (camera frame of keyframe
        ``index``)? Checked at every keyframe: a map is wrong where it has not been trained yet (new
        parts of the view, drift since), and one bad dense reference derails the tracker."""
        c = self.cfg
        check = {"frame": int(index), "landmarks": int(len(pts)), "used": False}
        self.dense_checks.append(check)
        if len(pts) < 20:
            return False
        p = pts[:: max(1, len(pts) // max_check)]
        uv = np.stack([self.camera.fx * p[:, 0] / p[:, 2] + self.camera.cx,
                       self.camera.fy * p[:, 1] / p[:, 2] + self.camera.cy], -1)
        d = np.asarray(depth_fn(uv), np.float64)
        ok = np.isfinite(d)
        check["rendered"] = float(ok.mean())
        if ok.mean() < c.dense_min_rendered:
            return False
        check["gap"] = float(np.median(np.abs(d[ok] - p[ok, 2]) / p[ok, 2]))
        check["used"] = check["gap"] < c.dense_max_gap
        return check["used"]

    def _dense_points(self, rgb, depth_fn) -> np.ndarray:
        cfg = self.tracker.cfg
        uv = select_pixels(to_gray(rgb), cfg.num_points, cfg.min_grad).astype(np.float64)
        z = np.asarray(depth_fn(uv), np.float64)
        ok = np.isfinite(z) & (z > 1e-3)
        uv, z = uv[ok], z[ok]
        return np.stack([(uv[:, 0] - self.camera.cx) / self.camera.fx * z,
                         (uv[:, 1] - self.camera.cy) / self.camera.fy * z, z], -1)

    # ================================================================== results
    @property
    def keyframe_index(self) -> int:
        return self._kf_index

    def keyframe_poses(self) -> dict:
        return {k: p.copy() for k, p in self._kf_pose.items()}

    def poses(self, window_only: bool = False) -> dict:
        """Every tracked frame's pose, moved with its bundle-adjusted keyframe. With ``window_only``
        just the frames of the keyframes in the current BA window: the only ones the last BA moved."""
        keep = set(self._window) if window_only else self._kf_pose
        return {i: orthonormalize(self._kf_pose[k] @ rel) for i, (k, rel) in self._rel.items()
                if k in keep and k in self._kf_pose}

    def refined_poses(self) -> dict:
        """The poses the last keyframe's update may have moved: those of the BA window's frames, or
        every frame's after a loop closure. What to hand on to a mapper after a keyframe."""
        return self.poses(window_only=not self._moved_all)

    def poses_for(self, held: dict) -> dict:
        """The front end's current poses of the frames in ``held`` ({frame: c2w} handed out
        earlier, e.g. kept back while the scale was pending); a frame it has no pose for (a
        lost one) keeps its held pose, moved with the late anchor's rescale."""
        now = self.poses()
        factor = (self.late_anchor or {}).get("factor", 1.0)
        return {i: now[i] if i in now else scale_about(c2w, self._c2w0[:3, 3], factor) for i, c2w in held.items()}

    def landmarks(self) -> np.ndarray:
        return np.stack(self._lm) if self._lm else np.zeros((0, 3))

    # ================================================================== restart
    def keyframe_states(self, n: int = 5) -> list:
        """What a restarted front end needs to go on in this world frame and scale (:meth:`resume`): for
        the newest ``n`` keyframes of the bundle-adjustment window (oldest first), the frame number, grey
        image and pose, and the landmarks it observed (world points and their pixels there). Empty
        before the bootstrap and while the scale is pending."""
        if not self.initialized or self.scale_pending:
            return []
        kfs = self._window[-n:]
        seen_by: dict = {k: {} for k in kfs}  # keyframe -> {landmark: pixel}, in one pass over the observations
        for o in self._obs:
            if o[0] in seen_by:
                seen_by[o[0]][int(o[1])] = (o[2], o[3])
        out = []
        for k in kfs:
            seen = seen_by[k]
            if k not in self._kf_pose or k not in self._kf_rgb or len(seen) < self.cfg.min_ref_points:
                continue
            lids = np.array(sorted(seen), np.int64)
            prev = max((j for j in self._kf_pose if j < k), default=k)  # for a motion guess (resume)
            out.append({"index": int(k), "gray": to_u8(self._kf_rgb[k]), "c2w": self._kf_pose[k].copy(),
                        "world": np.stack([self._lm[i] for i in lids]).astype(np.float64),
                        "uv": np.array([seen[i] for i in lids], np.float64),
                        "prev_index": int(prev), "prev_c2w": self._kf_pose[prev].copy()})
        return out

    def resume(self, index: int, rgb: np.ndarray, states: list) -> Optional[np.ndarray]:
        """Start from saved keyframes (``states`` of :meth:`keyframe_states`) instead of a bootstrap:
        frame ``index`` is located among the landmarks of the keyframe nearest to it in frame number
        (KLT from the keyframe's image, rotated into the view, then PnP:
        :func:`~fmapping.tracking.loop.locate_in_keyframe`), the next nearest when that fails. When
        it is found, it becomes the first keyframe, at the located pose, holding the located
        landmarks, and tracking goes on from it in the saved world frame and scale: returns its
        pose. None when the images do not agree (the front end is unchanged). The pose is searched
        from guesses along the keyframes' motion, continued at constant velocity up to frame
        ``index`` (the frames between went by unseen); the guess locating most landmarks wins."""
        for state in sorted(states, key=lambda st: (abs(index - int(st["index"])), -int(st["index"]))):
            c2w = self._resume_from(index, rgb, state)
            if c2w is not None:
                return c2w
        return None

    def _resume_from(self, index: int, rgb: np.ndarray, state: dict) -> Optional[np.ndarray]:
        """:meth:`resume` against one saved keyframe."""
        gray = to_u8(rgb)
        c2w_kf = np.asarray(state["c2w"], np.float64)
        best = None
        for guess in resume_guesses(state, index):
            m = locate_in_keyframe(self.camera, np.asarray(state["gray"], np.uint8),
                                   np.asarray(state["uv"], np.float64), np.asarray(state["world"], np.float64),
                                   c2w_kf, gray, guess, self.cfg.klt, self.cfg.loop)
            if m is not None and (best is None or m.inliers > best.inliers):
                best = m
        m = best
        if m is None or len(m.index) < self.cfg.min_ref_points:
            return None
        c2w = orthonormalize(m.c2w)
        world = np.asarray(state["world"], np.float64)[m.index]
        self._first_index = self._kf_index = index
        self._c2w0 = c2w.copy()
        self._kf_pose = {index: c2w.copy()}
        self._kf_rgb = {index: rgb}
        self._window = [index]
        self._lm = list(world)
        self._obs = [(index, lid, float(u), float(v)) for lid, (u, v) in enumerate(m.uv)]
        tr = _Tracks(m.uv, index)
        tr.lid = np.arange(len(world), dtype=np.int64)
        self._tracks = tr
        self._rel = {index: (index, np.eye(4))}
        self._last_gray = gray
        self.tracker.reset_motion([c2w])
        try:
            self._set_reference(index, rgb, gray)
        except ValueError:
            return None  # too few points with depth to track against (still uninitialised)
        if self.cfg.loop.enabled:
            self._kf_images = {index: gray}
        self.initialized, self.failed, self._buf = True, False, []
        self.init_info = {"frame": int(index), "resumed_from": int(state["index"]), "points": int(len(world)),
                          "scale_from": "resumed"}
        return c2w


def resume_guesses(state: dict, index: int, n: int = 8) -> list:
    """Pose guesses for frame ``index`` after a saved keyframe ``state`` (one of :meth:`MonoFrontend.keyframe_states`):
    the keyframe's pose moved on at the velocity between its previous keyframe and it, by 0 to
    1.5 times the frames in between, backwards for a frame before the keyframe (``n`` + 1 guesses;
    the keyframe's pose alone without a previous keyframe)."""
    import cv2

    c2w, k = np.asarray(state["c2w"], np.float64), int(state["index"])
    prev, kp = np.asarray(state.get("prev_c2w", c2w), np.float64), int(state.get("prev_index", k))
    if kp >= k or index == k:
        return [c2w]
    rvec = cv2.Rodrigues(prev[:3, :3].T @ c2w[:3, :3])[0].ravel() / (k - kp)  # per frame, in the camera frame
    vel = (c2w[:3, 3] - prev[:3, 3]) / (k - kp)  # per frame, in the world
    out = []
    for d in np.linspace(0.0, 1.5 * (index - k), n + 1):
        g = np.eye(4)
        g[:3, :3] = c2w[:3, :3] @ cv2.Rodrigues(rvec * d)[0]
        g[:3, 3] = c2w[:3, 3] + vel * d
        out.append(g)
    return out
