"""Loop closure: the pose graph, the loop verification, the monocular front end closing a loop."""
from __future__ import annotations

from typing import Optional

import numpy as np
import pytest
import torch

from fmapping.geometry import inv_pose, pose_distance, se3_exp_np


def _circle_poses(n: int, radius: float = 1.0) -> list:
    """Cameras on a circle in the xy plane, each turned by its angle about z."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        p = np.eye(4)
        p[:3, :3] = se3_exp_np(np.r_[0, 0, 0, 0.1, 0.05, a])[:3, :3]
        p[:3, 3] = radius * np.cos(a), radius * np.sin(a), 0.1 * np.sin(3 * a)
        out.append(p)
    return out


def test_pose_graph_recovers_poses_that_agree_with_every_edge():
    """Exact chain and loop edges, start poses drifted ever more along the chain (up to 6 cm /
    4 deg): the optimum is the true poses (the first one fixed)."""
    from fmapping.tracking.posegraph import optimize_pose_graph

    gt = _circle_poses(12)
    edges = [(k, k + 1, inv_pose(gt[k]) @ gt[k + 1]) for k in range(11)] + [(0, 11, inv_pose(gt[0]) @ gt[11])]
    rng = np.random.default_rng(0)
    drift = np.eye(4)
    start = [gt[0]]
    for k in range(1, 12):
        drift = drift @ se3_exp_np(np.r_[rng.normal(0, 0.005, 3), rng.normal(0, 0.006, 3)])
        start.append(drift @ gt[k])
    assert max(pose_distance(s, g)[0] for s, g in zip(start, gt)) > 0.02
    out, stats = optimize_pose_graph(start, edges, [0], unit=1.0)
    torch.testing.assert_close(torch.tensor(np.stack(out)), torch.tensor(np.stack(gt)), atol=1e-6, rtol=0)
    assert stats["cost_after"] < 1e-12 < stats["cost_before"]


def test_pose_graph_matches_a_dense_per_edge_reference_on_a_drifted_loop():
    """Chain edges with drift in rotation and translation, an exact loop edge: the result equals a
    slow, obvious reference (each residual from 4x4 products, ``E = inv(T_ij) inv(X_i) X_j``,
    dense finite-difference Jacobian), and the loop's contradiction is spread over the chain."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from fmapping.tracking.posegraph import optimize_pose_graph

    n, unit = 10, 0.7
    gt = _circle_poses(n)
    rng = np.random.default_rng(1)
    edges = [(k, k + 1, inv_pose(gt[k]) @ gt[k + 1] @ se3_exp_np(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 3)]))
             for k in range(n - 1)]
    edges.append((0, n - 1, inv_pose(gt[0]) @ gt[n - 1]))
    start = [gt[0]]
    for i, j, t in edges[:-1]:
        start.append(start[-1] @ t)  # the chain as tracked: all of the drift at the end
    out, stats = optimize_pose_graph(start, edges, [0], unit=unit)

    def poses_of(x):
        ps = [start[0]]
        for k in range(1, n):
            d = x[6 * (k - 1): 6 * k]
            p = np.eye(4)
            p[:3, :3] = Rotation.from_rotvec(d[:3]).as_matrix() @ start[k][:3, :3]
            p[:3, 3] = start[k][:3, 3] + unit * d[3:]
            ps.append(p)
        return ps

    def residuals(x):
        ps = poses_of(x)
        r = []
        for i, j, t in edges:
            e = np.linalg.inv(t) @ np.linalg.inv(ps[i]) @ ps[j]
            r += list(Rotation.from_matrix(e[:3, :3]).as_rotvec()) + list(e[:3, 3] / unit)
        return np.array(r)

    ref = poses_of(least_squares(residuals, np.zeros(6 * (n - 1)), method="trf", xtol=1e-12, ftol=1e-12).x)
    torch.testing.assert_close(torch.tensor(np.stack(out)), torch.tensor(np.stack(ref)), atol=1e-6, rtol=0)
    # the end of the chain moved most, towards where the loop edge puts it
    before = pose_distance(start[-1], gt[-1])[0]
    assert pose_distance(out[-1], gt[-1])[0] < 0.5 * before
    assert stats["cost_after"] < 0.2 * stats["cost_before"]


