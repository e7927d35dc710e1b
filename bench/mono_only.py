"""The monocular front end alone (what ``fmapping slam`` tracks with, without the mapper), for quick
before / after comparisons of tracking changes on several datasets.

    python bench/mono_only.py DATA [DATA ...] [--config slam.yaml] [--max-frames N] [--json out.json]

Per dataset: the same calls as :meth:`fmapping.slam.SlamRun.run_mono` (world frame and scale anchor
from the GT of frame 0 / the bootstrap / frame 14; a failed bootstrap starts again at the next frame, anchored
there, and the frames before the one that succeeds have no pose; the mapper does not influence the mono front end
unless ``mono.dense_extra``), then Sim3 / SE3 ATE of every frame with a pose, the Sim3 scale, the local scale of
consecutive segments (Sim3 of each segment alone: the scale drift), the map's scale keyframe by keyframe
against the GT depth (the frames' own, else a z-buffer of the data's ``gt_points.ply``) and its spread, lost
frames, keyframes, loops accepted and whether the GT contradicts each (bench/real.py's check, on the loop's own
measurement).
GT is used for the anchor (as ``fmapping slam``) and the evaluation only.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def segment_scales(est: np.ndarray, gt: np.ndarray, length: int = 40) -> list:
    """Sim3 scale of each run of ``length`` frames aligned alone (None where the GT barely moves)."""
    from fmapping.metrics import align_trajectory

    out = []
    for a in range(0, len(est) - length // 2, length):
        e, g = est[a:a + length], gt[a:a + length]
        if len(e) < 5 or np.ptp(g[:, :3, 3], axis=0).max() < 0.05:
            out.append(None)
            continue
        out.append(round(float(align_trajectory(e, g, "sim3")[1][0]), 3))
    return out


def gt_depth_source(frames, camera, surface=None, quarter: int = 4):
    """``depth(k)`` -> (H, W) GT depth of frame ``k`` (0 where unknown): the frame's own depth when it has
    one, else a z-buffer of the GT surface points ``surface`` (N, 3) seen from the frame's GT pose at
    1/``quarter`` of the resolution (each point fills its cell; upsampled by repetition). None when neither."""
    if frames[0].depth is not None:
        return lambda k: np.asarray(frames[k].depth, np.float64)
    if surface is None:
        return None
    pts = np.asarray(surface, np.float64)

    def depth(k):
        c2w = np.asarray(frames[k].c2w, np.float64)
        x = (pts - c2w[:3, 3]) @ c2w[:3, :3]
        x = x[x[:, 2] > 0.05]
        w, h = -(-camera.width // quarter), -(-camera.height // quarter)
        u = np.floor((camera.fx * x[:, 0] / x[:, 2] + camera.cx) / quarter).astype(np.int64)
        v = np.floor((camera.fy * x[:, 1] / x[:, 2] + camera.cy) / quarter).astype(np.int64)
        ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z = np.full(h * w, np.inf)
        np.minimum.at(z, v[ok] * w + u[ok], x[ok, 2])
        z[~np.isfinite(z)] = 0.0
        z = z.reshape(h, w).repeat(quarter, 0).repeat(quarter, 1)
        return z[:camera.height, :camera.width]
    return depth


def keyframe_scales(fe, depth, min_points: int = 10) -> dict:
    """How consistent the map's scale is, keyframe by keyframe: for each keyframe, the median over the
    landmarks it observes of GT depth / estimated depth at their pixels (``depth(k)``, :func:`gt_depth_source`;
    GT is used for this evaluation only). A map whose scale drifted has keyframes whose ratios differ even
    where the trajectory's Sim3 fits. Returns {"per_keyframe": {k: ratio}, "spread": p95 / p5 of the ratios}."""
    st, out = fe.store, {}
    for k in sorted(st.kf_pose):
        lids, uv = st.obs.of_keyframe(k)
        if len(lids) < min_points:
            continue
        z = st.depths_seen(k, lids)[1]
        g = depth(k)
        h, w = g.shape
        gz = g[np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1), np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)]
        ok = (gz > 0) & (z > 1e-6)
        if ok.sum() >= min_points:
            out[int(k)] = round(float(np.median(gz[ok] / z[ok])), 4)
    r = np.array(list(out.values()))
    return {"per_keyframe": out,
            "spread": round(float(np.percentile(r, 95) / np.percentile(r, 5)), 4) if len(r) >= 3 else None}


