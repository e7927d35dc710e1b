"""``io view`` (services/io/view.py): what the zenoh-free Viewer logs (trajectories, keyframes,
lag, map points, final map and mesh; depth only when the run uses depth), the .rrd it writes read
back with ``rerun rrd print``, serving the web viewer on a given port, and the view options
``fmapping up --view live|save`` passes."""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from fmapping import protocol as P  # noqa: E402
from services.io import view  # noqa: E402


class Capture:
    """A stand-in RecordingStream: the (entity, archetype name, static) of every log call."""

    def __init__(self):
        self.logged: list[tuple[str, str, bool]] = []

    def log(self, entity, archetype, static=False):
        self.logged.append((entity, type(archetype).__name__, static))

    def set_time(self, *a, **k):
        pass

    def flush(self, *a, **k):
        pass

    def entities(self) -> set[str]:
        return {e for e, _, _ in self.logged}


CAM = {"fx": 40.0, "fy": 40.0, "cx": 15.5, "cy": 11.5, "width": 32, "height": 24}


def _frame(seq: int, depth: bool = True) -> P.Frame:
    return P.Frame(seq=seq, timestamp=float(seq), rgb=np.full((24, 32, 3), 100, np.uint8), camera=dict(CAM),
                   depth=np.full((24, 32), 2.0, np.float32) if depth else None)


def _pose(seq: int, source: str = "tracker", x: float = 0.0) -> P.Pose:
    c2w = np.eye(4)
    c2w[0, 3] = x if x else 0.1 * seq
    return P.Pose(seq=seq, timestamp=float(seq), c2w=c2w, source=source)


def _run(viewer, n: int = 6) -> None:
    for i in range(n):
        viewer.on_frame(_frame(i))
        viewer.on_pose(_pose(i, "tracker"))
        viewer.on_pose(_pose(i, "gt"))
    viewer.on_pose(_pose(2, "tracker", x=5.0))  # a bundle adjustment moved frame 2
    viewer.on_points(P.PointsSnapshot(version=1, points=np.zeros((10, 3), np.float32),
                                      colors=np.zeros((10, 3), np.uint8), frame_seq=n - 1))
    viewer.on_status(P.Status(service="mapper", lag=0.25, counters={"last_keyframe": 0, "windows": 1}))
    viewer.on_status(P.Status(service="mapper", lag=0.5, counters={"last_keyframe": 4}))
    viewer.on_status(P.Status(service="tracker", lag=0.1, counters={"last_keyframe": 99}))  # no pose yet: later
    viewer.finish()


def test_rgb_only_run_logs_no_depth_but_trajectories_keyframes_lag_and_points():
    cap = Capture()
    v = view.Viewer(cap)  # the default: depth_every 0, as fmapping up runs RGB-only
    _run(v)
    ents = cap.entities()
    assert not any("depth" in e for e in ents)
    assert not v.logs_depth(_frame(0))
    assert {"world/traj/tracker", "world/traj/gt", "world/camera/image", "world/map/points",
            "status/mapper/lag", "status/tracker/lag", "world/keyframes"} <= ents
    assert v.keyframes == [0, 4]
    assert {"world/keyframes/kf000000", "world/keyframes/kf000004/frustum"} <= ents
    # the trajectory is in frame order with the newest pose of each frame (no zig-zag back to frame 2's old pose)
    assert sorted(v.poses["tracker"]) == list(range(6)) and v.poses["tracker"][2][0, 3] == 5.0


def test_a_run_that_uses_depth_logs_it():
    cap = Capture()
    v = view.Viewer(cap, depth_every=2)
    _run(v)
    depth_logs = [e for e, kind, _ in cap.logged if e == "world/camera/image/depth"]
    assert len(depth_logs) == 3 and all(k == "DepthImage" for e, k, _ in cap.logged if e.endswith("depth"))
    assert not v.logs_depth(_frame(0, depth=False))


