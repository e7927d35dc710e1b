"""Frame-to-keyframe tracking with motion prediction, loss detection, re-localisation and keyframe decisions.

:class:`DirectTracker` wraps :func:`fmapping.tracking.direct_align.align`: it keeps the
current reference keyframe (image + depth at selected pixels, see
:func:`~fmapping.tracking.direct_align.make_reference`) and a few recent ones, predicts
each new pose with a constant-velocity model, aligns, and judges the result:

* **lost** when too few reference points are visible, the inlier ratio or the
  residual is bad, or the pose jumps far from the prediction. The tracker then
  tries again from a zero-motion guess and against the recent keyframes
  (re-localisation); if nothing passes, the frame is reported lost and its pose
  is the prediction (never a wild optimiser output), and the motion model is not
  updated from it.
* **need_keyframe** when the overlap with the reference drops or the camera has
  moved / turned far from it. The caller then supplies depth for a new reference
  (rendered from the map in SLAM), via :meth:`DirectTracker.set_reference`.

Poses are camera-to-world 4x4 float64 (see :mod:`fmapping.geometry`).
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import extrapolate_motion, inv_pose, orthonormalize, pose_distance, scale_about
from fmapping.tracking.direct_align import (
    AlignConfig, AlignResult, DepthSource, Reference, align, build_pyramid, evaluate_pose, image_valid_mask,
    make_reference, reference_from_points, to_gray,
)


@dataclass
class TrackerConfig:
    align: AlignConfig = field(default_factory=AlignConfig)
    num_points: int = 2500  # reference pixels per keyframe
    min_grad: float = 0.02  # grey levels per pixel
    # loss detection
    min_inlier_ratio: float = 0.5
    min_visible_ratio: float = 0.2
    max_rmse: float = 0.15
    max_relative_rmse: float = 0.6  # residual RMS / std of the reference intensities (1 = explains nothing)
    max_jump_rel: float = 0.25  # translation from the prediction, relative to the reference's median depth
    max_jump_deg: float = 15.0
    # keyframes (the tracker's reference; the mapper keeps its own window)
    kf_min_visible: float = 0.7
    kf_max_translation_rel: float = 0.1  # translation from the reference / median depth
    kf_max_rotation_deg: float = 10.0
    kf_min_inlier_ratio: float = 0.7
    recent_keyframes: int = 5  # kept for re-localisation
    max_velocity_after_loss: int = 2  # consecutive losses after which the prediction stops extrapolating
    # the constant-velocity prediction over a gap of skipped frames covers at most this many times the last step
    max_prediction_steps: float = 3.0


@dataclass
class TrackResult:
    c2w: np.ndarray  # (4, 4) estimated camera-to-world (the prediction when lost)
    lost: bool
    relocalised: bool
    need_keyframe: bool
    rmse: float
    inlier_ratio: float
    visible_ratio: float
    iterations: int
    ms: float
    reference: int  # frame index of the reference used
    reason: str = ""  # why the frame was judged lost ("" when tracked)

    def to_dict(self) -> dict:
        return {
            "lost": self.lost, "relocalised": self.relocalised, "need_keyframe": self.need_keyframe,
            "rmse": self.rmse, "inlier_ratio": self.inlier_ratio, "visible_ratio": self.visible_ratio,
            "iterations": self.iterations, "ms": self.ms, "reference": self.reference, "reason": self.reason,
        }


class DirectTracker:
    """Photometric frame-to-keyframe tracker (the fast path)."""

    def __init__(self, camera: PinholeCamera, cfg: Optional[TrackerConfig] = None):
        self.camera = camera
        self.cfg = cfg or TrackerConfig()
        self.reference: Optional[Reference] = None
        self.recent: deque = deque(maxlen=max(1, self.cfg.recent_keyframes))
        self._history: list = []  # last two good poses (c2w)
        self._frames: list = []  # their frame indices (None: not known; then one frame apart is assumed)
        # index of the frame being tracked, set by the caller (:meth:`at_frame`): with frames skipped (a live camera
        # the tracker cannot keep up with) the prediction covers the frames since the last pose, not one step
        self.frame: Optional[int] = None
        self._losses = 0
        self._last_affine = np.zeros(2)

    # ------------------------------------------------------------ state
    def set_reference(self, rgb: np.ndarray, depth: DepthSource, c2w: np.ndarray, frame_index: int = -1) -> Reference:
        """Make frame ``rgb`` at pose ``c2w`` with ``depth`` (image or callable) the reference."""
        ref = make_reference(rgb, depth, self.camera, orthonormalize(c2w), self.cfg.align.levels, self.cfg.num_points,
                             self.cfg.min_grad, frame_index, blur=self.cfg.align.blur)
        if len(ref.points) < self.cfg.align.min_valid:
            raise ValueError(f"reference frame {frame_index}: only {len(ref.points)} pixels with gradient and depth")
        return self._push_reference(ref)  # replaces an older entry of the same frame (refresh)

    def set_reference_points(self, rgb: np.ndarray, points_cam: np.ndarray, c2w: np.ndarray,
                             frame_index: int = -1) -> Reference:
        """Make ``rgb`` the reference with given 3D points in its camera frame (sparse depth)."""
        ref = reference_from_points(rgb, points_cam, self.camera, orthonormalize(c2w), self.cfg.align.levels,
                                    frame_index, blur=self.cfg.align.blur)
        if len(ref.points) < self.cfg.align.min_valid:
            raise ValueError(f"reference frame {frame_index}: only {len(ref.points)} points with depth")
        return self._push_reference(ref)

    def push_reference(self, ref: Reference) -> Reference:
        """Make an already built :class:`Reference` the current one (kept among the recent keyframes)."""
        return self._push_reference(ref)

    def _push_reference(self, ref: Reference) -> Reference:
        for i, r in enumerate(self.recent):
            if r.frame_index == ref.frame_index and ref.frame_index >= 0:
                del self.recent[i]
                break
        self.recent.append(ref)
        self.reference = ref
        self._last_affine = np.zeros(2)
        return ref

    def at_frame(self, index: Optional[int]) -> None:
        """The frames tracked, observed or predicted next are frame ``index`` of the stream (None: unknown)."""
        self.frame = None if index is None else int(index)

    def _remember(self, c2w: np.ndarray) -> None:
        self._history = (self._history + [c2w])[-2:]
        self._frames = (self._frames + [self.frame])[-2:]

    def observe(self, c2w: np.ndarray) -> None:
        """Feed a trusted pose (first frame, another pose source, a refined pose) to the motion model."""
        self._remember(orthonormalize(c2w))
        self._losses = 0

    def correct_last(self, c2w: np.ndarray) -> None:
        """Replace the latest pose of the motion model (e.g. after a refinement of the tracked pose)."""
        if self._history:
            self._history[-1] = orthonormalize(c2w)

    @property
    def motion_history(self) -> list:
        return [p.copy() for p in self._history]

    def reset_motion(self, c2w_list: list, frames: Optional[list] = None) -> None:
        """Replace the motion history (e.g. with mapper-refined poses of the last two frames), ``frames`` their
        frame indices (None: not known, one frame apart assumed)."""
        self._history = [orthonormalize(p) for p in c2w_list[-2:]]
        self._frames = [None] * len(self._history) if frames is None else [int(f) for f in frames[-2:]]
        if len(self._frames) != len(self._history):
            raise ValueError(f"reset_motion: {len(c2w_list)} poses but {len(frames or [])} frame indices")

    def move_motion(self, t: np.ndarray) -> None:
        """Move the motion history's poses to ``t @ c2w`` (their keyframe was moved by ``t``: a bundle
        adjustment, a loop closure); their frames stay."""
        self._history = [orthonormalize(t @ p) for p in self._history]

    def _references(self) -> list:
        """Every reference held (the recent keyframes and the current one), each once."""
        return list({id(r): r for r in [*self.recent, self.reference] if r is not None}.values())

    def rescale(self, center: np.ndarray, s: float, frames: Optional[set] = None) -> None:
        """Scale the world about ``center`` by ``s``: keyframe poses and points, the motion model.
        With ``frames``, only the references of those frame indices (the motion model stays)."""
        for r in self._references():
            if frames is None or r.frame_index in frames:
                r.c2w = scale_about(r.c2w, center, s)
                r.points = r.points * s
                r.median_depth *= s
        if frames is None:
            self._history = [scale_about(p, center, s) for p in self._history]

    def move_references(self, moves: dict) -> None:
        """Move the references of keyframes ``moves`` ({frame index: 4x4 T}) to ``T @ c2w`` (their
        points stay in the camera frame), e.g. after a loop closure corrected those keyframes."""
        for r in self._references():
            if r.frame_index in moves:
                r.c2w = orthonormalize(moves[r.frame_index] @ r.c2w)

    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of the next camera-to-world pose."""
        if not self._history:
            if self.reference is None:
                return np.eye(4)
            return self.reference.c2w.copy()
        last = self._history[-1]
        if len(self._history) < 2 or self._losses >= self.cfg.max_velocity_after_loss:
            return last.copy()
        return orthonormalize(extrapolate_motion(self._history[-2], last, self._step_ratio()))

    def frames_between(self) -> int:
        """Frames from the older to the newer pose of the motion model (1 when not known)."""
        prev, last = ([None, None] + self._frames)[-2:]
        return last - prev if prev is not None and last is not None and last > prev else 1

    def _step_ratio(self) -> float:
        """Frames from the newest pose to the one being tracked over frames between the two poses of the motion
        model (1 when a frame index is not known or they do not follow each other), at most
        ``max_prediction_steps``."""
        prev, last, now = *self._frames[-2:], self.frame
        if prev is None or last is None or now is None or not prev < last < now:
            return 1.0
        return min((now - last) / (last - prev), self.cfg.max_prediction_steps)

    # ------------------------------------------------------------ tracking
    def _check(self, res: AlignResult, c2w: np.ndarray, pred: np.ndarray, ref: Reference) -> str:
        c = self.cfg
        if not res.ok:
            return "too few visible points"
        if res.visible_ratio < c.min_visible_ratio:
            return f"visible ratio {res.visible_ratio:.2f} < {c.min_visible_ratio}"
        if res.inlier_ratio < c.min_inlier_ratio:
            return f"inlier ratio {res.inlier_ratio:.2f} < {c.min_inlier_ratio}"
        if res.rmse > c.max_rmse:
            return f"residual {res.rmse:.3f} > {c.max_rmse}"
        if res.rmse > c.max_relative_rmse * res.ref_std:
            return f"residual {res.rmse:.3f} > {c.max_relative_rmse} x reference contrast {res.ref_std:.3f}"
        dt, dr = pose_distance(pred, c2w)
        scale = ref.median_depth if np.isfinite(ref.median_depth) and ref.median_depth > 0 else 1.0
        if dt > c.max_jump_rel * scale or dr > c.max_jump_deg:
            return f"pose jump {dt:.3f} m / {dr:.1f} deg from the prediction"
        return ""

    def _align_to(self, ref: Reference, pyr, c2w_init: np.ndarray, affine=None):
        t_init = inv_pose(c2w_init) @ ref.c2w  # reference camera -> current camera
        res = align(ref, pyr, t_init, self.cfg.align, affine)
        return res, orthonormalize(ref.c2w @ inv_pose(res.t_cr))

    def track(self, rgb: np.ndarray, c2w_guess: Optional[np.ndarray] = None) -> TrackResult:
        """Estimate the pose of ``rgb``. ``c2w_guess`` overrides the motion-model prediction."""
        if self.reference is None:
            raise RuntimeError("DirectTracker.track called before set_reference")
        t0 = time.perf_counter()
        pyr = build_pyramid(to_gray(rgb), self.camera, self.cfg.align.levels, self.cfg.align.blur,
                            image_valid_mask(rgb))
        pred = self.predict() if c2w_guess is None else np.asarray(c2w_guess, np.float64)
        ref = self.reference
        res, c2w = self._align_to(ref, pyr, pred, self._last_affine)
        reason = self._check(res, c2w, pred, ref)
        relocalised = False
        if reason:
            # retry: zero motion from the last good pose, then the recent keyframes
            cands = []
            starts = [self._history[-1]] if self._history else []
            for start in starts:
                r2, p2 = self._align_to(ref, pyr, start)
                if not self._check(r2, p2, start, ref):
                    cands.append((r2.inlier_ratio, r2, p2, ref))
            for kf in list(self.recent)[::-1]:
                if kf is ref:
                    continue
                for start in (pred, kf.c2w):
                    r2, p2 = self._align_to(kf, pyr, start)
                    if not self._check(r2, p2, start, kf):
                        cands.append((r2.inlier_ratio, r2, p2, kf))
            if cands:
                _, res, c2w, ref = max(cands, key=lambda x: x[0])
                reason = ""
                relocalised = True
                if ref is not self.reference:
                    self.reference = ref
        ms = (time.perf_counter() - t0) * 1000.0
        if reason:
            self._losses += 1
            return TrackResult(pred, True, False, False, res.rmse, res.inlier_ratio, res.visible_ratio,
                               res.iterations, ms, ref.frame_index, reason)
        return self._accept(res, c2w, ref, relocalised, ms)

    def _accept(self, res: AlignResult, c2w: np.ndarray, ref: Reference, relocalised: bool, ms: float) -> TrackResult:
        """Take ``c2w`` (judged by ``res`` against ``ref``) as the frame's tracked pose: the motion model and the
        brightness move on, and the keyframe decision is made."""
        self._losses = 0
        self._last_affine = res.affine
        self._remember(c2w)
        return TrackResult(c2w, False, relocalised, self._need_keyframe(res, c2w, ref), res.rmse, res.inlier_ratio,
                           res.visible_ratio, res.iterations, ms, ref.frame_index)

    def verify(self, rgb: np.ndarray, c2w: np.ndarray) -> Optional[TrackResult]:
        """Judge a pose of ``rgb`` found elsewhere (e.g. PnP on tracked landmarks) as :meth:`track` judges
        its own: the reference's points are warped into the frame at ``c2w`` (not moved; the brightness
        gain / offset fitted, :func:`~fmapping.tracking.direct_align.evaluate_pose`) and the same loss checks
        run against the motion model's prediction. Passed: the pose is taken as tracked (motion model,
        keyframe decision) and returned as a :class:`TrackResult`; failed: None, and nothing changes."""
        if self.reference is None:
            raise RuntimeError("DirectTracker.verify called before set_reference")
        t0 = time.perf_counter()
        ref, pred = self.reference, self.predict()
        c2w = orthonormalize(np.asarray(c2w, np.float64))
        res = evaluate_pose(ref, to_gray(rgb), self.camera, inv_pose(c2w) @ ref.c2w, self.cfg.align,
                            self._last_affine, mask=image_valid_mask(rgb))
        if self._check(res, c2w, pred, ref):
            return None
        return self._accept(res, c2w, ref, False, (time.perf_counter() - t0) * 1000.0)

    def _need_keyframe(self, res: AlignResult, c2w: np.ndarray, ref: Reference) -> bool:
        c = self.cfg
        dt, dr = pose_distance(ref.c2w, c2w)
        scale = ref.median_depth if np.isfinite(ref.median_depth) and ref.median_depth > 0 else 1.0
        return bool(
            res.visible_ratio < c.kf_min_visible or res.inlier_ratio < c.kf_min_inlier_ratio
            or dt > c.kf_max_translation_rel * scale or dr > c.kf_max_rotation_deg
        )
