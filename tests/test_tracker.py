"""Direct photometric tracking (direct_align, direct_tracker): Jacobians, pose recovery, loss detection; pose sources;
two-view geometry and bundle adjustment."""
import math

import numpy as np
import pytest

from fmapping.camera import PinholeCamera
from fmapping.geometry import inv_pose, pose_distance, se3_exp_np
from fmapping.tracking.direct_align import (
    AlignConfig, align, bilinear, build_pyramid, evaluate_pose, make_reference, select_pixels, to_gray, warp_residuals,
    with_gradients,
)
from fmapping.tracking.direct_tracker import DirectTracker, TrackerConfig


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def scene_pair():
    """Two 160x120 views of synthetic room seed 0 with a known 2 cm / 1 deg offset, GT depth."""
    from fmapping.synthetic import camera_for_size, make_scene, make_trajectory, render_view

    cam = camera_for_size(160, 120)
    scene = make_scene(0)
    c2w0 = make_trajectory(scene, 10, 0)[0]
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    tdir = np.array([1.0, 0.4, -0.3]) / np.linalg.norm([1.0, 0.4, -0.3])
    delta = np.concatenate([0.02 * tdir, math.radians(1.0) * axis])
    c2w1 = c2w0 @ se3_exp_np(delta)  # offset in the camera frame of view 0
    rgb0, d0 = render_view(scene, cam, c2w0)
    rgb1, d1 = render_view(scene, cam, c2w1)
    return cam, c2w0, c2w1, rgb0, d0, rgb1, d1


def _linear_image(h, w, a=0.003, b=-0.002, c=0.4):
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return a * u + b * v + c  # float64: exactly linear


# ----------------------------------------------------------------------------- small pieces
def test_bilinear_matches_cv2_style_reference():
    rng = np.random.default_rng(1)
    img = rng.random((20, 30, 3)).astype(np.float32)
    u = rng.uniform(0, 29, 200)
    v = rng.uniform(0, 19, 200)
    out = bilinear(img, u, v)
    # slow reference
    ref = np.zeros_like(out)
    for k in range(len(u)):
        x0, y0 = min(int(u[k]), 28), min(int(v[k]), 18)
        fx, fy = u[k] - x0, v[k] - y0
        ref[k] = ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
                  + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])
    np.testing.assert_allclose(out, ref, atol=1e-5)


def test_select_pixels_spread_and_strength():
    rng = np.random.default_rng(2)
    img = rng.random((120, 160)).astype(np.float32)
    img[:, :80] = 0.5  # left half flat: nothing to select there
    uv = select_pixels(img, 300, min_grad=0.02)
    assert 100 < len(uv) <= 300
    assert (uv[:, 0] >= 78).all()  # only in the textured half (cells straddling the edge allowed)
    assert len(np.unique(uv // 16, axis=0)) > 30  # spread over many 16-px cells


# ----------------------------------------------------------------------------- Jacobians
@pytest.mark.parametrize("affine", [(0.0, 0.0), (0.1, -0.05)])
def test_jacobian_exact_on_linear_image(affine):
    """On an image linear in (u, v) the bilinear sampler and the central-difference
    gradient are exact, so the analytic Jacobian must match finite differences tightly."""
    cam = PinholeCamera(200.0, 210.0, 79.5, 59.5, 160, 120)
    lvl = with_gradients(_linear_image(120, 160))
    rng = np.random.default_rng(3)
    n = 60
    uv = np.stack([rng.uniform(40, 120, n), rng.uniform(30, 90, n)], -1)
    z = rng.uniform(1.0, 3.0, n)
    pts = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], -1)
    iref = rng.uniform(0, 1, n).astype(np.float32)
    t = se3_exp_np(np.array([0.03, -0.02, 0.01, 0.02, -0.01, 0.015]))
    ab = np.array(affine)
    r, jac, valid = warp_residuals(lvl, cam, pts, iref, t, ab)
    assert valid.all()
    eps = 1e-6
    num = np.zeros_like(jac)
    for k in range(8):
        d = np.zeros(8)
        d[k] = eps

        def f(sign):
            dd = sign * d
            return warp_residuals(lvl, cam, pts, iref, se3_exp_np(dd[:6]) @ t, ab + dd[6:], with_jacobian=False)[0]
        num[:, k] = (f(1) - f(-1)) / (2 * eps)
    np.testing.assert_allclose(jac, num, rtol=1e-5, atol=1e-6)


def test_jacobian_close_on_smooth_image():
    """On a smooth textured image the central-difference gradient approximates the derivative of
    the bilinear interpolant: the Jacobian agrees with finite differences to a few percent."""
    cam = PinholeCamera(200.0, 200.0, 79.5, 59.5, 160, 120)
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    img = (0.5 + 0.2 * np.sin(0.05 * u + 0.3) * np.cos(0.07 * v) + 0.1 * np.sin(0.03 * u + 0.02 * v))
    lvl = with_gradients(img.astype(np.float32)).astype(np.float64)
    rng = np.random.default_rng(4)
    n = 300
    uv = np.stack([rng.uniform(40, 120, n), rng.uniform(30, 90, n)], -1)
    z = rng.uniform(1.0, 3.0, n)
    pts = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], -1)
    t = se3_exp_np(np.array([0.02, 0.01, -0.01, -0.01, 0.02, 0.0]))
    r, jac, _ = warp_residuals(lvl, cam, pts, np.zeros(n, np.float32), t, np.zeros(2))
    eps = 1e-4
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        fp = warp_residuals(lvl, cam, pts, np.zeros(n, np.float32), se3_exp_np(d) @ t, np.zeros(2), False)[0]
        fm = warp_residuals(lvl, cam, pts, np.zeros(n, np.float32), se3_exp_np(-d) @ t, np.zeros(2), False)[0]
        num = (fp - fm) / (2 * eps)
        rel = np.linalg.norm(jac[:, k] - num) / np.linalg.norm(num)
        assert rel < 0.06, (k, rel)


# ----------------------------------------------------------------------------- pose recovery
def test_pose_recovery_on_synthetic_pair(scene_pair):
    cam, c2w0, c2w1, rgb0, d0, rgb1, _ = scene_pair
    ref = make_reference(rgb0, d0, cam, c2w0, levels=3, num_points=2000)
    cur = build_pyramid(to_gray(rgb1), cam, 3)
    res = align(ref, cur, np.eye(4), AlignConfig())  # start from "no motion"
    est = c2w0 @ inv_pose(res.t_cr)
    start_t, start_r = pose_distance(c2w0, c2w1)
    assert start_t > 0.019 and start_r > 0.99
    dt, dr = pose_distance(est, c2w1)
    assert dt < 0.002 and dr < 0.1, (dt, dr)
    assert res.ok and res.inlier_ratio > 0.9