@pytest.mark.parametrize("off", [0.0, 1e-3, 0.1, 1.2])
def test_pose_graph_edge_jacobians_match_finite_differences(off):
    """The pose graph's analytic edge Jacobians against central differences of its residuals, each pose
    perturbed as the solver moves it (``exp(phi) R``, ``t + unit d``), for edges whose residual rotation
    is nil (the small-angle series), small, and 1.2 rad (the closed form of ``Jr^-1``)."""
    from scipy.spatial.transform import Rotation

    from fmapping.tracking.posegraph import edge_jacobians, edge_residuals

    rng = np.random.default_rng(3)
    n, unit = 6, 0.8
    rot = Rotation.from_rotvec(rng.normal(0, 0.8, (n, 3))).as_matrix()
    trans = rng.normal(0, 1.0, (n, 3))
    ei, ej = np.array([0, 1, 2, 4, 0]), np.array([1, 3, 5, 2, 4])
    rel = []
    for i, j in zip(ei, ej):
        xi, xj = np.eye(4), np.eye(4)
        xi[:3, :3], xi[:3, 3], xj[:3, :3], xj[:3, 3] = rot[i], trans[i], rot[j], trans[j]
        wobble = se3_exp_np(np.r_[rng.normal(0, 0.05, 3), off * rng.normal(size=3) / np.sqrt(3)]) if off else np.eye(4)
        rel.append(inv_pose(xi) @ xj @ wobble)
    rel = np.stack(rel)
    res = edge_residuals(rot, trans, ei, ej, rel, unit)
    ji, jj = edge_jacobians(rot, trans, ei, ej, rel, unit, res)
    eps = 1e-6
    for e, (i, j) in enumerate(zip(ei, ej)):
        for which, pose, jac in (("i", i, ji), ("j", j, jj)):
            num = np.zeros((6, 6))
            for k in range(6):
                out = []
                for sgn in (1.0, -1.0):
                    r2, t2 = rot.copy(), trans.copy()
                    step = np.zeros(3)
                    step[k % 3] = sgn * eps
                    if k < 3:
                        r2[pose] = Rotation.from_rotvec(step).as_matrix() @ rot[pose]
                    else:
                        t2[pose] = trans[pose] + unit * step
                    out.append(edge_residuals(r2, t2, ei[e:e + 1], ej[e:e + 1], rel[e:e + 1], unit)[0])
                num[:, k] = (out[0] - out[1]) / (2 * eps)
            np.testing.assert_allclose(jac[e], num, atol=1e-7, err_msg=f"edge {e}, pose {which}")


def test_rotation_homography_maps_points_at_infinity():
    from fmapping.camera import PinholeCamera
    from fmapping.tracking.loop import rotation_homography

    cam = PinholeCamera(fx=250.0, fy=240.0, cx=160.0, cy=120.0, width=320, height=240)
    a = se3_exp_np(np.r_[0.3, -0.1, 0.2, 0.05, 0.2, -0.1])
    b = se3_exp_np(np.r_[-0.4, 0.2, 0.1, -0.1, -0.15, 0.3])
    rng = np.random.default_rng(2)
    dirs = rng.normal(0, 0.3, (50, 3)) + a[:3, 2] + b[:3, 2]  # in front of both
    far = a[:3, 3] + 1e7 * dirs

    def pix(c2w, x):
        y = (x - c2w[:3, 3]) @ c2w[:3, :3]
        return np.stack([cam.fx * y[:, 0] / y[:, 2] + cam.cx, cam.fy * y[:, 1] / y[:, 2] + cam.cy], -1)

    ua, ub = pix(a, far), pix(b, far)
    q = np.c_[ua, np.ones(len(ua))] @ rotation_homography(cam, a, b).T
    torch.testing.assert_close(torch.tensor(q[:, :2] / q[:, 2:]), torch.tensor(ub), atol=1e-4, rtol=0)


def _room_points(ds, frame: int):
    """Corners of ``frame`` and their world points from the dataset's depth."""
    from fmapping.tracking.features import KltConfig, detect_corners, to_u8

    f = ds[frame]
    gray = to_u8(f.rgb)
    uv = detect_corners(gray, KltConfig()).astype(np.float64)
    cam = ds.camera
    z = f.depth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)].astype(np.float64)
    ok = z > 0
    uv, z = uv[ok], z[ok]
    y = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], -1)
    c2w = ds.gt_poses[frame]
    return gray, uv, y @ c2w[:3, :3].T + c2w[:3, 3]


