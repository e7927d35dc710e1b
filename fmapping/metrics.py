"""Evaluation metrics: reconstruction, trajectory and image quality (numpy in, numpy / float out).

Conventions (stated once, used by every function here):

* Units: points and translations in metres; the reconstruction metrics report
  distances in **centimetres** (``*_cm``) and ratios in **percent** (0-100),
  as in the NICE-SLAM tables; trajectory metrics report metres (``*_m``) and
  degrees (``*_deg``).
* Poses are 4x4 camera-to-world matrices (see :mod:`fmapping.geometry`).
* Alignment maps the *estimate onto the ground truth*: ``umeyama(est, gt)``
  returns ``(s, R, t)`` minimising ``sum |gt - (s R est + t)|^2``. Hence an
  estimate that is twice as large as the ground truth gets ``scale = 0.5``.
  An aligned pose has rotation ``R @ R_est`` and translation ``s R t_est + t``.
  Orientation errors that must not depend on the path's shape use their own,
  orientation-only alignment (:func:`align_rotations`, :func:`rotation_errors_deg`).
* Reconstruction (NICE-SLAM protocol): both surfaces are sampled (meshes
  area-weighted, clouds by random subset), then
  accuracy = mean distance from predicted samples to their nearest GT sample,
  completion = mean distance from GT samples to their nearest predicted sample,
  completion ratio = % of GT samples within ``threshold`` of the prediction.
  Note that nearest-neighbour distances measure distance to the *surface*, not
  to a corresponding point: noise tangent to the surface is mostly invisible
  (e.g. isotropic noise of std ``sigma`` on a densely sampled plane gives an
  accuracy close to ``E|z| = sigma * sqrt(2/pi)``, not the 3-D ``1.596 sigma``).
"""
from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

__all__ = [
    "sample_surface", "recon_metrics", "eval_recon_files", "error_sources", "ERROR_SOURCES",
    "umeyama", "align_trajectory", "align_rotations", "rotation_errors_deg", "ate", "rpe", "eval_traj_files",
    "psnr", "ssim", "depth_l1", "rotation_angle_deg",
]


# ----------------------------------------------------------------------------- helpers
def _np(x, dtype=np.float64) -> np.ndarray:
    """numpy / list / torch tensor -> numpy array of ``dtype``."""
    if hasattr(x, "detach"):  # torch tensor, without importing torch
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def _points(x, what: str) -> np.ndarray:
    p = _np(x)
    if p.size == 0:
        return p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what}: expected an (N, 3) array of points, got shape {p.shape}")
    return p


# ----------------------------------------------------------------------------- reconstruction
def sample_surface(ply, n: int, seed: int = 0) -> np.ndarray:
    """Sample up to ``n`` points from a mesh or a point cloud -> (M, 3) float64.

    ``ply`` is a :class:`fmapping.ply.PlyData`, a ``(points, faces)`` tuple
    (``faces`` may be None) or a bare (N, 3) point array.

    * Mesh (at least one triangle with positive area): exactly ``n`` points,
      uniform over the surface: faces drawn with probability proportional to
      their area, then uniform random barycentric coordinates (the ``u + v > 1``
      half is folded back into the triangle).
    * Point cloud (no faces, or a mesh of zero total area): a random subset of
      ``min(n, N)`` distinct points (all points, in order, when ``N <= n``).
    """
    if n < 0:
        raise ValueError(f"sample_surface: n must be >= 0, got {n}")
    if hasattr(ply, "points"):
        pts, faces = ply.points, getattr(ply, "faces", None)
    elif isinstance(ply, (tuple, list)) and len(ply) == 2:
        pts, faces = ply
    else:
        pts, faces = ply, None
    pts = _points(pts, "sample_surface")
    rng = np.random.default_rng(seed)
    if faces is not None and len(faces):
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if f.min() < 0 or f.max() >= len(pts):
            raise ValueError(f"sample_surface: face index out of range [0, {len(pts)}) "
                             f"(min {f.min()}, max {f.max()})")
        a, b, c = pts[f[:, 0]], pts[f[:, 1]], pts[f[:, 2]]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        total = area.sum()
        if total > 0 and np.isfinite(total):
            cdf = np.cumsum(area) / total
            idx = np.minimum(np.searchsorted(cdf, rng.random(n), side="right"), len(f) - 1)
            u, v = rng.random(n), rng.random(n)
            fold = u + v > 1.0
            u[fold], v[fold] = 1.0 - u[fold], 1.0 - v[fold]
            return a[idx] + u[:, None] * (b[idx] - a[idx]) + v[:, None] * (c[idx] - a[idx])
    if len(pts) <= n:
        return pts.copy()
    return pts[np.sort(rng.choice(len(pts), size=n, replace=False))]