def test_evaluate_pose_measures_what_align_measures_at_its_optimum_and_fits_a_known_exposure(scene_pair):
    """evaluate_pose: the residual, inlier and visible ratios align reports, for a pose it is given (a fast
    path of the same measures: one warp, no pose steps). At align's own optimum both agree; with the frame's
    exposure changed by a known gain and offset it recovers them; at a pose 2 deg off the inliers collapse."""
    cam, c2w0, c2w1, rgb0, d0, rgb1, _ = scene_pair
    cfg = AlignConfig()
    ref = make_reference(rgb0, d0, cam, c2w0, levels=3, num_points=2000)
    gray = to_gray(rgb1)
    best = align(ref, build_pyramid(gray, cam, 3), np.eye(4), cfg)
    ev = evaluate_pose(ref, gray, cam, best.t_cr, cfg, best.affine)
    assert ev.ok and ev.iterations == 0
    np.testing.assert_allclose(ev.t_cr, best.t_cr, atol=1e-12)  # the pose is not moved
    assert abs(ev.rmse - best.rmse) < 0.1 * best.rmse and abs(ev.inlier_ratio - best.inlier_ratio) < 0.01
    assert ev.visible_ratio == pytest.approx(best.visible_ratio, abs=1e-9)

    gain, offset = 1.15, -0.04  # observed = gain * I + offset: affine (log gain, offset)
    darker = np.clip(gain * gray + offset, 0.0, 1.0).astype(np.float32)
    from_zero = evaluate_pose(ref, darker, cam, best.t_cr, cfg, np.zeros(2))
    a0, b0 = best.affine  # gray ~ exp(a0) I_ref + b0, so darker ~ exp(a0 + log gain) I_ref + gain b0 + offset
    np.testing.assert_allclose(from_zero.affine, [a0 + math.log(gain), gain * b0 + offset], atol=0.01)
    assert from_zero.inlier_ratio > best.inlier_ratio - 0.02
    off = evaluate_pose(ref, gray, cam, se3_exp_np(np.r_[0, 0, 0, 0, math.radians(2.0), 0]) @ best.t_cr, cfg,
                        best.affine)
    assert off.inlier_ratio < best.inlier_ratio - 0.2, (off.inlier_ratio, best.inlier_ratio)


def test_tracker_verify_takes_a_good_pose_from_elsewhere_and_refuses_a_wrong_one(scene_pair):
    """DirectTracker.verify judges a pose found elsewhere with track's own checks: the true pose of the
    second view passes (and feeds the motion model), one 0.25 m off does not and changes nothing."""
    cam, c2w0, c2w1, rgb0, d0, rgb1, _ = scene_pair
    tr = DirectTracker(cam, TrackerConfig(num_points=1500))
    tr.set_reference(rgb0, d0, c2w0, 0)
    tr.observe(c2w0)
    pred = tr.predict()
    wrong = c2w1 @ se3_exp_np(np.r_[0.25, 0, 0, 0, 0, 0])
    assert tr.verify(rgb1, wrong) is None
    np.testing.assert_allclose(tr.predict(), pred, atol=1e-12)
    got = tr.verify(rgb1, c2w1)
    assert got is not None and not got.lost and got.inlier_ratio > 0.9
    assert pose_distance(got.c2w, c2w1)[0] < 1e-9
    assert pose_distance(tr.motion_history[-1], c2w1)[0] < 1e-9


def test_motion_model_predicts_across_skipped_frames_from_the_frame_indices():
    """A live tracker that cannot keep up skips frames (never two in a row). The constant-velocity prediction
    must cover the frames since the last pose: with poses at frames 10 and 12 and frame 13 next it is half the
    step, with poses at 12 and 13 and frame 15 next two steps. Without indices it is one step, as before; the
    true pose of a camera moving at constant velocity is then a whole frame's motion away."""
    rng = np.random.default_rng(3)
    p0 = se3_exp_np(rng.normal(0, 0.3, 6))
    xi = np.array([0.024, 0.004, -0.006, 0.002, 0.015, 0.001])  # 2.5 cm and ~0.9 deg a frame
    pose = lambda k: p0 @ se3_exp_np(k * xi)  # noqa: E731
    cam = PinholeCamera(250.0, 250.0, 159.5, 119.5, 320, 240)
    for seen, nxt in (((10, 12), 13), ((12, 13), 15), ((20, 21), 22)):
        tr = DirectTracker(cam, TrackerConfig())
        for k in seen:
            tr.at_frame(k)
            tr.observe(pose(k))
        tr.at_frame(nxt)
        dt, dr = pose_distance(tr.predict(), pose(nxt))
        assert dt < 1e-9 and dr < 1e-7, (seen, nxt, dt, dr)
        blind = DirectTracker(cam, TrackerConfig())  # no frame indices: one step per pose
        for k in seen:
            blind.observe(pose(k))
        off = pose_distance(blind.predict(), pose(nxt))[0]
        if nxt - seen[1] == seen[1] - seen[0]:
            assert off < 1e-9
        else:
            assert off > 0.01, off
    # the history moves with its keyframe and keeps its frames; a history given anew takes its own
    tr = DirectTracker(cam, TrackerConfig())
    for k in (4, 6):
        tr.at_frame(k)
        tr.observe(pose(k))
    t = se3_exp_np(np.array([0.1, 0.0, -0.05, 0.0, 0.02, 0.0]))
    tr.move_motion(t)
    tr.at_frame(7)
    assert pose_distance(tr.predict(), t @ pose(7))[0] < 1e-9
    tr.reset_motion([pose(7), pose(8)], [7, 8])
    tr.at_frame(10)
    assert pose_distance(tr.predict(), pose(10))[0] < 1e-9
    tr.at_frame(30)  # a long gap: at most max_prediction_steps steps
    assert pose_distance(tr.predict(), pose(8 + TrackerConfig().max_prediction_steps))[0] < 1e-9
    with pytest.raises(ValueError, match="frame indices"):
        tr.reset_motion([pose(1), pose(2)], [2])


def test_tracker_flags_noise_frame_and_keeps_pose(scene_pair):
    cam, c2w0, c2w1, rgb0, d0, rgb1, _ = scene_pair
    tr = DirectTracker(cam, TrackerConfig(num_points=1500))
    tr.set_reference(rgb0, d0, c2w0, 0)
    tr.observe(c2w0)
    good = tr.track(rgb1)
    assert not good.lost
    assert pose_distance(good.c2w, c2w1)[0] < 0.003
    pred = tr.predict()
    noise = np.random.default_rng(5).integers(0, 256, rgb0.shape, dtype=np.uint8)
    bad = tr.track(noise)
    assert bad.lost and bad.reason
    dt, dr = pose_distance(bad.c2w, pred)
    assert dt < 1e-9 and dr < 1e-6  # the reported pose is the prediction, not an optimiser output
    # the motion model was not updated from the noise frame
    np.testing.assert_allclose(tr.predict(), pred, atol=1e-12)


def test_tracker_recovers_after_a_lost_frame(scene_pair):
    cam, c2w0, c2w1, rgb0, d0, rgb1, _ = scene_pair
    tr = DirectTracker(cam, TrackerConfig(num_points=1500))
    tr.set_reference(rgb0, d0, c2w0, 0)
    tr.observe(c2w0)
    tr.track(np.zeros_like(rgb0))  # black frame: lost
    res = tr.track(rgb1)
    assert not res.lost
    assert pose_distance(res.c2w, c2w1)[0] < 0.003


def test_reference_depth_callable_matches_depth_image(scene_pair):
    cam, c2w0, _, rgb0, d0, _, _ = scene_pair
    a = make_reference(rgb0, d0, cam, c2w0, num_points=500)
    b = make_reference(rgb0, lambda uv: d0[uv[:, 1].astype(int), uv[:, 0].astype(int)], cam, c2w0, num_points=500)
    np.testing.assert_allclose(a.points, b.points)


def test_make_reference_rejects_mismatched_depth(scene_pair):
    cam, c2w0, _, rgb0, d0, _, _ = scene_pair
    with pytest.raises(ValueError, match="depth is"):
        make_reference(rgb0, d0[:-1], cam, c2w0)


