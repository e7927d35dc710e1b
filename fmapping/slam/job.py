"""``run_slam(job)``: a :class:`~fmapping.slam.run.SlamRun` over ``job.data``, then ``traj.txt``, the map
export and ``stats.json`` (per-frame tracking, windows, ATE, summary). See :mod:`fmapping.slam`.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.cancel import StopFn
from fmapping.config import to_dict
from fmapping.job import Job
from fmapping.map_outputs import MESH_RESOLUTION, write_map_outputs
from fmapping.pipeline import open_job_dataset, recon_stats, write_stats
from fmapping.run_warnings import tracking_warnings
from fmapping.slam.config import build_slam_config
from fmapping.slam.run import SlamRun

log = logging.getLogger("fmapping.slam")


def _with_gt(est: np.ndarray, gt: list) -> tuple[np.ndarray, np.ndarray]:
    """The estimated and GT poses of the frames that have both (``gt`` entries may be None)."""
    ok = [j for j, g in enumerate(gt) if g is not None]
    if not ok:
        return np.zeros((0, 4, 4)), np.zeros((0, 4, 4))
    return np.stack([est[j] for j in ok]), np.stack([gt[j] for j in ok])


def _ate_block(est: np.ndarray, gt: list) -> Optional[dict]:
    from fmapping.metrics import ate

    e, g = _with_gt(est, gt)
    if len(e) < 3:
        return None
    res = {}
    for a in ("se3", "sim3", "none"):
        try:
            r = ate(e, g, a)
            res[a] = {k: r[k] for k in ("rmse_m", "mean_m", "max_m", "rot_err_mean_deg", "rot_fit_mean_deg",
                                        "rot_fit_rmse_deg", "scale")}
        except ValueError as err:
            res[a] = {"error": str(err)}
    return res


def _sim3_to_gt(est: np.ndarray, gt: list) -> Optional[tuple]:
    """(s, R, t) aligning the estimated camera positions to the GT ones (as the Sim3 ATE does)."""
    from fmapping.metrics import align_trajectory

    e, g = _with_gt(est, gt)
    if len(e) < 3:
        return None
    try:
        return align_trajectory(e, g, "sim3")[1]
    except (ValueError, np.linalg.LinAlgError):
        return None


def _export(run: SlamRun, out: Path) -> dict:
    """map.ply and mesh.ply from the mapper's views (keyframes and the local window), in the output
    frame (scaled about frame 0 by the anchor)."""
    m = run.mapper
    cfg = run.cfg.mapper
    poses = m.frame_poses()
    kf_poses = {k: poses[k] for k in m.view_ids() if k in poses}
    return write_map_outputs(m, kf_poses, run.camera, out, near=cfg.near, far=cfg.far,
                             mesh_samples=(48, 16), mesh_resolution=MESH_RESOLUTION,
                             center=run.c2w0[:3, 3], scale=run.scale)


def run_slam(job: Job, should_stop: StopFn = None) -> dict:
    """Run the SLAM loop (see the module docstring); returns the stats dict with a ``summary``.
    ``should_stop()`` True ends it early: the frames so far are written, without the closing
    optimisation (``summary["stopped_at"]``: the first frame not processed)."""
    import torch

    from fmapping.trajectory import write_tum_trajectory

    t_start = time.perf_counter()
    ds = open_job_dataset(job)
    cfg = build_slam_config(job)
    poses_mode = job.poses or "photometric"
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    run = SlamRun(ds, cfg, poses_mode, out, progress=not job.quiet, should_stop=should_stop)
    run.run()
    t_loop = time.perf_counter() - t_start
    idx, est = run.output_poses()
    write_tum_trajectory(out / "traj.txt", np.asarray(ds.timestamps, np.float64)[idx], est)
    mapped = run.mapper is not None and (run.stopped_at is None or run.mapper.initialized)
    if run.stopped_at is not None:
        log.warning("stopped before frame %d of %d: wrote %s%s", run.stopped_at, len(ds), out / "traj.txt",
                    "; exporting the map so far" if cfg.export and mapped else "")
    export = _export(run, out) if cfg.export and mapped else None

    ms = np.array([run.track_ms[i] for i in sorted(run.track_ms)], np.float64)
    track_ms_after_init = np.array([run.track_info[i]["ms"] for i in sorted(run.track_info)], np.float64)
    wins = [w for w in run.window_stats if w.get("kind") == "window"]
    mstats = run.mapper.stats() if run.mapper is not None else {}
    stats = {
        "config": to_dict(cfg),
        "dataset": ds.describe(),
        "poses": poses_mode,
        "scale_anchor": run.anchor,
        "output_scale": run.scale,
        "init": getattr(run, "init_report", None),
        "frames": len(ds),
        "frames_mapped": len(run.fid_of),
        "tracking_ms": {str(i): run.track_ms[i] for i in sorted(run.track_ms)},
        "tracking": {str(i): run.track_info[i] for i in sorted(run.track_info)},
        "tracking_loss_events": run.loss_events,
        "loop_closures": run.frontend.loops if run.frontend is not None else [],
        "loops_refused": run.frontend.loops_refused if run.frontend is not None else [],
        "mapper_pose_updates": run.pose_updates,
        "windows": run.window_stats,
        "mapper": mstats,
        "export": export,
        "notes": run.notes,
        "map_depth_checks": run.frontend.dense_checks if run.frontend is not None else [],
        "seconds": {"loop": t_loop, "total": time.perf_counter() - t_start},
        "torch_threads": torch.get_num_threads(),
    }
    gt = [ds.gt_poses[int(i)] for i in idx]  # the frames with a pose
    ate_res = _ate_block(est, gt) if run.has_gt else None
    stats["ate"] = ate_res
    if export is not None and export["points"] > 0:
        stats.update(recon_stats(ds, out, sim3=_sim3_to_gt(est, gt)))
    summary = {
        "out": str(out),
        "poses": poses_mode,
        "frames": len(ds),
        "frames_mapped": len(run.fid_of),
        "frames_posed": len(idx),
        "stopped_at": run.stopped_at,
        "tracking_loss_events": len(run.loss_events),
        "loop_closures": len(run.frontend.loops) if run.frontend is not None else 0,
        "relocalised_frames": sum(bool(v.get("relocalised")) for v in run.track_info.values()),
        "tracking_ms_median": float(np.median(track_ms_after_init)) if len(track_ms_after_init) else
        (float(np.median(ms)) if len(ms) else None),
        "tracking_ms_min": float(np.min(track_ms_after_init)) if len(track_ms_after_init) else None,
        "window_seconds_median": float(np.median([w["seconds"] for w in wins])) if wins else None,
        "init_seconds": mstats.get("init_seconds"),
        "total_seconds": stats["seconds"]["total"],
        "scale_anchor": run.anchor,
        "output_scale": run.scale,
        "init_ok": bool(getattr(run, "init_report", {}).get("ok", True)),
        "init_frames": getattr(run, "init_report", {}).get("frames"),
        "degraded_at_end": run.degraded,
    }
    summary["warnings"] = tracking_warnings(run.stopped_at if run.stopped_at is not None else len(ds), len(idx),
                                            len(run.loss_events), summary["relocalised_frames"], run.degraded,
                                            poses_mode)
    for w in summary["warnings"]:
        log.warning("%s", w)
    if ate_res:
        for a in ("se3", "sim3", "none"):
            if "rmse_m" in ate_res.get(a, {}):
                summary[f"ate_{a}_rmse_m"] = ate_res[a]["rmse_m"]
                summary[f"ate_{a}_rot_deg"] = ate_res[a]["rot_err_mean_deg"]
                # orientation-only fit: the same for every position alignment, well posed on straight runs
                summary.setdefault("ate_rot_fit_deg", ate_res[a]["rot_fit_mean_deg"])
    return write_stats(out, stats, summary)
