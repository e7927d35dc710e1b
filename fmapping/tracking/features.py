"""Sparse geometry for monocular tracking: KLT tracks, two-view initialisation, triangulation.

RGB-only tracking needs depth at the reference keyframe before the map can render
any. This module supplies it with standard two-view geometry (OpenCV):

* :func:`detect_corners` (Shi-Tomasi) and :func:`klt_track` (pyramidal Lucas-Kanade
  with a forward-backward check, compensating exposure changes: :func:`klt_track_gain`)
  follow points from a keyframe to later frames;
* :func:`two_view_init` recovers the relative pose of two views from the tracks
  (essential matrix, RANSAC) up to scale and triangulates the inliers; with the tracks'
  covariances it refits the pose on the whitened epipolar error
  (:mod:`fmapping.tracking.whitened_two_view`);
* :func:`triangulate` gives world points of tracks between two views with known
  poses, rejecting low parallax and large reprojection errors;
* :func:`two_view_known_baseline` recovers the relative rotation when the baseline
  vector is known (from a pose source), for the rotation-dominant starts where the
  essential matrix confuses rotation with translation.

Conventions: pixels (u, v) with integer centres, poses camera-to-world 4x4
(OpenCV axes), see :mod:`fmapping.geometry`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import cv2
import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.tracking.whitened_two_view import bearings, epipolar_whitened_px, refine_two_view_whitened


@dataclass
class KltConfig:
    max_corners: int = 800
    quality: float = 0.001  # Shi-Tomasi quality level (low: weakly textured walls still give corners)
    min_distance: int = 7  # pixels between corners
    # LK window = 2 * half + 1 pixels, ``half_window`` at 320 px image width scaled with the width: 11 px at
    # 320, 21 px at 640. Measured on five synthetic rooms (200 frames, 320x240): Sim3 ATE mean 2.84 cm with a
    # 21 px window, 1.46 cm with 11 px (big windows straddle depth edges and perspective distortion, which
    # biases the tracks); on TUM fr1_rpy (640x480) 11 px leaves too few tracks to bootstrap, 21 px is best.
    half_window: int = 5
    levels: int = 4  # LK pyramid levels
    fb_threshold: float = 1.0  # forward-backward error (pixels) above which a track is dropped
    max_iters: int = 30  # LK iterations per pyramid level (and a step below 0.01 px stops it)
    border: int = 8
    # Lucas-Kanade assumes the brightness stays constant. A gain change g between the two images moves a
    # track by about (g - 1) * I / |grad I|, towards where the intensities match: on a pale, weakly textured
    # wall 0.3-0.4 px for every 0.5 % of exposure drift, and the bias adds up along a track. Each call
    # measures the gain at the tracks (:func:`track_gain`, over windows ``gain_half_window`` wide at 320 px:
    # a small window's mean follows the biased track and reads a gain near 1). While that gain is off by
    # more than ``gain_tol`` and by more than the tracks' own spread of ratios, the points are tracked again
    # (at most ``gain_passes`` times) in the second image scaled back to the first's exposure.
    # bench/klt_exposure.py: median epipolar (Sampson) error against the GT poses after 5 frames, widened
    # synthetic room 2 (0.5-1.5 % drift a frame) 1.15 -> 0.28 px, TUM fr1_rpy 0.93 -> 0.83 px, 7-Scenes and
    # the default rooms unchanged (bench/results/klt_exposure/).
    gain_compensation: bool = True
    gain_tol: float = 0.002
    gain_half_window: int = 30
    gain_passes: int = 2
    # Track in the images halved until they are at most this wide (0: at full size), positions scaled back; the
    # window (``half_window`` at 320 px) then covers the same view angle with a quarter of the pixels per halving,
    # and the front end's re-track from the keyframe refines at full size (fine_klt_config). Off: on 640x480 clips
    # (bench/mono_variants.py, max_width 320) a frame's median time halves, but over each clip and perturbed
    # copies of it (bench/results/probes_2026-12-06b/) the Sim3 ATE median went TUM fr1_rpy 2.19 -> 2.84 cm and
    # 7-Scenes long 5.20 -> 7.97 cm (a quarter more keyframes); 7-Scenes dev the same (2.98 -> 2.92 cm).
    # Images 320 px wide (the synthetic rooms) are never halved.
    max_width: int = 0


def to_u8(rgb: np.ndarray) -> np.ndarray:
    img = np.asarray(rgb)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img * (255.0 if img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def detect_corners(gray: np.ndarray, cfg: KltConfig, existing: Optional[np.ndarray] = None) -> np.ndarray:
    """Shi-Tomasi corners (N, 2) float32, away from the border, from black fill (undistortion) and from
    ``existing`` points."""
    from fmapping.tracking.direct_align import image_valid_mask

    h, w = gray.shape
    mask = np.zeros((h, w), np.uint8)
    b = cfg.border
    mask[b:h - b, b:w - b] = 255
    fill = image_valid_mask(gray, erode=cfg.border)
    if fill is not None:
        mask[~fill] = 0
    n = cfg.max_corners
    if existing is not None and len(existing):
        for u, v in np.round(existing).astype(int):
            cv2.circle(mask, (int(u), int(v)), cfg.min_distance, 0, -1)
        n = max(0, cfg.max_corners - len(existing))
    if n == 0:
        return np.zeros((0, 2), np.float32)
    pts = cv2.goodFeaturesToTrack(gray, n, cfg.quality, cfg.min_distance, mask=mask)
    return np.zeros((0, 2), np.float32) if pts is None else pts.reshape(-1, 2).astype(np.float32)


REFERENCE_WIDTH = 320  # pixel sizes and thresholds of the front-end configs are given at this image width


def at_width(px: float, width: int) -> float:
    """A pixel size given at :data:`REFERENCE_WIDTH` for an image ``width`` pixels wide."""
    return px * width / REFERENCE_WIDTH


def odd_window(half: float, width: int) -> int:
    """An odd window (pixels) of half size ``half`` at :data:`REFERENCE_WIDTH` for an image ``width`` wide."""
    return 2 * max(2, int(round(at_width(half, width)))) + 1


def klt_window(cfg: KltConfig, width: int) -> int:
    """The LK window (pixels, odd) for an image ``width`` pixels wide (see ``KltConfig.half_window``)."""
    return odd_window(cfg.half_window, width)


def _lk(img0: np.ndarray, img1: np.ndarray, pts0: np.ndarray, cfg: KltConfig,
        guess: Optional[np.ndarray], fb: bool = True, fb_guess: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade from ``img0`` to ``img1`` with the forward-backward check (``fb``): (pts1, ok).
    With ``fb_guess`` the backward pass starts where the prior motion of ``guess`` (pts1's starting points),
    reversed, puts the points, not at zero motion: on a repeating pattern a flow beyond half a period would
    lock it elsewhere."""
    p0 = np.ascontiguousarray(pts0, np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, cfg.max_iters, 0.01)
    win = klt_window(cfg, img0.shape[1])
    kw = dict(winSize=(win, win), maxLevel=cfg.levels - 1, criteria=crit)
    if guess is not None:
        p1 = np.ascontiguousarray(guess, np.float32).reshape(-1, 1, 2).copy()
        p1, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p0, p1, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **kw)
    else:
        p1, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p0, None, **kw)
    ok = st.reshape(-1) == 1
    if fb and fb_guess and guess is not None:  # back from where the same prior motion, reversed, puts the points
        pb = np.ascontiguousarray(p1 - (np.asarray(guess, np.float32).reshape(-1, 1, 2) - p0), np.float32)
        pb, stb, _ = cv2.calcOpticalFlowPyrLK(img1, img0, p1, pb, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **kw)
        ok &= (stb.reshape(-1) == 1) & (np.linalg.norm((pb - p0).reshape(-1, 2), axis=1) < cfg.fb_threshold)
    elif fb:
        pb, stb, _ = cv2.calcOpticalFlowPyrLK(img1, img0, p1, None, **kw)
        ok &= (stb.reshape(-1) == 1) & (np.linalg.norm((pb - p0).reshape(-1, 2), axis=1) < cfg.fb_threshold)
    p1 = p1.reshape(-1, 2)
    h, w = img1.shape[:2]
    ok &= (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    return p1, ok


def _window_means(img: np.ndarray, pts: np.ndarray, win: int) -> np.ndarray:
    """Mean intensity of the ``win`` x ``win`` window around each point (N, 2) at its nearest pixel, from the
    integral image (windows clipped at the border)."""
    h, w = img.shape[:2]
    ii = cv2.integral(img)
    x = np.clip(np.round(pts[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.round(pts[:, 1]).astype(np.int64), 0, h - 1)
    r = win // 2
    x0, x1 = np.clip(x - r, 0, w), np.clip(x + r + 1, 0, w)
    y0, y1 = np.clip(y - r, 0, h), np.clip(y + r + 1, 0, h)
    total = ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]
    return total / ((x1 - x0) * (y1 - y0))


def track_gain(img0: np.ndarray, img1: np.ndarray, pts0: np.ndarray, pts1: np.ndarray, win: int,
               min_points: int = 10, min_level: float = 16.0) -> Optional[tuple[float, float]]:
    """The exposure gain of ``img1`` against ``img0`` (>1: brighter) from point tracks ``pts0`` -> ``pts1``:
    the median ratio of their window means (``win`` pixels), over windows brighter than ``min_level`` in
    both images and below saturation, and the spread of those ratios (their MAD, scaled to a standard
    deviation). None with fewer than ``min_points`` such tracks."""
    if len(pts0) < min_points:
        return None
    a, b = _window_means(img0, pts0, win), _window_means(img1, pts1, win)
    use = (a > min_level) & (b > min_level) & (a < 250.0) & (b < 250.0)
    if use.sum() < min_points:
        return None
    ratio = b[use] / a[use]
    r = float(np.median(ratio))
    return r, float(1.4826 * np.median(np.abs(ratio - r)))


def scale_exposure(img: np.ndarray, gain: float) -> np.ndarray:
    """``img`` (uint8) divided by ``gain``, rounded and saturated."""
    return img if gain == 1.0 else cv2.convertScaleAbs(img, alpha=1.0 / gain)


def klt_track_gain(img0: np.ndarray, img1: np.ndarray, pts0: np.ndarray, cfg: KltConfig,
                   guess: Optional[np.ndarray] = None, gain: float = 1.0,
                   fb: bool = True, fb_guess: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`klt_track` with ``img1`` taken at ``gain`` times ``img0``'s exposure (a prediction; 1: the
    same). Returns (pts1, ok, the gain the points were tracked under). With ``cfg.gain_compensation``, a
    gain measured at the tracks more than ``cfg.gain_tol`` (and more than the tracks' spread) off the one
    applied is applied instead and the points tracked again from ``guess`` (``cfg.gain_passes`` times at
    most): a first pass far off under the wrong exposure is a worse start than the guess. ``fb`` False:
    no forward-backward check (half the cost; for a caller that checks the tracks otherwise). ``fb_guess``: the
    backward pass starts from ``guess``'s motion reversed (:func:`_lk`)."""
    if len(pts0) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool), gain
    halvings = klt_halvings(cfg, img0.shape[1])
    if halvings:
        return _klt_halved(img0, img1, pts0, cfg, guess, gain, fb, halvings, fb_guess)
    p1, ok = _lk(img0, scale_exposure(img1, gain), pts0, cfg, guess, fb, fb_guess)
    if not cfg.gain_compensation:
        return p1, ok, gain
    win = odd_window(cfg.gain_half_window, img0.shape[1])
    pts0 = np.asarray(pts0, np.float64).reshape(-1, 2)
    for _ in range(cfg.gain_passes):
        m = track_gain(img0, img1, pts0[ok], p1[ok], win)
        if m is None:
            break
        r, spread = m
        # a gain the tracks disagree on (parallax, motion blur, tracks gone astray) is no exposure change
        if abs(r / gain - 1.0) <= max(cfg.gain_tol, spread):
            return p1, ok, gain
        gain = r
        p1, ok = _lk(img0, scale_exposure(img1, gain), pts0, cfg, guess, fb, fb_guess)
    return p1, ok, gain


def klt_halvings(cfg: KltConfig, width: int) -> int:
    """How often an image ``width`` pixels wide is halved to track in it (``cfg.max_width``; never below 64 px)."""
    k = 0
    while cfg.max_width > 0 and (width >> k) > cfg.max_width and (width >> (k + 1)) >= 64:
        k += 1
    return k


def fine_klt_config(cfg: KltConfig, width: int, levels: int = 2) -> KltConfig:
    """A config that tracks at full size with the window ``cfg`` has in the halved image
    (:func:`klt_halvings`) and ``levels`` pyramid levels: a full-resolution refinement of positions known to
    within a pixel or two of the halved image. ``cfg`` itself when images of ``width`` are not halved."""
    k = klt_halvings(cfg, width)
    if k == 0:
        return cfg
    return replace(cfg, max_width=0, levels=levels, half_window=cfg.half_window / 2 ** k)


def _klt_halved(img0: np.ndarray, img1: np.ndarray, pts0: np.ndarray, cfg: KltConfig, guess: Optional[np.ndarray],
                gain: float, fb: bool, halvings: int, fb_guess: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`klt_track_gain` in both images halved ``halvings`` times (``cv2.pyrDown``: pixel ``i`` of the
    halved image is centred on ``2 i + 0.5`` of the full one), positions scaled back to the full size."""
    s = float(2 ** halvings)
    for _ in range(halvings):
        img0, img1 = cv2.pyrDown(img0), cv2.pyrDown(img1)

    def down(p):
        return None if p is None else (np.asarray(p, np.float64).reshape(-1, 2) + 0.5) / s - 0.5

    p1, ok, gain = klt_track_gain(img0, img1, down(pts0), replace(cfg, max_width=0), down(guess), gain, fb, fb_guess)
    return ((np.asarray(p1, np.float64) + 0.5) * s - 0.5).astype(np.float32), ok, gain


def klt_track(img0: np.ndarray, img1: np.ndarray, pts0: np.ndarray, cfg: KltConfig,
              guess: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """Track ``pts0`` (N, 2) from ``img0`` to ``img1`` (uint8 grey), exposure-compensated when
    ``cfg.gain_compensation`` (:func:`klt_track_gain`). Returns (pts1, ok)."""
    p1, ok, _ = klt_track_gain(img0, img1, pts0, cfg, guess)
    return p1, ok


def _spread(x: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid and RMS distance from it of points (N, 3)."""
    mu = x.mean(0)
    return mu, max(float(np.sqrt(((x - mu) ** 2).sum(1).mean())), 1e-12)


def _w2c_from_normalised(rvec: np.ndarray, tvec: np.ndarray, mu: np.ndarray, d: float) -> np.ndarray:
    """World-to-camera pose from OpenCV's solution for the points ``(x - mu) / d``."""
    w2c = np.eye(4)
    w2c[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    w2c[:3, 3] = d * np.asarray(tvec, np.float64).reshape(-1) - w2c[:3, :3] @ mu
    return w2c


def refine_pnp(camera: PinholeCamera, x: np.ndarray, uv: np.ndarray, w2c: np.ndarray) -> Optional[np.ndarray]:
    """World-to-camera pose refined from ``w2c`` on the reprojection error of world points ``x``
    (N, 3) seen at pixels ``uv`` (OpenCV's iterative PnP), or None. The points are centred and
    scaled to unit spread first: OpenCV's stopping rule is in absolute units, so the result would
    otherwise depend on where the world's origin is and on its unit of length."""
    mu, d = _spread(x)
    rot = w2c[:3, :3]
    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(rot))
    tvec = ((w2c[:3, 3] + rot @ mu) / d).reshape(3, 1)
    ok, rvec, tvec = cv2.solvePnP((x - mu) / d, uv, camera.K, None, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    return _w2c_from_normalised(rvec, tvec, mu, d) if ok else None


def pnp_ransac(camera: PinholeCamera, x: np.ndarray, uv: np.ndarray, inlier_px: float,
               iterations: int = 200) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """World-to-camera pose of world points ``x`` (N, 3) seen at pixels ``uv`` without a prior
    (EPnP in RANSAC, then :func:`refine_pnp` on the inliers), and the inlier mask; or None.
    Normalised as :func:`refine_pnp` is."""
    if len(x) < 6:
        return None
    mu, d = _spread(x)
    ok, rvec, tvec, inl = cv2.solvePnPRansac((x - mu) / d, uv, camera.K, None, reprojectionError=inlier_px,
                                             iterationsCount=iterations, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < 6:
        return None
    mask = np.zeros(len(x), bool)
    mask[inl.reshape(-1)] = True
    w2c = refine_pnp(camera, x[mask], uv[mask], _w2c_from_normalised(rvec, tvec, mu, d))
    return None if w2c is None else (w2c, mask)


def _rays(camera: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    return np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))], -1)


def triangulate(camera: PinholeCamera, c2w_a: np.ndarray, c2w_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray,
                min_parallax_deg: float = 1.0, max_reproj_px: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) from pixel pairs in two views with known poses, and a validity mask.

    Linear (DLT) triangulation in the frame of view a with the baseline scaled to 1, so
    the result moves with any rigid motion and scaling of the world (a DLT in world
    coordinates weighs its algebraic error by where the world origin is and by the unit
    of length). A point is valid when it lies in front of both cameras, its rays meet at
    an angle of at least ``min_parallax_deg`` and it reprojects within ``max_reproj_px``
    in both views.
    """
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    if len(uv_a) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    k = camera.K
    c2w_a = np.asarray(c2w_a, np.float64)
    w2c_a = np.linalg.inv(c2w_a)[:3]
    w2c_b4 = np.linalg.inv(c2w_b)
    w2c_b = w2c_b4[:3]
    a_to_b = w2c_b4 @ c2w_a  # a's camera frame -> b's camera frame
    base = max(float(np.linalg.norm(a_to_b[:3, 3])), 1e-12)
    a_to_b[:3, 3] /= base
    xh = cv2.triangulatePoints(k @ np.eye(4)[:3], k @ a_to_b[:3], uv_a.T, uv_b.T)
    w = xh[3]
    good_w = np.abs(w) > 1e-12
    x_a = (xh[:3] / np.where(good_w, w, 1.0)).T * base  # in a's camera frame
    x = x_a @ c2w_a[:3, :3].T + c2w_a[:3, 3]
    ok = good_w & np.isfinite(x).all(1)
    out = []
    for c2w, w2c, uv in ((c2w_a, w2c_a, uv_a), (c2w_b, w2c_b, uv_b)):
        xc = x @ w2c[:, :3].T + w2c[:, 3]
        z = xc[:, 2]
        ok &= z > 1e-3
        zs = np.where(z > 1e-3, z, 1.0)
        proj = np.stack([camera.fx * xc[:, 0] / zs + camera.cx, camera.fy * xc[:, 1] / zs + camera.cy], -1)
        ok &= np.linalg.norm(proj - uv, axis=1) < max_reproj_px
        out.append(x - c2w[:3, 3])
    ra, rb = out
    cosang = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
    ok &= cosang < math.cos(math.radians(min_parallax_deg))
    return x, ok


@dataclass
class TwoViewResult:
    c2w_b: np.ndarray  # pose of view b with view a at the identity, translation of unit norm
    inliers: np.ndarray  # (N,) bool
    points: np.ndarray  # (N, 3) in view a's camera frame (unit baseline)
    valid: np.ndarray  # (N,) bool: inlier, triangulated, in front, enough parallax
    median_parallax_deg: float


def corner_covariance(gray: np.ndarray, uv: np.ndarray, cfg: KltConfig, cap: float = 100.0) -> np.ndarray:
    """The shape of the position error of KLT tracks at pixels ``uv`` (N, 2) of ``gray``: (N, 2, 2) covariances
    (pixels squared) from the structure tensor ``G`` summed over the LK window (:func:`klt_window`),
    ``lambda_max(G) G^-1`` with its eigenvalues clipped to [1, ``cap``].

    A corner textured in every direction gets the identity: the isotropic one-pixel error the rest of the
    front end assumes. A point on an edge or a stripe gets up to ``cap`` times that variance along the edge,
    where LK cannot tell how far it moved (the aperture problem) and settles near its starting guess, so its
    error there is systematic, not noise. On a widened synthetic room whose first frames see a striped,
    nearly planar wall, such points pulled the two-view translation 25-56 deg off the true direction
    (bench/results/anisotropic_tracks/)."""
    w, vec = np.linalg.eigh(structure_tensor(gray, uv, cfg))  # ascending eigenvalues
    var = np.clip(w[:, 1:2] / np.maximum(w, 1e-12), 1.0, cap)
    return np.einsum("nij,nj,nkj->nik", vec, var, vec)


def structure_tensor(gray: np.ndarray, uv: np.ndarray, cfg: KltConfig) -> np.ndarray:
    """The structure tensor ``G`` (N, 2, 2) of ``gray`` at pixels ``uv`` (N, 2): the image gradient's outer
    product (grey levels per pixel, squared) summed over the LK window (:func:`klt_window`) around each."""
    g = np.asarray(gray, np.float32)
    ix = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    iy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    win = klt_window(cfg, g.shape[1])
    sxx, sxy, syy = (cv2.boxFilter(a, -1, (win, win), normalize=False) for a in (ix * ix, ix * iy, iy * iy))
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    u = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, g.shape[1] - 1)
    v = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, g.shape[0] - 1)
    tensor = np.stack([np.stack([sxx[v, u], sxy[v, u]], -1), np.stack([sxy[v, u], syy[v, u]], -1)], -2)
    return tensor.astype(np.float64)


def two_view_init(camera: PinholeCamera, uv_a: np.ndarray, uv_b: np.ndarray, ransac_px: float = 1.0,
                  min_parallax_deg: float = 1.0, refine: bool = True,
                  cov: Optional[np.ndarray] = None, starts: int = 0) -> Optional[TwoViewResult]:
    """Relative pose (unit translation) of view b w.r.t. view a from tracked pixels, or None.

    Essential matrix (RANSAC, 5-point) and ``recoverPose``; with ``refine`` a two-view
    bundle adjustment on the inliers (view a fixed) polishes pose and points. With the
    tracks' position covariances ``cov`` (N, 2, 2, :func:`corner_covariance`) the pose is
    instead refined on the whitened epipolar error of every pair
    (:func:`refine_two_view_whitened`, from ``starts`` more translation directions too), which
    also chooses the inliers.
    """
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    if len(uv_a) < 20:
        return None
    k = camera.K
    e, mask = cv2.findEssentialMat(uv_a, uv_b, k, method=cv2.RANSAC, prob=0.999, threshold=ransac_px)
    if e is None or e.shape != (3, 3):
        return None
    n_in, r, t, mask2 = cv2.recoverPose(e, uv_a, uv_b, k, mask=mask.copy())
    inl = mask2.reshape(-1) > 0
    if n_in < 20:
        return None
    if cov is not None:
        fit = refine_two_view_whitened(camera, r, t, uv_a, uv_b, np.asarray(cov, np.float64), ransac_px, starts)
        if fit is None:
            return None
        r, t, inl = fit
        t = t.reshape(3, 1)
        # the epipolar error does not see the sign of t: take the one that puts more points in front of both views
        front = []
        for sign in (1.0, -1.0):
            t_ab = np.eye(4)
            t_ab[:3, :3], t_ab[:3, 3] = r, sign * t.reshape(-1)
            front.append((triangulate(camera, np.eye(4), np.linalg.inv(t_ab), uv_a[inl], uv_b[inl], 0.0,
                                      4 * ransac_px)[1].sum(), sign))
        t = max(front)[1] * t
        # points (landmarks to be) only from the pairs that also fit the pose in plain pixels: the bundle
        # adjustments after the bootstrap weigh every pixel error alike, and an edge point's error along its edge
        # would pull the pose back
        eye = np.broadcast_to(np.eye(2), (len(uv_a), 2, 2))
        inl &= np.abs(epipolar_whitened_px(camera, r, t.reshape(-1), uv_a, uv_b, eye)) < ransac_px
        if inl.sum() < 20:
            return None
        refine = False  # the two-view bundle adjustment's isotropic error would pull the pose back too
    # recoverPose gives x_b = R x_a + t  (a -> b); c2w_b = inv([R|t]) with a at the identity
    t_ab = np.eye(4)
    t_ab[:3, :3] = r
    t_ab[:3, 3] = t.reshape(-1)
    c2w_b = np.linalg.inv(t_ab)
    pts, ok = triangulate(camera, np.eye(4), c2w_b, uv_a, uv_b, min_parallax_deg=0.0, max_reproj_px=4 * ransac_px)
    ok &= inl
    if refine and ok.sum() >= 10:
        from fmapping.tracking.ba import bundle_adjust

        idx = np.flatnonzero(ok)
        n = len(idx)
        res = bundle_adjust(camera, [np.eye(4), c2w_b], [0], pts[idx], np.repeat([0, 1], n),
                            np.tile(np.arange(n), 2), np.concatenate([uv_a[idx], uv_b[idx]]), huber_px=ransac_px,
                            max_nfev=20)
        c2w_b = res.poses[1]
        s = np.linalg.norm(c2w_b[:3, 3])
        if s > 1e-9:
            c2w_b[:3, 3] /= s
            pts[idx] = res.points / s
        pts2, ok2 = triangulate(camera, np.eye(4), c2w_b, uv_a, uv_b, min_parallax_deg=0.0,
                                max_reproj_px=4 * ransac_px)
        ok = ok2 & inl
        pts = pts2
    ra = pts
    rb = pts - c2w_b[:3, 3]
    cosang = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
    par = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    med = float(np.median(par[ok])) if ok.any() else 0.0
    valid = ok & (par >= min_parallax_deg)
    return TwoViewResult(c2w_b, inl, pts, valid, med)


def sampson_px(camera: PinholeCamera, rot_ab: np.ndarray, centre_b_in_a: np.ndarray, uv_a: np.ndarray,
               uv_b: np.ndarray) -> np.ndarray:
    """Signed Sampson distance (pixels, in the geometric mean focal length) of pixel pairs under the
    relative pose ``X_b = R (X_a - c)`` (``R = rot_ab``, ``c`` = view b's centre in view a's frame).

    The epipolar constraint is ``x_b^T E x_a = 0`` with ``E = R [c]_x``.
    """
    c = np.asarray(centre_b_in_a, np.float64)
    cx = np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    e = np.asarray(rot_ab, np.float64) @ cx
    xa, xb = bearings(camera, uv_a), bearings(camera, uv_b)
    exa = xa @ e.T
    etxb = xb @ e
    num = (xb * exa).sum(1)
    den = np.sqrt(exa[:, 0] ** 2 + exa[:, 1] ** 2 + etxb[:, 0] ** 2 + etxb[:, 1] ** 2)
    return num / np.maximum(den, 1e-15) * math.sqrt(camera.fx * camera.fy)


def two_view_known_baseline(camera: PinholeCamera, uv_a: np.ndarray, uv_b: np.ndarray, centre_b_in_a: np.ndarray,
                            inlier_px: float = 1.0, rot_init: Optional[np.ndarray] = None) -> Optional[tuple]:
    """Relative rotation of view b when its centre ``c`` in view a's camera frame is known.

    With the baseline fixed only the 3 rotation parameters are fitted (robust least
    squares on :func:`sampson_px`), so the rotation / translation ambiguity of a short
    baseline cannot trade one for the other. Start: ``rot_init`` or the best pure
    rotation between the bearings (Kabsch, fine for the small parallax it is meant
    for). Returns ``(c2w_b with view a at the identity, inlier mask)`` (inliers:
    ``|sampson| < 2 * inlier_px``) or None with fewer than 10 pairs.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    c = np.asarray(centre_b_in_a, np.float64).reshape(3)
    if len(uv_a) < 10 or len(uv_a) != len(uv_b):
        return None
    if rot_init is None:
        fa = bearings(camera, uv_a)
        fb = bearings(camera, uv_b)
        fa /= np.linalg.norm(fa, axis=1, keepdims=True)
        fb /= np.linalg.norm(fb, axis=1, keepdims=True)
        u, _, vt = np.linalg.svd(fb.T @ fa)  # R fa ~ fb
        rot_init = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    x0 = Rotation.from_matrix(rot_init).as_rotvec()
    inl = np.ones(len(uv_a), bool)
    for _ in range(2):  # fit, drop outliers, refit
        fun = lambda x, m=inl: sampson_px(camera, Rotation.from_rotvec(x).as_matrix(), c, uv_a[m], uv_b[m])  # noqa: E731
        x0 = least_squares(fun, x0, loss="huber", f_scale=inlier_px).x
        inl = np.abs(sampson_px(camera, Rotation.from_rotvec(x0).as_matrix(), c, uv_a, uv_b)) < 2 * inlier_px
        if inl.sum() < 10:
            return None
    rot = Rotation.from_rotvec(x0).as_matrix()
    t_ab = np.eye(4)
    t_ab[:3, :3] = rot
    t_ab[:3, 3] = -rot @ c
    return np.linalg.inv(t_ab), inl


def points_to_camera(c2w: np.ndarray, pts_world: np.ndarray) -> np.ndarray:
    w2c = np.linalg.inv(c2w)
    return pts_world @ w2c[:3, :3].T + w2c[:3, 3]
