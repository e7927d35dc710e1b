"""Pose-graph optimisation over keyframe poses (camera-to-world 4x4, see :mod:`fmapping.geometry`).

Each edge ``(i, j, T_ij)`` says "keyframe ``j`` seen from keyframe ``i`` is ``T_ij``"
(``inv(X_i) @ X_j``). The graph of a loop closure is the chain of consecutive
keyframes (their relative poses as tracked) plus one loop edge that contradicts the
chain by the drift; least squares spreads that contradiction over the chain. The
residual of an edge is ``E = inv(T_ij) @ inv(X_i) @ X_j`` written as (rotation vector
of ``E``, translation of ``E`` / ``unit``): ``unit`` (metres per radian, e.g. the median
scene depth) weighs a rotation error against the image motion a translation error makes.
Each pose ``X_k`` is perturbed as ``[exp(phi_k) R_k | t_k + unit d_k]`` about its current value.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from fmapping.geometry import hat_np, so3_right_jacobian_inv_np


def edge_residuals(rot: np.ndarray, trans: np.ndarray, edges_i: np.ndarray, edges_j: np.ndarray,
                   rel: np.ndarray, unit: float) -> np.ndarray:
    """(E, 6) residuals of the edges for poses given as rotations (N, 3, 3) and centres (N, 3)."""
    ri, rj, ti, tj = rot[edges_i], rot[edges_j], trans[edges_i], trans[edges_j]
    rel_r, rel_t = rel[:, :3, :3], rel[:, :3, 3]
    # X_i^-1 X_j = [Ri^T Rj | Ri^T (tj - ti)];  E = T_ij^-1 (X_i^-1 X_j)
    r_ij = np.einsum("nki,nkj->nij", ri, rj)
    t_ij = np.einsum("nki,nk->ni", ri, tj - ti)
    e_r = np.einsum("nki,nkj->nij", rel_r, r_ij)
    e_t = np.einsum("nki,nk->ni", rel_r, t_ij - rel_t)
    return np.concatenate([Rotation.from_matrix(e_r).as_rotvec(), e_t / unit], axis=1)


def edge_jacobians(rot: np.ndarray, trans: np.ndarray, edges_i: np.ndarray, edges_j: np.ndarray,
                   rel: np.ndarray, unit: float, res: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d(residual)/d(pose i) and d(residual)/d(pose j), each (E, 6, 6), for each pose perturbed as
    ``X = [exp(phi) R | t + unit d]`` about its current value (parameters ``(phi, d)``); ``res`` (E, 6) are
    the residuals there (:func:`edge_residuals`). With ``E_R = Rrel^T Ri^T Rj`` and
    ``e_t = Rrel^T (Ri^T (tj - ti) - trel) / unit``: ``d e_r = Jr^-1(e_r) Rj^T (dphi_j - dphi_i)``,
    ``d e_t = Rrel^T Ri^T (unit (dd_j - dd_i) + hat(tj - ti) dphi_i) / unit``."""
    ri, rj = rot[edges_i], rot[edges_j]
    a = so3_right_jacobian_inv_np(res[:, :3]) @ np.swapaxes(rj, 1, 2)  # Jr^-1 Rj^T
    b = np.swapaxes(rel[:, :3, :3], 1, 2) @ np.swapaxes(ri, 1, 2)  # Rrel^T Ri^T
    ji, jj = np.zeros((len(edges_i), 6, 6)), np.zeros((len(edges_i), 6, 6))
    ji[:, :3, :3], jj[:, :3, :3] = -a, a
    ji[:, 3:, :3] = b @ hat_np(trans[edges_j] - trans[edges_i]) / unit
    ji[:, 3:, 3:], jj[:, 3:, 3:] = -b, b
    return ji, jj


def optimize_pose_graph(poses: Sequence[np.ndarray], edges: Sequence[tuple[int, int, np.ndarray]],
                        fixed: Sequence[int], unit: float = 1.0, max_iters: int = 50,
                        rel_tol: float = 1e-12) -> tuple[list, dict]:
    """Poses (list of 4x4) that best agree with the relative-pose ``edges``; poses in ``fixed``
    stay. Levenberg-Marquardt with the analytic Jacobians (:func:`edge_jacobians`) on the dense
    normal equations of the free poses (6 each; a loop's graph has tens of keyframes); it stops when
    a step lowers the cost by less than ``rel_tol`` of it, or after ``max_iters`` Jacobians.
    Returns (poses, {"cost_before", "cost_after", "nfev"})."""
    poses = [np.asarray(p, np.float64) for p in poses]
    n = len(poses)
    fixed_set = set(int(f) for f in fixed)
    free = [k for k in range(n) if k not in fixed_set]
    if not fixed_set:
        raise ValueError("optimize_pose_graph: at least one pose must be fixed (the gauge)")
    col = np.full(n, -1, np.int64)
    col[free] = np.arange(len(free))
    rot = np.stack([p[:3, :3] for p in poses])
    trans = np.stack([p[:3, 3] for p in poses])
    ei = np.array([e[0] for e in edges], np.int64)
    ej = np.array([e[1] for e in edges], np.int64)
    rel = np.stack([np.asarray(e[2], np.float64) for e in edges])
    res = edge_residuals(rot, trans, ei, ej, rel, unit)
    cost = cost_before = 0.5 * float(np.sum(res * res))
    nfev, nf, lam = 1, len(free), 1e-4
    for _ in range(max_iters if nf else 0):
        ji, jj = edge_jacobians(rot, trans, ei, ej, rel, unit, res)
        h = np.zeros((nf, nf, 6, 6))
        g = np.zeros((nf, 6))
        for ja, ca in ((ji, col[ei]), (jj, col[ej])):
            use = ca >= 0
            np.add.at(g, ca[use], np.einsum("eki,ek->ei", ja[use], res[use]))
            for jb, cb in ((ji, col[ei]), (jj, col[ej])):
                both = use & (cb >= 0)
                np.add.at(h, (ca[both], cb[both]), np.swapaxes(ja[both], 1, 2) @ jb[both])
        h = h.transpose(0, 2, 1, 3).reshape(6 * nf, 6 * nf)
        diag = np.diag(h).copy()
        improved = False
        while lam < 1e8:
            try:
                dx = np.linalg.solve(h + lam * np.diag(diag + 1e-12), -g.reshape(-1)).reshape(nf, 6)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            if -0.5 * float(g.reshape(-1) @ dx.reshape(-1)) <= rel_tol * cost + 1e-30:
                break  # what the step could still gain is below the tolerance: converged
            rot_new, trans_new = rot.copy(), trans.copy()
            rot_new[free] = Rotation.from_rotvec(dx[:, :3]).as_matrix() @ rot[free]
            trans_new[free] = trans[free] + unit * dx[:, 3:]
            res_new = edge_residuals(rot_new, trans_new, ei, ej, rel, unit)
            nfev += 1
            c_new = 0.5 * float(np.sum(res_new * res_new))
            if c_new < cost:
                gain = (cost - c_new) / max(cost, 1e-300)
                rot, trans, res, cost = rot_new, trans_new, res_new, c_new
                lam = max(lam / 10.0, 1e-12)
                improved = gain > rel_tol
                break
            lam *= 10.0
        if not improved:
            break
    out = []
    for k in range(n):
        p = np.eye(4)
        p[:3, :3], p[:3, 3] = rot[k], trans[k]
        out.append(p)
    return out, {"cost_before": cost_before, "cost_after": cost, "nfev": nfev}
