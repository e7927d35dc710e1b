"""Supervision of the service processes of ``fmapping up``: :class:`Proc` (one child, its log and
status files), waiting for start-up, the progress line, heartbeats, restarts of a crashed service,
OUT/up.json and the shutdown (SIGINT, then SIGKILL)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

from fmapping.run_warnings import tracking_warnings

# A service's status file is rewritten by its heartbeat thread every 0.5 s, even during a long update:
# one unchanged for this long belongs to a hung process, and the run is stopped with its name.
HEARTBEAT_TIMEOUT = 120.0
# Supervision: a service that dies while play still streams is started again, at most MAX_RESTARTS
# times each, after RESTART_BACKOFF * 2**k seconds (k = restarts so far). The mapper resumes from
# OUT/checkpoint.pt, the tracker re-syncs from map/latest. Play is not restarted (it would start the
# sequence over), nor is anything once play has finished (the end-of-sequence stop is gone then).
RESTARTABLE = ("mapper", "tracker", "record", "view")
MAX_RESTARTS = 3
RESTART_BACKOFF = 1.0
FINAL_CODES = (2, 3)  # bad input, gave up waiting (services.process.EXIT_STALLED): starting again changes nothing


# CPU priority (nice increments) by service: the camera's path (play, tracker) first; the mapper may lag (it keeps
# every keyframe and catches up), the recorder and the viewer come last. Only matters when the cores are busy.
# 1,000 frames at 30 fps, secure, two alternated pairs (bench/results/secure_system/nice_*.json): 5 / 5 / 10 ->
# 10 / 10 / 15 tracked 624 / 675 -> 740 / 795 frames (the rest skipped to keep pace), pose latency median
# 0.156 / 0.113 -> 0.076 / 0.055 s, p95 0.446 / 0.636 -> 0.428 / 0.271 s; map after the Sim3 94.4-95.2 -> 95.5-96.1 %.
NICE = {"mapper": 10, "record": 10, "view": 15}
# ... and the mapper and the viewer under SCHED_IDLE: they run on what the camera's path leaves, and a tracker waking
# for a frame preempts them at once (a nice value only weighs their shares: the woken tracker still waited for the
# mapper's time slice). 200 frames at 30 fps, six alternated pairs (bench/results/sched_idle_2026-12-07/): pose
# latency p95 once tracking 0.147-0.823 s (median 0.23) -> 0.065-0.277 s (median 0.10), frames tracked 105-158 ->
# 117-193 of 200, the mapper's init 8.8-11.3 -> 8.6-10.7 s, map after the Sim3 93.7-94.5 -> 92.1-95.1 %.
# A service enters SCHED_IDLE itself once started (``--sched-idle``, which the launcher passes them): under it from
# its first instruction, a mapper on a machine whose cores were busy with other work got almost no CPU for its
# imports and did not start within the launcher's 120 s. Its start-up runs at its nice value.
IDLE = ("mapper", "view")


def _child_setup(increment: int):
    """A ``preexec_fn``: the child gets a process group of its own (a Ctrl-C in the terminal reaches only the
    launcher, which stops the services in order) and a CPU priority lowered by ``increment``.

    A process group, not a session: with the kernel's autogroup scheduling (``sched_autogroup_enabled``, on by
    default) every session is scheduled as one group with an equal share of the CPU, and nice values only rank
    processes within a session. Services in sessions of their own got equal shares whatever their nice value:
    a busy mapper took a full core from the tracker."""
    def setup() -> None:
        try:
            os.setpgid(0, 0)
            if increment > 0:
                os.nice(increment)
        except OSError:
            pass
    return setup


class Proc:
    """One child service process with its log file and status file (CPU priority by :data:`NICE`)."""

    def __init__(self, name: str, argv: list[str], out: Path, env: dict):
        self.name = name
        self._preexec = _child_setup(NICE.get(name, 0))
        self.status_file = out / "status" / f"{name}.json"
        self.log_path = out / "logs" / f"{name}.log"
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self.status_file.parent.mkdir(parents=True, exist_ok=True)
        if self.status_file.exists():
            self.status_file.unlink()
        self.argv = argv + ["--status-file", str(self.status_file), "--exit-with-parent"]
        self.env = env
        self.restarts = 0
        self._log = open(self.log_path, "w")
        self.popen = subprocess.Popen(self.argv, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                      preexec_fn=self._preexec)

    def restart(self) -> None:
        """Start the same command again after it died: the log goes on, the status starts over."""
        self._log.write(f"\n--- fmapping up: restart {self.restarts + 1} (exit code {self.rc}) ---\n")
        self._log.flush()
        if self.status_file.exists():
            self.status_file.unlink()
        self.popen = subprocess.Popen(self.argv, stdout=self._log, stderr=subprocess.STDOUT, env=self.env,
                                      preexec_fn=self._preexec)
        self.restarts += 1

    @property
    def rc(self) -> Optional[int]:
        return self.popen.poll()

    def status(self) -> dict:
        try:
            return json.loads(self.status_file.read_text())
        except (OSError, ValueError):
            return {}

    def silent_for(self) -> float:
        """Seconds since the status file last changed (0 before it exists: start-up has its own timeout)."""
        try:
            return max(0.0, time.time() - self.status_file.stat().st_mtime)
        except OSError:
            return 0.0

    def signal(self, sig: int) -> None:
        if self.popen.poll() is None:
            try:
                self.popen.send_signal(sig)
            except ProcessLookupError:
                pass

    def close(self) -> None:
        self._log.close()

    def tail(self, n: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


def wait_ready(procs: list[Proc], timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for p in procs:
            if p.rc is not None:
                raise RuntimeError(f"{p.name} exited with code {p.rc} during start-up:\n{p.tail()}")
        if all(p.status_file.exists() for p in procs):
            return
        time.sleep(0.1)
    missing = [p.name for p in procs if not p.status_file.exists()]
    raise RuntimeError(f"{', '.join(missing)} did not start within {timeout:.0f} s (see {procs[0].log_path.parent})")


def _progress(procs: dict[str, Proc], t0: float) -> str:
    play = procs["play"].status() if "play" in procs else {}
    pc = play.get("counters", {})
    total = int(pc.get("frames_total", 0) or 0)
    sent = int(pc.get("frames_sent", 0) or 0)
    parts = [f"{time.monotonic() - t0:6.1f}s", f"play {sent}/{total or '?'}"]
    m = procs["mapper"].status()
    if m:
        mc = m.get("counters", {})
        parts.append(f"mapper acked {m.get('frame_seq', -1) + 1} windows {int(mc.get('windows', 0))} "
                     f"v{int(mc.get('field_version', 0))} [{m.get('state', '?')}]")
    if "tracker" in procs:
        t = procs["tracker"].status()
        tc = t.get("counters", {})
        parts.append(f"tracker {int(tc.get('frames_tracked', 0))} tracked {int(tc.get('frames_lost', 0))} lost")
    errs = sum(int(p.status().get("counters", {}).get("decode_errors", 0)) for p in procs.values())
    if errs:
        parts.append(f"decode errors {errs}")
    return " | ".join(parts)


def linger(view: Proc, url: str) -> None:
    """After a live run: the viewer keeps serving until Ctrl-C when someone is at the terminal."""
    if view.rc is not None or not sys.stdin.isatty():
        return
    print(f"fmapping up: the viewer keeps serving at {url}; Ctrl-C to stop it", flush=True)
    try:
        while view.rc is None:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass


def monitor(procs: dict[str, Proc], t0: float, timeout: Optional[float], out: Path, serving: tuple = (),
            infra: Optional[dict] = None, errors: Optional[list] = None) -> int:
    """Wait until every process has exited (those in ``serving``, a live viewer, may serve on); a process
    of ``infra`` (the router) must stay up meanwhile, and every running service must keep beating
    (:data:`HEARTBEAT_TIMEOUT`). A failure is printed and appended to ``errors``; returns 1 then."""
    errors = errors if errors is not None else []
    pending: dict[str, float] = {}  # service -> when to restart it

    def fail(msg: str) -> int:
        print(f"\nfmapping up: {msg}", file=sys.stderr, flush=True)
        errors.append(msg.split("\n", 1)[0])
        return 1

    tty = sys.stdout.isatty()
    last_print = 0.0
    while True:
        now = time.monotonic()
        if now - last_print >= (0.5 if tty else 5.0):
            line = _progress(procs, t0)
            print(("\r" + line + " " * 8) if tty else line, end="" if tty else "\n", flush=True)
            last_print = now
        _supervise(procs, pending, now)
        rcs = {n: p.rc for n, p in procs.items()}
        failed = {n: rc for n, rc in rcs.items() if rc not in (None, 0) and n not in pending}
        failed.update({n: p.rc for n, p in (infra or {}).items() if p.rc is not None})
        if failed:
            name, rc = next(iter(failed.items()))
            tail = {**procs, **(infra or {})}[name].tail()
            return fail(f"{name} exited with code {rc}; last log lines:\n{tail}")
        if all(rc == 0 for n, rc in rcs.items() if n not in serving):
            break
        if timeout is not None and now - t0 > timeout:
            return fail(f"timed out after {timeout:.0f} s")
        silent = [p.name for p in procs.values() if p.rc is None and p.silent_for() > HEARTBEAT_TIMEOUT]
        if silent:
            return fail(f"no heartbeat from {', '.join(silent)} for {HEARTBEAT_TIMEOUT:.0f} s (a hung process; "
                        f"see {out / 'logs'})")
        time.sleep(0.2)
    if tty:
        print()
    summary = write_summary(procs, t0, out)
    print("fmapping up: done in %.1f s; outputs: %s" % (summary["seconds"], ", ".join(summary["outputs"].values())),
          flush=True)
    for w in summary["warnings"]:
        print(f"fmapping up: warning: {w}", file=sys.stderr, flush=True)
    missing = [n for n in ("map.ply", "traj.txt") if n not in summary["outputs"]]
    if missing:
        print(f"fmapping up: missing outputs {missing} (see {out / 'logs'})", file=sys.stderr, flush=True)
        return 1
    return 0


def _supervise(procs: dict[str, Proc], pending: dict[str, float], now: float) -> None:
    """Schedule a restart (``pending``: service -> monotonic time) for every restartable service that
    died while play still runs and has restarts left; start those whose time has come."""
    play = procs.get("play")
    streaming = play is None or play.rc is None
    for name in RESTARTABLE:
        p = procs.get(name)
        if p is None or p.rc in (None, 0, *FINAL_CODES) or name in pending or not streaming \
                or p.restarts >= MAX_RESTARTS:
            continue
        delay = RESTART_BACKOFF * 2 ** p.restarts
        pending[name] = now + delay
        print(f"\nfmapping up: {name} exited with code {p.rc}; restarting it in {delay:.0f} s "
              f"({p.restarts + 1}/{MAX_RESTARTS})", file=sys.stderr, flush=True)
    for name, when in list(pending.items()):
        if now >= when:
            del pending[name]
            procs[name].restart()


def tracker_warnings(status: Optional[dict]) -> list[str]:
    """The tracker's last status as warnings for the user (:func:`fmapping.run_warnings.tracking_warnings`):
    frames it answered without a pose (``frames_posed`` of ``frames_received``), frames lost or many
    re-localised. None or no frame received: none."""
    c = (status or {}).get("counters") or {}
    n = int(c.get("frames_received", 0) or 0)
    if n == 0:
        return []
    posed = c.get("frames_posed")
    source = "photometric" if c.get("frontend_mono", 1) else "the tracker's map front end, once the mapper has a map"
    return tracking_warnings(n, posed=None if posed is None else int(posed), lost=int(c.get("frames_lost", 0) or 0),
                             relocalised=int(c.get("relocalised", 0) or 0), source=source)


def write_summary(procs: dict[str, Proc], t0: float, out: Path, error: str = "") -> dict:
    """OUT/up.json: seconds, the outputs present, every service's last status, the tracker's warnings
    (:func:`tracker_warnings`), and ``error`` (why the run failed) when there is one."""
    summary: dict = {"seconds": round(time.monotonic() - t0, 1), "outputs": {}}
    if error:
        summary["error"] = error
    for name in ("map.ply", "mesh.ply", "traj.txt", "stats.json", "run.rrd", "record/traj.txt", "record/points.ply"):
        p = out / name
        if p.exists():
            summary["outputs"][name] = str(p)
    summary["status"] = {n: {"state": p.status().get("state"), "frame_seq": p.status().get("frame_seq"),
                             "counters": p.status().get("counters", {}), "rc": p.rc,
                             "last_error": p.status().get("last_error", "")} for n, p in procs.items()}
    summary["restarts"] = {n: p.restarts for n, p in procs.items() if p.restarts}
    summary["warnings"] = tracker_warnings(summary["status"].get("tracker"))
    (out / "up.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def stop_all(procs: dict[str, Proc], grace: float, first: tuple) -> None:
    """SIGINT to every running process (in ``first`` order), SIGKILL what is left after ``grace`` s."""
    running = [procs[n] for n in first if n in procs and procs[n].rc is None]
    if not running:
        return
    for p in running:
        p.signal(signal.SIGINT)
    end = time.monotonic() + grace
    for p in running:
        try:
            p.popen.wait(timeout=max(0.1, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            print(f"fmapping up: {p.name} did not stop within {grace:.0f} s: killing it", file=sys.stderr, flush=True)
            p.popen.kill()
            try:  # a process dies when it next runs: a SCHED_IDLE one on a busy machine may take a while
                p.popen.wait(timeout=5)
            except subprocess.TimeoutExpired:
                print(f"fmapping up: {p.name} (pid {p.popen.pid}) has not ended 5 s after SIGKILL; going on",
                      file=sys.stderr, flush=True)
