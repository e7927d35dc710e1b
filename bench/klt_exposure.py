"""How precise are the KLT tracks, with and without the exposure compensation (``KltConfig.gain_compensation``),
side by side on the same frames.

    python bench/klt_exposure.py                    # widened synthetic rooms 0-4, default rooms 0-1, shared data
    python bench/klt_exposure.py --seeds 2 --frames 5 --starts 20

For each data set, from ``--starts`` start frames spread over the sequence: Shi-Tomasi corners in the start
frame, tracked frame to frame over ``--frames`` frames (``fmapping.tracking.features.klt_track``), then the
epipolar error of each surviving track (start, end) under the GT relative pose (its Sampson distance,
``features.sampson_px``).
That error needs no depth and no estimated pose: it measures the tracks alone. Reported per variant: tracks
alive at the end (mean per start), median / 75th percentile of the epipolar error (pixels) over all starts,
and KLT milliseconds per frame (min / median over the starts; this machine's CPU speed swings, compare
within one run).

Data: the synthetic rooms ``fmapping synth --variety wide`` (exposure drift, noise, blur, JPEG; seeds
``--seeds``) and ``--variety default`` (seeds 0-1), 200 frames 320x240, generated into ``--work`` when
missing; ``../shared/data/tum_fr1_rpy`` (its lens model, as bench/tracking.py) and
``7scenes_redkitchen_dev`` when present (their GT poses carry their own errors: compare the variants, not
the absolute numbers). Writes ``--out`` (JSON).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
SHARED = ROOT.parent / "shared" / "data"

VARIANTS = {"compensated": {}, "plain": {"gain_compensation": False}}


def epipolar_px(camera, c2w_a: np.ndarray, c2w_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """Epipolar error (Sampson distance, pixels) of the pixel pairs under the poses' relative motion."""
    from fmapping.geometry import inv_pose
    from fmapping.tracking.features import sampson_px

    b_in_a = inv_pose(c2w_a) @ c2w_b
    return np.abs(sampson_px(camera, b_in_a[:3, :3].T, b_in_a[:3, 3], uv_a, uv_b))


def track_run(grey: list, cfg) -> tuple[np.ndarray, np.ndarray, float]:
    """Corners of ``grey[0]`` tracked frame to frame: (start pixels, end pixels) of the survivors, KLT ms/frame."""
    from fmapping.tracking.features import detect_corners, klt_track

    uv0 = detect_corners(grey[0], cfg).astype(np.float64)
    uv, alive = uv0.copy(), np.ones(len(uv0), bool)
    t0 = time.perf_counter()
    for i in range(1, len(grey)):
        idx = np.flatnonzero(alive)
        new, ok = klt_track(grey[i - 1], grey[i], uv[idx], cfg)
        uv[idx] = new
        alive[idx[~ok]] = False
    ms = (time.perf_counter() - t0) * 1e3 / max(1, len(grey) - 1)
    return uv0[alive], uv[alive], ms


def bench_data(name: str, ds, frames: int, starts: int) -> dict:
    from fmapping.tracking.features import KltConfig, to_u8

    n = len(ds)
    first = [int(s) for s in np.linspace(0, n - frames - 1, starts)]
    errs = {v: [] for v in VARIANTS}
    alive = {v: [] for v in VARIANTS}
    ms = {v: [] for v in VARIANTS}
    for f0 in first:
        if ds.gt_poses[f0] is None or ds.gt_poses[f0 + frames] is None:
            continue
        grey = [to_u8(ds[i].rgb) for i in range(f0, f0 + frames + 1)]
        for v, kw in VARIANTS.items():
            a, b, t = track_run(grey, dataclasses.replace(KltConfig(), **kw))
            errs[v].append(epipolar_px(ds.camera, ds.gt_poses[f0], ds.gt_poses[f0 + frames], a, b))
            alive[v].append(len(a))
            ms[v].append(t)
    out = {}
    for v in VARIANTS:
        e = np.concatenate(errs[v]) if errs[v] else np.zeros(0)
        out[v] = {"starts": len(errs[v]), "tracks_alive_mean": round(float(np.mean(alive[v])), 1) if alive[v] else 0,
                  "epipolar_px_median": round(float(np.median(e)), 3) if len(e) else None,
                  "epipolar_px_p75": round(float(np.percentile(e, 75)), 3) if len(e) else None,
                  "klt_ms_per_frame_min": round(float(np.min(ms[v])), 2) if ms[v] else None,
                  "klt_ms_per_frame_median": round(float(np.median(ms[v])), 2) if ms[v] else None}
        print(f"{name:22s} {v:12s} " + "  ".join(f"{k} {val}" for k, val in out[v].items()), flush=True)
    return out


def datasets(args) -> list:
    from fmapping.datasets import open_dataset
    from fmapping.synthetic import generate_scene
    from tracking import tum_camera_arg

    out = []
    for variety, seeds in (("wide", args.seeds), ("default", args.default_seeds)):
        for seed in seeds:
            d = Path(args.work) / f"{variety}_s{seed}_f200_320x240"
            if not (d / "scene.json").exists():
                generate_scene(d, seed=seed, frames=200, size=(320, 240), variety=variety)
            out.append((f"{variety}_s{seed}", lambda d=d: open_dataset(d)))
    tum = SHARED / "tum_fr1_rpy"
    if tum.is_dir():
        out.append(("tum_fr1_rpy", lambda: open_dataset(tum, camera=tum_camera_arg(tum))))
    kitchen = SHARED / "7scenes_redkitchen_dev"
    if kitchen.is_dir():
        out.append(("7scenes_dev", lambda: open_dataset(kitchen)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4], help="widened rooms")
    ap.add_argument("--default-seeds", type=int, nargs="*", default=[0, 1])
    ap.add_argument("--frames", type=int, default=5, help="frames each track is followed")
    ap.add_argument("--starts", type=int, default=10, help="start frames per data set")
    ap.add_argument("--work", default="/tmp/fmapping_bench_klt_exposure")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "klt_exposure" / "klt_exposure.json"))
    args = ap.parse_args()
    import cv2

    cv2.setNumThreads(1)
    res = {"machine": {"platform": platform.platform(), "python": platform.python_version()},
           "settings": {"frames": args.frames, "starts": args.starts, "variants": VARIANTS}, "data": {}}
    for name, opener in datasets(args):
        res["data"][name] = bench_data(name, opener(), args.frames, args.starts)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
