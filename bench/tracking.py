"""Tracking benchmark: the direct (fast) path, the monocular front end, render-and-compare and kiss-icp
side by side on the same frames.

Data: a synthetic room (``fmapping synth`` seed 0, generated into ``--work`` when
missing) at 320x240, and the TUM fr1_rpy clip in ``../shared/data`` when present.

Methods (each on the same frames, one process, ``torch`` on ``--threads``):

* ``direct_gt_depth``  - :class:`DirectTracker` against keyframes whose depth is the
  dataset's depth image (the tracker itself, isolated from depth quality);
* ``direct_map_depth`` - the same against keyframes whose depth is rendered from a map
  (built first by the mapper from GT poses + depth on the benchmark frames);
* ``render_compare``   - Adam on se(3) through the same map (the paper-style path), from
  the previous estimate with a constant-velocity prediction;
* ``mono``             - the RGB-only front end (two-view bootstrap, sparse depth, BA),
  scale anchored with the GT baseline length of its bootstrap and again at frame 14;
* ``mono_no_late_anchor`` - the same with the bootstrap's scale kept;
* ``mono_ba_thread``   - ``mono`` with the keyframe bundle adjustment in a worker thread
  (``MonoConfig.ba_thread``, as the tracker service at a camera's rate); ``wall`` times each
  ``track`` call as its caller waits (merges of the worker's solutions included);
* ``mono_anchor_position`` - the same with the bootstrap's baseline *vector* from the GT
  camera centres (rotation fitted to the tracks, no essential matrix);
* ``kiss_icp``         - kiss-icp on back-projected depth.

``pose_consistency`` (frames with depth only): how well a set of poses explains the images.
KLT tracks between consecutive frames, back-projected with the dataset's depth and moved with
the poses, land a median of so many pixels from where KLT found them; for the ground truth
and for each method's poses. A ground truth that does worse than an estimate limits what ATE
and rotation error can tell apart (:mod:`fmapping.tracking.consistency`).

``gt_camera_offset`` (frames with depth only): the constant rotation of the GT's camera frame
(a hand-eye or principal-point error) that makes the GT explain tracks 10 and 15 frames long
best, its spread over two halves of the pairs, and the rotation errors ``GT @ X`` itself has
against the GT (what a tracker agreeing with the images as well as ``GT @ X`` would score).

``images_optimum`` (frames with depth only, the depth placing the starting points): the
trajectory that explains multi-frame KLT tracks best, a bundle adjustment of every frame on
the reprojection error alone, started from the GT and from the mono estimate. Where both
starts reach the same optimum, that optimum is what the images determine (with these
intrinsics): its errors against the GT bound what an RGB-only tracker can reach except by
chance. ``anchored``: the same optimum scaled about frame 0 so that its baseline to frame 14
is the GT's, as the mono front end's late anchor does (its SE3 ATE is what the optimum scores
under the monocular scale protocol).
The same from the GT with the tracks unrolled for a rolling shutter of several readout times:
the readout whose optimum costs least is the one the images prefer (no GT in that choice).

``mono_rolling_shutter`` (with ``images_optimum``): the mono front end with that readout
(``MonoConfig.rolling_shutter``), once and over the perturbed copies (``..._spread``).

``mono_spread``: the mono front end again on five copies of the frames with one grey level
added to or taken from 5 % of the pixels; min / median / max of its ATE and rotation errors.

``ba_allocator``: the mono front end on the synthetic frames under glibc's default allocator,
then with :func:`fmapping.runtime.retain_freed_memory` (on for the rest of the run, as in
the CLI and the tracker service).

Per method: milliseconds per frame (min, median, mean: a keyframe's bundle adjustment counts
in its frame, so the mean is the rate a live stream must sustain), frames per second at the median,
ATE RMSE (SE3, Sim3, unaligned) and mean rotation errors (after the position alignment,
and the well-posed ``rot_first`` / ``rot_fit`` of :func:`fmapping.metrics.ate`), plus
``camera_offset``: a constant camera-frame rotation between estimate and GT fitted as a
diagnostic. TUM uses the TUM fr1 lens distortion (``--tum-camera auto``). Timings on a shared CPU are
noisy (report min and median). Writes ``bench/results/tracking.json``.

    PYTHONPATH=. .venv/bin/python bench/tracking.py --frames 60
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
TUM = ROOT.parent / "shared" / "data" / "tum_fr1_rpy"


ROT_KEYS = ("rot_first_mean_deg", "rot_fit_mean_deg", "rot_fit_rmse_deg")  # well-posed, when metrics.ate has them


def _ate(est, gt) -> dict:
    from fmapping.metrics import ate

    out = {}
    for a in ("se3", "sim3", "none"):
        r = ate(np.stack(est), np.stack(gt), a)
        out[a] = {"rmse_m": r["rmse_m"], "rot_err_mean_deg": r["rot_err_mean_deg"], "scale": r["scale"]}
        out[a].update({k: r[k] for k in ROT_KEYS if k in r})
    out["camera_offset"] = camera_offset_fit(est, gt)
    return out


def camera_offset_fit(est, gt, prior: float = 0.05) -> dict:
    """Diagnostic: a constant rotation ``X`` between the estimate's camera frame and the
    ground truth's (a hand-eye / principal-point error), fitted so that the relative
    rotations from the first pose agree, ``R_est0^T R_est_i ~ X (R_gt0^T R_gt_i) X^T``.

    Returns X as a rotation vector (degrees, camera axes x right, y down, z forward)
    and the mean angle of the relative-rotation residual before and after the fit. The
    component along the dominant rotation axis is unobservable (weak ``prior`` towards 0).
    A large drop after fitting a few-degree X means the error is a frame offset, not drift.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    e = np.stack(est)[:, :3, :3]
    g = np.stack(gt)[:, :3, :3]
    qe = np.swapaxes(e[:1], -1, -2) @ e
    qg = np.swapaxes(g[:1], -1, -2) @ g

    def res(x):
        xm = Rotation.from_rotvec(x).as_matrix()
        r = Rotation.from_matrix(np.swapaxes(xm @ qg @ xm.T, -1, -2) @ qe).as_rotvec()
        return np.concatenate([r.reshape(-1), prior * x])

    n = len(e)
    before = np.degrees(np.linalg.norm(res(np.zeros(3))[: 3 * n].reshape(-1, 3), axis=1))
    sol = least_squares(res, np.zeros(3))
    after = np.degrees(np.linalg.norm(sol.fun[: 3 * n].reshape(-1, 3), axis=1))
    return {"offset_rotvec_deg": [float(v) for v in np.degrees(sol.x)],
            "rel_rot_err_mean_deg": float(before.mean()), "after_offset_mean_deg": float(after.mean())}