def test_locate_in_keyframe_recovers_the_pose_from_an_old_keyframe(room320):
    """Frame 12 of the synthetic room located on frame 0's corners (their GT-depth world points),
    starting from a guess 2.9 cm / 1.5 deg off. Measured: 3.6 mm / 0.12 deg from the GT pose, 108 of 119
    points inliers (nearest-pixel depth at the corners; frame 8: 1.1 mm / 0.04 deg, frame 16: 7 mm /
    0.30 deg, frame 20: refused); a frame of noise is refused."""
    from fmapping.datasets import open_dataset
    from fmapping.tracking.features import KltConfig, to_u8
    from fmapping.tracking.loop import LoopConfig, locate_in_keyframe

    ds = open_dataset(room320)
    old_gray, uv, world = _room_points(ds, 0)
    gt = ds.gt_poses[12]
    guess = gt @ se3_exp_np(np.r_[0.02, -0.015, 0.015, 0.015, -0.02, 0.01])
    assert pose_distance(guess, gt)[0] > 0.025
    m = locate_in_keyframe(ds.camera, old_gray, uv, world, ds.gt_poses[0], to_u8(ds[12].rgb), guess,
                           KltConfig(), LoopConfig())
    assert m is not None and m.inliers >= 0.8 * m.points
    dt, dr = pose_distance(m.c2w, gt)
    assert dt < 0.008 and dr < 0.25, (dt, dr)
    noise = np.random.default_rng(3).integers(0, 256, ds[12].rgb.shape, dtype=np.uint8)
    assert locate_in_keyframe(ds.camera, old_gray, uv, world, ds.gt_poses[0], to_u8(noise), guess,
                              KltConfig(), LoopConfig()) is None


def test_cross_check_confirms_a_true_loop_and_measures_a_wrong_rotation(room320):
    """Frame 12 located on frame 0's corners, then the other way round (frame 12's corners located in
    frame 0, :func:`cross_check`): the two relative rotations agree for the true match, and a match
    whose rotation is 4 deg off is found about 4 deg away from the other way's measurement. Measured:
    0.06 deg for the true match; 0.99 / 1.91 / 3.99 deg for matches 1 / 2 / 4 deg off."""
    from fmapping.datasets import open_dataset
    from fmapping.tracking.features import KltConfig
    from fmapping.tracking.loop import LoopConfig, LoopMatch, cross_check, locate_in_keyframe

    ds = open_dataset(room320)
    old_gray, old_uv, old_world = _room_points(ds, 0)
    gray, uv, world = _room_points(ds, 12)
    g0, g12 = ds.gt_poses[0], ds.gt_poses[12]
    m = locate_in_keyframe(ds.camera, old_gray, old_uv, old_world, g0, gray, g12, KltConfig(), LoopConfig())
    assert m is not None
    true = cross_check(ds.camera, old_gray, g0, m, gray, uv, world, g12, KltConfig(), LoopConfig())
    assert true is not None and true[0] < 0.3 and true[1] < 0.01, true
    off = LoopMatch(m.c2w @ se3_exp_np(np.r_[0.0, 0.0, 0.0, 0.0, np.radians(4.0), 0.0]), m.points, m.inliers,
                    m.index, m.uv)
    wrong = cross_check(ds.camera, old_gray, g0, off, gray, uv, world, g12, KltConfig(), LoopConfig())
    assert wrong is not None and 3.5 < wrong[0] < 4.5, wrong


@pytest.fixture(scope="module")
def loop160(tmp_path_factory):
    """A synthetic room whose 200 frames (160x120) go once round the room's loop and back."""
    from fmapping.synthetic import generate_scene

    root = tmp_path_factory.mktemp("loop160")
    generate_scene(root, seed=4, frames=200, size=(160, 120), supersample=1, max_cloud_points=2000)
    return root


