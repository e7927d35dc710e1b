"""Mapping benchmark: quality and speed of the mapper, side by side in one process.

    python bench/mapping.py                 # CP default on seeds 0 1 2 + all variants on seed 0
    python bench/mapping.py --quick         # a short smoke run (small scene, few frames)
    python bench/mapping.py --variants cp,vm --seeds 0 --compare-seeds 0
    python bench/mapping.py --speed         # window-update seconds of the default at 1 and 2 threads
    python bench/mapping.py --real-data     # TUM fr1_rpy and NeRF lego from ../shared/data

Each run streams a synthetic scene (``fmapping.synthetic.generate_scene``, RGB only, GT
poses) through :class:`fmapping.mapping.Mapper`, exports the point cloud like
``fmapping map`` (every 3rd frame, consistency-filtered) and scores it against the
scene's ``gt_visible_cloud.ply``. Variants (config overrides of the CP default):

* field kinds: ``cp`` (default), ``vm``, ``mlp`` (iMAP-like), ``grid`` (dense voxels);
* sampling: ``cp-stratified`` (stratified only, same sample count), ``cp-sliding``
  (sliding-window sampler for the on-the-fly stage instead of importance sampling);
* opacity: ``cp-occupancy`` (UNISURF occupancy instead of density);
* ablations: ``cp-nowarp`` (no warping loss), ``cp-nopc`` (no per-sample photo-consistency).

Reported per run: seconds per on-the-fly window update (min / median: the machine is
shared, timings are noisy), init / final / total seconds, parameters, FLOPs per point,
accuracy / completion / completion ratio (5 cm), held-out PSNR. Writes
``bench/results/mapping.json`` and ``bench/results/mapping.png``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

VARIANTS = {
    "cp": {},
    "vm": {"field": {"kind": "vm"}},
    "mlp": {"field": {"kind": "mlp"}},
    "grid": {"field": {"kind": "grid"}},
    "cp-stratified": {"sampler": "stratified", "n_coarse": 48, "n_fine": 0},
    "cp-sliding": {"sampler": "sliding_window"},
    "cp-occupancy": {"field": {"alpha_mode": "occupancy"}},
    "cp-nowarp": {"warp_weight": 0.0},
    "cp-nopc": {"pc_weight": 0.0},
}
QUICK = {"init_iters_per_round": 25, "final_global_iters": 40, "rays_per_iter": 512}


def scene_dir(base: Path, seed: int, frames: int, size: tuple[int, int]) -> Path:
    from fmapping.synthetic import generate_scene

    d = base / f"synth_s{seed}_f{frames}_{size[0]}x{size[1]}"
    if not (d / "scene.json").is_file():
        print(f"[bench] generating {d}", flush=True)
        generate_scene(d, seed=seed, frames=frames, size=size)
    return d


def run_one(data: Path, overrides: dict, threads: int, export_every: int = 3, keep: Optional[list] = None) -> dict:
    import torch

    from fmapping.config import merge
    from fmapping.datasets import open_dataset
    from fmapping.export import export_point_cloud
    from fmapping.mapping import Mapper, MapperConfig
    from fmapping.metrics import recon_metrics
    from fmapping.pipeline import _heldout_psnr, scene_aabb
    from fmapping.ply import read_ply

    torch.set_num_threads(threads)
    ds = open_dataset(data)
    cfg = merge(MapperConfig(), {**overrides, "optimize_init_poses": False})
    poses = list(ds.gt_poses)
    mapper = Mapper(cfg, ds.camera, aabb=scene_aabb(ds, cfg, poses))
    t0 = time.perf_counter()
    for i in range(len(ds)):
        f = ds[i]
        mapper.add_frame(f.rgb, poses[i], f.timestamp)
    mapper.finish()
    t_map = time.perf_counter() - t0
    s = mapper.stats()
    allp = mapper.frame_poses()
    t0 = time.perf_counter()
    pts, _ = export_point_cloud(mapper, {k: allp[k] for k in sorted(allp)[::export_every]}, ds.camera,
                                near=cfg.near, far=cfg.far, n_samples=cfg.n_coarse, n_importance=max(cfg.n_fine, 16))
    t_exp = time.perf_counter() - t0
    gt = read_ply(ds.meta["gt_visible_cloud"]).points
    rec = recon_metrics(pts, gt, threshold=0.05)
    win = [w["seconds"] for w in s["windows"] if w["kind"] == "window"]
    if keep is not None:
        keep.append(mapper)
    return {
        "parameters": s["parameters"],
        "flops_per_point": int(mapper.field.flops_per_point()),
        "window_seconds": win,
        "window_seconds_min": float(np.min(win)) if win else None,
        "window_seconds_median": float(np.median(win)) if win else None,
        "init_seconds": s["init_seconds"],
        "final_seconds": s["final_seconds"],
        "mapping_seconds": t_map,
        "export_seconds": t_exp,
        "points": int(len(pts)),
        "accuracy_cm": rec["accuracy_cm"],
        "completion_cm": rec["completion_cm"],
        "completion_ratio": rec["completion_ratio"],
        "psnr_heldout": _heldout_psnr(mapper, ds, list(range(len(ds)))),
    }


def interleaved_window_timing(mappers: dict, rounds: int) -> dict:
    """Seconds of one window update (``iters_per_window`` iterations on each mapper's last
    window) for every variant, measured round-robin so that load swings hit all alike."""
    times: dict = {k: [] for k in mappers}
    for _ in range(rounds):
        for name, m in mappers.items():
            ids = m.window_ids()
            cfg = m.cfg
            t0 = time.perf_counter()
            m._run_iters("window", ids, cfg.iters_per_window, cfg.sampler, cfg.n_coarse, cfg.n_fine, cfg.sw_window)
            times[name].append(time.perf_counter() - t0)
    return {k: {"min": float(np.min(v)), "median": float(np.median(v)), "all": v} for k, v in times.items()}


def speed(data: Path, frames: int, rounds: int, thread_counts: list[int]) -> dict:
    """Seconds of one on-the-fly window update of the CP default, per torch thread count.

    Maps the first ``frames`` frames once (GT poses, RGB only), then times ``rounds``
    window updates (``iters_per_window`` iterations on the last window) for each thread
    count round-robin, so load swings hit every setting alike.
    """
    import torch

    from fmapping.datasets import open_dataset
    from fmapping.mapping import Mapper, MapperConfig
    from fmapping.config import merge
    from fmapping.pipeline import scene_aabb

    torch.set_num_threads(max(thread_counts))
    ds = open_dataset(data)
    cfg = merge(MapperConfig(), {"optimize_init_poses": False})
    poses = list(ds.gt_poses)
    mapper = Mapper(cfg, ds.camera, aabb=scene_aabb(ds, cfg, poses))
    for i in range(min(frames, len(ds))):
        f = ds[i]
        mapper.add_frame(f.rgb, poses[i], f.timestamp)
    ids = mapper.window_ids()
    times: dict = {str(t): [] for t in thread_counts}
    for _ in range(rounds):
        for t in thread_counts:
            torch.set_num_threads(t)
            t0 = time.perf_counter()
            mapper._run_iters("window", ids, cfg.iters_per_window, cfg.sampler, cfg.n_coarse, cfg.n_fine, cfg.sw_window)
            times[str(t)].append(time.perf_counter() - t0)
    return {"frames_mapped": min(frames, len(ds)), "window_frames": len(ids), "rays_per_iter": cfg.rays_per_iter,
            "samples_per_ray": cfg.n_coarse + cfg.n_fine, "iters_per_window": cfg.iters_per_window,
            "seconds": {t: {"min": float(np.min(v)), "median": float(np.median(v)), "all": v}
                        for t, v in times.items()}}


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results["variants"])
    if not names:
        return
    agg = {n: results["variants"][n]["mean"] for n in names}
    fig, ax = plt.subplots(1, 4, figsize=(18, 4.5))
    x = np.arange(len(names))
    inter = results.get("interleaved_window_seconds", {})
    med = [inter[n]["median"] if n in inter else (agg[n]["window_seconds_median"] or 0) for n in names]
    mn = [inter[n]["min"] if n in inter else (agg[n]["window_seconds_min"] or 0) for n in names]
    ax[0].bar(x - 0.2, mn, 0.4, label="min")
    ax[0].bar(x + 0.2, med, 0.4, label="median")
    ax[0].axhline(2.0, color="r", ls="--", lw=1, label="2.0 s target")
    ax[0].set_title("seconds per window update (20 iters)")
    ax[0].legend()
    ax[1].bar(x, [agg[n]["parameters"] for n in names])
    ax[1].set_yscale("log")
    ax[1].set_title("parameters")
    ax[2].bar(x, [agg[n]["completion_ratio"] for n in names])
    ax[2].axhline(90, color="r", ls="--", lw=1)
    ax[2].set_title("completion ratio (5 cm) %")
    ax[3].bar(x - 0.2, [agg[n]["accuracy_cm"] for n in names], 0.4, label="accuracy")
    ax[3].bar(x + 0.2, [agg[n]["completion_cm"] for n in names], 0.4, label="completion")
    ax[3].set_title("cm (lower is better)")
    ax[3].legend()
    for a in ax:
        a.set_xticks(x)
        a.set_xticklabels(names, rotation=35, ha="right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)


def _mean(runs: list[dict]) -> dict:
    keys = ["parameters", "flops_per_point", "window_seconds_min", "window_seconds_median", "init_seconds",
            "final_seconds", "mapping_seconds", "export_seconds", "points", "accuracy_cm", "completion_cm",
            "completion_ratio", "psnr_heldout"]
    out = {}
    for k in keys:
        vals = [r[k] for r in runs if r.get(k) is not None]
        out[k] = float(np.mean(vals)) if vals else None
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="short run: 1 seed, 40 frames at 160x120, fewer iterations")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma list of {', '.join(VARIANTS)}")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds for the cp default")
    ap.add_argument("--compare-seeds", type=int, nargs="+", default=[0], help="seeds for the other variants")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--timing-rounds", type=int, default=5,
                    help="round-robin window updates per variant after the runs (comparable timings)")
    ap.add_argument("--scenes", default=str(Path(tempfile.gettempdir()) / "fmapping_bench_scenes"))
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "mapping.json"))
    ap.add_argument("--real-data", action="store_true",
                    help="instead: TUM fr1_rpy and NeRF lego from ../shared/data (held-out PSNR + pictures)")
    ap.add_argument("--speed", action="store_true",
                    help="instead: time window updates of the CP default at 1 and 2 threads (mapping_speed.json)")
    ap.add_argument("--speed-frames", type=int, default=60, help="frames mapped before timing (--speed)")
    a = ap.parse_args(argv)
    if a.speed:
        size = tuple(int(v) for v in a.size.lower().split("x"))
        res = speed(scene_dir(Path(a.scenes), a.seeds[0], a.frames, size), a.speed_frames, a.timing_rounds, [1, 2])
        res["cpu_load_at_end"] = list(os.getloadavg())
        for t, v in res["seconds"].items():
            print(f"[bench] {t} thread(s): window update {v['min']:.2f} / {v['median']:.2f} s (min / median)",
                  flush=True)
        out = Path(a.out).with_name("mapping_speed.json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=2))
        return 0
    if a.real_data:
        out = Path(a.out).with_name("mapping_real.json")
        res = run_real(a.threads, out.parent)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=2))
        return 0
    size = tuple(int(v) for v in a.size.lower().split("x"))
    extra = {}
    if a.quick:
        a.frames, size, a.seeds, a.compare_seeds = 40, (160, 120), [0], [0]
        extra = QUICK
    names = [n.strip() for n in a.variants.split(",") if n.strip()]
    bad = [n for n in names if n not in VARIANTS]
    if bad:
        ap.error(f"unknown variants {bad}; choose from {', '.join(VARIANTS)}")
    base = Path(a.scenes)
    results = {"settings": {"frames": a.frames, "size": list(size), "threads": a.threads, "quick": a.quick,
                            "seeds": a.seeds, "compare_seeds": a.compare_seeds, "overrides": extra},
               "variants": {}}
    out = Path(a.out)
    kept: dict = {}
    for name in names:
        seeds = a.seeds if name == "cp" else a.compare_seeds
        runs = []
        for seed in seeds:
            data = scene_dir(base, seed, a.frames, size)
            ov = _merge_dicts(extra, VARIANTS[name])
            print(f"[bench] {name} seed {seed} ...", flush=True)
            hold: list = []
            r = run_one(data, ov, a.threads, keep=hold if seed == a.compare_seeds[0] else None)
            if hold:
                kept[name] = hold[0]
            r["seed"] = seed
            runs.append(r)
            print(f"[bench] {name} seed {seed}: window {r['window_seconds_min']:.2f}/"
                  f"{r['window_seconds_median']:.2f} s (min/median), acc {r['accuracy_cm']:.2f} cm, "
                  f"comp {r['completion_cm']:.2f} cm, "
                  f"ratio {r['completion_ratio']:.1f} %, params {r['parameters']}", flush=True)
        results["variants"][name] = {"overrides": VARIANTS[name], "runs": runs, "mean": _mean(runs)}
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(results, indent=2))  # partial results survive an interrupted run
    if len(kept) > 1 and a.timing_rounds > 0:
        print(f"[bench] interleaved window timing ({a.timing_rounds} rounds) ...", flush=True)
        results["interleaved_window_seconds"] = interleaved_window_timing(kept, a.timing_rounds)
        for n, t in results["interleaved_window_seconds"].items():
            print(f"[bench] {n}: window {t['min']:.2f}/{t['median']:.2f} s (min/median, interleaved)", flush=True)
        out.write_text(json.dumps(results, indent=2))
    plot(results, out.with_suffix(".png"))
    print(json.dumps({n: v["mean"] for n, v in results["variants"].items()}, indent=2))
    return 0


def _held_out_figure(rows: list, path: Path, title: str) -> None:
    """rows: (gt rgb, rendered rgb, depth) per view -> one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(len(rows), 3, figsize=(11, 3.3 * len(rows)), squeeze=False)
    for r, (gt, rgb, dep) in enumerate(rows):
        for c, (img, name) in enumerate(((gt, "input (held out)"), (rgb, "rendered"), (dep, "rendered depth"))):
            ax[r, c].imshow(img, cmap="turbo" if c == 2 else None)
            ax[r, c].set_title(name, fontsize=9)
            ax[r, c].axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def run_real(threads: int, out_dir: Path) -> dict:
    """TUM fr1_rpy (GT poses, RGB only) and NeRF-synthetic lego: held-out PSNR and pictures.

    Data from ``../shared/data`` (skipped when absent). TUM: every frame is streamed, PSNR
    over the frames that are not keyframes (half resolution). Lego: views resized to
    200x200 over a black background, every 8th view held out, all others fitted together
    (init stage over all of them + the closing refinement), PSNR of the held-out views.
    """
    import cv2
    import torch

    from fmapping.config import merge
    from fmapping.datasets import open_dataset
    from fmapping.mapping import Mapper, MapperConfig
    from fmapping.metrics import psnr
    from fmapping.pipeline import scene_aabb

    torch.set_num_threads(threads)
    data = ROOT.parent / "shared" / "data"
    res: dict = {}
    tum_dir = data / "tum_fr1_rpy"
    if tum_dir.is_dir():
        ds = open_dataset(tum_dir)
        cfg = merge(MapperConfig(), {"far": 4.0, "optimize_init_poses": False})
        poses = list(ds.gt_poses)
        m = Mapper(cfg, ds.camera, aabb=scene_aabb(ds, cfg, poses))
        t0 = time.perf_counter()
        used = [i for i in range(len(ds)) if poses[i] is not None]
        for i in used:
            m.add_frame(ds[i].rgb, poses[i], ds[i].timestamp)
        m.finish()
        kf = set(m.keyframe_ids())
        cam = ds.camera.resized(ds.camera.width // 2, ds.camera.height // 2)
        fp = m.frame_poses()
        vals, rows = [], []
        held = [k for k in range(len(used)) if k not in kf]
        for j, k in enumerate(held):
            gt = cv2.resize(ds[used[k]].rgb, (cam.width, cam.height), interpolation=cv2.INTER_AREA) / 255.0
            out = m.render(fp[k], cam)
            vals.append(psnr(out["rgb"], gt))
            if j in (0, len(held) // 2, len(held) - 1):
                rows.append((gt, out["rgb"], out["depth_normalized"]))
        s = m.stats()
        res["tum_fr1_rpy"] = {"frames": len(used), "held_out": len(held), "psnr_heldout": float(np.mean(vals)),
                              "window_seconds_min": s["window_seconds_min"],
                              "window_seconds_median": s["window_seconds_median"],
                              "mapping_seconds": time.perf_counter() - t0}
        _held_out_figure(rows, out_dir / "mapping_tum_fr1_rpy.png",
                         f"TUM fr1_rpy, GT poses, RGB only: held-out PSNR {np.mean(vals):.2f} dB")
        print("[bench] tum_fr1_rpy", res["tum_fr1_rpy"], flush=True)
    lego_dir = data / "nerf_synthetic_lego"
    if lego_dir.is_dir():
        res["lego"] = run_lego(lego_dir, out_dir / "mapping_lego.png")
        print("[bench] lego", res["lego"], flush=True)
    return res


LEGO_CONFIG = {"init_iters_per_round": 150, "optimize_init_poses": False, "final_global_iters": 600, "near": 2.0,
               "far": 6.0, "warp_keep": 0.5, "bbox": [[-1.5] * 3, [1.5] * 3], "rays_per_iter": 2048}


def run_lego(lego_dir: Path, png: Optional[Path], overrides: Optional[dict] = None, size: int = 200,
             max_views: Optional[int] = None) -> dict:
    """NeRF-synthetic lego: views resized to ``size`` x ``size`` over a black background, every 8th
    view held out, all others fitted together (init stage over all of them + the closing refinement);
    returns the novel-view PSNR of the held-out views and writes a picture to ``png`` (if given).
    ``overrides`` go over :data:`LEGO_CONFIG`; ``max_views`` keeps the first views only (smoke runs).
    Shared with ``bench/real.py``."""
    import cv2

    from fmapping.config import merge
    from fmapping.datasets import open_dataset
    from fmapping.mapping import Mapper, MapperConfig
    from fmapping.metrics import psnr

    ds = open_dataset(lego_dir, background=(0, 0, 0), max_frames=max_views)
    cam = ds.camera.resized(size, size)
    frames = [ds[i] for i in range(len(ds))]
    imgs = [cv2.resize(f.rgb, (size, size), interpolation=cv2.INTER_AREA) for f in frames]
    test = list(range(0, len(frames), 8))
    train = [i for i in range(len(frames)) if i not in test]
    cfg = merge(MapperConfig(), _merge_dicts(LEGO_CONFIG, {**(overrides or {}), "init_frames": len(train)}))
    m = Mapper(cfg, cam)
    t0 = time.perf_counter()
    for i in train:
        m.add_frame(imgs[i], frames[i].c2w)
    m.finish()
    vals, rows = [], []
    for j, i in enumerate(test):
        out = m.render(frames[i].c2w, cam)
        vals.append(psnr(out["rgb"], imgs[i] / 255.0))
        if j < 3:
            rows.append((imgs[i], out["rgb"], out["depth_normalized"]))
    if png is not None:
        _held_out_figure(rows, png,
                         f"NeRF-synthetic lego ({size}x{size}, black bg): novel-view PSNR {np.mean(vals):.2f} dB")
    return {"train_views": len(train), "test_views": len(test), "size": [size, size],
            "psnr_novel_views": float(np.mean(vals)), "seconds": time.perf_counter() - t0}


def _merge_dicts(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge_dicts(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


if __name__ == "__main__":
    sys.exit(main())
