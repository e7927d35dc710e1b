"""The relative pose of two views fitted to tracked pixel pairs on the *whitened* epipolar error: each pair's
epipolar error divided by its standard deviation under the tracks' anisotropic position covariances (an edge
point is only measured across its edge). Used by the monocular bootstrap (:func:`~fmapping.tracking.features.
two_view_init` with ``cov``), on the frame path: the fit runs from several translation directions at once.

The error of pair *i* under ``x_b = R x_a + t`` (bearings ``x = (u, v, 1)`` in normalised coordinates, ``E =
[t]_x R``) is ``r_i = e_i / s_i`` with ``e_i = x_b^T E x_a`` and ``s_i^2 = g_a^T C_i g_a + g_b^T C_i g_b``, where
``g_a``, ``g_b`` are the image-plane parts of ``E^T x_b`` and ``E x_a`` (first order). :func:`whitened_residuals`
gives the errors and their exact derivatives in a rotation increment (``R <- exp(w) R``) and a translation step on
the unit sphere (two tangent directions); :func:`robust_fit` is a Levenberg-Marquardt on the Huber cost, batched
over starts; :func:`refine_two_view_whitened` is the bootstrap's use of it.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from fmapping.camera import PinholeCamera
from fmapping.geometry import so3_exp


def bearings(camera: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> z-normalised camera rays (N, 3) (x/z, y/z, 1)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    return np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))], -1)


def normalised_cov(camera: PinholeCamera, cov: np.ndarray) -> np.ndarray:
    """Pixel covariances (N, 2, 2) in normalised image coordinates (scaled by 1 / f per axis)."""
    inv_f = np.array([1.0 / camera.fx, 1.0 / camera.fy])
    return np.asarray(cov, np.float64) * inv_f[:, None] * inv_f[None, :]


def epipolar_whitened_px(camera: PinholeCamera, rot_ab: np.ndarray, t_ab: np.ndarray, uv_a: np.ndarray,
                         uv_b: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Signed epipolar error (N,) of pixel pairs under ``x_b = rot_ab x_a + t_ab``, each divided by its standard
    deviation under the pairs' position covariances ``cov`` (N, 2, 2), the same for both pixels (first order:
    the Sampson error with anisotropic pixel noise; with the identity it is the Sampson distance in pixels)."""
    r, _ = whitened_residuals(np.asarray(rot_ab, np.float64)[None], np.asarray(t_ab, np.float64).reshape(1, 3),
                              bearings(camera, uv_a), bearings(camera, uv_b), normalised_cov(camera, cov),
                              jacobian=False)
    return r[0]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products along the last axis (numpy's ``np.cross`` without its checks: this runs per iteration)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)


def sphere_tangents(t: np.ndarray) -> np.ndarray:
    """Two unit vectors (S, 3, 2) orthogonal to each unit vector of ``t`` (S, 3) and to each other."""
    helper = np.where(np.abs(t[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    b1 = _cross(t, helper)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    return np.stack([b1, _cross(t, b1)], -1)


def whitened_residuals(rot: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray, cov_n: np.ndarray,
                       jacobian: bool = True) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Whitened epipolar errors (S, N) of bearings ``xa``, ``xb`` (N, 3) with normalised covariances ``cov_n``
    (N, 2, 2) under S poses ``rot`` (S, 3, 3), ``t`` (S, 3) (any length: the error is homogeneous in ``t``), and
    with ``jacobian`` their derivatives (S, N, 5): three for ``rot <- exp(w) rot``, two for ``t <- t + B d``
    with ``B = sphere_tangents(t)`` (``t`` of unit length)."""
    ya = xa[None] @ rot.transpose(0, 2, 1)                      # R x_a
    u = _cross(t[:, None, :], ya)                               # E x_a = t x R x_a
    w = _cross(xb[None], t[:, None, :])                         # x_b x t, so E^T x_b = R^T w
    e = (xb[None] * u).sum(-1)
    gb = u[..., :2]
    ga = (w @ rot)[..., :2]
    c00, c01, c10, c11 = cov_n[:, 0, 0], cov_n[:, 0, 1], cov_n[:, 1, 0], cov_n[:, 1, 1]
    cga = np.stack([c00 * ga[..., 0] + c01 * ga[..., 1], c10 * ga[..., 0] + c11 * ga[..., 1]], -1)
    cgb = np.stack([c00 * gb[..., 0] + c01 * gb[..., 1], c10 * gb[..., 0] + c11 * gb[..., 1]], -1)
    s = np.sqrt(np.maximum((cga * ga).sum(-1) + (cgb * gb).sum(-1), 1e-30))
    r = e / s
    if not jacobian:
        return r, None
    # d e: t . (R x_a x x_b) in t; (t . R x_a) x_b - (x_b . R x_a) t in w
    de_t = _cross(ya, xb[None])
    de_w = (t[:, None, :] * ya).sum(-1, keepdims=True) * xb[None] - (xb[None] * ya).sum(-1, keepdims=True) * t[:, None]
    # d s = ((C g_a) . d g_a + (C g_b) . d g_b) / s, with p = (C g, 0) in 3-D:
    # g_b = t x R x_a:   d/dt -> R x_a x p_b,      d/dw -> R x_a x (p_b x t)
    # g_a = R^T (x_b x t): d/dt -> (R p_a) x x_b,  d/dw -> (R p_a) x w
    pa = cga @ rot[:, :, :2].transpose(0, 2, 1)
    pb = np.concatenate([cgb, np.zeros(cgb.shape[:-1] + (1,))], -1)
    ds_t = (_cross(ya, pb) + _cross(pa, xb[None])) / s[..., None]
    ds_w = (_cross(ya, _cross(pb, t[:, None, :])) + _cross(pa, w)) / s[..., None]
    coef = (e / s ** 2)[..., None]
    dr_w = de_w / s[..., None] - coef * ds_w
    dr_t = de_t / s[..., None] - coef * ds_t
    jac = np.concatenate([dr_w, dr_t @ sphere_tangents(t)], -1)
    return r, jac


def huber_cost(r: np.ndarray, k: float) -> np.ndarray:
    """Huber cost (S,) of errors ``r`` (S, N) at threshold ``k``: ``r^2 / 2`` within it, ``k |r| - k^2 / 2``
    beyond."""
    a = np.abs(r)
    return np.where(a <= k, 0.5 * r * r, k * a - 0.5 * k * k).sum(-1)


def _step(rot: np.ndarray, t: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The poses moved by ``delta`` (S, 5): rotation increment on the left, unit translation along its tangents."""
    r_new = so3_exp(torch.from_numpy(delta[:, :3])).numpy() @ rot
    t_new = t + (sphere_tangents(t) @ delta[:, 3:, None])[..., 0]
    return r_new, t_new / np.linalg.norm(t_new, axis=1, keepdims=True)


def _normal_equations(r: np.ndarray, jac: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton normal equations (S, 5, 5), (S, 5) of the Huber cost at errors ``r`` (S, N) with Jacobians
    ``jac`` (S, N, 5): the errors weighted 1 within ``k`` and ``k / |r|`` beyond (iteratively reweighted)."""
    a = np.abs(r)
    wt = np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
    jw_t = (jac * wt[..., None]).transpose(0, 2, 1)
    return jw_t @ jac, (jw_t @ r[..., None])[..., 0]


def robust_fit(rot: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray, cov_n: np.ndarray, k: float,
               max_iters, ftol: float = 1e-8, xtol: float = 1e-8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the Huber cost (threshold ``k``) of :func:`whitened_residuals`, from S starts
    ``rot`` (S, 3, 3), ``t`` (S, 3) at once; start ``j`` stops after ``max_iters[j]`` cost evaluations (an int: the
    same for all) or when a step lowers its cost by less than ``ftol`` of it or moves it by less than ``xtol``.
    Returns the rotations, unit translations and costs (S,)."""
    rot = np.array(rot, np.float64)
    t = np.array(t, np.float64)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n_s = len(rot)
    caps = np.broadcast_to(np.asarray(max_iters), (n_s,))
    r, jac = whitened_residuals(rot, t, xa, xb, cov_n)
    cost = huber_cost(r, k)
    hess, grad = _normal_equations(r, jac, k)
    lam = np.full(n_s, 1e-3)
    evals = np.ones(n_s, int)
    active = evals < caps
    while active.any():
        idx = np.flatnonzero(active)  # only the starts still moving are evaluated
        h = hess[idx]
        diag = np.maximum(np.diagonal(h, axis1=1, axis2=2), 1e-12)
        delta = -np.linalg.solve(h + lam[idx, None, None] * (diag[:, :, None] * np.eye(5)), grad[idx, :, None])[..., 0]
        rot_n, t_n = _step(rot[idx], t[idx], delta)
        r_n, jac_n = whitened_residuals(rot_n, t_n, xa, xb, cov_n)
        cost_n = huber_cost(r_n, k)
        evals[idx] += 1
        better = cost_n < cost[idx]
        small = (cost[idx] - cost_n < ftol * cost[idx]) | (np.linalg.norm(delta, axis=1) < xtol)
        moved = idx[better]
        rot[moved], t[moved], cost[moved] = rot_n[better], t_n[better], cost_n[better]
        hess[moved], grad[moved] = _normal_equations(r_n[better], jac_n[better], k)
        lam[idx] = np.where(better, lam[idx] * 0.1, lam[idx] * 10.0)
        active[idx] = ~(better & small) & (evals[idx] < caps[idx]) & (lam[idx] < 1e12)
    return rot, t, cost


def hemisphere_directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the half sphere z >= 0 (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - i / n)
    azimuth = np.pi * (1.0 + 5 ** 0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], -1)


def _line_angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (degrees, 0-90) between the lines of unit vectors ``a`` (S, 3) and ``b`` (3,)."""
    return np.degrees(np.arccos(np.clip(np.abs(a @ b), 0.0, 1.0)))


def refine_two_view_whitened(camera: PinholeCamera, rot_ab: np.ndarray, t_ab: np.ndarray, uv_a: np.ndarray,
                             uv_b: np.ndarray, cov: np.ndarray, inlier_px: float = 1.0, starts: int = 0,
                             distinct_deg: float = 15.0, margin: float = 0.1) -> Optional[tuple]:
    """Relative rotation and unit translation (a -> b) fitted to every pair by robust least squares (Huber at
    ``inlier_px``) on :func:`epipolar_whitened_px`, then again on the pairs within ``inlier_px``. Returns
    ``(rot_ab, t_ab, inlier mask)``, or None when fewer than 20 pairs fit or the fit is ambiguous.

    With ``starts`` > 0 the fit also starts from that many translation directions spread over the half sphere
    (the rotation from ``rot_ab``; 60 cost evaluations each, against 200 for the given start) and keeps the
    lowest cost. On a nearly planar scene seen over a short baseline the cost has several minima tens of degrees
    of translation apart, and RANSAC's isotropic start can sit in a wrong one; when a minimum more than
    ``distinct_deg`` away from the best costs less than ``1 + margin`` times as much, the pairs cannot tell the
    two apart yet: None (wait for more baseline)."""
    r0 = np.asarray(rot_ab, np.float64)
    t0 = np.asarray(t_ab, np.float64).reshape(3) / max(float(np.linalg.norm(t_ab)), 1e-12)
    # bearings and normalised covariances once: the error is evaluated for every start and step
    xa, xb, cov_n = bearings(camera, uv_a), bearings(camera, uv_b), normalised_cov(camera, cov)
    t_starts = np.concatenate([t0[None], hemisphere_directions(starts) if starts > 0 else np.zeros((0, 3))])
    caps = np.r_[200, np.full(len(t_starts) - 1, 60)]
    rots, ts, costs = robust_fit(np.repeat(r0[None], len(t_starts), 0), t_starts, xa, xb, cov_n, inlier_px, caps)
    best = int(np.argmin(costs))
    apart = _line_angles_deg(ts, ts[best]) > distinct_deg
    if apart.any() and costs[apart].min() < (1.0 + margin) * costs[best]:
        return None
    rot, t = rots[best:best + 1], ts[best:best + 1]
    inl = np.abs(whitened_residuals(rot, t, xa, xb, cov_n, jacobian=False)[0][0]) < inlier_px
    if inl.sum() < 20:
        return None
    rot, t, _ = robust_fit(rot, t, xa[inl], xb[inl], cov_n[inl], inlier_px, 200)  # again on its inliers
    inl = np.abs(whitened_residuals(rot, t, xa, xb, cov_n, jacobian=False)[0][0]) < inlier_px
    if inl.sum() < 20:
        return None
    return rot[0], t[0], inl
