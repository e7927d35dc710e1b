"""Rolling-shutter unrolling against an exact simulation of a rolling-shutter camera."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fmapping.camera import PinholeCamera
from fmapping.tracking.rolling_shutter import rotation_step, rotation_steps, unroll, unroll_tracks

CAM = PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480)


def _rolling_shutter_pixels(cam: PinholeCamera, r0: np.ndarray, step: np.ndarray, readout: float,
                            dirs: np.ndarray) -> np.ndarray:
    """Where a rolling-shutter camera (orientation ``r0 exp(tau [step])`` at row time ``tau``) sees
    world directions ``dirs``: each row's own orientation, solved by fixed-point iteration on the row."""
    v = np.full(len(dirs), cam.height / 2.0)
    for _ in range(50):
        tau = readout * (v - cam.height / 2.0) / cam.height
        rot = r0 @ Rotation.from_rotvec(tau[:, None] * step).as_matrix()  # (N, 3, 3) camera-to-world
        b = np.einsum("nji,nj->ni", rot, dirs)
        uv = np.stack([cam.fx * b[:, 0] / b[:, 2] + cam.cx, cam.fy * b[:, 1] / b[:, 2] + cam.cy], -1)
        v = uv[:, 1]
    return uv


def test_unroll_gives_the_global_shutter_pixels_of_the_middle_row_pose():
    rng = np.random.default_rng(0)
    r0 = Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix()
    step = np.radians([0.8, -3.5, 1.2])  # per frame: 110 deg/s about y at 30 Hz, as on TUM fr1_rpy
    gs = np.c_[rng.uniform(40, 600, 300), rng.uniform(30, 450, 300)]
    rays = np.c_[(gs[:, 0] - CAM.cx) / CAM.fx, (gs[:, 1] - CAM.cy) / CAM.fy, np.ones(len(gs))]
    dirs = rays @ r0.T  # the world directions the middle-row pose sees at ``gs``
    rs = _rolling_shutter_pixels(CAM, r0, step, 0.85, dirs)
    assert np.abs(rs - gs).max() > 10  # the rows' different orientations move pixels by ~15 px
    np.testing.assert_allclose(unroll(CAM, rs, step, 0.85), gs, atol=1e-6)
    # no readout, no motion: nothing moves
    assert np.array_equal(unroll(CAM, rs, step, 0.0), rs)
    np.testing.assert_allclose(unroll(CAM, gs, np.zeros(3), 0.85), gs, atol=1e-9)


def test_rotation_steps_of_a_constant_rate_turn():
    step = np.radians([0.5, -2.0, 0.3])
    r = [np.eye(3)]
    for _ in range(7):
        r.append(r[-1] @ Rotation.from_rotvec(step).as_matrix())
    c2w = np.tile(np.eye(4), (8, 1, 1))
    c2w[:, :3, :3] = r
    c2w[:, :3, 3] = np.arange(8)[:, None] * 0.01
    np.testing.assert_allclose(rotation_step(c2w[2], c2w[3]), step, atol=1e-12)
    np.testing.assert_allclose(rotation_steps(c2w), np.tile(step, (8, 1)), atol=1e-9)


def test_unroll_tracks_uses_each_frames_own_step():
    from fmapping.tracking.consistency import FrameTracks

    uv = np.array([[100.0, 50.0], [500.0, 400.0], [320.0, 240.0], [20.0, 470.0]])
    tracks = FrameTracks(np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]), uv)
    steps = np.radians([[0.0, -3.0, 0.0], [1.0, 0.0, 0.5]])
    out = unroll_tracks(CAM, tracks, steps, 0.9)
    np.testing.assert_allclose(out.uv[:2], unroll(CAM, uv[:2], steps[0], 0.9))
    np.testing.assert_allclose(out.uv[2:], unroll(CAM, uv[2:], steps[1], 0.9))
    assert np.array_equal(tracks.uv, uv)  # the input is left as it was


@pytest.mark.parametrize("readout", [0.5, 1.0])
def test_mono_front_end_with_a_rolling_shutter_model_on_global_shutter_frames(room320, readout):
    """On global-shutter frames the unrolling is a model error of ~readout x the rotation per frame
    (0.3-0.9 deg here): tracking must stay close to the global-shutter model's result."""
    from fmapping.datasets import open_dataset
    from fmapping.metrics import ate
    from fmapping.tracking.mono import MonoConfig, MonoFrontend

    ds = open_dataset(room320)
    frames = [ds[i] for i in range(30)]
    results = {}
    for r in (0.0, readout):
        fe = MonoFrontend(ds.camera, cfg=MonoConfig(rolling_shutter=r))
        g0 = frames[0].c2w
        anchor = lambda k: float(np.linalg.norm(frames[k].c2w[:3, 3] - g0[:3, 3]))  # noqa: E731
        est, i = {}, 0
        while not fe.initialized:
            out = fe.bootstrap(i, frames[i].rgb, g0, anchor)
            i += 1
        est.update(out)
        for j in range(i, len(frames)):
            est[j] = fe.track(j, frames[j].rgb).c2w
        est.update(fe.poses())
        results[r] = ate(np.stack([est[k] for k in sorted(est)]), np.stack([f.c2w for f in frames]), "sim3")
    assert results[0.0]["rmse_m"] < 0.01
    assert results[readout]["rmse_m"] < 0.02, results  # measured 0.26 cm at 0.5, 0.62 cm at 1.0 (0.23 cm at 0)


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_mono_config_refuses_a_readout_outside_one_frame(bad):
    from fmapping.tracking.mono import MonoConfig, MonoFrontend

    with pytest.raises(ValueError, match="mono.rolling_shutter"):
        MonoFrontend(CAM, cfg=MonoConfig(rolling_shutter=bad))
