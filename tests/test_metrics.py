"""Tests of fmapping.metrics against analytic cases and independent references."""
import json
import math

import numpy as np
import pytest
from scipy import integrate, stats
from scipy.spatial.transform import Rotation

from fmapping import metrics as M
from fmapping.cli import main
from fmapping.ply import PlyData, write_ply
from fmapping.trajectory import write_tum_trajectory


# ----------------------------------------------------------------------------- helpers
def _plane(n, side, seed):
    """n uniform points on the square [0, side]^2 in the z = 0 plane."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.random((n, 2)) * side, np.zeros(n)]


def _expected_nn_distance(sigma, density):
    """E of the nearest-neighbour distance from p = g + N(0, sigma^2 I3) to a planar
    Poisson set of ``density`` points/m^2 that also contains g.

    The NN is the GT point with the smallest in-plane distance r (z is shared), and
    P(r > x) = P(|n_xy| > x) P(no other point within x) = exp(-x^2/(2 sigma^2)) exp(-density pi x^2),
    so r is Rayleigh with 1/s^2 = 1/sigma^2 + 2 pi density, independent of z ~ N(0, sigma^2);
    the distance is sqrt(z^2 + r^2)."""
    s2 = 1.0 / (1.0 / sigma ** 2 + 2 * math.pi * density)
    z = np.linspace(0, 10 * sigma, 2001)[:, None]  # |z| half-normal: density 2 phi(z)
    r = np.linspace(0, 10 * math.sqrt(s2), 2001)[None, :]
    w = 2 * stats.norm.pdf(z, scale=sigma) * r / s2 * np.exp(-r * r / (2 * s2))
    return float(integrate.trapezoid(integrate.trapezoid(np.hypot(z, r) * w, r[0], axis=1), z[:, 0]))


def _random_traj(n, seed):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, n)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.6, size=(n, 3))).as_matrix()
    c2w[:, :3, 3] = np.c_[np.cos(t) * 2, np.sin(t), 0.3 * t] + rng.normal(scale=0.05, size=(n, 3))
    return c2w


def _sim3_apply(c2w, s, rot, t):
    out = c2w.copy()
    out[:, :3, :3] = rot @ c2w[:, :3, :3]
    out[:, :3, 3] = s * c2w[:, :3, 3] @ rot.T + t
    return out


# ----------------------------------------------------------------------------- reconstruction
def test_expected_nn_distance_helper_limits():
    # sparse GT -> distance to the true point: chi(3) mean 2 sqrt(2/pi) sigma = 1.596 sigma;
    # dense GT -> distance to the plane: E|z| = sqrt(2/pi) sigma = 0.798 sigma.
    assert _expected_nn_distance(1.0, 0.0) == pytest.approx(2 * math.sqrt(2 / math.pi), rel=1e-5)
    assert _expected_nn_distance(1.0, 1e6) == pytest.approx(math.sqrt(2 / math.pi), rel=1e-3)


def test_identical_clouds():
    pts = _plane(5000, 1.0, 0)
    r = M.recon_metrics(pts, pts)
    assert r["accuracy_cm"] == 0 and r["completion_cm"] == 0
    assert r["completion_ratio"] == 100 and r["accuracy_ratio"] == 100 and r["fscore"] == 100
    assert r["n_pred"] == r["n_gt"] == 5000


@pytest.mark.parametrize("n_gt", [5_000, 100_000])  # sparse (~1.2 sigma) and dense (~0.85 sigma) GT on 2 m x 2 m
def test_plane_with_gaussian_noise(n_gt):
    sigma, side = 0.01, 2.0
    gt = _plane(n_gt, side, 1)
    pred = gt + np.random.default_rng(2).normal(scale=sigma, size=gt.shape)
    r = M.recon_metrics(pred, gt, threshold=0.05)
    expected_cm = 100 * _expected_nn_distance(sigma, n_gt / side ** 2)
    # tolerance 3 %: sampling error of the mean <= 0.6 sigma / sqrt(5000) ~ 0.6 % relative, plus
    # border effects (points within a few mm of the square's edge: ~1 % of points).
    assert r["accuracy_cm"] == pytest.approx(expected_cm, rel=0.03)
    assert 0.8 * 0.9 < r["accuracy_cm"] < 1.596 * 1.02  # between the dense-plane and sparse limits
    assert r["completion_ratio"] == 100.0
    assert r["accuracy_ratio"] == 100.0


def test_shifted_cloud_ratio_zero():
    gt = _plane(5000, 1.0, 3)
    r = M.recon_metrics(gt + [0, 0, 0.10], gt, threshold=0.05)
    assert r["completion_ratio"] == 0.0 and r["accuracy_ratio"] == 0.0 and r["fscore"] == 0.0
    assert r["accuracy_cm"] == pytest.approx(10.0, abs=1e-9)
    assert r["completion_cm"] == pytest.approx(10.0, abs=1e-9)


def test_partial_prediction_completion():
    gt = _plane(20000, 1.0, 4)
    pred = gt[gt[:, 0] < 0.5]  # half the surface reconstructed, exactly
    r = M.recon_metrics(pred, gt, threshold=0.05)
    assert r["accuracy_cm"] == 0.0
    # GT points with x in [0.5, 0.55) are within 5 cm of the predicted half (up to sampling gaps)
    frac = 100 * np.mean(gt[:, 0] < 0.55)
    assert r["completion_ratio"] == pytest.approx(frac, abs=0.3)


def test_error_sources_classes_points_by_what_the_depth_frames_saw():
    """A wall at z = 2 m seen by a depth camera at the origin, with readings on its left half only.
    Points on it, in front of it, behind it, and where no frame reads, land in their classes; a
    second frame that reads farther (3 m) at the same pixels makes the behind points free space."""
    from fmapping.camera import PinholeCamera

    cam = PinholeCamera(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)
    depth = np.zeros((48, 64))
    depth[:, :32] = 2.0
    eye = np.eye(4)
    uu, vv = np.meshgrid(np.arange(4, 29, 4), np.arange(4, 45, 4))
    uu, vv = uu.reshape(-1).astype(float), vv.reshape(-1).astype(float)

    def at(u, v, z):  # points at camera depth z on the rays of pixels (u, v)
        return np.c_[(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, np.full(len(u), z)]

    gt = at(uu, vv, 2.0)
    on, front, back = gt + [0.01, 0.0, 0.0], at(uu, vv, 1.5), at(uu, vv, 2.5)
    unseen = at(uu + 32, vv, 1.2)  # right half: no reading there
    pred = np.concatenate([on, front, back, unseen])
    n = len(gt)
    d_ref = np.array([np.linalg.norm(gt - p, axis=1).min() for p in pred])  # brute force

    r = M.error_sources(pred, gt, [(depth, eye)], cam, threshold=0.05)
    assert r["n_pred"] == 4 * n
    for name in ("near", "free", "behind", "unseen"):
        assert r[name]["share"] == pytest.approx(25.0)
    assert r["other"]["share"] == 0.0 and r["other"]["mean_cm"] is None
    for k, name in enumerate(("near", "free", "behind", "unseen")):
        part = d_ref[k * n:(k + 1) * n]
        assert r[name]["mean_cm"] == pytest.approx(100 * part.mean(), rel=1e-9)
        assert r[name]["error_share"] == pytest.approx(100 * part.sum() / d_ref.sum(), rel=1e-9)
    assert r["accuracy_cm"] == pytest.approx(M.recon_metrics(pred, gt)["accuracy_cm"], rel=1e-9)
    assert r["accuracy_seen_cm"] == pytest.approx(100 * d_ref[:3 * n].mean(), rel=1e-9)

    farther = np.where(depth > 0, 3.0, 0.0)
    r2 = M.error_sources(pred, gt, [(depth, eye), (farther, eye)], cam, threshold=0.05)
    assert r2["behind"]["share"] == 0.0 and r2["free"]["share"] == pytest.approx(50.0)
    with pytest.raises(ValueError, match="does not match the camera"):
        M.error_sources(pred, gt, [(depth[:, :10], eye)], cam)


def test_empty_prediction_is_not_a_crash():
    r = M.recon_metrics(np.zeros((0, 3)), _plane(100, 1.0, 0))
    assert r["accuracy_cm"] == math.inf and r["completion_cm"] == math.inf
    assert r["completion_ratio"] == 0.0 and r["accuracy_ratio"] == 0.0 and r["n_pred"] == 0
    assert "no (finite) points" in r["note"]
    r = M.recon_metrics(np.full((5, 3), np.nan), _plane(100, 1.0, 0))  # non-finite points are dropped
    assert r["n_pred"] == 0 and r["n_pred_dropped"] == 5 and r["completion_ratio"] == 0.0
    with pytest.raises(ValueError, match="ground-truth"):
        M.recon_metrics(_plane(10, 1.0, 0), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="threshold"):
        M.recon_metrics(_plane(10, 1.0, 0), _plane(10, 1.0, 0), threshold=0)


def _chi2_grid(pts, k=4):
    h, _, _ = np.histogram2d(pts[:, 0], pts[:, 1], bins=k, range=[[0, 1], [0, 1]])
    e = len(pts) / k ** 2
    return float(((h - e) ** 2 / e).sum())


def test_mesh_sampling_uniform_on_two_triangles():
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    n = 40_000
    p = M.sample_surface(PlyData(verts, None, faces), n, seed=0)
    assert p.shape == (n, 3)
    assert np.all(p[:, 2] == 0) and p[:, :2].min() >= 0 and p[:, :2].max() <= 1
    limit = stats.chi2.ppf(0.999, 15)  # 4x4 cells -> 15 degrees of freedom
    assert _chi2_grid(p) < limit
    # same seed -> same points; the tuple form is accepted too
    np.testing.assert_array_equal(p, M.sample_surface((verts, faces), n, seed=0))


def test_mesh_sampling_is_area_weighted():
    # a fan of 4 triangles of very different areas around an off-centre vertex
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.85, 0.1, 0]], float)
    faces = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    n = 40_000
    limit = stats.chi2.ppf(0.999, 15)
    assert _chi2_grid(M.sample_surface((verts, faces), n, seed=1)) < limit
    # control: picking faces uniformly (not by area) is visibly non-uniform, so the test can fail
    rng = np.random.default_rng(0)
    per_face = [M.sample_surface((verts, faces[i:i + 1]), n // 4, seed=i) for i in range(4)]
    assert _chi2_grid(np.concatenate(per_face)[rng.permutation(n)]) > 10 * limit


def test_mesh_sampling_tilted_triangle_in_3d():
    rot = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    tri = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0]], float) @ rot.T + [1, 2, 3]
    p = M.sample_surface((tri, [[0, 1, 2]]), 5000, seed=3)
    local = (p - [1, 2, 3]) @ rot  # back to the triangle's frame
    assert np.abs(local[:, 2]).max() < 1e-12
    assert local[:, 0].min() >= -1e-12 and local[:, 1].min() >= -1e-12
    assert (local[:, 0] / 2 + local[:, 1]).max() <= 1 + 1e-12
    # centroid of uniform samples -> centroid of the triangle
    np.testing.assert_allclose(p.mean(0), tri.mean(0), atol=0.02)


def test_cloud_sampling_subset():
    pts = _plane(1000, 1.0, 5)
    sub = M.sample_surface(pts, 100, seed=0)
    assert sub.shape == (100, 3)
    assert len(np.unique(sub, axis=0)) == 100  # without replacement
    assert len(M.sample_surface(PlyData(pts), 100, seed=0)) == 100
    assert {tuple(x) for x in sub} <= {tuple(x) for x in pts}
    np.testing.assert_array_equal(M.sample_surface(pts, 5000, seed=0), pts)  # fewer than n: all
    with pytest.raises(ValueError, match="out of range"):
        M.sample_surface((pts[:3], [[0, 1, 3]]), 10)


# ----------------------------------------------------------------------------- trajectories
def test_umeyama_recovers_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    rot = Rotation.from_rotvec([0.4, -2.0, 1.0]).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    s, r, tt = M.umeyama(src, 1.7 * src @ rot.T + t, with_scale=True)
    assert s == pytest.approx(1.7, abs=1e-12)
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(tt, t, atol=1e-12)
    s, r, tt = M.umeyama(src, src @ rot.T + t, with_scale=False)
    assert s == 1.0
    np.testing.assert_allclose(r, rot, atol=1e-12)


def test_umeyama_rotation_matches_scipy_kabsch_on_noisy_data():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(40, 3))
    dst = src @ Rotation.from_rotvec([1.0, 0.2, -0.3]).as_matrix().T + rng.normal(scale=0.3, size=(40, 3))
    _, r, _ = M.umeyama(src, dst, with_scale=False)
    ref, _ = Rotation.align_vectors(dst - dst.mean(0), src - src.mean(0))
    np.testing.assert_allclose(r, ref.as_matrix(), atol=1e-9)
    # a mirrored target still yields a proper rotation
    _, r, _ = M.umeyama(src, src * [1, 1, -1], with_scale=True)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_align_poses_recovers_a_similarity_and_pins_the_rotation_about_a_straight_path():
    """align_poses finds the similarity between two trajectories from their whole poses: exactly on any path, and
    on a straight one too, where the camera centres alone (align_trajectory) leave the rotation about the line
    free."""
    gt = _random_traj(30, 3)
    est = _sim3_apply(gt, 0.5, Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix(), np.array([1.0, 2.0, -1.0]))
    s, r, t = M.align_poses(est, gt)
    np.testing.assert_allclose(_sim3_apply(est, s, r, t), gt, atol=1e-9)
    line = gt.copy()
    line[:, :3, 3] = np.linspace(0.0, 1.0, 30)[:, None] * [1.0, 0.0, 0.0]
    roll = Rotation.from_rotvec([np.radians(10.0), 0.0, 0.0]).as_matrix()  # about the path itself
    est = _sim3_apply(line, 2.0, roll, np.zeros(3))
    s, r, t = M.align_poses(est, line)
    np.testing.assert_allclose(_sim3_apply(est, s, r, t), line, atol=1e-9)
    _, (_, r_centres, _) = M.align_trajectory(est, line, "sim3")
    assert float(M.rotation_angle_deg(r_centres @ roll)) > 1.0  # the centres alone: the roll is lost
    with pytest.raises(ValueError, match="lever_m"):
        M.align_poses(est, line, lever_m=0.0)


def test_ate_sim3_vs_se3_on_scaled_rotated_trajectory():
    gt = _random_traj(60, 0)
    rot = Rotation.from_rotvec([0.5, 1.0, -0.7]).as_matrix()
    est = _sim3_apply(gt, 2.0, rot, np.array([3.0, -1.0, 2.0]))  # est = 2x larger, rotated, moved
    a = M.ate(est, gt, align="sim3")
    assert a["rmse_m"] < 1e-9 and a["max_m"] < 1e-9
    assert a["scale"] == pytest.approx(0.5, abs=1e-12)  # maps est onto gt
    assert a["rot_err_mean_deg"] < 1e-6 and a["n"] == 60
    # rigid alignment of x -> 2 R x: the best rotation undoes R and the residual of each
    # centred GT position c_i is |c_i - 2 c_i| = |c_i|, so the RMSE is the RMS radius of the GT.
    b = M.ate(est, gt, align="se3")
    c = gt[:, :3, 3] - gt[:, :3, 3].mean(0)
    rms_radius = math.sqrt(np.mean((c ** 2).sum(1)))
    assert b["scale"] == 1.0
    assert b["rmse_m"] == pytest.approx(rms_radius, rel=1e-9)
    assert b["rmse_m"] > 1.0
    assert b["rot_err_mean_deg"] < 1e-6  # rotations are still aligned exactly
    assert M.ate(gt, gt, align="none")["rmse_m"] == 0.0
    with pytest.raises(ValueError, match="mode"):
        M.ate(est, gt, align="sim2")


def test_ate_rotation_error_of_known_perturbation():
    gt = _random_traj(30, 1)
    est = gt.copy()
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec([0, 0, math.radians(3.0)]).as_matrix()
    a = M.ate(est, gt, align="none")
    assert a["rmse_m"] == 0.0
    assert a["rot_err_mean_deg"] == pytest.approx(3.0, abs=1e-9)


def test_rpe_constant_drift():
    gt = _random_traj(40, 2)
    drift = np.eye(4)
    drift[:3, :3] = Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix()
    drift[:3, 3] = [0.03, 0.0, -0.04]
    est = [gt[0]]
    for i in range(len(gt) - 1):
        est.append(est[-1] @ np.linalg.inv(gt[i]) @ gt[i + 1] @ drift)
    est = np.stack(est)
    r = M.rpe(est, gt, delta=1)
    assert r["trans_rmse_m"] == pytest.approx(0.05, abs=1e-9)
    assert r["rot_rmse_deg"] == pytest.approx(math.degrees(np.linalg.norm([0.01, -0.02, 0.005])), abs=1e-7)
    assert r["n"] == 39
    # invariant to a rigid change of world frame
    moved = _sim3_apply(est, 1.0, Rotation.from_rotvec([1, 2, 3]).as_matrix(), np.array([5.0, 0, 1]))
    assert M.rpe(moved, gt)["trans_rmse_m"] == pytest.approx(0.05, abs=1e-9)


def test_rotation_angle_deg_precise_near_zero_and_pi():
    for ang in [1e-9, 0.5, math.pi - 1e-7]:
        r = Rotation.from_rotvec(np.array([0.6, 0.8, 0.0]) * ang).as_matrix()
        assert M.rotation_angle_deg(r) == pytest.approx(math.degrees(ang), rel=1e-6)


def _straight_run_with_rotation_noise(seed: int = 7):
    """A 1 m straight run (camera centres on a line, 1 mm jitter) with varied orientations, and an
    estimate = the GT moved by a known Sim(3) (plus 3 mm position noise) whose orientations carry known per-frame errors
    ``E_k`` of angle ``theta_k`` about random axes. Every frame appears twice, once with
    ``E_k`` and once with ``E_k^T``, so that ``sum_k R_gt_k R_est_k^T = S R0^T`` with ``S``
    symmetric positive definite: the orientation-only best fit is then exactly ``R0^T`` and
    the per-frame errors after it exactly ``theta_k``."""
    rng = np.random.default_rng(seed)
    n = 30
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.3, size=(n, 3))).as_matrix()
    gt[:, :3, 3] = np.c_[np.linspace(0, 1, n), np.zeros(n), np.zeros(n)] + rng.normal(scale=1e-3, size=(n, 3))
    theta = np.radians(rng.uniform(0.5, 5.0, n))
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    noise = Rotation.from_rotvec(theta[:, None] * axes).as_matrix()
    rot0 = Rotation.from_rotvec([0.3, -1.1, 0.8]).as_matrix()
    gt2 = np.concatenate([gt, gt])
    noisy = gt2.copy()
    noisy[:, :3, :3] = gt2[:, :3, :3] @ np.concatenate([noise, np.swapaxes(noise, 1, 2)])
    est = _sim3_apply(noisy, 1.5, rot0, np.array([0.2, 1.0, -0.4]))
    est[:, :3, 3] += rng.normal(scale=3e-3, size=(2 * n, 3))  # estimated centres are off by a few mm
    return est, gt2, rot0, np.degrees(np.r_[theta, theta])


def test_orientation_fit_recovers_known_rotation_and_noise_on_a_straight_run():
    est, gt, rot0, theta_deg = _straight_run_with_rotation_noise()
    ra = M.align_rotations(est[:, :3, :3], gt[:, :3, :3])
    np.testing.assert_allclose(ra, rot0.T, atol=1e-12)
    np.testing.assert_allclose(M.rotation_errors_deg(est, gt, "fit"), theta_deg, atol=1e-9)
    a = M.ate(est, gt, align="sim3")
    assert a["rot_fit_mean_deg"] == pytest.approx(theta_deg.mean(), abs=1e-9)
    assert a["rot_fit_rmse_deg"] == pytest.approx(math.sqrt(np.mean(theta_deg ** 2)), abs=1e-9)
    assert a["rot_fit_max_deg"] == pytest.approx(theta_deg.max(), abs=1e-9)
    assert a["scale"] == pytest.approx(1 / 1.5, rel=2e-2)
    # the position-based alignment cannot see the spin about the line: its rotation error is
    # set by the millimetre noise, not by the orientations (15.6 deg vs 2.4 deg for this seed)
    assert a["rot_err_mean_deg"] > theta_deg.mean() + 5.0, a
    # the fit does not depend on the position alignment
    for mode in ("se3", "none"):
        assert M.ate(est, gt, align=mode)["rot_fit_mean_deg"] == pytest.approx(theta_deg.mean(), abs=1e-9)


def test_orientation_fit_is_the_chordal_mean_of_scipy():
    # general (non-symmetric, large) noise: the fit is scipy's chordal L2 mean of R_gt R_est^T
    gt = _random_traj(40, 8)
    rng = np.random.default_rng(9)
    rot0 = Rotation.from_rotvec([-2.0, 0.4, 0.9]).as_matrix()
    est = _sim3_apply(gt, 1.0, rot0, np.zeros(3))
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(scale=0.5, size=(40, 3))).as_matrix()
    ra = M.align_rotations(est[:, :3, :3], gt[:, :3, :3])
    ref = Rotation.from_matrix(gt[:, :3, :3] @ np.swapaxes(est[:, :3, :3], 1, 2)).mean().as_matrix()
    np.testing.assert_allclose(ra, ref, atol=1e-9)
    # and it is a minimum of the cost: small perturbations only increase it
    cost = lambda r: float(((r @ est[:, :3, :3] - gt[:, :3, :3]) ** 2).sum())  # noqa: E731
    for k in range(6):
        d = Rotation.from_rotvec(1e-3 * np.eye(3)[k % 3] * (1 if k < 3 else -1)).as_matrix()
        assert cost(d @ ra) > cost(ra)


def test_rotation_errors_first_pose_alignment():
    gt = _random_traj(20, 10)
    rng = np.random.default_rng(11)
    theta = np.radians(rng.uniform(0.0, 4.0, 20))
    theta[0] = 0.0  # the first pose carries no orientation error: aligning it is then exact
    axes = rng.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    est = gt.copy()
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(theta[:, None] * axes).as_matrix()
    est = _sim3_apply(est, 3.0, Rotation.from_rotvec([0.0, 2.5, 0.0]).as_matrix(), np.ones(3))
    np.testing.assert_allclose(M.rotation_errors_deg(est, gt, "first"), np.degrees(theta), atol=1e-9)
    assert M.ate(est, gt, "sim3")["rot_first_mean_deg"] == pytest.approx(np.degrees(theta).mean(), abs=1e-9)
    # unaligned, every frame also carries the 2.5 rad world rotation
    assert M.rotation_errors_deg(est, gt, "none").min() > 100.0
    with pytest.raises(ValueError, match="align"):
        M.rotation_errors_deg(est, gt, "best")
    with pytest.raises(ValueError, match="equal shape"):
        M.align_rotations(est[:3, :3, :3], gt[:4, :3, :3])


def test_cli_eval_traj_reports_orientation_fit(tmp_path, capsys):
    est, gt, _, theta_deg = _straight_run_with_rotation_noise()
    ts = 1000.0 + np.arange(len(gt)) / 30.0
    write_tum_trajectory(tmp_path / "gt.txt", ts, gt)
    write_tum_trajectory(tmp_path / "est.txt", ts, est)
    code, out, _ = _run_cli(["eval", "traj", "--est", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt"),
                             "--align", "se3"], capsys)
    assert code == 0
    a = json.loads(out)["ate"]
    assert a["rot_fit_mean_deg"] == pytest.approx(theta_deg.mean(), abs=1e-5)  # files keep 9 decimals
    assert a["rot_fit_max_deg"] == pytest.approx(theta_deg.max(), abs=1e-5)
    assert {"rmse_m", "rot_err_mean_deg", "scale", "rot_first_mean_deg", "rot_fit_rmse_deg"} <= set(a)


# ----------------------------------------------------------------------------- images
def test_psnr_known_mse():
    a = np.zeros((8, 10, 3))
    assert M.psnr(a, a + 0.1) == pytest.approx(20.0)  # mse 0.01
    assert M.psnr(a, a + 25.5, max_val=255) == pytest.approx(20.0)
    assert M.psnr(a, a) == math.inf
    b = a + 0.1
    mask = np.ones((8, 10), bool)
    mask[:, :3] = False
    b[:, :3] = 5.0  # huge error outside the mask is ignored
    assert M.psnr(a, b, mask=mask) == pytest.approx(20.0)


def test_ssim_matches_skimage():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    from scipy.ndimage import gaussian_filter

    a = np.clip(gaussian_filter(rng.random((48, 64, 3)), (2, 2, 0)) * 1.5 - 0.2, 0, 1)
    for noise in [0.0, 0.02, 0.2]:
        b = np.clip(a + rng.normal(scale=noise, size=a.shape), 0, 1)
        ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                    data_range=1.0, channel_axis=-1)
        assert M.ssim(a, b) == pytest.approx(ref, abs=1e-4)
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    g = a[..., 0]
    ref = structural_similarity(g, g[::-1], gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                data_range=1.0)
    assert M.ssim(g, g[::-1]) == pytest.approx(ref, abs=1e-4)


def test_depth_l1_ignores_invalid():
    gt = np.full((4, 5), 2.0)
    gt[0] = 0.0  # invalid
    gt[1, 0] = np.nan  # invalid
    pred = gt + 0.25
    pred[0] = 100.0
    pred[1, 0] = 100.0
    assert M.depth_l1(pred, gt) == pytest.approx(0.25)
    mask = np.ones_like(gt, bool)
    mask[2] = False
    pred[2] = 50.0
    assert M.depth_l1(pred, gt, mask=mask) == pytest.approx(0.25)
    assert math.isnan(M.depth_l1(pred, np.zeros_like(gt)))


# ----------------------------------------------------------------------------- CLI round trips
def _run_cli(args, capsys):
    code = main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cli_eval_recon_round_trip(tmp_path, capsys):
    gt = _plane(4000, 1.0, 7)
    write_ply(tmp_path / "gt.ply", gt)
    write_ply(tmp_path / "pred.ply", gt + [0, 0, 0.02])  # 2 cm above GT
    code, out, _ = _run_cli(["eval", "recon", "--pred", str(tmp_path / "pred.ply"),
                             "--gt", str(tmp_path / "gt.ply")], capsys)
    assert code == 0
    r = json.loads(out)
    assert r["accuracy_cm"] == pytest.approx(2.0, abs=1e-4) and r["completion_cm"] == pytest.approx(2.0, abs=1e-4)
    assert r["completion_ratio"] == 100.0 and r["pred_kind"] == "cloud" and r["n_gt"] == 4000
    code, out, _ = _run_cli(["eval", "recon", "--pred", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "gt.ply"),
                             "--threshold", "0.01"], capsys)
    assert json.loads(out)["completion_ratio"] == 0.0


def test_eval_recon_files_scores_a_map_after_the_trajectory_sim3(tmp_path):
    """A monocular map lives in the estimate's frame and scale. Moving it by the Sim3 that aligns
    its trajectory to the GT (here known: the map is the GT seen through the inverse similarity)
    gives back the GT scores; unaligned it scores nothing."""
    gt = _plane(4000, 1.0, 7) + [0.0, 0.0, 1.0]
    s, rot, t = 0.6, Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), np.array([0.5, -0.2, 0.1])
    est_traj = np.tile(np.eye(4), (5, 1, 1))
    est_traj[:, :3, 3] = np.random.default_rng(1).normal(size=(5, 3))
    gt_traj = est_traj.copy()
    gt_traj[:, :3, :3] = rot @ est_traj[:, :3, :3]
    gt_traj[:, :3, 3] = s * est_traj[:, :3, 3] @ rot.T + t
    write_ply(tmp_path / "gt.ply", gt)
    write_ply(tmp_path / "pred.ply", ((gt - t) @ rot) / s)  # the inverse of x -> s R x + t
    sim3 = M.align_trajectory(est_traj, gt_traj, "sim3")[1]
    np.testing.assert_allclose(sim3[0], s, rtol=1e-9)
    r = M.eval_recon_files(tmp_path / "pred.ply", tmp_path / "gt.ply", samples=4000, align=sim3)
    # float32 PLY rounding and r["align_scale"] == pytest.approx(s)
    assert r["accuracy_cm"] < 1e-4 and r["completion_ratio"] == 100.0
    assert M.eval_recon_files(tmp_path / "pred.ply", tmp_path / "gt.ply", samples=4000)["completion_ratio"] < 5.0


def test_cli_eval_recon_meshes(tmp_path, capsys):
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    write_ply(tmp_path / "gt.ply", verts, faces=faces)
    write_ply(tmp_path / "pred.ply", verts + [0, 0, 0.01], faces=faces)
    n = 20_000
    code, out, _ = _run_cli(["eval", "recon", "--pred", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "gt.ply"),
                             "--samples", str(n)], capsys)
    assert code == 0
    r = json.loads(out)
    assert r["pred_kind"] == "mesh" and r["n_pred"] == n and r["n_gt"] == n
    # independent uniform samples on two parallel planes 1 cm apart: the NN distance is sqrt(h^2 + r^2)
    # with h = 1 cm and r the in-plane distance to the nearest of a Poisson set of density n / m^2,
    # P(r > x) = exp(-n pi x^2), i.e. Rayleigh with s^2 = 1 / (2 pi n).
    s2 = 1 / (2 * math.pi * n)
    exp_cm = 100 * integrate.quad(lambda x: math.hypot(0.01, x) * x / s2 * math.exp(-x * x / (2 * s2)),
                                  0, 12 * math.sqrt(s2))[0]
    assert 1.0 < exp_cm < 1.1
    assert r["accuracy_cm"] == pytest.approx(exp_cm, rel=0.02)
    assert r["completion_cm"] == pytest.approx(exp_cm, rel=0.02)


def test_cli_eval_recon_empty_prediction(tmp_path, capsys):
    write_ply(tmp_path / "gt.ply", _plane(100, 1.0, 0))
    write_ply(tmp_path / "pred.ply", np.zeros((0, 3)))
    code, out, _ = _run_cli(["eval", "recon", "--pred", str(tmp_path / "pred.ply"),
                             "--gt", str(tmp_path / "gt.ply")], capsys)
    assert code == 0
    r = json.loads(out)
    assert r["accuracy_cm"] == math.inf and r["completion_ratio"] == 0.0 and "pred.ply" in r["note"]


def test_cli_eval_traj_round_trip(tmp_path, capsys):
    gt = _random_traj(50, 3)
    ts = 1000.0 + np.arange(50) / 30.0
    est = _sim3_apply(gt, 2.0, Rotation.from_rotvec([0.2, -0.4, 1.0]).as_matrix(), np.array([1.0, 2.0, 3.0]))
    write_tum_trajectory(tmp_path / "gt.txt", ts, gt)
    # estimate: timestamps jittered by 5 ms, first GT pose missing, one extra pose far in time
    est_ts = np.r_[ts[1:] + 0.005, 2000.0]
    write_tum_trajectory(tmp_path / "est.txt", est_ts, np.concatenate([est[1:], est[-1:]]))
    code, out, _ = _run_cli(["eval", "traj", "--est", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt"),
                             "--align", "sim3"], capsys)
    assert code == 0
    r = json.loads(out)
    assert r["n_matched"] == 49 and r["n_est"] == 50 and r["n_gt"] == 50
    assert r["ate"]["rmse_m"] < 1e-6  # TUM files keep 9 decimals
    assert r["ate"]["scale"] == pytest.approx(0.5, abs=1e-7)
    assert r["rpe"]["trans_rmse_m"] < 1e-6 and r["rpe"]["rot_rmse_deg"] < 1e-4
    code, out, _ = _run_cli(["eval", "traj", "--est", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt"),
                             "--align", "se3"], capsys)
    assert json.loads(out)["ate"]["rmse_m"] > 0.5


def test_cli_eval_traj_too_few_matches(tmp_path, capsys):
    gt = _random_traj(10, 4)
    write_tum_trajectory(tmp_path / "gt.txt", np.arange(10.0), gt)
    write_tum_trajectory(tmp_path / "est.txt", np.arange(10.0) + 0.5, gt)
    code, _, err = _run_cli(["eval", "traj", "--est", str(tmp_path / "est.txt"), "--gt", str(tmp_path / "gt.txt")],
                            capsys)
    assert code == 2
    assert "est.txt" in err and "gt.txt" in err and "0 timestamp matches" in err
    with pytest.raises(ValueError, match="est.txt"):
        M.eval_traj_files(tmp_path / "est.txt", tmp_path / "gt.txt")


def test_timestamp_matching_is_one_to_one():
    est_ts = np.array([0.0, 0.004, 0.1, 0.2])
    gt_ts = np.array([0.005, 0.1, 0.2])
    i, j = M._match(est_ts, gt_ts, 0.02)
    np.testing.assert_array_equal(i, [1, 2, 3])  # 0.004 is closer to 0.005 than 0.0 is
    np.testing.assert_array_equal(j, [0, 1, 2])


def _room_cloud(rng, n: int) -> np.ndarray:
    """Points on the inside of a 4 x 3 x 2.5 m box room and on a 1 x 0.5 x 0.8 m cabinet in one corner."""
    faces = []
    for lo, hi in (((0, 0, 0), (4, 3, 2.5)), ((0.2, 0.2, 0), (1.2, 0.7, 0.8))):
        lo, hi = np.array(lo, float), np.array(hi, float)
        for axis in range(3):
            for side in (lo, hi):
                p = lo + rng.random((n // 12, 3)) * (hi - lo)
                p[:, axis] = side[axis]
                faces.append(p)
    return np.concatenate(faces)


def test_icp_similarity_recovers_a_known_tilt_shift_and_scale_of_a_room():
    """A room's cloud moved by a known similarity (6 deg about a tilted axis, 12 cm, scale 1.05), with 3 mm
    noise and 10 % of the points thrown anywhere in the room: trimmed ICP from the identity, and from a Sim3
    that is part of the way (composed in), lands on the inverse to 0.05 deg, 2 mm and 0.2 %; the info says how far
    the refinement moved."""
    from fmapping.metrics import icp_similarity, rotation_angle_deg

    rng = np.random.default_rng(3)
    dst = _room_cloud(rng, 60_000)
    rot = Rotation.from_rotvec(np.radians(6.0) * np.array([1.0, 0.4, 0.2]) / np.linalg.norm([1.0, 0.4, 0.2]))
    s, r, t = 1.05, rot.as_matrix(), np.array([0.08, -0.06, 0.07])
    src = (dst - t) @ r / s  # s R src + t = dst
    src = src[rng.permutation(len(src))[:40_000]] + rng.normal(0, 0.003, (40_000, 3))
    src[:4000] = rng.random((4000, 3)) * [4, 3, 2.5]
    for init in (None, (1.02, Rotation.from_rotvec(0.5 * rot.as_rotvec()).as_matrix(), 0.5 * t)):
        (s2, r2, t2), info = icp_similarity(src, dst, init=init)
        assert abs(s2 / s - 1) < 2e-3
        assert float(rotation_angle_deg(r2.T @ r)) < 0.05
        centre = src.mean(0)
        assert np.linalg.norm((s2 * r2 @ centre + t2) - (s * r @ centre + t)) < 0.002
        assert info["kept_share"] > 0.85
        if init is None:
            assert 5.9 < info["rotation_deg"] < 6.1 and abs(info["scale"] / s - 1) < 2e-3
