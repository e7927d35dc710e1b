"""Long runs: does ``fmapping slam`` stay flat in memory and in window time over 1,000 frames?

    python bench/long_run.py --synth-frames 1000                 # a synthetic room walk, 320x240
    python bench/long_run.py --data ../shared/data/7scenes_redkitchen_long --max-frames 700

Runs the library's SLAM loop (:func:`fmapping.slam.run_slam`, RGB only, mono front end) in this process
and, after every mapping window, records the process's resident memory (``VmRSS``), the window's seconds
and what the long-lived containers hold: the mapper's kept images (local window + keyframes) and their
bytes, its keyframes, the front end's keyframes and landmarks, the triangulated points. Prints a table per
group of ``--group`` windows and writes ``bench/results/long_run.json`` (``--out``).

Targets (issue 18): RSS flat to within 10 % from frame 200 to the end; window time not growing with the
sequence length (median per group of 24 windows).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
import report  # noqa: E402  (bench/report.py: the machine line)


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def long_room(work: Path, seed: int = 0, frames: int = 1000, size: tuple = (320, 240)) -> Path:
    """The generated room of the long run in ``work`` (made when missing; ``bench/export_memory.py`` uses it too)."""
    from fmapping.synthetic import generate_scene

    data = work / f"synth_s{seed}_f{frames}_{size[0]}x{size[1]}"
    if not (data / "scene.json").is_file():
        t = time.perf_counter()
        print(f"[long] generating {data} ...", flush=True)
        generate_scene(data, seed=seed, frames=frames, size=size, max_cloud_points=20000)
        print(f"[long] generated in {time.perf_counter() - t:.0f} s", flush=True)
    return data


def holdings(run) -> dict:
    """What the long-lived containers of a :class:`fmapping.slam.SlamRun` hold now."""
    out: dict = {}
    m = run.mapper
    if m is not None:
        out["mapper_images"] = len(m._images)
        out["mapper_image_mb"] = round(m._images.nbytes() / 2 ** 20, 1)
        out["mapper_keyframes"] = len(m.keyframe_ids())
        out["mapper_frames"] = len(m._poses)
        if m._sparse is not None:
            out["sparse_points"] = int(len(m._sparse.points))
    fe = getattr(run, "frontend", None)
    if fe is not None:
        st = fe.store
        out["frontend_keyframes"] = len(st.kf_pose)
        out["frontend_landmarks"] = len(st.lm)
        out["frontend_observations"] = len(st.obs)
        out["frontend_frames"] = len(st.rel)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="a dataset folder (default: a generated synthetic room)")
    ap.add_argument("--synth-frames", type=int, default=1000)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--group", type=int, default=24, help="windows per row of the table")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "fmapping_bench_long"))
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "long_run.json"))
    a = ap.parse_args(argv)

    import torch

    from fmapping.job import Job
    from fmapping.slam import run as slam_run
    from fmapping.slam.job import run_slam

    torch.set_num_threads(a.threads)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    if a.data:
        data = Path(a.data)
    else:
        data = long_room(work, a.seed, a.synth_frames, tuple(int(v) for v in a.size.lower().split("x")))
    rows: list[dict] = []
    t0 = time.perf_counter()
    orig = slam_run.SlamRun._on_window

    def on_window(self, d: dict) -> None:
        orig(self, d)
        rows.append({"after_frame": int(d.get("after_frame", -1)), "kind": d.get("kind"),
                     "seconds": round(float(d.get("seconds", 0.0)), 3), "rss_mb": round(rss_mb(), 1),
                     "t": round(time.perf_counter() - t0, 1), **holdings(self)})
        if len(rows) % a.group == 0:
            r = rows[-1]
            print(f"[long] window {len(rows)} after frame {r['after_frame']}: {r['seconds']:.2f} s, RSS "
                  f"{r['rss_mb']:.0f} MB, {json.dumps({k: v for k, v in r.items() if k not in ('t', 'kind')})}",
                  flush=True)

    slam_run.SlamRun._on_window = on_window
    out_dir = work / "slam_out"
    args = argparse.Namespace(data=str(data), out=str(out_dir), max_frames=a.max_frames, quiet=True)
    job = Job.from_args(args, poses="photometric")
    rss0 = rss_mb()
    try:
        stats = run_slam(job)
    finally:
        slam_run.SlamRun._on_window = orig
    groups = []
    wins = [r for r in rows if r["kind"] == "window"]
    for g in range(0, len(wins), a.group):
        chunk = wins[g:g + a.group]
        groups.append({"windows": f"{g + 1}-{g + len(chunk)}", "frames": f"..{chunk[-1]['after_frame']}",
                       "window_s_median": round(float(np.median([r["seconds"] for r in chunk])), 3),
                       "window_s_min": round(float(np.min([r["seconds"] for r in chunk])), 3),
                       "rss_mb_max": max(r["rss_mb"] for r in chunk),
                       "mapper_image_mb": chunk[-1].get("mapper_image_mb")})
    at200 = next((r["rss_mb"] for r in rows if r["after_frame"] >= 200), None)
    end = rows[-1]["rss_mb"] if rows else None
    res = {"machine": {"cpu": report.cpu_model(), "cpus": os.cpu_count(),
                       "loadavg_at_end": [round(x, 2) for x in os.getloadavg()]},
           "settings": {"data": str(data), "max_frames": a.max_frames, "threads": a.threads},
           "rss_mb_start": round(rss0, 1), "rss_mb_at_frame_200": at200, "rss_mb_end": end,
           "rss_growth_from_frame_200_pct": round(100 * (end - at200) / at200, 1) if at200 and end else None,
           "rss_mb_peak_at_windows": max((r["rss_mb"] for r in rows), default=None),
           # the process's high-water mark, the closing refinement and the export (map.ply, mesh.ply) included
           "rss_mb_high_water": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
           "rss_mb_after_export": round(rss_mb(), 1),
           "groups": groups, "summary": stats.get("summary"), "windows": rows,
           "seconds": round(time.perf_counter() - t0, 1)}
    for g in groups:
        print(f"[long] windows {g['windows']} (frames {g['frames']}): median {g['window_s_median']:.2f} s, "
              f"min {g['window_s_min']:.2f} s, RSS max {g['rss_mb_max']:.0f} MB, mapper images "
              f"{g['mapper_image_mb']} MB", flush=True)
    print(f"[long] RSS at frame 200 {at200} MB, at the end {end} MB ({res['rss_growth_from_frame_200_pct']} %), "
          f"peak at windows {res['rss_mb_peak_at_windows']} MB, high-water mark {res['rss_mb_high_water']} MB (export "
          f"included)", flush=True)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1, default=str) + "\n")
    print(f"[long] wrote {out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