def tum_camera_arg(root: Path) -> "str | None":
    """The TUM table's calibration (with lens distortion) when ``calib.txt`` holds the same
    ``fx fy cx cy`` without distortion (the shared fr1 clip does): tracking on distorted
    images with a pinhole model bends every ray by up to ~3% at the image edge."""
    from fmapping.datasets.tum import TUM_INTRINSICS, read_calib, sequence_rig

    rig = sequence_rig(root.resolve().name)
    calib = root / "calib.txt"
    if rig is None or not calib.is_file():
        return None
    vals, _, _ = read_calib(calib)
    k, dist = TUM_INTRINSICS[rig]
    if len(vals) == 4 and dist is not None and np.allclose(vals, k, atol=0.05):
        return ",".join(str(v) for v in (*k, *dist))
    return None


def _timing(ms) -> dict:
    ms = np.asarray(ms, np.float64)
    return {"ms_min": float(ms.min()), "ms_median": float(np.median(ms)), "fps_median": float(1000 / np.median(ms)),
            "ms_p95": float(np.percentile(ms, 95)), "fps_p95": float(1000 / np.percentile(ms, 95)),
            "ms_mean": float(ms.mean()), "fps_mean": float(1000 / ms.mean()), "frames": int(len(ms))}


def pose_consistency(frames, camera, poses: dict) -> dict:
    """Per consecutive frame pair: median pixel distance between KLT tracks and the frame-k pixels
    back-projected with frame k's depth and moved with the poses. ``poses``: name -> (N, 4, 4) array
    over all frames. Returns name -> {median_px, mean_px} over the pairs."""
    from fmapping.tracking.consistency import depth_tracks, reprojection_px

    pairs = depth_tracks([f.rgb for f in frames], [f.depth for f in frames], camera, steps=(1,))
    return {name: reprojection_px(pairs, c2w, camera) for name, c2w in poses.items()}


