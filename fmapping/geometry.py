"""Batched, differentiable SO(3) / SE(3) in torch.

Conventions (the only place they are written down; every module follows them):

* World units are metres. Camera frames are OpenCV: x right, y down, z forward.
* A pose is a 4x4 camera-to-world matrix ``c2w`` (``x_world = c2w @ x_cam``).
* A tangent vector of SE(3) is ``xi = (rho, phi)`` with translation part ``rho``
  first and rotation part ``phi`` (axis-angle) last; ``se3_exp(xi)`` is the
  matrix exponential of ``[[hat(phi), rho], [0, 0]]``.
* Pose corrections are applied on the left: ``c2w_new = se3_exp(xi) @ c2w``.
* Quaternions are ``(qx, qy, qz, qw)`` (TUM and scipy order), unit norm.

All functions accept any leading batch shape ``(..., 3)`` / ``(..., 3, 3)`` /
``(..., 4, 4)`` and are stable at small angles (Taylor branches chosen with
``torch.where`` on safe inputs, so gradients stay finite at exactly zero).
The projections onto SO(3) (:func:`nearest_rotation`, :func:`orthonormalize`) take one
matrix, numpy or torch; the numpy pose helpers at the end (:func:`se3_exp_np`, :func:`inv_pose`,
:func:`scale_about`, :func:`pose_distance`) take one float64 4x4 pose, for the numpy tracking code.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

_SMALL = 1e-6  # theta^2 below which Taylor expansions are used


def hat(v: Tensor) -> Tensor:
    """Skew-symmetric matrix of ``v`` (..., 3) -> (..., 3, 3)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2
    )


def vee(m: Tensor) -> Tensor:
    """Inverse of :func:`hat` for the antisymmetric part of ``m``."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )


def _sin_coeffs(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A = sin(t)/t, B = (1-cos t)/t^2, C = (t - sin t)/t^3, safe at t = 0."""
    small = theta2 < _SMALL
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(t)) / t2)
    c = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(phi: Tensor) -> Tensor:
    """Rodrigues: axis-angle (..., 3) -> rotation (..., 3, 3)."""
    theta2 = (phi * phi).sum(-1)
    a, b, _ = _sin_coeffs(theta2)
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(rot: Tensor) -> Tensor:
    """Rotation (..., 3, 3) -> axis-angle (..., 3), valid on [0, pi]."""
    s_vec = vee(rot)  # sin(theta) * axis
    cos = ((rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2]) - 1) / 2
    sin = torch.linalg.norm(s_vec, dim=-1)
    theta = torch.atan2(sin, cos.clamp(-1, 1))
    small = theta < 1e-3
    near_pi = theta > math.pi - 1e-2
    # generic: theta / sin(theta) * s_vec
    sin_safe = torch.where(small | near_pi, torch.ones_like(sin), sin)
    generic = (theta / sin_safe)[..., None] * s_vec
    # small: theta/sin(theta) ~= 1 + theta^2/6, theta^2 ~= |s_vec|^2
    s2 = (s_vec * s_vec).sum(-1)
    small_v = (1 + s2 / 6 + 7 * s2**2 / 120)[..., None] * s_vec
    # near pi: axis from the symmetric part, sign from the antisymmetric one
    sym = 0.5 * (rot + rot.transpose(-1, -2))
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
    one_m_cos = torch.where(near_pi, 1 - cos, torch.ones_like(cos))
    nn_t = (sym - cos[..., None, None] * eye) / one_m_cos[..., None, None]
    diag = torch.diagonal(nn_t, dim1=-2, dim2=-1)
    idx = diag.argmax(-1)
    col = torch.gather(nn_t, -1, idx[..., None, None].expand(*nn_t.shape[:-1], 1))[..., 0]
    col_norm = torch.linalg.norm(col, dim=-1, keepdim=True).clamp_min(1e-12)
    axis = col / col_norm
    sign = torch.where((axis * s_vec).sum(-1) < 0, -torch.ones_like(theta), torch.ones_like(theta))
    pi_v = (sign * theta)[..., None] * axis
    out = torch.where(small[..., None], small_v, generic)
    return torch.where(near_pi[..., None], pi_v, out)


def _left_jacobian(phi: Tensor) -> Tensor:
    theta2 = (phi * phi).sum(-1)
    _, b, c = _sin_coeffs(theta2)
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye + b[..., None, None] * k + c[..., None, None] * (k @ k)


