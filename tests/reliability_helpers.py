"""The process scaffolding of the reliability tests (test_reliability.py): a Status watcher on the
bus, services as real OS processes with their status file and log (``Svc``), their memory, a GT
producer paced by a service's acknowledgement, and the map digest of the determinism tests.

Importable as a plain module (``tests/`` is on ``sys.path`` under pytest, and the determinism
test puts it there for a fresh interpreter).
"""
from __future__ import annotations

import hashlib
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from fmapping import protocol as P
from service_helpers import ROOT, GtProducer, feed, small_cfg, subprocess_env
from services.zenoh_session import payload_bytes

TIMEOUT = 60.0


# ============================================================================ Status on the bus
class StatusWatch:
    """The newest Status of one service heard on the bus, with a deadline-bounded wait."""

    def __init__(self, session, key):
        self.cond = threading.Condition()
        self.latest: Optional[P.Status] = None
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample):
        st = P.decode(payload_bytes(sample), P.Status)
        with self.cond:
            if self.latest is None or st.seq > self.latest.seq:
                self.latest = st
            self.cond.notify_all()

    def wait(self, pred, timeout=TIMEOUT, what="status") -> P.Status:
        end = time.monotonic() + timeout
        with self.cond:
            while self.latest is None or not pred(self.latest):
                left = end - time.monotonic()
                assert left > 0, f"timed out waiting for {what}; last status: {self.latest}"
                self.cond.wait(min(left, 0.2))
            return self.latest


# ============================================================================ subprocess helpers
class Svc:
    """A service as a real OS process, with its status file and log (for the reliability tests)."""

    def __init__(self, name: str, argv: list, workdir: Path, ep: str, connect: Optional[list] = None,
                 ns: str = "rel", interval: float = 0.2):
        self.name, self.ep = name, ep
        self.status_file = workdir / f"{name}.status.json"
        self.log_path = workdir / f"{name}.log"
        if self.status_file.exists():
            self.status_file.unlink()
        net = ["--listen", ep, "--ns", ns, "--status-file", str(self.status_file), "--status-interval", str(interval)]
        if connect:
            net += ["--connect", ",".join(connect)]
        self._log = open(self.log_path, "ab")
        self.argv = [sys.executable, "-m"] + argv + net
        self.popen = subprocess.Popen(self.argv, cwd=ROOT, env=subprocess_env(), stdout=self._log,
                                      stderr=subprocess.STDOUT)
        self.pid = self.popen.pid

    def status(self) -> dict:
        try:
            return json.loads(self.status_file.read_text())
        except (OSError, ValueError):
            return {}

    def counters(self) -> dict:
        return self.status().get("counters", {})

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def wait_for(self, pred: Callable[[dict], bool], timeout: float = TIMEOUT, what: str = "") -> dict:
        """Poll the status file until ``pred(status)`` holds (fails on exit or after ``timeout``)."""
        end = time.monotonic() + timeout
        while True:
            st = self.status()
            if st and pred(st):
                return st
            assert self.popen.poll() is None, f"{self.name} exited ({self.popen.returncode}) waiting for {what}:\n" \
                                              + self.log()[-3000:]
            assert time.monotonic() < end, f"{self.name}: timed out waiting for {what}; status {st}\n" \
                                           + self.log()[-3000:]
            time.sleep(0.05)

    def stop(self, sig=signal.SIGTERM, timeout: float = 30.0) -> tuple[int, float]:
        """Send ``sig``; returns (exit code, seconds until the process was gone)."""
        t0 = time.monotonic()
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
        try:
            rc = self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            rc = self.popen.wait()
        return rc, time.monotonic() - t0

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()
        self._log.close()


def rss_kb(pid: int) -> int:
    """Resident set size of ``pid`` in kB (VmRSS of /proc/<pid>/status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for {pid}")


class Producer(GtProducer):
    """The test as the frame + GT pose source of a mapper process (paced by its acknowledgement)."""

    def stream(self, svc: "Svc", ids, in_flight: int = 2, stop_when: Optional[Callable[[dict], bool]] = None):
        """Send ``ids`` keeping at most ``in_flight`` frames beyond the service's ack; returns early
        (with the status) once ``stop_when(status)`` holds."""
        for i in ids:
            st = svc.wait_for(lambda s: s.get("frame_seq", -1) >= i - in_flight or (stop_when and stop_when(s)),
                              TIMEOUT, f"ack of frame {i - in_flight}")
            if stop_when and stop_when(st):
                return st
            self.send(i)
        return svc.status()


# ============================================================================ determinism
def map_digest(scene_dir: str, frames: int = 10, threads: int = 1) -> str:
    """sha256 over the field tensors (name, dtype, shape, bytes) and every frame pose after mapping
    ``frames`` frames of ``scene_dir`` through a MapperCore (GT poses) and its closing stage."""
    from fmapping.datasets import open_dataset
    from services.mapper.core import MapperCore, MapperServiceOptions

    torch.set_num_threads(threads)
    ds = open_dataset(scene_dir)
    core = MapperCore(small_cfg(), MapperServiceOptions(pose_source="gt", points_interval=1e9, checkpoint_every=0))
    feed(core, ds, range(frames))
    core.finish()
    h = hashlib.sha256()
    for k, v in sorted(core.mapper.field.state_dict().items()):
        t = v.detach().cpu().contiguous()
        h.update(f"{k}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.numpy().tobytes())
    for i, p in sorted(core.mapper.frame_poses().items()):
        h.update(np.ascontiguousarray(p).tobytes())
    return h.hexdigest()
