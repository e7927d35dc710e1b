"""Bring-your-own-camera sources: image folders, videos, webcams, EuRoC, ScanNet, ROS bags.

Every fixture is a few tiny frames written here; each reader must give back what was written
(frames, intrinsics, poses, timestamps), and a source without intrinsics must say how to give them.
"""
from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from fakes import FakeSession, fake_up
from fmapping.camera import PinholeCamera
from fmapping.datasets import DatasetError, LiveCamera, detect_kind, open_dataset

W, H = 32, 24


def _write(path, rgb):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def _rgb(rng, h=H, w=W):
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def _rot(axis, deg):
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _pose(r, t):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


# ------------------------------------------------------------------ image folder
def _image_folder(root, n=4, seed=0):
    rng = np.random.default_rng(seed)
    names = [f"img_{k}.png" for k in (1, 2, 10, 3)][:n]  # name order must compare numbers as numbers
    imgs = {}
    for name in names:
        imgs[name] = _rgb(rng)
        _write(root / name, imgs[name])
    order = sorted(names, key=lambda s: int(s[4:-4]))
    return [imgs[k] for k in order]


def test_image_folder_with_calib(tmp_path):
    want = _image_folder(tmp_path)
    (tmp_path / "calib.txt").write_text("# fx fy cx cy\n20 21 15.5 11.5\n")
    assert detect_kind(tmp_path) == "images"
    ds = open_dataset(tmp_path)
    assert ds.kind == "images" and len(ds) == 4 and not ds.has_depth
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy) == (20, 21, 15.5, 11.5)
    assert ds.camera.size == (W, H)
    np.testing.assert_allclose(ds.timestamps, np.arange(4) / 30.0)
    for i in range(4):
        np.testing.assert_array_equal(ds[i].rgb, want[i])
    assert all(p is None for p in ds.gt_poses)
    assert ds.describe()["camera_source"].endswith("calib.txt")
    np.testing.assert_allclose(open_dataset(tmp_path, fps=10, max_frames=2).timestamps, [0.0, 0.1])


def test_image_folder_without_intrinsics_says_how(tmp_path):
    _image_folder(tmp_path)
    with pytest.raises(DatasetError) as e:
        open_dataset(tmp_path)
    msg = str(e.value)
    assert str(tmp_path) in msg and "--camera fx,fy,cx,cy" in msg and "calib.txt" in msg and "camera.yaml" in msg
    ds = open_dataset(tmp_path, camera="20,20,15.5,11.5")  # the override alone is enough
    assert ds.camera.fx == 20 and ds.meta["camera_source"] == "--camera"


def test_image_folder_camera_yaml_and_ros_yaml(tmp_path):
    folder = tmp_path / "imgs"
    _image_folder(folder, n=3)
    (folder / "camera.yaml").write_text("fx: 25\nfy: 26\ncx: 16\ncy: 12\nwidth: 32\nheight: 24\nfps: 15\n")
    ds = open_dataset(folder)
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy) == (25, 26, 16, 12)
    np.testing.assert_allclose(ds.timestamps, np.arange(3) / 15.0)
    # --camera PATH: a ROS camera_info yaml (what camera_calibration writes), with distortion
    ros = tmp_path / "ost.yaml"
    ros.write_text(
        "image_width: 32\nimage_height: 24\ncamera_name: cam\n"
        "camera_matrix: {rows: 3, cols: 3, data: [30, 0, 15.5, 0, 31, 11.5, 0, 0, 1]}\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients: {rows: 1, cols: 5, data: [0.1, -0.05, 0.001, 0.002, 0.0]}\n"
    )
    ds = open_dataset(folder, camera=str(ros))
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy) == (30, 31, 15.5, 11.5)
    assert ds.camera.dist is None and ds.meta["distortion"] == [0.1, -0.05, 0.001, 0.002, 0.0]
    assert ds.meta["camera_source"] == str(ros)
    raw = cv2.imread(str(folder / "img_1.png"))[..., ::-1]
    np.testing.assert_array_equal(ds[0].rgb, ds.raw_camera.undistort_image(np.ascontiguousarray(raw)))
    with pytest.raises(DatasetError, match="applies to"):
        open_dataset(folder, topic="/cam")


# ------------------------------------------------------------------ video and live camera
VW, VH, VFPS, VN = 64, 48, 12.0, 7


