"""The monocular front end (:class:`MonoFrontend`): per-frame tracking against keyframes with PnP
recovery, keyframes and their bundle adjustment, the late anchor's rescale; see :mod:`fmapping.tracking.mono`."""
from __future__ import annotations

import dataclasses
import time
from typing import Callable, Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import inv_pose, orthonormalize, pose_distance, scale_about
from fmapping.tracking.direct_align import select_pixels, to_gray
from fmapping.tracking.direct_tracker import DirectTracker, TrackerConfig, TrackResult
from fmapping.tracking.features import (
    REFERENCE_WIDTH, at_width, detect_corners, fine_klt_config, klt_track_gain, pnp_ransac, refine_pnp, to_u8,
)
from fmapping.tracking.mono.ba_thread import BackgroundBA
from fmapping.tracking.mono.bootstrap import Bootstrap
from fmapping.tracking.mono.config import MonoConfig
from fmapping.tracking.mono.loop_closing import LoopClosing
from fmapping.tracking.mono.restart import Restart
from fmapping.tracking.ba import BAResult
from fmapping.tracking.mono.store import BAProblem, KeyframeStore, Tracks, solve_ba_problem
from fmapping.tracking.mono.worker import BackgroundJob
from fmapping.tracking.rolling_shutter import rotation_step, unroll


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


