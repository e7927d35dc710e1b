"""Windowed bundle adjustment of keyframe poses and sparse points (reprojection error, Huber).

Residuals ``pi(T_cw X) - uv`` for every observation (each multiplied by its own 2x2 whitening matrix when
given: the monocular front end discounts a track on an edge along the edge); poses are updated as
``T_cw <- se3_exp(dx) @ T_cw`` (world-to-camera, left-multiplied; the caller's
camera-to-world poses are converted at the boundary), points additively.
Solved by Levenberg-Marquardt with iteratively reweighted Huber weights, the points
eliminated by the Schur complement (3x3 blocks) so only a small dense pose system
is solved; analytic Jacobians (tested against finite differences).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Optional, Sequence

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import inv_pose, orthonormalize, se3_exp_np


@dataclass
class BAResult:
    poses: list  # refined camera-to-world poses (same order as given)
    points: np.ndarray  # (M, 3) refined world points
    residual_px: np.ndarray  # (O,) reprojection error norm per observation after BA
    cost_before: float
    cost_after: float
    nfev: int
    ms: float = 0.0  # wall time of the solve, when the caller measured it


def _project(camera: PinholeCamera, t_cw: np.ndarray, x: np.ndarray):
    y = np.einsum("nij,nj->ni", t_cw[:, :3, :3], x) + t_cw[:, :3, 3]
    z = y[:, 2]
    zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
    uv = np.stack([camera.fx * y[:, 0] / zs + camera.cx, camera.fy * y[:, 1] / zs + camera.cy], -1)
    return uv, y, zs


def reprojection_jacobians(camera: PinholeCamera, t_cw: np.ndarray, x: np.ndarray):
    """d(uv)/d(pose twist) (O, 2, 6) and d(uv)/dX (O, 2, 3) at the given poses (O, 4, 4) and points (O, 3).

    With ``y = T_cw X`` and the projection's derivative ``dpi = [[fx/z, 0, -fx y0/z^2], [0, fy/z, -fy y1/z^2]]``:
    ``d(uv)/dxi = dpi [I | -hat(y)]`` and ``d(uv)/dX = dpi R_cw``, written out entry by entry (3-4x faster than
    the stacked (2, 3) @ (3, 6) products; ``tests/test_tracker.py`` checks both against finite differences)."""
    rot = t_cw[:, :3, :3]
    y = np.einsum("nij,nj->ni", rot, x) + t_cw[:, :3, 3]
    z = y[:, 2]
    iz = 1.0 / np.where(np.abs(z) > 1e-9, z, 1e-9)
    a, b = camera.fx * iz, camera.fy * iz
    u0, u1 = y[:, 0] * iz, y[:, 1] * iz  # normalised image coordinates
    j_pose = np.empty((len(x), 2, 6))
    j_pose[:, 0, 0] = a
    j_pose[:, 0, 1] = 0.0
    j_pose[:, 0, 2] = -a * u0
    j_pose[:, 0, 3] = -a * u0 * y[:, 1]
    j_pose[:, 0, 4] = a * (y[:, 2] + u0 * y[:, 0])
    j_pose[:, 0, 5] = -a * y[:, 1]
    j_pose[:, 1, 0] = 0.0
    j_pose[:, 1, 1] = b
    j_pose[:, 1, 2] = -b * u1
    j_pose[:, 1, 3] = -b * (y[:, 2] + u1 * y[:, 1])
    j_pose[:, 1, 4] = b * u1 * y[:, 0]
    j_pose[:, 1, 5] = b * y[:, 0]
    j_point = np.empty((len(x), 2, 3))
    j_point[:, 0] = a[:, None] * (rot[:, 0] - u0[:, None] * rot[:, 2])
    j_point[:, 1] = b[:, None] * (rot[:, 1] - u1[:, None] * rot[:, 2])
    return j_pose, j_point


def whitening(cov: np.ndarray) -> np.ndarray:
    """``cov^(-1/2)`` (N, 2, 2) of pixel error covariances ``cov`` (N, 2, 2, symmetric positive definite): the
    matrix that turns a residual into one of unit covariance (:func:`bundle_adjust`'s ``whiten``)."""
    w, vec = np.linalg.eigh(np.asarray(cov, np.float64).reshape(-1, 2, 2))
    return np.einsum("nij,nj,nkj->nik", vec, 1.0 / np.sqrt(np.maximum(w, 1e-12)), vec)


def _huber_w(r2: np.ndarray, k: float) -> np.ndarray:
    n = np.sqrt(r2)
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-12))