def test_final_map_and_mesh_are_logged_when_this_run_wrote_them(tmp_path):
    from fmapping.ply import write_ply

    pts = np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32)
    write_ply(tmp_path / "map.ply", pts, np.zeros((20, 3), np.uint8))
    write_ply(tmp_path / "mesh.ply", pts[:4], np.zeros((4, 3), np.uint8), faces=np.array([[0, 1, 2], [0, 2, 3]]))
    cap = Capture()
    v = view.Viewer(cap)
    assert v.log_final_outputs(tmp_path) == ["world/map/final", "world/map/mesh"]
    assert ("world/map/mesh", "Mesh3D", True) in cap.logged and ("world/map/final", "Points3D", True) in cap.logged
    assert view.Viewer(Capture()).log_final_outputs(tmp_path, since=os.path.getmtime(tmp_path / "map.ply") + 60) == []


def _rrd_entities(path: Path, home: Path) -> str:
    exe = Path(sys.executable).with_name("rerun")
    exe = str(exe) if exe.is_file() else shutil.which("rerun")
    if exe is None:
        pytest.skip("no rerun CLI to read the .rrd back")
    env = dict(os.environ, HOME=str(home), RERUN_ANALYTICS="0")
    out = subprocess.run([exe, "rrd", "print", str(path)], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_saved_recording_of_an_rgb_only_run_has_no_depth(tmp_path):
    rec = rr.RecordingStream("fmapping_test")
    rec.save(str(tmp_path / "run.rrd"))
    _run(view.Viewer(rec))
    rec.disconnect()
    text = _rrd_entities(tmp_path / "run.rrd", tmp_path)
    for ent in ("/world/traj/tracker", "/world/keyframes", "/world/map/points", "/status/mapper/lag",
                "/world/camera/image"):
        assert ent in text, ent
    assert "depth" not in text.lower()


def _view_args(argv):
    return view.add_args(argparse.ArgumentParser()).parse_args(argv)


def test_live_view_serves_the_web_viewer_on_the_given_port_and_saves_too(tmp_path, capsys):
    from fmapping.launcher import free_port

    web, grpc = free_port(), free_port()
    args = _view_args(["--serve", "--save", str(tmp_path / "run.rrd"), "--web-port", str(web),
                       "--grpc-port", str(grpc)])
    assert view.serving(args) and not view.serving(_view_args(["--save", "x.rrd"])) and view.serving(_view_args([]))
    try:
        rec = view.open_recording(args)
    except Exception as e:  # no sockets or no web assets in this build
        pytest.skip(f"rerun cannot serve here: {e}")
    try:
        rec.log("world/x", rr.Points3D([[0.0, 0.0, 0.0]]))
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as r:
            assert r.status == 200 and r.read(100)
        printed = capsys.readouterr().out
        assert f"http://localhost:{web}/?url=rerun+http://localhost:{grpc}/proxy" in printed
    finally:
        rec.flush(timeout_sec=5)
        rec.disconnect()
    assert (tmp_path / "run.rrd").stat().st_size > 0


def test_fmapping_up_view_options(tmp_path, monkeypatch):
    from fmapping.cli import build_parser
    from fmapping.launcher import live_url, view_argv, view_mode

    a = build_parser().parse_args(["up", "--view", "live", "--view-port", "9191", "--grpc-port", "9877"])
    live = view_argv(tmp_path, "live", a, uses_depth=False)
    assert live[:2] == ["--save", str(tmp_path / "run.rrd")] and "--serve" in live
    assert live[live.index("--web-port") + 1] == "9191" and live[live.index("--grpc-port") + 1] == "9877"
    assert "--depth-every" not in live  # RGB-only: the dataset's depth stays out of the recording
    assert "--depth-every" in view_argv(tmp_path, "save", a, uses_depth=True)
    assert "--serve" not in view_argv(tmp_path, "save", a, uses_depth=False)
    assert live_url(a) == "http://localhost:9191/?url=rerun+http://localhost:9877/proxy"
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert view_mode("auto") == "save" and view_mode(None) == "save" and view_mode("live") == "live"
    assert build_parser().parse_args(["up"]).view == "auto"
    with pytest.raises(ValueError):
        view_mode("browser")