def _left_jacobian_inv(phi: Tensor) -> Tensor:
    theta2 = (phi * phi).sum(-1)
    small = theta2 < _SMALL
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    # coefficient of K^2: (1/t^2) * (1 - (t/2) cot(t/2)); Taylor 1/12 + t^2/720
    half = t / 2
    d = torch.where(small, 1 / 12 + theta2 / 720, (1 - half * torch.cos(half) / torch.sin(half)) / t2)
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye - 0.5 * k + d[..., None, None] * (k @ k)


def se3_exp(xi: Tensor) -> Tensor:
    """Twist (..., 6) = (rho, phi) -> rigid transform (..., 4, 4)."""
    rho, phi = xi[..., :3], xi[..., 3:]
    rot = so3_exp(phi)
    trans = (_left_jacobian(phi) @ rho[..., None])[..., 0]
    return make_pose(rot, trans)


def se3_log(t: Tensor) -> Tensor:
    """Rigid transform (..., 4, 4) -> twist (..., 6) = (rho, phi)."""
    phi = so3_log(t[..., :3, :3])
    rho = (_left_jacobian_inv(phi) @ t[..., :3, 3:4])[..., 0]
    return torch.cat([rho, phi], -1)


def make_pose(rot: Tensor, trans: Tensor) -> Tensor:
    """Stack rotation (..., 3, 3) and translation (..., 3) into (..., 4, 4)."""
    top = torch.cat([rot, trans[..., None]], -1)
    bottom = torch.zeros(*rot.shape[:-2], 1, 4, dtype=rot.dtype, device=rot.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def se3_inverse(t: Tensor) -> Tensor:
    """Inverse of a rigid transform without a general matrix inverse."""
    rot_t = t[..., :3, :3].transpose(-1, -2)
    return make_pose(rot_t, -(rot_t @ t[..., :3, 3:4])[..., 0])


def se3_compose(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for rigid transforms (kept for readability at call sites)."""
    return a @ b


def transform_points(t: Tensor, pts: Tensor) -> Tensor:
    """Apply (..., 4, 4) to points (..., N, 3)."""
    return pts @ t[..., :3, :3].transpose(-1, -2) + t[..., None, :3, 3]


def quat_to_matrix(q: Tensor) -> Tensor:
    """Quaternion (..., 4) as (x, y, z, w) -> rotation (..., 3, 3). Normalises first."""
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(rot: Tensor) -> Tensor:
    """Rotation (..., 3, 3) -> unit quaternion (..., 4) as (x, y, z, w) with w >= 0."""
    m = rot
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # four candidate parametrisations; pick the numerically largest denominator
    cands = torch.stack(
        [
            torch.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1],
                         1 + tr], -1),
            torch.stack([1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0],
                         m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] - m[..., 1, 2]], -1),
            torch.stack([m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                         m[..., 1, 2] + m[..., 2, 1], m[..., 0, 2] - m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                         1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2], m[..., 1, 0] - m[..., 0, 1]], -1),
        ],
        -2,
    )  # (..., 4 candidates, 4)
    keys = torch.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = keys.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def rotation_angle(rot: Tensor) -> Tensor:
    """Angle in radians of a rotation (..., 3, 3)."""
    return torch.linalg.norm(so3_log(rot), dim=-1)


def nearest_rotation(m):
    """The rotation nearest to the 3x3 matrix ``m`` (Frobenius norm): its polar factor by SVD,
    with the sign of the last singular direction flipped when that one is a reflection.
    numpy array in, numpy array out; torch tensor in, tensor out (same dtype and device)."""
    if isinstance(m, Tensor):
        u, _, vt = torch.linalg.svd(m)
        r = u @ vt
        if torch.linalg.det(r) < 0:
            u[:, -1] *= -1
            r = u @ vt
        return r
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def orthonormalize(t) -> np.ndarray:
    """A copy of the 4x4 pose ``t`` (float64 numpy) with its rotation block projected onto SO(3)
    (:func:`nearest_rotation`) and last row ``0 0 0 1``. Chained products of poses let round-off
    grow geometrically, and the protocol's rotation check refuses float poses straight out of an
    optimiser."""
    out = np.array(t, np.float64)
    out[:3, :3] = nearest_rotation(out[:3, :3])
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def as_tensor_pose(c2w, dtype=torch.float32, device=None) -> Tensor:
    """numpy / list / tensor 4x4 -> tensor, checking shape and finiteness."""
    t = torch.as_tensor(c2w, dtype=dtype, device=device)
    if t.shape[-2:] != (4, 4):
        raise ValueError(f"pose must be 4x4, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError("pose contains NaN or Inf")
    return t


# --- numpy pose helpers
def hat_np(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices (..., 3, 3) of vectors (..., 3): ``hat_np(a) @ b = a x b`` (:func:`hat` in numpy)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def so3_right_jacobian_inv_np(w: np.ndarray) -> np.ndarray:
    """Inverse right Jacobians (N, 3, 3) of SO(3) at rotation vectors ``w`` (N, 3): ``log(exp(w) exp(d))
    = w + Jr^-1(w) d`` to first order in ``d``."""
    th = np.linalg.norm(w, axis=-1)
    k = hat_np(w)
    small = th < 1e-5
    ts = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0 + th ** 2 / 720.0, 1.0 / ts ** 2 - (1.0 + np.cos(ts)) / (2.0 * ts * np.sin(ts)))
    return np.eye(3) + 0.5 * k + c[..., None, None] * (k @ k)


def se3_exp_np(xi: np.ndarray) -> np.ndarray:
    """se(3) twist (6,) (rho, phi) -> 4x4 float64.

    The same map as :func:`se3_exp` (tested against it), written
    for one float64 6-vector in numpy because the torch version costs ~1 ms per call
    and the optimiser calls it every iteration.
    """
    xi = np.asarray(xi, np.float64)
    rho, phi = xi[:3], xi[3:]
    th2 = float(phi @ phi)
    if th2 < 1e-10:
        a, b, c = 1 - th2 / 6, 0.5 - th2 / 24, 1 / 6 - th2 / 120
    else:
        th = math.sqrt(th2)
        a, b, c = math.sin(th) / th, (1 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    k = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    k2 = k @ k
    out = np.eye(4)
    out[:3, :3] += a * k + b * k2
    out[:3, 3] = (np.eye(3) + b * k + c * k2) @ rho
    return out


def so3_log_np(r: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of one rotation matrix (3, 3), angle in [0, pi) (:func:`so3_log` for one matrix in
    numpy; the axis is ill-defined only at pi, which a camera's motion between two frames never nears)."""
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0
    s = float(np.linalg.norm(w))
    th = math.atan2(s, (float(np.trace(r)) - 1.0) / 2.0)
    return w * (th / s if s > 1e-12 else 1.0 + s * s / 6.0)


def se3_log_np(t: np.ndarray) -> np.ndarray:
    """Twist (6,) (rho, phi) of one rigid transform (4, 4) in float64: :func:`se3_log` for one matrix in numpy,
    the inverse of :func:`se3_exp_np`."""
    phi = so3_log_np(t[:3, :3])
    th2 = float(phi @ phi)
    if th2 < 1e-10:
        d = 1.0 / 12.0 + th2 / 720.0
    else:
        th = math.sqrt(th2)
        d = (1.0 - (th / 2.0) / math.tan(th / 2.0)) / th2
    k = hat_np(phi)
    return np.concatenate([(np.eye(3) - 0.5 * k + d * (k @ k)) @ t[:3, 3], phi])


def extrapolate_motion(prev: np.ndarray, last: np.ndarray, ratio: float = 1.0) -> np.ndarray:
    """Constant velocity: the pose (4, 4) after ``last`` when the camera goes on moving as it did from ``prev`` to
    ``last`` for ``ratio`` times that step, ``last @ step ** ratio`` with the step ``inv(prev) @ last`` in the
    camera's own frame (a screw motion: ``exp(ratio log(step))``). ``ratio`` 1 gives ``last @ step``; 0.5 fits the
    last two poses two frames apart and the next frame one after the last (a frame skipped in between)."""
    step = inv_pose(prev) @ last
    if ratio == 1.0:
        return last @ step
    return last @ se3_exp_np(ratio * se3_log_np(step))


def inv_pose(t: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def scale_about(c2w: np.ndarray, center: np.ndarray, s: float) -> np.ndarray:
    """The pose in a world scaled by ``s`` about ``center``: its camera centre ``t`` moves to
    ``center + s * (t - center)``, its rotation stays."""
    out = np.array(c2w, np.float64)
    out[:3, 3] = center + s * (out[:3, 3] - center)
    return out


def rotation_angle_np(r: np.ndarray) -> float:
    """Angle in radians of one rotation matrix (3, 3): ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)``, exact
    near 0 and pi alike (the same as :func:`rotation_angle`, tested against it; no torch for one matrix)."""
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0
    return float(math.atan2(float(np.linalg.norm(w)), (float(np.trace(r)) - 1.0) / 2.0))


def line_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees, 0-90) between the lines of vectors ``a`` and ``b`` (3,): their signs aside."""
    c = abs(float(np.dot(a, b))) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
    return math.degrees(math.acos(min(c, 1.0)))


def pose_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation metres, rotation degrees) of ``inv(a) @ b``."""
    d = inv_pose(a) @ b
    return float(np.linalg.norm(d[:3, 3])), math.degrees(rotation_angle_np(d[:3, :3]))
