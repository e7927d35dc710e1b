"""The monocular front end under configuration variants, side by side on the same frames: accuracy and
where the time goes.

    python bench/mono_variants.py                                  # the defaults alone
    python bench/mono_variants.py --variants "old_ba:ba_rel_tol=1e-9" "kf2:klt.refine_levels=2"
    python bench/mono_variants.py --data /tmp/room --variants "w7:window=7" "t:tracker.align.step_tol=1e-4"

A variant is ``name:key=value;key=value``: ``MonoConfig`` fields, ``klt.*`` / ``loop.*`` of its parts,
``tracker.*`` / ``tracker.align.*`` of the ``TrackerConfig`` (values are Python literals). The defaults
(``base``) run first. For every data set each variant runs in turn in this process, offline (the bundle
adjustment on the frame path, as ``fmapping slam``: deterministic for a given code and config), with the
scale anchored as the tracker service does (GT baseline at the bootstrap and at frame 14).

Data (default): the synthetic rooms of seeds 0-4 (``fmapping synth``, 200 frames 320x240, generated into
``--work`` when missing), and ``../shared/data/tum_fr1_rpy`` (TUM fr1 lens model, as bench/tracking.py)
and ``7scenes_redkitchen_dev`` when present.

Per run: Sim3 ATE of every frame's final pose, the spread of the map's scale over the keyframes against the GT
depth (p95 / p5 of the keyframes' GT / estimated landmark depths, :func:`mono_only.keyframe_scales`), frames
lost, keyframes, loop closures, the bundle adjustments (count, summed and median ms, mean residual
evaluations), and per frame the wall time of ``track`` (median / mean / p95: a keyframe's bundle adjustment
counts in its frame) with the KLT and direct-alignment parts. Single runs of a monocular front end are
chaotic (a different loop closure moves the ATE by 20 %): judge a variant over the data sets, not on one.
Timings are this machine's, noisy (the CPU's speed swings): compare within one run of this script. Writes
``--out`` (JSON).
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
SHARED = ROOT.parent / "shared" / "data"


def make_configs(spec: str):
    """(MonoConfig, TrackerConfig) with the overrides of ``spec`` (``key=value;...``)."""
    from fmapping.tracking.direct_tracker import TrackerConfig
    from fmapping.tracking.mono import MonoConfig

    mono, trk = MonoConfig(), TrackerConfig()

    def put(obj, path: list, value):
        if len(path) == 1:
            if not hasattr(obj, path[0]):
                raise SystemExit(f"no setting {path[0]!r} in {type(obj).__name__}")
            return dataclasses.replace(obj, **{path[0]: value})
        return dataclasses.replace(obj, **{path[0]: put(getattr(obj, path[0]), path[1:], value)})

    for kv in filter(None, spec.split(";")):
        key, _, val = kv.partition("=")
        path = key.strip().split(".")
        value = ast.literal_eval(val.strip())
        if path[0] == "tracker":
            trk = put(trk, path[1:], value)
        else:
            mono = put(mono, path, value)
    return mono, trk


def run(frames, camera, mono_cfg, trk_cfg, depth=None) -> dict:
    """One offline pass of the front end over ``frames`` (see the module docstring); with ``depth`` (GT depth of a
    frame, :func:`mono_only.gt_depth_source`) also the spread of the map's scale over the keyframes."""
    import fmapping.tracking.mono.frontend as fe_mod
    from fmapping.metrics import ate
    from fmapping.tracking.mono import MonoFrontend

    fe = MonoFrontend(camera, tracker_cfg=trk_cfg, cfg=mono_cfg)
    spent = {"klt": 0.0, "direct": 0.0}

    def timed(fn, key):
        def wrapped(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[key] += time.perf_counter() - t
        return wrapped

    klt = fe_mod.klt_track_gain
    fe_mod.klt_track_gain = timed(klt, "klt")
    fe.tracker.track = timed(fe.tracker.track, "direct")
    try:
        g0 = frames[0].c2w
        anchor = lambda k: float(np.linalg.norm(frames[k].c2w[:3, 3] - g0[:3, 3]))  # noqa: E731
        i = 0
        while i < len(frames) and not fe.initialized and not fe.failed:
            fe.bootstrap(i, frames[i].rgb, g0, anchor)
            i += 1
        if not fe.initialized:
            return {"error": f"bootstrap failed within {i} frames"}
        wall, est, lost, plain = [], {}, 0, []
        spent.update(klt=0.0, direct=0.0)
        for j in range(i, len(frames)):
            t = time.perf_counter()
            r = fe.track(j, frames[j].rgb)
            wall.append((time.perf_counter() - t) * 1e3)
            plain.append(not r.need_keyframe)
            est[j] = r.c2w
            lost += int(r.lost)
        fe.final_ba()
        est.update(fe.poses())
    finally:
        fe_mod.klt_track_gain = klt
    ids = sorted(est)
    a = ate(np.stack([est[k] for k in ids]), np.stack([frames[k].c2w for k in ids]), align="sim3")
    ba_ms = [b["ms"] for b in fe.ba_stats]
    w = np.asarray(wall)
    plain = np.asarray(plain, bool)
    from mono_only import keyframe_scales
    return {"ate_sim3_cm": round(100 * a["rmse_m"], 3), "scale": round(a["scale"], 4),
            "map_scale_spread": keyframe_scales(fe, depth)["spread"] if depth is not None else None, "lost": lost,
            "keyframes": len(fe.store.kf_pose), "loops": len(fe.loops),
            "ba_count": len(ba_ms), "ba_ms_sum": round(float(np.sum(ba_ms)), 1),
            "ba_ms_median": round(float(np.median(ba_ms)), 1) if ba_ms else None,
            "ba_nfev_mean": round(float(np.mean([b["nfev"] for b in fe.ba_stats])), 2) if ba_ms else None,
            "frame_ms_median": round(float(np.median(w)), 2), "frame_ms_mean": round(float(w.mean()), 2),
            "frame_ms_p95": round(float(np.percentile(w, 95)), 2),
            # frames that did not become keyframes: a keyframe's BA is off the frame path at a camera's rate
            "plain_ms_median": round(float(np.median(w[plain])), 2) if any(plain) else None,
            "plain_ms_p95": round(float(np.percentile(w[plain], 95)), 2) if any(plain) else None,
            "frames_pnp": int(getattr(fe, "frames_pnp", 0)),
            "klt_ms_per_frame": round(1e3 * spent["klt"] / len(w), 2),
            "direct_ms_per_frame": round(1e3 * spent["direct"] / len(w), 2)}


def datasets(args) -> list[tuple[str, Path, "str | None"]]:
    """(name, folder, camera argument) of the data sets to run."""
    from tracking import tum_camera_arg

    if args.data:
        return [(Path(d).name, Path(d), None) for d in args.data]
    from fmapping.synthetic import generate_scene

    out = []
    for seed in args.seeds:
        d = Path(args.work) / f"synth_s{seed}_f200_320x240"
        if not (d / "scene.json").exists():
            generate_scene(d, seed=seed, frames=200, size=(320, 240))
        out.append((f"synth_s{seed}", d, None))
    tum = SHARED / "tum_fr1_rpy"
    if tum.is_dir():
        out.append(("tum_fr1_rpy", tum, tum_camera_arg(tum)))
    kitchen = SHARED / "7scenes_redkitchen_dev"
    if kitchen.is_dir():
        out.append(("7scenes_dev", kitchen, None))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="*", default=[], help="name:key=value;key=value (see the docstring)")
    ap.add_argument("--data", nargs="*", default=None, help="data folders (default: see the docstring)")
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    ap.add_argument("--work", default="/tmp/fmapping_bench_mono_variants")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "mono_variants.json"))
    args = ap.parse_args()
    from fmapping.datasets import open_dataset
    from fmapping.ply import read_ply
    from fmapping.runtime import limit_blas_threads, retain_freed_memory
    from mono_only import gt_depth_source

    torch.set_num_threads(args.threads)
    retain_freed_memory()
    limit_blas_threads(1)  # as the tracker service
    variants = [("base", "")] + [(v.partition(":")[0], v.partition(":")[2]) for v in args.variants]
    configs = {name: make_configs(spec) for name, spec in variants}  # a typo fails before any run
    res = {"machine": {"platform": platform.platform(), "cpu": platform.processor() or platform.machine()},
           "variants": dict(variants), "runs": {}}
    for name, folder, cam in datasets(args):
        ds = open_dataset(folder, camera=cam)
        frames = [ds[k] for k in range(len(ds))]
        surface = Path(folder) / "gt_points.ply"
        depth = gt_depth_source(frames, ds.camera, read_ply(surface).points if surface.exists() else None)
        for v, _ in variants:
            r = run(frames, ds.camera, *configs[v], depth=depth)
            res["runs"].setdefault(name, {})[v] = r
            print(f"{name:14s} {v:10s} " + ("  ".join(f"{k} {x}" for k, x in r.items())), flush=True)
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
