"""Collect ``bench/results/*.json`` into one Markdown summary and the README's benchmark section.

    python bench/report.py            # writes bench/results/summary.md and updates README.md
    python bench/report.py --no-readme

Each benchmark writes its own JSON (and, for mapping and system, its own PNG); this script
only reads them. Missing results are listed as "not run", never invented. The README keeps
the table between the markers ``<!-- bench:begin -->`` and ``<!-- bench:end -->``; the
machine line is read off the machine that runs this script, and every table names the JSON
it came from (each JSON records its own settings and timestamps).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
BEGIN, END = "<!-- bench:begin -->", "<!-- bench:end -->"


def load(name: str) -> Optional[dict]:
    p = RESULTS / f"{name}.json"
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise SystemExit(f"{p}: not valid JSON ({e})") from e


def fmt(x, nd: int = 2, unit: str = "") -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        if x != x or x in (float("inf"), float("-inf")):
            return str(x)
        return f"{x:.{nd}f}{unit}"
    return f"{x}{unit}"


def table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> str:
    cpu = cpu_model()
    mem = ""
    try:
        kb = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text()).group(1))
        mem = f", {kb / 2**20:.0f} GiB RAM"
    except (OSError, AttributeError):
        pass
    try:
        import torch

        tv = f", torch {torch.__version__}"
    except ImportError:  # pragma: no cover - the venv has torch
        tv = ""
    return f"{cpu}, {os.cpu_count()} cores{mem}, no GPU, Python {platform.python_version()}{tv}"


def mapping_section() -> str:
    d = load("mapping")
    if d is None:
        return "### Mapping (`bench/mapping.py`)\n\nnot run\n"
    s = d["settings"]
    out = ["### Mapping (`bench/mapping.py` -> `mapping.json`, `mapping.png`)\n",
           f"Synthetic rooms, {s['frames']} frames {s['size'][0]}x{s['size'][1]}, RGB only, GT poses, "
           f"{s['threads']} torch thread(s). Quality against the visible GT cloud (5 cm threshold). "
           "Targets: completion ratio >= 90 %, accuracy <= 5 cm, completion <= 3 cm, window update <= 2.0 s.\n"]
    inter = d.get("interleaved_window_seconds", {})
    rows = []
    for name, v in d["variants"].items():
        for r in v["runs"]:
            t = inter.get(name) if r["seed"] == s["compare_seeds"][0] else None
            rows.append([name, r["seed"], f"{r['parameters']:,}", fmt(r["completion_ratio"], 1, " %"),
                         fmt(r["accuracy_cm"]), fmt(r["completion_cm"]), fmt(r.get("psnr_heldout"), 1),
                         f"{fmt(r['window_seconds_min'])} / {fmt(r['window_seconds_median'])}",
                         f"{fmt(t['min'])} / {fmt(t['median'])}" if t else "-",
                         fmt(r.get("init_seconds"), 0), fmt(r.get("export_seconds"), 0)])
    for extra in ("mapping_fields", "mapping_variants"):
        e = load(extra)
        if e is None:
            continue
        ei = e.get("interleaved_window_seconds", {})
        for name, v in e["variants"].items():
            if extra == "mapping_variants" and name == "cp":
                continue  # the same CP run as in mapping.json
            for r in v["runs"]:
                t = ei.get(name)
                rows.append([f"{name} ({extra}.json)", r["seed"], f"{r['parameters']:,}",
                             fmt(r["completion_ratio"], 1, " %"), fmt(r["accuracy_cm"]), fmt(r["completion_cm"]),
                             fmt(r.get("psnr_heldout"), 1),
                             f"{fmt(r['window_seconds_min'])} / {fmt(r['window_seconds_median'])}",
                             f"{fmt(t['min'])} / {fmt(t['median'])}" if t else "-",
                             fmt(r.get("init_seconds"), 0), fmt(r.get("export_seconds"), 0)])
    out.append(table(["variant", "seed", "params", "compl. ratio", "acc. cm", "compl. cm", "PSNR dB",
                      "window s min / med (in run)", "window s min / med (interleaved)", "init s", "export s"],
                     rows))
    sp = load("mapping_speed")
    if sp:
        out.append(f"\nWindow update of the CP default (`bench/mapping.py --speed` -> `mapping_speed.json`; "
                   f"{sp['iters_per_window']} iterations x {sp['rays_per_iter']} rays x {sp['samples_per_ray']} "
                   f"samples, {sp['window_frames']}-frame window, after mapping {sp['frames_mapped']} frames): " +
                   "; ".join(f"{t} thread(s) {fmt(v['min'])} / {fmt(v['median'])} s (min / median)"
                             for t, v in sp["seconds"].items()) + ".\n")
    out.append("\nThe in-run window times share the CPU with whatever else ran; the interleaved column "
               "times every variant's window update round-robin in one process after the runs.\n")
    real = load("mapping_real")
    if real:
        rows = []
        if "tum_fr1_rpy" in real:
            t = real["tum_fr1_rpy"]
            rows.append(["TUM fr1_rpy (GT poses, RGB only)", f"{t['frames']} frames",
                         f"held-out PSNR {fmt(t['psnr_heldout'], 1)} dB",
                         f"{fmt(t.get('window_seconds_min'))} / {fmt(t.get('window_seconds_median'))}"])
        if "lego" in real:
            t = real["lego"]
            rows.append(["NeRF lego", f"{t['train_views']} train / {t['test_views']} test views",
                         f"novel-view PSNR {fmt(t['psnr_novel_views'], 1)} dB", "-"])
        out.append("Real data (`bench/mapping.py --real-data` -> `mapping_real.json`):\n")
        out.append(table(["data", "frames", "quality", "window s min / med"], rows))
    return "\n".join(out) + "\n"


def tracking_section() -> str:
    d = load("tracking")
    if d is None:
        return "### Tracking (`bench/tracking.py`)\n\nnot run\n"
    out = ["### Tracking (`bench/tracking.py` -> `tracking.json`)\n",
           "Same frames for every method. ATE RMSE in cm after SE3 / Sim3 alignment; rotation error is the "
           "mean per-frame angle, with the trajectory anchored at the first GT pose and after the best-fit "
           "rotation between the two trajectories' orientations. "
           "Targets: >= 15 fps at 320x240; TUM RGB only SE3 <= 2 cm and rotation <= 1 deg.\n"]
    rows = []
    for data_name, block in d.items():
        if not isinstance(block, dict) or "frames" not in block:
            continue
        for method, r in block.items():
            if not isinstance(r, dict) or "ate" not in r:
                continue
            a = r["ate"]
            rows.append([data_name, method, fmt(r.get("fps_median"), 1), fmt(r.get("fps_mean"), 1),
                         fmt(r.get("ms_median"), 1),
                         fmt(a["se3"]["rmse_m"] * 100), fmt(a["sim3"]["rmse_m"] * 100),
                         fmt(a["se3"].get("rot_first_mean_deg", a["none"].get("rot_err_mean_deg"))),
                         fmt(a["se3"].get("rot_fit_mean_deg")), r.get("lost", "-")])
    out.append(table(["data", "method", "fps (median)", "fps (mean, with BA)", "ms median", "ATE SE3 cm",
                      "ATE Sim3 cm", "rot. err deg (from first GT pose)", "rot. err deg (best-fit rotation)", "lost"],
                     rows))
    for data_name, block in d.items():
        pc = block.get("pose_consistency") if isinstance(block, dict) else None
        if pc:
            out.append(f"\nPose consistency with the images, {data_name} (KLT tracks between consecutive frames "
                       "against the dataset depth moved by the poses; median px over the frame pairs): "
                       + ", ".join(f"{k} {fmt(v['median_px'])} px" for k, v in pc.items()) + ".")
        off = block.get("gt_camera_offset") if isinstance(block, dict) else None
        if off and "xyz" in off:
            fit = lambda v: "(" + ", ".join(fmt(c) for c in v) + ") deg"  # noqa: E731
            out.append(f"GT camera frame against the images, {data_name} (tracks {off['steps']} frames long): "
                       f"the GT explains them to {fmt(off['gt_px'])} px, rotated by {fit(off['xyz']['rotvec_deg'])} "
                       f"to {fmt(off['xyz']['px_after'])} px (halves of the pairs: "
                       + ", ".join(fit(h) for h in off['xyz']['halves_rotvec_deg']) + "); "
                       f"the GT so rotated scores {fmt(off['xyz']['floor_rot_first_mean_deg'])} "
                       f"deg from the first GT pose and {fmt(off['xyz']['floor_rot_fit_mean_deg'])} deg best-fit "
                       f"(x and z only: {fmt(off['xz']['floor_rot_first_mean_deg'])} / "
                       f"{fmt(off['xz']['floor_rot_fit_mean_deg'])} deg).")
        opt = block.get("images_optimum") if isinstance(block, dict) else None
        if opt and opt.get("starts"):
            parts = []
            for start, r in opt["starts"].items():
                o = r["optimum"]
                txt = (f"from {start}: Sim3 {fmt(o['sim3']['rmse_m'] * 100)} cm, rotation "
                       f"{fmt(o['none']['rot_first_mean_deg'])} deg from the first GT pose / "
                       f"{fmt(o['none']['rot_fit_mean_deg'])} deg best-fit, {fmt(r['median_px'])} px median")
                if "anchored" in r:
                    txt += (f", SE3 {fmt(r['anchored']['se3']['rmse_m'] * 100)} cm with the scale of the GT baseline "
                            f"to frame {r['anchored']['frame']}")
                if "apart_from_first" in r:
                    a = r["apart_from_first"]
                    txt += (f", {fmt(a['sim3_rmse_m'] * 100)} cm / {fmt(a['rot_first_mean_deg'])} deg from the "
                            "first start's optimum")
                parts.append(txt)
            out.append(f"The trajectory the images determine, {data_name} (global bundle adjustment of all "
                       f"{block.get('frames', '?')} frames on {opt['tracks']} KLT tracks, reprojection error only): "
                       + "; ".join(parts) + ".")
            rs = opt.get("rolling_shutter") or {}
            if rs:
                start = next(iter(opt["starts"]))
                cells = [f"0 (global shutter): cost {fmt(opt['starts'][start]['cost'], 0)}"]
                for readout, r in rs.items():
                    o = r["optimum"]
                    se3 = fmt(r["anchored"]["se3"]["rmse_m"] * 100) if "anchored" in r else "-"
                    cells.append(f"{readout}: cost {fmt(r['cost'], 0)}, Sim3 {fmt(o['sim3']['rmse_m'] * 100)} cm, "
                                 f"SE3 (anchored) {se3} cm, "
                                 f"rotation {fmt(o['none']['rot_first_mean_deg'])} / "
                                 f"{fmt(o['none']['rot_fit_mean_deg'])} deg")
                out.append(f"The same from {start} with the tracks unrolled for a rolling shutter, by readout "
                           "(fraction of the frame interval): " + "; ".join(cells)
                           + f". The images prefer {opt['best_readout']}.")
    spreads = (("mono_spread", "Mono"), ("mono_rolling_shutter_spread", "Mono with the rolling shutter"))
    for data_name, block in d.items():
        for key, what in spreads:
            sp = block.get(key) if isinstance(block, dict) else None
            if not (sp and "se3_cm" in sp):
                continue
            rng = lambda k, u: f"{fmt(sp[k]['median'])} {u} ({fmt(sp[k]['min'])}-{fmt(sp[k]['max'])})"  # noqa: E731
            out.append(f"{what}, {data_name}, over {sp['runs']} runs (the frames as they are and with "
                       f"{sp['perturbation']}), median (min-max): SE3 {rng('se3_cm', 'cm')}, "
                       f"Sim3 {rng('sim3_cm', 'cm')}, rotation from the first GT pose {rng('rot_first_deg', 'deg')}, "
                       f"best-fit {rng('rot_fit_deg', 'deg')}.")
    al = d.get("ba_allocator")
    if al and "glibc_default" in al:
        out.append("\nMono front end, synthetic, allocator (`fmapping.runtime`): mean ms per frame "
                   f"{fmt(al['glibc_default'].get('ms_mean'), 1)} "
                   f"(BA median {fmt(al['glibc_default'].get('ba_ms_median'), 0)} ms) "
                   f"with glibc's default, {fmt(al['retain_freed_memory'].get('ms_mean'), 1)} "
                   f"(BA {fmt(al['retain_freed_memory'].get('ba_ms_median'), 0)} ms) with freed memory retained.")
    return "\n".join(out) + "\n"


def slam_section() -> str:
    d = load("slam")
    if d is None:
        return "### SLAM loop (`bench/slam.py`)\n\nnot run\n"
    st = d.get("settings", {})
    size = "x".join(str(v) for v in st.get("size", []))
    rows = []
    for seed, r in d["runs"].items():
        cm = lambda k: fmt(r[k] * 100) if r.get(k) is not None else "-"  # noqa: E731
        pct = lambda k: fmt(r.get(k), 1, " %") if r.get(k) is not None else "-"  # noqa: E731
        rows.append([seed, cm("ate_sim3_rmse_m"), cm("ate_se3_rmse_m"), cm("ate_none_rmse_m"),
                     fmt(r.get("ate_rot_fit_deg")), r.get("tracking_loss_events"), r.get("loop_closures", "-"),
                     pct("completion_ratio"), fmt(r.get("accuracy_cm")), pct("completion_ratio_sim3"),
                     fmt(r.get("accuracy_cm_sim3")), fmt(r.get("completion_cm_sim3"))])
    return "\n".join([
        "### SLAM loop (`bench/slam.py` -> `slam.json`)\n",
        f"`fmapping slam` RGB only on synthetic rooms ({st.get('frames')} frames, {size}), one run per seed, "
        f"run {d.get('date', '')}; scale anchored by the GT baseline of the bootstrap and again at frame 14; "
        "loops closed back at an old keyframe. Map scores against the "
        "visible GT cloud (5 cm), unaligned and after the trajectory's Sim3. "
        "Targets: Sim3 ATE <= 2 cm, completion ratio >= 85 % (seeds 0-2; 3 and 4 held out).\n",
        table(["seed", "ATE Sim3 cm", "ATE SE3 cm", "ATE unaligned cm", "rot. err deg (best fit)", "losses",
               "loops closed", "compl. ratio", "acc. cm", "after Sim3: compl. ratio", "acc. cm", "compl. cm"],
              rows)]) + "\n"


def real_section() -> str:
    """The table ``bench/real.py`` stored in ``real.json`` (nothing when it has not run)."""
    d = load("real")
    if d is None:
        return ""
    st = d.get("settings", {})
    variants = "; ".join(f"`{v}`: mapper overrides {x.get('applied') or 'none'}"
                         for v, x in d.get("variants", {}).items())
    rows = [[t["row"], t["variant"], t["measure"], t["value"], t["target"], t["met"]] for t in d.get("table", [])]
    skipped = "".join(f" `{r}` skipped: {why}." for r, why in d.get("skipped", {}).items())
    return "\n".join([
        "### Unseen scenes (`bench/real.py` -> `real.json`, maps in `real_maps/`)\n",
        f"Rows {', '.join(st.get('rows', []))} (7-Scenes redkitchen dev 200 / long 700 frames, synthetic seeds "
        f"{st.get('seeds')}, TUM fr1_rpy, NeRF lego), RGB only, run {d.get('date', '')}"
        f"{' (--quick)' if st.get('quick') else ''}; "
        f"variants side by side in one process ({variants}). "
        f"Synthetic rows: the worst seed against the target.{skipped}\n",
        table(["row", "variant", "measure", "value", "target", "met"], rows)]) + "\n"


def transport_section() -> str:
    d = load("transport")
    if d is None:
        return "### Transport (`bench/transport.py`)\n\nnot run\n"
    rows = []
    for name, r in d["results"].items():
        rows.append([name, f"{r['bytes']:,}", fmt(r["latency_ms"]["median"]), fmt(r["latency_ms"]["p95"]),
                     fmt(r["latency_with_codec_ms"]["median"]), fmt(r["throughput"]["msgs_per_s"], 0)])
    return "\n".join([
        "### Transport (`bench/transport.py` -> `transport.json`)\n",
        f"Two zenoh peer processes over loopback; goal: {d.get('goal', '')}.\n",
        table(["message", "bytes", "one-way ms median", "p95", "median incl. encode+decode", "msgs/s"], rows)]) + "\n"


def field_section() -> str:
    d = load("field_micro")
    if d is None:
        return ""
    rows = [[n, f"{r['params']:,}", r["flops_per_point"], fmt(r["min_s"], 3), fmt(r["median_s"], 3),
             fmt(r["us_per_sample_min"])] for n, r in d["results"].items()]
    return "\n".join([
        "### Field micro-benchmark (`bench/field_micro.py` -> `field_micro.json`)\n",
        f"One forward + backward + Adam step of {d['rays']} rays x {d['samples']} samples, {d['threads']} thread.\n",
        table(["field", "params", "FLOPs/point", "min s", "median s", "us/sample (min)"], rows)]) + "\n"


def init_section() -> str:
    d = load("init_speed")
    if d is None:
        return ""
    rows = []
    for name, v in d["variants"].items():
        q = v.get("quality_mean") or v["runs"][0]  # the mean over the mapper seeds (older files: one run)
        iv, ho = q["init_views"], q["held_out"]
        rows.append([name, fmt(v["seconds_min"], 1), fmt(v["seconds_median"], 1), fmt(iv["depth_rel_median"], 3),
                     fmt(iv["psnr"]), fmt(ho["depth_rel_median"], 3), fmt(ho["psnr"]), fmt(ho["coverage"])])
    sc = d["scene"]
    where = (f"of {Path(sc['data']).name}" if "data" in sc
             else f"of a synthetic room (seed {sc['seed']}, {sc['variety']}, {sc['size']})")
    seeds = sc.get("mapper_seeds", [0])
    return "\n".join([
        "### Init stage (`bench/init_speed.py` -> `init_speed.json`)\n",
        f"The mapper's init on the first 15 frames {where}, GT poses, no depth, {d['machine']['threads']} threads, "
        f"variants alternated in one process; quality: the mean over mapper seeds {seeds}. "
        "Depth error: median relative error of the rendered depth (uncovered pixels count 1) over 5 init views and "
        "3 held-out views (frames 17, 22, 27). Target: <= 5 s at the quality of the init before. Four rooms and the "
        "final maps: `bench/results/init_fog/`.\n",
        table(["variant", "s min", "s median", "init views depth err", "init views PSNR", "held-out depth err",
               "held-out PSNR", "held-out covered"], rows)]) + "\n"


def system_section() -> str:
    parts = [system_table(n) for n in ("system", "system_gt") if load(n) is not None]
    return "\n".join(parts) if parts else "### End to end (`bench/system.py`)\n\nnot run\n"


def _rmse_cm(ate) -> Optional[float]:
    return 100.0 * ate["rmse_m"] if isinstance(ate, dict) and "rmse_m" in ate else None


def _keyframes(tr: dict, mp: dict) -> str:
    """Keyframes flagged / dropped: the tracker's, or (GT poses) those the mapper flagged itself / evicted."""
    if tr.get("keyframes_flagged"):
        return f"{tr['keyframes_flagged']} / {mp.get('keyframes_dropped', '-')}"
    return f"{mp.get('keyframes_integrated', '-')} (mapper's) / {mp.get('keyframes_evicted_from_inbox', 0)}"