def _run_mono(ds, loop_enabled: bool, ba_thread: bool = False, mono: Optional[dict] = None,
              frames: Optional[list] = None, **loop):
    from fmapping.tracking.loop import LoopConfig
    from fmapping.tracking.mono import MonoConfig, MonoFrontend

    g = ds.gt_poses
    fe = MonoFrontend(ds.camera, None, MonoConfig(loop=LoopConfig(enabled=loop_enabled, **loop), ba_thread=ba_thread,
                                                  **(mono or {})))
    i = 0
    while not fe.initialized:
        fe.bootstrap(i, ds[i].rgb, g[0], lambda k: float(np.linalg.norm(g[k][:3, 3] - g[0][:3, 3])))
        i += 1
    handed_on = {}
    for n, k in enumerate(frames or range(len(ds))):
        if n < i:
            continue  # (the bootstrap's)
        r = fe.track(n, ds[k].rgb)
        if r.need_keyframe:
            handed_on[n] = set(fe.refined_poses())
    return fe, handed_on


@pytest.mark.slow
def test_mono_closes_the_loop_back_at_the_first_keyframe(loop160):
    """The camera comes back to its start: the loop to the first keyframe closes and the drift
    at the end of the sequence shrinks. Measured (GT-anchored, no alignment, last 10 frames):
    8.35 cm without loop closure, 0.94 cm with (loops at frames 190 and 196, 52 and 85 inliers; 1.14 cm
    with the pose graph alone, without the loop's bundle adjustment)."""
    from fmapping.datasets import open_dataset

    ds = open_dataset(loop160)
    g = ds.gt_poses
    errs = {}
    for enabled in (False, True):
        fe, handed_on = _run_mono(ds, enabled)
        p = fe.poses()
        errs[enabled] = np.mean([np.linalg.norm(p[k][:3, 3] - g[k][:3, 3]) for k in range(190, 200)])
    assert fe.loops and fe.loops[0]["keyframe"] == 0 and fe.loops[0]["frame"] >= 150
    # at the loop's keyframe every frame's pose is handed on, not just the BA window's
    loop_kf = fe.loops[0]["frame"]
    assert handed_on[loop_kf] == set(range(loop_kf + 1))
    # the loop's inliers became observations of the first keyframe's landmarks (what holds the BA closed);
    # measured: all 52 kept, BA RMS 0.31 px
    first_kf = {}
    for kf, lid, _, _ in fe.store.obs:
        first_kf.setdefault(lid, kf)
    assert (sum(1 for kf, lid, _, _ in fe.store.obs if kf == loop_kf and first_kf[lid] == 0)
            >= 0.5 * fe.loops[0]["inliers"])
    assert fe.loops[0]["ba_rms_px"] < 1.0
    assert errs[True] < 0.03 and errs[True] < 0.4 * errs[False], errs
    # a loop was closed: the final bundle adjustment ("after_loops", the default) covers every keyframe
    assert fe.final_ba() and fe.final_ba_stats["keyframes"] == len(fe.store.kf_pose)
    p = fe.poses()
    err_final = np.mean([np.linalg.norm(p[k][:3, 3] - g[k][:3, 3]) for k in range(190, 200)])
    print(f"final BA: RMS {fe.final_ba_stats['rms_before_px']:.3f} -> {fe.final_ba_stats['rms_after_px']:.3f} px, "
          f"drift at the end {100 * errs[True]:.2f} -> {100 * err_final:.2f} cm")
    assert fe.final_ba_stats["rms_after_px"] <= fe.final_ba_stats["rms_before_px"] and err_final < 0.03


