"""A whole ``fmapping up`` run with a fault injected (kill -9 of one service at a given frame), and its
outputs measured against the scene's ground truth, for the kill tests (test_supervision.py) that
compare a disturbed run with an undisturbed one of the same data.

Importable as a plain module (``tests/`` is on ``sys.path`` under pytest).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from service_helpers import ROOT, subprocess_env


# The mapper of the kill tests is bench/faults.py's (one definition): it maps the 160x120 room
# within a minute on one thread (an undisturbed 48-frame run there, 32 s, completion ratio 26-28 %
# after Sim3). The tests' SMALL_MAPPER leaves no map to compare.
sys.path.insert(0, str(ROOT / "bench"))
from faults import BENCH_MAPPER as FAULT_MAPPER  # noqa: E402, F401


@dataclass
class FaultRun:
    """What one run left: exit code, the launcher's output, OUT/up.json, the mapper's stats and the
    metrics of :func:`services.launcher.demo.demo_metrics` (ATE of OUT/traj.txt, map vs visible GT)."""
    rc: int
    log: str
    out: Path
    up: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    killed_at: Optional[int] = None  # frame the killed service had acknowledged when it was killed

    @property
    def frames(self) -> int:
        return int(self.metrics.get("trajectory", {}).get("frames", 0))

    @property
    def ate_cm(self) -> float:
        return float(self.metrics["trajectory"]["ate_sim3_cm"])

    @property
    def completion(self) -> float:
        return float(self.metrics["recon_sim3"]["completion_ratio"])


def _status(out: Path, name: str) -> dict:
    try:
        return json.loads((out / "status" / f"{name}.json").read_text())
    except (OSError, ValueError):
        return {}


def up_argv(scene: Path, out: Path, poses: str, config: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "services.cli", "up", "--data", str(scene), "--poses", poses, "--out", str(out),
            "--config", str(config), *extra]


def run_with_fault(scene: Path, out: Path, poses: str, config: Path, kill: Optional[str] = None,
                   at_frame: int = 0, timeout: float = 300.0, argv: Optional[list] = None) -> FaultRun:
    """``fmapping up`` on ``scene``; with ``kill``, that service is killed with SIGKILL once its status
    acknowledges frame ``at_frame`` (the mapper: also once it has a checkpoint). Waits at most
    ``timeout`` s for the run (then kills it and fails the test with the log)."""
    from services.launcher.demo import demo_metrics

    proc = subprocess.Popen(argv or up_argv(scene, out, poses, config), cwd=ROOT, env=subprocess_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    killed_at = None
    try:
        deadline = time.monotonic() + timeout
        while kill and killed_at is None and proc.poll() is None:
            if time.monotonic() > deadline:
                raise AssertionError(f"{kill} never acknowledged frame {at_frame} within {timeout:.0f} s")
            st = _status(out, kill)
            ready = st.get("frame_seq", -1) >= at_frame and st.get("pid")
            if ready and (kill != "mapper" or (out / "checkpoint.pt").is_file()):
                killed_at = int(st["frame_seq"])
                os.kill(int(st["pid"]), signal.SIGKILL)
            time.sleep(0.02)
        try:
            rc = proc.wait(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            raise AssertionError(f"fmapping up did not finish within {timeout:.0f} s:\n{proc.stdout.read()[-3000:]}")
        log = proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    run = FaultRun(rc=rc, log=log, out=out, killed_at=killed_at)
    for name, attr in (("up.json", "up"), ("stats.json", "stats")):
        try:
            setattr(run, attr, json.loads((out / name).read_text()))
        except (OSError, ValueError):
            pass
    if rc == 0:
        run.metrics = demo_metrics(out, scene)
    return run
