"""Direct (photometric) image alignment of a frame against a reference keyframe with depth.

The fast tracking path. A *reference* is a keyframe image, its pose ``c2w_ref``
and depth at a few thousand high-gradient pixels (ground-truth depth, depth
rendered from the map, or a depth sensor). Aligning a new frame minimises the
robust photometric error

    r_i = I_cur(pi(T_cr X_i)) - (exp(a) I_ref(p_i) + b)

over ``T_cr`` (reference camera -> current camera, 4x4) and an optional affine
brightness change ``(a, b)``, with ``X_i = depth_i * K^-1 p_i`` the reference
points in the reference camera frame. Gauss-Newton (Levenberg-Marquardt damped)
on a left-multiplied se(3) correction ``T_cr <- se3_exp(delta) @ T_cr`` (delta =
(rho, phi), translation first, as in :mod:`fmapping.geometry`), coarse to fine
over an image pyramid, Huber weights with a MAD scale. The current camera pose is
``c2w_cur = c2w_ref @ inv(T_cr)``.

Everything here is vectorised numpy (float32 images, float64 6x6 systems);
intensities are grey levels in [0, 1]; pixel centres are integers (see
:mod:`fmapping.camera`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Union

import cv2
import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import orthonormalize, se3_exp_np


# ----------------------------------------------------------------------------- images
def to_gray(rgb: np.ndarray) -> np.ndarray:
    """uint8 (H, W, 3) RGB (or (H, W) grey) -> float32 grey in [0, 1]."""
    img = np.asarray(rgb)
    if img.ndim == 3:
        if img.shape[2] != 3:
            raise ValueError(f"expected an RGB image (H, W, 3), got shape {img.shape}")
    elif img.ndim != 2:
        raise ValueError(f"expected an image (H, W, 3) or (H, W), got shape {img.shape}")
    scale = np.float32(1.0 / 255.0 if img.dtype == np.uint8 else 1.0)
    img = img.astype(np.float32) * scale  # convert before mixing channels: no re-quantisation
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def level_camera(camera: PinholeCamera, level: int, size: tuple[int, int]) -> PinholeCamera:
    """Intrinsics of pyramid level ``level`` built with ``cv2.pyrDown``.

    ``pyrDown`` keeps fine pixel ``2j`` as coarse pixel ``j``, so every level halves
    ``fx, fy, cx, cy`` (no half-pixel shift). ``size`` is (W, H) of the level.
    """
    s = 0.5**level
    return PinholeCamera(camera.fx * s, camera.fy * s, camera.cx * s, camera.cy * s, int(size[0]), int(size[1]))


def with_gradients(img: np.ndarray) -> np.ndarray:
    """Stack (I, dI/du, dI/dv) as (H, W, 3) in the image's float dtype; central differences, zero on the border."""
    out = np.zeros(img.shape + (3,), img.dtype if img.dtype in (np.float32, np.float64) else np.float32)
    out[..., 0] = img
    out[:, 1:-1, 1] = 0.5 * (img[:, 2:] - img[:, :-2])
    out[1:-1, :, 2] = 0.5 * (img[2:] - img[:-2])
    return out


@dataclass
class Pyramid:
    """Grey image pyramid with gradients; level 0 is full resolution."""

    levels: list  # of (H_l, W_l, 3) float32 (I, Iu, Iv)
    cameras: list  # PinholeCamera per level
    masks: Optional[list] = None  # per level (H_l, W_l) bool: pixels whose samples are real image (None: all)