def system_table(name: str) -> str:
    d = load(name)
    st = d.get("settings", {})
    rows = []
    for run in d.get("runs", []):
        r = run.get("summary", run)
        tr, mp, rec = r.get("tracker", {}), r.get("mapper", {}), r.get("map") or {}
        sim = r.get("map_sim3_aligned") or {}
        rss = r.get("rss_mb_peak") or {}
        fps = r.get("fps")
        lat = tr.get("latency_s_usable_poses") or {}
        rows.append([f"{fps:g} fps" if fps else "paced by consumers", fmt(r.get("wall_seconds"), 0),
                     f"{tr.get('tracked', '-')} / {tr.get('lost', '-')} / {tr.get('skipped_to_keep_pace', '-')}",
                     f"{fmt(lat.get('median'), 2)} / {fmt(lat.get('p95'), 2)}",
                     _keyframes(tr, mp),
                     f"{mp.get('mapped', '-')} / {mp.get('windows', '-')} / {mp.get('thinned_non_keyframes', '-')} / "
                     f"{mp.get('dropped_inbox', '-')}", str(mp.get("refinements_final", "-")),
                     f"{fmt(rss.get('mapper'), 0)} / {fmt(rss.get('tracker'), 0)}",
                     fmt(rec.get("completion_ratio"), 1, " %"), fmt(sim.get("completion_ratio"), 1, " %"),
                     fmt(sim.get("accuracy_cm")), fmt(_rmse_cm(tr.get("ate_sim3")))])
    b = d.get("slam_baseline")
    if b:
        sim = b.get("map_sim3_aligned") or {}
        rows.append(["`fmapping slam` (in-process, every frame)", fmt(b.get("wall_seconds"), 0), "-", "-", "-", "-",
                     "1", "-", fmt((b.get("map") or {}).get("completion_ratio"), 1, " %"),
                     fmt(sim.get("completion_ratio"), 1, " %"), fmt(sim.get("accuracy_cm")),
                     fmt(_rmse_cm(b.get("ate_sim3")))])
    return "\n".join([
        f"### End to end (`bench/system.py` -> `{name}.json`, `{name}.png`)\n",
        f"`fmapping up` on a synthetic room ({st.get('frames')} frames {st.get('size')}, poses from the "
        f"{st.get('poses')}), all services as OS processes on this machine, sampled every "
        f"{st.get('interval')} s over a monitoring zenoh session ("
        f"{'the secure default, the monitor role' if st.get('secure') else 'the open mesh: --insecure'}). "
        "Keyframes dropped: flagged by the tracker "
        "but never in a mapper window (GT poses: the keyframes the mapper flagged by motion, mapped / evicted).\n",
        table(["playback", "wall s", "tracker tracked / lost / skipped to keep pace", "pose latency s median / p95",
               "keyframes flagged / dropped", "mapper frames / windows / thinned / inbox-dropped",
               "closing refinements", "RSS peak MB mapper / tracker", "map compl. ratio",
               "after Sim3: compl. ratio", "acc. cm", "ATE Sim3 cm"], rows)]) + "\n"


