"""Image consistency of a trajectory (KLT tracks + depth) and the camera-frame rotation fit."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fmapping.tracking.consistency import depth_tracks, fit_camera_rotation, reprojection_errors, reprojection_px


@pytest.fixture(scope="module")
def room(room320):
    from fmapping.datasets import open_dataset

    ds = open_dataset(room320)
    frames = [ds[i] for i in range(len(ds))]
    return ds.camera, frames, np.stack([f.c2w for f in frames])


def _rot(axis: int, deg: float) -> np.ndarray:
    v = np.zeros(3)
    v[axis] = np.radians(deg)
    x = np.eye(4)
    x[:3, :3] = Rotation.from_rotvec(v).as_matrix()
    return x


def test_ground_truth_explains_the_tracks_and_a_rotated_pose_moves_them_by_f_times_the_angle(room):
    camera, frames, gt = room
    pairs = depth_tracks([f.rgb for f in frames[:2]], [f.depth for f in frames[:2]], camera, steps=(1,))
    assert len(pairs) == 1 and len(pairs[0].uv_b) > 200
    assert reprojection_px(pairs, gt, camera)["median_px"] < 0.2  # rendered images, exact depth (measured 0.08 px)
    # frame 1 tilted by 0.5 deg about its x axis: every point moves ~ fy * 0.5 deg vertically (measured 1.06x)
    bad = gt.copy()
    bad[1] = gt[1] @ _rot(0, 0.5)
    moved = np.median(reprojection_errors(pairs, bad, camera)[0])
    expected = camera.fy * np.radians(0.5)
    assert 0.9 * expected < moved < 1.3 * expected


def test_fit_camera_rotation_recovers_a_rotated_camera_frame(room):
    camera, frames, gt = room
    pairs = depth_tracks([f.rgb for f in frames], [f.depth for f in frames], camera, steps=(1, 10, 20),
                         start_every=4)
    base = reprojection_px(pairs, gt, camera)["median_px"]
    for axis in range(3):
        y = _rot(axis, 1.5)
        wrong = gt @ y  # poses whose camera frame is rotated by 1.5 deg against the images
        assert reprojection_px(pairs, wrong, camera)["median_px"] > 2 * base
        x = fit_camera_rotation(pairs, wrong, camera)
        left = np.degrees(Rotation.from_matrix(y[:3, :3] @ x).magnitude())
        assert left < 0.15, (axis, left)  # measured 0.05 deg (the GT itself fits 0.05 deg off: KLT)
        assert reprojection_px(pairs, wrong, camera, x)["median_px"] < base + 0.02
    # restricted to the other axes, an x rotation cannot be fitted
    x = fit_camera_rotation(pairs, gt @ _rot(0, 1.5), camera, axes="yz")
    assert abs(Rotation.from_matrix(x).as_rotvec()[0]) < 1e-12


def test_frame_tracks_follow_corners_within_the_length_limits(room):
    from fmapping.tracking.consistency import frame_tracks

    camera, frames, gt = room
    tr = frame_tracks([f.rgb for f in frames[:12]], start_every=4, max_length=5, min_length=3)
    assert tr.tracks > 300 and np.array_equal(np.unique(tr.track), np.arange(tr.tracks))
    for t in range(0, tr.tracks, 37):
        seen = np.sort(tr.frame[tr.track == t])
        assert 3 <= len(seen) <= 5 and np.array_equal(seen, np.arange(seen[0], seen[0] + len(seen)))
        assert seen[0] % 4 == 0  # started at a start frame
    # the tracked pixels are where the GT puts their points: back-project the first observation with
    # the rendered depth, move it with the GT, compare with the last (measured median 0.07 px)
    err = []
    for t in range(0, tr.tracks, 5):
        o = np.flatnonzero(tr.track == t)
        a, b = o[np.argmin(tr.frame[o])], o[np.argmax(tr.frame[o])]
        fa, fb = tr.frame[a], tr.frame[b]
        u, v = tr.uv[a]
        z = frames[fa].depth[int(round(v)), int(round(u))]
        p = np.linalg.inv(camera.K) @ np.array([u, v, 1.0]) * z
        q = (np.linalg.inv(gt[fb]) @ gt[fa] @ np.r_[p, 1.0])[:3]
        err.append(np.linalg.norm((camera.K @ q)[:2] / q[2] - tr.uv[b]))
    assert np.median(err) < 0.3
    with pytest.raises(ValueError, match="max_length"):
        frame_tracks([f.rgb for f in frames[:3]], max_length=1)


def test_best_explaining_poses_finds_the_images_trajectory_from_a_wrong_start(room):
    """From poses 2 cm / 1 deg off the GT the global BA comes back to the GT (up to the scale it
    cannot see), and to the same poses as from the GT itself."""
    from fmapping.metrics import ate
    from fmapping.tracking.consistency import best_explaining_poses, frame_tracks

    camera, frames, gt = room
    frames, gt = frames[:20], gt[:20]
    tracks = frame_tracks([f.rgb for f in frames])
    depths = [f.depth for f in frames]
    rng = np.random.default_rng(0)
    start = gt.copy()
    for i in range(1, len(gt)):
        start[i, :3, :3] = Rotation.from_rotvec(np.radians(1.0) * rng.normal(size=3) / np.sqrt(3)).as_matrix() \
            @ gt[i, :3, :3]
        start[i, :3, 3] += 0.02 * rng.normal(size=3) / np.sqrt(3)
    before = ate(start, gt, "sim3")
    assert before["rmse_m"] > 0.012 and before["rot_first_mean_deg"] > 0.7  # measured 1.58 cm, 0.91 deg
    from_wrong, info = best_explaining_poses(camera, tracks, start, depths)
    from_gt, _ = best_explaining_poses(camera, tracks, gt, depths)
    after = ate(from_wrong, gt, "sim3")
    assert info["cost"] < 0.05 * info["cost_start"] and info["median_px"] < 0.3  # measured 0.3 %, 0.08 px
    assert after["rmse_m"] < 0.003 and after["rot_first_mean_deg"] < 0.15, after  # measured 0.07 cm, 0.074 deg
    apart = ate(from_wrong, from_gt, "sim3")
    assert apart["rmse_m"] < 1e-4 and apart["rot_first_mean_deg"] < 0.01, apart  # measured 1e-8 m, 1e-6 deg
    with pytest.raises(ValueError, match="same frames"):
        best_explaining_poses(camera, tracks, gt[:10], depths[:10])
