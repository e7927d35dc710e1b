"""The tracker service's core fed at a camera's rate in this process, beside a busy core: pose latency per frame,
side by side for front-end variants.

    python bench/tracker_realtime.py                                     # the defaults, 3 rounds
    python bench/tracker_realtime.py --variants "wait:loop_ba_defer_frames=0" --rounds 5
    python bench/tracker_realtime.py --variants "direct:frame_pose='direct'"   # every frame aligned first
    python bench/tracker_realtime.py --variants "loop_sync:loop_thread=False"   # the loop search on the frame path
    python bench/tracker_realtime.py --variants "kf_first:service.keyframe_after_pose=False"   # keyframe work first

What ``fmapping up`` does around the tracker, without the other services: a player thread puts frame k and its GT
anchor pose into the tracker's bounded inbox (:class:`services.core_support.Inbox`) at k / ``--fps`` seconds
whether the tracker is ready or not; the main thread runs the tracker shell's loop (``services.tracker``: take the
next message, :meth:`TrackerCore.apply`), with the keyframe bundle adjustment in its worker thread (``--ba-thread
on``, as at a camera's rate), the service's camera-rate ``--frame-pose pnp`` and its skip rule. ``--load``
processes spin a one-thread torch loop meanwhile, standing in for the mapper. A frame's latency is from its
arrival in the inbox to the tracker's first answer for it (as ``bench/system.py`` measures between processes,
without the transport and the other services' CPU). "once tracking": frames that arrived after the first pose came
out (the bootstrap and the late anchor hold the first ~15 frames' poses by design).

A variant is ``name:key=value;key=value`` as in ``bench/mono_variants.py``: ``MonoConfig`` fields (``klt.*`` /
``loop.*`` of its parts), ``tracker.*`` of the ``TrackerConfig``, ``service.*`` of the tracker service's
``TrackerServiceOptions`` (values are Python literals). The variants
run in turn within each round, so that the CPU's swings fall on all.
Per run: latency median / p95 / max once tracking, per-message wall time of ``apply`` (median / p95 / max),
frames tracked / answered untracked, keyframes deferred, the Sim3 ATE of the final poses (the bundle
adjustment's timing differs from run to run, so the poses do too) and the slowest frames. Writes ``--out``.
"""
from __future__ import annotations

import argparse
import ast
import json
import multiprocessing as mp
import platform
import sys
import threading
import time
from typing import Optional
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def spin(stop, nice: int = 0) -> None:
    """A busy core: a one-thread torch loop (the mapper's kind of load) at CPU priority ``nice`` until ``stop``
    is set."""
    import os

    import torch

    if nice > 0:
        os.nice(nice)
    torch.set_num_threads(1)
    a = torch.randn(256, 256)
    while not stop.is_set():
        for _ in range(50):
            a = torch.tanh(a @ a * 0.01)


def encode_stream(ds) -> tuple[list[bytes], list[bytes]]:
    from fmapping import protocol as P

    frames = [P.encode(P.frame_from_dataset(ds[k], seq=k, with_depth=False)) for k in range(len(ds))]
    gts = [P.encode(P.Pose(seq=k, timestamp=float(ds[k].timestamp), c2w=np.asarray(ds[k].c2w, np.float64),
                           source="gt")) for k in range(len(ds))]
    return frames, gts


SERVICE_FRAME_POSE = "pnp"  # what the tracker service's CLI runs at a camera's rate (services.tracker --frame-pose)