def long_run_section() -> str:
    d = load("long_run")
    if d is None:
        return "### Long run (`bench/long_run.py`)\n\nnot run\n"
    rows = [[g["windows"], g["frames"], fmt(g["window_s_min"]), fmt(g["window_s_median"]), fmt(g["rss_mb_max"], 0),
             fmt(g.get("mapper_image_mb"), 1)] for g in d.get("groups", [])]
    return "\n".join([
        "### Long run (`bench/long_run.py` -> `long_run.json`)\n",
        f"In-process `fmapping slam` (RGB only) on `{Path(d['settings']['data']).name}`: window time and resident "
        f"memory per group of windows. RSS {fmt(d.get('rss_mb_at_frame_200'), 0)} MB at frame 200, "
        f"{fmt(d.get('rss_mb_end'), 0)} MB at the end ({fmt(d.get('rss_growth_from_frame_200_pct'), 1)} %), high-water "
        f"mark {fmt(d.get('rss_mb_high_water'), 0)} MB (export included).\n",
        table(["windows", "frames", "window s min", "window s median", "RSS max MB", "mapper images MB"], rows),
        _trim_note()]) + "\n"


def _ab_part(d: dict) -> str:
    return (f"RSS max {fmt(min(g['rss_mb_max'] for g in d['groups']), 0)}-"
            f"{fmt(max(g['rss_mb_max'] for g in d['groups']), 0)} MB per group, "
            f"{fmt(d.get('rss_growth_from_frame_200_pct'), 1)} % from frame 200")


