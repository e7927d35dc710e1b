"""Loop closure for the monocular front end: find an old keyframe the camera has come back to,
verify it on the old keyframe's landmarks, and say where the current keyframe is in the old map.

1. **Candidates** (:func:`loop_candidates`): old keyframes (at least ``min_frames_apart``
   frames back) whose estimated camera centre is within ``max_distance`` (times the median
   scene depth) and whose viewing direction is within ``max_angle_deg`` of the current
   keyframe's. The estimate has drifted, but by centimetres where the room is metres across:
   pose proximity is enough to propose a loop, the images decide it.
2. **Verification** (:func:`locate_in_keyframe`): the landmarks the old keyframe observed are
   projected into the current keyframe with its (drifted) pose as KLT's guess and tracked from
   the old keyframe's image, rotated into the current view first; PnP + RANSAC on their world
   positions gives the current keyframe's pose in the old map. Accepted with at least
   ``min_inliers`` inliers making up ``min_inlier_ratio`` of the tracked points.
3. **Cross-check** (:func:`cross_check`): the same the other way round, the current keyframe's
   own landmarks located in the old keyframe's image, gives the relative pose a second time from
   structure the first measurement did not use; the loop is accepted only when the two agree within
   ``max_cross_deg`` and ``max_cross_dist`` (times the median depth). Repeated texture and a few wrong
   landmarks can give a PnP pose with enough inliers that is degrees off (a real kitchen: loops whose
   relative pose the GT puts 30-40 cm and 7-9 deg away).

The correction itself (a pose graph over the keyframes of the loop,
:mod:`fmapping.tracking.posegraph`, then a bundle adjustment with the loop's matches) is
applied by :class:`~fmapping.tracking.mono.MonoFrontend`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import inv_pose
from fmapping.tracking.features import REFERENCE_WIDTH, KltConfig, at_width, klt_track, pnp_ransac


@dataclass
class LoopConfig:
    enabled: bool = True
    min_frames_apart: int = 60  # a candidate is at least this many frames older than the current keyframe
    max_distance: float = 0.3  # camera centres this close (times the median scene depth) ...
    max_angle_deg: float = 30.0  # ... and optical axes this close make a candidate
    max_candidates: int = 2  # nearest candidates verified per keyframe
    min_points: int = 40  # old landmarks projecting into the current keyframe needed to try
    min_inliers: int = 40
    min_inlier_ratio: float = 0.5
    inlier_px: float = 2.0  # PnP inlier threshold, per 320 pixels of image width
    min_correction_m: float = 0.002  # below this (times the median depth) and ...
    min_correction_deg: float = 0.1  # ... this, the loop agrees with the chain: nothing to correct
    # After the pose graph, bundle-adjust the keyframes of the loop with the loop's matches as observations
    # of the old landmarks: the pose graph bends the chain's relative poses, the BA makes them agree with the
    # images again while the matches hold the loop closed.
    loop_ba: bool = True
    loop_ba_max_nfev: int = 15
    # The BA's cost grows with the loop (dense camera-point coupling; a 35-keyframe loop of a synthetic room
    # took 0.8 s of the 0.9 s a closure costs on one core): longer loops get the pose graph alone.
    loop_ba_max_keyframes: int = 50
    loop_ba_keep_scale: bool = True  # scale the BA's result about the first keyframe back to the pose graph's size
    max_correction: float = 0.5  # a correction moving the keyframe more (times the median depth) is refused
    max_keyframe_images: int = 400  # keyframe images kept for verification (the oldest go first)
    # Loops whose relative pose from the old keyframe's landmarks and from the current keyframe's own
    # landmarks (located in the old image) differ by more than this rotation or translation (times the
    # median depth) are refused (cross_check); inf: no cross-check.
    max_cross_deg: float = 2.0
    max_cross_dist: float = 0.05

    def validate(self) -> None:
        if self.min_frames_apart < 1 or self.max_distance <= 0 or not 0 < self.max_angle_deg <= 180:
            raise ValueError("mono.loop: min_frames_apart >= 1, max_distance > 0, 0 < max_angle_deg <= 180")


def _axis(c2w: np.ndarray) -> np.ndarray:
    return np.asarray(c2w)[:3, 2]


def loop_candidates(kf_poses: dict, current: int, scale: float, cfg: LoopConfig) -> list[int]:
    """Keyframes of ``kf_poses`` ({frame: c2w}) that may close a loop with keyframe ``current``,
    nearest first. ``scale``: the median scene depth (the unit of ``cfg.max_distance``)."""
    cur = kf_poses[current]
    found = []
    for k, p in kf_poses.items():
        if k > current - cfg.min_frames_apart:
            continue
        dist = float(np.linalg.norm(p[:3, 3] - cur[:3, 3])) / scale
        ang = math.degrees(math.acos(float(np.clip(_axis(p) @ _axis(cur), -1.0, 1.0))))
        if dist <= cfg.max_distance and ang <= cfg.max_angle_deg:
            found.append((dist / cfg.max_distance + ang / cfg.max_angle_deg, k))
    return [k for _, k in sorted(found)[: cfg.max_candidates]]


@dataclass
class LoopMatch:
    c2w: np.ndarray  # the current keyframe's pose in the old keyframe's map
    points: int  # old landmarks tracked into the current keyframe
    inliers: int
    index: np.ndarray  # (inliers,) which of the old keyframe's points are the inliers ...
    uv: np.ndarray  # (inliers, 2) ... and where they are in the current image


def rotation_homography(camera: PinholeCamera, c2w_from: np.ndarray, c2w_to: np.ndarray) -> np.ndarray:
    """3x3 homography taking pixels of a camera at ``c2w_from`` to one at ``c2w_to`` for points
    at infinity (the rotation between them alone): ``K R_to^T R_from K^-1``."""
    k = camera.K
    return k @ (np.asarray(c2w_to)[:3, :3].T @ np.asarray(c2w_from)[:3, :3]) @ np.linalg.inv(k)


def locate_in_keyframe(camera: PinholeCamera, old_gray: np.ndarray, old_uv: np.ndarray, old_world: np.ndarray,
                       old_c2w: np.ndarray, gray: np.ndarray, c2w_guess: np.ndarray, klt: KltConfig,
                       cfg: LoopConfig) -> Optional[LoopMatch]:
    """The pose of the image ``gray`` in the map of an old keyframe (image ``old_gray``, pose
    ``old_c2w``, which saw world points ``old_world`` (N, 3) at pixels ``old_uv``), or None
    when the images disagree. The old image is first rotated into the current view
    (:func:`rotation_homography`): KLT's patches then differ by the parallax alone (on a
    synthetic room with 15 deg between the views, 159 of 163 points tracked instead of 54)."""
    guess, z = camera.world_to_pixels(c2w_guess, old_world)
    inside = (z > 1e-6) & (guess[:, 0] >= 0) & (guess[:, 0] <= camera.width - 1) \
        & (guess[:, 1] >= 0) & (guess[:, 1] <= camera.height - 1)
    if inside.sum() < cfg.min_points:
        return None
    h = rotation_homography(camera, old_c2w, c2w_guess)
    warped = cv2.warpPerspective(old_gray, h, (camera.width, camera.height), flags=cv2.INTER_LINEAR)
    q = np.c_[old_uv[inside], np.ones(int(inside.sum()))] @ h.T
    q = q[:, :2] / q[:, 2:]
    b = klt.border
    keep = (q[:, 0] >= b) & (q[:, 0] <= camera.width - 1 - b) & (q[:, 1] >= b) & (q[:, 1] <= camera.height - 1 - b)
    if keep.sum() < cfg.min_points:
        return None
    idx = np.flatnonzero(inside)[keep]
    x, q, guess = old_world[idx], q[keep], guess[inside][keep]
    uv1, ok = klt_track(warped, gray, q, klt, guess=guess)
    if ok.sum() < cfg.min_points:
        return None
    idx, x, uv1 = idx[ok], x[ok], uv1[ok].astype(np.float64)
    found = pnp_ransac(camera, x, uv1, at_width(cfg.inlier_px, max(camera.width, REFERENCE_WIDTH)))
    if found is None:
        return None
    w2c, inl = found
    n = int(inl.sum())
    if n < cfg.min_inliers or n < cfg.min_inlier_ratio * len(x):
        return None
    return LoopMatch(inv_pose(w2c), len(x), n, idx[inl], uv1[inl])


def rotation_deg(r: np.ndarray) -> float:
    """Angle (degrees) of a 3x3 rotation."""
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def cross_check(camera: PinholeCamera, old_gray: np.ndarray, old_c2w: np.ndarray, match: LoopMatch,
                gray: np.ndarray, uv: np.ndarray, world: np.ndarray, c2w: np.ndarray, klt: KltConfig,
                cfg: LoopConfig) -> Optional[tuple[float, float]]:
    """How far the loop ``match`` (the current keyframe at ``match.c2w`` in the map of the old keyframe,
    image ``old_gray``, pose ``old_c2w``) is from the same loop measured the other way round: the
    current keyframe (image ``gray``, pose ``c2w`` in its own, drifted map, in which it saw the world
    points ``world`` (N, 3) at pixels ``uv``) located in the old image with :func:`locate_in_keyframe`.
    Returns (degrees between the two relative rotations, distance between the two relative
    translations in the old map's units), or None when the other way finds no pose (the loop is not
    confirmed). The translations differ by the two maps' scale drift times the loop's length as well."""
    rel = inv_pose(old_c2w) @ match.c2w  # current keyframe in the old one's camera frame
    back = locate_in_keyframe(camera, gray, uv, world, c2w, old_gray, c2w @ inv_pose(rel), klt, cfg)
    if back is None:
        return None
    rel_back = inv_pose(back.c2w) @ c2w
    return rotation_deg(rel[:3, :3].T @ rel_back[:3, :3]), float(np.linalg.norm(rel[:3, 3] - rel_back[:3, 3]))
