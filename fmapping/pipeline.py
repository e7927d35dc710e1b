"""The mapping job behind ``fmapping map``.

``run_map(job)`` (:class:`fmapping.job.Job`) opens a dataset, streams its frames with known poses (ground truth
or a TUM trajectory file) into a :class:`fmapping.mapping.Mapper`, exports the map and
writes into ``job.out``:

* ``map.ply``    coloured point cloud (:func:`fmapping.export.export_point_cloud`),
* ``mesh.ply``   coloured mesh (:func:`fmapping.export.export_mesh`),
* ``traj.txt``   the poses used (refined for the init frames when pose optimisation is on), TUM format,
* ``stats.json`` config, dataset description (intrinsics, depth scale), parameter
  count, per-window seconds, totals, held-out PSNR and - when the dataset ships a
  visible GT cloud (``meta["gt_visible_cloud"]``) - reconstruction metrics.

Scene bounds: the config ``bbox`` (``--bbox``) when set, else the box of the back-projected
depth (with ``--use-depth``), else (``bounds: points``, the default) the mapper's own: the box
of the points it triangulates from KLT tracks with the given poses
(:mod:`fmapping.sparse_points`), grown as they spread; else the view frusta of all given poses
between ``near`` and ``far``. Nothing the generator of a synthetic scene knows (its
``scene.json``) is used.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.cancel import Cancelled, StopFn
from fmapping.config import load_config, to_dict
from fmapping.fileio import json_default
from fmapping.job import Job
from fmapping.map_outputs import write_map_outputs
from fmapping.mapping import Mapper, MapperConfig, aabb_from_depth, aabb_from_poses

log = logging.getLogger("fmapping.pipeline")

EXPORT_EVERY = 3  # export renders every 3rd frame's view


def _pose_source(ds, poses_arg: str) -> list:
    """Per-frame c2w (or None when unknown) from ``"gt"`` or a TUM trajectory file."""
    if poses_arg == "gt":
        if not any(p is not None for p in ds.gt_poses):
            raise ValueError(f"--poses gt: dataset {ds.root} has no ground-truth poses; give a trajectory file")
        return list(ds.gt_poses)
    from fmapping.trajectory import associate, read_tum_trajectory

    path = Path(poses_arg)
    if not path.is_file():
        raise FileNotFoundError(f"--poses: trajectory file not found: {path}")
    ts, c2w = read_tum_trajectory(path)
    idx = associate(np.asarray(ds.timestamps, np.float64), ts, max_dt=0.02)
    if (idx < 0).all():
        raise ValueError(f"--poses {path}: no timestamp matches the dataset frames within 0.02 s")
    return [c2w[j] if j >= 0 else None for j in idx]


def scene_aabb(ds, cfg: MapperConfig, poses: list, use_depth: Optional[bool] = None) -> Optional[np.ndarray]:
    """The mapper's box for ``ds`` with the given ``poses`` (None entries skipped), or None when the
    mapper decides it itself: ``cfg.bbox`` is set, or (``cfg.bounds == "points"``, the default) it
    bounds the points it triangulates and grows the box with them. Else the dataset's depth (when
    ``use_depth``, default ``cfg.use_depth``), else the frusta of all ``poses``."""
    use_depth = cfg.use_depth if use_depth is None else use_depth
    if cfg.bbox is not None:
        return None  # the mapper takes it from its config
    known = [(i, p) for i, p in enumerate(poses) if p is not None]
    if use_depth and ds.has_depth:
        step = max(1, len(known) // 30)
        sel = known[::step]
        box = aabb_from_depth(np.stack([p for _, p in sel]), [ds[i].depth for i, _ in sel], ds.camera, cfg.bbox_margin)
        if box is not None:
            return box
    if cfg.bounds == "points":
        return None
    return aabb_from_poses(np.stack([p for _, p in known]), ds.camera, cfg.near, cfg.far, cfg.bbox_margin)


def build_config(job: Job) -> MapperConfig:
    """The mapper config of a ``fmapping map`` job: its YAML, then the job's field, depth, box, device."""
    cfg = load_config(MapperConfig(), job.config)
    cfg = job.mapper_config(cfg)
    if job.poses == "gt":
        cfg = dataclasses.replace(cfg, optimize_init_poses=False)  # ground truth is trusted
    cfg.validate()
    return cfg


