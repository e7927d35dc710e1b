"""Windowed bundle adjustment of keyframe poses and sparse points (reprojection error, Huber).

Residuals ``pi(T_cw X) - uv`` for every observation; poses are updated as
``T_cw <- se3_exp(dx) @ T_cw`` (world-to-camera, left-multiplied; the caller's
camera-to-world poses are converted at the boundary), points additively.
Solved by Levenberg-Marquardt with iteratively reweighted Huber weights, the points
eliminated by the Schur complement (3x3 blocks) so only a small dense pose system
is solved; analytic Jacobians (tested against finite differences).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.tracking.direct import exp_se3, inv_pose, orthonormalize


@dataclass
class BAResult:
    poses: list  # refined camera-to-world poses (same order as given)
    points: np.ndarray  # (M, 3) refined world points
    residual_px: np.ndarray  # (O,) reprojection error norm per observation after BA
    cost_before: float
    cost_after: float
    nfev: int


def _project(camera: PinholeCamera, t_cw: np.ndarray, x: np.ndarray):
    y = np.einsum("nij,nj->ni", t_cw[:, :3, :3], x) + t_cw[:, :3, 3]
    z = y[:, 2]
    zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
    uv = np.stack([camera.fx * y[:, 0] / zs + camera.cx, camera.fy * y[:, 1] / zs + camera.cy], -1)
    return uv, y, zs


def reprojection_jacobians(camera: PinholeCamera, t_cw: np.ndarray, x: np.ndarray):
    """d(uv)/d(pose twist) (O, 2, 6) and d(uv)/dX (O, 2, 3) at the given poses (O, 4, 4) and points (O, 3)."""
    _, y, z = _project(camera, t_cw, x)
    iz = 1.0 / z
    dpi = np.zeros((len(x), 2, 3))
    dpi[:, 0, 0] = camera.fx * iz
    dpi[:, 0, 2] = -camera.fx * y[:, 0] * iz * iz
    dpi[:, 1, 1] = camera.fy * iz
    dpi[:, 1, 2] = -camera.fy * y[:, 1] * iz * iz
    dy_dxi = np.zeros((len(x), 3, 6))
    dy_dxi[:, :, :3] = np.eye(3)
    # -hat(y)
    dy_dxi[:, 0, 4] = y[:, 2]
    dy_dxi[:, 0, 5] = -y[:, 1]
    dy_dxi[:, 1, 3] = -y[:, 2]
    dy_dxi[:, 1, 5] = y[:, 0]
    dy_dxi[:, 2, 3] = y[:, 1]
    dy_dxi[:, 2, 4] = -y[:, 0]
    j_pose = dpi @ dy_dxi
    j_point = dpi @ t_cw[:, :3, :3]
    return j_pose, j_point


def _huber_w(r2: np.ndarray, k: float) -> np.ndarray:
    n = np.sqrt(r2)
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-12))


def _robust_cost(r2: np.ndarray, k: float) -> float:
    n = np.sqrt(r2)
    return float(np.sum(np.where(n <= k, 0.5 * r2, k * (n - 0.5 * k))))


def bundle_adjust(camera: PinholeCamera, poses_c2w: Sequence[np.ndarray], fixed: Sequence[int], points: np.ndarray,
                  obs_kf: np.ndarray, obs_pt: np.ndarray, obs_uv: np.ndarray, huber_px: float = 1.5,
                  max_nfev: int = 15) -> BAResult:
    """Refine the non-``fixed`` poses and all ``points`` from observations (keyframe index, point index, pixel).

    Levenberg-Marquardt with Huber weights (IRLS); each iteration eliminates the points
    (Schur complement, 3x3 blocks) and solves the small dense pose system. ``max_nfev``
    bounds the number of residual evaluations.
    """
    k = len(poses_c2w)
    obs_kf = np.asarray(obs_kf, np.int64)
    obs_pt = np.asarray(obs_pt, np.int64)
    obs_uv = np.asarray(obs_uv, np.float64)
    t = np.stack([inv_pose(np.asarray(p, np.float64)) for p in poses_c2w])
    x = np.asarray(points, np.float64).copy()
    m = len(x)
    fixed = set(int(f) for f in fixed)
    free = [i for i in range(k) if i not in fixed]
    col = np.full(k, -1, np.int64)
    col[free] = np.arange(len(free))
    nf = len(free)
    oc = col[obs_kf]  # free-pose column of each observation (-1: fixed)

    def residuals(t_, x_):
        uv, _, _ = _project(camera, t_[obs_kf], x_[obs_pt])
        r = uv - obs_uv
        return r, (r * r).sum(1)

    r, r2 = residuals(t, x)
    cost0 = cost = _robust_cost(r2, huber_px)
    lam = 1e-3
    nfev = 1
    while nfev < max_nfev:
        w = _huber_w(r2, huber_px)
        jp, jx = reprojection_jacobians(camera, t[obs_kf], x[obs_pt])
        jxw = jx * w[:, None, None]
        hxx = np.zeros((m, 3, 3))
        np.add.at(hxx, obs_pt, np.einsum("oai,oaj->oij", jxw, jx))
        gx = np.zeros((m, 3))
        np.add.at(gx, obs_pt, np.einsum("oai,oa->oi", jxw, r))
        hpp = np.zeros((nf, 6, 6))
        gp = np.zeros((nf, 6))
        wmat = np.zeros((nf, 6, m, 3))  # pose-point coupling blocks
        fo = oc >= 0
        if nf and fo.any():
            jpw = jp[fo] * w[fo, None, None]
            np.add.at(hpp, oc[fo], np.einsum("oai,oaj->oij", jpw, jp[fo]))
            np.add.at(gp, oc[fo], np.einsum("oai,oa->oi", jpw, r[fo]))
            np.add.at(wmat, (oc[fo], slice(None), obs_pt[fo]), np.einsum("oai,oaj->oij", jpw, jx[fo]))
        improved = False
        while nfev < max_nfev:
            hxx_d = hxx + lam * (np.eye(3) * (np.einsum("mii->mi", hxx)[:, :, None] + 1e-9))
            hinv = np.linalg.inv(hxx_d)
            if nf:
                big_h = np.zeros((nf * 6, nf * 6))
                for a in range(nf):
                    big_h[6 * a:6 * a + 6, 6 * a:6 * a + 6] = hpp[a] + lam * np.diag(np.diag(hpp[a]) + 1e-9)
                wf = wmat.reshape(nf * 6, m, 3)
                wh = np.einsum("pmi,mij->pmj", wf, hinv)
                schur = big_h - np.einsum("pmj,qmj->pq", wh, wf)
                rhs = -gp.reshape(-1) + np.einsum("pmj,mj->p", wh, gx)
                try:
                    dp = np.linalg.solve(schur, rhs)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                dx = -np.einsum("mij,mj->mi", hinv, gx + np.einsum("pmi,p->mi", wf, dp))
            else:
                dp = np.zeros(0)
                dx = -np.einsum("mij,mj->mi", hinv, gx)
            t_new = t.copy()
            for a, pi in enumerate(free):
                t_new[pi] = exp_se3(dp[6 * a:6 * a + 6]) @ t[pi]
            x_new = x + dx
            r_new, r2_new = residuals(t_new, x_new)
            nfev += 1
            c_new = _robust_cost(r2_new, huber_px)
            if c_new < cost:
                t, x, r, r2 = t_new, x_new, r_new, r2_new
                rel = (cost - c_new) / max(cost, 1e-12)
                cost = c_new
                lam = max(lam / 3, 1e-9)
                improved = rel > 1e-9
                break
            lam *= 5
        if not improved:
            break
    return BAResult([orthonormalize(inv_pose(ti)) for ti in t], x, np.sqrt(r2), cost0, cost, nfev)
