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
    torch.testing.assert_close(g.se3_inverse(t) @ t, torch.eye(4, dtype=torch.float64).expand(8, 4, 4), atol=1e-12, rtol=0)


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