def _heldout_psnr(mapper: Mapper, ds, used: list, n: int = 8) -> Optional[float]:
    """Mean PSNR of up to ``n`` frames that are not keyframes, rendered at half resolution with the
    frame's estimated exposure. Undistortion's black borders are no image content: masked out."""
    import cv2

    from fmapping.metrics import psnr
    from fmapping.tracking.direct_align import image_valid_mask

    kf = set(mapper.keyframe_ids())
    cand = [(fid, i) for fid, i in enumerate(used) if fid not in kf]
    if not cand:
        return None
    sel = [cand[int(k)] for k in np.linspace(0, len(cand) - 1, min(n, len(cand)))]
    cam = ds.camera.resized(max(1, ds.camera.width // 2), max(1, ds.camera.height // 2))
    poses = mapper.frame_poses()
    vals = []
    for fid, i in sel:
        rgb = ds[i].rgb
        valid = image_valid_mask(rgb, erode=2)
        img = cv2.resize(rgb, (cam.width, cam.height), interpolation=cv2.INTER_AREA) / 255.0
        mask = None if valid is None else cv2.resize(valid.astype(np.uint8), (cam.width, cam.height),
                                                     interpolation=cv2.INTER_NEAREST) > 0
        out = mapper.render(poses[fid], cam, frame=fid)
        vals.append(psnr(out["rgb"], img, mask=mask))
    return float(np.mean(vals))


# ----------------------------------------------------------------------------- job I/O (shared with fmapping.slam)
def open_job_dataset(job: Job):
    """The dataset of a job: ``job.data`` with its camera, frame count and source options.
    A dataset without frames is a ValueError naming the folder."""
    from fmapping.datasets import open_dataset

    ds = open_dataset(job.data, camera=job.camera, max_frames=job.max_frames, **job.source_options())
    if len(ds) == 0:
        raise ValueError(f"dataset {job.data} has no frames")
    return ds


def recon_stats(ds, out: Path, mesh: bool = False, sim3: Optional[tuple] = None,
                pose_sim3: Optional[tuple] = None) -> dict:
    """Reconstruction metrics (NICE-SLAM protocol, 200k samples, 5 cm) of ``out/map.ply`` - and of
    ``out/mesh.ply`` with ``mesh`` - against the dataset's visible GT cloud
    (``meta["gt_visible_cloud"]``): ``{"recon": ..., "recon_mesh": ...}``, ``{}`` without one.
    With ``sim3 = (s, R, t)`` (the trajectory's alignment to the GT) also ``"recon_sim3"``: the
    map moved by it first, the usual protocol for monocular maps; with ``pose_sim3`` (the alignment by whole
    poses, :func:`fmapping.metrics.align_poses`) also ``"recon_pose_sim3"``."""
    gt_cloud = ds.meta.get("gt_visible_cloud") if isinstance(ds.meta, dict) else None
    if not gt_cloud or not Path(gt_cloud).is_file():
        return {}
    from fmapping.metrics import eval_recon_files

    res = {"recon": eval_recon_files(str(out / "map.ply"), gt_cloud, samples=200_000, threshold=0.05, seed=0)}
    for name, align in (("recon_sim3", sim3), ("recon_pose_sim3", pose_sim3)):
        if align is not None:
            res[name] = eval_recon_files(str(out / "map.ply"), gt_cloud, samples=200_000, threshold=0.05, seed=0,
                                         align=align)
    if mesh:
        res["recon_mesh"] = eval_recon_files(str(out / "mesh.ply"), gt_cloud, samples=200_000, threshold=0.05, seed=0)
    return res


def write_stats(out: Path, stats: dict, summary: dict) -> dict:
    """Copy the main reconstruction metrics (if any) into ``summary``, store it as
    ``stats["summary"]`` and write ``out/stats.json``; returns ``stats``."""
    for key, suffix in (("recon", ""), ("recon_sim3", "_sim3")):
        if key in stats:
            summary.update({k + suffix: stats[key][k] for k in ("accuracy_cm", "completion_cm", "completion_ratio")
                            if k in stats[key]})
    stats["summary"] = summary
    (out / "stats.json").write_text(json.dumps(stats, indent=2, default=json_default))
    return stats


# ----------------------------------------------------------------------------- the mapping job
def run_map(job: Job, should_stop: StopFn = None) -> dict:
    """Run the mapping job (see the module docstring); returns the stats dict with a ``summary``.
    ``should_stop()`` True ends it early: the map so far is exported without the closing stage
    (``summary["stopped_at"]``: the first frame not given to the mapper)."""
    import torch
    from tqdm import tqdm

    from fmapping.trajectory import write_tum_trajectory

    t_start = time.perf_counter()
    ds = open_job_dataset(job)
    cfg = build_config(job)
    poses = _pose_source(ds, job.poses)
    aabb = scene_aabb(ds, cfg, poses)
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    mapper = Mapper(cfg, ds.camera, aabb=aabb, should_stop=should_stop)
    used, skipped, stopped_at = [], 0, None
    with tqdm(range(len(ds)), desc="mapping", unit="frame", disable=job.quiet) as bar:
        for i in bar:
            if should_stop is not None and should_stop():
                stopped_at = i
                break
            if poses[i] is None:
                skipped += 1
                continue
            f = ds[i]
            used.append(i)
            try:
                mapper.add_frame(f.rgb, poses[i], f.timestamp, f.depth if cfg.use_depth else None)
            except Cancelled:  # inside an update: this frame was the last one given
                stopped_at = i + 1
                break
    if not used and stopped_at is None:
        raise ValueError(f"no frame of {job.data} has a pose")
    if stopped_at is None:
        try:
            mapper.finish()
        except Cancelled:  # in the closing stage: every frame was given, the map is as far as it got
            stopped_at = len(ds)
    if stopped_at is not None and not mapper.initialized:
        log.warning("stopped before frame %d, before the mapper's init stage ended: no map to write", stopped_at)
        return write_stats(out, {"dataset": ds.describe(), "frames_used": len(used), "stopped_at": stopped_at},
                           {"out": str(out), "frames": len(used), "stopped_at": stopped_at, "points": 0})
    if stopped_at is not None:
        log.warning("stopped before frame %d of %d: exporting the map so far", stopped_at, len(ds))
    t_map = time.perf_counter() - t_start

    # ---- export
    t0 = time.perf_counter()
    all_poses = mapper.frame_poses()
    # every EXPORT_EVERY-th frame (not only keyframes): views seen briefly between keyframes count too
    exp_poses = {k: all_poses[k] for k in sorted(all_poses)[::EXPORT_EVERY]}
    samples = (cfg.n_coarse, max(cfg.n_fine, 16))
    export = write_map_outputs(mapper, exp_poses, ds.camera, out, near=cfg.near, far=cfg.far,
                               cloud_samples=samples, mesh_samples=samples)
    ts = mapper.frame_timestamps()
    write_tum_trajectory(out / "traj.txt", np.array([ts[k] for k in all_poses]), np.stack(list(all_poses.values())))
    t_export = time.perf_counter() - t0
    export["seconds"] = t_export

    mstats = mapper.stats()
    stats = {
        "config": to_dict(cfg),
        "dataset": ds.describe(),
        "poses": job.poses,
        "frames_used": len(used),
        "frames_without_pose": skipped,
        "stopped_at": stopped_at,
        "aabb": mapper.aabb.cpu().tolist(),
        "mapper": mstats,
        "export": export,
        "seconds": {"mapping": t_map, "export": t_export, "total": time.perf_counter() - t_start},
        "torch_threads": torch.get_num_threads(),
    }
    stats["psnr_heldout"] = _heldout_psnr(mapper, ds, used)
    stats.update(recon_stats(ds, out, mesh=export["mesh_faces"] > 0))
    summary = {
        "out": str(out),
        "frames": len(used),
        "stopped_at": stopped_at,
        "parameters": mstats["parameters"],
        "window_seconds_min": mstats["window_seconds_min"],
        "window_seconds_median": mstats["window_seconds_median"],
        "init_seconds": mstats["init_seconds"],
        "final_seconds": mstats["final_seconds"],
        "total_seconds": stats["seconds"]["total"],
        "points": export["points"],
        "psnr_heldout": stats["psnr_heldout"],
    }
    return write_stats(out, stats, summary)