def _robust_cost(r2: np.ndarray, k: float) -> float:
    n = np.sqrt(r2)
    return float(np.sum(np.where(n <= k, 0.5 * r2, k * (n - 0.5 * k))))


def block_sum(index: np.ndarray, blocks: np.ndarray, n: int) -> np.ndarray:
    """``out[i] = sum of blocks[o] with index[o] == i`` for blocks (O, ...) -> (n, ...)."""
    shape = blocks.shape[1:]
    return _summed(_flat_index(index, int(np.prod(shape))), blocks, n)


def _flat_index(index: np.ndarray, k: int) -> np.ndarray:
    """Where each entry of per-observation blocks of ``k`` entries goes in ``n`` such blocks laid out flat."""
    return (np.asarray(index, np.int64)[:, None] * k + np.arange(k)).ravel()


def _summed(flat: np.ndarray, blocks: np.ndarray, n: int) -> np.ndarray:
    """:func:`block_sum` with the flat positions :func:`_flat_index` made in advance."""
    shape = blocks.shape[1:]
    return np.bincount(flat, weights=blocks.reshape(-1), minlength=n * int(np.prod(shape))).reshape((n,) + shape)


def same_point_pairs(point_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair (a, b) of observations of the same point (a == b included), as two index
    arrays: the pose-pose blocks of the Schur complement, one per pair."""
    f = len(point_of)
    order = np.argsort(point_of, kind="stable")
    ps = point_of[order]
    first = np.searchsorted(ps, ps, "left")
    count = np.searchsorted(ps, ps, "right") - first
    a = np.repeat(np.arange(f), count)
    b = np.repeat(first, count) + np.arange(len(a)) - np.repeat(np.cumsum(count) - count, count)
    return order[a], order[b]


class ObservationLayout:
    """Where a BA problem's observations go in its normal equations: the index arrays every
    Levenberg-Marquardt iteration of one problem shares (which observations have a free pose,
    the flat positions their blocks are summed into, the pairs of observations of one point).
    Made once per problem; each is built when first asked for."""

    def __init__(self, pose_col: np.ndarray, point: np.ndarray, n_free: int, n_points: int):
        self.pose_col = np.asarray(pose_col, np.int64)
        self.point = np.asarray(point, np.int64)
        self.n_free, self.n_points = int(n_free), int(n_points)
        self.free_obs = np.flatnonzero(self.pose_col >= 0)
        self.pose_of = self.pose_col[self.free_obs]  # of the observations of a free pose
        self.point_of = self.point[self.free_obs]
        self._flat: dict = {}

    @cached_property
    def all_free(self) -> bool:
        return len(self.free_obs) == len(self.pose_col)

    @cached_property
    def by_pose(self) -> list[np.ndarray]:
        """The observations of each free pose."""
        if self.n_free == 0:
            return []
        order = np.argsort(self.pose_of, kind="stable")
        cuts = np.searchsorted(self.pose_of[order], np.arange(1, self.n_free))
        return np.split(self.free_obs[order], cuts)

    def flat(self, which: str, k: int) -> np.ndarray:
        """The flat positions (:func:`_flat_index`) of ``k``-entry blocks of every observation by its point
        (``which`` "point"), or of the free-pose observations by their pose ("pose") or their point
        ("point_of")."""
        if (which, k) not in self._flat:
            index = {"point": self.point, "pose": self.pose_of, "point_of": self.point_of}[which]
            self._flat[which, k] = _flat_index(index, k)
        return self._flat[which, k]

    @cached_property
    def at(self) -> np.ndarray:
        """Each free-pose observation's (6, 3) ``hpx`` block's entries in the dense (6P, 3M) matrix, flat."""
        rows = 6 * self.pose_of[:, None, None] + np.arange(6)[None, :, None]
        cols = 3 * self.point_of[:, None, None] + np.arange(3)[None, None, :]
        return (rows * (3 * self.n_points) + cols).ravel()

    @cached_property
    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`same_point_pairs` of the free-pose observations."""
        return same_point_pairs(self.point_of)


@dataclass
class NormalEquations:
    """Gauss-Newton normal equations of a BA problem in block form: free poses (6 each), points (3 each).

    ``hpp`` (P, 6, 6) and ``hxx`` (M, 3, 3) are the block diagonals (an observation involves
    one pose and one point), ``gp`` (P, 6) / ``gx`` (M, 3) the gradients, and the pose-point
    coupling has one 6x3 block ``hpx`` per observation of a free pose (``layout.pose_of``,
    ``layout.point_of``)."""
    hpp: np.ndarray
    gp: np.ndarray
    hxx: np.ndarray
    gx: np.ndarray
    hpx: np.ndarray
    layout: ObservationLayout

    @property
    def pose_of(self) -> np.ndarray:
        return self.layout.pose_of

    @property
    def point_of(self) -> np.ndarray:
        return self.layout.point_of

    @cached_property
    def hpx_dense(self) -> np.ndarray:
        """``hpx`` as the dense (6P, 3M) matrix (built once per normal equations, for every damping tried)."""
        return _scatter(self.layout.at, self.hpx, len(self.hpp), len(self.hxx))


def _scatter(at: np.ndarray, blocks: np.ndarray, n_free: int, n_points: int) -> np.ndarray:
    """Per-observation (6, 3) blocks summed into a dense (6P, 3M) matrix at the flat positions ``at``."""
    size = 6 * n_free * 3 * n_points
    return np.bincount(at, weights=blocks.ravel(), minlength=size).reshape(6 * n_free, 3 * n_points)


def _t(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)


def normal_equations(jp: np.ndarray, jx: np.ndarray, r: np.ndarray, w: np.ndarray, pose_col: np.ndarray,
                     point: np.ndarray, n_free: int, n_points: int,
                     layout: Optional[ObservationLayout] = None) -> NormalEquations:
    """Weighted normal equations from per-observation Jacobians ``jp`` (O, 2, 6), ``jx`` (O, 2, 3),
    residuals ``r`` (O, 2), weights ``w`` (O,); ``pose_col`` is the free-pose column of each
    observation (-1: a fixed pose, which contributes to the points only). ``layout``: the problem's
    :class:`ObservationLayout` of these indices, when the caller keeps one across iterations.

    The point blocks and the pose-point coupling of each observation come from one (9, 2) x (2, 3)
    product of its stacked Jacobian ``[jp | jx]`` with ``jx``, each pose's block from one product of
    its observations' stacked Jacobians (about half the time of per-observation products summed)."""
    if layout is None:
        layout = ObservationLayout(pose_col, point, n_free, n_points)
    jw_t = _t(np.concatenate([jp, jx], axis=2) * w[:, None, None])  # (O, 9, 2): [jp | jx]^T W
    hx = jw_t @ jx  # (O, 9, 3): jp^T W jx over jx^T W jx
    g = (jw_t @ r[:, :, None])[..., 0]  # (O, 9)
    hxx = _summed(layout.flat("point", 9), hx[:, 6:], n_points)
    gx = _summed(layout.flat("point", 3), g[:, 6:], n_points)
    hpp, gp = np.empty((n_free, 6, 6)), np.empty((n_free, 6))
    for p, idx in enumerate(layout.by_pose):
        a = jp[idx].reshape(-1, 6)
        aw_t = (a * np.repeat(w[idx], 2)[:, None]).T
        hpp[p] = aw_t @ a
        gp[p] = aw_t @ r[idx].reshape(-1)
    return NormalEquations(hpp, gp, hxx, gx, hx[:, :6] if layout.all_free else hx[layout.free_obs, :6], layout)


DENSE_SCHUR_MAX = 50_000  # free poses x points up to which Hpx Hxx^-1 Hxp is one dense product
PAIRS_CHUNK = 16_384  # pairs of observations summed at a time by the other way (bounds its temporaries)


def _hpx_hinv_hxp(ne: NormalEquations, u: np.ndarray) -> np.ndarray:
    """``Hpx Hxx^-1 Hxp`` (6P, 6P) from the per-observation blocks ``u = Hpx_o Hxx^-1``. A window
    BA (few poses) takes one product of dense (6P, 3M) matrices (repeated observations summed); a
    large one (a loop's: tens of poses and thousands of points, where those matrices reach tens of
    MB and the product took 3 x longer) sums one 6x6 block per pair of observations of the same
    point into its pose pair (:func:`same_point_pairs`)."""
    nf, m = len(ne.hpp), len(ne.hxx)
    if nf * m <= DENSE_SCHUR_MAX:
        return _scatter(ne.layout.at, u, nf, m) @ ne.hpx_dense.T
    a, b = ne.layout.pairs
    blocks = np.zeros((nf * nf, 6, 6))
    for s in range(0, len(a), PAIRS_CHUNK):  # in chunks: the temporaries of all pairs at once took ~60 MB
        aa, bb = a[s:s + PAIRS_CHUNK], b[s:s + PAIRS_CHUNK]
        blocks += block_sum(ne.pose_of[aa] * nf + ne.pose_of[bb], u[aa] @ _t(ne.hpx[bb]), nf * nf)
    return blocks.reshape(nf, nf, 6, 6).transpose(0, 2, 1, 3).reshape(6 * nf, 6 * nf)


def inv_sym3(h: np.ndarray) -> np.ndarray:
    """Inverses of symmetric positive definite 3x3 blocks (M, 3, 3) by their cofactors (4-5x faster than
    ``np.linalg.inv`` on a window's points); ``np.linalg.LinAlgError`` when a block is not positive definite."""
    a, b, c = h[:, 0, 0], h[:, 0, 1], h[:, 0, 2]
    d, e, f = h[:, 1, 1], h[:, 1, 2], h[:, 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * c00 + b * c01 + c * c02
    if not (np.isfinite(det).all() and (det > 0).all()):
        raise np.linalg.LinAlgError("inv_sym3: a block is singular or not positive definite")
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    out = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], -1).reshape(-1, 3, 3)
    return out / det[:, None, None]


