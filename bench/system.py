"""System benchmark: the multi-process demo (``fmapping up``) paced by its consumers and at 30 fps playback.

    python bench/system.py                  # in-process fmapping slam, then fmapping up paced and at 30 fps,
                                            # 200 frames at 320x240
    python bench/system.py --poses gt --fps 0 10 --out bench/results/system_gt.json   # GT poses, paced and 10 fps
    python bench/system.py --quick          # smoke check: 24 frames at 160x120, tiny mapper (writes to --work)
    python bench/system.py --fps 10 --frames 200 --max-seconds 300
    python bench/system.py --init-iters 25 --max-seconds 240       # shorter init (does not converge)

One synthetic scene (``fmapping.synthetic.generate_scene``) is generated once and reused.
For every playback rate the whole system runs through :func:`services.launcher.up.run_up`
(``--poses tracker``: ``services.mapper``, ``services.io record``, ``services.io view``
unless ``--no-view``, ``services.tracker`` and ``services.io play --fps F``, each an OS
process). By default the run is secure, as ``fmapping up``'s is (a router with per-run
credentials, zenoh clients, no shared memory) and this process joins it with the ``monitor``
role's credentials (``observe``); with ``--insecure`` the services are zenoh peers on loopback
and every one also connects to this process's session (``connect_extra``). It listens to:

* ``status/*``: per-service counters, acknowledgement (``frame_seq``) and ``lag``;
* ``poses/gt`` (the player publishes it right before each frame: the publish time of
  every frame), ``poses/tracker`` and ``poses/mapper`` (when each frame got its tracked
  pose and its first mapper window pose).

Every ``--interval`` seconds it records (time series, ``t`` = seconds since the run started):

* ``published``: newest frame published; ``tracker_ack``: newest frame answered by the
  tracker; ``tracker_lag_frames`` = published - tracker_ack; ``tracker_lag_s`` = how long
  the oldest frame not yet answered by the tracker has been waiting (0 when caught up);
* ``mapper_ack`` (newest frame mapped or dropped by the mapper), ``mapper_waiting`` =
  published - mapper_ack, ``windows_behind`` = mapper_waiting / ``new_frames_per_window``,
  ``windows`` done, ``mapper_lag_s`` (the mapper's own: sequence seconds between the newest
  frame received and the newest integrated);
* ``dropped``: per service, the ``dropped_*`` inbox counters plus the frames a service
  gave up on (tracker ``frames_skipped`` / ``frames_lost``; mapper ``frames_without_pose``,
  ``frames_skipped``);
* ``rss_mb``: resident memory of every child process (psutil, else /proc/<pid>/status); the summary's
  ``rss_mb_growth`` is each service's from frame 200 to the end of playback (issue 18: within 10 %), one
  sample at frame 200 against the highest after it; ``rss_mb_envelope`` compares the lowest and the highest
  RSS over frames 200-399 with those over the last 200 frames (the mapper's RSS is a sawtooth of updates).

At the end of each run: the final counters, per-frame latencies (tracker pose - publish,
first mapper pose - publish; the tracker's also frame by frame: ``frames`` in the JSON, dots in the
plot), ATE of the tracker's poses (quality > 0) and of the mapper's trajectory (OUT/traj.txt)
against the ground truth (sim3), and the quality of OUT/map.ply against the scene's
``gt_visible_cloud.ply`` (``fmapping.metrics.recon_metrics``, 5 cm).

The mapper runs the library default config with a shorter closing refinement so that a run
stays bounded (``--max-seconds`` per rate; on time-out the launcher stops the services and the
mapper writes its current map): see ``BENCH_MAPPER`` (``settings.mapper`` in the JSON). Writes
``bench/results/system.json`` and ``bench/results/system.png``. The CPU is shared: every
timing here is noisy; the JSON records the load average along the run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
import report  # noqa: E402  (bench/report.py: the machine line)

from fmapping import protocol as P  # noqa: E402

# the library defaults except a shorter closing refinement (bounded run time)
BENCH_MAPPER = {"final_global_iters": 50, "device": "cpu"}
QUICK_MAPPER = {
    "init_frames": 6, "init_rounds": [[0, 16], [3, 16]], "init_iters_per_round": 8,
    "window_size": 10, "n_global_keyframes": 4, "new_frames_per_window": 3, "iters_per_window": 4,
    "keyframe_every": 3, "rays_per_iter": 256, "init_rays_per_iter": 256, "n_coarse": 16, "n_fine": 8,
    "final_global_iters": 8,
    "device": "cpu", "field": {"resolution": 24},
}
SERVICES = ("play", "tracker", "mapper", "record", "view")


# ---------------------------------------------------------------------------- processes
def _service_name(cmdline: list[str]) -> Optional[str]:
    """The service of a child process from its command line (``-m services.io play`` -> play)."""
    for i, a in enumerate(cmdline):
        if a.startswith("services."):
            mod = a.split(".", 1)[1]
            if mod == "io":
                return cmdline[i + 1] if i + 1 < len(cmdline) else "io"
            return mod
    return None


def _rss_proc(pid: int) -> Optional[float]:
    """VmRSS of ``pid`` in MB from /proc (None when the process is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        return None
    return None


#: Issue 18's memory measure: each service's resident size from this frame on (flat to within 10 %).
RSS_FROM_FRAME = 200
#: frames per span of :func:`rss_envelope` (frames 200-399 against the last 200 of playback)
RSS_ENVELOPE_SPAN = 200


def rss_growth(rows: list[dict], from_frame: int, until_t) -> dict:
    """Per service: RSS (MB) at the first sample once ``from_frame`` frames were published, the largest after
    it up to time ``until_t`` (the end of playback; None: the whole run) and the growth in %. Empty when the
    run never published ``from_frame`` frames."""
    start = next((i for i, r in enumerate(rows) if r.get("published", -1) >= from_frame), None)
    if start is None:
        return {}
    span = [r for r in rows[start:] if until_t is None or r["t"] <= until_t] or [rows[start]]
    out = {}
    for name, at in rows[start].get("rss_mb", {}).items():
        vals = [r["rss_mb"][name] for r in span if r.get("rss_mb", {}).get(name) is not None]
        if at and vals:
            out[name] = {"at_frame": round(at, 1), "max_after": round(max(vals), 1),
                         "growth_pct": round(100.0 * (max(vals) / at - 1.0), 1)}
    return out


def rss_envelope(rows: list[dict], from_frame: int, span: int, until_t) -> dict:
    """Per service: the lowest and highest RSS (MB) while frames ``from_frame`` .. ``from_frame + span`` were
    published and while the last ``span`` frames of playback were (up to ``until_t``), and the growth of each
    in %. The mapper's RSS is a sawtooth (an update's temporaries, handed back after it): :func:`rss_growth`
    compares one sample, possibly a trough, with the highest peak after it; this compares peaks with peaks
    and troughs with troughs. Empty when the run is too short for two disjoint spans."""
    pub = [r.get("published", -1) for r in rows]
    last = max(pub, default=-1)
    if last - span < from_frame + span:
        return {}
    first = [r for r, p in zip(rows, pub) if from_frame <= p < from_frame + span]
    end = [r for r, p in zip(rows, pub) if p > last - span and (until_t is None or r["t"] <= until_t)]
    out = {}
    for name in sorted({n for r in first for n in r.get("rss_mb", {})}):
        a = [r["rss_mb"][name] for r in first if r.get("rss_mb", {}).get(name)]
        b = [r["rss_mb"][name] for r in end if r.get("rss_mb", {}).get(name)]
        if a and b:
            out[name] = {"frames": [from_frame, from_frame + span, last - span + 1, last + 1],
                         "min_first": round(min(a), 1), "max_first": round(max(a), 1),
                         "min_last": round(min(b), 1), "max_last": round(max(b), 1),
                         "floor_growth_pct": round(100.0 * (min(b) / min(a) - 1.0), 1),
                         "peak_growth_pct": round(100.0 * (max(b) / max(a) - 1.0), 1)}
    return out


def child_rss_mb() -> dict[str, float]:
    """RSS (MB) of every service process started by this process, by service name."""
    out: dict[str, float] = {}
    try:
        import psutil

        for c in psutil.Process().children(recursive=True):
            try:
                name = _service_name(c.cmdline())
                if name:
                    out[name] = out.get(name, 0.0) + c.memory_info().rss / 2 ** 20
            except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
                pass
        return out
    except ImportError:
        pass
    me = os.getpid()
    kids: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            kids.setdefault(ppid, []).append(int(d.name))
    todo = list(kids.get(me, []))
    while todo:
        pid = todo.pop()
        todo += kids.get(pid, [])
        try:
            cmd = (Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0"))
        except OSError:
            continue
        name, rss = _service_name(cmd), _rss_proc(pid)
        if name and rss is not None:
            out[name] = out.get(name, 0.0) + rss
    return out


def child_cpu_s() -> dict[str, float]:
    """CPU seconds (user + system, threads included) each service process started by this process has used so
    far, by service name; empty without psutil."""
    out: dict[str, float] = {}
    try:
        import psutil
    except ImportError:
        return out
    for c in psutil.Process().children(recursive=True):
        try:
            name = _service_name(c.cmdline())
            if name:
                t = c.cpu_times()
                out[name] = out.get(name, 0.0) + t.user + t.system
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            pass
    return out


def cpu_shares(rows: list[dict], t_from, t_to) -> dict:
    """Per service: the cores it used on average between the rows nearest times ``t_from`` and ``t_to`` (its CPU
    seconds over the wall seconds; 1.0 = one core all the time). Empty without two such rows."""
    if t_from is None or t_to is None:
        return {}
    span = [r for r in rows if r.get("cpu_s") and t_from <= r["t"] <= t_to]
    if len(span) < 2 or span[-1]["t"] <= span[0]["t"]:
        return {}
    a, b = span[0], span[-1]
    wall = b["t"] - a["t"]
    return {n: round((b["cpu_s"][n] - a["cpu_s"].get(n, 0.0)) / wall, 2) for n in sorted(b["cpu_s"])
            if n in a["cpu_s"]}


# ---------------------------------------------------------------------------- zenoh monitor
class Monitor:
    """A zenoh session of the run's; keeps the newest Status per service and the arrival time of each
    frame's GT / tracker / mapper pose (monotonic seconds). :meth:`listen` for the open mesh (every
    service connects to it), :meth:`join` for a secure run (a client of the run's router with the
    ``monitor`` role's credentials)."""

    def __init__(self, ns: str):
        self.keys = P.Keys(ns)
        self.lock = threading.Lock()
        self.session = None
        self.endpoint: Optional[str] = None
        self.status: dict[str, P.Status] = {}
        self.t_pub: dict[int, float] = {}  # seq -> when poses/gt (sent right before the frame) arrived
        self.tracker: dict[int, tuple[float, Optional[float], np.ndarray]] = {}  # seq -> (t, quality, c2w)
        self.keyframes: set[int] = set()  # frames the tracker flagged as keyframes (Pose.keyframe)
        self.t_map: dict[int, float] = {}  # seq -> first mapper pose
        self.gt: dict[int, np.ndarray] = {}
        self.decode_errors = 0
        self._subs = []

    def listen(self) -> str:
        """A peer listening on a fresh loopback port (the open mesh: pass it as connect_extra)."""
        from services.zenoh_session import free_port, zenoh_config

        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self._open(zenoh_config("peer", listen=[self.endpoint], connect=[], multicast=False))
        return self.endpoint

    def join(self, config_path, ns: str) -> None:
        """``fmapping up``'s observe hook of a secure run: the monitor role's client config."""
        import zenoh

        assert ns == self.keys.ns, (ns, self.keys.ns)
        self._open(zenoh.Config.from_file(str(config_path)))

    def _open(self, conf) -> None:
        from services.zenoh_session import payload_bytes
        import zenoh

        self.session = zenoh.open(conf)
        subs = ((self.keys.status(), self._on_status), (self.keys.poses("gt"), self._on_pose),
                (self.keys.poses("tracker"), self._on_pose), (self.keys.poses("mapper"), self._on_pose))
        for key, fn in subs:
            def cb(sample, fn=fn):
                t = time.monotonic()
                try:
                    fn(P.decode(payload_bytes(sample)), t)
                except P.ProtocolError:
                    with self.lock:
                        self.decode_errors += 1
            self._subs.append(self.session.declare_subscriber(key, cb))

    def _on_status(self, st: P.Status, t: float) -> None:
        with self.lock:
            old = self.status.get(st.service)
            if old is None or st.seq > old.seq or st.time > old.time:
                self.status[st.service] = st

    def _on_pose(self, p: P.Pose, t: float) -> None:
        with self.lock:
            if p.source == "gt":
                self.t_pub.setdefault(p.seq, t)
                self.gt[p.seq] = np.array(p.c2w)
            elif p.source == "tracker":  # first arrival (latency), newest pose (bundle-adjusted again)
                first = self.tracker.get(p.seq)
                self.tracker[p.seq] = (t if first is None else first[0], p.quality, np.array(p.c2w))
                if p.keyframe and (p.quality is None or p.quality > 0):
                    self.keyframes.add(p.seq)
            elif p.source == "mapper":
                self.t_map.setdefault(p.seq, t)

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                pass
        if self.session is not None:
            self.session.close()


def _drops(name: str, counters: dict) -> dict:
    keep = {"tracker": ("frames_skipped", "frames_lost", "frames_skipped_behind"),
            "mapper": ("frames_without_pose", "frames_skipped", "unusable_poses", "frames_thinned")}.get(name, ())
    return {k: int(v) for k, v in counters.items() if k.startswith("dropped_") or k in keep}


def sample_row(mon: Monitor, t0: float, per_window: int) -> dict:
    """One time-series row from the newest statuses, the pose arrival times and the RSS."""
    now = time.monotonic()
    with mon.lock:
        st = dict(mon.status)
        t_pub = mon.t_pub
        published = max(t_pub) if t_pub else -1
        row: dict = {"t": round(now - t0, 2), "published": int(published)}
        play = st.get("play")
        if play is not None:
            row["play_state"] = play.state
            row["frames_sent"] = int(play.counters.get("frames_sent", 0))
        tr = st.get("tracker")
        if tr is not None:
            c = tr.counters
            ack = tr.frame_seq
            row.update(tracker_ack=ack, tracker_state=tr.state, tracker_received=int(c.get("frames_received", 0)),
                       tracker_tracked=int(c.get("frames_tracked", 0)), tracker_poses_out=int(c.get("published", 0)),
                       tracker_lag_frames=max(0, published - ack) if published >= 0 else 0)
            oldest = t_pub.get(ack + 1) if published > ack else None
            row["tracker_lag_s"] = round(now - oldest, 2) if oldest is not None else 0.0
            row["tracker_track_ms"] = float(c.get("track_ms", 0.0))
        m = st.get("mapper")
        if m is not None:
            c = m.counters
            waiting = max(0, published - m.frame_seq) if published >= 0 else 0
            row.update(mapper_ack=m.frame_seq, mapper_state=m.state, mapper_received=int(c.get("frames_received", 0)),
                       mapper_mapped=int(c.get("frames_processed", 0)), windows=int(c.get("windows", 0)),
                       mapper_waiting=waiting, windows_behind=round(waiting / per_window, 2),
                       mapper_lag_s=round(float(m.lag), 2), mapper_queued=int(c.get("queued_frames", 0)),
                       last_window_s=float(c.get("last_window_s", 0.0)))
        row["dropped"] = {n: _drops(n, s.counters) for n, s in st.items()}
    row["rss_mb"] = {k: round(v, 1) for k, v in child_rss_mb().items()}
    row["cpu_s"] = {k: round(v, 2) for k, v in child_cpu_s().items()}
    row["loadavg1"] = round(os.getloadavg()[0], 2)
    return row


# ---------------------------------------------------------------------------- one run
def run_one(fps: float, scene: Path, out: Path, mapper_cfg: dict, max_seconds: float, view: bool, threads: int,
            interval: float, poses: str = "tracker", insecure: bool = False) -> dict:
    import yaml

    from services.launcher.up import run_up

    if out.exists():
        shutil.rmtree(out)  # a left-over checkpoint would make the mapper resume
    out.mkdir(parents=True)
    cfg = out / "system.yaml"
    cfg.write_text(yaml.safe_dump({"mapper": mapper_cfg,
                                   "launcher": {"view": view, "threads": threads, "timeout": max_seconds}},
                                  sort_keys=False))
    ns = f"bench{os.getpid()}f{int(fps)}"
    mon = Monitor(ns)
    per_window = int(mapper_cfg.get("new_frames_per_window", 5))
    rows: list[dict] = []
    stop = threading.Event()
    t0 = time.monotonic()

    def sampler() -> None:
        while not stop.wait(interval):
            rows.append(sample_row(mon, t0, per_window))

    th = threading.Thread(target=sampler, name="system-bench-sampler", daemon=True)
    th.start()
    # secure (fmapping up's default): the monitor joins as the run's monitor role once the router is up;
    # --insecure: the open loopback mesh, every service also connecting to the monitor
    net = {"connect_extra": [mon.listen()]} if insecure else {"observe": mon.join}
    args = argparse.Namespace(out=str(out), data=str(scene), poses=poses, fps=fps, config=str(cfg),
                              timeout=max_seconds, ns=ns, **net)
    print(f"[system] fps {fps:g}: fmapping up{' --insecure' if insecure else ''} (ns {ns}, out {out}) ...",
          flush=True)
    try:
        rc = run_up(args)
    finally:
        stop.set()
        th.join(timeout=5)
        rows.append(sample_row(mon, t0, per_window))
        wall = time.monotonic() - t0
        mon.close()
    return {"fps": fps, "rc": rc, "wall_seconds": round(wall, 1),
            "summary": summarize(fps, rows, mon, out, scene, t0, rc, wall), "series": to_columns(rows),
            "frames": per_frame(mon, t0)}


def per_frame(mon: Monitor, t0: float) -> dict:
    """Per published frame: when it was published (s since the run started), the latency of the tracker's
    first answer (s, null without one), whether that answer was usable and a keyframe."""
    seqs = sorted(mon.t_pub)
    trk = [mon.tracker.get(s) for s in seqs]
    return {"seq": seqs, "published_s": [round(mon.t_pub[s] - t0, 4) for s in seqs],
            "latency_s": [None if v is None else round(v[0] - mon.t_pub[s], 4) for s, v in zip(seqs, trk)],
            "usable": [v is not None and (v[1] is None or v[1] > 0) for v in trk],
            "keyframe": [s in mon.keyframes for s in seqs]}


def _stats(xs) -> Optional[dict]:
    a = np.asarray([x for x in xs if x is not None and math.isfinite(x)], np.float64)
    if a.size == 0:
        return None
    return {"median": round(float(np.median(a)), 3), "p95": round(float(np.percentile(a, 95)), 3),
            "max": round(float(a.max()), 3), "n": int(a.size)}


def mapper_init_seconds(stats_json: Path) -> Optional[float]:
    """The mapper's own time for its init stage (``init_seconds`` of the stats it writes at the end), or None."""
    try:
        v = json.loads(stats_json.read_text()).get("mapper", {}).get("init_seconds")
    except (OSError, ValueError, AttributeError):
        return None
    return round(float(v), 2) if isinstance(v, (int, float)) and v > 0 else None


def summarize(fps: float, rows: list[dict], mon: Monitor, out: Path, scene: Path, t0: float, rc: int,
              wall: float) -> dict:
    from fmapping.metrics import ate, eval_traj_files

    up = {}
    try:
        up = json.loads((out / "up.json").read_text())
    except (OSError, ValueError):
        pass
    final = {n: dict(s.counters) for n, s in mon.status.items()}
    for n, s in (up.get("status") or {}).items():  # the launcher's last reading (status files)
        if s.get("counters"):
            final[n] = s["counters"]
    total = len(mon.t_pub)
    pub_times = sorted(mon.t_pub.values())
    play_end = (pub_times[-1] - t0) if pub_times else None
    play_start = (pub_times[0] - t0) if pub_times else None
    during = [r for r in rows if play_end is not None and play_start is not None and play_start <= r["t"] <= play_end]
    trk_lat = [mon.tracker[s][0] - mon.t_pub[s] for s in mon.tracker if s in mon.t_pub]
    tracked_lat = [mon.tracker[s][0] - mon.t_pub[s] for s in mon.tracker
                   if s in mon.t_pub and (mon.tracker[s][1] is None or mon.tracker[s][1] > 0)]
    # once tracking runs: frames published after the first tracker pose arrived (the monocular bootstrap
    # and the late anchor hold the first ~15 frames' poses by design)
    first_pose = min((v[0] for v in mon.tracker.values()), default=None)
    steady_lat = [mon.tracker[s][0] - mon.t_pub[s] for s in mon.tracker
                  if s in mon.t_pub and first_pose is not None and mon.t_pub[s] > first_pose]
    map_lat = [mon.t_map[s] - mon.t_pub[s] for s in mon.t_map if s in mon.t_pub]
    tc, mc = final.get("tracker", {}), final.get("mapper", {})
    s: dict = {
        "fps": fps, "rc": rc, "wall_seconds": round(wall, 1),
        "frames_total": int(final.get("play", {}).get("frames_total", total)), "frames_published": total,
        "playback_seconds": round(play_end - play_start, 2) if pub_times else None,
        "playback_started_at_s": round(play_start, 2) if play_start is not None else None,
        "tracker": {
            "poses_out": len(mon.tracker), "tracked": int(tc.get("frames_tracked", 0)),
            "from_mapper": int(tc.get("poses_from_mapper", 0)), "lost": int(tc.get("frames_lost", 0)),
            "skipped": int(tc.get("frames_skipped", 0)), "dropped": int(tc.get("dropped_frames", 0)),
            "skipped_to_keep_pace": int(tc.get("frames_skipped_behind", 0)),
            "keyframes_flagged": len(mon.keyframes),
            "usable_poses": sum(1 for v in mon.tracker.values() if v[1] is None or v[1] > 0),
            "lag_frames_max": max((r.get("tracker_lag_frames", 0) for r in rows), default=0),
            "lag_frames_mean_during_playback":
            round(float(np.mean([r.get("tracker_lag_frames", 0) for r in during])), 2) if during else None,
            "lag_s_max": max((r.get("tracker_lag_s", 0.0) for r in rows), default=0.0),
            "latency_s_all_poses": _stats(trk_lat), "latency_s_usable_poses": _stats(tracked_lat),
            "latency_s_once_tracking": _stats(steady_lat),
            "track_ms_last": float(tc.get("track_ms", 0.0)),
        },
        "mapper": {
            "received": int(mc.get("frames_received", 0)), "mapped": int(mc.get("frames_processed", 0)),
            "windows": int(mc.get("windows", 0)), "dropped_inbox": int(mc.get("dropped_frames", 0)),
            "without_pose": int(mc.get("frames_without_pose", 0)),
            "skipped_unusable_pose": int(mc.get("frames_skipped", 0)),
            "windows_behind_max": max((r.get("windows_behind", 0.0) for r in rows), default=0.0),
            "windows_behind_mean_during_playback":
            round(float(np.mean([r.get("windows_behind", 0.0) for r in during])), 2) if during else None,
            "windows_behind_at_playback_end": next((r.get("windows_behind") for r in rows
                                                    if play_end is not None and r["t"] >= play_end), None),
            "latency_s_first_window_pose": _stats(map_lat),
            "thinned_non_keyframes": int(mc.get("frames_thinned", 0)),
            "keyframes_integrated": int(mc.get("keyframes_integrated", 0)),
            # keyframes the tracker flagged that never reached a mapper window (no poses/mapper for them)
            "keyframes_dropped": len(mon.keyframes - set(mon.t_map)) if mon.t_map else None,
            "refinements_final": int(mc.get("updates_final", 0)),
            "keyframes_evicted_from_inbox": int(mc.get("dropped_frames_rank2", 0)),  # any source, GT poses too
            "closing_extra_iters": int(mc.get("closing_extra_iters", 0)),
        },
        "dropped": {n: _drops(n, c) for n, c in final.items()},
        "rss_mb_peak": {}, "rss_mb_end_of_playback": {},
    }
    for r in rows:
        for n, v in r.get("rss_mb", {}).items():
            s["rss_mb_peak"][n] = max(s["rss_mb_peak"].get(n, 0.0), v)
    s["rss_mb_peak_total"] = round(max((sum(r.get("rss_mb", {}).values()) for r in rows), default=0.0), 1)
    end_row = next((r for r in rows if play_end is not None and r["t"] >= play_end), None)
    if end_row:
        s["rss_mb_end_of_playback"] = end_row.get("rss_mb", {})
    s["rss_mb_growth"] = rss_growth(rows, RSS_FROM_FRAME, play_end)
    s["rss_mb_envelope"] = rss_envelope(rows, RSS_FROM_FRAME, RSS_ENVELOPE_SPAN, play_end)
    done_t = next((r["t"] for r in rows if r.get("mapper_state") == "done"), None)
    s["mapper"]["done_after_playback_s"] = round(done_t - play_end, 1) if done_t is not None and play_end else None
    s["loadavg1"] = _stats([r.get("loadavg1") for r in rows])
    # cores each service used: over the playback, and from its start to the mapper's first update (the init)
    init_t = next((r["t"] for r in rows if r.get("windows", 0) >= 1), None)
    s["cpu_cores_during_playback"] = cpu_shares(rows, play_start, play_end)
    s["cpu_cores_until_init_done"] = cpu_shares(rows, play_start, init_t)
    s["mapper"]["init_done_after_playback_start_s"] = (round(init_t - play_start, 1)
                                                       if init_t is not None and play_start is not None else None)
    s["mapper"]["init_s"] = mapper_init_seconds(out / "stats.json")
    if s["playback_seconds"]:
        s["keyframes_per_s"] = round(len(mon.keyframes) / s["playback_seconds"], 2)
    # tracker ATE over its usable poses (seq = frame index: no looping)
    seqs = sorted(k for k, v in mon.tracker.items() if (v[1] is None or v[1] > 0) and k in mon.gt)
    if len(seqs) >= 3:
        try:
            s["tracker"]["ate_sim3"] = _round(ate(np.stack([mon.tracker[k][2] for k in seqs]),
                                                  np.stack([mon.gt[k] for k in seqs]), "sim3"))
        except (ValueError, np.linalg.LinAlgError) as e:
            s["tracker"]["ate_sim3"] = {"error": str(e)}
    gt_traj = scene / "groundtruth.txt"
    if (out / "traj.txt").is_file():
        try:
            s["mapper"]["ate_sim3"] = _round(eval_traj_files(out / "traj.txt", gt_traj, "sim3")["ate"])
        except ValueError as e:
            s["mapper"]["ate_sim3"] = {"error": str(e)}
    s.update(map_quality(out, scene))
    s["outputs"] = sorted(p.name for p in out.iterdir() if p.is_file())
    return s


def map_quality(out: Path, scene: Path) -> dict:
    """``map``: OUT/map.ply against the scene's visible GT cloud (5 cm), and ``map_sim3_aligned``: the same
    after the Sim3 that aligns OUT/traj.txt to the GT trajectory (monocular maps have their own scale)."""
    from fmapping.metrics import recon_metrics
    from fmapping.ply import read_ply

    if not (out / "map.ply").is_file():
        return {"map": {"error": "no map.ply"}}
    t = time.perf_counter()
    pts = read_ply(out / "map.ply").points
    gt = read_ply(scene / "gt_visible_cloud.ply").points
    q = {"map": _round(recon_metrics(pts, gt, threshold=0.05))}
    q["map"]["eval_seconds"] = round(time.perf_counter() - t, 1)
    sim3 = traj_sim3(out / "traj.txt", scene / "groundtruth.txt") if len(pts) else None
    if sim3 is not None:
        sc, R, tr = sim3
        q["map_sim3_aligned"] = _round({**recon_metrics(sc * pts @ R.T + tr, gt, threshold=0.05), "scale": sc})
    return q


def run_slam_baseline(scene: Path, out: Path, mapper_cfg: dict, threads: int) -> dict:
    """In-process ``fmapping slam`` (RGB only, the same mapper settings) on the same frames: what the live
    system should reach when nothing is dropped."""
    import subprocess

    import yaml

    from fmapping.metrics import eval_traj_files

    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    cfg = out / "slam.yaml"
    cfg.write_text(yaml.safe_dump({"mapper": mapper_cfg}, sort_keys=False))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if threads > 0:  # 0: fmapping slam's own default
        env["OMP_NUM_THREADS"] = str(threads)
    t = time.monotonic()
    print(f"[system] fmapping slam baseline (out {out}) ...", flush=True)
    rc = subprocess.run([sys.executable, "-m", "fmapping.cli", "slam", "--data", str(scene), "--out", str(out),
                         "--config", str(cfg)], env=env, cwd=str(ROOT)).returncode
    res: dict = {"rc": rc, "wall_seconds": round(time.monotonic() - t, 1)}
    if (out / "traj.txt").is_file():
        try:
            res["ate_sim3"] = _round(eval_traj_files(out / "traj.txt", scene / "groundtruth.txt", "sim3")["ate"])
        except ValueError as e:
            res["ate_sim3"] = {"error": str(e)}
    res.update(map_quality(out, scene))
    return res


def traj_sim3(est_path: Path, gt_path: Path):
    """(s, R, t) aligning a TUM trajectory's positions to GT (as the Sim3 ATE does), or None."""
    from fmapping.metrics import align_trajectory, match_trajectory_files

    if not (est_path.is_file() and gt_path.is_file()):
        return None
    try:
        est, gt, _, _ = match_trajectory_files(est_path, gt_path)
        return align_trajectory(est, gt, "sim3")[1]
    except (ValueError, np.linalg.LinAlgError):
        return None


def to_columns(rows: list[dict]) -> dict:
    """Time-series rows -> columns (one list per quantity, None where a service had not reported
    yet); ``rss_mb`` and ``dropped`` become {service: list} and {service: {counter: list}}; the
    services' states become ``states`` {service: [[t, state], ...]} (changes only)."""
    scalars = sorted({k for r in rows for k, v in r.items() if not isinstance(v, dict) and not k.endswith("_state")},
                     key=lambda k: (k != "t", k))
    cols: dict = {k: [r.get(k) for r in rows] for k in scalars}
    states: dict = {}  # service -> [[t, state], ...] at every change
    for r in rows:
        for k in (k for k in r if k.endswith("_state")):
            seq = states.setdefault(k[: -len("_state")], [])
            if not seq or seq[-1][1] != r[k]:
                seq.append([r["t"], r[k]])
    cols["states"] = states
    names = sorted({n for r in rows for n in r.get("rss_mb", {})})
    cols["rss_mb"] = {n: [r.get("rss_mb", {}).get(n) for r in rows] for n in names}
    drops: dict = {}
    for r in rows:
        for n, c in r.get("dropped", {}).items():
            for k in c:
                drops.setdefault(n, {}).setdefault(k, None)
    cols["dropped"] = {n: {k: [r.get("dropped", {}).get(n, {}).get(k, 0) for r in rows] for k in sorted(ks)}
                       for n, ks in sorted(drops.items()) if ks}
    return cols


def dumps(o, ind: int = 0) -> str:
    """JSON with nested maps indented and lists of numbers / strings on one line (compact time
    series); non-finite floats become null."""
    pad, pad1 = " " * ind, " " * (ind + 1)
    if isinstance(o, dict):
        if not o:
            return "{}"
        return "{\n" + ",\n".join(f"{pad1}{json.dumps(str(k))}: {dumps(v, ind + 1)}" for k, v in o.items()) \
            + "\n" + pad + "}"
    if isinstance(o, (list, tuple)):
        if all(not isinstance(v, (dict, list, tuple)) for v in o):
            return "[" + ",".join(dumps(v) for v in o) + "]"
        return "[\n" + ",\n".join(pad1 + dumps(v, ind + 1) for v in o) + "\n" + pad + "]"
    if isinstance(o, (float, np.floating)):
        return json.dumps(float(o)) if math.isfinite(o) else "null"
    if isinstance(o, np.integer):
        return str(int(o))
    return json.dumps(o, default=str)


def _round(d: dict, nd: int = 4) -> dict:
    return {k: (round(v, nd) if isinstance(v, float) else v) for k, v in d.items()}


# ---------------------------------------------------------------------------- plot
def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(13, 8))
    for i, run in enumerate(results["runs"]):
        cols, col, lab = run["series"], f"C{i}", f"{run['fps']:g} fps" if run["fps"] else "paced"
        t0 = run["summary"].get("playback_started_at_s") or 0.0
        t = np.asarray(cols["t"], float) - t0

        def y(v):
            return np.asarray([np.nan if x is None else x for x in (v or [None] * len(t))], float)
        ax[0, 0].plot(t, y(cols.get("tracker_lag_s")), col, label=lab)
        fr = run.get("frames") or {}
        if fr.get("seq"):
            ax[0, 0].plot(np.asarray(fr["published_s"], float) - t0, y(fr["latency_s"]), col, ls="none",
                          marker=".", ms=3, label=f"{lab}: each frame's pose latency")
        ax[0, 1].plot(t, y(cols.get("windows_behind")), col, label=lab)
        for name, ls in (("mapper", "-"), ("tracker", "--"), ("view", ":")):
            if name in cols["rss_mb"]:
                ax[1, 0].plot(t, y(cols["rss_mb"][name]), col, ls=ls, label=f"{lab} {name}")
        ax[1, 1].plot(t, y(cols.get("published")), col, ls=":", label=f"{lab} published")
        ax[1, 1].plot(t, y(cols.get("tracker_ack")), col, ls="--", label=f"{lab} tracker ack")
        ax[1, 1].plot(t, y(cols.get("mapper_ack")), col, label=f"{lab} mapper ack")
    per_window = results["settings"]["mapper"].get("new_frames_per_window", 5)
    titles = ("tracker lag: age of the oldest unanswered frame (s); dots: pose latency per frame",
              f"mapper windows behind (frames waiting / {per_window})",
              "RSS (MB): mapper solid, tracker dashed, view dotted", "frame numbers")
    for a, title in zip(ax.flat, titles):
        a.set_title(title, fontsize=10)
        a.set_xlabel("seconds since the first frame was published")
        a.grid(alpha=0.3)
    ax[0, 0].legend(fontsize=8)
    ax[0, 1].legend(fontsize=8)
    ax[1, 0].legend(fontsize=6, ncol=3)
    ax[1, 1].legend(fontsize=6, ncol=3)
    st = results["settings"]
    fig.suptitle(f"fmapping up, --poses {st['poses']}: {st['frames']} frames {st['size'][0]}x{st['size'][1]} "
                 f"(shared 2-core CPU, noisy)", fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=85)
    plt.close(fig)


# ---------------------------------------------------------------------------- main
def make_scene(work: Path, frames: int, size: tuple[int, int], seed: int) -> Path:
    from fmapping.synthetic import generate_scene

    d = work / f"scene_s{seed}_f{frames}_{size[0]}x{size[1]}"
    if not (d / "scene.json").is_file():
        t = time.perf_counter()
        print(f"[system] generating {d} ...", flush=True)
        generate_scene(d, seed=seed, frames=frames, size=size)
        print(f"[system] scene generated in {time.perf_counter() - t:.1f} s", flush=True)
    return d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: 24 frames at 160x120, tiny mapper, no viewer")
    ap.add_argument("--fps", type=float, nargs="+", default=[0.0, 30.0],
                    help="playback rates (0 = paced: the player waits for the mapper's acknowledgement)")
    ap.add_argument("--no-slam-baseline", action="store_true",
                    help="skip the in-process fmapping slam run on the same frames")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-seconds", type=float, default=420.0, help="time-out of one run (the launcher stops it)")
    ap.add_argument("--no-view", action="store_true", help="do not start the rerun viewer process")
    ap.add_argument("--poses", default="tracker", choices=["tracker", "gt"],
                    help="mapper pose source (gt: no tracker process; for comparison)")
    ap.add_argument("--init-iters", type=int, default=None,
                    help="mapper init_iters_per_round (default: the library's)")
    ap.add_argument("--mapper-set", default=None,
                    help="YAML mapping of mapper overrides: '{init_iters_per_round: 75, field: {init_opacity: 0}}'")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch threads of the mapper and the tracker (0: each service's default, as fmapping up: "
                         "1 each, the mapper every core for its closing stage; the tables before 2026-12-07 were "
                         "measured with 1)")
    ap.add_argument("--insecure", action="store_true",
                    help="the open loopback mesh (zenoh shared memory on) instead of fmapping up's secure default")
    ap.add_argument("--interval", type=float, default=0.5, help="seconds between samples")
    ap.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "fmapping_bench_system"))
    ap.add_argument("--out", default=None, help="JSON path (default bench/results/system.json; "
                                                "WORK/system_quick.json with --quick)")
    a = ap.parse_args(argv)
    size = tuple(int(v) for v in a.size.lower().split("x"))
    mapper_cfg = dict(BENCH_MAPPER)
    if a.init_iters is not None:
        mapper_cfg["init_iters_per_round"] = a.init_iters
    if a.mapper_set:
        import yaml

        mapper_cfg.update(yaml.safe_load(a.mapper_set))
    view = not a.no_view
    if a.quick:
        a.frames, size, view, mapper_cfg = 24, (160, 120), False, dict(QUICK_MAPPER)
        a.max_seconds = min(a.max_seconds, 90.0)
    work = Path(a.work)
    out = Path(a.out) if a.out else (work / "system_quick.json" if a.quick
                                     else ROOT / "bench" / "results" / "system.json")
    work.mkdir(parents=True, exist_ok=True)
    t_all = time.monotonic()
    scene = make_scene(work, a.frames, size, a.seed)
    results = {
        "machine": {"platform": platform.platform(), "cpu": report.cpu_model(), "python": platform.python_version(),
                    "cpus": os.cpu_count(),
                    "loadavg_at_start": [round(x, 2) for x in os.getloadavg()],
                    "note": "2 CPU cores shared with other jobs: timings and lags are noisy"},
        "settings": {"frames": a.frames, "size": list(size), "seed": a.seed, "fps": a.fps, "poses": a.poses,
                     "view": view, "threads": a.threads, "max_seconds": a.max_seconds, "interval": a.interval,
                     "quick": a.quick, "mapper": mapper_cfg, "scene": str(scene), "secure": not a.insecure},
        "runs": [],
    }
    if not a.quick and not a.no_slam_baseline and a.poses == "tracker":
        results["slam_baseline"] = run_slam_baseline(scene, work / "slam_baseline", mapper_cfg, a.threads)
        b = results["slam_baseline"]
        print(f"[system] fmapping slam: rc {b['rc']}, {b['wall_seconds']} s, ATE {b.get('ate_sim3')}, map after Sim3 "
              f"{b.get('map_sim3_aligned')}", flush=True)
    for fps in a.fps:
        run = run_one(fps, scene, work / f"run_{a.poses}_fps{fps:g}", mapper_cfg, a.max_seconds, view, a.threads,
                      a.interval, a.poses, a.insecure)
        results["runs"].append(run)
        s = run["summary"]
        print(f"[system] fps {fps:g}: rc {run['rc']}, {run['wall_seconds']} s | published {s['frames_published']} | "
              f"tracker poses {s['tracker']['poses_out']} (tracked {s['tracker']['tracked']}, lost "
              f"{s['tracker']['lost']}, dropped {s['tracker']['dropped']}), lag max {s['tracker']['lag_frames_max']} "
              f"frames / {s['tracker']['lag_s_max']} s | mapper mapped {s['mapper']['mapped']}, windows "
              f"{s['mapper']['windows']}, behind max {s['mapper']['windows_behind_max']}, dropped "
              f"{s['mapper']['dropped_inbox']} + no pose {s['mapper']['without_pose']} | RSS peak "
              f"{s['rss_mb_peak']} | map {({k: s['map'].get(k) for k in ('accuracy_cm', 'completion_ratio')})}"
              f" | keyframes flagged {s['tracker']['keyframes_flagged']}, dropped {s['mapper']['keyframes_dropped']}, "
              f"non-keyframes thinned {s['mapper']['thinned_non_keyframes']}, tracker skipped to keep pace "
              f"{s['tracker']['skipped_to_keep_pace']} | mapper init {s['mapper'].get('init_s')} s, done "
              f"{s['mapper'].get('init_done_after_playback_start_s')} s after the first frame | map after Sim3 "
              f"{s.get('map_sim3_aligned')}", flush=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(dumps(results) + "\n")  # partial results survive an interruption
        if run["rc"] == 130:
            break
    results["total_seconds"] = round(time.monotonic() - t_all, 1)
    out.write_text(dumps(results) + "\n")
    plot(results, out.with_suffix(".png"))
    print(json.dumps({f"{r['fps']:g}": {k: r["summary"].get(k) for k in ("tracker", "mapper", "map", "map_sim3_aligned",
                                                                       "rss_mb_peak", "rss_mb_growth")}
                      for r in results["runs"]}, indent=1, default=str))
    print(f"[system] wrote {out} and {out.with_suffix('.png')} in {results['total_seconds']} s", flush=True)
    return 0 if all(r["rc"] == 0 for r in results["runs"]) else 1


if __name__ == "__main__":
    sys.exit(main())
