"""``io view`` (services/io/view.py): what the zenoh-free Viewer logs (trajectories, keyframes,
lag, map points, final map and mesh; depth only when the run uses depth; colour and depth
rendered from the field snapshot and a live mesh, rate-limited), the .rrd it writes read
back with ``rerun rrd print``, serving the web viewer on a given port, and the view options
``fmapping up --view live|save`` passes."""
from __future__ import annotations

import argparse
import dataclasses
import os
import threading
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
        self.archetypes: list[tuple[str, object]] = []
        self._lock = threading.Lock()  # the service's Viewer logs from its preview thread too

    def log(self, entity, archetype, static=False):
        with self._lock:
            self.logged.append((entity, type(archetype).__name__, static))
            self.archetypes.append((entity, archetype))

    def last(self, entity):
        return [a for e, a in self.archetypes if e == entity][-1]

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
    from services.zenoh_session import free_port

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
    from services.cli import build_parser
    from services.launcher.commands import live_url, view_argv, view_mode

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


# ---------------------------------------------------------------- rendered views and the live mesh
BLOB_CENTRE, BLOB_HALF = np.array([0.0, 0.0, 2.0]), 0.3  # an opaque cube 2 m in front of the camera at the origin
BOX = np.array([[-1.0, -1.0, 0.5], [1.0, 1.0, 3.5]])


def _blob_snapshot(frame_seq: int = 5, **config) -> P.FieldSnapshot:
    """A small CP field over ``BOX`` that is empty but for an opaque cube (``BLOB_*``): one density
    component whose three lines are constant inside the cube's extent and 0 outside, so that
    ``raw = 60`` inside (``softplus(60 - 10)`` = 50 / m: opaque within centimetres)."""
    import torch

    from fmapping.field import FieldConfig, build_field

    cfg = FieldConfig(resolution=64, density_components=2, appearance_components=2, app_features=4, hidden=8)
    field = build_field(cfg, BOX)
    with torch.no_grad():
        field.density_lines.zero_()
        for a in range(3):
            nodes = np.linspace(BOX[0, a], BOX[1, a], cfg.resolution)
            inside = np.abs(nodes - BLOB_CENTRE[a]) <= BLOB_HALF
            field.density_lines[a, 0, :, 0] = torch.as_tensor(np.where(inside, 60.0 ** (1 / 3), 0.0))
    conf = {"field": dataclasses.asdict(cfg), "near": 0.1, "far": 6.0, "n_coarse": 64, "n_fine": 16, **config}
    return P.FieldSnapshot(version=1, kind="cp", config=conf, aabb=BOX.copy(), arrays=field.snapshot(),
                           frame_seq=frame_seq, frame_c2w=np.eye(4))


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def _image_array(arch) -> np.ndarray:
    """The pixels of a logged rr.DepthImage (float32) as (H, W)."""
    fmt = arch.image_format()
    values = arch.buffer.as_arrow_array()[0].values.to_numpy(zero_copy_only=False)
    return np.frombuffer(values.tobytes(), np.float32).reshape(fmt.height, fmt.width)


def _posed(viewer, n: int = 6, depth: bool = True) -> None:
    """Frames 0..n-1 at the origin looking down +z (the blob ahead), tracker and GT poses."""
    for i in range(n):
        viewer.on_frame(_frame(i, depth=depth))
        for src in ("gt", "tracker"):
            viewer.on_pose(P.Pose(seq=i, timestamp=float(i), c2w=np.eye(4), source=src))


def test_field_snapshot_renders_depth_and_colour_next_to_the_input_image_and_a_mesh():
    cap, clock = Capture(), Clock()
    v = view.Viewer(cap, clock=clock, render_width=160)  # RGB-only run (no --depth-every)
    _posed(v)
    v.on_field(_blob_snapshot())
    assert v.renders == 1 and v.meshes == 1
    ents = cap.entities()
    assert {"world/camera/rendered", "world/camera/rendered/rgb", "world/camera/rendered/depth",
            "world/map/mesh_live", "world/camera/image"} <= ents
    assert "world/camera/image/depth" not in ents  # the dataset's depth stays out of an RGB-only run
    # rendered at the newest frame's pose, in the camera's tree, at the preview size (never enlarged: 32 px wide)
    pin = cap.last("world/camera/rendered")
    assert [int(x) for x in pin.resolution.as_arrow_array().to_pylist()[0]] == [32, 24]
    depth = _image_array(cap.last("world/camera/rendered/depth"))
    assert depth.shape == (24, 32)
    front = BLOB_CENTRE[2] - BLOB_HALF  # 1.7 m: the cube's face towards the camera
    # the cube spans |x|, |y| <= 0.3 at z = 1.7: pixels within 0.3 * 40 / 1.7 = 7 px of the centre see it
    centre = depth[11 - 4:13 + 4, 15 - 4:17 + 4]
    assert np.all(np.abs(centre - front) < 0.08), centre
    assert depth[0, 0] == 0 and depth[-1, -1] == 0  # the corners see empty space: no depth
    rgb = cap.last("world/camera/rendered/rgb")
    assert rgb.image_format().width == 32
    mesh = cap.last("world/map/mesh_live")
    faces = mesh.triangle_indices.as_arrow_array()
    verts = np.array(mesh.vertex_positions.as_arrow_array().to_pylist())
    assert len(faces) > 0 and np.abs(verts - BLOB_CENTRE).max() < BLOB_HALF + 0.1