@pytest.mark.slow
def test_the_loops_bundle_adjustment_runs_in_the_worker_with_ba_thread(loop160, monkeypatch):
    """With ``ba_thread`` (the tracker service) the loop's bundle adjustment, the longest one (tens of
    keyframes, a second or more), is solved in the worker thread like a keyframe's instead of on the
    frame path: the pose graph corrects the keyframes at once, the BA's result is merged later and scaled
    back to the graph's size, and every frame's pose is handed on again then. The end of the sequence
    is as close to the GT as with the BA on the frame path (measured: 0.94 cm on the frame path)."""
    import threading

    from fmapping.datasets import open_dataset
    from fmapping.tracking.mono import ba_thread, loop_closing

    def not_here(*a, **k):
        raise AssertionError("the loop's bundle adjustment was solved on the frame path")

    solved_in = []
    real = ba_thread.solve_ba_problem

    def solve(camera, prob):
        solved_in.append((len(prob.window), threading.current_thread().name))
        return real(camera, prob)

    monkeypatch.setattr(loop_closing, "solve_ba_problem", not_here)
    monkeypatch.setattr(ba_thread, "solve_ba_problem", solve)
    # every solution is merged at the next frame (the worker's timing would pick the frame: the run deterministic)
    real_take = ba_thread.BackgroundBA.take
    monkeypatch.setattr(ba_thread.BackgroundBA, "take", lambda bg, wait: real_take(bg, True))
    ds = open_dataset(loop160)
    fe, handed_on = _run_mono(ds, True, ba_thread=True)
    fe.flush_ba()
    assert fe.loops and fe.loops[0]["keyframe"] == 0 and all(rec.get("ba_in_worker") for rec in fe.loops)
    assert (fe.loops[0]["keyframes"], "fmapping-ba") in solved_in
    assert fe.loops[0]["ba_rms_px"] < 1.0 and 0.8 < fe.loops[0]["ba_scale"] < 1.25  # filled in at the merge
    loop_kf = fe.loops[0]["frame"]
    assert handed_on[loop_kf] == set(range(loop_kf + 1))  # the pose graph's moves, at once
    p = fe.poses()
    err = np.mean([np.linalg.norm(p[k][:3, 3] - ds.gt_poses[k][:3, 3]) for k in range(190, 200)])
    assert err < 0.03, err


@pytest.mark.slow
def test_the_loop_search_runs_in_its_worker_and_is_merged_frames_later_with_loop_thread(loop160, monkeypatch):
    """With ``loop_thread`` (the tracker service) the loop search of a keyframe (verification, cross-check,
    pose graph: 20-60 ms at 320x240) runs in its own worker while the next frames are tracked; its correction
    is merged at a later frame (held here until the third frame that asks), the loop's bundle adjustment goes
    to the BA worker, and every frame's pose moves then. Held until the 13th, the search leaves the next
    keyframes unsearched; the last of them is searched from when the stream ends. The end of the sequence is
    as close to the GT as with the search on the frame path (measured: 1.00 cm at the loop's keyframe, 1.01 cm
    merged 3 frames after it, 1.01 cm closed at the end)."""
    import threading

    from fmapping.datasets import open_dataset
    from fmapping.tracking.loop import LoopConfig
    from fmapping.tracking.mono import MonoConfig, MonoFrontend, ba_thread, loop_closing, worker

    searched_in, searched_from = [], []
    real_search = loop_closing.search_loop

    def search(camera, q, *a):
        searched_in.append(threading.current_thread().name)
        searched_from.append(q.index)
        return real_search(camera, q, *a)

    monkeypatch.setattr(loop_closing, "search_loop", search)
    real_take = ba_thread.BackgroundBA.take
    monkeypatch.setattr(ba_thread.BackgroundBA, "take", lambda bg, wait: real_take(bg, True))
    looked, now = {}, {"frame": -1, "hold": 3}  # the loop worker's job -> the frames that asked whether it was done
    real_ready = worker.BackgroundJob.ready

    def ready(job):
        if job.name != "fmapping-loop" or job._job is None:
            return real_ready(job)
        job._job[1].join()  # done, but handed over only from the n-th frame that asks on: the run deterministic
        looked.setdefault(job.submitted, set()).add(now["frame"])
        return len(looked[job.submitted]) >= now["hold"]

    monkeypatch.setattr(worker.BackgroundJob, "ready", ready)
    ds = open_dataset(loop160)
    g = ds.gt_poses
    err, merged_at, passed_over, searched = {}, {}, {}, {}
    for run, thread, hold in (("frame_path", False, 0), ("worker", True, 3), ("late", True, 13)):
        searched_in.clear(), searched_from.clear(), looked.clear()
        now["hold"] = hold
        fe = MonoFrontend(ds.camera, None, MonoConfig(loop=LoopConfig(), ba_thread=True, loop_thread=thread))
        i = 0
        while not fe.initialized:
            fe.bootstrap(i, ds[i].rgb, g[0], lambda k: float(np.linalg.norm(g[k][:3, 3] - g[0][:3, 3])))
            i += 1
        merged_at[run] = []
        for n in range(i, len(ds)):
            had, now["frame"] = len(fe.loops), n
            fe.track(n, ds[n].rgb)
            if len(fe.loops) > had:
                merged_at[run].append((fe.loops[-1]["frame"], n, set(fe.refined_poses()) == set(fe.poses())))
        passed_over[run] = fe._loop_passed_over
        fe.flush_ba()
        searched[run] = list(searched_from)
        p = fe.poses()
        err[run] = np.mean([np.linalg.norm(p[k][:3, 3] - g[k][:3, 3]) for k in range(190, 200)])
        assert searched_in and set(searched_in) == {"fmapping-loop" if thread else "MainThread"}, searched_in
        assert fe.loops and fe.loops[0]["keyframe"] == 0 and all(rec.get("ba_in_worker") for rec in fe.loops)
    # on the frame path the correction lands at the loop's keyframe, from the worker at least 2 frames later;
    # either way every frame's pose is handed on then
    assert merged_at["frame_path"] and all(kf == n and every for kf, n, every in merged_at["frame_path"]), merged_at
    assert merged_at["worker"] and all(n >= kf + 2 and every for kf, n, every in merged_at["worker"]), merged_at
    # held long, the last keyframe was passed over; the end of the stream searched from it and closed the loop
    last = passed_over["late"]
    assert last is not None and searched["late"][-1] == last and last not in searched["late"][:-1], \
        (passed_over, searched)
    assert err["worker"] < 0.03 and err["worker"] < 1.25 * err["frame_path"] + 0.005, err
    assert err["late"] < 0.03 and err["late"] < 1.25 * err["frame_path"] + 0.005, err


