import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fmapping import geometry as g

torch.manual_seed(0)


def _axes(n, dtype=torch.float64):
    a = torch.randn(n, 3, dtype=dtype)
    return a / a.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-4, 0.3, 2.0, math.pi - 1e-6])
def test_so3_exp_log_roundtrip(angle):
    phi = _axes(16) * angle
    rot = g.so3_exp(phi)
    # proper rotation
    eye = torch.eye(3, dtype=torch.float64).expand(16, 3, 3)
    torch.testing.assert_close(rot @ rot.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(16, dtype=torch.float64))
    # against scipy's independent implementation
    ref = torch.from_numpy(Rotation.from_rotvec(phi.numpy()).as_matrix())
    torch.testing.assert_close(rot, ref, atol=1e-12, rtol=0)
    back = g.so3_log(rot)
    torch.testing.assert_close(back, phi, atol=1e-9, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 0.5, math.pi - 1e-6])
def test_se3_exp_log_roundtrip(angle):
    xi = torch.cat([torch.randn(8, 3, dtype=torch.float64), _axes(8) * angle], -1)
    t = g.se3_exp(xi)
    torch.testing.assert_close(g.se3_log(t), xi, atol=1e-8, rtol=0)
    torch.testing.assert_close(g.se3_inverse(t) @ t, torch.eye(4, dtype=torch.float64).expand(8, 4, 4), atol=1e-12,
                               rtol=0)


def test_se3_exp_matches_matrix_exponential():
    xi = torch.randn(5, 6, dtype=torch.float64)
    m = torch.zeros(5, 4, 4, dtype=torch.float64)
    m[:, :3, :3] = g.hat(xi[:, 3:])
    m[:, :3, 3] = xi[:, :3]
    torch.testing.assert_close(g.se3_exp(xi), torch.linalg.matrix_exp(m), atol=1e-10, rtol=0)


@pytest.mark.parametrize("scale", [0.0, 1e-8, 0.7])
def test_exp_gradcheck(scale):
    phi = (_axes(3) * scale).requires_grad_()
    assert torch.autograd.gradcheck(g.so3_exp, (phi,))
    xi = torch.cat([torch.randn(3, 3, dtype=torch.float64), _axes(3) * scale], -1).requires_grad_()
    assert torch.autograd.gradcheck(g.se3_exp, (xi,))


def test_log_gradcheck():
    rot = g.so3_exp(_axes(3) * 1.1).requires_grad_()
    assert torch.autograd.gradcheck(g.so3_log, (rot,))
    t = g.se3_exp(torch.randn(3, 6, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(g.se3_log, (t,))


def test_quaternion_roundtrip_and_scipy_order():
    q = torch.randn(32, 4, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, 3:] < 0, -q, q)
    rot = g.quat_to_matrix(q)
    ref = Rotation.from_quat(q.numpy()).as_matrix()  # scipy is (x, y, z, w)
    np.testing.assert_allclose(rot.numpy(), ref, atol=1e-12)
    torch.testing.assert_close(g.matrix_to_quat(rot), q, atol=1e-12, rtol=0)
    # near-180-degree rotations exercise the other branches
    rot_pi = g.so3_exp(_axes(8) * (math.pi - 1e-9))
    torch.testing.assert_close(g.quat_to_matrix(g.matrix_to_quat(rot_pi)), rot_pi, atol=1e-9, rtol=0)


def test_transform_points_and_inverse():
    t = g.se3_exp(torch.randn(6, dtype=torch.float64))
    p = torch.randn(10, 3, dtype=torch.float64)
    q = g.transform_points(t, p)
    torch.testing.assert_close(g.transform_points(g.se3_inverse(t), q), p)


def test_as_tensor_pose_rejects_nan():
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        g.as_tensor_pose(bad)


def test_nearest_rotation_matches_kabsch_on_random_matrices_numpy_and_torch():
    """The nearest rotation to A maximises trace(R^T A): the Kabsch rotation taking the basis
    vectors onto A's columns (scipy's align_vectors, an independent implementation). Reflections
    (det A < 0) included."""
    rng = np.random.default_rng(0)
    signs = set()
    for _ in range(200):
        a = rng.normal(size=(3, 3)) * 10 ** rng.uniform(-2, 2)
        signs.add(bool(np.linalg.det(a) > 0))
        ref = Rotation.align_vectors(a.T, np.eye(3))[0].as_matrix()
        r = g.nearest_rotation(a)
        np.testing.assert_allclose(r, ref, atol=1e-9)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) > 0
        rt = g.nearest_rotation(torch.from_numpy(a))
        assert isinstance(rt, torch.Tensor) and rt.dtype == torch.float64
        torch.testing.assert_close(rt, torch.from_numpy(ref), atol=1e-9, rtol=0)
    assert signs == {True, False}