def run_once(frames: list, gts: list, gt_c2w: list, mono, trk, fps: float, tail_s: float = 3.0,
             options: Optional[dict] = None) -> dict:
    """One playback at ``fps`` through a fresh tracker core (see the module docstring)."""
    from fmapping import protocol as P
    from fmapping.metrics import ate
    from services.core_support import Counters, Inbox
    from services.tracker.core import TrackerCore, TrackerServiceOptions

    counters = Counters()
    inbox = Inbox({"end": 8, "poses": 8192, "frames": 64}, counters, thin=("frames",))  # the service's bounds
    opts = TrackerServiceOptions(ba_thread=True, loop_thread=mono.loop_thread, **(options or {}))
    core = TrackerCore(trk, opts, counters=counters, mono_cfg=mono)
    core.backlog = lambda: inbox.size("frames")
    core.stream_idle = lambda: inbox.idle("frames")
    t_in: dict = {}

    def player() -> None:
        t0 = time.monotonic()
        for k in range(len(frames)):
            wait = t0 + k / fps - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            t_in[k] = time.monotonic()
            inbox.put("poses", ("poses/gt", core.admit("poses", gts[k], "poses/gt")))
            inbox.put("frames", ("frames", core.admit("frames", frames[k], "frames")))
        time.sleep(tail_s)  # then the end of the stream
        inbox.put("end", ("end", P.Control("stop", {"reason": "end"})))

    th = threading.Thread(target=player, name="player", daemon=True)
    th.start()
    t_out, usable, final, applies = {}, {}, {}, []
    while True:
        item = inbox.get(timeout=0.1)
        if item is None:
            continue
        channel, (_, msg) = item
        t0 = time.perf_counter()
        out = core.apply(msg)
        now = time.monotonic()
        for stage in (out, core.finish_frame()):  # as the shell: a keyframe's work after its pose went out
            for _, p in stage:
                good = p.quality is None or p.quality > 0
                if good:
                    final[p.seq] = np.array(p.c2w)
                if p.seq not in t_out:
                    t_out[p.seq], usable[p.seq] = now, good
            now = time.monotonic()
        ms = (time.perf_counter() - t0) * 1e3
        if channel == "frames":
            applies.append((msg.seq, ms))
        if channel == "end":
            break
    th.join()
    fe = core.session.frontend
    bg = getattr(fe, "_bg", None)
    core.close()
    first = min(t_out.values())
    steady = np.array([t_out[k] - t_in[k] for k in t_out if k in t_in and t_in[k] > first])
    ms = np.array([m for _, m in applies])
    ks = sorted(final)
    err = ate(np.stack([final[k] for k in ks]), np.stack([gt_c2w[k] for k in ks]))
    return {
        "latency_s_once_tracking": {"median": float(np.median(steady)), "p95": float(np.percentile(steady, 95)),
                                    "max": float(steady.max()), "n": int(len(steady))},
        "apply_ms": {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "max": float(ms.max())},
        "tracked": int(counters.get("frames_tracked")), "untracked": int(counters.get("frames_skipped")),
        "lost": int(counters.get("frames_lost")), "keyframes_deferred": int(getattr(fe, "keyframes_deferred", 0)),
        "loops": len(fe.loops),
        "ba_submitted": None if bg is None else bg.submitted, "ba_waited": None if bg is None else bg.waited,
        "ate_sim3_cm": round(100 * err["rmse_m"], 3), "posed": len(ks),
        "slowest_frames": [[int(s), round(m, 1)] for s, m in sorted(applies, key=lambda x: -x[1])[:8]],
        "latency_s_per_frame": {int(k): round(t_out[k] - t_in[k], 4) for k in sorted(t_out) if k in t_in},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None,
                    help="a dataset folder (default: the synthetic room, seed 0, made in --work)")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--load", type=int, default=1, help="busy one-thread processes beside the tracker (the mapper)")
    ap.add_argument("--load-nice", type=int, default=0,
                    help="their nice increment (fmapping up runs the mapper at 5: services.launcher.supervise.NICE)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--variants", nargs="*", default=[], help="name:key=value;... (see the docstring)")
    ap.add_argument("--work", default="/tmp/fmapping_bench_tracker_realtime")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "tracker_realtime.json"))
    a = ap.parse_args(argv)

    import torch

    from fmapping.datasets import open_dataset
    from fmapping.runtime import limit_blas_threads, retain_freed_memory, single_malloc_arena
    from mono_variants import make_configs
    from report import cpu_model

    torch.set_num_threads(1)  # as the tracker service
    limit_blas_threads(1)
    retain_freed_memory()
    single_malloc_arena()
    data = Path(a.data) if a.data else None
    if data is None:
        from fmapping.synthetic import generate_scene

        w, h = (int(x) for x in a.size.split("x"))
        data = Path(a.work) / f"synth_s0_f{a.frames}_{a.size}"
        if not (data / "gt_visible_cloud.ply").exists():  # (written last by generate_scene)
            generate_scene(data, seed=0, frames=a.frames, size=(w, h))
    ds = open_dataset(data)
    frames, gts = encode_stream(ds)
    gt_c2w = [np.asarray(ds[k].c2w, np.float64) for k in range(len(ds))]
    variants = [("base", "")] + [tuple(v.split(":", 1)) if ":" in v else (v, "") for v in a.variants]
    # (MonoConfig, TrackerConfig); the service's own camera-rate choice first (services.tracker --frame-pose), then
    # the variant's settings
    service = f"frame_pose={SERVICE_FRAME_POSE!r};ba_thread=True;loop_thread=True"
    configs = {name: make_configs(f"{service};" + ";".join(x for x in spec.split(";") if not x.startswith("service.")))
               for name, spec in variants}
    # TrackerServiceOptions fields as "service.<field>=<literal>"
    options = {name: {x.split("=", 1)[0][8:]: ast.literal_eval(x.split("=", 1)[1]) for x in spec.split(";")
                      if x.startswith("service.")} for name, spec in variants}
    stop = mp.Event()
    load = [mp.Process(target=spin, args=(stop, a.load_nice), daemon=True) for _ in range(a.load)]
    for p in load:
        p.start()
    runs: dict = {name: [] for name, _ in variants}
    try:
        time.sleep(1.0)
        for r in range(a.rounds):
            for name, _ in variants:
                res = run_once(frames, gts, gt_c2w, *configs[name], a.fps, options=options[name])
                runs[name].append(res)
                lat, ms = res["latency_s_once_tracking"], res["apply_ms"]
                print(f"round {r + 1} {name:12s} latency median / p95 / max {lat['median']:.3f} / {lat['p95']:.3f} / "
                      f"{lat['max']:.3f} s  apply ms median / p95 {ms['median']:.1f} / {ms['p95']:.1f}  tracked "
                      f"{res['tracked']} untracked {res['untracked']} lost {res['lost']} deferred "
                      f"{res['keyframes_deferred']} BAs {res['ba_submitted']} waited for {res['ba_waited']}  Sim3 ATE "
                      f"{res['ate_sim3_cm']:.2f} cm  slowest "
                      f"{res['slowest_frames'][:3]}", flush=True)
    finally:
        stop.set()
        for p in load:
            p.join(timeout=5)
    summary = {}
    for name, rs in runs.items():
        col = lambda f: [f(x) for x in rs]  # noqa: E731
        summary[name] = {k: {"min": float(np.min(v)), "median": float(np.median(v)), "max": float(np.max(v))}
                         for k, v in (("latency_p95_s", col(lambda x: x["latency_s_once_tracking"]["p95"])),
                                      ("latency_max_s", col(lambda x: x["latency_s_once_tracking"]["max"])),
                                      ("latency_median_s", col(lambda x: x["latency_s_once_tracking"]["median"])),
                                      ("ate_sim3_cm", col(lambda x: x["ate_sim3_cm"])))}
        s = summary[name]
        print(f"{name:12s} over {len(rs)} runs: latency p95 median {s['latency_p95_s']['median']:.3f} s "
              f"({s['latency_p95_s']['min']:.3f}-{s['latency_p95_s']['max']:.3f}), max median "
              f"{s['latency_max_s']['median']:.3f} s, Sim3 ATE median {s['ate_sim3_cm']['median']:.2f} cm "
              f"({s['ate_sim3_cm']['min']:.2f}-{s['ate_sim3_cm']['max']:.2f})")
    out = {"machine": {"platform": platform.platform(), "cpu": cpu_model(), "cpus": mp.cpu_count()},
           "settings": {k: v for k, v in vars(a).items() if k != "out"} | {"data": str(data)},
           "variants": dict(variants), "summary": summary, "runs": runs}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