def test_rendered_view_is_the_blob_depth_at_the_preview_resolution():
    from fmapping.camera import PinholeCamera

    field, rs = view.field_of_snapshot(_blob_snapshot())
    assert (rs.n_coarse, rs.n_fine) == view.PREVIEW_SAMPLES  # capped: a preview needs no more
    big = {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480}
    cam = view.preview_camera(big, 160)
    assert (cam.width, cam.height) == (160, 120) and cam == PinholeCamera.from_dict(big).resized(160, 120)
    rgb, depth = view.render_view(field, rs, cam, np.eye(4))
    assert rgb.shape == (120, 160, 3) and rgb.dtype == np.uint8 and depth.dtype == np.float32
    # the face is 0.6 m wide at 1.7 m: 0.6 * 125 / 1.7 = 44 px wide in the preview (fx = 125)
    assert np.all(np.abs(depth[60 - 15:60 + 15, 80 - 15:80 + 15] - 1.7) < 0.08)
    assert (depth > 0).sum() == pytest.approx(44 * 44, rel=0.2)


def test_previews_in_small_chunks_equal_the_one_pass_render_and_mesh():
    """The preview renders ``PREVIEW_CHUNK`` rays and evaluates the mesh grid ``MESH_GRID_CHUNK`` nodes at a
    time (a tenth of the temporaries): the same image and mesh as in one pass (well under 1,024 / 32,768 here
    would be one chunk, so the sizes below force several)."""
    import torch

    from fmapping.camera import PinholeCamera
    from fmapping.export import export_mesh
    from fmapping.render import render_image

    field, rs = view.field_of_snapshot(_blob_snapshot())
    big = {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480}
    cam = view.preview_camera(big, 160)
    assert cam.width * cam.height > 4 * view.PREVIEW_CHUNK
    rgb, depth = view.render_view(field, rs, cam, np.eye(4))
    one = render_image(field, cam, np.eye(4), rs.near, rs.far, rs.n_coarse, background=0.0,
                       n_importance=rs.n_fine, chunk=cam.width * cam.height)
    torch.testing.assert_close(torch.from_numpy(rgb), (one["rgb"].clamp(0, 1) * 255).round().to(torch.uint8))
    acc = one["acc"].numpy()
    ref = np.where(acc > 0.5, one["depth_normalized"].numpy(), 0.0).astype(np.float32)
    np.testing.assert_allclose(depth, ref, rtol=1e-5, atol=1e-5)
    res = 64
    assert res ** 3 > 4 * view.MESH_GRID_CHUNK
    poses = [np.eye(4)]
    v, f, c = view.field_mesh(field, rs, PinholeCamera.from_dict(big), poses, res)
    v1, f1, c1 = export_mesh(field, field.aabb, res, poses, PinholeCamera.from_dict(big), near=rs.near,
                             far=rs.far, grid_chunk=res ** 3)
    assert len(f) > 0
    np.testing.assert_allclose(v, v1, atol=1e-9)
    np.testing.assert_array_equal(f, f1)
    np.testing.assert_array_equal(c, c1)


def test_renders_and_meshes_are_rate_limited_and_the_mesh_comes_at_the_end():
    cap, clock = Capture(), Clock()
    v = view.Viewer(cap, clock=clock, render_every=2.0, mesh_every=10.0)
    _posed(v)

    def field_after(dt, seq):
        clock.t += dt
        v.render_seconds = v.mesh_seconds = 0.0  # as if instant: the duty limit is tested below
        v.on_field(_blob_snapshot(frame_seq=seq))

    field_after(0.0, 1)
    field_after(1.0, 2)  # within 2 s: no render, no mesh
    assert (v.renders, v.meshes) == (1, 1)
    field_after(1.5, 3)
    assert (v.renders, v.meshes) == (2, 1)
    field_after(8.0, 4)
    assert (v.renders, v.meshes) == (3, 2)
    # a render that took 1 s (a loaded machine) holds the next one back 5 s (20 % of a core), not 2
    v.render_seconds = 1.0
    clock.t += 3.0
    v.on_field(_blob_snapshot(frame_seq=5))
    assert v.renders == 3
    field_after(2.1, 6)
    assert v.renders == 4
    v.finish()  # the mesh of the newest field, whatever the time
    assert v.meshes == 3

    only_end = view.Viewer(Capture(), clock=Clock(), render_every=0, mesh_every=0)  # 0: never / only at the end
    _posed(only_end)
    only_end.on_field(_blob_snapshot())
    assert (only_end.renders, only_end.meshes) == (0, 0)
    only_end.finish()
    assert (only_end.renders, only_end.meshes) == (0, 1) and "world/map/mesh_live" in only_end.rec.entities()


