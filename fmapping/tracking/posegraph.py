"""Pose-graph optimisation over keyframe poses (camera-to-world 4x4, see :mod:`fmapping.geometry`).

Each edge ``(i, j, T_ij)`` says "keyframe ``j`` seen from keyframe ``i`` is ``T_ij``"
(``inv(X_i) @ X_j``). The graph of a loop closure is the chain of consecutive
keyframes (their relative poses as tracked) plus one loop edge that contradicts the
chain by the drift; least squares spreads that contradiction over the chain. The
residual of an edge is ``E = inv(T_ij) @ inv(X_i) @ X_j`` written as (rotation vector
of ``E``, translation of ``E`` / ``unit``): ``unit`` (metres per radian, e.g. the median
scene depth) weighs a rotation error against the image motion a translation error makes.
Each pose ``X_k`` is parametrised as ``[exp(phi_k) R_k | t_k + d_k]`` about its start.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation


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


def optimize_pose_graph(poses: Sequence[np.ndarray], edges: Sequence[tuple[int, int, np.ndarray]],
                        fixed: Sequence[int], unit: float = 1.0, max_nfev: int = 50) -> tuple[list, dict]:
    """Poses (list of 4x4) that best agree with the relative-pose ``edges``; poses in ``fixed``
    stay. Returns (poses, {"cost_before", "cost_after", "nfev"})."""
    poses = [np.asarray(p, np.float64) for p in poses]
    n = len(poses)
    fixed_set = set(int(f) for f in fixed)
    free = [k for k in range(n) if k not in fixed_set]
    if not fixed_set:
        raise ValueError("optimize_pose_graph: at least one pose must be fixed (the gauge)")
    col = {k: c for c, k in enumerate(free)}
    r0 = np.stack([p[:3, :3] for p in poses])
    t0 = np.stack([p[:3, 3] for p in poses])
    ei = np.array([e[0] for e in edges], np.int64)
    ej = np.array([e[1] for e in edges], np.int64)
    rel = np.stack([np.asarray(e[2], np.float64) for e in edges])

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rot, trans = r0.copy(), t0.copy()
        if free:
            d = x.reshape(len(free), 6)
            rot[free] = Rotation.from_rotvec(d[:, :3]).as_matrix() @ r0[free]
            trans[free] = t0[free] + d[:, 3:] * unit
        return rot, trans

    def fun(x: np.ndarray) -> np.ndarray:
        rot, trans = unpack(x)
        return edge_residuals(rot, trans, ei, ej, rel, unit).reshape(-1)

    x0 = np.zeros(6 * len(free))
    res0 = fun(x0)
    cost_before = 0.5 * float(res0 @ res0)
    if not free:
        return poses, {"cost_before": cost_before, "cost_after": cost_before, "nfev": 0}
    sparsity = lil_matrix((6 * len(edges), 6 * len(free)), dtype=np.int8)
    for e, (i, j) in enumerate(zip(ei, ej)):
        for k in (int(i), int(j)):
            if k in col:
                sparsity[6 * e: 6 * e + 6, 6 * col[k]: 6 * col[k] + 6] = 1
    res = least_squares(fun, x0, jac_sparsity=sparsity, method="trf", x_scale=1.0, max_nfev=max_nfev)
    rot, trans = unpack(res.x)
    out = []
    for k in range(n):
        p = np.eye(4)
        p[:3, :3], p[:3, 3] = rot[k], trans[k]
        out.append(p)
    return out, {"cost_before": cost_before, "cost_after": float(res.cost), "nfev": int(res.nfev)}
