"""Sparse scene points from the images and their poses: KLT tracks triangulated with known poses.

The mapper needs to know where the scene is before its field can represent it (the box) and,
on weakly textured surfaces, where along a ray the surface lies (the photometric losses leave
that ambiguous there). Both come from the same sparse points, made from what any user has:
the frames and the poses the mapper is given (ground truth, a trajectory file or the tracker).

:class:`TrackTriangulator` is fed frame by frame (``add``). Corners are followed from frame to
frame with KLT (forward-backward checked); a track that ends, or reaches ``max_track``
observations, is triangulated over all its views at once (least-squares ray intersection),
kept when it lies in front of every camera, reprojects within ``max_reproj_px`` everywhere
and its rays span at least ``min_parallax_deg``. Its weight comes from its expected relative
depth error ``sigma = rms / (focal * parallax)`` (``rms``: its reprojection error over its views,
at least ``min_rms_px``; parallax in radians): ``1 / (1 + (sigma / sigma_ref)^2)``. The residual
is what tells a good track from one that drifted on blurred, noisy or low-contrast images: on a
sharp, textured synthetic room the points' median rms is 0.13 px and their median distance to
the true surface 1.3 % of their depth; on a blurred, low-contrast one (``fmapping synth
--variety wide --seed 1``) 0.65 px and 11 %, with GT poses in both.

Each kept point remembers the pixels it was seen at, so that a frame's sparse depth
(``frame_depths``) can be read with the frame's *current* pose.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.tracking.features import KltConfig, at_width, detect_corners, klt_track_gain, to_u8


@dataclass
class SparsePointsConfig:
    max_corners: int = 1000  # corners tracked at a time
    min_track: int = 3  # observations a track needs to be triangulated
    max_track: int = 15  # a track is triangulated (and restarted) after this many observations
    min_parallax_deg: float = 1.5  # rays of a point must span at least this angle
    sigma_ref: float = 0.01  # expected relative depth error at which a point's weight is 1/2
    min_rms_px: float = 0.1  # floor of the reprojection rms in the depth error (at 320 px width)
    max_reproj_px: float = 1.5  # at 320 px image width (scaled with the width)
    half_window: int = 7  # KLT half window at 320 px width
    min_distance: int = 8  # pixels between corners at 320 px width
    # depth filled in between a frame's points (fill_depths), pixel sizes at 320 px width
    fill_step_px: float = 8.0  # grid step of the filled pixels
    fill_max_edge_px: float = 40.0  # longest triangle edge used: larger ones bridge too much unknown surface
    fill_max_ratio: float = 1.1  # largest / smallest corner depth of a triangle used (no depth edges)

    def validate(self) -> None:
        if self.max_corners < 1 or self.min_track < 2 or self.max_track < self.min_track:
            raise ValueError("SparsePointsConfig: need max_corners >= 1 and 2 <= min_track <= max_track")
        if not (self.min_parallax_deg > 0 and self.sigma_ref > 0 and self.min_rms_px > 0):
            raise ValueError("SparsePointsConfig: min_parallax_deg, sigma_ref and min_rms_px must be > 0")
        if not self.max_reproj_px > 0:
            raise ValueError("SparsePointsConfig.max_reproj_px must be > 0")
        if not (self.fill_step_px > 0 and self.fill_max_edge_px > 0 and self.fill_max_ratio >= 1):
            raise ValueError("SparsePointsConfig: need fill_step_px > 0, fill_max_edge_px > 0, fill_max_ratio >= 1")


def triangulate_rays(centres: np.ndarray, dirs: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Least-squares intersection of rays, batched over tracks.

    ``centres`` (T, K, 3) ray origins, ``dirs`` (T, K, 3) directions (any length), ``valid``
    (T, K) which of the K rays of each track count. Returns (T, 3) points minimising the
    summed squared distance to the valid rays (NaN where they are parallel)."""
    d = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    proj = np.eye(3) - d[..., :, None] * d[..., None, :]  # (T, K, 3, 3): removes the ray direction
    proj = proj * valid[..., None, None]
    a = proj.sum(1)
    b = np.einsum("tkij,tkj->ti", proj, centres)
    ok = np.abs(np.linalg.det(a)) > 1e-12
    out = np.full((len(a), 3), np.nan)
    if ok.any():
        out[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    return out


class TrackTriangulator:
    """Incremental KLT tracks over the frames given to :meth:`add`, triangulated with their poses."""

    def __init__(self, camera: PinholeCamera, cfg: Optional[SparsePointsConfig] = None):
        self.camera = camera
        self.cfg = cfg or SparsePointsConfig()
        self.cfg.validate()
        w = camera.width
        self._klt = KltConfig(max_corners=self.cfg.max_corners, half_window=self.cfg.half_window,
                              min_distance=max(3, int(round(at_width(self.cfg.min_distance, w)))))
        self._reproj = at_width(self.cfg.max_reproj_px, w)
        self._grey: Optional[np.ndarray] = None
        self._gain = 1.0  # exposure of the last frame over the one before
        self._last_fid: Optional[int] = None
        self._uv = np.zeros((0, 2), np.float64)  # current pixel of each live track
        self._obs: list[list[tuple[int, np.ndarray]]] = []  # per live track: [(frame id, uv)]
        self._poses: dict[int, np.ndarray] = {}
        self.points = np.zeros((0, 3))  # (N, 3) world points
        self.weights = np.zeros(0)  # (N,) in (0, 1]
        # frame id -> (point indices (M,) int64, pixels (M, 2) float64): compact, it grows with the sequence
        self._frame_obs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.frame_ids: list[int] = []
        self._cuts: dict[int, dict[tuple[float, int], float]] = {}  # frame id -> {(quantile, min points): depth}

    # -------------------------------------------------------------- input
    def add(self, fid: int, rgb: np.ndarray, c2w: np.ndarray) -> None:
        """Follow the live tracks into frame ``fid`` (pose ``c2w``), triangulate those that end."""
        grey = to_u8(rgb)
        self._poses[fid] = np.asarray(c2w, np.float64)
        self.frame_ids.append(fid)
        if self._grey is not None and len(self._uv):
            # the last step's exposure change predicts this one's (klt_track_gain measures and corrects it)
            uv, ok, self._gain = klt_track_gain(self._grey, grey, self._uv.astype(np.float32), self._klt,
                                                gain=self._gain)
            ended = [o for o, k in zip(self._obs, ok) if not k]
            self._obs = [o for o, k in zip(self._obs, ok) if k]
            self._uv = np.asarray(uv[ok], np.float64)
            for o, p in zip(self._obs, self._uv):
                o.append((fid, p.copy()))
            full = np.array([len(o) >= self.cfg.max_track for o in self._obs], bool)
            if full.any():
                ended += [o for o, f in zip(self._obs, full) if f]
                self._obs = [o for o, f in zip(self._obs, full) if not f]
                self._uv = self._uv[~full]
            self._triangulate(ended)
        new = detect_corners(grey, self._klt, self._uv if len(self._uv) else None).astype(np.float64)
        if len(new):
            self._uv = np.concatenate([self._uv, new]) if len(self._uv) else new
            self._obs += [[(fid, p.copy())] for p in new]
        self._grey = grey
        self._last_fid = fid

    def set_poses(self, poses: dict) -> None:
        """Newer poses of frames already added (used by the tracks still live and by ``frame_depths``)."""
        for fid, c2w in poses.items():
            if fid in self._poses:
                self._poses[fid] = np.array(c2w, np.float64)
                self._cuts.pop(fid, None)

    def flush(self) -> None:
        """Triangulate every live track now (the tracks restart at the next frame)."""
        self._triangulate(self._obs)
        self._obs = [[(self._last_fid, p.copy())] for p in self._uv] if self._last_fid is not None else []

    # -------------------------------------------------------------- output
    def frame_depths(self, fid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sparse depth of frame ``fid``: pixels (M, 2), camera depths (M,) of its triangulated points
        under the frame's current pose, weights (M,). Empty arrays when it has none."""
        obs = self._frame_obs.get(fid)
        if obs is None:
            return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
        idx, uv = obs
        c2w = self._poses[fid]
        z = (self.points[idx] - c2w[:3, 3]) @ c2w[:3, 2]
        ok = z > 1e-6
        return uv[ok], z[ok], self.weights[idx][ok]

    def depth_quantile(self, fid: int, quantile: float = 50.0, min_points: int = 10) -> float:
        """The ``quantile`` of frame ``fid``'s sparse depths (:meth:`frame_depths`); NaN with fewer than
        ``min_points``. Kept until the frame's points or pose change: the scene box asks for every frame's
        at every window, so its cost must not grow with the sequence."""
        cuts = self._cuts.setdefault(int(fid), {})
        key = (float(quantile), int(min_points))
        if key not in cuts:
            z = self.frame_depths(fid)[1]
            cuts[key] = float(np.percentile(z, quantile)) if len(z) >= min_points else float("nan")
        return cuts[key]

    def frame_fill(self, fid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depth filled in between frame ``fid``'s points (:func:`fill_depths`): pixels, depths, weights."""
        uv, z, w = self.frame_depths(fid)
        width, cfg = self.camera.width, self.cfg
        return fill_depths(uv, z, w, width, self.camera.height, at_width(cfg.fill_step_px, width),
                           at_width(cfg.fill_max_edge_px, width), cfg.fill_max_ratio)

    # -------------------------------------------------------------- state
    def state_dict(self) -> dict:
        """Everything needed to go on exactly (tensors and plain python, for ``torch.load(weights_only=True)``).

        The tracks' observations, the per-frame observations and the poses are packed into a few flat
        tensors each: ``torch.save`` costs ~40 us a tensor, and one small tensor per observation made a
        48-frame mapper's checkpoint take ~0.3 s."""
        import torch

        t = torch.from_numpy
        lens = np.array([len(o) for o in self._obs], np.int64)
        flat = [ob for o in self._obs for ob in o]
        fo_ids = sorted(self._frame_obs)
        fo = [self._frame_obs[k] for k in fo_ids]
        pose_ids = sorted(self._poses)
        return {
            "grey": None if self._grey is None else t(self._grey.copy()),
            "gain": float(self._gain),
            "last_fid": self._last_fid,
            "uv": t(self._uv.copy()),
            "obs": {"lengths": t(lens),
                    "frames": t(np.array([f for f, _ in flat], np.int64)),
                    "uv": t(np.array([uv for _, uv in flat], np.float64).reshape(-1, 2))},
            "poses": {"ids": t(np.array(pose_ids, np.int64)),
                      "c2w": t(np.array([self._poses[k] for k in pose_ids], np.float64).reshape(-1, 4, 4))},
            "points": t(self.points.copy()),
            "weights": t(self.weights.copy()),
            "frame_obs": {"ids": t(np.array(fo_ids, np.int64)),
                          "lengths": t(np.array([len(i) for i, _ in fo], np.int64)),
                          "points": t(np.concatenate([i for i, _ in fo]).astype(np.int64) if fo
                                      else np.zeros(0, np.int64)),
                          "uv": t(np.concatenate([uv for _, uv in fo]).reshape(-1, 2).astype(np.float64) if fo
                                  else np.zeros((0, 2)))},
            "frame_ids": list(self.frame_ids),
        }

    def load_state_dict(self, d: dict) -> None:
        self._grey = None if d["grey"] is None else d["grey"].numpy().copy()
        self._gain = float(d.get("gain", 1.0))
        self._last_fid = d["last_fid"]
        self._uv = d["uv"].numpy().copy()
        self.points = d["points"].numpy().copy()
        self.weights = d["weights"].numpy().copy()
        self.frame_ids = list(d["frame_ids"])
        obs, poses, fobs = d["obs"], d["poses"], d["frame_obs"]
        if isinstance(obs, dict):  # packed (state_dict above)
            frames, uv = obs["frames"].numpy(), obs["uv"].numpy()
            cuts = np.concatenate([[0], np.cumsum(obs["lengths"].numpy())])
            self._obs = [[(int(frames[j]), uv[j].copy()) for j in range(a, b)] for a, b in zip(cuts[:-1], cuts[1:])]
            self._poses = {int(k): c.copy() for k, c in zip(poses["ids"].numpy(), poses["c2w"].numpy())}
            cuts = np.concatenate([[0], np.cumsum(fobs["lengths"].numpy())])
            pts, fuv = fobs["points"].numpy(), fobs["uv"].numpy()
            self._frame_obs = {int(k): (pts[a:b].copy(), fuv[a:b].copy())
                               for k, a, b in zip(fobs["ids"].numpy(), cuts[:-1], cuts[1:])}
        else:  # a checkpoint written before the packing: one tensor per observation, pose and frame
            self._obs = [[(int(f), uv.numpy().copy()) for f, uv in o] for o in obs]
            self._poses = {int(k): v.numpy().copy() for k, v in poses.items()}
            self._frame_obs = {int(k): (np.asarray(i, np.int64).reshape(-1).copy(),
                                        np.asarray(uv, np.float64).reshape(-1, 2).copy())
                               for k, (i, uv) in fobs.items()}
        self._cuts = {}

    # -------------------------------------------------------------- triangulation
    def _triangulate(self, tracks: list) -> None:
        tracks = [t for t in tracks if len(t) >= self.cfg.min_track]
        if not tracks:
            return
        cam = self.camera
        k = max(len(t) for t in tracks)
        n = len(tracks)
        centres = np.zeros((n, k, 3))
        dirs = np.zeros((n, k, 3))
        dirs[..., 2] = 1.0
        uvs = np.zeros((n, k, 2))
        fids = np.full((n, k), -1)
        valid = np.zeros((n, k), bool)
        for ti, t in enumerate(tracks):
            for j, (fid, uv) in enumerate(t):
                c2w = self._poses[fid]
                ray = np.array([(uv[0] - cam.cx) / cam.fx, (uv[1] - cam.cy) / cam.fy, 1.0])
                centres[ti, j] = c2w[:3, 3]
                dirs[ti, j] = c2w[:3, :3] @ ray
                uvs[ti, j] = uv
                fids[ti, j] = fid
                valid[ti, j] = True
        x = triangulate_rays(centres, dirs, valid)
        ok = np.isfinite(x).all(1)
        xs = np.where(ok[:, None], x, 0.0)
        # reprojection and cheirality in every view
        rel = xs[:, None, :] - centres  # (n, k, 3) in world axes
        r_t = np.stack([self._poses[f][:3, :3] if f >= 0 else np.eye(3) for f in fids.reshape(-1)]).reshape(n, k, 3, 3)
        pc = np.einsum("nkji,nkj->nki", r_t, rel)  # world -> camera: R^T (x - c)
        z = pc[..., 2]
        front = (z > 1e-6) | ~valid
        zs = np.where(z > 1e-6, z, 1.0)
        proj = np.stack([cam.fx * pc[..., 0] / zs + cam.cx, cam.fy * pc[..., 1] / zs + cam.cy], -1)
        err = np.linalg.norm(proj - uvs, axis=-1)
        ok &= front.all(1) & np.where(valid, err < self._reproj, True).all(1)
        # parallax: the widest angle between any two of the point's rays
        u = rel / np.maximum(np.linalg.norm(rel, axis=-1, keepdims=True), 1e-12)
        cos = np.einsum("nai,nbi->nab", u, u)
        cos = np.where(valid[:, :, None] & valid[:, None, :], cos, 1.0)
        par = np.degrees(np.arccos(np.clip(cos.min((1, 2)), -1.0, 1.0)))
        ok &= par >= self.cfg.min_parallax_deg
        if not ok.any():
            return
        base = len(self.points)
        keep = np.flatnonzero(ok)
        self.points = np.concatenate([self.points, x[keep]])
        self.weights = np.concatenate([self.weights, point_weights(err[keep], valid[keep], par[keep], cam.fx,
                                                                   at_width(self.cfg.min_rms_px, cam.width),
                                                                   self.cfg.sigma_ref)])
        # the kept tracks' observations, appended to each frame's arrays in the tracks' order
        rows = valid[keep]
        obs_fid, obs_idx, obs_uv = fids[keep][rows], np.broadcast_to(base + np.arange(len(keep))[:, None],
                                                                     rows.shape)[rows], uvs[keep][rows]
        order = np.argsort(obs_fid, kind="stable")
        obs_fid, obs_idx, obs_uv = obs_fid[order], obs_idx[order], obs_uv[order]
        starts = np.flatnonzero(np.r_[True, obs_fid[1:] != obs_fid[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(obs_fid)]):
            fid = int(obs_fid[a])
            idx, pix = self._frame_obs.get(fid, (np.zeros(0, np.int64), np.zeros((0, 2))))
            self._frame_obs[fid] = (np.concatenate([idx, obs_idx[a:b]]), np.concatenate([pix, obs_uv[a:b]]))
            self._cuts.pop(fid, None)


def point_weights(err: np.ndarray, valid: np.ndarray, parallax_deg: np.ndarray, focal: float, min_rms: float,
                  sigma_ref: float) -> np.ndarray:
    """Confidence in (0, 1] of triangulated points from their reprojection errors ``err`` (N, K) px over
    the ``valid`` (N, K) views and their parallax: ``1 / (1 + (sigma / sigma_ref)^2)`` with the expected
    relative depth error ``sigma = max(rms, min_rms) / (focal * radians(parallax))``."""
    n = np.maximum(valid.sum(1), 1)
    rms = np.sqrt((np.where(valid, err, 0.0) ** 2).sum(1) / n)
    sigma = np.maximum(rms, min_rms) / (focal * np.radians(np.maximum(parallax_deg, 1e-6)))
    return 1.0 / (1.0 + (sigma / sigma_ref) ** 2)


def fill_depths(uv: np.ndarray, z: np.ndarray, w: np.ndarray, width: int, height: int, step: float,
                max_edge_px: float, max_ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth between a frame's sparse points: a regular pixel grid (``step`` px) read off the image
    Delaunay triangulation of the points ``uv`` (M, 2) with depths ``z`` (M,) and weights ``w``.

    Inverse depth is interpolated linearly inside each triangle, which is exact where the three
    points lie on one plane (1/z is affine in the pixel coordinates on a plane): walls, cabinet
    fronts and floors, the surfaces that have no texture of their own between their corners.
    Only small triangles (longest edge <= ``max_edge_px``) whose corners agree in depth
    (largest / smallest <= ``max_ratio``) are used, so a triangle spanning a depth edge gives
    nothing. Returns grid pixels (K, 2), their depths (K,) and weights (K,: the smallest corner
    weight)."""
    empty = np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    if len(z) < 3:
        return empty
    from scipy.spatial import Delaunay, QhullError

    try:
        tri = Delaunay(uv)
    except (QhullError, ValueError):  # all points on a line, or too few distinct ones
        return empty
    s = tri.simplices
    corners = uv[s]  # (T, 3, 2)
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1).max(-1)
    zc = z[s]
    good = (edges <= max_edge_px) & (zc.max(-1) <= max_ratio * zc.min(-1))
    if not good.any():
        return empty
    gx, gy = np.meshgrid(np.arange(step / 2, width, step), np.arange(step / 2, height, step))
    grid = np.stack([gx.ravel(), gy.ravel()], -1)
    simplex = tri.find_simplex(grid)
    inside = simplex >= 0
    inside[inside] = good[simplex[inside]]
    grid, simplex = grid[inside], simplex[inside]
    if not len(grid):
        return empty
    tr = tri.transform[simplex]  # barycentric coordinates: T (x - r)
    b = np.einsum("kij,kj->ki", tr[:, :2], grid - tr[:, 2])
    bary = np.concatenate([b, 1 - b.sum(-1, keepdims=True)], -1)
    inv = (bary / zc[simplex]).sum(-1)
    return grid, 1.0 / inv, w[s[simplex]].min(-1)


def aabb_from_points(points: np.ndarray, centres: Optional[np.ndarray] = None, percentile: float = 0.5,
                     margin: float = 0.1, rel_margin: float = 0.1) -> Optional[np.ndarray]:
    """Box (2, 3) around scene points (robust ``percentile`` / ``100 - percentile`` per axis), the
    camera ``centres`` and a margin of ``max(margin, rel_margin * extent)`` per axis; None for
    fewer than 20 points."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)]
    if len(pts) < 20:
        return None
    lo = np.percentile(pts, percentile, axis=0)
    hi = np.percentile(pts, 100.0 - percentile, axis=0)
    if centres is not None and len(centres):
        c = np.asarray(centres, np.float64).reshape(-1, 3)
        lo, hi = np.minimum(lo, c.min(0)), np.maximum(hi, c.max(0))
    pad = np.maximum(margin, rel_margin * (hi - lo))
    return np.stack([lo - pad, hi + pad])


def seen_depth_box(c2w: np.ndarray, depths: list, camera: PinholeCamera, quantile: float = 50.0,
                   stretch: float = 1.0, min_points: int = 10) -> Optional[np.ndarray]:
    """Box (2, 3) of the view frusta of cameras ``c2w`` (N, 4, 4), each cut at the typical depth of its own
    sparse points (``quantile`` of ``depths[i]``, times ``stretch``); frames with fewer than
    ``min_points`` depths take the median cut of the others. Where texture is too weak for points
    (a plain upper wall, a ceiling), the camera still saw the scene out to about that depth: the box
    must hold it. None when no frame has enough depths."""
    cuts = np.array([np.percentile(d, quantile) if len(d) >= min_points else np.nan for d in depths], np.float64)
    return frusta_box(c2w, cuts * stretch, camera)


def frusta_box(c2w: np.ndarray, cuts: np.ndarray, camera: PinholeCamera) -> Optional[np.ndarray]:
    """Box (2, 3) of the view frusta of cameras ``c2w`` (N, 4, 4) cut at depths ``cuts`` (N,); a NaN cut
    takes the median of the others (:func:`seen_depth_box`). None when every cut is NaN."""
    cuts = np.asarray(cuts, np.float64).reshape(-1)
    known = np.isfinite(cuts)
    if not known.any():
        return None
    cuts = np.where(known, cuts, np.median(cuts[known]))
    w, h = camera.width, camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]], np.float64)
    rays = np.stack([(corners[:, 0] - camera.cx) / camera.fx, (corners[:, 1] - camera.cy) / camera.fy, np.ones(4)], -1)
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    far = rays[None] * cuts[:, None, None]  # (N, 4, 3) camera frame
    pts = np.einsum("nij,nkj->nki", c2w[:, :3, :3], far) + c2w[:, None, :3, 3]
    allp = np.concatenate([pts.reshape(-1, 3), c2w[:, :3, 3]])
    return np.stack([allp.min(0), allp.max(0)])