def _video(path):
    """VN frames of flat colours (they survive the lossy codec) at VFPS."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), VFPS, (VW, VH))
    assert writer.isOpened(), "this OpenCV build cannot write mp4v"
    colours = [(40 * k % 256, 255 - 30 * k, 100 + 20 * k) for k in range(VN)]
    for c in colours:
        writer.write(np.full((VH, VW, 3), c[::-1], np.uint8))  # written BGR
    writer.release()
    return np.asarray(colours, np.float64)


def test_video_file(tmp_path):
    colours = _video(tmp_path / "clip.mp4")
    (tmp_path / "calib.txt").write_text("50 50 31.5 23.5\n")
    assert detect_kind(tmp_path / "clip.mp4") == "video"
    ds = open_dataset(tmp_path / "clip.mp4")
    assert ds.kind == "video" and len(ds) == VN and ds.camera.size == (VW, VH)
    np.testing.assert_allclose(ds.timestamps, np.arange(VN) / VFPS)
    seq = [ds[i].rgb for i in range(VN)]
    for i, img in enumerate(seq):
        assert img.shape == (VH, VW, 3) and img.dtype == np.uint8
        np.testing.assert_allclose(img.reshape(-1, 3).mean(0), colours[i], atol=8)
    # going back or skipping ahead gives the same frames as reading in order
    np.testing.assert_array_equal(ds[2].rgb, seq[2])
    np.testing.assert_array_equal(ds[5].rgb, seq[5])
    assert ds[-1].index == VN - 1 and ds[3].timestamp == pytest.approx(3 / VFPS)
    assert len(open_dataset(tmp_path / "clip.mp4", max_frames=3)) == 3
    np.testing.assert_allclose(open_dataset(tmp_path / "clip.mp4", fps=24).timestamps, np.arange(VN) / 24)
    ds.close()


def test_video_without_intrinsics_says_how(tmp_path):
    _video(tmp_path / "clip.avi")
    with pytest.raises(DatasetError, match=r"clip\.avi.*no camera intrinsics.*--camera"):
        open_dataset(tmp_path / "clip.avi")


def test_live_camera_only_where_streamed(tmp_path):
    with pytest.raises(DatasetError, match="live camera stream.*services.io play"):
        open_dataset("camera:0")
    # refused before any device is opened when no intrinsics are given
    with pytest.raises(DatasetError, match="no camera intrinsics.*--camera"):
        open_dataset("camera:0", live=True)
    # the live reader itself, on a file instead of a device: frames in order, no length, then IndexError
    colours = _video(tmp_path / "clip.mp4")
    cam = LiveCamera(str(tmp_path / "clip.mp4"), camera="50,50,31.5,23.5", max_frames=5)
    with pytest.raises(TypeError, match="no length"):
        len(cam)
    frames = list(cam)
    assert [f.index for f in frames] == list(range(5))
    for f, c in zip(frames, colours):
        np.testing.assert_allclose(f.rgb.reshape(-1, 3).mean(0), c, atol=8)
    assert np.all(np.diff([f.timestamp for f in frames]) >= 0)
    assert cam.describe()["live"] is True and cam.camera.fx == 50
    cam.close()


# ------------------------------------------------------------------ EuRoC
T_BS = _pose(_rot(2, 90) @ _rot(0, -90), [-0.02, -0.06, 0.01])  # camera axes in the body frame, plus a lever arm
EUROC_DIST = [-0.28, 0.07, 0.0002, 1.8e-05]


def _euroc(root, n=3):
    rng = np.random.default_rng(3)
    cam = root / "mav0" / "cam0"
    t0 = 1403636579763555584
    ns = [t0 + k * 50_000_000 for k in range(n)]  # 20 Hz
    lines = ["#timestamp [ns],filename"]
    grey = []
    for t in ns:
        g = rng.integers(0, 256, (H, W), dtype=np.uint8)
        (cam / "data").mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(cam / "data" / f"{t}.png"), g)
        lines.append(f"{t},{t}.png")
        grey.append(g)
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    data = ", ".join(repr(float(v)) for v in T_BS.reshape(-1))
    (cam / "sensor.yaml").write_text(
        "# General sensor definitions.\nsensor_type: camera\ncomment: VI-Sensor cam0 (MT9M034)\n\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n\n"
        f"rate_hz: 20\nresolution: [{W}, {H}]\ncamera_model: pinhole\n"
        "intrinsics: [30.5, 30.25, 15.75, 11.25] #fu, fv, cu, cv\n"
        f"distortion_model: radial-tangential\ndistortion_coefficients: {EUROC_DIST}\n"
    )
    # body poses: frame 0 exactly on a row; frame 1 halfway between two rows (rotation about z, linear
    # translation); frame 2 after the last row (beyond 0.02 s: no ground truth)
    rows = [
        (ns[0], [1.0, 2.0, 3.0], 0.0),
        (ns[1] - 5_000_000, [1.0, 2.0, 3.0], 10.0),
        (ns[1] + 5_000_000, [1.2, 2.0, 2.8], 30.0),
    ]
    gt = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt.parent.mkdir(parents=True)
    out = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
           "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
           "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"]
    for t, p, deg in rows:
        h = np.deg2rad(deg) / 2
        out.append(",".join([str(t), *map(repr, p), repr(float(np.cos(h))), "0.0", "0.0", repr(float(np.sin(h)))]
                            + ["0.0"] * 9))
    gt.write_text("\n".join(out) + "\n")
    return ns, grey


def test_euroc(tmp_path):
    ns, grey = _euroc(tmp_path)
    for root in (tmp_path, tmp_path / "mav0"):
        assert detect_kind(root) == "euroc"
    ds = open_dataset(tmp_path)
    assert ds.kind == "euroc" and len(ds) == 3
    np.testing.assert_allclose(ds.timestamps, np.asarray(ns) / 1e9, rtol=0, atol=1e-6)
    raw = ds.raw_camera
    assert (raw.fx, raw.fy, raw.cx, raw.cy) == (30.5, 30.25, 15.75, 11.25)
    assert raw.dist == tuple(EUROC_DIST) and ds.camera.dist is None
    f = ds[0]
    assert f.rgb.shape == (H, W, 3)
    np.testing.assert_array_equal(f.rgb[..., 0], f.rgb[..., 2])  # grey delivered as 3 equal channels
    np.testing.assert_array_equal(f.rgb, raw.undistort_image(np.repeat(grey[0][..., None], 3, axis=2)))
    # camera pose = body pose (from the GT file) @ T_BS
    np.testing.assert_allclose(ds.gt_poses[0], _pose(np.eye(3), [1, 2, 3]) @ T_BS, atol=1e-12)
    np.testing.assert_allclose(ds.gt_poses[1], _pose(_rot(2, 20), [1.1, 2.0, 2.9]) @ T_BS, atol=1e-9)
    assert ds.gt_poses[2] is None
    assert ds.meta["groundtruth_association"] == {"interpolated": 2, "nearest": 0, "none": 1}


# ------------------------------------------------------------------ ScanNet
SCW, SCH = 40, 30


def _scannet(root, depth_size=(20, 15), intrinsic_depth=True):
    rng = np.random.default_rng(4)
    k = np.array([[35.5, 0, 19.75, 0], [0, 35.25, 14.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    (root / "intrinsic").mkdir(parents=True)
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", k, fmt="%.17g")
    dw, dh = depth_size
    s = dw / SCW  # the depth camera sees the same view at a lower resolution
    kd = np.array([[k[0, 0] * s, 0, (k[0, 2] + 0.5) * s - 0.5, 0], [0, k[1, 1] * s, (k[1, 2] + 0.5) * s - 0.5, 0],
                   [0, 0, 1, 0], [0, 0, 0, 1]])
    if intrinsic_depth:
        np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", kd, fmt="%.17g")
    poses = []
    for sub in ("color", "depth", "pose"):
        (root / sub).mkdir()
    for i in range(3):
        cv2.imwrite(str(root / "color" / f"{i}.jpg"), _rgb(rng, SCH, SCW))
        u, v = np.meshgrid(np.arange(dw), np.arange(dh))
        cv2.imwrite(str(root / "depth" / f"{i}.png"), (1000 + 10 * u + 100 * v + i).astype(np.uint16))
        p = _pose(_rot(1, 17.3 * i + 0.1) @ _rot(0, 3.7), rng.normal(size=3))
        if i == 2:
            p = np.full((4, 4), -np.inf)  # ScanNet's mark of a frame without a pose
        np.savetxt(root / "pose" / f"{i}.txt", p, fmt="%.17g")
        poses.append(p)
    return k, kd, poses


def test_scannet(tmp_path):
    k, kd, poses = _scannet(tmp_path)
    assert detect_kind(tmp_path) == "scannet"
    ds = open_dataset(tmp_path)
    assert ds.kind == "scannet" and len(ds) == 3 and ds.depth_scale == 1000.0
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy) == (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    assert ds.camera.size == (SCW, SCH)
    np.testing.assert_array_equal(ds.gt_poses[0], poses[0])  # exactly what was written
    np.testing.assert_array_equal(ds.gt_poses[1], poses[1])
    assert ds.gt_poses[2] is None
    np.testing.assert_allclose(ds.timestamps, np.arange(3) / 30.0)
    f = ds[1]
    assert f.depth.shape == (SCH, SCW) and f.rgb.shape == (SCH, SCW, 3)
    np.testing.assert_array_equal(f.c2w, poses[1])
    # each colour pixel gets the depth pixel on its ray: u_d = (u + 0.5) / 2 - 0.5, nearest
    u, v = np.meshgrid(np.arange(SCW), np.arange(SCH))
    ud = (u - k[0, 2]) / k[0, 0] * kd[0, 0] + kd[0, 2]
    vd = (v - k[1, 2]) / k[1, 1] * kd[1, 1] + kd[1, 2]
    inside = (ud > 0) & (vd > 0) & (ud < 19) & (vd < 14)
    want = (1000 + 10 * ud + 100 * vd + 1) / 1000.0
    assert np.abs(f.depth - want)[inside].max() <= (10 * 0.5 + 100 * 0.5) / 1000 + 1e-6
    assert np.all(f.depth[inside] > 0)


def test_scannet_depth_of_another_size_without_its_intrinsics_is_ignored(tmp_path):
    _scannet(tmp_path, intrinsic_depth=False)
    ds = open_dataset(tmp_path)
    assert not ds.has_depth and ds[0].depth is None and "ignored" in ds.meta["depth_note"]


# ------------------------------------------------------------------ ROS bags
def _bag(path, storage="sqlite3", n=3, camera_info=True, compressed=False):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    img_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    rng = np.random.default_rng(5)
    imgs, stamps = [], []
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        ci = w.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        ic = w.add_connection("/cam/image_raw", img_type, typestore=ts)
        w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)  # another topic, never read
        for i in range(n):
            stamp_ns = 1_700_000_000_000_000_000 + i * 33_333_333
            header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="cam")
            rgb = _rgb(rng)
            if compressed:
                ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
                msg = T[img_type](header=header, format="png", data=buf.reshape(-1))
            else:
                step = W * 3 + 4  # rows padded past the pixels, as some drivers do
                data = np.zeros((H, step), np.uint8)
                data[:, : W * 3] = rgb.reshape(H, -1)
                msg = T[img_type](header=header, height=H, width=W, encoding="rgb8", is_bigendian=0,
                                  step=step, data=data.reshape(-1))
            if camera_info and i == 0:
                info = T["sensor_msgs/msg/CameraInfo"](
                    header=header, height=H, width=W, distortion_model="plumb_bob", d=np.zeros(5),
                    k=np.array([28.0, 0, 15.5, 0, 29.0, 11.5, 0, 0, 1]), r=np.eye(3).reshape(-1),
                    p=np.zeros(12), binning_x=0, binning_y=0,
                    roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                              do_rectify=False))
                w.write(ci, stamp_ns + 1000, ts.serialize_cdr(info, info.__msgtype__))
            w.write(ic, stamp_ns + 2_000_000, ts.serialize_cdr(msg, img_type))  # received 2 ms after capture
            imgs.append(rgb)
            stamps.append(stamp_ns)
    return imgs, stamps


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_rosbag_images_and_camera_info(tmp_path, storage):
    pytest.importorskip("rosbags")
    bag = tmp_path / "bag"
    imgs, stamps = _bag(bag, storage)
    assert detect_kind(bag) == "rosbag"
    ds = open_dataset(bag)
    assert ds.kind == "rosbag" and len(ds) == 3 and ds.meta["topic"] == "/cam/image_raw"
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy) == (28, 29, 15.5, 11.5)
    assert ds.camera.size == (W, H) and ds.meta["camera_source"].endswith("/cam/camera_info")
    assert ds.meta["timestamps"] == "header.stamp"
    np.testing.assert_allclose(ds.timestamps, np.asarray(stamps) / 1e9, rtol=0, atol=1e-6)
    for i in (2, 0, 1):  # any order
        np.testing.assert_array_equal(ds[i].rgb, imgs[i])
    # the storage file alone opens the same bag
    inner = next(bag.glob("*.mcap" if storage == "mcap" else "*.db3"))
    assert detect_kind(inner) == "rosbag" and len(open_dataset(inner, max_frames=2)) == 2
    ds.close()


def test_rosbag_compressed_without_camera_info(tmp_path):
    pytest.importorskip("rosbags")
    bag = tmp_path / "bag"
    imgs, _ = _bag(bag, camera_info=False, compressed=True)
    with pytest.raises(DatasetError, match="without a CameraInfo.*--camera"):
        open_dataset(bag)
    ds = open_dataset(bag, camera="30,30,15.5,11.5", topic="/cam/image_raw")
    np.testing.assert_array_equal(ds[1].rgb, imgs[1])
    with pytest.raises(DatasetError, match="not an Image"):
        open_dataset(bag, camera="30,30,15.5,11.5", topic="/imu")


def test_rosbag_without_the_extra_names_it(tmp_path, monkeypatch):
    (tmp_path / "x.mcap").write_bytes(b"")
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import fails as if not installed
    with pytest.raises(DatasetError, match=r"fmapping\[ros\]"):
        open_dataset(tmp_path / "x.mcap")


def test_camera_override_object_and_unknown_file(tmp_path):
    _image_folder(tmp_path, n=2)
    cam = PinholeCamera(22, 22, 15.5, 11.5, W, H)
    assert open_dataset(tmp_path, camera=cam).camera == cam
    (tmp_path / "notes.bin").write_bytes(b"\0")
    with pytest.raises(DatasetError, match="not a dataset file"):
        open_dataset(tmp_path / "notes.bin")


def test_play_streams_a_live_camera_to_its_end(tmp_path):
    """services.io play sends a live source frame after frame until it ends, then the end-of-sequence stop."""
    import argparse

    from fmapping import protocol as P
    from services.io import play
    from services.transport import Service

    _video(tmp_path / "clip.mp4")
    live = LiveCamera(str(tmp_path / "clip.mp4"), camera="50,50,31.5,23.5", max_frames=4)
    args = play.add_args(argparse.ArgumentParser()).parse_args(
        ["--data", "camera:0", "--ack-from", "", "--wait-for", ""])
    session, keys = FakeSession(), P.Keys("live")
    svc = Service("play", args, session=session, keys=keys, install_signals=False)
    assert play.Player(svc, live, args).run() == 0
    frames = [P.decode(d, P.Frame) for k, d in session.puts if k == keys.frames]
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    stop = [P.decode(d, P.Control) for k, d in session.puts if k == keys.control][-1]
    assert stop.command == "stop" and stop.args == {"reason": "end", "last_seq": 3}
    live.close()


# ------------------------------------------------------------------ the source options through fmapping up to io play
def _up_play_argv(monkeypatch, argv):
    """The command line `fmapping up ARGV` gives io play (after `services.io play`), no process started;
    None when up refused the input."""
    from services.cli import main

    started = fake_up(monkeypatch)
    rc = main(["up", "--poses", "gt", "--view", "save", "--insecure"] + argv)
    if rc != 0:
        assert "play" not in started  # bad input: refused before any process
        return None
    play = started["play"]
    return play[play.index("play") + 1:]


def _play_opens(argv):
    """The source `python -m services.io play ARGV` plays (its own parser, its own opening)."""
    from services.io import play
    from services.process import service_parser

    return play.open_source(play.add_args(service_parser("services.io play", None)).parse_args(argv))


def test_up_and_play_read_an_image_folder_at_data_fps(tmp_path, monkeypatch):
    want = _image_folder(tmp_path / "imgs")
    argv = _up_play_argv(monkeypatch, ["--data", str(tmp_path / "imgs"), "--camera", "20,21,15.5,11.5",
                                       "--fps", "2", "--data-fps", "12.5", "--out", str(tmp_path / "up")])
    assert float(argv[argv.index("--fps") + 1]) == 2.0  # the playback rate stays play's own
    ds = _play_opens(argv)
    assert ds.kind == "images" and len(ds) == 4 and ds.camera.fx == 20
    np.testing.assert_allclose(np.diff(ds.timestamps), 1 / 12.5)
    np.testing.assert_array_equal(ds[3].rgb, want[3])
    # without --data-fps: none passed on, the folder's default rate
    argv = _up_play_argv(monkeypatch, ["--data", str(tmp_path / "imgs"), "--camera", "20,21,15.5,11.5",
                                       "--out", str(tmp_path / "up")])
    assert "--data-fps" not in argv and "--topic" not in argv
    np.testing.assert_allclose(np.diff(_play_opens(argv).timestamps), 1 / 30)


def test_up_and_play_read_a_video_at_data_fps(tmp_path, monkeypatch):
    colours = _video(tmp_path / "clip.mp4")
    (tmp_path / "calib.txt").write_text("50 50 31.5 23.5\n")
    argv = _up_play_argv(monkeypatch, ["--data", str(tmp_path / "clip.mp4"), "--data-fps", "24",
                                       "--out", str(tmp_path / "up")])
    ds = _play_opens(argv)
    assert ds.kind == "video" and len(ds) == VN
    np.testing.assert_allclose(ds.timestamps, np.arange(VN) / 24)
    np.testing.assert_allclose(ds[VN - 1].rgb.reshape(-1, 3).mean(0), colours[VN - 1], atol=8)
    ds.close()
    argv = _up_play_argv(monkeypatch, ["--data", str(tmp_path / "clip.mp4"), "--out", str(tmp_path / "up")])
    ds = _play_opens(argv)
    np.testing.assert_allclose(ds.timestamps, np.arange(VN) / VFPS)  # the file's own rate
    ds.close()


def test_up_and_play_take_a_bags_topic(tmp_path, monkeypatch, capsys):
    pytest.importorskip("rosbags")
    bag = tmp_path / "bag"
    imgs, stamps = _bag(bag, camera_info=False, compressed=True)
    cam = "30,30,15.5,11.5"
    argv = _up_play_argv(monkeypatch, ["--data", str(bag), "--camera", cam, "--topic", "/cam/image_raw",
                                       "--out", str(tmp_path / "up")])
    assert argv[argv.index("--topic") + 1] == "/cam/image_raw"
    ds = _play_opens(argv)
    assert ds.meta["topic"] == "/cam/image_raw" and len(ds) == 3
    np.testing.assert_allclose(ds.timestamps, np.asarray(stamps) / 1e9, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(ds[2].rgb, imgs[2])
    ds.close()
    # a topic without images: one line from up before anything starts, and from play itself
    capsys.readouterr()
    assert _up_play_argv(monkeypatch, ["--data", str(bag), "--camera", cam, "--topic", "/imu",
                                       "--out", str(tmp_path / "up")]) is None
    err = capsys.readouterr().err.strip()
    assert err.startswith("fmapping up: error:") and "/imu" in err and len(err.splitlines()) == 1
    from services.io.__main__ import main as io_main

    assert io_main(["play", "--data", str(bag), "--camera", cam, "--topic", "/imu"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("services.io play: error:") and "/imu" in err and len(err.splitlines()) == 1


def test_a_camera_that_does_not_open_is_one_line(capfd):
    from services.io.__main__ import main as io_main

    assert io_main(["play", "--data", "camera:63", "--camera", "20,20,15.5,11.5"]) == 2  # no device 63
    err = capfd.readouterr().err.strip()
    assert err == "services.io play: error: cannot open camera:63 with OpenCV (missing file or device, or a codec " \
                  "this build lacks)"


def test_source_options_that_do_not_apply_are_refused(tmp_path, capsys):
    from services.io.__main__ import main as io_main

    _image_folder(tmp_path / "imgs")
    assert io_main(["play", "--data", str(tmp_path / "imgs"), "--camera", "20,20,15.5,11.5", "--topic", "/x"]) == 2
    assert "topic= applies to rosbag sources, not to images" in capsys.readouterr().err
    with pytest.raises(DatasetError, match="fps= applies to images / video sources, not to a live camera"):
        open_dataset("camera:0", camera="20,20,15.5,11.5", fps=10, live=True)
