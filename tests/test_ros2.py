"""The ROS 2 bridge (services/ros2): CDR round trips of poses, paths, clouds and images through
rosbags' serialisers, the key mapping of zenoh-bridge-ros2dds / rmw_zenoh, the bridge core's
bad-input handling, and the zenoh shell publishing a PoseStamped for every tracker pose."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("rosbags")

from fmapping import protocol as P  # noqa: E402
from services.ros2 import convert as C  # noqa: E402
from services.ros2.core import BridgeCore, Topics  # noqa: E402


def _pose(seq: int, t: float, seed: int = 0, source: str = "tracker") -> P.Pose:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    m[:3, 3] = rng.normal(size=3) * 3
    return P.Pose(seq=seq, timestamp=t, c2w=m, source=source)


def test_pose_stamped_cdr_round_trip_is_exact():
    for seed in range(20):
        p = _pose(seed, 1305031102.175304 + seed * 0.033, seed)
        data = C.to_cdr(C.pose_stamped(p), C.POSE_STAMPED)
        assert data[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation, as DDS / rmw_zenoh send
        msg = C.from_cdr(data, C.POSE_STAMPED)
        assert msg.header.frame_id == "map"
        back = C.pose_from_stamped(msg, seq=p.seq, source="tracker")
        np.testing.assert_allclose(back.c2w, p.c2w, atol=1e-9, rtol=0)
        assert abs(back.timestamp - p.timestamp) < 1e-6  # float64 resolution at 1.3e9 s
        assert msg.pose.orientation.w >= 0


def test_ros_time_splits_seconds_without_a_nanosecond_overflow():
    t = C.ros_time(12.9999999999)
    assert (t.sec, t.nanosec) == (13, 0)
    t = C.ros_time(1.5)
    assert (t.sec, t.nanosec) == (1, 500_000_000)


def test_path_cdr_round_trip_keeps_the_order_and_poses():
    poses = [_pose(i, 10.0 + i, i) for i in range(5)]
    msg = C.from_cdr(C.to_cdr(C.path_msg(poses), C.PATH), C.PATH)
    assert len(msg.poses) == 5 and C.seconds(msg.header.stamp) == pytest.approx(14.0)
    for p, m in zip(poses, msg.poses):
        np.testing.assert_allclose(C.c2w_of(m.pose), p.c2w, atol=1e-9, rtol=0)


def test_points_snapshot_to_pointcloud2_and_back():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)).astype(np.float32)
    cols = rng.integers(0, 256, size=(500, 3)).astype(np.uint8)
    snap = P.PointsSnapshot(version=3, points=pts, colors=cols, frame_seq=7)
    data = C.to_cdr(C.cloud_from_snapshot(snap, 5.25), C.POINT_CLOUD2)
    msg = C.from_cdr(data, C.POINT_CLOUD2)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb"] and msg.point_step == 16
    assert (msg.height, msg.width, msg.row_step) == (1, 500, 16 * 500)
    p2, c2 = C.points_of_cloud(msg)
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_array_equal(c2, cols)
    # the packed colour is RViz's 0x00RRGGBB
    assert int(C.pack_rgb(np.array([[1, 2, 3]], np.uint8)).view("<u4")[0]) == 0x010203
    empty = C.from_cdr(C.to_cdr(C.point_cloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), 0.0), C.POINT_CLOUD2),
                       C.POINT_CLOUD2)
    assert C.points_of_cloud(empty)[0].shape == (0, 3)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_image_and_camera_info_become_a_frame(encoding):
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, size=(24, 32, 3)).astype(np.uint8)
    if encoding == "mono8":
        rgb = np.repeat(rgb[..., :1], 3, axis=2)
    cam = {"fx": 30.0, "fy": 31.0, "cx": 15.5, "cy": 11.5, "width": 32, "height": 24}
    src = rgb[..., 0] if encoding == "mono8" else rgb
    img = C.from_cdr(C.to_cdr(C.image_msg(src, 3.5, encoding=encoding), C.IMAGE), C.IMAGE)
    info = C.from_cdr(C.to_cdr(C.camera_info_msg(cam, 3.5), C.CAMERA_INFO), C.CAMERA_INFO)
    f = C.frame_from_ros(img, info, seq=4)
    assert f.seq == 4 and f.timestamp == pytest.approx(3.5) and f.depth is None
    np.testing.assert_array_equal(f.rgb, rgb)
    assert {k: f.camera[k] for k in cam} == cam and not f.camera.get("dist")
    P.decode(P.encode(f), P.Frame)  # a valid protocol message


def test_distorted_camera_info_gives_undistorted_frames_and_bad_images_are_refused():
    rgb = np.full((24, 32, 3), 128, np.uint8)
    cam = {"fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0, "width": 32, "height": 24, "dist": [0.1, -0.05, 0, 0, 0]}
    f = C.frame_from_ros(C.image_msg(rgb, 0.0), C.camera_info_msg(cam, 0.0), seq=0)
    assert f.camera.get("dist") is None and f.camera["fx"] == 30.0
    with pytest.raises(C.RosConversionError, match="is for 32x24"):  # CameraInfo of another resolution
        C.frame_from_ros(C.image_msg(np.zeros((10, 10, 3), np.uint8), 0.0), C.camera_info_msg(cam, 0.0), 0)
    bad = C.image_msg(rgb, 0.0)
    bad.encoding = "16UC1"
    with pytest.raises(C.RosConversionError):
        C.frame_from_ros(bad, C.camera_info_msg(cam, 0.0), 0)


def test_key_mapping_of_the_bridge_and_of_rmw_zenoh():
    b = C.TopicKeys("bridge")
    assert b.publish_key("/fmapping/pose", C.POSE_STAMPED) == "fmapping/pose"
    prefixed = C.TopicKeys("bridge", prefix="/robot1")  # the bridge's ROS namespace
    assert prefixed.subscribe_key("/camera/image_raw", C.IMAGE) == "robot1/camera/image_raw"
    r = C.TopicKeys("rmw", domain=3)
    key = r.publish_key("/fmapping/pose", C.POSE_STAMPED)
    assert key.startswith("3/fmapping/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_")
    assert len(key.rsplit("/", 1)[1]) == 71  # RIHS01_ + 64 hex digits
    assert r.subscribe_key("/camera/image_raw", C.IMAGE) == "3/camera/image_raw/sensor_msgs::msg::dds_::Image_/*"
    with pytest.raises(ValueError):
        C.TopicKeys("dds")


def test_rmw_attachment_reads_back_with_zenoh_ext():
    zenoh = pytest.importorskip("zenoh")
    att = C.rmw_attachment(7, 123456789, bytes(range(16)))
    ext = pytest.importorskip("zenoh.ext")
    vals = ext.z_deserialize(tuple[str, ext.Int64, str, ext.Int64, str, bytes], zenoh.ZBytes(att))
    assert list(vals) == ["sequence_number", 7, "source_timestamp", 123456789, "source_gid", bytes(range(16))]


def test_bridge_core_converts_both_ways_and_counts_bad_input():
    keys = P.Keys("t")
    errors = []
    clock = iter(range(0, 10**12, 10**9))  # one second between calls: every pose also sends the Path
    core = BridgeCore(keys, on_bad_input=errors.append, clock=lambda: next(clock))
    outs = core.handle("poses", P.encode(_pose(0, 1.0)))
    assert [o.key for o in outs] == ["fmapping/pose", "fmapping/path"]
    outs = core.handle("poses", P.encode(_pose(1, 2.0, 1)))
    refined = _pose(0, 1.0, 5)
    outs = core.handle("poses", P.encode(refined))  # a refinement of frame 0 replaces it in the Path
    path = C.from_cdr(outs[1].payload, C.PATH)
    assert len(path.poses) == 2
    np.testing.assert_allclose(C.c2w_of(path.poses[0].pose), refined.c2w, atol=1e-9)
    assert core.handle("poses", P.encode(_pose(2, 3.0, source="gt"))) == []  # other sources: not bridged
    assert core.handle("poses", b"\x00garbage") == [] and core.counters.get("decode_errors") == 1
    snap = P.PointsSnapshot(version=1, points=np.zeros((3, 3), np.float32), colors=np.zeros((3, 3), np.uint8),
                            frame_seq=1)
    (cloud,) = core.handle("points", P.encode(snap))
    assert cloud.key == "fmapping/points" and C.seconds(C.from_cdr(cloud.payload, C.POINT_CLOUD2).header.stamp) == 2.0
    # images wait for their CameraInfo; then every image is the next frame
    cam = {"fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0, "width": 32, "height": 24}
    img = C.to_cdr(C.image_msg(np.zeros((24, 32, 3), np.uint8), 4.0), C.IMAGE)
    assert core.handle("image", img) == [] and core.counters.get("frames_without_info") == 1
    core.handle("camera_info", C.to_cdr(C.camera_info_msg(cam, 4.0), C.CAMERA_INFO))
    for seq in (0, 1):
        (out,) = core.handle("image", img)
        assert out.key == keys.frames and P.decode(out.payload, P.Frame).seq == seq
    assert core.handle("image", b"\x00\x01\x00\x00\x01") == [] and core.counters.get("rejected_images") == 1
    assert core.counters.get("bad_input") == 2 and len(errors) == 2


def test_bridge_core_rmw_style_attaches_rmw_metadata():
    core = BridgeCore(P.Keys("t"), Topics(pose="/slam/pose"), C.TopicKeys("rmw", domain=0))
    outs = core.handle("poses", P.encode(_pose(0, 1.0)))
    assert outs[0].key.startswith("0/slam/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_")
    assert outs[0].attachment is not None and b"source_gid" in outs[0].attachment


def test_bridge_service_publishes_a_pose_stamped_for_each_tracker_pose(zpair):
    """The zenoh shell in this process on peer ``a``; the test (peer ``b``) plays the tracker and a
    ROS 2 subscriber on the zenoh-bridge-ros2dds key ``fmapping/pose``."""
    import zenoh
    from service_helpers import wait_matching

    from services.ros2.__main__ import build_parser, run
    from services.transport import Service

    a, b, _ = zpair
    keys = P.Keys("ros")
    got, lock = [], threading.Lock()

    def on_sample(s):
        with lock:
            got.append(s.payload.to_bytes())

    sub = b.declare_subscriber("fmapping/pose", on_sample)
    args = build_parser().parse_args(["--ns", "ros", "--image-topic", ""])
    svc = Service("ros2", args, capacities={"poses": 1000, "points": 2}, session=a, keys=keys)
    t = threading.Thread(target=run, args=(svc, args), daemon=True)
    t.start()
    pub = b.declare_publisher(keys.poses("tracker"), congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        wait_matching(pub, timeout=30)
        poses = [_pose(i, 100.0 + 0.1 * i, i) for i in range(5)]
        for p in poses:
            pub.put(P.encode(p))
        pub.put(P.encode(_pose(9, 0.0, source="gt")))  # not the tracker's: not bridged
        end = time.monotonic() + 30
        while time.monotonic() < end:
            with lock:
                if len(got) >= len(poses):
                    break
            time.sleep(0.02)
        time.sleep(0.2)  # nothing more comes
    finally:
        svc.shutdown.set("test")
        t.join(timeout=10)
        svc.close()
        sub.undeclare()
        pub.undeclare()
    assert not t.is_alive()
    assert len(got) == len(poses)
    for p, data in zip(poses, got):
        back = C.pose_from_stamped(C.from_cdr(data, C.POSE_STAMPED), p.seq)
        np.testing.assert_allclose(back.c2w, p.c2w, atol=1e-9, rtol=0)
        assert back.timestamp == pytest.approx(p.timestamp, abs=1e-6)


def test_bridge_service_turns_ros_images_into_frames(zpair):
    """ROS side (peer ``b``) publishes CameraInfo + Image CDR on the bridge keys; the shell on
    ``a`` publishes our Frames on fmapping/<ns>/frames."""
    import zenoh
    from service_helpers import wait_matching

    from services.ros2.__main__ import build_parser, run
    from services.transport import Service

    a, b, _ = zpair
    keys = P.Keys("rosin")
    frames, lock = [], threading.Lock()

    def on_frame(s):
        with lock:
            frames.append(P.decode(s.payload.to_bytes(), P.Frame))

    sub = b.declare_subscriber(keys.frames, on_frame)
    args = build_parser().parse_args(["--ns", "rosin"])
    svc = Service("ros2", args, capacities={"poses": 10, "points": 2, "camera_info": 4, "image": 16},
                  session=a, keys=keys)
    t = threading.Thread(target=run, args=(svc, args), daemon=True)
    t.start()
    block = zenoh.CongestionControl.BLOCK
    pinfo = b.declare_publisher("camera/camera_info", congestion_control=block)
    pimg = b.declare_publisher("camera/image_raw", congestion_control=block)
    cam = {"fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0, "width": 32, "height": 24}
    rgb = np.random.default_rng(3).integers(0, 256, size=(24, 32, 3)).astype(np.uint8)
    try:
        wait_matching(pinfo, pimg, timeout=30)
        pinfo.put(C.to_cdr(C.camera_info_msg(cam, 1.0), C.CAMERA_INFO))
        time.sleep(0.2)  # the info first: an image before it is only counted
        for i in range(3):
            pimg.put(C.to_cdr(C.image_msg(rgb, 1.0 + i, encoding="bgr8"), C.IMAGE))
        end = time.monotonic() + 30
        while time.monotonic() < end:
            with lock:
                if len(frames) >= 3:
                    break
            time.sleep(0.02)
    finally:
        svc.shutdown.set("test")
        t.join(timeout=10)
        svc.close()
        for d in (sub, pinfo, pimg):
            d.undeclare()
    assert [f.seq for f in frames] == [0, 1, 2]
    assert [f.timestamp for f in frames] == pytest.approx([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(frames[0].rgb, rgb)
    assert frames[0].camera["fx"] == 30.0 and frames[0].camera["width"] == 32