# ----------------------------------------------------------------------------- pose sources
def test_poses_from_file_matches_and_reports_missing(tmp_path):
    from fmapping.tracking.sources import poses_from_file
    from fmapping.trajectory import write_tum_trajectory

    poses = np.stack([se3_exp_np(np.array([0.1 * i, 0, 0, 0, 0.01 * i, 0])) for i in range(5)])
    ts = np.arange(5) * 0.1
    write_tum_trajectory(tmp_path / "t.txt", ts, poses)
    got = poses_from_file(tmp_path / "t.txt", ts + 0.001)
    np.testing.assert_allclose(np.stack(got), poses, atol=1e-8)
    with pytest.raises(ValueError, match="t.txt"):
        poses_from_file(tmp_path / "t.txt", np.array([5.0]))


def test_kiss_icp_recovers_motion_of_a_box_room():
    """kiss-icp on depth images of an analytic room with boxes (camera translating 2.5 cm per frame)."""
    from fmapping.tracking.sources import KissIcpConfig, KissIcpOdometry

    cam = PinholeCamera(120.0, 120.0, 79.5, 59.5, 160, 120)
    rng = np.random.default_rng(6)
    centers = np.stack([rng.uniform(-1.8, 2.3, 40), rng.uniform(-1.3, 1.0, 40), rng.uniform(1.5, 3.8, 40)], -1)
    sizes = rng.uniform(0.1, 0.3, (40, 3))
    boxes = [(c - s, c + s) for c, s in zip(centers, sizes)]

    def depth_of_room(c2w):
        v, u = np.mgrid[0:120, 0:160].astype(np.float64)
        d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1) @ c2w[:3, :3].T
        o = c2w[:3, 3]
        best = np.full(u.shape, np.inf)
        lo, hi = np.array([-2.0, -1.5, -1.0]), np.array([2.5, 1.2, 4.0])
        for ax in range(3):
            for bound in (lo[ax], hi[ax]):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = (bound - o[ax]) / d[..., ax]
                best = np.where((t > 0) & (t < best), t, best)
        # small boxes give the scan structure in every direction (point-to-point ICP slides on bare walls)
        for blo, bhi in boxes:
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (blo - o) / d
                t2 = (bhi - o) / d
            tn = np.minimum(t1, t2).max(-1)
            tf = np.maximum(t1, t2).min(-1)
            best = np.where((tn < tf) & (tn > 0) & (tn < best), tn, best)
        return best.astype(np.float32)

    odo = KissIcpOdometry(cam, KissIcpConfig(voxel_size=0.05, stride=1))
    poses = [se3_exp_np(np.array([0.02 * i, 0.0, 0.015 * i, 0.0, 0.0, 0.0])) for i in range(8)]
    est = [odo.register(depth_of_room(p)) for p in poses]
    t_est, t_gt = est[-1][:3, 3], poses[-1][:3, 3]
    # conventions: the camera-to-world motion comes out in the right direction, without rotation.
    # Magnitude: point-to-point ICP on re-sampled depth with 5 cm voxels under-estimates mm-scale
    # per-frame motion (measured ratio ~0.5 here; ~0.3 on TUM fr1_rpy), so only bounds are asserted.
    cos = float(t_est @ t_gt / (np.linalg.norm(t_est) * np.linalg.norm(t_gt)))
    ratio = float(np.linalg.norm(t_est) / np.linalg.norm(t_gt))
    assert cos > 0.95 and 0.2 < ratio < 1.2, (cos, ratio)
    assert pose_distance(est[-1], poses[-1])[1] < 1.0
    # a frame offset: the first pose is c2w_first
    first = se3_exp_np(np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]))
    odo2 = KissIcpOdometry(cam, KissIcpConfig(voxel_size=0.05, stride=2), c2w_first=first)
    np.testing.assert_allclose(odo2.register(depth_of_room(poses[0])), first, atol=1e-9)


# ----------------------------------------------------------------------------- two-view geometry and BA
def _points_and_views(seed=7, n=300):
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240)
    pts = np.stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(2.0, 5.0, n)], -1)
    poses = [np.eye(4), se3_exp_np(np.array([0.25, 0.05, 0.05, 0.02, -0.05, 0.01])),
             se3_exp_np(np.array([0.45, -0.05, 0.1, -0.01, -0.09, 0.02]))]

    def project(c2w):
        w2c = inv_pose(c2w)
        y = pts @ w2c[:3, :3].T + w2c[:3, 3]
        return np.stack([cam.fx * y[:, 0] / y[:, 2] + cam.cx, cam.fy * y[:, 1] / y[:, 2] + cam.cy], -1)
    return cam, pts, poses, [project(p) for p in poses]


