"""The launcher supervises: a service killed with -9 while play streams is started again (bounded,
with backoff, counted in OUT/up.json) and the run completes; the mapper resumes from its checkpoint."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

pytest.importorskip("zenoh")

from fmapping import launcher as L  # noqa: E402
from service_helpers import ROOT, SMALL_MAPPER, subprocess_env  # noqa: E402


class FakeProc:
    def __init__(self, name: str, rc=None):
        self.name, self._rc, self.restarts = name, rc, 0

    @property
    def rc(self):
        return self._rc

    def restart(self):
        self.restarts += 1
        self._rc = None


def test_supervise_restarts_crashes_with_backoff_and_a_bound(capsys):
    procs = {"play": FakeProc("play"), "mapper": FakeProc("mapper", -9), "record": FakeProc("record", 2)}
    pending: dict = {}
    L._supervise(procs, pending, now=100.0)
    assert pending == {"mapper": 100.0 + L.RESTART_BACKOFF}  # bad input (2) is not retried
    L._supervise(procs, pending, now=100.5)
    assert procs["mapper"].restarts == 0
    L._supervise(procs, pending, now=101.0)
    assert procs["mapper"].restarts == 1 and not pending
    for k in range(1, L.MAX_RESTARTS):
        procs["mapper"]._rc = 1
        L._supervise(procs, pending, now=200.0 * k)
        assert pending["mapper"] == 200.0 * k + L.RESTART_BACKOFF * 2 ** k
        L._supervise(procs, pending, now=pending["mapper"])
    procs["mapper"]._rc = 1
    L._supervise(procs, pending, now=1e6)
    assert not pending and procs["mapper"].restarts == L.MAX_RESTARTS  # the bound: it stays down
    procs = {"play": FakeProc("play", 0), "tracker": FakeProc("tracker", -9)}
    L._supervise(procs, pending, now=0.0)
    assert not pending  # play has finished: nobody would send the end-of-sequence stop again
    assert "restarting it in 1 s (1/3)" in capsys.readouterr().err


@pytest.mark.slow
def test_fmapping_up_survives_kill_9_of_the_mapper(scene, tmp_path):
    import yaml

    from fmapping.trajectory import read_tum_trajectory

    cfg = tmp_path / "up.yaml"
    cfg.write_text(yaml.safe_dump({"mapper": SMALL_MAPPER, "launcher": {"timeout": 240, "threads": 1,
                                                                         "view": False}}))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "fmapping.cli", "up", "--data", str(scene), "--poses", "gt",
                             "--out", str(out), "--config", str(cfg)], cwd=ROOT, env=subprocess_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 180
        killed = None
        while killed is None:
            assert proc.poll() is None and time.monotonic() < deadline, "the mapper never checkpointed"
            try:
                st = json.loads((out / "status" / "mapper.json").read_text())
            except (OSError, ValueError):
                st = {}
            if st.get("counters", {}).get("windows", 0) >= 1 and (out / "checkpoint.pt").is_file():
                killed = st
                os.kill(st["pid"], signal.SIGKILL)
            time.sleep(0.02)
        rc = proc.wait(timeout=280)
        log = proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, log[-3000:]
    assert "mapper exited with code -9; restarting it" in log
    up = json.loads((out / "up.json").read_text())
    assert up["restarts"] == {"mapper": 1}
    stats = json.loads((out / "stats.json").read_text())
    assert stats["counters"]["resumes"] == 1 and stats["final"] is True
    ts, _ = read_tum_trajectory(out / "traj.txt")
    lost = 14 - len(ts)
    print(f"\n[supervision] mapper killed at frame {killed['frame_seq']} (windows {killed['counters']['windows']}); "
          f"restarted once, resumed from the checkpoint; {len(ts)} of 14 frames mapped ({lost} lost)")
    # at most the frames play had in flight (window 4) plus those of the update in progress
    assert lost <= 4 + SMALL_MAPPER["new_frames_per_window"] + 2


@pytest.mark.slow
def test_a_router_port_taken_before_it_binds_is_replaced(scene, tmp_path, monkeypatch, capsys):
    """free_port() then bind is a race: when someone takes the router's port first, the router
    fails (nobody can pose as it) and the launcher makes new credentials on another port."""
    import argparse
    import socket

    import yaml

    squatter = socket.socket()
    squatter.bind(("127.0.0.1", 0))
    squatter.listen()
    taken = squatter.getsockname()[1]
    ports = iter([taken])
    real = L.free_port
    monkeypatch.setattr(L, "free_port", lambda host="127.0.0.1": next(ports, None) or real(host))
    cfg = tmp_path / "up.yaml"
    cfg.write_text(yaml.safe_dump({"mapper": SMALL_MAPPER, "launcher": {"timeout": 240, "threads": 1,
                                                                         "view": False}}))
    out = tmp_path / "out"
    try:
        rc = L.run_up(argparse.Namespace(data=str(scene), poses="gt", out=str(out), fps=0.0, config=str(cfg)))
    finally:
        squatter.close()
    err = capsys.readouterr()
    assert rc == 0, err.out[-2000:] + err.err[-2000:]
    # the first router could not bind the taken port: the run announced (and used) another one
    assert f"tcp/127.0.0.1:{taken}" not in err.out and "secure run: router on tcp/127.0.0.1:" in err.out


def test_mapper_skips_the_frames_a_restarted_pose_source_will_never_answer(dataset):
    """The tracker died with frames in flight: its restarted process never saw them. The mapper
    notices the restart (the tracker's status counter starts over) and skips them at once instead
    of holding the player's window for pose_timeout (30 s)."""
    from fmapping import protocol as P
    from service_helpers import feed, gt_messages, small_cfg
    from services.mapper import MapperCore, MapperServiceOptions

    core = MapperCore(small_cfg(), MapperServiceOptions(pose_source="tracker"))
    feed(core, dataset, range(4), source="tracker")  # the init
    assert core.ack == 3
    for i in (4, 5, 6):  # frames whose poses the dead tracker never sent
        core.handle("frames", gt_messages(dataset, i, "tracker")[1])
    core.handle("poses", gt_messages(dataset, 5, "tracker")[0])  # one it did answer
    assert core.ack == 3
    core.on_source_status(P.Status(service="tracker", seq=40))
    core.on_source_status(P.Status(service="mapper", seq=1))  # another service: ignored
    assert core.ack == 3
    core.on_source_status(P.Status(service="tracker", seq=1))  # restarted
    assert core.ack == 6 and core.counters.get("orphaned_frames") == 2 and core.counters.get("source_restarts") == 1
    assert core.seq_of_fid[-1] == 5  # the answered one was mapped, in order
    feed(core, dataset, [7, 8], source="tracker")  # the new tracker's frames go on as usual
    assert core.ack == 8 and core.seq_of_fid[-2:] == [7, 8]
