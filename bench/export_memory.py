"""Memory of the end of a run: resident size and high-water mark around each export stage of ``fmapping slam``.

    python bench/export_memory.py                       # the first 300 frames of bench/long_run.py's room
    python bench/export_memory.py --data DATASET --frames 300

Runs ``fmapping slam`` (RGB only, export on) in this process with the export stages wrapped: for each of
``write_map_outputs``, ``export_point_cloud``, ``export_mesh`` and the map scores it prints ``VmRSS`` before
and after and the process's high-water mark (``ru_maxrss``) before and after, and writes them as JSON
(``--out``). The high-water mark only grows, so a stage that does not raise it stayed under the peak before it.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from long_run import long_room, rss_mb  # noqa: E402  (bench/long_run.py: its room and its RSS reading)


def high_water_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="a dataset folder (default: bench/long_run.py's generated "
                    "1,000-frame room, generated here when missing)")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "export_memory" / "export_memory.json"))
    a = ap.parse_args(argv)

    import torch

    import fmapping.export as export
    import fmapping.slam.job as slam_job
    from fmapping.job import Job

    torch.set_num_threads(a.threads)
    if a.data is None:
        a.data = str(long_room(Path(tempfile.gettempdir()) / "fmapping_bench_long"))  # long_run.py's default work
    stages: list[dict] = []

    def wrap(mod, name: str) -> None:
        inner = getattr(mod, name)

        def timed(*args, **kw):
            r0, h0, t0 = rss_mb(), high_water_mb(), time.perf_counter()
            out = inner(*args, **kw)
            row = {"stage": f"{mod.__name__}.{name}", "rss_mb": [round(r0), round(rss_mb())],
                   "high_water_mb": [round(h0), round(high_water_mb())], "seconds": round(time.perf_counter() - t0, 1)}
            stages.append(row)
            print(f"[mem] {row['stage']}: rss {row['rss_mb'][0]} -> {row['rss_mb'][1]} MB, high-water "
                  f"{row['high_water_mb'][0]} -> {row['high_water_mb'][1]} MB, {row['seconds']} s", flush=True)
            return out
        setattr(mod, name, timed)

    for name in ("export_point_cloud", "export_mesh"):  # looked up in fmapping.export at call time
        wrap(export, name)
    for name in ("write_map_outputs", "recon_stats"):  # imported into fmapping.slam.job by name
        wrap(slam_job, name)
    with tempfile.TemporaryDirectory() as tmp:
        slam_job.run_slam(Job(data=a.data, out=tmp, poses="photometric", config=None, device="auto",
                              max_frames=a.frames, export=True, quiet=True))
    res = {"data": a.data, "frames": a.frames, "threads": a.threads, "stages": stages,
           "rss_mb_end": round(rss_mb()), "high_water_mb_end": round(high_water_mb())}
    print(f"[mem] end: rss {res['rss_mb_end']} MB, high-water {res['high_water_mb_end']} MB")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