def build_pyramid(gray: np.ndarray, camera: PinholeCamera, levels: int, blur: float = 0.0,
                  valid: Optional[np.ndarray] = None) -> Pyramid:
    """Pyramid of ``levels`` levels; ``blur`` > 0 smooths level 0 with a Gaussian of that sigma (pixels).

    ``valid`` (H, W) bool marks real image content (e.g. :func:`image_valid_mask`, which
    excludes the black fill of an undistorted image); each coarser level keeps a pixel
    only when its whole ``pyrDown`` footprint is valid. Points warped onto invalid
    pixels are left out of the alignment (:func:`warp_residuals`).
    """
    if gray.shape != (camera.height, camera.width):
        raise ValueError(f"image is {gray.shape[1]}x{gray.shape[0]} but the camera is {camera.width}x{camera.height}")
    if blur > 0:
        gray = cv2.GaussianBlur(gray, (0, 0), blur)
    imgs = [gray]
    for _ in range(1, levels):
        imgs.append(cv2.pyrDown(imgs[-1]))
    masks = None
    if valid is not None:
        valid = np.asarray(valid, bool)
        if valid.shape != gray.shape:
            raise ValueError(f"valid mask is {valid.shape[1]}x{valid.shape[0]} but the image is "
                             f"{gray.shape[1]}x{gray.shape[0]}")
        k = cv2.getStructuringElement(cv2.MORPH_RECT, (5, 5))
        masks = [valid]
        for im in imgs[1:]:
            m = cv2.erode(masks[-1].view(np.uint8), k, borderValue=1)[::2, ::2][: im.shape[0], : im.shape[1]]
            masks.append(m > 0)
    return Pyramid(
        [with_gradients(im) for im in imgs],
        [level_camera(camera, i, (im.shape[1], im.shape[0])) for i, im in enumerate(imgs)],
        masks,
    )


def bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) at float pixels (N,) -> (N, C); callers keep ``0 <= u <= W-1``, ``0 <= v <= H-1``."""
    h, w = img.shape[:2]
    u0 = u.astype(np.int32)
    v0 = v.astype(np.int32)
    np.clip(u0, 0, w - 2, out=u0)
    np.clip(v0, 0, h - 2, out=v0)
    fu = (u - u0).astype(img.dtype)[:, None]  # weights in the image dtype (float32 in tracking)
    fv = (v - v0).astype(img.dtype)[:, None]
    flat = img.reshape(h * w, -1)
    i00 = v0 * w + u0
    a = np.take(flat, i00, 0)
    b = np.take(flat, i00 + 1, 0)
    c = np.take(flat, i00 + w, 0)
    d = np.take(flat, i00 + w + 1, 0)
    top = a + (b - a) * fu
    bot = c + (d - c) * fu
    return top + (bot - top) * fv


# ----------------------------------------------------------------------------- reference points
def select_pixels(gray: np.ndarray, num_points: int, min_grad: float = 0.02, valid: Optional[np.ndarray] = None,
                  border: int = 4) -> np.ndarray:
    """High-gradient pixels spread over the image: the strongest pixel of each grid cell.

    The cell size is chosen so that about ``1.5 * num_points`` cells cover the image;
    cells whose best gradient magnitude is below ``min_grad`` (grey levels per pixel)
    are skipped and at most ``num_points`` of the strongest survivors are kept.
    Returns integer pixel coordinates (N, 2) as (u, v).
    """
    h, w = gray.shape
    g = with_gradients(gray)
    mag = np.sqrt(g[..., 1] ** 2 + g[..., 2] ** 2)
    mask = np.zeros_like(mag, dtype=bool)
    mask[border:h - border, border:w - border] = True
    if valid is not None:
        mask &= valid
    mag = np.where(mask, mag, 0.0)
    cell = max(1, int(math.sqrt(h * w / (1.5 * max(num_points, 1)))))
    hc, wc = h // cell, w // cell
    blocks = (mag[: hc * cell, : wc * cell].reshape(hc, cell, wc, cell).transpose(0, 2, 1, 3)
              .reshape(hc, wc, cell * cell))
    arg = blocks.argmax(-1)
    best = np.take_along_axis(blocks, arg[..., None], -1)[..., 0]
    cy, cx = np.meshgrid(np.arange(hc), np.arange(wc), indexing="ij")
    v = cy * cell + arg // cell
    u = cx * cell + arg % cell
    keep = best > min_grad
    u, v, best = u[keep], v[keep], best[keep]
    if len(best) > num_points:
        top = np.argpartition(-best, num_points - 1)[:num_points]
        u, v = u[top], v[top]
    return np.stack([u, v], -1).astype(np.int64)


DepthSource = Union[np.ndarray, Callable[[np.ndarray], np.ndarray]]


@dataclass
class Reference:
    """A keyframe prepared for alignment: 3D points in its camera frame and their intensities per level."""

    c2w: np.ndarray  # (4, 4) float64
    points: np.ndarray  # (N, 3) float64, reference camera frame
    intensities: list  # per level (N,) float32 grey of the reference pyramid at the projected points
    pyramid: Pyramid
    uv: np.ndarray  # (N, 2) selected full-resolution pixels
    median_depth: float
    frame_index: int = -1
    gray: Optional[np.ndarray] = None


def image_valid_mask(rgb: np.ndarray, erode: int = 4) -> Optional[np.ndarray]:
    """Pixels away from exactly-black fill (undistortion borders); None when there is no such fill."""
    img = np.ascontiguousarray(rgb)
    if img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3:
        black = cv2.inRange(img, (0, 0, 0), (0, 0, 0))  # 255 where all channels are 0 (fast path)
    else:
        black = (img.reshape(img.shape[0], img.shape[1], -1) == 0).all(-1).astype(np.uint8) * 255
    if cv2.countNonZero(black) == 0:
        return None
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * erode + 1, 2 * erode + 1))
    return cv2.erode(cv2.bitwise_not(black), k) > 0


def make_reference(rgb: np.ndarray, depth: DepthSource, camera: PinholeCamera, c2w: np.ndarray, levels: int = 3,
                   num_points: int = 2500, min_grad: float = 0.02, frame_index: int = -1,
                   min_depth: float = 1e-3, blur: float = 0.0) -> Reference:
    """Select pixels on the keyframe image and attach depth.

    ``depth`` is either an (H, W) metric depth image (0 / non-finite = invalid) or
    a callable ``uv (N, 2) float64 -> depth (N,)`` that is queried only at the
    selected pixels (e.g. volume rendering through the map; return NaN or 0 where
    the map is empty).
    """
    gray = to_gray(rgb)
    pyr = build_pyramid(gray, camera, levels, blur)
    border_ok = image_valid_mask(rgb)
    if callable(depth):
        uv = select_pixels(gray, num_points, min_grad, border_ok)
        z = np.asarray(depth(uv.astype(np.float64)), np.float64).reshape(-1)
        if z.shape[0] != uv.shape[0]:
            raise ValueError(f"depth callable returned {z.shape[0]} values for {uv.shape[0]} pixels")
    else:
        d = np.asarray(depth, np.float64)
        if d.shape != gray.shape:
            raise ValueError(f"depth is {d.shape[1]}x{d.shape[0]} but the image is {gray.shape[1]}x{gray.shape[0]}")
        valid = np.isfinite(d) & (d > min_depth)
        if border_ok is not None:
            valid &= border_ok
        uv = select_pixels(gray, num_points, min_grad, valid)
        z = d[uv[:, 1], uv[:, 0]]
    ok = np.isfinite(z) & (z > min_depth)
    uv, z = uv[ok], z[ok]
    pts = np.stack([(uv[:, 0] - camera.cx) / camera.fx * z, (uv[:, 1] - camera.cy) / camera.fy * z, z], -1)
    return _reference(pyr, pts, uv, c2w, frame_index, gray)


def reference_from_points(rgb: np.ndarray, points_cam: np.ndarray, camera: PinholeCamera, c2w: np.ndarray,
                          levels: int = 3, frame_index: int = -1, blur: float = 0.0, margin: float = 2.0) -> Reference:
    """A reference from 3D points already in the keyframe's camera frame (e.g. triangulated tracks).

    Points behind the camera or projecting outside the image (``margin`` pixels) are dropped.
    """
    gray = to_gray(rgb)
    pyr = build_pyramid(gray, camera, levels, blur)
    pts = np.asarray(points_cam, np.float64).reshape(-1, 3)
    z = pts[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    u = camera.fx * pts[:, 0] / zs + camera.cx
    v = camera.fy * pts[:, 1] / zs + camera.cy
    ok = ((z > 1e-3) & (u >= margin) & (u <= camera.width - 1 - margin) & (v >= margin)
          & (v <= camera.height - 1 - margin))
    border_ok = image_valid_mask(rgb)
    if border_ok is not None:
        iu = np.clip(np.round(u), 0, camera.width - 1).astype(int)
        iv = np.clip(np.round(v), 0, camera.height - 1).astype(int)
        ok &= border_ok[iv, iu]
    return _reference(pyr, pts[ok], np.stack([u[ok], v[ok]], -1), c2w, frame_index, gray)


def _reference(pyr: Pyramid, pts: np.ndarray, uv: np.ndarray, c2w, frame_index: int, gray) -> Reference:
    intens = []
    for lvl, cam in zip(pyr.levels, pyr.cameras):
        pu = cam.fx * pts[:, 0] / np.maximum(pts[:, 2], 1e-9) + cam.cx
        pv = cam.fy * pts[:, 1] / np.maximum(pts[:, 2], 1e-9) + cam.cy
        pu = np.clip(pu, 0, cam.width - 1)
        pv = np.clip(pv, 0, cam.height - 1)
        intens.append(bilinear(lvl[..., :1], pu, pv)[:, 0])
    med = float(np.median(pts[:, 2])) if len(pts) else float("nan")
    return Reference(np.asarray(c2w, np.float64), pts, intens, pyr, uv, med, frame_index, gray)


# ----------------------------------------------------------------------------- residuals and Jacobians
def warp_residuals(level_img: np.ndarray, cam: PinholeCamera, points: np.ndarray, ref_int: np.ndarray,
                   t_cr: np.ndarray, affine: np.ndarray, with_jacobian: bool = True, margin: float = 1.0,
                   mask: Optional[np.ndarray] = None):
    """Photometric residuals of reference points warped into a pyramid level of the current frame.

    Returns ``(r, J, valid)``: residuals (M,) for the valid points, Jacobian (M, 8)
    with respect to ``(delta_rho, delta_phi, a, b)`` for ``T_cr <- se3_exp(delta) @ T_cr``,
    ``a <- a + da``, ``b <- b + db``; and the boolean mask (N,) of points that land
    in the image (``margin`` pixels inside) in front of the camera and, when ``mask``
    (H_l, W_l) bool is given, on a valid pixel (nearest).
    """
    y = points @ t_cr[:3, :3].T + t_cr[:3, 3]
    z = y[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    u = cam.fx * y[:, 0] / zs + cam.cx
    v = cam.fy * y[:, 1] / zs + cam.cy
    valid = (z > 1e-6) & (u >= margin) & (u <= cam.width - 1 - margin) & (v >= margin) & (v <= cam.height - 1 - margin)
    if mask is not None:
        iu = np.clip(np.rint(u), 0, cam.width - 1).astype(np.int64)
        iv = np.clip(np.rint(v), 0, cam.height - 1).astype(np.int64)
        valid &= mask[iv, iu]
    idx = np.flatnonzero(valid)
    s = bilinear(level_img, u[idx], v[idx]).astype(np.float64)
    ea = math.exp(affine[0])
    iref = ref_int[idx].astype(np.float64)
    r = s[:, 0] - (ea * iref + affine[1])
    if not with_jacobian:
        return r, None, valid
    yv = y[idx]
    iz = 1.0 / yv[:, 2]
    gu = s[:, 1] * cam.fx * iz  # dI/du * du/dx-part
    gv = s[:, 2] * cam.fy * iz
    # dI/dY = (gu, gv, -(gu x + gv y)/z)
    gz = -(gu * yv[:, 0] + gv * yv[:, 1]) * iz
    jac = np.empty((len(idx), 8))
    jac[:, 0] = gu
    jac[:, 1] = gv
    jac[:, 2] = gz
    # rotation block: dY/dphi = -hat(Y)  ->  g^T (-hat(Y)) = Y x g
    x_, y_, z_ = yv[:, 0], yv[:, 1], yv[:, 2]
    jac[:, 3] = y_ * gz - z_ * gv
    jac[:, 4] = z_ * gu - x_ * gz
    jac[:, 5] = x_ * gv - y_ * gu
    jac[:, 6] = -ea * iref
    jac[:, 7] = -1.0
    return r, jac, valid


def huber_weights(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def huber_cost(r: np.ndarray, k: float) -> float:
    a = np.abs(r)
    return float(np.where(a <= k, 0.5 * a * a, k * (a - 0.5 * k)).mean()) if len(a) else float("inf")


def robust_scale(r: np.ndarray, floor: float) -> float:
    """1.4826 * median absolute residual, at least ``floor``."""
    if len(r) == 0:
        return floor
    return max(floor, 1.4826 * float(np.median(np.abs(r))))


# ----------------------------------------------------------------------------- the optimiser
def _total_cost(r: np.ndarray, k: float, ab: np.ndarray, cfg: "AlignConfig") -> float:
    prior = 0.5 * cfg.affine_prior * float(ab @ ab) if cfg.affine else 0.0
    return huber_cost(r, k) + prior

@dataclass
class AlignConfig:
    levels: int = 3
    blur: float = 0.0  # Gaussian sigma (pixels) applied to level 0 of both images
    iterations: tuple = (12, 10, 8)  # per level, fine (0) ... coarse
    affine: bool = True  # estimate brightness gain / offset
    huber_k: float = 1.345  # in units of the robust scale
    scale_floor: float = 2.0 / 255.0  # lower bound of the robust residual scale
    inlier_threshold: float = 0.05  # |r| (grey levels in [0, 1]) counted as inlier
    min_valid: int = 30  # fewer visible points -> failure
    step_tol: float = 1e-6  # stop when |delta| (m / rad) is below
    lm_init: float = 1e-4
    affine_prior: float = 1e-4  # weight of 0.5 * |(a, b)|^2 added to the mean robust cost
    affine_bound: tuple = (0.5, 0.3)  # |a| (log gain) and |b| (offset) are clipped to these


@dataclass
class AlignResult:
    t_cr: np.ndarray  # (4, 4) reference -> current camera
    affine: np.ndarray  # (a, b)
    rmse: float  # RMS photometric residual of the valid points at level 0 (grey levels)
    inlier_ratio: float  # fraction of valid points with |r| < inlier_threshold
    visible_ratio: float  # fraction of reference points that land in the current image
    iterations: int
    ok: bool  # enough points and a finite solution
    ref_std: float = 0.0  # std of the reference intensities of the valid points (the residual's yardstick)
    hessian: Optional[np.ndarray] = None  # 6x6 pose block at level 0 (information)


def align(ref: Reference, cur: Pyramid, t_init: np.ndarray, cfg: AlignConfig,
          affine_init: Optional[np.ndarray] = None, trace: Optional[list] = None) -> AlignResult:
    """Coarse-to-fine Levenberg-Marquardt on the robust photometric cost.

    ``trace``, when given, receives one dict per iteration (level, cost, lambda, step).
    """
    t = np.array(t_init, np.float64)
    ab = np.zeros(2) if affine_init is None else np.array(affine_init, np.float64)
    nparam = 8 if cfg.affine else 6
    n_levels = min(cfg.levels, len(cur.levels), len(ref.intensities))
    total_it = 0
    h6 = None
    for lvl in reversed(range(n_levels)):
        img, cam, iref = cur.levels[lvl], cur.cameras[lvl], ref.intensities[lvl]
        msk = cur.masks[lvl] if cur.masks is not None else None
        iters = cfg.iterations[lvl] if lvl < len(cfg.iterations) else cfg.iterations[-1]
        lam = cfg.lm_init
        r, jac, valid = warp_residuals(img, cam, ref.points, iref, t, ab, mask=msk)
        if len(r) < cfg.min_valid:
            continue
        k = cfg.huber_k * robust_scale(r, cfg.scale_floor)
        cost = _total_cost(r, k, ab, cfg)
        for _ in range(iters):
            total_it += 1
            w = huber_weights(r, k)
            m = max(len(r), 1)
            jw = jac[:, :nparam] * (w / m)[:, None]
            hess = jw.T @ jac[:, :nparam]
            grad = jw.T @ r
            if cfg.affine:
                hess[6:, 6:] += np.eye(2) * cfg.affine_prior
                grad[6:] += cfg.affine_prior * ab
            accepted = False
            step = np.zeros(nparam)
            for _try in range(4):
                hd = hess + lam * np.diag(np.diag(hess) + 1e-12)
                try:
                    step = -np.linalg.solve(hd, grad)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                t_new = se3_exp_np(step[:6]) @ t
                ab_new = (np.clip(ab + step[6:8], -np.asarray(cfg.affine_bound), np.asarray(cfg.affine_bound))
                          if cfg.affine else ab)
                r_new, jac_new, valid_new = warp_residuals(img, cam, ref.points, iref, t_new, ab_new, mask=msk)
                if len(r_new) >= cfg.min_valid and _total_cost(r_new, k, ab_new, cfg) <= cost * (1 + 1e-9):
                    t, ab, r, jac, valid = t_new, ab_new, r_new, jac_new, valid_new
                    lam = max(lam * 0.3, 1e-7)
                    accepted = True
                    break
                lam *= 8
            if trace is not None:
                trace.append({"level": lvl, "cost": cost, "lam": lam, "accepted": accepted,
                              "step": float(np.linalg.norm(step[:6])), "n": len(r)})
            if not accepted or np.linalg.norm(step[:6]) < cfg.step_tol:
                break
            # re-estimate the robust scale as the fit improves
            k = cfg.huber_k * robust_scale(r, cfg.scale_floor)
            cost = _total_cost(r, k, ab, cfg)
        if lvl == 0:
            w = huber_weights(r, k)
            h6 = (jac[:, :6] * w[:, None]).T @ jac[:, :6]
    r, _, valid = warp_residuals(cur.levels[0], cur.cameras[0], ref.points, ref.intensities[0], t, ab,
                                 with_jacobian=False,
                                 mask=cur.masks[0] if cur.masks is not None else None)
    return _result(ref, t, ab, r, valid, cfg, total_it, h6)


def _result(ref: Reference, t: np.ndarray, ab: np.ndarray, r: np.ndarray, valid: np.ndarray, cfg: AlignConfig,
            iterations: int, hessian: Optional[np.ndarray] = None) -> AlignResult:
    """The :class:`AlignResult` of pose ``t`` and brightness ``ab`` from the full-resolution residuals ``r`` of
    the reference's points that land in the image (``valid``)."""
    ok = len(r) >= cfg.min_valid and bool(np.all(np.isfinite(t)))
    rmse = float(np.sqrt(np.mean(r * r))) if len(r) else float("inf")
    inl = float(np.mean(np.abs(r) < cfg.inlier_threshold)) if len(r) else 0.0
    ref_std = float(np.std(ref.intensities[0][valid])) if len(r) else 0.0
    return AlignResult(orthonormalize(t), ab, rmse, inl, float(valid.sum()) / max(len(ref.points), 1), iterations,
                       ok, ref_std=ref_std, hessian=hessian)


