"""``fmapping demo``: the multi-process system on a generated synthetic room, then its trajectory and
reconstruction metrics."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from fmapping.up_config import LauncherOptions
from services.launcher.up import make_scene, run_up


def run_demo(args) -> int:
    """``fmapping demo``, the main job on the embedded default: a synthetic room in ``args.out/scene``, run
    the multi-process system on it (``fmapping up``, poses from the RGB-only tracker unless
    ``args.poses`` says ``gt``, playback paced by the consumers) and print the trajectory and
    reconstruction metrics (``args.out/demo.json``)."""
    from fmapping.fileio import json_default

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene_dir = make_scene(out, LauncherOptions(frames=int(getattr(args, "frames", 200)),
                                                seed=int(getattr(args, "seed", 0))))
    poses = getattr(args, "poses", None) or "tracker"
    uargs = argparse.Namespace(data=str(scene_dir), poses=poses, out=str(out), fps=0.0,
                               config=getattr(args, "config", None))
    rc = run_up(uargs)
    if rc != 0:
        return rc
    report = demo_metrics(out, scene_dir)
    (out / "demo.json").write_text(json.dumps(report, indent=2, default=json_default))
    print(json.dumps(report, indent=2, default=json_default))
    t, r, r3 = report.get("trajectory", {}), report.get("recon", {}), report.get("recon_sim3", {})
    if "ate_sim3_cm" in t:
        print(f"trajectory ({poses} poses, {t['frames']} frames): ATE {t['ate_se3_cm']:.2f} cm (SE3), "
              f"{t['ate_sim3_cm']:.2f} cm (Sim3)")
    if "completion_ratio" in r:
        print(f"reconstruction vs visible GT: accuracy {r['accuracy_cm']:.2f} cm, "
              f"completion {r['completion_cm']:.2f} cm, "
              f"completion ratio (5 cm) {r['completion_ratio']:.1f} %")
    if "completion_ratio" in r3:
        print(f"after the trajectory's Sim3: accuracy {r3['accuracy_cm']:.2f} cm, completion "
              f"{r3['completion_cm']:.2f} cm, completion ratio (5 cm) {r3['completion_ratio']:.1f} %")
    return 0


def demo_metrics(out: Path, scene_dir: Path) -> dict:
    """ATE of ``out/traj.txt`` against the scene's ground truth (SE3 and Sim3) and the map's scores
    (:func:`fmapping.pipeline.recon_stats`: unaligned, after the trajectory's Sim3, and after the Sim3 of its whole
    poses, :func:`fmapping.metrics.align_poses`)."""
    from fmapping.datasets import open_dataset
    from fmapping.metrics import align_poses, align_trajectory, ate, match_trajectory_files
    from fmapping.pipeline import recon_stats

    report: dict = {"out": str(out)}
    sim3 = pose_sim3 = None
    if (out / "traj.txt").is_file():
        est, gt, _, _ = match_trajectory_files(out / "traj.txt", scene_dir / "groundtruth.txt")
        t = {a: ate(est, gt, a) for a in ("se3", "sim3")}
        sim3 = align_trajectory(est, gt, "sim3")[1]
        pose_sim3 = align_poses(est, gt)
        report["trajectory"] = {"frames": len(est), "ate_se3_cm": 100 * t["se3"]["rmse_m"],
                                "ate_sim3_cm": 100 * t["sim3"]["rmse_m"], "sim3_scale": float(sim3[0]),
                                "rot_fit_mean_deg": t["sim3"]["rot_fit_mean_deg"]}
    if (out / "map.ply").is_file():
        keys = ("accuracy_cm", "completion_cm", "completion_ratio")
        for name, r in recon_stats(open_dataset(scene_dir), out, sim3=sim3, pose_sim3=pose_sim3).items():
            report[name] = {k: r[k] for k in keys if k in r}
    return report