def damped_step(ne: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Solve the Levenberg-Marquardt system (diagonal scaled by ``1 + lam``) for the pose and point
    updates, the points eliminated by the Schur complement ``S = Hpp - Hpx Hxx^-1 Hxp``
    (:func:`_hpx_hinv_hxp`). Returns (dp (P, 6), dx (M, 3)); raises ``np.linalg.LinAlgError``
    when S is singular."""
    nf, m = len(ne.hpp), len(ne.hxx)
    hinv = inv_sym3(ne.hxx + lam * np.eye(3) * (np.einsum("mii->mi", ne.hxx)[:, :, None] + 1e-9))
    if nf == 0:
        return np.zeros((0, 6)), -(hinv @ ne.gx[:, :, None])[..., 0]
    u = ne.hpx @ hinv[ne.point_of]  # (F, 6, 3): Hpx_o Hxx^-1 of its point
    schur = -_hpx_hinv_hxp(ne, u)
    hpp_d = ne.hpp + lam * np.eye(6) * (np.einsum("pii->pi", ne.hpp)[:, :, None] + 1e-9)
    for p in range(nf):
        schur[6 * p:6 * p + 6, 6 * p:6 * p + 6] += hpp_d[p]
    lay = ne.layout
    rhs = -ne.gp + _summed(lay.flat("pose", 6), (u @ ne.gx[ne.point_of][:, :, None])[..., 0], nf)
    dp = np.linalg.solve(schur, rhs.reshape(-1)).reshape(nf, 6)
    back = _summed(lay.flat("point_of", 3), (_t(ne.hpx) @ dp[ne.pose_of][:, :, None])[..., 0], m)
    dx = -(hinv @ (ne.gx + back)[:, :, None])[..., 0]
    return dp, dx


def bundle_adjust(camera: PinholeCamera, poses_c2w: Sequence[np.ndarray], fixed: Sequence[int], points: np.ndarray,
                  obs_kf: np.ndarray, obs_pt: np.ndarray, obs_uv: np.ndarray, huber_px: float = 1.5,
                  max_nfev: int = 15, rel_tol: float = 1e-9, whiten: Optional[np.ndarray] = None) -> BAResult:
    """Refine the non-``fixed`` poses and all ``points`` from observations (keyframe index, point index, pixel).

    Levenberg-Marquardt with Huber weights (IRLS); each iteration eliminates the points
    (:func:`damped_step`) and solves the small dense pose system. ``max_nfev`` bounds the
    number of residual evaluations; the solve also stops after an accepted step that lowers the
    robust cost by less than ``rel_tol`` of it. ``whiten`` (O, 2, 2), when given, multiplies each
    observation's residual and Jacobians (``L`` with ``L^T L`` its pixel error's information,
    :func:`whitening`): the Huber weights, the cost and ``residual_px`` are then of the whitened
    residuals, in pixels of the best-measured direction.
    """
    k = len(poses_c2w)
    obs_kf = np.asarray(obs_kf, np.int64)
    obs_pt = np.asarray(obs_pt, np.int64)
    obs_uv = np.asarray(obs_uv, np.float64)
    t = np.stack([inv_pose(np.asarray(p, np.float64)) for p in poses_c2w])
    x = np.asarray(points, np.float64).copy()
    fixed = set(int(f) for f in fixed)
    free = [i for i in range(k) if i not in fixed]
    col = np.full(k, -1, np.int64)
    col[free] = np.arange(len(free))
    oc = col[obs_kf]  # free-pose column of each observation (-1: fixed)
    layout = ObservationLayout(oc, obs_pt, len(free), len(x))

    if whiten is not None:
        whiten = np.asarray(whiten, np.float64).reshape(-1, 2, 2)
        if len(whiten) != len(obs_uv):
            raise ValueError(f"bundle_adjust: {len(obs_uv)} observations but {len(whiten)} whitening matrices")

    def residuals(t_, x_):
        uv, _, _ = _project(camera, t_[obs_kf], x_[obs_pt])
        r = uv - obs_uv
        if whiten is not None:
            r = np.einsum("nij,nj->ni", whiten, r)
        return r, (r * r).sum(1)

    r, r2 = residuals(t, x)
    cost0 = cost = _robust_cost(r2, huber_px)
    lam = 1e-3
    nfev = 1
    while nfev < max_nfev:
        jp, jx = reprojection_jacobians(camera, t[obs_kf], x[obs_pt])
        if whiten is not None:
            jp, jx = whiten @ jp, whiten @ jx
        ne = normal_equations(jp, jx, r, _huber_w(r2, huber_px), oc, obs_pt, len(free), len(x), layout)
        improved = False
        while nfev < max_nfev:
            try:
                dp, dx = damped_step(ne, lam)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            t_new = t.copy()
            for a, pi in enumerate(free):
                t_new[pi] = se3_exp_np(dp[a]) @ t[pi]
            x_new = x + dx
            r_new, r2_new = residuals(t_new, x_new)
            nfev += 1
            c_new = _robust_cost(r2_new, huber_px)
            if c_new < cost:
                t, x, r, r2 = t_new, x_new, r_new, r2_new
                rel = (cost - c_new) / max(cost, 1e-12)
                cost = c_new
                lam = max(lam / 3, 1e-9)
                improved = rel > rel_tol
                break
            lam *= 5
        if not improved:
            break
    return BAResult([orthonormalize(inv_pose(ti)) for ti in t], x, np.sqrt(r2), cost0, cost, nfev)