def test_the_final_mesh_ply_replaces_the_live_mesh_at_the_end():
    cap = Capture()
    v = view.Viewer(cap, clock=Clock())
    _posed(v)
    v.on_field(_blob_snapshot())
    v.finish(final_mesh_logged=True)
    assert v.meshes == 1  # no end-of-run live mesh: the mapper's own (finer, occlusion-culled) one is there
    assert [k for e, k, _ in cap.logged if e == "world/map/mesh_live"] == ["Mesh3D", "Clear"]


def test_the_service_renders_on_its_own_thread_and_survives_a_forged_snapshot():
    cap, errors = Capture(), []
    v = view.Viewer(cap, background=True, on_error=errors.append)
    _posed(v)
    forged = _blob_snapshot()
    forged.config["field"]["resolution"] = 10 ** 6  # would be gigabytes: refused before building
    v.on_field(forged)
    assert v.worker.wait_idle(60) and len(errors) == 1 and "parameters" in str(errors[0])
    v.render_every = v.mesh_every = 0.0  # next snapshot: no rate limit in the way of the end mesh only
    v.on_field(_blob_snapshot())
    v.finish()
    assert v.worker is None and v.meshes == 1 and len(errors) == 1
    assert "world/map/mesh_live" in cap.entities() and "world/camera/image/depth" not in cap.entities()


def test_a_snapshot_before_any_pose_renders_from_its_own_frame_pose():
    cap = Capture()
    v = view.Viewer(cap, clock=Clock())
    v.on_frame(_frame(0, depth=False))
    v.on_field(_blob_snapshot(frame_seq=0))
    assert v.renders == 1 and "world/camera/rendered/depth" in cap.entities()
    no_camera = view.Viewer(Capture(), clock=Clock())  # neither a frame nor the snapshot says the camera
    no_camera.on_field(_blob_snapshot())
    assert no_camera.renders == 0


def test_saved_recording_of_an_rgb_only_run_with_a_field_has_rendered_but_no_dataset_depth(tmp_path):
    rec = rr.RecordingStream("fmapping_test")
    rec.save(str(tmp_path / "run.rrd"))
    v = view.Viewer(rec)
    _posed(v)
    v.on_field(_blob_snapshot())
    v.finish()
    rec.disconnect()
    text = _rrd_entities(tmp_path / "run.rrd", tmp_path)
    for ent in ("/world/camera/rendered/rgb", "/world/camera/rendered/depth", "/world/map/mesh_live",
                "/world/camera/image"):
        assert ent in text, ent
    assert "/world/camera/image/depth" not in text


_WARM_UP = r"""
import sys
from services.io import view
class Rec:
    def __init__(self):
        self.logged = []
    def log(self, entity, *a, **k):
        self.logged.append(entity)
    def set_time(self, *a, **k):
        pass
MODULES = ("torch", "scipy.spatial", "skimage.measure")
rec, errors = Rec(), []
v = view.Viewer(rec, background=True, on_error=errors.append, torch_threads=1)
before = [m for m in MODULES if m in sys.modules]
v.warm_up()
assert v.worker.wait_idle(120)
import torch
print(before, [m for m in MODULES if m in sys.modules], torch.get_num_threads(), rec.logged, v.renders, v.meshes,
      errors)
"""


def test_the_view_warms_its_previews_up_on_the_preview_thread_at_the_start_and_logs_nothing():
    """The service takes the previews' one-time costs (torch, the mesh's scipy and scikit-image, the first
    kernels: ~45 MB) before the run instead of at the first field snapshot mid-run. In a fresh process: the
    warm-up imports what the previews use, sets the preview thread count, and logs and counts no preview."""
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", _WARM_UP], capture_output=True, text=True, check=True, cwd=root,
                         env={**os.environ, "PYTHONPATH": str(root)}, timeout=300).stdout.strip().splitlines()[-1]
    assert out == "[] ['torch', 'scipy.spatial', 'skimage.measure'] 1 ['world'] 0 0 []", out