def recon_metrics(pred_pts, gt_pts, threshold: float = 0.05) -> dict:
    """NICE-SLAM reconstruction metrics between two point samples (metres in).

    Returns ``accuracy_cm`` (mean pred->GT nearest distance), ``completion_cm``
    (mean GT->pred), ``completion_ratio`` (% of GT points closer than
    ``threshold`` to the prediction, a.k.a. recall), ``accuracy_ratio`` (% of
    predicted points closer than ``threshold`` to GT, a.k.a. precision),
    ``fscore`` (harmonic mean of the two ratios, %), the medians
    ``accuracy_median_cm`` / ``completion_median_cm``, ``threshold_m``,
    ``n_pred`` and ``n_gt``. Non-finite predicted points are dropped (counted
    in ``n_pred_dropped``). An empty prediction gives infinite distances, 0 %
    ratios and a ``note``; an empty GT is an error.
    """
    if not threshold > 0:
        raise ValueError(f"recon_metrics: threshold must be > 0 metres, got {threshold}")
    gt = _points(gt_pts, "recon_metrics gt")
    if len(gt) == 0:
        raise ValueError("recon_metrics: ground-truth point set is empty")
    if not np.isfinite(gt).all():
        raise ValueError("recon_metrics: ground-truth points contain NaN or Inf")
    pred = _points(pred_pts, "recon_metrics pred")
    finite = np.isfinite(pred).all(axis=1)
    dropped = int((~finite).sum())
    pred = pred[finite]
    out: dict[str, Any] = {"threshold_m": float(threshold), "n_pred": int(len(pred)), "n_gt": int(len(gt))}
    if dropped:
        out["n_pred_dropped"] = dropped
    if len(pred) == 0:
        inf = float("inf")
        out.update(accuracy_cm=inf, completion_cm=inf, accuracy_median_cm=inf, completion_median_cm=inf,
                   completion_ratio=0.0, accuracy_ratio=0.0, fscore=0.0,
                   note="prediction has no (finite) points: accuracy and completion are infinite")
        return out
    d_acc, _ = cKDTree(gt).query(pred, k=1, workers=-1)
    d_comp, _ = cKDTree(pred).query(gt, k=1, workers=-1)
    prec = 100.0 * float(np.mean(d_acc < threshold))
    rec = 100.0 * float(np.mean(d_comp < threshold))
    out.update(
        accuracy_cm=100.0 * float(d_acc.mean()),
        completion_cm=100.0 * float(d_comp.mean()),
        accuracy_median_cm=100.0 * float(np.median(d_acc)),
        completion_median_cm=100.0 * float(np.median(d_comp)),
        completion_ratio=rec,
        accuracy_ratio=prec,
        fscore=0.0 if prec + rec == 0 else 2 * prec * rec / (prec + rec),
    )
    return out