class MonoFrontend(Bootstrap, LoopClosing, Restart):
    """See :mod:`fmapping.tracking.mono`. Call :meth:`bootstrap` per frame until it returns poses, then
    :meth:`track`. The bootstrap, loop closure and restarts are in its mixins
    (:mod:`~fmapping.tracking.mono.bootstrap`, :mod:`~fmapping.tracking.mono.loop_closing`,
    :mod:`~fmapping.tracking.mono.restart`), the keyframes and landmarks in its ``store``."""

    def __init__(self, camera: PinholeCamera, tracker_cfg: Optional[TrackerConfig] = None,
                 cfg: Optional[MonoConfig] = None):
        self.camera = camera
        self.cfg = cfg or MonoConfig()
        self.cfg.validate()
        tcfg = tracker_cfg or TrackerConfig()
        if self.cfg.pose_refine == "pnp" and self.cfg.direct_step_tol > tcfg.align.step_tol:
            tcfg = dataclasses.replace(tcfg, align=dataclasses.replace(tcfg.align, step_tol=self.cfg.direct_step_tol))
        self.tracker = DirectTracker(camera, tcfg)
        self.initialized = False
        self.failed = False
        self.init_info: dict = {}
        self.store = KeyframeStore(camera, self.cfg)  # tracks, keyframes, landmarks, the BA window
        self._buf: list = []  # bootstrap frames: (index, rgb)
        self._last_gray: Optional[np.ndarray] = None
        self._last_gray_frame: Optional[int] = None  # the frame of _last_gray (tracks' last pixels)
        self._gain_step = 1.0  # exposure of the last frame over the one before (KLT's prediction)
        self._gain_kf = 1.0  # exposure of the last frame over the keyframe image ``_kf_gray``
        self._kf_index = -1
        self._lost_run = 0
        self._deferred = 0  # frames in a row whose keyframe was put off (a loop's BA in the worker)
        self.keyframes_deferred = 0  # such frames in all (MonoConfig.loop_ba_defer_frames)
        self.frames_pnp = 0  # frames posed from their tracked landmarks alone (MonoConfig.frame_pose "pnp")
        self.reinits: list = []
        self.dense_checks: list = []  # per keyframe with extra depth: did it agree with the landmarks?
        self._first_index = 0  # the bootstrap's first frame
        self._anchor: Optional[Callable[[int], Optional[float]]] = None  # baseline source of the late anchor
        self.late_anchor: Optional[dict] = None  # {"frame", "factor"} once the scale was taken again (or refused)
        self.loops: list = []  # loop closures: {"frame", "keyframe", "inliers", "moved_m", "moved_deg", ...}
        self.loops_refused: list = []  # verified loops whose correction was too large to trust
        self._kf_images: dict = {}  # keyframe index -> grey image, for loop verification (bounded)
        self._moved_all = False  # the last keyframe's update moved every keyframe (a loop closure)
        self._loop_ba = None  # a loop's bundle adjustment in the worker (loop_closing.PendingLoopBA)
        self._step = np.zeros(3)  # the current frame's rotation since the previous one (camera frame)
        # the keyframe BA in a worker thread (MonoConfig.ba_thread), merged between frames
        self._bg: Optional[BackgroundBA] = BackgroundBA(camera) if self.cfg.ba_thread else None
        # the loop search in another worker (MonoConfig.loop_thread), merged at a later frame
        self._loop_worker: Optional[BackgroundJob] = BackgroundJob("fmapping-loop") if self.cfg.loop_thread else None
        self._loop_epoch = 0  # a rescale or re-initialisation since a search began voids it
        self._loop_passed_over: Optional[int] = None  # the last keyframe not searched from (a search was busy)
        self._kf_pending: Optional[tuple] = None  # (frame, rgb, grey, extra_depth): a keyframe's work for later
        # bundle adjustments (the worker's, the final one) and loop corrections (loop_thread) merged so far: their
        # poses moved
        self.ba_merges = 0
        self.final_ba_stats: Optional[dict] = None  # the final bundle adjustment's (:meth:`final_ba`)
        self._ref_src: Optional[tuple] = None  # (keyframe, landmark ids, pixels, extra points): its reference

    def _geo(self, uv: np.ndarray) -> np.ndarray:
        """Pixels of the current frame unrolled for the rolling shutter (``MonoConfig.rolling_shutter``)."""
        return unroll(self.camera, uv, self._step, self.cfg.rolling_shutter)

    # ================================================================== tracking
    def track(self, index: int, rgb: np.ndarray,
              extra_depth: Optional[Callable[[np.ndarray], Callable]] = None,
              keyframe_later: bool = False) -> TrackResult:
        """Track a frame after the bootstrap. ``extra_depth(c2w)`` -> ``uv -> depth`` callable
        (e.g. rendered from the map) adds dense points to new keyframes. With ``keyframe_later`` a frame
        that becomes a keyframe returns its tracked pose at once and the keyframe's work (landmarks, its
        bundle adjustment and loop search handed to the workers, the new reference) waits for
        :meth:`finish_keyframe`: a caller at a camera's rate hands the pose on first (the next call, or
        :meth:`flush_ba`, does that work if the caller did not)."""
        if not self.initialized:
            raise RuntimeError("MonoFrontend.track before a successful bootstrap")
        self.finish_keyframe()
        if self._anchor is not None and index - self._first_index >= 2 * self.cfg.late_anchor_frames:
            self.settle_scale(f"no tracked frame with an anchor pose in the first {2 * self.cfg.late_anchor_frames}")
        self._merge_ba(wait=False)  # a bundle adjustment finished since the last frame: take it first
        self._merge_loop()  # ... and a loop search (loop_thread), once the BA worker is idle
        self.tracker.at_frame(index)  # the motion model predicts over the frames skipped since the last one
        gray = to_u8(rgb)
        quick = None
        if self.cfg.frame_pose == "pnp":
            t0 = time.perf_counter()
            self._klt(gray, index, None)
            quick = self._pose_from_tracks(rgb)
            if quick is not None:
                quick.ms += (time.perf_counter() - t0) * 1000.0
                self.frames_pnp += 1
        if quick is not None:
            res = quick
        else:
            res = self.tracker.track(rgb)
            if self.cfg.rolling_shutter and not res.lost:
                hist = self.tracker.motion_history  # [previous tracked frame, this frame]
                if len(hist) == 2:
                    self._step = rotation_step(hist[0], hist[1]) / self.tracker.frames_between()
            if self.cfg.frame_pose != "pnp":
                self._klt(gray, index, None if res.lost else res.c2w)
            if res.lost and self.cfg.pnp_recovery:
                res = self._recover(rgb, res)
        if res.lost:
            self._lost_run += 1
            if self._lost_run >= self.cfg.reinit_after:
                self._reinit(index, rgb, gray, self._merge_moving(res.c2w))
                res.reason += f"; re-initialised at frame {index} (constant-depth keyframe)"
                self.reinits.append(index)
                self._lost_run = 0
            return res
        self._lost_run = 0
        if self.cfg.pose_refine == "pnp" and quick is None:
            t0 = time.perf_counter()
            refined = self._pnp(res.c2w)
            if refined is not None:
                res.c2w = refined
                self.tracker.correct_last(refined)
            res.ms += (time.perf_counter() - t0) * 1000.0
        self.store.rel[index] = (self._kf_index, inv_pose(self.store.kf_pose[self._kf_index]) @ res.c2w)
        if res.need_keyframe and self._defer_keyframe(res):
            res.need_keyframe = False
        if res.need_keyframe and keyframe_later and self._anchor is None:
            self._kf_pending = (index, rgb, gray, extra_depth)
            return res
        if res.need_keyframe:
            t0 = time.perf_counter()
            res.c2w = self._keyframe_work(index, rgb, gray, res.c2w, extra_depth)
            res.ms += (time.perf_counter() - t0) * 1000.0  # keyframe work counts as tracking time
        if self._anchor is not None and index - self._first_index >= self.cfg.late_anchor_frames - 1:
            res.c2w = self._late_anchor(index, self._merge_moving(res.c2w))
        return res

    def _keyframe_work(self, index: int, rgb, gray, c2w: np.ndarray, extra_depth=None) -> np.ndarray:
        """Frame ``index`` (tracked at ``c2w``) becomes a keyframe and the new reference; its pose after that."""
        c2w = self._add_keyframe(index, rgb, gray, c2w)
        try:
            self._set_reference(index, rgb, gray, extra_depth)
        except ValueError:
            pass  # keep the old reference; the tracker asks again next frame
        return c2w

    @property
    def keyframe_pending(self) -> bool:
        """Is a keyframe's work waiting for :meth:`finish_keyframe` (``track(keyframe_later=True)``)?"""
        return self._kf_pending is not None

    def finish_keyframe(self) -> Optional[np.ndarray]:
        """The work of the keyframe :meth:`track` left for later (``keyframe_later``), from the frame's pose as
        the front end has it now; that keyframe's pose after it, or None when none was waiting."""
        if self._kf_pending is None:
            return None
        (index, rgb, gray, extra), self._kf_pending = self._kf_pending, None
        k, rel = self.store.rel[index]
        return self._keyframe_work(index, rgb, gray, orthonormalize(self.store.kf_pose[k] @ rel), extra)

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
        self._merge_ba(wait=True)  # a solution in flight is in the old scale
        self._loop_epoch += 1  # ... and a loop search in flight is dropped
        self.store.scale_part(c0, s, kfs)
        self.tracker.rescale(c0, s, frames=kfs)

    # ================================================================== internals
    def _klt(self, gray: np.ndarray, index: Optional[int] = None, c2w: Optional[np.ndarray] = None) -> None:
        """The tracks into frame ``index`` (``gray``), posed at ``c2w`` when known (else the motion model's
        prediction guides them after skipped frames: :meth:`_klt_guess`)."""
        tr = self.store.tracks
        if tr is not None and len(tr):
            # exposure: the last step's gain predicts this one's (klt_track_gain measures and corrects it)
            guess = self._klt_guess(index, c2w)
            new, ok, self._gain_step = klt_track_gain(self._last_gray, gray, tr.uv, self.cfg.klt, guess=guess,
                                                      gain=self._gain_step, fb_guess=guess is not None)
            kf_gray = getattr(self, "_kf_gray", None)
            if self.cfg.klt_from_keyframe and kf_gray is not None and tr.uv_kf is not None:
                # refine from the keyframe image: positions no longer accumulate frame-to-frame drift
                # (with klt.max_width the chained pass ran in halved images: this one refines at full size)
                ref, ok2, self._gain_kf = klt_track_gain(kf_gray, gray, tr.uv_kf,
                                                         fine_klt_config(self.cfg.klt, gray.shape[1]), guess=new,
                                                         gain=self._gain_kf * self._gain_step,
                                                         fb=self.cfg.klt_keyframe_fb)
                good = ok2 & (np.linalg.norm(ref - new, axis=1) < 2.0)
                new = np.where(good[:, None], ref, new)
            tr.uv = new.astype(np.float64)
            tr.geo = self._geo(tr.uv)
            tr.keep(ok)
        self._last_gray = gray
        self._last_gray_frame = index

    def _klt_guess(self, index: Optional[int], c2w: Optional[np.ndarray]) -> Optional[np.ndarray]:
        """Where the tracks should be in frame ``index`` when frames were skipped since the last one
        (``MonoConfig.klt_gap_guess``): a track with a landmark at its projection from the frame's pose ``c2w``
        (None: the motion model's prediction), the others moved by the median of those moves. None (KLT starts
        at the last pixels) right after a tracked frame or with too few landmarks. A flow of two frames or more
        on a repeating pattern makes KLT lock onto the next period."""
        tr = self.store.tracks
        last = self._last_gray_frame
        if not self.cfg.klt_gap_guess or index is None or last is None or index - last < 2:
            return None
        has = np.flatnonzero(tr.lid >= 0)
        if len(has) < self.cfg.pnp_min_points:
            return None
        proj, z = self.camera.world_to_pixels(self.tracker.predict() if c2w is None else c2w,
                                              np.stack([self.store.lm[i] for i in tr.lid[has]]))
        ok = z > 1e-3
        if ok.sum() < self.cfg.pnp_min_points:
            return None
        guess = tr.uv + np.median(proj[ok] - tr.uv[has[ok]], axis=0)
        guess[has[ok]] = proj[ok]
        return guess

    def _reinit(self, index: int, rgb, gray, c2w: np.ndarray) -> None:
        from fmapping.tracking.direct_align import make_reference

        med = self.tracker.reference.median_depth if self.tracker.reference is not None else self.cfg.unit_depth
        cam = self.camera
        depth = np.full((cam.height, cam.width), med if np.isfinite(med) else self.cfg.unit_depth, np.float32)
        self._loop_epoch += 1  # a new world frame: a loop search in flight is dropped
        self.store.kf_pose[index] = np.asarray(c2w, np.float64).copy()
        self.store.kf_rgb[index] = rgb
        self.store.window = [index]
        tcfg = self.tracker.cfg
        ref = make_reference(rgb, depth, cam, self.store.kf_pose[index], tcfg.align.levels, tcfg.num_points,
                             tcfg.min_grad, index, blur=tcfg.align.blur)
        self.tracker.push_reference(ref)
        self.tracker.reset_motion([self.store.kf_pose[index]], [index])
        self._kf_index = index
        self.store.rel[index] = (index, np.eye(4))
        tr = Tracks(detect_corners(gray, self.cfg.klt).astype(np.float64), index)
        tr.mark_keyframe(index)
        self.store.tracks = tr
        self._kf_gray = gray
        self._gain_kf = 1.0

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
        found = self.store.tracked_landmarks()
        if found is None:
            return None
        x, uv = found
        px = at_width(self.cfg.pnp_inlier_px, max(self.camera.width, REFERENCE_WIDTH))  # KLT noise grows with the size
        found = pnp_ransac(self.camera, x, uv, px)
        if found is None or found[1].sum() < max(self.cfg.pnp_min_points, 0.5 * len(x)):
            return None
        return orthonormalize(inv_pose(found[0]))

    def _pose_from_tracks(self, rgb: np.ndarray) -> Optional[TrackResult]:
        """``MonoConfig.frame_pose`` "pnp": the frame's pose from its KLT-tracked landmarks, refined by PnP from
        the motion model's prediction (inliers within ``pnp_first_gate_px``, then again within
        ``pnp_inlier_px`` of the first fit), and judged photometrically against the reference as the direct
        alignment's own result would be (:meth:`DirectTracker.verify`). None, and the direct alignment runs,
        when fewer than ``pnp_min_points`` or than ``pnp_first_min_share`` of the tracked landmarks fit, or
        when the reference's points do not agree with the pose."""
        c = self.cfg
        w2c = self._fit_to_tracks(inv_pose(self.tracker.predict()),
                                  (at_width(c.pnp_first_gate_px, self.camera.width), c.pnp_inlier_px),
                                  c.pnp_first_min_share, check_final=True)
        return None if w2c is None else self.tracker.verify(rgb, orthonormalize(inv_pose(w2c)))

    def _fit_to_tracks(self, w2c: np.ndarray, gates: tuple, min_share: float = 0.0,
                       check_final: bool = False) -> Optional[np.ndarray]:
        """PnP of the tracked landmarks from pose ``w2c``: at each gate (pixels) in turn, refitted to those that
        reproject within it (an unchanged set ends it early). None when at a gate fewer than ``pnp_min_points``
        and than ``min_share`` of them fit, or a fit fails; with ``check_final`` also when too few fit within
        the last gate at the final pose."""
        found = self.store.tracked_landmarks()
        if found is None:
            return None
        x, uv = found
        need = max(self.cfg.pnp_min_points, min_share * len(x))
        last = None
        for gate in gates:
            inl = self._reprojects_within(x, uv, w2c, gate)
            if inl.sum() < need:
                return None
            if last is not None and np.array_equal(inl, last):
                break  # the same inliers: the same fit
            w2c, last = refine_pnp(self.camera, x[inl], uv[inl], w2c), inl
            if w2c is None:
                return None
        if check_final and self._reprojects_within(x, uv, w2c, gates[-1]).sum() < need:
            return None
        return w2c

    def _reprojects_within(self, x: np.ndarray, uv: np.ndarray, w2c: np.ndarray, px: float) -> np.ndarray:
        """Which world points ``x`` (N, 3) project within ``px`` pixels of ``uv`` (N, 2) at pose ``w2c``."""
        y = x @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.where(y[:, 2] > 1e-6, y[:, 2], 1e-6)
        cam = self.camera
        proj = np.stack([cam.fx * y[:, 0] / z + cam.cx, cam.fy * y[:, 1] / z + cam.cy], -1)
        return (y[:, 2] > 1e-3) & (np.linalg.norm(proj - uv, axis=1) < px)

    def _pnp(self, c2w: np.ndarray) -> Optional[np.ndarray]:
        """Refine a pose on the reprojection error of the tracked landmarks (inliers of the given pose)."""
        refined = self._fit_to_tracks(inv_pose(c2w), (self.cfg.pnp_inlier_px,))
        if refined is None:
            return None
        out = orthonormalize(inv_pose(refined))
        dt, dr = pose_distance(out, c2w)
        scale = self.tracker.reference.median_depth if self.tracker.reference is not None else 1.0
        if dt > 0.1 * scale or dr > 5.0:
            return None  # disagrees wildly with the photometric pose: keep that one
        return out

    def _defer_keyframe(self, res: TrackResult) -> bool:
        """Should this frame's keyframe wait (``ba_thread``)? Every keyframe first merges the bundle
        adjustment in flight (the store changes), waiting for it on the frame path if need be. A loop
        closure's BA covers tens of keyframes and takes the worker 0.3-0.6 s at 320x240 on 2 cores, 10-20
        frames of a 30-fps camera: while one is in flight, the frame stays an ordinary one, tracked
        against the current reference, for up to ``MonoConfig.loop_ba_defer_frames`` frames in a row while
        it still sees ``ba_defer_min_visible`` of the reference; the next frame asks again. A keyframe's own
        BA is waited for (deferring those too cost accuracy: bench/results/realtime_tail/). A re-localised
        frame is never deferred."""
        if (self._bg is None or not self._bg.busy or self._loop_ba is None or res.relocalised
                or self._deferred >= self.cfg.loop_ba_defer_frames
                or res.visible_ratio < self.cfg.ba_defer_min_visible):
            self._deferred = 0
            return False
        self._deferred += 1
        self.keyframes_deferred += 1
        return True

    def _add_keyframe(self, index: int, rgb: np.ndarray, gray: np.ndarray, c2w: np.ndarray) -> np.ndarray:
        """Frame ``index`` becomes a keyframe (:meth:`KeyframeStore.add_keyframe`); the window is
        bundle-adjusted, loops are looked for, the motion model moves with the refined keyframe.
        With ``ba_thread`` the previous keyframe's BA is merged first (waiting for it if need be),
        loops are looked for, and this keyframe's BA goes to the worker (merged by :meth:`_merge_ba`)."""
        c = self.cfg
        self._moved_all = False  # (a loop's bundle adjustment merged just below sets it again)
        # one bundle adjustment in flight at a time; the store changes now. With loop_thread a loop's (tens of
        # keyframes, most of a second) is not waited for: keyframes go on meanwhile and move with it when it is merged
        c2w = self._merge_moving(c2w, wait=self._loop_ba is None or not c.loop_thread)
        self.store.add_keyframe(index, rgb, c2w, gray)
        before = self.store.kf_pose[index].copy()
        if c.ba and self._bg is None:
            self.store.run_ba()
        if c.loop.enabled:
            self._close_loop(index, gray)
            self._kf_images[index] = gray
            while len(self._kf_images) > c.loop.max_keyframe_images:
                self._kf_images.pop(next(iter(self._kf_images)))
        if c.ba and self._bg is not None and not self._bg.busy:  # (busy: the loop's BA covers this keyframe)
            prob = self.store.ba_problem()
            if prob is not None:
                self._bg.submit(prob)
        after = self.store.kf_pose[index]
        # move the motion model with the refined keyframe
        self.tracker.move_motion(after @ inv_pose(before))
        return after

    def _merge_ba(self, wait: bool) -> bool:
        """Merge the worker's bundle adjustment when it is done (``wait``: block until it is); see
        :meth:`_take_ba`. True when one was merged."""
        got = None if self._bg is None else self._bg.take(wait)
        if got is None:
            return False
        self._take_ba(*got)
        return True

    def _take_ba(self, prob: BAProblem, res: BAResult) -> None:
        """The solution ``res`` of ``prob`` into the store (its poses and landmarks), the tracker's references
        moved with their keyframes and the motion model with the current one; a loop closure's back to the
        graph's scale. Keyframes added while a loop's was in flight move as its newest keyframe did, with the
        landmarks they first saw."""
        loop = self._loop_ba is not None and self._loop_ba.prob is prob
        before = {k: self.store.kf_pose[k].copy() for k in prob.window if k in self.store.kf_pose}
        last = prob.window[-1]
        newer = {k: p.copy() for k, p in self.store.kf_pose.items() if k > last} if loop and last in before else {}
        dropped = self.store.apply_ba(prob, res)
        if newer:
            tail = self.store.kf_pose[last] @ inv_pose(before[last])
            for k, b in newer.items():
                self.store.kf_pose[k] = orthonormalize(tail @ b)
            self.store.move_landmarks({k: tail for k in newer})
            before.update(newer)
        moves = {k: self.store.kf_pose[k] @ inv_pose(b) for k, b in before.items()}
        self.tracker.move_references(moves)
        if self._kf_index in moves:
            self.tracker.move_motion(moves[self._kf_index])
            self._rebuild_reference(dropped)
        self.ba_merges += 1
        if loop:  # a loop closure's: back to the graph's scale
            loop, self._loop_ba = self._loop_ba, None
            k = self._kf_index
            was = self.store.kf_pose[k].copy() if k in self.store.kf_pose else None
            loop.record["keyframes_meanwhile"] = len(newer)
            self._after_loop_ba(loop.keyframes, loop.old, loop.graph_size, loop.record, tuple(sorted(newer)))
            if was is not None:  # the motion model moves with the current keyframe (as at a keyframe)
                self.tracker.move_motion(self.store.kf_pose[k] @ inv_pose(was))
            self._moved_all = True

    def _rebuild_reference(self, dropped: set) -> None:
        """The current keyframe's reference again, from its landmarks as the merged bundle adjustment
        left them (without the observations it ``dropped``), as :meth:`_set_reference` builds it when
        the BA runs first: the frames tracked after the merge align to refined depths."""
        src = self._ref_src
        if src is None or src[0] != self._kf_index or self._kf_index not in self.store.kf_rgb:
            return
        k, lids, uv, extra = src
        keep = np.array([(k, int(i)) not in dropped for i in lids], bool) if len(lids) else np.zeros(0, bool)
        pts = self.store.cam_points(k, lids[keep], uv[keep])
        if extra is not None:
            pts = np.concatenate([pts, extra])
        if len(pts) >= self.cfg.min_ref_points:
            try:
                self.tracker.set_reference_points(self.store.kf_rgb[k], pts, self.store.kf_pose[k], k)
            except ValueError:
                pass  # keep the moved one

    def _merge_moving(self, c2w: np.ndarray, wait: bool = True) -> np.ndarray:
        """Wait for (``wait``; else take it if done) and merge a bundle adjustment in flight, then a finished
        loop search (``loop_thread``; one still running stays in flight); ``c2w``, a pose tracked against the
        current keyframe before the merge, moved with that keyframe."""
        k = self._kf_index
        before = self.store.kf_pose[k].copy() if k in self.store.kf_pose else None
        merged = self._merge_ba(wait=wait)
        merged = self._merge_loop() or merged
        if not merged or before is None:
            return c2w
        return orthonormalize(self.store.kf_pose[k] @ inv_pose(before) @ c2w)

    def flush_ba(self) -> bool:
        """Wait for a bundle adjustment in flight and merge it, then a loop search in flight (``loop_thread``)
        and one from the last keyframe if it was passed over, with the bundle adjustment each correction starts
        (the end of a sequence, a snapshot of the final poses). True when poses moved."""
        merged = self.finish_keyframe() is not None
        merged = self._merge_ba(wait=True) or merged
        if self._loop_worker is not None:
            merged = self._flush_loop() or merged
        return merged

    def final_ba(self) -> bool:
        """The sequence ended: the bundle adjustment in flight merged (:meth:`flush_ba`), then one bundle
        adjustment of every keyframe and the landmarks they observe (the first two keyframes fixed, as in the
        window's), at most ``final_ba_max_nfev`` iterations, when ``MonoConfig.final_ba`` says so ("after_loops":
        once a loop was closed). The window's adjustment leaves older keyframes where they were when they left it;
        this one fits them to every observation at once, the loops' too. True when poses moved."""
        merged = self.flush_ba()
        kfs = sorted(self.store.kf_pose)
        mode = self.cfg.final_ba
        if (not (self.initialized and self.cfg.ba) or mode == "never" or (mode == "after_loops" and not self.loops)
                or len(kfs) < 3):
            return merged
        prob = self.store.ba_problem(window=kfs, max_nfev=self.cfg.final_ba_max_nfev)
        if prob is None:
            return merged
        self._take_ba(prob, solve_ba_problem(self.camera, prob))
        self.final_ba_stats = dict(self.store.ba_stats[-1])
        return True

    def _set_reference(self, index: int, rgb, gray, extra_depth=None) -> None:
        c = self.cfg
        tr = self.store.tracks
        has = tr.lid >= 0
        pts = self.store.cam_points(index, tr.lid[has], tr.uv[has])
        extra = None
        if extra_depth is not None and c.dense_extra:
            fn = extra_depth(self.store.kf_pose[index])
            if self._dense_agrees(index, fn, pts):
                dense = self._dense_points(rgb, fn)
                if len(dense):
                    pts, extra = np.concatenate([pts, dense]), dense
        if len(pts) < c.min_ref_points:
            raise ValueError(f"keyframe {index}: only {len(pts)} points with depth")
        self.tracker.set_reference_points(rgb, pts, self.store.kf_pose[index], index)
        if self._bg is not None:  # rebuilt when this keyframe's bundle adjustment is merged
            self._ref_src = (index, tr.lid[has].copy(), tr.uv[has].copy(), extra)
        self._kf_index = index
        # restart tracks here: live ones continue, fresh corners start at this keyframe
        newc = detect_corners(gray, c.klt, existing=tr.uv)
        if len(newc):
            tr.add(newc.astype(np.float64), index, self._geo(newc.astype(np.float64)))
        tr.mark_keyframe(index)
        self._kf_gray = gray
        self._gain_kf = 1.0

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

    def is_keyframe(self, index: int) -> bool:
        """Is frame ``index`` one of the front end's keyframes (bootstrap or tracked, or its work pending)?"""
        return index in self.store.kf_pose or (self._kf_pending is not None and self._kf_pending[0] == index)

    def keyframe_poses(self) -> dict:
        return {k: p.copy() for k, p in self.store.kf_pose.items()}

    def poses(self, window_only: bool = False) -> dict:
        """Every tracked frame's pose, moved with its bundle-adjusted keyframe. With ``window_only``
        just the frames of the keyframes in the current BA window: the only ones the last BA moved.
        A bundle adjustment still in the worker (``ba_thread``), or a loop search (``loop_thread``), is not in
        them until it is merged: at the next frame when it is done by then, or :meth:`flush_ba`."""
        keep = set(self.store.window) if window_only else self.store.kf_pose
        return {i: orthonormalize(self.store.kf_pose[k] @ rel) for i, (k, rel) in self.store.rel.items()
                if k in keep and k in self.store.kf_pose}

    def interpolate_frame(self, index: int, before: int, after: int, w: float) -> Optional[np.ndarray]:
        """Frame ``index``, not tracked, between tracked frames ``before`` and ``after``: its pose ``w`` of the
        way from ``before``'s to ``after``'s as the front end has them now (translation linear, rotation on the
        geodesic), kept relative to ``before``'s keyframe like a tracked frame's (bundle adjustments move it).
        None when either is not a tracked frame."""
        from fmapping.trajectory import interpolate_poses

        rel = self.store.rel
        if before not in rel or after not in rel or any(rel[i][0] not in self.store.kf_pose for i in (before, after)):
            return None
        ends = [self.store.kf_pose[rel[i][0]] @ rel[i][1] for i in (before, after)]
        c2w = orthonormalize(interpolate_poses([w], [0.0, 1.0], np.stack(ends), max_dt=1.0)[0][0])
        kf = rel[before][0]
        rel[index] = (kf, inv_pose(self.store.kf_pose[kf]) @ c2w)
        return c2w

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
        return np.stack(self.store.lm) if self.store.lm else np.zeros((0, 3))

    @property
    def ba_stats(self) -> list:
        """Per bundle adjustment: keyframes, points, observations, rms before / after, outliers, ms."""
        return self.store.ba_stats
