"""The mapper's init stage, variants side by side: its time and the map right after it.

    python bench/init_speed.py                     # synthetic room seed 0, 320x240, 2 repetitions
    python bench/init_speed.py --reps 3 --seed 2 --variety wide
    python bench/init_speed.py --data ../shared/data/7scenes_redkitchen_dev --mapper-seeds 0 1 2 --variants 1,6

Issue 18 asks for an init of at most 5 s on 2 CPU cores at the quality of the init before (4 rounds x 75
iterations x 1024 rays from a clear field, :data:`BEFORE`). Each variant is a set of
:class:`~fmapping.mapping.MapperConfig` overrides (nested for the field); all run in this process, alternated,
on the same 15 frames with GT poses and no depth. After the init it renders five of the init views and three
views it has not seen (frames 17, 22, 27) and reports the median relative depth error against the scene's
depth (evaluation only), PSNR, and the share of held-out pixels the map covers (``acc`` > 0.5; a pixel it does
not cover counts as a relative error of 1). Writes ``bench/results/init_speed.json`` (``--out``); min and
median over the repetitions. ``--mapper-seeds``: each variant runs once per mapper seed (its random rays) and the
quality is the mean over them (one seed moves these numbers by about as much as the variants differ).
``--data``: a dataset folder with depth (the depth for evaluation only) instead of a generated room, e.g. the
7-Scenes dev clip (its depth is not registered with the colour: compare variants there, not absolute values).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
import report  # noqa: E402  (bench/report.py: the machine line)

# the init before 2026-12-04: 4 rounds x 75 iterations x 1024 rays at the grid's lr 0.02, from a clear field
BEFORE = {"init_iters_per_round": 75, "init_rays_per_iter": 1024, "init_lr_grid": 0.02,
          "field": {"init_opacity": 0.0}}
VARIANTS = {
    "before: 4 x 75 x 1024 rays, lr 0.02, clear": BEFORE,
    "default: 4 x 20 x 192 rays, lr 0.05 -> 0.02, fog 0.95": {},
    "default, clear start": {"field": {"init_opacity": 0.0}},
    "default, fog 0.5": {"field": {"init_opacity": 0.5}},
    "default, constant lr 0.02": {"init_lr_grid": 0.02},
    "before with the fog (4 x 75 x 1024, lr 0.02)": {**BEFORE, "field": {"init_opacity": 0.95}},
    "default, 512 rays (the default before 2026-12-07)": {"init_rays_per_iter": 512},
    "default, 256 rays": {"init_rays_per_iter": 256},
    "default, 16 iterations per round": {"init_iters_per_round": 16},
}
INIT_VIEWS, HELD_OUT = list(range(0, 15, 3)), [17, 22, 27]


def _as_unit(rgb) -> np.ndarray:
    a = np.asarray(rgb)
    return a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)


def evaluate(mapper, frames, ids) -> dict:
    """Median relative depth error (uncovered pixels count 1), mean PSNR and coverage over views ``ids``."""
    rel, psnr, cov = [], [], []
    for i in ids:
        r = mapper.render(frames[i].c2w)
        gt = frames[i].depth
        valid = gt > 0
        ok = valid & (r["acc"] > 0.5)
        err = np.ones(int(valid.sum()), np.float32)
        err[ok[valid]] = np.abs(r["depth_normalized"][ok] - gt[ok]) / gt[ok]
        rel.append(float(np.median(err)))
        psnr.append(float(-10 * np.log10(max(np.mean((r["rgb"] - _as_unit(frames[i].rgb)) ** 2), 1e-12))))
        cov.append(float(ok.sum() / max(valid.sum(), 1)))
    return {"depth_rel_median": float(np.median(rel)), "psnr": float(np.mean(psnr)), "coverage": float(np.mean(cov))}


def run_variant(frames, camera, overrides: dict) -> dict:
    from fmapping.config import merge
    from fmapping.mapping import Mapper, MapperConfig

    m = Mapper(merge(MapperConfig(), overrides), camera)
    t0 = time.perf_counter()
    for f in frames[:15]:
        m.add_frame(f.rgb, f.c2w, f.timestamp)
    seconds = time.perf_counter() - t0
    return {"seconds": seconds, "init_views": evaluate(m, frames, INIT_VIEWS),
            "held_out": evaluate(m, frames, HELD_OUT)}


def quality_mean(runs: list) -> dict:
    """The mean of each quality figure over ``runs`` (one per mapper seed; the quality is deterministic)."""
    return {part: {k: float(np.mean([r[part][k] for r in runs])) for k in runs[0][part]}
            for part in ("init_views", "held_out")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variety", default="default", choices=["default", "wide"])
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--mapper-seeds", type=int, nargs="+", default=[0], help="MapperConfig.seed values (rays)")
    ap.add_argument("--data", default=None, help="a dataset folder with depth instead of a generated room")
    ap.add_argument("--variants", default="", help="comma list of variant numbers (0-based) to run; default all")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default=os.path.join(tempfile.gettempdir(), "fmapping_bench_init"))
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "init_speed.json"))
    a = ap.parse_args(argv)
    import torch

    from fmapping.datasets import open_dataset
    from fmapping.synthetic import generate_scene

    torch.set_num_threads(a.threads)
    from fmapping.runtime import preload_optimiser

    preload_optimiser()  # the first optimiser's imports (1-2 s) out of the first variant's time, as the service does
    size = tuple(int(v) for v in a.size.split("x"))
    data = Path(a.data) if a.data else Path(a.work) / f"scene_s{a.seed}_{a.variety}_{a.size}"
    if not a.data and not (data / "rgb.txt").exists():
        print(f"[init] generating {data} ...", flush=True)
        generate_scene(data, seed=a.seed, frames=max(HELD_OUT) + 1, size=size, max_cloud_points=20000,
                       variety=a.variety)
    ds = open_dataset(data, max_frames=max(HELD_OUT) + 1)
    frames = [ds[i] for i in range(len(ds))]
    names = list(VARIANTS)
    if a.variants:
        names = [names[int(i)] for i in a.variants.split(",")]
    runs: dict = {name: [] for name in names}
    for rep in range(a.reps):
        for seed in a.mapper_seeds:
            for name in names:
                r = run_variant(frames, ds.camera, {**VARIANTS[name], "seed": seed})
                r.update(rep=rep, mapper_seed=seed)
                runs[name].append(r)
                iv = r["init_views"]
                print(f"[init] rep {rep} seed {seed} {name:46s} {r['seconds']:5.1f} s | init views: depth rel "
                      f"{iv['depth_rel_median']:.3f}, PSNR {iv['psnr']:.2f} | held out: depth rel "
                      f"{r['held_out']['depth_rel_median']:.3f}, PSNR {r['held_out']['psnr']:.2f}, "
                      f"covered {r['held_out']['coverage']:.2f}", flush=True)
    summary = {name: {"seconds_min": min(r["seconds"] for r in rs),
                      "seconds_median": float(np.median([r["seconds"] for r in rs])),
                      "quality_mean": quality_mean([r for r in rs if r["rep"] == 0]),
                      "overrides": VARIANTS[name], "runs": rs} for name, rs in runs.items()}
    scene = {"data": str(data)} if a.data else {"seed": a.seed, "variety": a.variety, "size": a.size}
    res = {"machine": {"cpu": report.cpu_model(), "cpus": os.cpu_count(), "threads": a.threads},
           "scene": {**scene, "mapper_seeds": a.mapper_seeds}, "variants": summary}
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1) + "\n")
    print(f"[init] wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