@pytest.mark.slow
def test_keyframes_go_on_without_waiting_for_a_loops_bundle_adjustment(loop160, monkeypatch):
    """A loop's bundle adjustment (tens of keyframes) keeps the worker busy for 10-20 frames of a live
    camera. Held in flight here for up to 15 frames (solved, but not handed over before) while the camera
    goes on (round the loop, then 60 frames back along it): with ``loop_ba_defer_frames`` the frames asking
    for a keyframe meanwhile stay ordinary frames, only while they still see half of the reference, and the
    frame path never waits for the worker; with 0 the next keyframe waits for it (the test can fail); with
    ``loop_thread`` and 0 it is added without waiting and moves with the loop's BA once that is merged. The
    poses from frame 150 on are as close to the GT every way (measured: 3.16 cm mean deferring one keyframe,
    3.48 cm waiting, 3.61 cm going on; most of it on the way back, which the loop does not cover)."""
    from fmapping.datasets import open_dataset
    from fmapping.tracking.mono import MonoConfig, MonoFrontend, ba_thread, worker

    real_take, real_defer = ba_thread.BackgroundBA.take, MonoFrontend._defer_keyframe
    held, asked = {}, []  # asked: (deferred?, visible ratio) of the frames asking for a keyframe meanwhile

    def take(bg, wait):
        loop_ba = bg._job is not None and len(bg._job[0].window) > MonoConfig().window  # longer than a keyframe's
        if loop_ba and not wait and held["frames"] < 15:
            bg._job[1].join()
            held["frames"] += 1
            return None
        held["waited"] += loop_ba and wait
        return real_take(bg, True)  # anything else at once: the run deterministic

    def defer_keyframe(fe, res):
        out = real_defer(fe, res)
        if fe._loop_ba is not None:
            asked.append((out, round(res.visible_ratio, 3)))
        return out

    def loop_search_ready(job):  # the loop search (loop_thread) is taken at the first frame that asks
        if job._job is not None:
            job._job[1].join()
        return job._job is not None

    monkeypatch.setattr(ba_thread.BackgroundBA, "take", take)
    monkeypatch.setattr(MonoFrontend, "_defer_keyframe", defer_keyframe)
    monkeypatch.setattr(worker.BackgroundJob, "ready", loop_search_ready)
    ds = open_dataset(loop160)
    frames = list(range(len(ds))) + list(range(len(ds) - 2, 139, -1))
    err, out, went_on = {}, {}, {}
    runs = {"defer": {"loop_ba_defer_frames": 15}, "wait": {"loop_ba_defer_frames": 0},
            "loop_thread": {"loop_ba_defer_frames": 0, "loop_thread": True}}
    for name, mono in runs.items():
        held.update(frames=0, waited=0)
        asked.clear()
        fe, _ = _run_mono(ds, True, ba_thread=True, mono=mono, frames=frames)
        out[name] = (fe.keyframes_deferred, dict(held), list(asked), len(fe.loops))
        went_on[name] = sum(rec.get("keyframes_meanwhile", 0) for rec in fe.loops)
        fe.flush_ba()
        p = fe.poses()
        err[name] = np.mean([np.linalg.norm(p[n][:3, 3] - ds.gt_poses[frames[n]][:3, 3])
                             for n in range(150, len(frames))])
    (n_def, held_d, asked_d, loops_d), (n_wait, held_w, _, loops_w) = out["defer"], out["wait"]
    assert loops_d and loops_w and held_d["frames"] >= 1 and held_w["frames"] >= 1, out
    assert n_def >= 1 and held_d["waited"] == 0, out  # the frame path never waited for the loop's BA
    assert all(v >= 0.5 for d, v in asked_d if d), asked_d
    assert n_wait == 0 and held_w["waited"] >= 1, out
    assert err["defer"] < 1.25 * err["wait"] + 0.005, err
    # loop_thread: nothing deferred, nothing waited for: the keyframes added meanwhile moved with the loop's BA
    n_thr, held_t, _, loops_t = out["loop_thread"]
    assert loops_t and n_thr == 0 and held_t["frames"] >= 1 and held_t["waited"] == 0 and went_on["loop_thread"] >= 1
    assert err["loop_thread"] < 1.25 * err["wait"] + 0.005, (err, out, went_on)


