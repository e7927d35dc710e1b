"""Faults benchmark: ``fmapping up`` under attack and crashes, measured against an undisturbed run.

    python bench/faults.py                       # 48 frames 160x120, a mapper that maps in minutes
    python bench/faults.py --quick               # the tests' tiny mapper (no map: completion "-")
    python bench/faults.py --frames 60 --rate 5000 --runs clean,flood

One synthetic room (``fmapping.synthetic.generate_scene``), then the same ``fmapping up --poses
tracker`` run (secure default: per-run credentials, access control) several times:

* ``clean``: undisturbed, the reference;
* ``flood``: while it runs, hostile messages at ``--rate`` per second from sessions holding the
  run's own credentials (an authorised peer gone wrong: play's, role ``io``, on ``frames``, ``poses/gt``
  and ``control``; the tracker's on ``poses/tracker``): undecodable bytes, truncated
  messages, frames and poses numbered 10^9 and -1, unknown commands; plus an outsider without
  credentials trying to join once a second (refused: counted);
* ``kill-mapper`` / ``kill-tracker``: ``kill -9`` of that service once it acknowledges the middle
  frame (the launcher restarts it; the mapper resumes from its checkpoint, the tracker re-localises);
* ``resume``: ``kill -9`` of the launcher itself at the middle frame, then ``fmapping up --resume OUT``.

For each: exit code, wall time, restarts (``OUT/up.json``), frames in the mapper's trajectory, ATE
against the GT (no alignment: the GT world frame the tracker anchors to; and Sim3), the map's
accuracy and completion ratio (5 cm) after the trajectory's Sim3, and the completion ratio after the Sim3 of its
whole poses (``services.launcher.demo.demo_metrics``),
the peak resident memory of every service (``/proc/<pid>/status`` VmRSS sampled every 0.5 s, over
restarts), and for the flood the messages sent, the rate reached and what the services counted
(``bad_input``). Writes ``bench/results/faults.json`` and ``faults.md``; ``bench/report.py`` puts
the table into the README. Every wait has a timeout (``--max-seconds`` per run).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
import report  # noqa: E402  (bench/report.py: the machine line)

from fmapping import protocol as P  # noqa: E402

# a mapper that gives a map of the 160x120 room within a minute on 2 shared cores (fmapping up, tracker
# poses, 48 frames: completion ratio 26 % after Sim3, accuracy 8.6 cm, 32 s); --quick: the tests' tiny one (no map)
BENCH_MAPPER = {
    "init_frames": 6, "init_rounds": [[0, 32], [3, 32]], "init_iters_per_round": 100, "window_size": 8,
    "n_global_keyframes": 3, "new_frames_per_window": 3, "iters_per_window": 10, "keyframe_every": 3,
    "rays_per_iter": 1024, "n_coarse": 16, "n_fine": 8, "warp_views": 2, "pc_rays": 128, "sparse_rays": 64,
    "final_global_iters": 10, "device": "cpu", "seed": 0,
    "field": {"resolution": 32, "density_components": 8, "appearance_components": 8},
}
QUICK_MAPPER = {
    "init_frames": 4, "init_rounds": [[0, 16], [3, 16]], "init_iters_per_round": 4,
    "window_size": 6, "n_global_keyframes": 2, "new_frames_per_window": 2, "iters_per_window": 2,
    "keyframe_every": 2, "rays_per_iter": 96, "n_coarse": 12, "n_fine": 4, "final_global_iters": 2,
    "device": "cpu", "seed": 0,
    "field": {"resolution": 12, "density_components": 4, "appearance_components": 4, "app_features": 8, "hidden": 8},
}
RUNS = ("clean", "flood", "kill-mapper", "kill-tracker", "resume")


# ---------------------------------------------------------------------------- processes
def status(out: Path, name: str) -> dict:
    try:
        return json.loads((out / "status" / f"{name}.json").read_text())
    except (OSError, ValueError):
        return {}


def rss_mb(pid: int) -> Optional[float]:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


class RssWatch(threading.Thread):
    """Peak VmRSS per service of a run (the pids in OUT/status/*.json, restarted ones included)."""

    def __init__(self, out: Path):
        super().__init__(daemon=True)
        self.out, self.peak, self.stop = out, {}, threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.5):
            for f in (self.out / "status").glob("*.json"):
                pid = status(self.out, f.stem).get("pid")
                mb = rss_mb(int(pid)) if pid else None
                if mb is not None:
                    self.peak[f.stem] = max(self.peak.get(f.stem, 0.0), round(mb, 1))


def up_cmd(scene: Path, out: Path, cfg: Path) -> list[str]:
    return [sys.executable, "-m", "services.cli", "up", "--data", str(scene), "--poses", "tracker", "--out",
            str(out), "--config", str(cfg), "--view", "save"]


def wait_for(cond, limit: float, what: str, proc: subprocess.Popen) -> None:
    end = time.monotonic() + limit
    while not cond():
        if proc.poll() is not None:
            raise RuntimeError(f"fmapping up ended (rc {proc.returncode}) before {what}")
        if time.monotonic() > end:
            raise RuntimeError(f"timed out after {limit:.0f} s waiting for {what}")
        time.sleep(0.05)


# ---------------------------------------------------------------------------- the hostile peer
def hostile_payloads(rng: np.random.Generator) -> list[tuple[str, bytes]]:
    """(key suffix, payload) pairs an authorised peer gone wrong sends (see the module docstring)."""
    frame = P.Frame(seq=10**9, timestamp=0.0, rgb=np.zeros((8, 8, 3), np.uint8),
                    camera={"fx": 10.0, "fy": 10.0, "cx": 4.0, "cy": 4.0, "width": 8, "height": 8})
    good = P.encode(P.Pose(seq=3, timestamp=0.0, c2w=np.eye(4), source="tracker"))
    return [("frames", rng.bytes(1024)), ("frames", P.encode(frame)), ("frames", P.encode(frame)[:40]),
            ("poses/gt", rng.bytes(200)), ("poses/gt", P.encode(P.Pose(seq=-1, timestamp=0.0, c2w=np.eye(4),
                                                                            source="gt"))),
            ("control", rng.bytes(64)), ("control", P.encode(P.Control("pause"))[:-3]),
            ("poses/tracker", good[:-5]),
            ("poses/tracker", P.encode(P.Pose(seq=10**9, timestamp=0.0, c2w=np.eye(4), source="tracker")))]


class Flood(threading.Thread):
    """Hostile messages at ``rate`` per second with the run's io and tracker credentials, and an
    outsider trying to join once a second, until stopped."""

    def __init__(self, out: Path, ns: str, rate: float, seed: int = 0):
        super().__init__(daemon=True)
        self.out, self.ns, self.rate = out, ns, rate
        self.stop, self.sent, self.outsider_refused, self.outsider_joined = threading.Event(), 0, 0, 0
        self.payloads = hostile_payloads(np.random.default_rng(seed))
        self.t0 = self.t1 = 0.0

    def run(self) -> None:
        import zenoh

        # the credentials of play (role io) and of the tracker, as the launcher wrote them for this run
        sessions = {r: zenoh.open(zenoh.Config.from_file(str(self.out / "secrets" / f"{r}.json5")))
                    for r in ("play", "tracker")}
        endpoint = json.loads((self.out / "secrets" / "play.json5").read_text())["connect"]["endpoints"][0]
        role_of = {"frames": "play", "poses/gt": "play", "control": "play", "poses/tracker": "tracker"}
        self.t0 = time.monotonic()
        next_outsider = self.t0
        try:
            while not self.stop.is_set():
                key, payload = self.payloads[self.sent % len(self.payloads)]
                sessions[role_of[key]].put(f"fmapping/{self.ns}/{key}", payload)
                self.sent += 1
                now = time.monotonic()
                if now >= next_outsider:
                    next_outsider = now + 1.0
                    self._outsider(zenoh, endpoint)
                ahead = self.sent / self.rate - (time.monotonic() - self.t0)
                if ahead > 0:
                    self.stop.wait(ahead)
        finally:
            self.t1 = time.monotonic()
            for s in sessions.values():
                s.close()

    def _outsider(self, zenoh, endpoint: str) -> None:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("connect/endpoints", json.dumps([endpoint]))
        c.insert_json5("connect/timeout_ms", "500")
        try:
            zenoh.open(c).close()
            self.outsider_joined += 1
        except zenoh.ZError:
            self.outsider_refused += 1


# ---------------------------------------------------------------------------- one run
def one_run(kind: str, scene: Path, cfg: Path, work: Path, rate: float, limit: float) -> dict:
    from services.launcher.demo import demo_metrics

    out = work / kind
    frames = json.loads((scene / "scene.json").read_text())["frames"]
    t0 = time.monotonic()
    proc = subprocess.Popen(up_cmd(scene, out, cfg), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    watch = RssWatch(out)
    watch.start()
    flood, rec = None, {"run": kind}
    try:
        if kind == "flood":
            wait_for(lambda: (out / "secrets" / "play.json5").is_file() and status(out, "play"), limit, "the run",
                     proc)
            flood = Flood(out, f"up{proc.pid}", rate)
            flood.start()
        elif kind != "clean":
            name = {"kill-mapper": "mapper", "kill-tracker": "tracker", "resume": "mapper"}[kind]
            wait_for(lambda: status(out, name).get("frame_seq", -1) >= frames // 2
                     and (name != "mapper" or (out / "checkpoint.pt").is_file()), limit, f"{name} at frame "
                     f"{frames // 2}", proc)
            rec["killed_at"] = status(out, name)["frame_seq"]
            os.kill(proc.pid if kind == "resume" else int(status(out, name)["pid"]), signal.SIGKILL)
        try:
            proc.wait(timeout=max(1.0, limit - (time.monotonic() - t0)))
        except subprocess.TimeoutExpired:
            proc.kill()
            raise RuntimeError(f"{kind}: fmapping up did not finish within {limit:.0f} s")
        if kind == "resume":
            time.sleep(3.0)  # its services stop with it (--exit-with-parent), writing what they have
            again = subprocess.run([sys.executable, "-m", "services.cli", "up", "--resume", str(out)], cwd=ROOT,
                                   capture_output=True, text=True, timeout=limit)
            rec["rc"] = again.returncode
        else:
            rec["rc"] = proc.returncode
    finally:
        if flood is not None:
            flood.stop.set()
            flood.join(timeout=10)
        watch.stop.set()
        if proc.poll() is None:
            proc.kill()
    rec["seconds"] = round(time.monotonic() - t0, 1)
    rec["rss_mb_peak"] = dict(sorted(watch.peak.items()))
    up = json.loads((out / "up.json").read_text()) if (out / "up.json").is_file() else {}
    rec["restarts"] = up.get("restarts", {})
    counters = {n: s.get("counters", {}) for n, s in up.get("status", {}).items()}
    rec["bad_input"] = {n: int(c.get("bad_input", 0)) for n, c in counters.items() if c.get("bad_input")}
    rec["tracker"] = {k: counters.get("tracker", {}).get(k)
                      for k in ("resumed_at", "resume_keyframe", "bootstrap_frame")}
    if flood is not None:
        rec["flood"] = {"sent": flood.sent, "seconds": round(flood.t1 - flood.t0, 1),
                        "rate_per_s": round(flood.sent / max(1e-9, flood.t1 - flood.t0)),
                        "outsider_refused": flood.outsider_refused, "outsider_joined": flood.outsider_joined}
    if rec["rc"] == 0:
        m = demo_metrics(out, scene)
        t, r3, rp = m.get("trajectory", {}), m.get("recon_sim3", {}), m.get("recon_pose_sim3", {})
        rec.update(frames=t.get("frames"), ate_cm=t.get("ate_se3_cm"), ate_sim3_cm=t.get("ate_sim3_cm"),
                   completion_ratio=r3.get("completion_ratio"), accuracy_cm=r3.get("accuracy_cm"),
                   completion_ratio_poses=rp.get("completion_ratio"))
    return rec


def markdown(res: dict) -> str:
    st = res["settings"]
    rows = []
    for r in res["runs"]:
        what = {"clean": "undisturbed", "kill-mapper": "kill -9 mapper", "kill-tracker": "kill -9 tracker",
                "resume": "kill -9 fmapping up"}.get(r["run"], r["run"])
        if "flood" in r:
            f = r["flood"]
            what = (f"hostile messages, {f['rate_per_s']:,}/s for {f['seconds']:.0f} s ({f['sent']:,}); outsider "
                    f"refused {f['outsider_refused']}x, joined {f['outsider_joined']}x")
        if "killed_at" in r:
            what += f" at frame {r['killed_at']}" + (", then `--resume`" if r["run"] == "resume" else "")
        restarts = ", ".join(f"{k} {v}" for k, v in r.get("restarts", {}).items()) or "0"
        rss = ", ".join(f"{k} {v:.0f}" for k, v in r.get("rss_mb_peak", {}).items())
        rows.append([what, r["rc"], report.fmt(r["seconds"], 0), restarts,
                     f"{r.get('frames', '-')} / {st['frames']}", report.fmt(r.get("ate_cm")),
                     report.fmt(r.get("ate_sim3_cm")), report.fmt(r.get("completion_ratio"), 1, " %"),
                     report.fmt(r.get("completion_ratio_poses"), 1, " %"), report.fmt(r.get("accuracy_cm")), rss])
    return report.table(["run", "rc", "s", "restarts", "frames mapped", "ATE cm", "ATE Sim3 cm",
                         "compl. ratio (Sim3)", "compl. ratio (poses' Sim3)", "acc. cm (Sim3)", "RSS peak MB"],
                        rows) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--rate", type=float, default=2000.0, help="hostile messages per second in the flood run")
    ap.add_argument("--runs", default=",".join(RUNS), help=f"comma-separated, of {', '.join(RUNS)}")
    ap.add_argument("--quick", action="store_true", help="the tests' tiny mapper (fast, but it maps nothing)")
    ap.add_argument("--max-seconds", type=float, default=900.0, help="per run")
    ap.add_argument("--work", default=None, help="folder for the scene and the runs (default: a temp folder)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "faults.json"))
    a = ap.parse_args(argv)
    runs = [r for r in a.runs.split(",") if r]
    if not runs or set(runs) - set(RUNS):
        ap.error(f"--runs: choose from {', '.join(RUNS)}")
    import tempfile

    from fmapping.synthetic import generate_scene

    work = Path(a.work or tempfile.mkdtemp(prefix="fmapping-faults-"))
    w, h = (int(v) for v in a.size.split("x"))
    scene = work / "scene"
    if not (scene / "scene.json").is_file():
        generate_scene(scene, seed=a.seed, frames=a.frames, size=(w, h), max_cloud_points=20000, mesh_spacing=0.1)
    mapper = QUICK_MAPPER if a.quick else BENCH_MAPPER
    cfg = work / "up.yaml"
    cfg.write_text(yaml.safe_dump({"mapper": mapper, "launcher": {"threads": 1, "view": False}}))
    res = {"settings": {"frames": a.frames, "size": a.size, "seed": a.seed, "rate": a.rate, "quick": a.quick,
                        "mapper": mapper, "machine": report.machine(), "load_avg": os.getloadavg()},
           "runs": []}
    out = Path(a.out)
    for kind in runs:
        print(f"[faults] {kind} ...", flush=True)
        res["runs"].append(one_run(kind, scene, cfg, work, a.rate, a.max_seconds))
        print(json.dumps(res["runs"][-1]), flush=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=1))
    res["settings"]["load_avg_end"] = os.getloadavg()
    out.write_text(json.dumps(res, indent=1))
    out.with_suffix(".md").write_text(markdown(res))
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
