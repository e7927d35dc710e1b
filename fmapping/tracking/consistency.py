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

:func:`best_explaining_poses` asks the question without a tracker in the way: the
trajectory that explains multi-frame KLT tracks (:func:`frame_tracks`) best, a bundle
adjustment of every frame and every track started from given poses (the ground truth, say).
Its result is what the images determine, up to a similarity; when it lands at the same
poses from different starts, no tracker can do better from the images. A target that even
this optimum misses cannot be met from the images alone, except by chance.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.tracking.ba import bundle_adjust
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


@dataclass(frozen=True)
class FrameTracks:
    """KLT tracks over many frames, one row per observation."""
    frame: np.ndarray  # (O,) frame index
    track: np.ndarray  # (O,) track index, 0 .. tracks - 1
    uv: np.ndarray  # (O, 2) pixel

    @property
    def tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0


def frame_tracks(rgbs: Sequence[np.ndarray], klt: Optional[KltConfig] = None, start_every: int = 3,
                 max_length: int = 30, min_length: int = 3) -> FrameTracks:
    """Corners of every ``start_every``-th frame followed frame by frame with KLT (forward-backward
    check) for up to ``max_length`` frames; tracks seen in fewer than ``min_length`` frames dropped."""
    if start_every < 1 or max_length < 2 or min_length < 2:
        raise ValueError(f"start_every >= 1, max_length >= 2 and min_length >= 2 needed, got "
                         f"{start_every}, {max_length}, {min_length}")
    klt = klt or KltConfig()
    grey = [to_u8(x) for x in rgbs]
    frame, track, uvs = [], [], []
    next_id = 0
    for a in range(0, len(grey) - 1, start_every):
        uv = detect_corners(grey[a], klt).astype(np.float64)
        ids = np.arange(next_id, next_id + len(uv))
        next_id += len(uv)
        frame.append(np.full(len(uv), a))
        track.append(ids)
        uvs.append(uv)
        for b in range(a + 1, min(len(grey), a + max_length)):
            if not len(uv):
                break
            uv, ok = klt_track(grey[b - 1], grey[b], uv, klt)
            uv, ids = np.asarray(uv[ok], np.float64), ids[ok]
            frame.append(np.full(len(uv), b))
            track.append(ids)
            uvs.append(uv)
    if not next_id:
        return FrameTracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    frame, track, uv = np.concatenate(frame), np.concatenate(track), np.concatenate(uvs)
    long = np.bincount(track, minlength=next_id)[track] >= min_length
    _, track = np.unique(track[long], return_inverse=True)
    return FrameTracks(frame[long].astype(np.int64), track.astype(np.int64), uv[long])


def best_explaining_poses(camera: PinholeCamera, tracks: FrameTracks, c2w_start: np.ndarray,
                          depths: Sequence[np.ndarray], huber_px: float = 2.0, max_nfev: int = 200,
                          fixed: Sequence[int] = (0,)) -> tuple[np.ndarray, dict]:
    """Bundle adjustment of every frame and every track on the reprojection error, started from
    ``c2w_start`` (N, 4, 4) with the frames ``fixed`` held. The depth only places the points to
    start from: each track's at its first observation with a reading in ``depths`` (N x (H, W)
    metres, 0 = none; tracks never seen with depth are dropped). With frame 0 alone fixed the
    result is what the images determine, up to its scale (the seventh degree of freedom):
    compare it after a Sim3 alignment or by its rotations. Returns the poses (N, 4, 4) and
    ``{"tracks", "observations", "cost", "cost_start", "median_px", "nfev"}``."""
    c2w_start = np.asarray(c2w_start, np.float64)
    n = len(c2w_start)
    if len(depths) != n or (len(tracks.frame) and tracks.frame.max() >= n):
        raise ValueError(f"{n} start poses, {len(depths)} depth images and tracks up to frame "
                         f"{int(tracks.frame.max()) if len(tracks.frame) else -1}: they must cover the same frames")
    ui = tracks.uv[:, 0].round().astype(np.int64).clip(0, camera.width - 1)
    vi = tracks.uv[:, 1].round().astype(np.int64).clip(0, camera.height - 1)
    z = np.stack([np.asarray(d, np.float32) for d in depths])[tracks.frame, vi, ui].astype(np.float64)
    z = np.where(np.isfinite(z) & (z > 0), z, 0.0)
    first = np.full(tracks.tracks, -1, np.int64)  # each track's first observation with depth
    o = np.flatnonzero(z > 0)
    o = o[np.lexsort((tracks.frame[o], tracks.track[o]))]
    starts = np.r_[True, tracks.track[o][1:] != tracks.track[o][:-1]] if len(o) else np.zeros(0, bool)
    first[tracks.track[o[starts]]] = o[starts]
    keep_track = first >= 0
    obs = keep_track[tracks.track]
    if keep_track.sum() < 10:
        raise ValueError(f"only {int(keep_track.sum())} tracks have a depth reading to start from")
    o1 = first[keep_track]
    rays = np.c_[tracks.uv[o1], np.ones(len(o1))] @ np.linalg.inv(camera.K).T * z[o1, None]
    pose1 = c2w_start[tracks.frame[o1]]
    points = np.einsum("nij,nj->ni", pose1[:, :3, :3], rays) + pose1[:, :3, 3]
    remap = np.cumsum(keep_track) - 1
    frame, track, uv = tracks.frame[obs], remap[tracks.track[obs]], tracks.uv[obs]
    res = bundle_adjust(camera, list(c2w_start), list(fixed), points, frame, track, uv, huber_px, max_nfev)
    info = {"tracks": int(keep_track.sum()), "observations": int(len(frame)), "cost": float(res.cost_after),
            "cost_start": float(res.cost_before),
            "median_px": float(np.median(res.residual_px)), "nfev": int(res.nfev)}
    return np.stack(res.poses), info
