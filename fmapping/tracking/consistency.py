"""How well a trajectory explains the images, independently of any tracker.

For frames with depth: corners of frame ``a``, tracked with KLT frame by frame up to frame
``b``, are back-projected with frame ``a``'s depth, moved by ``inv(c2w_b) @ c2w_a``,
projected, and compared with where KLT found them in ``b`` (:func:`reprojection_px`).
Poses that fit the images give a fraction of a pixel; a ground truth that does worse than
an estimate limits what ATE and rotation errors can tell apart.

:func:`fit_camera_rotation` fits one constant rotation ``X`` of the poses' camera frame
(``c2w @ X``: a hand-eye rotation of a motion-capture rig, or a principal point that is
off by ``f * angle`` pixels) that makes the poses explain the images best. A rotation of
the camera frame changes every relative rotation ``Q`` into ``X^T Q X``; it is observable
only through motions that do not share its axis, and more so over long frame gaps, so fit
it on pairs many frames apart. ``X`` about the axis of a single-axis motion stays
unobserved (it starts and stays near zero).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.tracking.features import KltConfig, detect_corners, klt_track, to_u8


@dataclass(frozen=True)
class TrackPair:
    a: int  # frame of the depth
    b: int  # frame where the points were found again
    points_a: np.ndarray  # (M, 3) camera-frame points of frame a (pixel rays times its depth)
    uv_b: np.ndarray  # (M, 2) where KLT found them in frame b


def depth_tracks(rgbs: Sequence[np.ndarray], depths: Sequence[np.ndarray], camera: PinholeCamera,
                 steps: Sequence[int] = (1,), start_every: int = 1,
                 klt: Optional[KltConfig] = None) -> list[TrackPair]:
    """Corners of every ``start_every``-th frame with valid depth, tracked frame by frame
    (KLT with its forward-backward check) and recorded ``steps`` frames later."""
    if min(steps) < 1:
        raise ValueError(f"steps must be >= 1 frame, got {list(steps)}")
    klt = klt or KltConfig()
    grey = [to_u8(x) for x in rgbs]
    k_inv = np.linalg.inv(camera.K)
    pairs = []
    for a in range(0, len(grey) - 1, start_every):
        uv0 = detect_corners(grey[a], klt).astype(np.float64)
        if len(uv0) == 0:
            continue
        ui = uv0[:, 0].round().astype(int).clip(0, camera.width - 1)
        vi = uv0[:, 1].round().astype(int).clip(0, camera.height - 1)
        z = np.asarray(depths[a], np.float64)[vi, ui]
        alive = np.isfinite(z) & (z > 0)
        cur = uv0
        for b in range(a + 1, min(len(grey), a + max(steps) + 1)):
            cur, ok = klt_track(grey[b - 1], grey[b], cur, klt)
            alive &= ok
            if b - a in steps and alive.any():
                pts = (np.c_[uv0[alive], np.ones(alive.sum())] @ k_inv.T) * z[alive, None]
                pairs.append(TrackPair(a, b, pts, np.asarray(cur[alive], np.float64)))
    return pairs


def _offset(rotation: Optional[np.ndarray]) -> np.ndarray:
    x = np.eye(4)
    if rotation is not None:
        x[:3, :3] = rotation
    return x


def _pixel_residuals(p: TrackPair, c2w: np.ndarray, x: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """(M, 2) projection of ``p.points_a`` into frame ``p.b`` minus the tracked pixels."""
    rel = np.linalg.inv(x) @ np.linalg.inv(c2w[p.b]) @ c2w[p.a] @ x
    q = (p.points_a @ rel[:3, :3].T + rel[:3, 3]) @ camera.K.T
    z = np.where(np.abs(q[:, 2:]) > 1e-9, q[:, 2:], 1e-9)
    return q[:, :2] / z - p.uv_b


def reprojection_errors(pairs: Sequence[TrackPair], c2w: np.ndarray, camera: PinholeCamera,
                        rotation: Optional[np.ndarray] = None) -> list[np.ndarray]:
    """Per pair, the pixel distance of each track from its point moved by the poses
    ``c2w`` (N, 4, 4), with the camera frame rotated by ``rotation`` (``c2w @ X``) if given."""
    x = _offset(rotation)
    c2w = np.asarray(c2w, np.float64)
    return [np.linalg.norm(_pixel_residuals(p, c2w, x, camera), axis=1) for p in pairs]


def reprojection_px(pairs: Sequence[TrackPair], c2w: np.ndarray, camera: PinholeCamera,
                    rotation: Optional[np.ndarray] = None) -> dict:
    """``median_px`` / ``mean_px`` over the pairs of the per-pair median distance."""
    per_pair = [np.median(e) for e in reprojection_errors(pairs, c2w, camera, rotation) if len(e)]
    return {"median_px": float(np.median(per_pair)), "mean_px": float(np.mean(per_pair)), "pairs": len(per_pair)}


def fit_camera_rotation(pairs: Sequence[TrackPair], c2w: np.ndarray, camera: PinholeCamera,
                        axes: str = "xyz", huber_px: float = 1.0) -> np.ndarray:
    """The rotation ``X`` (3, 3) about the camera ``axes`` (a subset of ``"xyz"``) for which
    ``c2w @ X`` explains the tracks best (robust least squares, Huber at ``huber_px``)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    idx = ["xyz".index(a) for a in axes]
    c2w = np.asarray(c2w, np.float64)

    def rot(y: np.ndarray) -> np.ndarray:
        v = np.zeros(3)
        v[idx] = y
        return Rotation.from_rotvec(v).as_matrix()

    def residual(y: np.ndarray) -> np.ndarray:
        x = _offset(rot(y))
        return np.concatenate([_pixel_residuals(p, c2w, x, camera).ravel() for p in pairs])

    sol = least_squares(residual, np.zeros(len(idx)), loss="huber", f_scale=huber_px)
    return rot(sol.x)