def _trim_note() -> str:
    """The side-by-side runs of ``long_run_trim/`` (the heap trimmed after each mapper update, or not) and of
    ``long_run_sparse_obs/`` (the sparse points' per-frame observations as arrays, or as lists)."""
    notes = []
    trim = {k: load(f"long_run_trim/{k}") for k in ("without_trim", "with_trim")}
    if all(v is not None for v in trim.values()):
        notes.append("\nThe heap trim after each mapper update (in the run above), side by side with the code before "
                     f"it (`long_run_trim/`): without it {_ab_part(trim['without_trim'])}; with it "
                     f"{_ab_part(trim['with_trim'])}.")
    obs = {k: load(f"long_run_sparse_obs/{k}") for k in ("before", "after")}
    if all(v is not None for v in obs.values()):
        notes.append("\nThe sparse points' per-frame observations kept as arrays (in the run above), side by side "
                     f"with the lists before (`long_run_sparse_obs/`): before {_ab_part(obs['before'])}; after "
                     f"{_ab_part(obs['after'])}.")
    real = {k: load(f"long_run_7scenes/{k}") for k in ("png", "jpeg")}
    if all(v is not None for v in real.values()):
        notes.append("\n700 real 640x480 frames (7-Scenes long, `long_run_7scenes/`), keyframes kept as PNG: "
                     f"{_ab_part(real['png'])}; as JPEG (the default): {_ab_part(real['jpeg'])}.")
    return "".join(notes)