def _pale_wall(shape=(240, 320), seed=3) -> np.ndarray:
    """A pale, weakly textured, smooth image (float): blurred noise of a few grey levels on a bright base."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, shape).astype(np.float32), (0, 0), 4.0)
    return 170.0 + 8.0 * tex / tex.std()


@pytest.mark.parametrize("gain", [1.03, 0.97])
def test_klt_compensates_an_exposure_change(gain):
    """Lucas-Kanade with brightness constancy slides a track on a pale, weakly textured wall when the
    exposure changes; the compensated tracker recovers the known sub-pixel shift and the gain."""
    import cv2

    from fmapping.tracking.features import KltConfig, detect_corners, klt_track, klt_track_gain, track_gain

    base = _pale_wall()
    shift = np.array([1.3, -0.6])
    moved = cv2.warpAffine(base, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), base.shape[::-1],
                           flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    img0 = np.clip(np.round(base), 0, 255).astype(np.uint8)
    img1 = np.clip(np.round(gain * moved), 0, 255).astype(np.uint8)
    cfg = KltConfig()
    pts = detect_corners(img0, cfg)
    inner = (pts[:, 0] > 40) & (pts[:, 0] < 280) & (pts[:, 1] > 40) & (pts[:, 1] < 200)
    pts = pts[inner]
    assert len(pts) > 30

    def median_err(p1, ok):
        return float(np.median(np.linalg.norm(p1[ok] - (pts[ok] + shift), axis=1)))

    plain = median_err(*klt_track(img0, img1, pts, KltConfig(gain_compensation=False)))
    p1, ok, g = klt_track_gain(img0, img1, pts, cfg)
    assert ok.mean() > 0.9
    assert abs(g / gain - 1) < 0.003
    assert median_err(p1, ok) < 0.15
    assert plain > 1.0 and plain > 5 * median_err(p1, ok)
    # the same from a prediction of the gain: one pass, the same answer
    p2, ok2, g2 = klt_track_gain(img0, img1, pts, cfg, gain=g)
    assert abs(g2 / gain - 1) < 0.003 and median_err(p2, ok2) < 0.15
    # the gain of an unmoved pair is read directly
    same = np.clip(np.round(gain * base), 0, 255).astype(np.uint8)
    measured, spread = track_gain(img0, same, pts.astype(float), pts.astype(float), 61)
    assert abs(measured / gain - 1) < 0.002 and spread < 0.002


def test_klt_without_the_backward_pass_keeps_the_forward_tracks_and_drops_fewer():
    """``fb=False`` (the front end's re-track from its keyframe) runs the same forward pass: the same
    positions, the known shift recovered, and a superset of the tracks kept; with the backward check a
    track whose patch changed (an occluded one) is dropped, without it only its 2-px agreement with the
    chained track (``MonoFrontend._klt``) can drop it."""
    import cv2

    from fmapping.tracking.features import KltConfig, detect_corners, klt_track_gain

    base = _pale_wall(seed=3)
    shift = np.array([0.7, 1.1])
    moved = cv2.warpAffine(base, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), base.shape[::-1],
                           flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    img0 = np.clip(np.round(base), 0, 255).astype(np.uint8)
    img1 = np.clip(np.round(moved), 0, 255).astype(np.uint8)
    img1[100:140, 100:160] = 255  # a patch that changed: an occluder
    cfg = KltConfig()
    pts = detect_corners(img0, cfg)
    p_fb, ok_fb, _ = klt_track_gain(img0, img1, pts, cfg)
    p_no, ok_no, _ = klt_track_gain(img0, img1, pts, cfg, fb=False)
    np.testing.assert_allclose(p_no, p_fb, atol=1e-4)
    assert np.all(ok_no[ok_fb]) and ok_no.sum() > ok_fb.sum()
    clear = ok_fb & ((np.abs(pts[:, 0] - 130) > 45) | (np.abs(pts[:, 1] - 120) > 35))
    assert clear.sum() > 30
    assert np.median(np.linalg.norm(p_no[clear] - (pts[clear] + shift), axis=1)) < 0.1


def test_klt_in_halved_images_recovers_a_known_shift_and_so_does_the_full_size_refinement():
    """``KltConfig.max_width``: a 640-px pair tracked in the images halved once (``cv2.pyrDown``), positions
    scaled back, recovers a known shift; so does :func:`fine_klt_config`'s full-size pass from those
    positions (11-px window, two levels), and it keeps most tracks; 320-px images are not halved."""
    import cv2

    from fmapping.tracking.features import (KltConfig, detect_corners, fine_klt_config, klt_halvings, klt_track_gain,
                                            klt_window)

    base = _pale_wall(shape=(480, 640), seed=5)
    shift = np.array([2.3, -1.6])
    moved = cv2.warpAffine(base, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), base.shape[::-1],
                           flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    img0, img1 = (np.clip(np.round(x), 0, 255).astype(np.uint8) for x in (base, moved))
    cfg = KltConfig(max_width=320)
    assert klt_halvings(cfg, 640) == 1 and klt_halvings(cfg, 320) == 0 and klt_halvings(KltConfig(), 640) == 0
    assert klt_halvings(KltConfig(max_width=10), 640) == 3  # 80 px: never below 64
    fine = fine_klt_config(cfg, 640)
    assert fine.levels == 2 and fine.max_width == 0 and klt_window(fine, 640) == klt_window(KltConfig(), 320) == 11
    assert fine_klt_config(cfg, 320) is cfg
    pts = detect_corners(img0, KltConfig())
    inner = (pts[:, 0] > 20) & (pts[:, 0] < 620) & (pts[:, 1] > 20) & (pts[:, 1] < 460)
    pts = pts[inner]
    coarse, ok, _ = klt_track_gain(img0, img1, pts, cfg)
    assert ok.mean() > 0.8
    err_coarse = np.linalg.norm(coarse[ok] - (pts[ok] + shift), axis=1)
    assert np.median(err_coarse) < 0.1
    refined, ok2, _ = klt_track_gain(img0, img1, pts, fine, guess=coarse, fb=False)
    both = ok & ok2
    err_fine = np.linalg.norm(refined[both] - (pts[both] + shift), axis=1)
    assert both.sum() > 0.8 * ok.sum() and np.median(err_fine) < 0.1


def test_two_view_init_recovers_relative_pose():
    from fmapping.tracking.features import two_view_init

    cam, pts, poses, uvs = _points_and_views()
    rng = np.random.default_rng(8)
    noisy = [uv + rng.normal(0, 0.2, uv.shape) for uv in uvs]
    tv = two_view_init(cam, noisy[0], noisy[1])
    assert tv is not None and tv.valid.mean() > 0.9
    assert pose_distance(tv.c2w_b, poses[1])[1] < 0.1  # rotation (deg)
    t_true = poses[1][:3, 3] / np.linalg.norm(poses[1][:3, 3])
    assert math.degrees(math.acos(np.clip(tv.c2w_b[:3, 3] @ t_true, -1, 1))) < 2.0  # unit translation direction
    # triangulated points, up to the unit-baseline scale
    s = np.linalg.norm(poses[1][:3, 3])
    err = np.linalg.norm(tv.points[tv.valid] * s - pts[tv.valid], axis=1) / pts[tv.valid, 2]
    assert np.median(err) < 0.02


def test_corner_covariance_is_round_at_corners_and_long_along_edges():
    """The structure tensor's shape: a checkerboard corner gets the identity (its error is the isotropic pixel
    error), a point on a vertical edge gets the cap along the edge (y) and 1 across it (x)."""
    from fmapping.tracking.features import KltConfig, corner_covariance

    img = np.zeros((120, 160), np.uint8)
    img[:60, :40] = 200
    img[60:, 40:80] = 200  # a checkerboard corner at (40, 60)
    img[:, 120:] = 200  # a vertical edge at x = 120
    cov = corner_covariance(img, np.array([[40.0, 60.0], [120.0, 60.0]]), KltConfig(), cap=50.0)
    w, v = np.linalg.eigh(cov)
    np.testing.assert_allclose(cov[0], np.eye(2), atol=1e-6)
    np.testing.assert_allclose(w[1], [1.0, 50.0])
    assert abs(v[1][1, 1]) > 0.999  # the long axis is vertical


def test_epipolar_whitened_px_with_the_identity_is_the_sampson_distance():
    """With identity covariances the whitened epipolar error is the Sampson distance in pixels, computed here
    point by point from F = K^-T [t]x R K^-1; a covariance n times larger divides it by sqrt(n)."""
    from fmapping.tracking.features import epipolar_whitened_px

    cam, pts, poses, uvs = _points_and_views()
    rng = np.random.default_rng(3)
    ua, ub = uvs[0] + rng.normal(0, 0.5, uvs[0].shape), uvs[1] + rng.normal(0, 0.5, uvs[1].shape)
    t_ab = inv_pose(poses[1]) @ poses[0]
    rot, t = t_ab[:3, :3], t_ab[:3, 3]
    eye = np.tile(np.eye(2), (len(ua), 1, 1))
    fast = epipolar_whitened_px(cam, rot, t, ua, ub, eye)
    k_inv = np.linalg.inv(cam.K)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    f = k_inv.T @ tx @ rot @ k_inv
    for i in range(len(ua)):
        xa, xb = np.r_[ua[i], 1.0], np.r_[ub[i], 1.0]
        fa, fb = f @ xa, f.T @ xb
        slow = (xb @ f @ xa) / math.sqrt(fa[0] ** 2 + fa[1] ** 2 + fb[0] ** 2 + fb[1] ** 2)
        assert fast[i] == pytest.approx(slow, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(epipolar_whitened_px(cam, rot, t, ua, ub, 4.0 * eye), fast / 2.0, rtol=1e-12)


def _edge_lag_views(relief: float, seed: int):
    """A wall 2.3 m ahead with ``relief`` (m) of depth spread, seen from two cameras 15 deg and 18 cm apart.
    80 % of its points lie on vertical edges, where LK lags half of the vertical motion (the aperture problem);
    0.1 px noise everywhere. Returns the camera, the pixels, their covariances (100 along the edges) and the
    true relative pose (x_b = R x_a + t)."""
    import cv2

    rng = np.random.default_rng(seed)
    cam = PinholeCamera(256.0, 256.0, 159.5, 119.5, 320, 240)
    n = 260
    u, v = rng.uniform(10, 310, n), rng.uniform(10, 230, n)
    z = 2.3 + 0.3 * (u - 160) / 160 + rng.normal(0, relief, n)
    xa = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    axis = np.array([0.2, 1.0, 0.1])
    rot = cv2.Rodrigues(axis / np.linalg.norm(axis) * math.radians(15.0))[0]
    t = np.array([-0.15, 0.05, 0.08])
    xb = xa @ rot.T + t
    ua = np.stack([u, v], 1)
    ub = np.stack([cam.fx * xb[:, 0] / xb[:, 2] + cam.cx, cam.fy * xb[:, 1] / xb[:, 2] + cam.cy], 1)
    edge = rng.random(n) < 0.8
    ub[edge, 1] = ua[edge, 1] + 0.5 * (ub[edge, 1] - ua[edge, 1])
    ub += rng.normal(0, 0.1, ub.shape)
    cov = np.tile(np.eye(2), (n, 1, 1))
    cov[edge, 1, 1] = 100.0
    return cam, ua, ub, cov, rot, t


def _two_view_errors(tv, rot, t) -> tuple:
    t_ab = np.linalg.inv(tv.c2w_b)
    drot = math.degrees(math.acos(np.clip((np.trace(rot.T @ t_ab[:3, :3]) - 1) / 2, -1, 1)))
    cos = t_ab[:3, 3] @ t / np.linalg.norm(t_ab[:3, 3]) / np.linalg.norm(t)
    return drot, math.degrees(math.acos(np.clip(cos, -1, 1)))


def test_two_view_whitened_by_the_tracks_covariances_undoes_the_edge_lag(seed=0):
    """Points on edges whose tracks lag along the edge pull the isotropic two-view pose far off (here the
    translation 140 deg or more). Weighed by their covariances (and searched from 8 translation directions)
    the pose comes back within a few degrees, and only pairs that fit it in plain pixels become points. On a
    nearly planar wall (2 cm relief) several minima cost about
    the same: the whitened fit then declines (None) rather than pick one."""
    from fmapping.tracking.features import two_view_init

    cam, ua, ub, cov, rot, t = _edge_lag_views(0.1, seed)
    iso = two_view_init(cam, ua, ub, 1.0, 0.5)
    assert iso is None or _two_view_errors(iso, rot, t)[1] > 20.0
    tv = two_view_init(cam, ua, ub, 1.0, 0.5, cov=cov, starts=8)
    # its points: the pairs that fit in plain pixels too (the corners, 20 %, and edge points with little lag)
    assert tv is not None and 40 < tv.valid.sum() < 0.5 * len(ua)
    drot, dt = _two_view_errors(tv, rot, t)
    assert drot < 1.0 and dt < 5.0, (drot, dt)
    cam, ua, ub, cov, rot, t = _edge_lag_views(0.02, seed)
    assert two_view_init(cam, ua, ub, 1.0, 0.5, cov=cov, starts=8) is None


def test_whitened_epipolar_jacobian_matches_finite_differences():
    """The exact derivatives of the whitened errors (rotation increment, two tangent steps of the unit
    translation) against central differences of the errors themselves, at poses away from the truth."""
    import torch

    from fmapping.geometry import so3_exp
    from fmapping.tracking.whitened_two_view import _step, bearings, normalised_cov, whitened_residuals

    cam, ua, ub, cov, rot, t = _edge_lag_views(0.1, 1)
    xa, xb, cov_n = bearings(cam, ua), bearings(cam, ub), normalised_cov(cam, cov)
    rng = np.random.default_rng(5)
    rots = so3_exp(torch.from_numpy(rng.normal(0, 0.2, (4, 3)))).numpy() @ rot
    ts = t + rng.normal(0, 0.1, (4, 3))
    ts /= np.linalg.norm(ts, axis=1, keepdims=True)
    _, jac = whitened_residuals(rots, ts, xa, xb, cov_n)
    h = 1e-6
    for i in range(5):
        d = np.zeros((4, 5))
        d[:, i] = h
        plus = whitened_residuals(*_step(rots, ts, d), xa, xb, cov_n, jacobian=False)[0]
        minus = whitened_residuals(*_step(rots, ts, -d), xa, xb, cov_n, jacobian=False)[0]
        np.testing.assert_allclose(jac[..., i], (plus - minus) / (2 * h), rtol=1e-5, atol=1e-5 * np.abs(jac).max())


def test_whitened_robust_fit_reaches_the_minimum_a_generic_solver_finds():
    """The batched Levenberg-Marquardt of the whitened two-view fit against scipy's least_squares (Huber loss,
    numerical Jacobian, a Rodrigues vector and a free 3-vector for the translation) from the same starts: the
    same minimum, the same Huber cost. And the starts are independent: fitted together or one by one."""
    import cv2
    from scipy.optimize import least_squares

    from fmapping.tracking.whitened_two_view import (
        bearings, epipolar_whitened_px, huber_cost, normalised_cov, robust_fit,
    )

    cam, ua, ub, cov, rot, t = _edge_lag_views(0.1, 0)
    xa, xb, cov_n = bearings(cam, ua), bearings(cam, ub), normalised_cov(cam, cov)
    r0 = cv2.Rodrigues(np.array([0.02, -0.03, 0.01]))[0] @ rot
    t_starts = np.stack([t / np.linalg.norm(t), np.array([0.3, 0.1, 0.95]), np.array([-0.9, 0.3, 0.3])])
    t_starts /= np.linalg.norm(t_starts, axis=1, keepdims=True)
    rots, ts, costs = robust_fit(np.repeat(r0[None], 3, 0), t_starts, xa, xb, cov_n, 1.0, 500, ftol=1e-14, xtol=1e-14)

    def pose(x):
        return cv2.Rodrigues(x[:3])[0] @ r0, x[3:] / np.linalg.norm(x[3:])

    for j, t0 in enumerate(t_starts):
        ref = least_squares(lambda x: epipolar_whitened_px(cam, *pose(x), ua, ub, cov), np.r_[np.zeros(3), t0],
                            loss="huber", f_scale=1.0, ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=2000)
        r_ref, t_ref = pose(ref.x)
        np.testing.assert_allclose(costs[j], ref.cost, rtol=1e-7)
        np.testing.assert_allclose(rots[j], r_ref, atol=1e-6)
        np.testing.assert_allclose(ts[j] * np.sign(ts[j] @ t_ref), t_ref, atol=1e-6)
        np.testing.assert_allclose(huber_cost(epipolar_whitened_px(cam, rots[j], ts[j], ua, ub, cov)[None], 1.0),
                                   [costs[j]], rtol=1e-12)
        alone = robust_fit(r0[None], t0[None], xa, xb, cov_n, 1.0, 500, ftol=1e-14, xtol=1e-14)
        np.testing.assert_allclose(alone[1][0], ts[j], atol=1e-9)
    # the start at the truth ends at the truth's minimum, within the edge lag's bias
    drot = math.degrees(math.acos(np.clip((np.trace(rot.T @ rots[0]) - 1) / 2, -1, 1)))
    assert drot < 1.0 and math.degrees(math.acos(abs(ts[0] @ t) / np.linalg.norm(t))) < 5.0


def test_triangulate_with_known_poses_and_rejections():
    from fmapping.tracking.features import triangulate

    cam, pts, poses, uvs = _points_and_views()
    x, ok = triangulate(cam, poses[0], poses[2], uvs[0], uvs[2], min_parallax_deg=0.5)
    assert ok.mean() > 0.95
    np.testing.assert_allclose(x[ok], pts[ok], atol=1e-6)
    # an outlier pixel is rejected by the reprojection test, no parallax between identical views
    bad = uvs[2].copy()
    bad[0] += 25.0
    _, ok2 = triangulate(cam, poses[0], poses[2], uvs[0], bad)
    assert not ok2[0]
    _, ok3 = triangulate(cam, poses[0], poses[0], uvs[0], uvs[0])
    assert not ok3.any()


def _similarity(rot_vec, shift, scale):
    """(4x4 rigid part, scale) of a world similarity x -> scale * (R x) + shift."""
    t = se3_exp_np(np.concatenate([np.zeros(3), rot_vec]))
    t[:3, 3] = shift
    return t, scale


def _moved(c2w, sim):
    t, s = sim
    out = t @ c2w
    out[:3, 3] = s * (t[:3, :3] @ c2w[:3, 3]) + t[:3, 3]
    return out


def test_triangulate_moves_with_a_similarity_of_the_world():
    """The same pixels and the same cameras in a moved, rotated and scaled world give the same
    points moved the same way, and the same valid set (the DLT runs in view a's frame)."""
    from fmapping.tracking.features import triangulate

    cam, pts, poses, uvs = _points_and_views()
    rng = np.random.default_rng(3)
    noisy = [uv + rng.normal(0, 0.7, uv.shape) for uv in uvs]  # noise: algebraic errors depend on the frame
    x, ok = triangulate(cam, poses[0], poses[1], noisy[0], noisy[1], 0.5, 1.0)
    for sim in (_similarity(np.array([0.3, -0.2, 0.1]), np.array([1.3, 0.6, 1.5]), 1.0),
                _similarity(np.array([0.0, 0.4, 0.0]), np.array([-2.0, 0.0, 7.0]), 3.0),
                _similarity(np.zeros(3), np.zeros(3), 0.01)):
        t, s = sim
        x2, ok2 = triangulate(cam, _moved(poses[0], sim), _moved(poses[1], sim), noisy[0], noisy[1], 0.5, 1.0)
        np.testing.assert_array_equal(ok2, ok)
        np.testing.assert_allclose(x2[ok], s * (x[ok] @ t[:3, :3].T) + t[:3, 3], rtol=0, atol=1e-9 * max(s, 1.0) * 10)
    assert 0.5 < ok.mean() < 1.0  # the noise makes the reprojection test reject some


def test_refine_pnp_recovers_the_pose_in_any_unit_and_origin():
    """refine_pnp from a guess 2 deg / 5 cm off: the exact pose from noise-free pixels, and the
    same pose (scaled) when the world is moved and scaled."""
    from fmapping.tracking.features import refine_pnp

    cam, pts, poses, uvs = _points_and_views()
    true_w2c = inv_pose(poses[2])
    guess = se3_exp_np(np.array([0.05, -0.03, 0.02, 0.02, 0.025, -0.01])) @ true_w2c
    out = refine_pnp(cam, pts, uvs[2], guess)
    dt, dr = pose_distance(out, true_w2c)
    assert dt < 1e-5 and dr < 1e-4, (dt, dr)  # OpenCV stops at ~3e-7 m here
    rng = np.random.default_rng(5)
    noisy = uvs[2] + rng.normal(0, 0.5, uvs[2].shape)
    ref = inv_pose(refine_pnp(cam, pts, noisy, guess))  # c2w
    for sim in (_similarity(np.zeros(3), np.array([1.3, 0.6, 1.5]), 4.0),
                _similarity(np.zeros(3), np.array([-50.0, 20.0, 3.0]), 0.05)):
        t, s = sim
        moved_guess = inv_pose(_moved(inv_pose(guess), sim))
        got = inv_pose(refine_pnp(cam, s * pts + t[:3, 3], noisy, moved_guess))
        want = _moved(ref, sim)
        np.testing.assert_allclose(got[:3, :3], want[:3, :3], atol=1e-8)
        np.testing.assert_allclose(got[:3, 3], want[:3, 3], atol=1e-8 * max(s, 1.0) * 100)


def test_reprojection_jacobians_match_finite_differences():
    from fmapping.tracking.ba import _project, reprojection_jacobians

    cam = PinholeCamera(250.0, 240.0, 160.0, 120.0, 320, 240)
    rng = np.random.default_rng(9)
    t = np.stack([se3_exp_np(rng.normal(size=6) * 0.2) for _ in range(6)])
    x = rng.normal(size=(6, 3)) + [0.0, 0.0, 4.0]
    jp, jx = reprojection_jacobians(cam, t, x)
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        num = (_project(cam, np.stack([se3_exp_np(d) @ ti for ti in t]), x)[0]
               - _project(cam, np.stack([se3_exp_np(-d) @ ti for ti in t]), x)[0]) / (2 * eps)
        np.testing.assert_allclose(jp[:, :, k], num, rtol=1e-6, atol=1e-6)
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        num = (_project(cam, t, x + d)[0] - _project(cam, t, x - d)[0]) / (2 * eps)
        np.testing.assert_allclose(jx[:, :, k], num, rtol=1e-6, atol=1e-6)


def test_reprojection_jacobians_match_the_chain_rule_products():
    """The entry-by-entry Jacobians against the obvious form, ``dpi @ [I | -hat(y)]`` and ``dpi @ R``, built as
    stacked matrix products at many random poses and points."""
    from fmapping.tracking.ba import reprojection_jacobians

    cam = PinholeCamera(300.0, 290.0, 161.0, 118.0, 320, 240)
    rng = np.random.default_rng(13)
    n = 200
    t = np.stack([se3_exp_np(rng.normal(size=6) * 0.3) for _ in range(n)])
    x = rng.normal(size=(n, 3)) * [1.0, 1.0, 0.5] + [0.0, 0.0, 3.0]
    y = np.einsum("nij,nj->ni", t[:, :3, :3], x) + t[:, :3, 3]
    dpi = np.zeros((n, 2, 3))
    dpi[:, 0, 0] = cam.fx / y[:, 2]
    dpi[:, 0, 2] = -cam.fx * y[:, 0] / y[:, 2] ** 2
    dpi[:, 1, 1] = cam.fy / y[:, 2]
    dpi[:, 1, 2] = -cam.fy * y[:, 1] / y[:, 2] ** 2
    minus_hat = np.zeros((n, 3, 3))
    minus_hat[:, 0, 1], minus_hat[:, 0, 2], minus_hat[:, 1, 2] = y[:, 2], -y[:, 1], y[:, 0]
    minus_hat[:, 1, 0], minus_hat[:, 2, 0], minus_hat[:, 2, 1] = -y[:, 2], y[:, 1], -y[:, 0]
    jp, jx = reprojection_jacobians(cam, t, x)
    np.testing.assert_allclose(jp, dpi @ np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), minus_hat], 2),
                               rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(jx, dpi @ t[:, :3, :3], rtol=1e-12, atol=1e-9)