@pytest.mark.slow
def test_mono_loop_longer_than_the_ba_cap_gets_the_pose_graph_alone(loop160):
    """``loop_ba_max_keyframes`` below the loop's length: the same loop closes without the BA
    (no loop observations added). Measured: end error 1.14 cm (0.94 cm with the BA)."""
    from fmapping.datasets import open_dataset

    ds = open_dataset(loop160)
    fe, _ = _run_mono(ds, True, loop_ba_max_keyframes=5)
    assert fe.loops and not any(rec["ba"] for rec in fe.loops) and fe.loops[0]["keyframes"] > 5
    first_kf = {}
    for kf, lid, _, _ in fe.store.obs:
        first_kf.setdefault(lid, kf)
    assert not any(kf == fe.loops[0]["frame"] and first_kf[lid] == 0 for kf, lid, _, _ in fe.store.obs)
    p = fe.poses()
    err = np.mean([np.linalg.norm(p[k][:3, 3] - ds.gt_poses[k][:3, 3]) for k in range(190, 200)])
    assert err < 0.03, err


def test_scaling_keyframes_moves_their_frames_landmarks_and_references_alike(loop160):
    """The loop BA's scale-back (``_scale_keyframes``) is a similarity of that part of the world:
    every frame stored relative to a scaled keyframe, every landmark first seen by one, and the
    tracker's reference of one end where scaling their old world positions puts them."""
    from fmapping.datasets import open_dataset
    from fmapping.geometry import scale_about
    from fmapping.tracking.loop import LoopConfig
    from fmapping.tracking.mono import MonoConfig, MonoFrontend

    ds = open_dataset(loop160)
    g = ds.gt_poses
    fe = MonoFrontend(ds.camera, None, MonoConfig(loop=LoopConfig(enabled=False)))
    i = 0
    while not fe.initialized:
        fe.bootstrap(i, ds[i].rgb, g[0], lambda k: float(np.linalg.norm(g[k][:3, 3] - g[0][:3, 3])))
        i += 1
    for k in range(i, 60):
        fe.track(k, ds[k].rgb)
    kfs = sorted(fe.keyframe_poses())
    moved = kfs[len(kfs) // 2:]
    about, s = moved[0], 1.25
    c0 = fe.keyframe_poses()[about][:3, 3].copy()
    poses, lms = fe.poses(), [p.copy() for p in fe.store.lm]
    ref = fe.tracker.reference
    assert ref.frame_index in moved
    ref_world = ref.points @ ref.c2w[:3, :3].T + ref.c2w[:3, 3]
    first = fe.store.first_keyframes()
    fe._scale_keyframes(moved, about, s)
    after = fe.poses()
    stored_at = {f: kf for f, (kf, _) in fe.store.rel.items()}
    n = 0
    for f, p in poses.items():
        want = scale_about(p, c0, s) if stored_at[f] in moved else p
        np.testing.assert_allclose(after[f], want, atol=1e-9)
        n += stored_at[f] in moved and stored_at[f] != f
    assert n > 10  # non-keyframes among them (the part the old code left unscaled)
    for lid, p in enumerate(lms):
        want = c0 + s * (p - c0) if first.get(lid) in moved else p
        np.testing.assert_allclose(fe.store.lm[lid], want, atol=1e-9)
    ref = fe.tracker.reference
    np.testing.assert_allclose(ref.points @ ref.c2w[:3, :3].T + ref.c2w[:3, 3], c0 + s * (ref_world - c0), atol=1e-9)


def test_the_bench_checks_a_loops_relative_pose_against_orb_matches_between_its_images(room320):
    """bench/real.py's ``images_verdict`` (beside the GT check of a loop, whose GT can be the one that
    drifted): two frames of a synthetic room 8 frames apart, their exact relative pose against the same pose
    turned by 2 deg or with its translation 20 deg off. The exact one fits the ORB matches (found without a
    pose) to well under a pixel, the wrong ones by pixels (measured: 0.32 against 3.37 and 1.18 px), and the
    verdict names the exact one from either side."""
    import sys
    from pathlib import Path

    from fmapping.datasets import open_dataset
    from fmapping.tracking.features import to_u8

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from real import images_verdict, orb_matches, sampson_px

    ds = open_dataset(room320)
    a, b = 10, 18
    g = ds.gt_poses
    true = inv_pose(g[a]) @ g[b]
    turned = true @ se3_exp_np(np.r_[0.0, 0.0, 0.0, 0.0, np.radians(2.0), 0.0])
    t = true[:3, 3]
    off = true.copy()  # the translation direction 20 deg off about an axis across it
    axis = np.cross(t, [0.0, 0.0, 1.0])
    off[:3, 3] = se3_exp_np(np.r_[0.0, 0.0, 0.0, np.radians(20.0) * axis / np.linalg.norm(axis)])[:3, :3] @ t
    ga, gb = to_u8(ds[a].rgb), to_u8(ds[b].rgb)
    p0, p1 = orb_matches(ga, gb)
    assert len(p0) >= 50
    exact = sampson_px(ds.camera, true, p0, p1)
    assert exact < 0.5
    for wrong in (turned, off):
        assert 2 * exact < 1.0 < sampson_px(ds.camera, wrong, p0, p1), wrong
        v = images_verdict(ga, gb, ds.camera, wrong, true)
        assert v["images_side_with"] == "gt" and v["sampson_px_gt"] == pytest.approx(exact, abs=1e-3), v
        assert images_verdict(ga, gb, ds.camera, true, wrong)["images_side_with"] == "loop"
    assert orb_matches(ga, np.zeros_like(gb)) is None  # a blank image: no matches, no verdict


def test_a_loop_search_begun_before_a_rescale_is_dropped():
    """``loop_thread``: a search works on a copy of the map as it was; a rescale (or a re-initialisation) while it
    runs voids it, so its result is dropped at the merge. Without the rescale the same result is merged."""
    from fmapping.camera import PinholeCamera
    from fmapping.tracking.mono import MonoConfig, MonoFrontend
    from fmapping.tracking.mono.loop_closing import LoopQuery, LoopSearch

    cam = PinholeCamera(100.0, 100.0, 80.0, 60.0, 160, 120)
    for rescale in (False, True):
        fe = MonoFrontend(cam, None, MonoConfig(ba_thread=True, loop_thread=True))
        q = LoopQuery(5, None, 1.0, {}, [], None, fe._loop_epoch)
        fe._loop_worker.start(q, lambda: LoopSearch([{"frame": 5, "keyframe": 0, "why": "a test"}]))
        if rescale:
            fe._scale_part(np.zeros(3), 2.0)
        fe._merge_loop(wait=True)
        assert not fe._loop_worker.busy
        assert fe.loops_refused == ([] if rescale else [{"frame": 5, "keyframe": 0, "why": "a test"}])