def eval_recon_files(pred, gt, samples: int = 200_000, threshold: float = 0.05, seed: int = 0,
                     align: Optional[tuple] = None) -> dict:
    """Read two PLY files (mesh or cloud each), sample up to ``samples`` points on
    each (see :func:`sample_surface`; the GT uses ``seed + 1``) and return
    :func:`recon_metrics` plus ``pred``/``gt`` paths, ``pred_kind``/``gt_kind``
    (``"mesh"`` or ``"cloud"``) and ``samples``. ``align = (s, R, t)`` first moves the
    prediction by ``x -> s R x + t`` (e.g. the Sim3 that aligns a monocular trajectory to the
    GT, :func:`align_trajectory`); the result then also holds ``align_scale``."""
    from fmapping.ply import read_ply

    if samples <= 0:
        raise ValueError(f"eval recon: samples must be > 0, got {samples}")
    pd, gd = read_ply(pred), read_ply(gt)
    kind = lambda d: "mesh" if d.faces is not None and len(d.faces) else "cloud"  # noqa: E731
    if len(gd.points) == 0:
        raise ValueError(f"{gt}: ground-truth PLY has no vertices")
    pts = sample_surface(pd, samples, seed)
    if align is not None:
        sc, rot, t = align
        pts = float(sc) * pts @ np.asarray(rot, np.float64).T + np.asarray(t, np.float64)
    res = recon_metrics(pts, sample_surface(gd, samples, seed + 1), threshold)
    res.update(pred=str(pred), gt=str(gt), pred_kind=kind(pd), gt_kind=kind(gd), samples=int(samples))
    if align is not None:
        res["align_scale"] = float(align[0])
    if "note" in res:
        res["note"] = f"{pred}: {res['note']}"
    return res


ERROR_SOURCES = ("near", "free", "behind", "unseen", "other")


def error_sources(pred_pts, gt_pts, depth_views, camera, threshold: float = 0.05) -> dict:
    """Where a cloud's accuracy error comes from, told by the depth frames the GT surface was made of.

    ``depth_views``: pairs (depth (H, W) metres, 0 = no reading; c2w 4x4) seen through ``camera``
    (a :class:`fmapping.camera.PinholeCamera`, e.g. the depth sensor's). Each predicted point
    falls in the first class of :data:`ERROR_SOURCES` that fits it:

    * ``near``: within ``threshold`` of its nearest GT point (counted as accurate);
    * ``free``: some frame measured a surface behind it by more than ``threshold`` at its pixel,
      so the sensor saw empty space there (a floater, or a surface placed too close);
    * ``behind``: frames measured its pixel, and every one of them a surface in front of it by
      more than ``threshold`` (a surface placed too far, or a part the GT never reached);
    * ``unseen``: no frame has a reading at its pixel (outside every frustum, no depth): the GT
      cannot judge it;
    * ``other``: the rest (on a measured surface but far from the GT points, e.g. their sampling).

    Returns per class ``{"share": % of the points, "mean_cm": their mean distance to the GT,
    "error_share": % of the accuracy's sum}`` plus ``accuracy_cm`` (all points, as
    :func:`recon_metrics`) and ``accuracy_seen_cm`` (the points some frame measured: all but
    ``unseen``). Pixels are the nearest ones; metres in, centimetres and percent out."""
    if not threshold > 0:
        raise ValueError(f"error_sources: threshold must be > 0 metres, got {threshold}")
    gt = _points(gt_pts, "error_sources gt")
    pred = _points(pred_pts, "error_sources pred")
    pred = pred[np.isfinite(pred).all(axis=1)]
    if len(gt) == 0 or len(pred) == 0:
        raise ValueError(f"error_sources: need points on both sides, got {len(pred)} predicted and {len(gt)} GT")
    dist, _ = cKDTree(gt).query(pred, k=1, workers=-1)
    free = np.zeros(len(pred), bool)
    measured = np.zeros(len(pred), bool)
    not_behind = np.zeros(len(pred), bool)  # some reading within threshold of the point or behind it
    for depth, c2w in depth_views:
        depth = np.asarray(depth, np.float64)
        if depth.shape != (camera.height, camera.width):
            raise ValueError(f"error_sources: depth frame {depth.shape} does not match the camera "
                             f"({camera.height}, {camera.width})")
        uv, z = camera.world_to_pixels(np.asarray(c2w, np.float64), pred)
        u, v = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        g = np.zeros(len(pred))
        g[ok] = depth[v[ok], u[ok]]
        ok &= np.isfinite(g) & (g > 0)
        measured |= ok
        free |= ok & (z < g - threshold)
        not_behind |= ok & (z <= g + threshold)
    near = dist < threshold
    cls = np.full(len(pred), 4)
    cls[~measured] = 3
    cls[measured & ~not_behind] = 2
    cls[free] = 1
    cls[near] = 0
    total = float(dist.sum())
    out: dict[str, Any] = {"threshold_m": float(threshold), "n_pred": int(len(pred)),
                           "accuracy_cm": 100.0 * float(dist.mean()),
                           "accuracy_seen_cm": 100.0 * float(dist[measured].mean()) if measured.any() else None}
    for k, name in enumerate(ERROR_SOURCES):
        m = cls == k
        out[name] = {"share": 100.0 * float(m.mean()),
                     "mean_cm": 100.0 * float(dist[m].mean()) if m.any() else None,
                     "error_share": 100.0 * float(dist[m].sum()) / total if total > 0 else 0.0}
    return out