def gt_camera_offset(frames, camera, steps=(10, 15)) -> dict:
    """The constant camera-frame rotation ``X`` that makes the GT explain the images best
    (:func:`fmapping.tracking.consistency.fit_camera_rotation`, tracks ``steps`` frames apart),
    fitted on all pairs and on the pairs of alternate start frames (its spread), about all
    three axes and about x and z only. ``floor``: the rotation errors of ``GT @ X`` against the
    GT, i.e. what a tracker that agrees with the images as well as ``GT @ X`` does would score."""
    from scipy.spatial.transform import Rotation

    from fmapping.metrics import ate
    from fmapping.tracking.consistency import depth_tracks, fit_camera_rotation, reprojection_px

    gt = np.stack([f.c2w for f in frames])
    pairs = depth_tracks([f.rgb for f in frames], [f.depth for f in frames], camera, steps=steps, start_every=2)
    out = {"steps": list(steps), "pairs": len(pairs), "tracks": int(sum(len(p.uv_b) for p in pairs)),
           "gt_px": reprojection_px(pairs, gt, camera)["median_px"]}
    for axes in ("xyz", "xz"):
        x = fit_camera_rotation(pairs, gt, camera, axes)
        halves = [fit_camera_rotation([p for p in pairs if (p.a // 2) % 2 == h], gt, camera, axes) for h in (0, 1)]
        corrected = gt.copy()
        corrected[:, :3, :3] = gt[:, :3, :3] @ x
        a = ate(corrected, gt, "none")
        out[axes] = {"rotvec_deg": [float(v) for v in np.degrees(Rotation.from_matrix(x).as_rotvec())],
                     "halves_rotvec_deg": [[float(v) for v in np.degrees(Rotation.from_matrix(h).as_rotvec())]
                                           for h in halves],
                     "px_after": reprojection_px(pairs, gt, camera, x)["median_px"],
                     "floor_rot_first_mean_deg": a["rot_first_mean_deg"],
                     "floor_rot_fit_mean_deg": a["rot_fit_mean_deg"]}
    return out


def anchored_ate(c2w: np.ndarray, gt: list, frame: int = 14) -> dict:
    """The ATE of a trajectory scaled about its first camera centre so that the baseline to ``frame``
    is the GT's (the front end's late anchor, ``MonoConfig.late_anchor_frames``): the SE3 figure
    that trajectory would score under the monocular scale protocol."""
    from fmapping.geometry import scale_about

    g = np.stack(gt)
    s = np.linalg.norm(g[frame, :3, 3] - g[0, :3, 3]) / max(np.linalg.norm(c2w[frame, :3, 3] - c2w[0, :3, 3]), 1e-12)
    return {"frame": frame, "factor": float(s), **_ate([scale_about(p, c2w[0, :3, 3], s) for p in c2w], gt)}


def images_optimum(frames, camera, starts: dict, readouts=(0.3, 0.6, 0.85, 1.0)) -> dict:
    """The trajectory that explains the images best (:func:`fmapping.tracking.consistency.best_explaining_poses`:
    multi-frame KLT tracks, bundle adjustment of every frame on the reprojection error alone), started
    from each of ``starts`` (name -> (N, 4, 4)): its ATE and rotation errors against the GT, and how
    far the optima from the different starts lie from the first one's (Sim3 RMSE, rotation). Optima
    that coincide are what the images determine; a target that they miss is out of reach of any
    RGB-only tracker with this camera model, except by chance.

    ``rolling_shutter``: the same from the first start with the tracks unrolled for a rolling
    shutter (:mod:`fmapping.tracking.rolling_shutter`) of each readout in ``readouts`` (fractions
    of the frame interval; rotation steps from the global-shutter optimum). The readout with the
    lowest cost is the one the images prefer (``best_readout``; no GT involved)."""
    from fmapping.metrics import ate
    from fmapping.tracking.consistency import best_explaining_poses, frame_tracks
    from fmapping.tracking.rolling_shutter import rotation_steps, unroll_tracks

    t0 = time.perf_counter()
    tracks = frame_tracks([f.rgb for f in frames])
    depths = [f.depth for f in frames]
    out: dict = {"tracks_seconds": time.perf_counter() - t0, "starts": {}, "rolling_shutter": {}}
    gt = [f.c2w for f in frames]
    first = None
    for name, start in starts.items():
        t0 = time.perf_counter()
        poses, info = best_explaining_poses(camera, tracks, start, depths)
        r = {**info, "seconds": time.perf_counter() - t0, "start": _ate(list(start), gt),
             "optimum": _ate(list(poses), gt), "anchored": anchored_ate(poses, gt)}
        if first is None:
            first = poses
        else:
            apart = ate(poses, first, "sim3")
            r["apart_from_first"] = {"sim3_rmse_m": apart["rmse_m"], "rot_first_mean_deg": apart["rot_first_mean_deg"],
                                     "rot_fit_mean_deg": apart["rot_fit_mean_deg"]}
        out["starts"][name] = r
    name, start = next(iter(starts.items()))
    out["tracks"] = out["starts"][name]["tracks"]
    costs = {0.0: out["starts"][name]["cost"]}
    steps = rotation_steps(first)
    for readout in readouts:
        t0 = time.perf_counter()
        poses, info = best_explaining_poses(camera, unroll_tracks(camera, tracks, steps, readout), start, depths)
        out["rolling_shutter"][str(readout)] = {**info, "seconds": time.perf_counter() - t0,
                                                "optimum": _ate(list(poses), gt), "anchored": anchored_ate(poses, gt)}
        costs[readout] = info["cost"]
    out["best_readout"] = float(min(costs, key=costs.get))
    return out


def run_direct(frames, camera, depth_of, poses_out: "dict | None" = None) -> dict:
    """``depth_of(i, c2w)`` -> depth image or uv callable for a new keyframe at frame i."""
    from fmapping.tracking.direct_tracker import DirectTracker

    tr = DirectTracker(camera)
    gt0 = frames[0].c2w
    tr.set_reference(frames[0].rgb, depth_of(0, gt0), gt0, 0)
    tr.observe(gt0)
    est, ms, lost, kfs = [gt0], [], 0, 1
    kf_ms = []
    for i in range(1, len(frames)):
        r = tr.track(frames[i].rgb)
        ms.append(r.ms)
        est.append(r.c2w)
        lost += r.lost
        if r.need_keyframe:
            t0 = time.perf_counter()
            try:
                tr.set_reference(frames[i].rgb, depth_of(i, r.c2w), r.c2w, i)
                kfs += 1
            except ValueError:
                pass
            kf_ms.append((time.perf_counter() - t0) * 1000)
    out = {**_timing(ms), "lost": int(lost), "keyframes": kfs,
           "keyframe_ms_median": float(np.median(kf_ms)) if kf_ms else None,
           "ate": _ate(est, [f.c2w for f in frames])}
    if poses_out is not None:
        poses_out["direct_gt_depth"] = np.stack(est)
    return out


def run_mono(frames, camera, anchor_position: bool = False, cfg=None, poses_out: "dict | None" = None) -> dict:
    """RGB-only front end; the bootstrap's scale comes from the GT baseline length |t_k - t_0|
    or, with ``anchor_position``, from the GT camera centres of frames 0 and k (baseline vector),
    and is taken again from the GT baseline to frame 14 (``MonoConfig.late_anchor_frames``)."""
    from fmapping.tracking.mono import MonoFrontend

    fe = MonoFrontend(camera, cfg=cfg)
    g0 = frames[0].c2w
    anchor = lambda k: float(np.linalg.norm(frames[k].c2w[:3, 3] - g0[:3, 3]))  # noqa: E731
    position = (lambda k: frames[k].c2w[:3, 3]) if anchor_position else None  # noqa: E731
    ms, est, lost = [], {}, 0
    i = 0
    t0 = time.perf_counter()
    while i < len(frames) and not fe.initialized and not fe.failed:
        out = fe.bootstrap(i, frames[i].rgb, g0, anchor, anchor_position=position)
        i += 1
    boot_ms = (time.perf_counter() - t0) * 1000
    if not fe.initialized:
        return {"error": f"bootstrap failed after {i} frames"}
    est.update(out)
    kf_ms, wall = [], []
    for j in range(i, len(frames)):
        tw = time.perf_counter()
        r = fe.track(j, frames[j].rgb)
        wall.append((time.perf_counter() - tw) * 1000)  # what the caller waits (a merge of a BA from the worker too)
        ms.append(r.ms)
        est[j] = r.c2w
        lost += r.lost
        if fe.is_keyframe(j):
            kf_ms.append(r.ms)
    fe.final_ba()  # a bundle adjustment still in the worker (ba_thread), then the final one (MonoConfig.final_ba)
    est.update(fe.poses())
    ids = sorted(est)
    if poses_out is not None and ids == list(range(len(frames))):
        poses_out["mono"] = np.stack([est[k] for k in ids])
    return {**_timing(ms), "lost": int(lost), "bootstrap": fe.init_info, "bootstrap_ms_total": boot_ms,
            "ba_ms_median": float(np.median([b["ms"] for b in fe.ba_stats])) if fe.ba_stats else None,
            # keyframe frames (their BA / triangulation on the frame path) and the others
            "keyframe_frames": len(kf_ms), "keyframe_ms_median": float(np.median(kf_ms)) if kf_ms else None,
            "non_keyframe_ms_p95": float(np.percentile([m for m in ms if m not in kf_ms] or [0.0], 95)),
            "wall": _timing(wall), "ba_thread_waits": fe._bg.waited if fe._bg is not None else None,
            "reinit": list(fe.reinits),
            "ate": _ate([est[k] for k in ids], [frames[k].c2w for k in ids])}


def perturbed(frames, seed: int, fraction: float = 0.05):
    """The frames with one grey level added to or taken from ``fraction`` of the pixels (all
    channels alike): far below sensor noise, so a method whose result moves with it is chaotic."""
    import dataclasses

    rng = np.random.default_rng(seed)
    out = []
    for f in frames:
        img = np.asarray(f.rgb)
        d = (rng.random(img.shape[:2]) < fraction) * rng.choice([-1, 1], img.shape[:2])
        if np.issubdtype(img.dtype, np.integer):
            rgb = np.clip(img.astype(np.int16) + d[..., None], 0, 255).astype(img.dtype)
        else:
            rgb = np.clip(img + d[..., None] / 255.0, 0.0, 1.0).astype(img.dtype)
        out.append(dataclasses.replace(f, rgb=rgb))
    return out


def mono_spread(frames, camera, seeds=(1, 2, 3, 4, 5), cfg=None) -> dict:
    """The mono front end on the frames as they are and on :func:`perturbed` copies: min,
    median and max of its ATE and rotation errors (one run's figure is one draw of these).
    ``cfg``: a callable giving a fresh :class:`MonoConfig` per run (default: the defaults)."""
    make = cfg or (lambda: None)
    runs = [run_mono(frames, camera, cfg=make())] + [run_mono(perturbed(frames, s), camera, cfg=make()) for s in seeds]
    keys = {"se3_cm": ("se3", "rmse_m", 100), "sim3_cm": ("sim3", "rmse_m", 100),
            "rot_first_deg": ("none", "rot_first_mean_deg", 1), "rot_fit_deg": ("none", "rot_fit_mean_deg", 1)}
    out: dict = {"runs": len(runs), "perturbation": "+-1 grey level on 5 % of the pixels", "seeds": list(seeds)}
    for name, (align, key, mult) in keys.items():
        v = np.array([r["ate"][align][key] * mult for r in runs if "ate" in r])
        out[name] = {"min": float(v.min()), "median": float(np.median(v)), "max": float(v.max()),
                     "values": [float(x) for x in v]}
    return out


def run_kiss(frames, camera) -> dict:
    from fmapping.tracking.sources import KissIcpOdometry, default_kiss_config_for

    cfg = default_kiss_config_for(camera, frames[0].depth)
    odo = KissIcpOdometry(camera, cfg, frames[0].c2w)
    est, ms = [], []
    for f in frames:
        t0 = time.perf_counter()
        est.append(odo.register(f.depth))
        ms.append((time.perf_counter() - t0) * 1000)
    return {**_timing(ms[1:]), "voxel_size": cfg.voxel_size, "ate": _ate(est, [f.c2w for f in frames])}


def build_map(frames, camera, iters: int):
    """A map of the benchmark frames from GT poses + depth (what the trackers are compared against)."""
    from fmapping.mapping import Mapper, MapperConfig

    cfg = MapperConfig(use_depth=True, optimize_init_poses=False, init_frames=min(15, len(frames)),
                       final_global_iters=iters, device="cpu")
    m = Mapper(cfg, camera)
    t0 = time.perf_counter()
    for f in frames:
        m.add_frame(f.rgb, f.c2w, f.timestamp, f.depth)
    m.finish()
    return m, time.perf_counter() - t0


def run_render_compare(frames, camera, view, iterations: int) -> dict:
    from fmapping.geometry import inv_pose, orthonormalize
    from fmapping.tracking.render_compare import RenderCompareConfig, RenderCompareTracker

    rc = RenderCompareTracker(view, RenderCompareConfig(iterations=iterations))
    est, ms = [frames[0].c2w], []
    prev = frames[0].c2w
    for f in frames[1:]:
        pred = est[-1] @ (inv_pose(prev) @ est[-1]) if len(est) > 1 else est[-1]
        prev = est[-1]
        r = rc.track(f.rgb, orthonormalize(pred))
        ms.append(r.ms)
        est.append(r.c2w)
    return {**_timing(ms), "iterations": iterations, "ate": _ate(est, [f.c2w for f in frames])}


def allocator_comparison(frames, camera) -> dict:
    """The mono front end under glibc's default allocator, then with
    :func:`fmapping.runtime.retain_freed_memory` (as the CLI and the tracker service run it; it
    stays on for the rest of the bench). Default first: the setting cannot be undone exactly."""
    from fmapping.runtime import retain_freed_memory

    out = {}
    for name in ("glibc_default", "retain_freed_memory"):
        if name == "retain_freed_memory":
            out["applied"] = retain_freed_memory()
        print(f"[synthetic] mono, allocator {name} ...", flush=True)
        r = run_mono(frames, camera)
        out[name] = {k: r[k] for k in ("ms_min", "ms_median", "ba_ms_median")}
        out[name]["ms_mean"] = r["ms_mean"]
    return out


def bench_dataset(name: str, frames, camera, args) -> dict:
    from fmapping.tracking.mapview import MapView
    from fmapping.tracking.mono import MonoConfig

    res = {"frames": len(frames), "size": [camera.width, camera.height]}
    print(f"[{name}] direct, GT depth ...", flush=True)
    est: dict = {}
    res["direct_gt_depth"] = run_direct(frames, camera, lambda i, c2w: frames[i].depth, est)
    print(f"[{name}] mono (RGB only) ...", flush=True)
    mono: dict = {}
    res["mono"] = run_mono(frames, camera, poses_out=mono)
    print(f"[{name}] mono, scale from the bootstrap alone ...", flush=True)
    res["mono_no_late_anchor"] = run_mono(frames, camera, cfg=MonoConfig(late_anchor_frames=0))
    print(f"[{name}] mono, keyframe bundle adjustment in a worker thread ...", flush=True)
    res["mono_ba_thread"] = run_mono(frames, camera, cfg=MonoConfig(ba_thread=True))
    print(f"[{name}] mono on perturbed copies of the frames ...", flush=True)
    res["mono_spread"] = mono_spread(frames, camera)
    print(f"[{name}] mono, bootstrap anchored with the GT baseline vector ...", flush=True)
    res["mono_anchor_position"] = run_mono(frames, camera, anchor_position=True)
    if frames[0].depth is not None:
        print(f"[{name}] kiss-icp ...", flush=True)
        res["kiss_icp"] = run_kiss(frames, camera)
        print(f"[{name}] pose consistency with the images ...", flush=True)
        res["pose_consistency"] = pose_consistency(frames, camera,
                                                   {"groundtruth": np.stack([f.c2w for f in frames]), **est})
        print(f"[{name}] camera-frame rotation of the GT against the images ...", flush=True)
        res["gt_camera_offset"] = gt_camera_offset(frames, camera)
        print(f"[{name}] the trajectory the images determine (global BA from GT and from mono) ...", flush=True)
        res["images_optimum"] = opt = images_optimum(frames, camera, {"groundtruth": np.stack([f.c2w for f in frames]),
                                                                      **mono})
        readout = opt["best_readout"]
        print(f"[{name}] mono with a rolling shutter of readout {readout} (the images' choice) ...", flush=True)
        cfg = lambda: MonoConfig(rolling_shutter=readout)  # noqa: E731
        res["mono_rolling_shutter"] = {**run_mono(frames, camera, cfg=cfg()), "readout": readout}
        if readout:  # with 0 it is the mono spread again
            res["mono_rolling_shutter_spread"] = mono_spread(frames, camera, cfg=cfg)
    if not args.no_map:
        print(f"[{name}] building a map from GT poses + depth ...", flush=True)
        m, secs = build_map(frames[: args.map_frames], camera, args.map_final_iters)
        view = MapView.from_mapper(m)
        res["map"] = {"seconds": secs, "frames": min(args.map_frames, len(frames))}
        sub = frames[: args.map_frames]
        print(f"[{name}] direct, map depth ...", flush=True)
        try:
            res["direct_map_depth"] = run_direct(sub, camera, lambda i, c2w: view.depth_fn(c2w))
        except ValueError as e:
            res["direct_map_depth"] = {"error": str(e)}
        print(f"[{name}] render-and-compare ...", flush=True)
        res["render_compare"] = run_render_compare(sub[: args.rc_frames], camera, view, args.rc_iters)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--work", default=str(ROOT / "out" / "bench_tracking"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-map", action="store_true", help="skip the map-based methods (mapping is slow)")
    ap.add_argument("--map-frames", type=int, default=30)
    ap.add_argument("--map-final-iters", type=int, default=100)
    ap.add_argument("--rc-frames", type=int, default=10)
    ap.add_argument("--rc-iters", type=int, default=30)
    ap.add_argument("--tum-camera", default="auto",
                    help="--camera for TUM; 'auto': calib.txt, plus the TUM table's lens distortion when calib.txt "
                         "has the table's fx fy cx cy without it; 'calib': calib.txt as is")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "tracking.json"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from fmapping.datasets import open_dataset
    from fmapping.synthetic import generate_scene

    results = {"host": platform.node(), "threads": args.threads, "note": "shared 2-core CPU: timings are noisy"}
    syn = Path(args.work) / "syn0"
    if not (syn / "scene.json").is_file():
        print(f"generating synthetic scene in {syn} ...", flush=True)
        generate_scene(syn, seed=0, frames=max(args.frames, 60), size=(320, 240))
    ds = open_dataset(syn, max_frames=args.frames)
    frames = [ds[i] for i in range(len(ds))]
    results["ba_allocator"] = allocator_comparison(frames, ds.camera)
    results["synthetic_320x240"] = bench_dataset("synthetic", frames, ds.camera, args)
    if TUM.is_dir():
        cam_arg = {"auto": tum_camera_arg(TUM), "calib": None}.get(args.tum_camera, args.tum_camera)
        ds = open_dataset(TUM, camera=cam_arg, max_frames=args.frames)
        frames = [ds[i] for i in range(len(ds))]
        results["tum_fr1_rpy_640x480"] = bench_dataset("tum", frames, ds.camera, args)
        results["tum_fr1_rpy_640x480"]["camera"] = {"arg": cam_arg, "undistorted": bool(ds.meta.get("undistorted")),
                                                    "groundtruth": ds.meta.get("groundtruth_association")}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2, default=str))
    for dname, d in results.items():
        if not isinstance(d, dict):
            continue
        for meth, r in d.items():
            if isinstance(r, dict) and "fps_median" in r:
                a = r.get("ate", {})
                print(f"{dname:22s} {meth:18s} ms min {r['ms_min']:7.1f} median {r['ms_median']:7.1f} "
                      f"({r['fps_median']:5.1f} fps)  ATE se3 {a.get('se3', {}).get('rmse_m', float('nan')):.4f} m "
                      f"sim3 {a.get('sim3', {}).get('rmse_m', float('nan')):.4f} m "
                      f"rot(none) {a.get('none', {}).get('rot_err_mean_deg', float('nan')):.2f} deg "
                      f"rot(first) {a.get('none', {}).get('rot_first_mean_deg', float('nan')):.2f} "
                      f"rot(fit) {a.get('none', {}).get('rot_fit_mean_deg', float('nan')):.2f} deg")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