def evaluate_pose(ref: Reference, gray: np.ndarray, cam: PinholeCamera, t_cr: np.ndarray, cfg: AlignConfig,
                  affine_init: Optional[np.ndarray] = None, mask: Optional[np.ndarray] = None,
                  affine_steps: int = 3) -> AlignResult:
    """The measures :func:`align` reports (residual, inlier and visible ratios), for the pose ``t_cr``
    found elsewhere (reference -> current camera), which is not moved: only the brightness gain / offset
    are fitted, by ``affine_steps`` robust Gauss-Newton steps from ``affine_init``. ``gray`` is the
    current frame's full-size grey image (:func:`to_gray`; ``cfg.blur`` is applied here, as to a pyramid's
    level 0), ``mask`` its valid pixels. One warp of the reference's points: a small part of an alignment's cost."""
    if cfg.blur > 0:
        gray = cv2.GaussianBlur(gray, (0, 0), cfg.blur)
    t = np.asarray(t_cr, np.float64)
    ab = np.zeros(2) if affine_init is None else np.array(affine_init, np.float64)
    r, _, valid = warp_residuals(gray[..., None], cam, ref.points, ref.intensities[0], t, ab, mask=mask,
                                 with_jacobian=False)
    if cfg.affine and len(r) >= cfg.min_valid:
        iref = ref.intensities[0][valid].astype(np.float64)
        sampled = r + math.exp(ab[0]) * iref + ab[1]
        for _ in range(affine_steps):
            k = cfg.huber_k * robust_scale(r, cfg.scale_floor)
            w = huber_weights(r, k) / max(len(r), 1)
            ea = math.exp(ab[0])
            j = np.stack([-ea * iref, -np.ones_like(iref)], -1)  # d r / d (a, b)
            jw = j * w[:, None]
            step = -np.linalg.solve(jw.T @ j + np.eye(2) * cfg.affine_prior, jw.T @ r + cfg.affine_prior * ab)
            ab = np.clip(ab + step, -np.asarray(cfg.affine_bound), np.asarray(cfg.affine_bound))
            r = sampled - (math.exp(ab[0]) * iref + ab[1])
    return _result(ref, t, ab, r, valid, cfg, 0)