# ----------------------------------------------------------------------------- trajectories
def rotation_angle_deg(rot) -> np.ndarray:
    """Angle in degrees of rotation matrices (..., 3, 3); accurate near 0 and 180 degrees
    (``atan2(|axis part|, cos part)`` instead of ``arccos``)."""
    r = _np(rot)
    cos = 0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1.0)
    w = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(w, axis=-1)
    return np.degrees(np.arctan2(sin, cos))


def umeyama(src, dst, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (or rigid, ``with_scale=False``) transform
    ``(s, R, t)`` minimising ``sum_i |dst_i - (s R src_i + t)|^2`` (Umeyama 1991).
    ``R`` is a proper rotation (det +1) even for reflected or planar data."""
    x, y = _points(src, "umeyama src"), _points(dst, "umeyama dst")
    if x.shape != y.shape:
        raise ValueError(f"umeyama: src and dst differ in shape {x.shape} vs {y.shape}")
    if len(x) < 2:
        raise ValueError(f"umeyama: need at least 2 point pairs, got {len(x)}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("umeyama: points contain NaN or Inf")
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    cov = yc.T @ xc / len(x)
    u, d, vt = np.linalg.svd(cov)
    sgn = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2] = -1.0
    rot = (u * sgn) @ vt
    s = 1.0
    if with_scale:
        var_x = float((xc ** 2).sum() / len(x))
        if var_x <= 0:
            raise ValueError("umeyama: source points are all identical; scale is undefined")
        s = float((d * sgn).sum() / var_x)
    t = my - s * rot @ mx
    return s, rot, t


def icp_similarity(src, dst, init: Optional[tuple] = None, iters: int = 40, coarse_iters: int = 10,
                   trim_m: float = 0.10, max_points: int = 100_000, seed: int = 0,
                   with_scale: bool = True) -> tuple[tuple, dict]:
    """Refine the similarity ``init = (s, R, t)`` (default the identity) that moves the cloud ``src`` onto the
    cloud ``dst`` by trimmed point-to-point ICP: each iteration pairs every moved point with its nearest
    ``dst`` point, keeps the pairs closer than the median distance (at least 5 cm) for ``coarse_iters``
    iterations and than ``trim_m`` after, and fits them by :func:`umeyama` (rigidly with ``with_scale``
    False: the scale stays ``init``'s). Both clouds are subsampled to
    ``max_points``. Returns the composed alignment ``(s, R, t)`` (``x -> s R x + t``, as ``eval_recon_files``
    takes it) and how far the refinement moved from ``init`` (``rotation_deg``, ``translation_m`` of the
    cloud's centroid, ``scale``) with the share of the points kept at the end.

    For a map whose trajectory alignment is poorly determined (a monocular map aligned by its camera centres
    along a nearly planar path leaves the tilt free): the map's shape scored apart from that alignment."""
    rng = np.random.default_rng(seed)
    x, y = _points(src, "icp src"), _points(dst, "icp dst")
    if len(x) < 3 or len(y) < 3:
        raise ValueError(f"icp: need at least 3 points in each cloud, got {len(x)} and {len(y)}")
    x = x[rng.choice(len(x), max_points, replace=False)] if len(x) > max_points else x
    y = y[rng.choice(len(y), max_points, replace=False)] if len(y) > max_points else y
    s0, r0, t0 = init if init is not None else (1.0, np.eye(3), np.zeros(3))
    x = float(s0) * x @ np.asarray(r0, np.float64).T + np.asarray(t0, np.float64)
    tree = cKDTree(y)
    s, rot, t = 1.0, np.eye(3), np.zeros(3)
    keep = np.ones(len(x), bool)
    for it in range(iters):
        d, idx = tree.query(s * x @ rot.T + t)
        keep = d < (max(0.05, float(np.median(d))) if it < coarse_iters else trim_m)
        if keep.sum() < 3:
            break
        s, rot, t = umeyama(x[keep], y[idx[keep]], with_scale=with_scale)
    moved = float(np.linalg.norm(s * rot @ x.mean(0) + t - x.mean(0)))
    info = {"rotation_deg": float(rotation_angle_deg(rot)), "translation_m": moved, "scale": float(s),
            "kept_share": float(keep.mean())}
    return (s * float(s0), rot @ np.asarray(r0, np.float64), s * rot @ np.asarray(t0, np.float64) + t), info


def _poses(c2w, what: str) -> np.ndarray:
    p = _np(c2w)
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise ValueError(f"{what}: expected (N, 4, 4) camera-to-world poses, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{what}: poses contain NaN or Inf")
    return p


def align_trajectory(est_c2w, gt_c2w, mode: str = "sim3") -> tuple[np.ndarray, tuple[float, np.ndarray, np.ndarray]]:
    """Align an estimated trajectory to the GT by its camera positions.

    ``mode``: ``"sim3"`` (scale, rotation, translation), ``"se3"`` (rigid) or
    ``"none"`` (identity). Returns the aligned poses (rotation ``R @ R_est``,
    translation ``s R t_est + t``; still proper rigid poses) and ``(s, R, t)``.
    """
    est, gt = _poses(est_c2w, "align_trajectory est"), _poses(gt_c2w, "align_trajectory gt")
    if len(est) != len(gt):
        raise ValueError(f"align_trajectory: {len(est)} estimated vs {len(gt)} GT poses")
    if mode == "none":
        s, rot, t = 1.0, np.eye(3), np.zeros(3)
    elif mode in ("sim3", "se3"):
        s, rot, t = umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=mode == "sim3")
    else:
        raise ValueError(f"align_trajectory: mode must be 'sim3', 'se3' or 'none', got {mode!r}")
    out = est.copy()
    out[:, :3, :3] = rot @ est[:, :3, :3]
    out[:, :3, 3] = s * est[:, :3, 3] @ rot.T + t
    return out, (s, rot, t)


def align_poses(est_c2w, gt_c2w, lever_m: float = 1.0) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``(s, R, t)`` that moves an estimated trajectory onto the GT by its whole poses: Umeyama over
    each camera centre and the three points ``lever_m`` metres (GT units; on the estimate, divided by the scale of
    the centres' own fit) along its x, y and z axes. Fitted to the centres alone (:func:`align_trajectory`), a path
    that is nearly a line or a plane leaves the rotation about it loose, and a map moved by that fit tilts with it
    (a 48-frame synthetic walk: 4-5 deg); the camera axes pin it. For scoring a map, not a trajectory (its ATE
    keeps the usual centres-only fit). It assumes the GT poses are of the camera that was tracked: 7-Scenes' are
    the depth camera's, 5 deg off the colour camera's axes here, and a slam map of its dev clip scores worse after
    this fit (completion ratio 9.9 against 13.8 %)."""
    est, gt = _poses(est_c2w, "align_poses est"), _poses(gt_c2w, "align_poses gt")
    if len(est) != len(gt):
        raise ValueError(f"align_poses: {len(est)} estimated vs {len(gt)} GT poses")
    if not lever_m > 0:
        raise ValueError(f"align_poses: lever_m must be > 0, got {lever_m}")
    s0 = umeyama(est[:, :3, 3], gt[:, :3, 3])[0] if len(est) > 1 else 1.0
    src = [est[:, :3, 3]] + [est[:, :3, 3] + (lever_m / s0) * est[:, :3, k] for k in range(3)]
    dst = [gt[:, :3, 3]] + [gt[:, :3, 3] + lever_m * gt[:, :3, k] for k in range(3)]
    return umeyama(np.concatenate(src), np.concatenate(dst))


def align_rotations(est_rot, gt_rot) -> np.ndarray:
    """Orientation-only best fit: the rotation ``R`` minimising ``sum_i |R R_est_i - R_gt_i|_F^2``.

    Since ``|R A - B|_F = |R - B A^T|_F`` this is the chordal L2 mean of
    ``R_gt_i R_est_i^T``: with ``U S V^T = sum_i R_gt_i R_est_i^T``,
    ``R = U diag(1, 1, det(U V^T)) V^T`` (a proper rotation). Inputs (N, 3, 3), N >= 1."""
    e, g = _np(est_rot), _np(gt_rot)
    if e.ndim != 3 or e.shape[1:] != (3, 3) or e.shape != g.shape:
        raise ValueError(f"align_rotations: expected two (N, 3, 3) stacks of equal shape, got {e.shape} and {g.shape}")
    if len(e) == 0:
        raise ValueError("align_rotations: no rotations")
    u, _, vt = np.linalg.svd((g @ np.swapaxes(e, -1, -2)).sum(0))
    d = np.ones(3)
    d[2] = 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0
    return (u * d) @ vt


def rotation_errors_deg(est_c2w, gt_c2w, align: str = "fit") -> np.ndarray:
    """Per-pose orientation error (degrees): angle of ``R_gt_i^T R_align R_est_i``.

    ``align``: ``"fit"`` (``R_align`` from :func:`align_rotations`, uses orientations
    only), ``"first"`` (``R_align = R_gt_0 R_est_0^T``: the first poses agree) or
    ``"none"`` (identity). Unlike the rotation error after a position-based
    (Umeyama) alignment, none of these depends on the shape of the path, so they
    stay meaningful for straight or rotation-only trajectories."""
    est, gt = _poses(est_c2w, "rotation_errors est"), _poses(gt_c2w, "rotation_errors gt")
    if len(est) != len(gt):
        raise ValueError(f"rotation_errors: {len(est)} estimated vs {len(gt)} GT poses")
    re, rg = est[:, :3, :3], gt[:, :3, :3]
    if align == "fit":
        ra = align_rotations(re, rg)
    elif align == "first":
        ra = rg[0] @ re[0].T
    elif align == "none":
        ra = np.eye(3)
    else:
        raise ValueError(f"rotation_errors: align must be 'fit', 'first' or 'none', got {align!r}")
    return rotation_angle_deg(np.swapaxes(rg, -1, -2) @ ra @ re)


def ate(est_c2w, gt_c2w, align: str = "sim3") -> dict:
    """Absolute trajectory error of corresponding poses after :func:`align_trajectory`.

    Returns ``rmse_m``, ``mean_m``, ``median_m``, ``max_m`` of the position
    errors, ``scale`` (the alignment scale; 1 unless sim3), ``rot_err_mean_deg``
    (mean angle of ``R_gt^T R_aligned``), ``align`` and ``n``.

    ``rot_err_mean_deg`` inherits the rotation of the *position* alignment, which is
    ill-posed when the camera centres are (nearly) collinear or coincident (a
    straight run, a rotation-dominant clip): the spin about the line is then fixed
    by noise and the number can be tens of degrees for a good estimate. The
    well-posed orientation errors below use :func:`rotation_errors_deg` instead and
    do not depend on ``align``: ``rot_fit_rmse_deg`` / ``rot_fit_mean_deg`` /
    ``rot_fit_max_deg`` after the orientation-only best fit (:func:`align_rotations`)
    and ``rot_first_mean_deg`` with the first orientations made equal. For the
    frame-to-frame rotation drift see :func:`rpe` (``rot_rmse_deg``)."""
    aligned, (s, _, _) = align_trajectory(est_c2w, gt_c2w, align)
    gt = _np(gt_c2w)
    e = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    rel = np.swapaxes(gt[:, :3, :3], -1, -2) @ aligned[:, :3, :3]
    fit = rotation_errors_deg(est_c2w, gt, "fit")
    return {
        "rmse_m": float(np.sqrt(np.mean(e ** 2))), "mean_m": float(e.mean()),
        "median_m": float(np.median(e)), "max_m": float(e.max()), "scale": float(s),
        "rot_err_mean_deg": float(rotation_angle_deg(rel).mean()),
        "rot_fit_rmse_deg": float(np.sqrt(np.mean(fit ** 2))), "rot_fit_mean_deg": float(fit.mean()),
        "rot_fit_max_deg": float(fit.max()),
        "rot_first_mean_deg": float(rotation_errors_deg(est_c2w, gt, "first").mean()),
        "align": align, "n": int(len(e)),
    }


def _inv(p: np.ndarray) -> np.ndarray:
    out = np.zeros_like(p)
    rt = np.swapaxes(p[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ p[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def rpe(est_c2w, gt_c2w, delta: int = 1) -> dict:
    """Relative pose error over pose pairs ``(i, i + delta)``.

    With relative motions ``Q = gt_i^-1 gt_{i+delta}`` and
    ``P = est_i^-1 est_{i+delta}``, the error is ``E = Q^-1 P``; returns the RMS
    of its translation norm (``trans_rmse_m``) and rotation angle
    (``rot_rmse_deg``), their means, ``delta`` and the number of pairs ``n``.
    Invariant to a rigid change of world frame; *not* to scale (align first)."""
    est, gt = _poses(est_c2w, "rpe est"), _poses(gt_c2w, "rpe gt")
    if len(est) != len(gt):
        raise ValueError(f"rpe: {len(est)} estimated vs {len(gt)} GT poses")
    if delta < 1 or len(est) <= delta:
        raise ValueError(f"rpe: need more than delta={delta} poses (delta >= 1), got {len(est)}")
    q = _inv(gt[:-delta]) @ gt[delta:]
    p = _inv(est[:-delta]) @ est[delta:]
    err = _inv(q) @ p
    te = np.linalg.norm(err[:, :3, 3], axis=1)
    re = rotation_angle_deg(err[:, :3, :3])
    return {
        "trans_rmse_m": float(np.sqrt(np.mean(te ** 2))), "trans_mean_m": float(te.mean()),
        "rot_rmse_deg": float(np.sqrt(np.mean(re ** 2))), "rot_mean_deg": float(re.mean()),
        "delta": int(delta), "n": int(len(te)),
    }


def _match(est_ts: np.ndarray, gt_ts: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one timestamp matches (est index, gt index), each GT pose used at most
    once (by the closest estimate), sorted by estimate time."""
    from fmapping.trajectory import associate

    j = associate(est_ts, gt_ts, max_dt)
    i = np.nonzero(j >= 0)[0]
    j = j[i]
    order = np.lexsort((np.abs(est_ts[i] - gt_ts[j]), j))  # by gt index, then by |dt|
    keep = np.unique(j[order], return_index=True)[1]
    i, j = i[order][keep], j[order][keep]
    o = np.argsort(est_ts[i], kind="stable")
    return i[o], j[o]


def eval_traj_files(est, gt, align: str = "sim3", max_dt: float = 0.02, delta: int = 1) -> dict:
    """Read two TUM trajectories, match timestamps within ``max_dt`` seconds
    (one-to-one), and return ``{"ate": ate(...), "rpe": rpe(...), "n_est",
    "n_gt", "n_matched", "est", "gt", "align", "max_dt"}``. RPE is computed on
    the *aligned* estimate (so a sim3 alignment fixes the scale of a monocular
    run) over consecutive matched poses. The well-posed orientation errors are
    ``ate.rot_fit_*`` / ``ate.rot_first_mean_deg`` (see :func:`ate`) and
    ``rpe.rot_rmse_deg``. Fewer than 3 matches is a ValueError."""
    est_m, gt_m, n_est, n_gt = match_trajectory_files(est, gt, max_dt)
    a = ate(est_m, gt_m, align)
    aligned, _ = align_trajectory(est_m, gt_m, align)
    return {
        "est": str(est), "gt": str(gt), "align": align, "max_dt": float(max_dt),
        "n_est": n_est, "n_gt": n_gt, "n_matched": int(len(est_m)),
        "ate": a, "rpe": rpe(aligned, gt_m, delta=delta),
    }


def match_trajectory_files(est, gt, max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Read two TUM trajectories and pair them one-to-one by timestamp (within ``max_dt`` s):
    ``(est_c2w, gt_c2w, n_est, n_gt)``, matched poses in estimate time order. Fewer than 3
    matches is a ValueError naming both files."""
    from fmapping.trajectory import read_tum_trajectory

    ets, ec = read_tum_trajectory(est)
    gts, gc = read_tum_trajectory(gt)
    i, j = _match(ets, gts, max_dt)
    if len(i) < 3:
        raise ValueError(
            f"only {len(i)} timestamp matches within max_dt={max_dt}s between {est} ({len(ets)} poses, "
            f"t={ets.min():.3f}..{ets.max():.3f}) and {gt} ({len(gts)} poses, t={gts.min():.3f}..{gts.max():.3f}); "
            "need at least 3")
    return ec[i], gc[j], int(len(ets)), int(len(gts))


# ----------------------------------------------------------------------------- images
def _image_pair(a, b, what: str) -> tuple[np.ndarray, np.ndarray]:
    x, y = _np(a), _np(b)
    if x.shape != y.shape:
        raise ValueError(f"{what}: image shapes differ: {x.shape} vs {y.shape}")
    return x, y


def psnr(a, b, max_val: float = 1.0, mask=None) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(max_val^2 / MSE)``; ``inf`` for
    identical images. ``mask`` (HxW bool) restricts the MSE to its pixels (all channels)."""
    x, y = _image_pair(a, b, "psnr")
    sq = (x - y) ** 2
    if mask is not None:
        m = _np(mask, bool)
        if m.shape != x.shape[: m.ndim]:
            raise ValueError(f"psnr: mask shape {m.shape} does not match image shape {x.shape}")
        sq = sq[m]
    if sq.size == 0:
        raise ValueError("psnr: no pixels to compare (empty image or mask)")
    mse = float(sq.mean())
    return float("inf") if mse == 0 else 10.0 * math.log10(max_val ** 2 / mse)


def ssim(a, b, data_range: float = 1.0, sigma: float = 1.5) -> float:
    """Mean structural similarity (Wang et al. 2004) with an 11x11 Gaussian window
    (sigma 1.5, truncated at 3.5 sigma), population covariances, K1 = 0.01,
    K2 = 0.03, reflect padding and the window radius cropped from every border
    before averaging; colour images (HxWxC) are averaged over channels.
    Matches ``skimage.metrics.structural_similarity(gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1)``."""
    x, y = _image_pair(a, b, "ssim")
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    if x.ndim != 3:
        raise ValueError(f"ssim: expected HxW or HxWxC images, got shape {x.shape}")
    truncate = 3.5
    r = int(truncate * sigma + 0.5)
    if min(x.shape[:2]) < 2 * r + 1:
        raise ValueError(f"ssim: images must be at least {2 * r + 1}x{2 * r + 1}, got {x.shape[:2]}")
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    filt = lambda im: ndimage.gaussian_filter(im, sigma=(sigma, sigma, 0), truncate=truncate, mode="reflect")  # noqa: E731
    ux, uy = filt(x), filt(y)
    vx = filt(x * x) - ux * ux
    vy = filt(y * y) - uy * uy
    vxy = filt(x * y) - ux * uy
    s = (2 * ux * uy + c1) * (2 * vxy + c2) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return float(s[r:-r, r:-r].mean())


def depth_l1(pred, gt, mask=None) -> float:
    """Mean absolute depth error in metres over pixels with valid GT (finite and > 0)
    and ``mask`` (if given). NaN when no pixel is valid."""
    p, g = _image_pair(pred, gt, "depth_l1")
    valid = np.isfinite(g) & (g > 0)
    if mask is not None:
        m = _np(mask, bool)
        if m.shape != g.shape:
            raise ValueError(f"depth_l1: mask shape {m.shape} does not match depth shape {g.shape}")
        valid &= m
    if not valid.any():
        return float("nan")
    return float(np.abs(p[valid] - g[valid]).mean())