def run(data: str, cfg, max_frames=None) -> dict:
    from fmapping.datasets import open_dataset
    from fmapping.metrics import ate
    from fmapping.ply import read_ply
    from fmapping.tracking.features import to_u8
    from fmapping.tracking.mono import MonoFrontend
    from real import check_loops, loop_capture

    ds = open_dataset(data, max_frames=max_frames)
    gt = list(ds.gt_poses)
    fe = MonoFrontend(ds.camera, cfg.tracker, cfg.mono)

    start = 0  # the first frame of the current bootstrap attempt: its world frame and scale anchor

    def base(k):
        return None if gt[k] is None else float(np.linalg.norm(gt[k][:3, 3] - gt[start][:3, 3]))

    t0 = time.perf_counter()
    est, lost, restarts = {}, [], 0
    with loop_capture() as captured:
        i = 0
        while i < len(ds) and not fe.initialized:  # a failed bootstrap starts again, as fmapping slam's does
            out = fe.bootstrap(i, ds[i].rgb, gt[start], base)
            i += 1
            if fe.failed:
                fe, start, restarts = MonoFrontend(ds.camera, cfg.tracker, cfg.mono), i, restarts + 1
        if not fe.initialized:
            return {"data": data, "error": f"bootstrap failed after {i} frames ({restarts} attempts)"}
        est.update(out)
        for j in range(i, len(ds)):
            r = fe.track(j, ds[j].rgb)
            est[j] = r.c2w
            if r.lost:
                lost.append(j)
        fe.settle_scale()
        est.update(fe.poses())
    secs = time.perf_counter() - t0
    first = min(est)  # frames before the bootstrap that succeeded have no pose (as in fmapping slam's traj.txt)
    last, poses = est[first], []
    for k in range(first, len(ds)):
        last = est.get(k, last)
        poses.append(last)
    e, g = np.stack(poses), np.stack(gt[first:])
    s3, se = ate(e, g, "sim3"), ate(e, g, "se3")
    by_frame = np.concatenate([np.repeat(e[:1], first, 0), e])  # indexed by frame (loops start after ``first``)
    chk = check_loops(fe.loops, captured, by_frame, gt, s3["scale"], gray=lambda k: to_u8(ds[k].rgb),
                      camera=ds.camera)
    surface = Path(data) / "gt_points.ply"
    depth = gt_depth_source(ds, ds.camera, read_ply(surface).points if surface.exists() else None)
    kscale = keyframe_scales(fe, depth) if depth is not None else {"per_keyframe": {}, "spread": None}
    return {"data": Path(data).name, "frames": len(ds), "first_posed": first, "bootstrap_restarts": restarts,
            "seconds": round(secs, 1),
            "ate_sim3_cm": round(100 * s3["rmse_m"], 2), "sim3_scale": round(s3["scale"], 4),
            "ate_se3_cm": round(100 * se["rmse_m"], 2), "rot_fit_deg": round(s3["rot_fit_mean_deg"], 2),
            "segment_scales": segment_scales(e, g), "map_scale_spread": kscale["spread"],
            "keyframe_scales": kscale["per_keyframe"], "lost": len(lost), "reinits": list(fe.reinits),
            "bootstrap": {k: fe.init_info.get(k) for k in ("frame", "points", "scale_from")},
            "late_anchor": fe.late_anchor, "keyframes": len(fe.keyframe_poses()),
            "loops": len(fe.loops), "loops_refused": len(fe.loops_refused),
            "loops_contradicted": chk["contradicted"],
            "loops_contradicted_images_agree": chk["contradicted_images_agree"],
            "loop_errors": [(r["keyframe"], r["frame"], round(r.get("loop_err_m", -1), 3),
                             round(r.get("loop_err_deg", -1), 2), rec.get("inliers"), rec.get("points"),
                             None if rec.get("cross_deg") is None else round(rec["cross_deg"], 2),
                             None if rec.get("cross_dist") is None else round(rec["cross_dist"], 4),
                            r.get("images"))
                            for r, rec in zip(chk["loops"], fe.loops)],
            "refused": [(r["keyframe"], r["frame"], r.get("cross_deg"), r.get("why")) for r in fe.loops_refused]}


def main(argv=None) -> int:
    from fmapping.config import load_config
    from fmapping.runtime import retain_freed_memory
    from fmapping.slam import SlamConfig

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="+")
    ap.add_argument("--config", default=None, help="slam config YAML (the mono / tracker sections count)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    retain_freed_memory()
    import torch
    torch.set_num_threads(1)
    res = []
    for d in a.data:
        cfg = load_config(SlamConfig(), a.config) if a.config else SlamConfig()
        r = run(d, cfg, a.max_frames)
        print(json.dumps(r), flush=True)
        res.append(r)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