def test_orthonormalize_pose_keeps_translation_fixes_last_row_and_copies():
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix() * 1.01
    t[:3, 3] = (1.0, 2.0, 3.0)
    t[3] = (1e-9, 0.0, 0.0, 1.0)
    keep = t.copy()
    out = g.orthonormalize(t.astype(np.float32))
    assert out.dtype == np.float64 and np.array_equal(t, keep)
    np.testing.assert_allclose(out[:3, :3], Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), atol=1e-6)
    assert out[:3, 3].tolist() == [1.0, 2.0, 3.0] and out[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    np.testing.assert_allclose(g.orthonormalize(out), out, atol=1e-15)  # a rotation stays put


# ----------------------------------------------------------------------------- numpy pose helpers
def test_se3_exp_np_matches_geometry():
    rng = np.random.default_rng(0)
    for scale in (0.0, 1e-7, 1e-3, 0.3, 2.5):
        xi = rng.normal(size=6) * scale
        ref = g.se3_exp(torch.as_tensor(xi)).numpy()
        np.testing.assert_allclose(g.se3_exp_np(xi), ref, atol=1e-12)


def test_se3_log_np_matches_geometry_and_inverts_se3_exp_np():
    """The one-matrix numpy log against the batched torch one, from 1e-7 rad up to 2.5 rad of rotation, and
    exp(log(T)) = T."""
    rng = np.random.default_rng(1)
    for scale in (0.0, 1e-7, 1e-3, 0.3, 1.0):
        xi = rng.normal(size=6) * scale
        t = g.se3_exp_np(xi)
        np.testing.assert_allclose(g.se3_log_np(t), g.se3_log(torch.as_tensor(t)).numpy(), atol=1e-10)
        np.testing.assert_allclose(g.se3_log_np(t), xi, atol=1e-10)
        np.testing.assert_allclose(g.se3_exp_np(g.se3_log_np(t)), t, atol=1e-12)


def test_extrapolate_motion_follows_a_constant_screw_motion_over_any_gap():
    """A camera moving by the same body-frame step every frame (pose k = P0 exp(k xi)): from two poses any number
    of frames apart, the prediction any number of frames later is that frame's pose; ratio 1 is the plain
    constant-velocity product."""
    rng = np.random.default_rng(2)
    p0 = g.se3_exp_np(rng.normal(0, 0.5, 6))
    xi = np.array([0.02, -0.01, 0.03, 0.01, 0.02, -0.015])
    pose = lambda k: p0 @ g.se3_exp_np(k * xi)  # noqa: E731
    for a, b, c in ((3, 4, 5), (3, 5, 6), (2, 3, 5), (0, 2, 7), (4, 7, 8)):
        got = g.extrapolate_motion(pose(a), pose(b), (c - b) / (b - a))
        np.testing.assert_allclose(got, pose(c), atol=1e-12)
    np.testing.assert_array_equal(g.extrapolate_motion(pose(1), pose(2)), pose(2) @ (g.inv_pose(pose(1)) @ pose(2)))


def test_orthonormalize_projects_to_rotation():
    t = g.se3_exp_np(np.array([0.1, 0.2, 0.3, 0.4, -0.2, 0.1]))
    noisy = t.copy()
    noisy[:3, :3] *= 1.001
    out = g.orthonormalize(noisy)
    np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(out[:3, :3], t[:3, :3], atol=2e-3)
    np.testing.assert_allclose(g.inv_pose(out) @ out, np.eye(4), atol=1e-12)


def test_rotation_angle_np_matches_the_torch_angle_from_zero_to_pi():
    """The one-matrix numpy angle (pose_distance's) against the batched torch one, including angles at
    1e-6 rad and within 1e-4 of pi, where an arccos of the trace would lose digits."""
    import math

    from fmapping.geometry import pose_distance, rotation_angle, rotation_angle_np, se3_exp_np

    rng = np.random.default_rng(0)
    angles = np.concatenate([[1e-6, 1e-3, math.pi - 1e-4, math.pi - 1e-2], rng.uniform(0, math.pi, 40)])
    for ang in angles:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        r = se3_exp_np(np.concatenate([np.zeros(3), axis * ang]))[:3, :3]
        assert abs(rotation_angle_np(r) - ang) < 1e-9
        assert abs(rotation_angle_np(r) - float(rotation_angle(torch.as_tensor(r)))) < 1e-6
    a = se3_exp_np(np.array([0.1, -0.2, 0.3, 0.2, 0.1, -0.3]))
    step = se3_exp_np(np.array([0.0, 0.0, 0.0, 0.0, math.radians(7.0), 0.0]))
    step[:3, 3] = [0.0, 0.0, 0.5]
    b = a @ step
    dt, dr = pose_distance(a, b)
    assert abs(dt - 0.5) < 1e-12 and abs(dr - 7.0) < 1e-9


@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.3, 2.5])
def test_numpy_hat_and_so3_right_jacobian_inverse(angle):
    """``hat_np`` equals the torch ``hat``; ``so3_right_jacobian_inv_np`` against central differences of
    ``log(exp(w) exp(d))`` (scipy's rotations), below the series' threshold and up to 2.5 rad."""
    from scipy.spatial.transform import Rotation

    from fmapping.geometry import hat, hat_np, so3_right_jacobian_inv_np

    rng = np.random.default_rng(5)
    v = rng.normal(size=(4, 3))
    np.testing.assert_array_equal(hat_np(v), hat(torch.tensor(v)).numpy())
    w = rng.normal(size=3)
    w = angle * w / np.linalg.norm(w)
    num, eps = np.zeros((3, 3)), 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        plus = (Rotation.from_rotvec(w) * Rotation.from_rotvec(d)).as_rotvec()
        minus = (Rotation.from_rotvec(w) * Rotation.from_rotvec(-d)).as_rotvec()
        num[:, k] = (plus - minus) / (2 * eps)
    np.testing.assert_allclose(so3_right_jacobian_inv_np(w[None])[0], num, atol=1e-8)