def faults_section() -> str:
    d = load("faults")
    if d is None:
        return "### Faults (`bench/faults.py`)\n\nnot run\n"
    import faults  # bench/faults.py: its table

    st = d["settings"]
    return "\n".join([
        "### Faults (`bench/faults.py` -> `faults.json`)\n",
        f"`fmapping up --poses tracker` on a synthetic room ({st['frames']} frames {st['size']}), secure default; "
        "each run against the undisturbed one: hostile messages from the run's own play and tracker "
        "credentials plus an outsider, kill -9 of a service, kill -9 of the launcher then `--resume`.\n",
        faults.markdown(d)]) + "\n"


def build() -> str:
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    parts = [f"Report built {stamp} on {machine()} by `python bench/report.py` from `bench/results/`; "
             "each table comes from its own run (the JSON files record when and, where they do, on which "
             "machine: the 2-core machines differ from run to run). `make bench` re-runs everything. "
             "The CPU is shared and its speed swings 3-4x: timings are min / median.\n",
             mapping_section(), init_section(), tracking_section(), slam_section(), real_section(),
             system_section(),
             long_run_section(),
             faults_section(), transport_section(),
             field_section()]
    pngs = sorted(p.name for p in RESULTS.glob("*.png"))
    if pngs:
        parts.append("Plots: " + ", ".join(f"[{n}](bench/results/{n})" for n in pngs) + "\n")
    return "\n".join(parts)


def update_readme(readme: Path, body: str) -> None:
    text = readme.read_text()
    block = f"{BEGIN}\n{body}\n{END}"
    if BEGIN in text and END in text:
        text = text[: text.index(BEGIN)] + block + text[text.index(END) + len(END):]
    else:
        text = text.rstrip() + "\n\n## Benchmarks\n\n" + block + "\n"
    readme.write_text(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--no-readme", action="store_true", help="only write bench/results/summary.md")
    a = ap.parse_args(argv)
    body = build()
    (RESULTS / "summary.md").write_text(body)
    if not a.no_readme:
        update_readme(ROOT / "README.md", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