def test_inverse_of_symmetric_3x3_blocks_matches_numpy_and_refuses_singular_ones():
    from fmapping.tracking.ba import inv_sym3

    rng = np.random.default_rng(12)
    a = rng.normal(size=(500, 3, 4))
    h = a @ np.swapaxes(a, 1, 2) + 1e-3 * np.eye(3)  # symmetric positive definite, some badly conditioned
    inv = inv_sym3(h)
    np.testing.assert_allclose(inv, np.linalg.inv(h), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(inv @ h, np.broadcast_to(np.eye(3), h.shape), atol=1e-8)
    h[7] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])  # rank 1
    with pytest.raises(np.linalg.LinAlgError):
        inv_sym3(h)


@pytest.mark.parametrize("path", ["dense", "pairs", "pairs-chunked", "repeated", "unobserved-pose", "all-fixed"])
def test_schur_step_matches_dense_normal_equations(path, monkeypatch):
    """The BA's Schur-complement step against the full (poses + points) damped normal equations
    built from a dense Jacobian and solved directly; by both ways of forming ``Hpx Hxx^-1 Hxp``
    (one dense product; pairs of observations of a point, which large problems take, also summed a
    few pairs at a time), with observations repeated, with a free pose that sees no point (its
    block is the damping alone) and with every pose fixed (the points alone)."""
    import fmapping.tracking.ba as ba
    from fmapping.tracking.ba import damped_step, normal_equations, reprojection_jacobians

    if path.startswith("pairs"):
        monkeypatch.setattr(ba, "DENSE_SCHUR_MAX", 0)
    if path == "pairs-chunked":
        monkeypatch.setattr(ba, "PAIRS_CHUNK", 7)

    cam = PinholeCamera(250.0, 240.0, 160.0, 120.0, 320, 240)
    rng = np.random.default_rng(11)
    n_pose, n_pt = 5, 40
    fixed = set(range(n_pose)) if path == "all-fixed" else {0, 2}
    t = np.stack([se3_exp_np(rng.normal(size=6) * 0.1) for _ in range(n_pose)])
    x = rng.normal(size=(n_pt, 3)) + [0.0, 0.0, 4.0]
    pairs = {(int(k), p) for p in range(n_pt) for k in rng.choice(n_pose, rng.integers(2, 5), replace=False)}
    if path == "unobserved-pose":
        pairs = {(k, p) for k, p in pairs if k != 3}
    kf, pt = np.array(sorted(pairs)).T
    if path == "repeated":
        kf, pt = np.concatenate([kf, kf[::7]]), np.concatenate([pt, pt[::7]])
    r = rng.normal(size=(len(kf), 2))
    w = rng.uniform(0.2, 1.0, len(kf))
    jp, jx = reprojection_jacobians(cam, t[kf], x[pt])
    free = [i for i in range(n_pose) if i not in fixed]
    col = np.full(n_pose, -1)
    col[free] = np.arange(len(free))
    lam = 0.05
    ne = normal_equations(jp, jx, r, w, col[kf], pt, len(free), n_pt)
    dp, dx = damped_step(ne, lam)

    n_var = 6 * len(free) + 3 * n_pt
    jac = np.zeros((2 * len(kf), n_var))
    for o in range(len(kf)):
        if col[kf[o]] >= 0:
            jac[2 * o:2 * o + 2, 6 * col[kf[o]]:6 * col[kf[o]] + 6] = jp[o]
        jac[2 * o:2 * o + 2, 6 * len(free) + 3 * pt[o]:6 * len(free) + 3 * pt[o] + 3] = jx[o]
    wr = np.repeat(w, 2)
    h = jac.T @ (wr[:, None] * jac)
    g = jac.T @ (wr * r.reshape(-1))
    ref = np.linalg.solve(h + lam * np.diag(np.diag(h) + 1e-9), -g)
    np.testing.assert_allclose(dp.reshape(-1), ref[:6 * len(free)], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(dx.reshape(-1), ref[6 * len(free):], rtol=1e-7, atol=1e-9)


def test_bundle_adjust_recovers_perturbed_geometry():
    from fmapping.tracking.ba import bundle_adjust

    cam, pts, poses, uvs = _points_and_views()
    rng = np.random.default_rng(10)
    start_poses = [poses[0], poses[1], se3_exp_np(np.array([0.01, -0.01, 0.02, 0.005, 0.004, -0.003])) @ poses[2]]
    start_pts = pts + rng.normal(0, 0.03, pts.shape)
    n = len(pts)
    obs_kf = np.repeat(np.arange(3), n)
    obs_pt = np.tile(np.arange(n), 3)
    obs_uv = np.concatenate(uvs)
    res = bundle_adjust(cam, start_poses, [0, 1], start_pts, obs_kf, obs_pt, obs_uv, max_nfev=50)
    assert res.cost_after < 1e-8 * res.cost_before
    dt, dr = pose_distance(res.poses[2], poses[2])
    assert dt < 1e-4 and dr < 1e-3
    np.testing.assert_allclose(res.points, pts, atol=1e-4)
    np.testing.assert_allclose(res.poses[0], poses[0], atol=1e-12)  # fixed


def test_bundle_adjust_stops_when_steps_stop_paying():
    """``rel_tol``: the solve ends after an accepted step that lowers the robust cost by less than that
    fraction, in fewer evaluations and within that margin of the cost of the solve run to ``max_nfev``."""
    from fmapping.tracking.ba import bundle_adjust

    cam, pts, poses, uvs = _points_and_views()
    rng = np.random.default_rng(12)
    start_poses = [poses[0], poses[1], se3_exp_np(np.array([0.02, -0.01, 0.03, 0.01, 0.006, -0.004])) @ poses[2]]
    start_pts = pts + rng.normal(0, 0.05, pts.shape)
    n = len(pts)
    obs = (np.repeat(np.arange(3), n), np.tile(np.arange(n), 3), np.concatenate(uvs) + rng.normal(0, 0.5, (3 * n, 2)))
    full = bundle_adjust(cam, start_poses, [0, 1], start_pts, *obs, max_nfev=40)
    early = bundle_adjust(cam, start_poses, [0, 1], start_pts, *obs, max_nfev=40, rel_tol=1e-3)
    assert early.nfev < full.nfev  # 4 against 8 evaluations here
    assert full.cost_after <= early.cost_after <= full.cost_after * (1 + 1e-3)
    assert early.cost_after < 0.02 * early.cost_before  # 8332 -> 118 (0.5 px noise on 900 observations)


def test_whitening_turns_covariances_into_the_identity():
    from fmapping.tracking.ba import whitening

    rng = np.random.default_rng(3)
    a = rng.normal(size=(20, 2, 2))
    cov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(2)
    wh = whitening(cov)
    np.testing.assert_allclose(wh @ cov @ np.swapaxes(wh, 1, 2), np.tile(np.eye(2), (20, 1, 1)), atol=1e-9)
    np.testing.assert_allclose(whitening(np.tile(np.diag([4.0, 100.0]), (1, 1, 1)))[0], np.diag([0.5, 0.1]))


def test_bundle_adjust_whitened_by_edge_shapes_discounts_errors_along_the_edges():
    """Tracks on horizontal stripes slide along them (KLT cannot see motion along an edge): in the third view half
    of the points are 6 px off along x, all the same way. Weighed alike, those errors pull the third pose by
    about 2 cm; whitened by their corners' shape (variance 100 along the stripe, as ``features.corner_covariance``
    caps it) the pose comes back to about a millimetre (the capped weight still pulls a little), and whitening by
    the identity changes nothing."""
    from fmapping.tracking.ba import bundle_adjust, whitening

    cam, pts, poses, uvs = _points_and_views()
    rng = np.random.default_rng(13)
    n = len(pts)
    stripe = np.zeros(n, bool)
    stripe[rng.choice(n, n // 2, replace=False)] = True
    uv2 = uvs[2].copy()
    uv2[stripe, 0] += 6.0
    obs = (np.repeat(np.arange(3), n), np.tile(np.arange(n), 3), np.concatenate([uvs[0], uvs[1], uv2]))
    cov = np.tile(np.eye(2), (3 * n, 1, 1))
    cov[2 * n:][stripe] = np.diag([100.0, 1.0])
    start = [poses[0], poses[1], se3_exp_np(np.array([0.01, -0.01, 0.02, 0.005, 0.004, -0.003])) @ poses[2]]
    plain = bundle_adjust(cam, start, [0, 1], pts, *obs, max_nfev=50)
    ident = bundle_adjust(cam, start, [0, 1], pts, *obs, max_nfev=50, whiten=np.tile(np.eye(2), (3 * n, 1, 1)))
    shaped = bundle_adjust(cam, start, [0, 1], pts, *obs, max_nfev=50, whiten=whitening(cov))
    np.testing.assert_allclose(ident.poses[2], plain.poses[2], atol=1e-12)
    err_plain = pose_distance(plain.poses[2], poses[2])[0]
    err_shaped = pose_distance(shaped.poses[2], poses[2])[0]
    print(f"\n[whitened BA] third pose off by {100 * err_plain:.2f} cm alike, {100 * err_shaped:.3f} cm whitened")
    assert err_plain > 0.01
    assert err_shaped < 0.1 * err_plain


# ----------------------------------------------------------------------------- black fill of undistorted frames
def test_pyramid_masks_erode_fill_per_level():
    cam = PinholeCamera(100.0, 100.0, 39.5, 29.5, 80, 60)
    valid = np.ones((60, 80), bool)
    valid[:, :20] = False  # black fill on the left
    pyr = build_pyramid(np.full((60, 80), 0.5, np.float32), cam, 3, valid=valid)
    assert [m.shape for m in pyr.masks] == [(60, 80), (30, 40), (15, 20)]
    np.testing.assert_array_equal(pyr.masks[0], valid)
    # a coarse pixel j covers fine pixels 2j-2..2j+2 (pyrDown's 5-tap kernel): valid iff 2j-2 >= 20
    np.testing.assert_array_equal(pyr.masks[1][0], np.arange(40) * 2 - 2 >= 20)
    np.testing.assert_array_equal(pyr.masks[2][0], np.arange(20) * 2 - 2 >= np.flatnonzero(pyr.masks[1][0])[0])
    with pytest.raises(ValueError, match="valid mask"):
        build_pyramid(np.zeros((60, 80), np.float32), cam, 2, valid=valid[:, :-1])


def test_warp_residuals_mask_drops_points_on_fill():
    rng = np.random.default_rng(3)
    cam = PinholeCamera(60.0, 60.0, 31.5, 23.5, 64, 48)
    lvl = with_gradients(rng.random((48, 64)).astype(np.float32))
    mask = rng.random((48, 64)) > 0.3
    pts = np.stack([rng.uniform(-1, 1, 400), rng.uniform(-0.8, 0.8, 400), rng.uniform(1.5, 3, 400)], -1)
    t = se3_exp_np(np.array([0.02, -0.01, 0.03, 0.01, -0.02, 0.015]))
    iref = rng.random(400).astype(np.float32)
    r_all, _, v_all = warp_residuals(lvl, cam, pts, iref, t, np.zeros(2))
    r_m, jac_m, v_m = warp_residuals(lvl, cam, pts, iref, t, np.zeros(2), mask=mask)
    expect = np.zeros(400, bool)
    for i, p in enumerate(pts @ t[:3, :3].T + t[:3, 3]):  # slow reference: project, round, look up
        u, v = cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy
        expect[i] = v_all[i] and bool(mask[int(np.floor(v + 0.5)), int(np.floor(u + 0.5))])
    np.testing.assert_array_equal(v_m, expect)
    assert 0 < v_m.sum() < v_all.sum()
    np.testing.assert_allclose(r_m, r_all[np.flatnonzero(v_m[v_all])])
    assert jac_m.shape == (v_m.sum(), 8)


def test_tracker_ignores_black_fill_of_current_frame(scene_pair):
    cam, c2w0, c2w1, rgb0, d0, rgb1, _ = scene_pair
    filled = rgb1.copy()
    filled[:, :40] = 0  # like the border of an undistorted image
    ref = make_reference(rgb0, d0, cam, c2w0, levels=3, num_points=2000)
    from fmapping.tracking.direct_align import image_valid_mask

    masked = build_pyramid(to_gray(filled), cam, 3, valid=image_valid_mask(filled))
    plain = build_pyramid(to_gray(filled), cam, 3)
    res_m = align(ref, masked, np.eye(4), AlignConfig())
    res_p = align(ref, plain, np.eye(4), AlignConfig())
    dt, dr = pose_distance(c2w0 @ inv_pose(res_m.t_cr), c2w1)
    assert dt < 0.003 and dr < 0.15, (dt, dr)
    assert res_m.inlier_ratio > 0.9 and res_m.visible_ratio < 0.85
    assert res_p.inlier_ratio < res_m.inlier_ratio - 0.1  # without the mask the fill counts as (outlier) residuals
    tr = DirectTracker(cam, TrackerConfig(num_points=2000))  # the tracker builds the mask itself
    tr.set_reference(rgb0, d0, c2w0, 0)
    tr.observe(c2w0)
    out = tr.track(filled)
    assert not out.lost and out.inlier_ratio > 0.9
    assert pose_distance(out.c2w, c2w1)[0] < 0.003


def test_two_view_known_baseline_recovers_rotation_despite_outliers():
    from fmapping.tracking.features import sampson_px, two_view_known_baseline

    cam = PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480)
    rng = np.random.default_rng(0)
    n = 150
    pts = np.stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(1.5, 4, n)], -1)
    c2w_b = se3_exp_np(np.array([0.02, 0.005, -0.01, 0.02, -0.3, 0.05]))  # 17 deg pan, 2 cm baseline

    def proj(c2w):
        w2c = inv_pose(c2w)
        x = pts @ w2c[:3, :3].T + w2c[:3, 3]
        return np.stack([cam.fx * x[:, 0] / x[:, 2] + cam.cx, cam.fy * x[:, 1] / x[:, 2] + cam.cy], -1)

    ua, ub = proj(np.eye(4)), proj(c2w_b)
    # exact pairs satisfy the epipolar constraint of the true pose
    t_ab = inv_pose(c2w_b)
    assert np.abs(sampson_px(cam, t_ab[:3, :3], c2w_b[:3, 3], ua, ub)).max() < 1e-6
    ua = ua + rng.normal(0, 0.3, (n, 2))
    ub = ub + rng.normal(0, 0.3, (n, 2))
    ub[:15] += rng.normal(0, 20, (15, 2))  # gross outliers
    est, inl = two_view_known_baseline(cam, ua, ub, c2w_b[:3, 3])
    dt, dr = pose_distance(est, c2w_b)
    assert dt < 1e-9 and dr < 0.05, (dt, dr)  # the centre is the given one; rotation from the tracks
    assert inl[15:].mean() > 0.95 and inl[:15].sum() <= 3
    assert two_view_known_baseline(cam, ua[:5], ub[:5], c2w_b[:3, 3]) is None
