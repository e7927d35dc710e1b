"""Dataset readers: every format reads back what a tiny fixture wrote, bad input names the file."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fmapping import geometry as g
from fmapping.camera import PinholeCamera
from fmapping.cli import main as cli_main
from fmapping.datasets import Dataset, DatasetError, Frame, detect_kind, open_dataset
from fmapping.ply import write_ply
from fmapping.trajectory import write_tum_trajectory

W, H = 32, 24
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _poses(n: int, seed: int = 0) -> np.ndarray:
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=gen, dtype=torch.float64) * 0.5
    return g.se3_exp(xi).numpy()


def _rgb(rng: np.random.Generator, h: int = H, w: int = W) -> np.ndarray:
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def _write_u16(path: Path, raw: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), raw.astype(np.uint16))


def make_tum(root: Path, n: int = 6, seed: int = 0, *, depth_skip=(), gt_frames=None, factor=5000.0,
             jitter: float = 0.0):
    """A TUM folder: n frames at 30 Hz; depth and GT timestamps jittered by up to ``jitter`` s."""
    rng = np.random.default_rng(seed)
    ts = 1000.0 + np.arange(n) / 30.0
    rgbs, raws = [], []
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    for i, t in enumerate(ts):
        rgb = _rgb(rng)
        raw = rng.integers(0, 20000, (H, W)).astype(np.uint16)
        _write_rgb(root / "rgb" / f"{t:.6f}.png", rgb)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if i not in depth_skip:
            td = t + rng.uniform(-jitter, jitter)
            _write_u16(root / "depth" / f"{td:.6f}.png", raw)
            depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
        rgbs.append(rgb)
        raws.append(raw)
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    poses = _poses(n, seed)
    keep = list(range(n)) if gt_frames is None else list(gt_frames)
    gt_ts = ts[keep] + rng.uniform(-jitter, jitter, len(keep))
    write_tum_trajectory(root / "groundtruth.txt", gt_ts, poses[keep])
    return ts, rgbs, raws, poses


# ----------------------------------------------------------------------------- TUM
def test_tum_roundtrip_with_jittered_association_and_missing_gt_tail(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg3_test"
    ts, rgbs, raws, poses = make_tum(root, n=6, depth_skip=(4,), gt_frames=range(4), jitter=0.012)
    ds = open_dataset(root)
    assert isinstance(ds, Dataset) and ds.kind == "tum" and len(ds) == 6
    # freiburg3 by folder name (no distortion, so pixels are untouched), its 640x480 intrinsics
    # rescaled by 1/20 to the 32x24 fixture: f / 20 and (c + 0.5) / 20 - 0.5
    want = (535.4 / 20, 539.2 / 20, 320.6 / 20 - 0.5, 248.1 / 20 - 0.5)
    np.testing.assert_allclose((ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy), want, rtol=1e-12)
    assert "rescaled" in ds.meta["camera_note"]
    assert ds.camera.dist is None and ds.camera.size == (W, H) and ds.depth_scale == 5000.0
    np.testing.assert_allclose(ds.timestamps, np.round(ts, 6), atol=1e-9)
    for i in range(6):
        f = ds[i]
        assert isinstance(f, Frame) and f.index == i
        np.testing.assert_array_equal(f.rgb, rgbs[i])
        assert f.rgb.dtype == np.uint8 and f.rgb.shape == (H, W, 3)
        if i == 4:
            assert f.depth is None
        else:
            assert f.depth.dtype == np.float32
            np.testing.assert_allclose(f.depth, raws[i] / 5000.0, rtol=1e-6, atol=0)
            np.testing.assert_array_equal(np.rint(f.depth.astype(np.float64) * 5000), raws[i])
        if i < 4:
            np.testing.assert_allclose(f.c2w, poses[i], atol=1e-6)
        else:
            assert f.c2w is None
    d = ds.describe()
    assert d["gt_poses"] == 4 and d["frames_with_depth"] == 5 and d["frames"] == 6
    json.dumps(d)  # what a run writes into its outputs must be JSON


def test_tum_association_rejects_beyond_20ms(tmp_path):
    root = tmp_path / "fr3_seq"
    ts, *_ = make_tum(root, n=3)
    poses = _poses(2, 9)
    # 25 ms before frame 0 (too far), 15 ms after frame 2 (close enough); frame 1 is 48 ms away
    write_tum_trajectory(root / "groundtruth.txt", [ts[0] - 0.025, ts[2] + 0.015], poses)
    gt = open_dataset(root).gt_poses
    assert gt[0] is None and gt[1] is None
    np.testing.assert_allclose(gt[2], poses[1], atol=1e-6)
    write_tum_trajectory(root / "groundtruth.txt", [ts[0] - 0.019], poses[:1])
    gt = open_dataset(root).gt_poses
    assert gt[0] is not None and gt[1] is None and gt[2] is None


# ----------------------------------------------------------------------------- GT interpolation
T0 = 1305031102.0  # a TUM-like epoch timestamp: float64 resolves it to ~0.2 us


def _analytic_pose(t: np.ndarray) -> np.ndarray:
    """A smooth c2w trajectory of ``t`` (seconds since T0) with a turning rotation axis.

    Bounds used by the tolerances: |p''| <= sqrt(1 + 4) m/s^2, angular acceleration
    below ~1.5 rad/s^2, so linear / geodesic interpolation over h = 0.01 s errs by at
    most ~h^2/8 * bound: 3e-5 m and 2e-5 rad (1e-3 deg)."""
    from scipy.spatial.transform import Rotation

    t = np.asarray(t, np.float64)
    rot = Rotation.from_euler("z", 0.8 * t[:, None]) * Rotation.from_euler("x", 0.5 * np.sin(1.3 * t)[:, None])
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = rot.as_matrix()
    out[:, :3, 3] = np.stack([np.sin(t), 0.5 * np.cos(2 * t), 0.3 * t], -1)
    return out


def _pose_errors(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position error m, rotation error deg) between pose stacks."""
    dr = np.swapaxes(a[:, :3, :3], -1, -2) @ b[:, :3, :3]
    ang = np.degrees(np.arccos(np.clip((np.trace(dr, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1), ang


def test_interpolate_poses_matches_analytic_trajectory_at_100hz():
    from fmapping.trajectory import associate, interpolate_poses

    rel = np.arange(0, 301) * 0.01  # 3 s of GT at 100 Hz
    ref_ts = np.round(T0 + rel, 6)  # as a TUM file stores them
    ref = _analytic_pose(ref_ts - T0)
    q = T0 + np.sort(np.random.default_rng(0).uniform(0.0, 3.0, 500))
    got, how = interpolate_poses(q, ref_ts, ref, max_dt=0.02)
    assert (how == "interpolated").all()
    want = _analytic_pose(q - T0)
    de, re = _pose_errors(got, want)
    assert de.max() < 1e-4 and re.max() < 5e-3, (de.max(), re.max())
    # the same tolerance fails the nearest sample (up to h/2 * |v| ~ 5 mm), so this test can tell
    j = associate(q, ref_ts, 0.02)
    de_n, re_n = _pose_errors(ref[j], want)
    assert de_n.max() > 2e-3 and re_n.max() > 0.1, (de_n.max(), re_n.max())
    # proper rigid poses
    np.testing.assert_allclose(got[:, :3, :3] @ np.swapaxes(got[:, :3, :3], 1, 2),
                               np.broadcast_to(np.eye(3), (500, 3, 3)), atol=1e-12)
    np.testing.assert_array_equal(got[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (500, 4)))


def test_interpolate_poses_exact_cases_gaps_and_range():
    from fmapping.trajectory import interpolate_poses

    # constant angular velocity and linear motion: geodesic + linear interpolation is exact
    xi = torch.tensor([0.4, -0.2, 0.1, 0.3, -0.5, 0.7], dtype=torch.float64)
    ts = np.array([0.0, 0.01, 0.02, 0.10, 0.11])  # a 0.08 s gap between 0.02 and 0.10
    rot = g.so3_exp(torch.from_numpy(ts)[:, None] * xi[3:]).numpy()
    ref = np.tile(np.eye(4), (len(ts), 1, 1))
    ref[:, :3, :3] = rot
    ref[:, :3, 3] = ts[:, None] * xi[:3].numpy()
    q = np.array([0.0, 0.0037, 0.01, 0.015, 0.035, 0.06, 0.09, 0.105, 0.125, -0.001, 0.11])
    got, how = interpolate_poses(q, ts, ref, max_dt=0.02)
    assert how.tolist() == ["interpolated", "interpolated", "interpolated", "interpolated", "nearest", "none",
                            "nearest", "interpolated", "nearest", "nearest", "interpolated"]
    np.testing.assert_array_equal(got[0], ref[0])  # on a sample: that sample, bit for bit
    np.testing.assert_array_equal(got[2], ref[1])
    for k in (1, 3, 7):
        want_r = g.so3_exp(torch.tensor(q[k] * xi[3:].numpy())).numpy()
        np.testing.assert_allclose(got[k, :3, :3], want_r, atol=1e-12)
        np.testing.assert_allclose(got[k, :3, 3], q[k] * xi[:3].numpy(), atol=1e-12)
    np.testing.assert_array_equal(got[4], ref[2])  # in the gap, 15 ms after 0.02: nearest
    np.testing.assert_array_equal(got[6], ref[3])  # 10 ms before 0.10
    assert np.isnan(got[5]).all()  # 40 ms from both ends of the gap
    np.testing.assert_array_equal(got[8], ref[4])  # past the end: no extrapolation, nearest within 20 ms
    np.testing.assert_array_equal(got[9], ref[0])  # before the start
    _, how_strict = interpolate_poses(q, ts, ref, max_dt=0.02, nearest_fallback=False)
    assert set(how_strict[[4, 6, 8, 9]]) == {"none"}
    # an unsorted reference gives the same answer
    perm = np.array([3, 0, 4, 2, 1])
    got_p, how_p = interpolate_poses(q, ts[perm], ref[perm], max_dt=0.02)
    np.testing.assert_array_equal(how_p, how)
    np.testing.assert_allclose(got_p, got, atol=0, equal_nan=True)
    with pytest.raises(ValueError, match="poses of shape"):
        interpolate_poses(q, ts, ref[:3])


def test_tum_ground_truth_is_interpolated_with_gaps(tmp_path):
    root = tmp_path / "fr1_interp"
    rel_gt = np.round(np.arange(-5, 101) * 0.01, 2)
    rel_gt = rel_gt[(rel_gt <= 0.40) | (rel_gt >= 0.50)]  # a 0.1 s drop-out in the motion capture
    write_tum_trajectory(root / "groundtruth.txt", T0 + rel_gt, _analytic_pose(rel_gt))
    rel = np.array([0.0, 0.123456, 0.25, 0.3777, 0.405, 0.45, 0.6, 0.999123, 1.2])
    rng = np.random.default_rng(3)
    lines = []
    for t in T0 + rel:
        _write_rgb(root / "rgb" / f"{t:.6f}.png", _rgb(rng))
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    ds = open_dataset(root)
    assert ds.meta["groundtruth_association"] == {"interpolated": 6, "nearest": 1, "none": 2}
    interp = [0, 1, 2, 3, 6, 7]
    got = np.stack([ds.gt_poses[i] for i in interp])
    de, re = _pose_errors(got, _analytic_pose(np.asarray(ds.timestamps)[interp] - T0))
    assert de.max() < 1e-4 and re.max() < 5e-3, (de, re)  # 1e-9 rounding of the file is far below
    np.testing.assert_allclose(ds.gt_poses[4], _analytic_pose(np.array([0.40]))[0], atol=1e-8)  # nearest row
    assert ds.gt_poses[5] is None and ds.gt_poses[8] is None
    assert ds.describe()["gt_poses"] == 7


def test_tum_name_table_and_unknown_camera_refused(tmp_path, capsys):
    make_tum(tmp_path / "rgbd_dataset_freiburg2_xyz", n=2)
    ds = open_dataset(tmp_path / "rgbd_dataset_freiburg2_xyz")
    assert ds.raw_camera.dist == (0.2312, -0.7849, -0.0033, -0.0001, 0.9172) and ds.camera.dist is None
    assert ds.camera.fx == pytest.approx(520.9 / 20) and ds.meta["undistorted"] is True
    for name, rig in (("tum_fr1_desk", "freiburg1"), ("fr3", "freiburg3")):
        make_tum(tmp_path / name, n=2)
        assert rig in open_dataset(tmp_path / name).meta["camera_source"]
    # not a TUM recording, no calib.txt: no guessed camera, an error saying how to give one
    root = tmp_path / "mystery"
    make_tum(root, n=2)
    _raises([str(root), "calib.txt", "--camera fx,fy,cx,cy"], open_dataset, root)
    assert cli_main(["info", "--data", str(root)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(root) in err and "--camera" in err
    ds = open_dataset(root, camera="30,30,15.5,11.5")
    assert ds.meta["camera_source"] == "--camera" and ds.camera.fx == 30.0
    (root / "calib.txt").write_text("31 32 15.5 11.5\n")
    ds = open_dataset(root)
    assert ds.meta["camera_source"].endswith("calib.txt") and (ds.camera.fx, ds.camera.fy) == (31.0, 32.0)


def test_calib_txt_wins_and_sets_depth_factor(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg2_custom"  # the name table would add distortion
    _, rgbs, raws, _ = make_tum(root, n=3)
    (root / "calib.txt").write_text("# fx fy cx cy\n30 31 15.5 11.5\ndepth_factor 1000\n")
    ds = open_dataset(root)
    assert ds.camera == PinholeCamera(30.0, 31.0, 15.5, 11.5, W, H) and ds.raw_camera.dist is None
    assert ds.depth_scale == 1000.0 and ds.meta["camera_source"].endswith("calib.txt")
    f = ds[2]
    np.testing.assert_array_equal(f.rgb, rgbs[2])
    np.testing.assert_allclose(f.depth, raws[2] / 1000.0, rtol=1e-6)


def test_tum_rig_intrinsics_without_distortion_get_the_rig_distortion(tmp_path):
    from fmapping.datasets.tum import TUM_INTRINSICS, complete_tum_distortion

    k, dist = TUM_INTRINSICS["freiburg1"]
    vals, note = complete_tum_distortion(tmp_path / "tum_fr1_rpy", list(k), (640, 480))
    assert vals == [*k, *dist] and "freiburg1" in note
    # anything else is taken as written: other numbers, explicit distortion, other size, unknown rig
    for root, v, size in [(tmp_path / "tum_fr1_rpy", [500.0, 500.0, 320.0, 240.0], (640, 480)),
                          (tmp_path / "tum_fr1_rpy", [*k, 0.1, 0, 0, 0], (640, 480)),
                          (tmp_path / "tum_fr1_rpy", list(k), (320, 240)),
                          (tmp_path / "mystery", list(k), (640, 480)),
                          (tmp_path / "tum_fr3_office", list(TUM_INTRINSICS["freiburg3"][0]), (640, 480))]:
        assert complete_tum_distortion(root, v, size) == (v, None)


def _distort(uv: np.ndarray, K: np.ndarray, d) -> np.ndarray:
    """Brown-Conrady forward model written out (k1 k2 p1 p2 k3): undistorted pixel -> distorted pixel."""
    k1, k2, p1, p2, k3 = d
    x = (uv[0] - K[0, 2]) / K[0, 0]
    y = (uv[1] - K[1, 2]) / K[1, 1]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.array([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]])


def _blob(h, w, centre, sigma=1.5):
    v, u = np.mgrid[0:h, 0:w]
    return np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma**2))


def _centroid(weight):
    v, u = np.mgrid[0 : weight.shape[0], 0 : weight.shape[1]]
    return np.array([(u * weight).sum(), (v * weight).sum()]) / weight.sum()


def test_calib_txt_distortion_is_removed(tmp_path):
    """A blob drawn at the distorted location of pixel p ends up at p after reading."""
    w, h = 96, 72
    dist = (0.15, -0.05, 0.004, -0.003, 0.01)
    K = np.array([[60.0, 0, 47.5], [0, 62.0, 35.5], [0, 0, 1]])
    target = np.array([80.0, 15.0])  # undistorted pixel, near a corner where distortion is strong
    src = _distort(target, K, dist)
    assert np.linalg.norm(src - target) > 1.5  # the test would notice a missing undistortion
    blob = _blob(h, w, src)
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 1] = np.round(blob * 255).astype(np.uint8)
    raw_depth = np.where(blob > 0.5, 10000, 5000).astype(np.uint16)
    root = tmp_path / "custom"
    _write_rgb(root / "rgb" / "0.png", rgb)
    _write_u16(root / "depth" / "0.png", raw_depth)
    (root / "rgb.txt").write_text("0.0 rgb/0.png\n")
    (root / "depth.txt").write_text("0.0 depth/0.png\n")
    (root / "calib.txt").write_text("60 62 47.5 35.5 " + " ".join(map(str, dist)) + "\n")
    ds = open_dataset(root)
    assert ds.camera.dist is None and ds.raw_camera.dist == dist and ds.meta["undistorted"]
    assert ds.camera.K.tolist() == K.tolist()
    f = ds[0]
    assert f.camera.dist is None and f.c2w is None
    np.testing.assert_allclose(_centroid(f.rgb[..., 1].astype(float)), target, atol=0.3)
    assert set(np.unique(f.depth)) <= {0.0, 1.0, 2.0}  # nearest interpolation: no mixed depths
    np.testing.assert_allclose(_centroid((f.depth == 2.0).astype(float)), target, atol=1.0)


def test_camera_override_string_and_object(tmp_path):
    root = tmp_path / "fr3"
    _, rgbs, _, _ = make_tum(root, n=2)
    ds = open_dataset(root, camera="20,21,16,12")
    assert ds.camera == PinholeCamera(20.0, 21.0, 16.0, 12.0, W, H) and ds.meta["camera_source"] == "--camera"
    np.testing.assert_array_equal(ds[1].rgb, rgbs[1])
    ds = open_dataset(root, camera="20,21,16,12,0.1,0,0,0")
    assert ds.camera.dist is None and ds.raw_camera.dist == (0.1, 0.0, 0.0, 0.0) and ds.meta["undistorted"]
    assert not np.array_equal(ds[1].rgb, rgbs[1])  # undistortion moved pixels
    cam = PinholeCamera(25.0, 25.0, 15.5, 11.5, W, H)
    assert open_dataset(root, camera=cam).camera == cam
    with pytest.raises(DatasetError, match="64x48"):
        open_dataset(root, camera=PinholeCamera(25.0, 25.0, 31.5, 23.5, 64, 48))
    with pytest.raises(DatasetError, match="--camera"):
        open_dataset(root, camera="20,21,16")
    with pytest.raises(DatasetError, match="--camera"):
        open_dataset(root, camera="20,-21,16,12")


def test_max_frames_truncates(tmp_path):
    root = tmp_path / "fr3"
    _, rgbs, _, poses = make_tum(root, n=5)
    ds = open_dataset(root, max_frames=3)
    assert len(ds) == 3 and len(ds.gt_poses) == 3 and len(list(ds)) == 3
    np.testing.assert_array_equal(ds[-1].rgb, rgbs[2])
    with pytest.raises(IndexError):
        ds[3]
    with pytest.raises(DatasetError, match="max_frames"):
        open_dataset(root, max_frames=0)


def test_synthetic_scene_detected_with_gt_files(tmp_path):
    root = tmp_path / "room0"
    make_tum(root, n=2)
    (root / "calib.txt").write_text("30 30 15.5 11.5\n")
    scene = {"generator": "fmapping.synthetic", "seed": 3, "frames": 2}
    (root / "scene.json").write_text(json.dumps(scene))
    write_ply(root / "gt_mesh.ply", np.eye(3), faces=np.array([[0, 1, 2]]))
    write_ply(root / "gt_visible_cloud.ply", np.eye(3))
    assert detect_kind(root) == "synthetic"
    ds = open_dataset(root)
    assert ds.kind == "synthetic" and ds.meta["scene"] == scene
    assert ds.meta["gt_mesh"] == str(root / "gt_mesh.ply")
    assert ds.meta["gt_visible_cloud"] == str(root / "gt_visible_cloud.ply")
    assert "gt_cloud" not in ds.meta  # only files that exist
    # a scene.json from another tool is just a TUM folder
    (root / "scene.json").write_text(json.dumps({"generator": "blender"}))
    assert open_dataset(root).kind == "tum"


def test_rgb_only_tum_and_image_conversions(tmp_path):
    """No depth.txt: depth None everywhere, depth_scale None; gray / RGBA / 16-bit images become RGB8."""
    root = tmp_path / "fr3"
    rng = np.random.default_rng(1)
    gray = rng.integers(0, 256, (H, W), dtype=np.uint8)
    rgba = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)
    rgb16 = rng.integers(0, 65536, (H, W, 3), dtype=np.uint16)
    root.mkdir()
    cv2.imwrite(str(root / "a.png"), gray)
    cv2.imwrite(str(root / "b.png"), rgba)  # stored as BGRA
    cv2.imwrite(str(root / "c.png"), rgb16)  # stored as BGR
    (root / "rgb.txt").write_text("1.0 a.png\n2.0 b.png\n3.0 c.png\n")
    ds = open_dataset(root, background=(0, 0, 255))
    assert not ds.has_depth and ds.depth_scale is None and ds.gt_poses == [None] * 3
    np.testing.assert_array_equal(ds[0].rgb, np.repeat(gray[..., None], 3, 2))
    a = rgba[..., 3:].astype(float) / 255
    want = np.rint(rgba[..., 2::-1] * a + np.array([0, 0, 255.0]) * (1 - a))
    np.testing.assert_allclose(ds[1].rgb, want, atol=1)
    np.testing.assert_array_equal(ds[2].rgb, (rgb16[..., ::-1] >> 8).astype(np.uint8))
    assert ds[0].depth is None


def test_construction_is_lazy(tmp_path):
    root = tmp_path / "fr3_big"
    n = 2000
    ts = 100.0 + np.arange(n) / 30.0
    _write_rgb(root / "rgb" / f"{ts[0]:.6f}.png", _rgb(np.random.default_rng(0)))
    (root / "rgb.txt").write_text("".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in ts))
    (root / "depth.txt").write_text("".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in ts))
    write_tum_trajectory(root / "groundtruth.txt", ts, np.repeat(np.eye(4)[None], n, 0))
    t0 = time.perf_counter()
    ds = open_dataset(root)
    elapsed = time.perf_counter() - t0
    assert len(ds) == n and ds.gt_poses[-1] is not None
    assert elapsed < 2.0, f"constructing a 2000-frame dataset took {elapsed:.2f} s: images are being read"
    missing = root / "rgb" / f"{ts[1500]:.6f}.png"
    with pytest.raises(DatasetError, match=str(missing).replace(".", r"\.")):
        ds[1500]
    with pytest.raises(DatasetError, match="depth"):  # rgb exists, its depth file does not
        ds[0]


# ------------------------------------------------------------------------- Replica
def _smooth_rgb(seed, h=H, w=W):
    """Smooth, per-channel distinct image: survives JPEG within a few levels and catches BGR swaps."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.array([200.0, 90.0, 20.0]) + rng.uniform(-10, 10, 3)
    img = base + 30 * np.stack([u, v, u * v], -1)
    return np.clip(img, 0, 255).astype(np.uint8)


def make_replica(root: Path, n=5, n_poses=None, cam="yaml"):
    res = root / "results"
    rgbs, raws = [], []
    rng = np.random.default_rng(2)
    for i in range(n):
        rgb = _smooth_rgb(i)
        raw = rng.integers(1, 60000, (H, W)).astype(np.uint16)
        _write_rgb(res / f"frame{i:06d}.jpg", rgb)
        _write_u16(res / f"depth{i:06d}.png", raw)
        rgbs.append(rgb)
        raws.append(raw)
    poses = _poses(n, 5)
    k = n if n_poses is None else n_poses
    (root / "traj.txt").write_text("".join(" ".join(f"{x:.17g}" for x in p.reshape(-1)) + "\n" for p in poses[:k]))
    if cam == "yaml":
        (root / "cam.yaml").write_text(
            "cam:\n  H: 24\n  W: 32\n  fx: 20.0\n  fy: 20.0\n  cx: 15.5\n  cy: 11.5\n  png_depth_scale: 6553.5\n"
        )
    elif cam == "json":
        (root / "cam.json").write_text(json.dumps({"w": 32, "h": 24, "fx": 21, "fy": 22, "cx": 16, "cy": 12,
                                                   "depth_scale": 1000.0}))
    return rgbs, raws, poses


def test_replica_roundtrip_and_short_trajectory(tmp_path):
    root = tmp_path / "room0"
    rgbs, raws, poses = make_replica(root, n=5, n_poses=3)
    assert detect_kind(root) == "replica"
    ds = open_dataset(root)
    assert ds.kind == "replica" and len(ds) == 5 and ds.depth_scale == 6553.5
    assert ds.camera == PinholeCamera(20.0, 20.0, 15.5, 11.5, W, H)
    np.testing.assert_allclose(ds.timestamps, np.arange(5) / 30.0)
    for i in range(5):
        f = ds[i]
        path = root / "results" / f"frame{i:06d}.jpg"
        np.testing.assert_array_equal(f.rgb, cv2.imread(str(path))[..., ::-1])  # the decoded file, RGB order
        assert np.abs(f.rgb.astype(int) - rgbs[i]).mean() < 3  # and close to what was encoded
        np.testing.assert_allclose(f.depth, raws[i] / 6553.5, rtol=1e-6)
        if i < 3:
            np.testing.assert_array_equal(f.c2w, poses[i])
        else:
            assert f.c2w is None
    assert "3 poses for 5 frames" in ds.meta["gt_note"]


def test_replica_cam_json_and_defaults(tmp_path):
    make_replica(tmp_path / "a", n=2, cam="json")
    ds = open_dataset(tmp_path / "a")
    assert ds.camera == PinholeCamera(21.0, 22.0, 16.0, 12.0, W, H) and ds.depth_scale == 1000.0
    make_replica(tmp_path / "b", n=2, cam=None)
    ds = open_dataset(tmp_path / "b")
    # NICE-SLAM defaults are for 1200x680 (fx 600, cx 599.5): rescaled to 32x24 with a note
    assert ds.camera.fx == pytest.approx(600 * 32 / 1200) and ds.camera.fy == pytest.approx(600 * 24 / 680)
    assert ds.camera.cx == pytest.approx(15.5) and ds.camera.cy == pytest.approx(11.5)
    assert "default" in ds.meta["camera_source"] and "camera_note" in ds.meta and ds.depth_scale == 6553.5
    (tmp_path / "a" / "cam.json").write_text(json.dumps({"w": 64, "h": 48, "fx": 21, "fy": 22, "cx": 16, "cy": 12}))
    with pytest.raises(DatasetError, match="cam.json.*64x48"):
        open_dataset(tmp_path / "a")


# ------------------------------------------------------------------------ 7-Scenes
def make_seq(seq: Path, n=4, seed=3):
    rng = np.random.default_rng(seed)
    rgbs, raws = [], []
    poses = _poses(n, seed)
    for i in range(n):
        rgb = _rgb(rng)
        raw = rng.integers(500, 4000, (H, W)).astype(np.uint16)
        raw[rng.random((H, W)) < 0.1] = 65535
        _write_rgb(seq / f"frame-{i:06d}.color.png", rgb)
        _write_u16(seq / f"frame-{i:06d}.depth.png", raw)
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", poses[i], fmt="%.17g", delimiter="\t")
        rgbs.append(rgb)
        raws.append(raw)
    return rgbs, raws, poses


def test_sevenscenes_scene_folder_reads_first_sequence(tmp_path):
    scene = tmp_path / "chess"
    rgbs, raws, poses = make_seq(scene / "seq-01", n=4, seed=3)
    make_seq(scene / "seq-02", n=2, seed=4)
    (scene / "TrainSplit.txt").write_text("sequence1\n")
    assert detect_kind(scene) == "7scenes"
    ds = open_dataset(scene)
    assert ds.kind == "7scenes" and len(ds) == 4 and ds.meta["sequences"] == ["seq-01", "seq-02"]
    assert ds.meta["sequence"] == "seq-01" and ds.depth_scale == 1000.0
    # nominal 640x480 intrinsics rescaled by 1/20 to the 32x24 fixture
    assert ds.camera.fx == pytest.approx(585 / 20) and ds.camera.fy == pytest.approx(585 / 20)
    for i in range(4):
        f = ds[i]
        np.testing.assert_array_equal(f.rgb, rgbs[i])
        want = np.where(raws[i] == 65535, 0, raws[i]).astype(np.float32) / 1000.0
        np.testing.assert_allclose(f.depth, want, rtol=1e-6)
        assert (f.depth == 0).sum() == (raws[i] == 65535).sum()
        np.testing.assert_array_equal(f.c2w, poses[i])
    ds2 = open_dataset(scene / "seq-02", camera="29,29,15.5,11.5")
    assert len(ds2) == 2 and ds2.meta["sequence"] == "seq-02" and ds2.camera.fx == 29.0


def test_sevenscenes_missing_pose_file_gives_none(tmp_path):
    seq = tmp_path / "seq-01"
    make_seq(seq, n=3)
    (seq / "frame-000002.pose.txt").unlink()
    ds = open_dataset(seq)
    assert ds.gt_poses[2] is None and ds.gt_poses[1] is not None and "1 of 3" in ds.meta["gt_note"]


# ----------------------------------------------------------------------------- NeRF
def _look_at_gl(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Blender/OpenGL camera-to-world: x right, y up, the camera looks along -z."""
    eye, target, up = map(np.asarray, (eye, target, up))
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, cam_up, -fwd, eye
    return m


def make_nerf(root: Path, n=4, name="transforms.json", intr=None):
    rng = np.random.default_rng(7)
    root.mkdir(parents=True, exist_ok=True)
    frames, rgbas, eyes = [], [], []
    for i in range(n):
        rgba = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)
        rgba[0, 0, 3], rgba[0, 1, 3] = 0, 255  # fully transparent and opaque pixels
        (root / "train").mkdir(exist_ok=True)
        assert cv2.imwrite(str(root / "train" / f"r_{i}.png"), rgba[..., [2, 1, 0, 3]])
        a = 2 * math.pi * i / n
        eye = 4.0 * np.array([math.cos(a), math.sin(a), 0.5])
        fp = f"./train/r_{i}" if i % 2 == 0 else f"train/r_{i}.png"  # with and without extension
        frames.append({"file_path": fp, "rotation": 0.1, "transform_matrix": _look_at_gl(eye).tolist()})
        rgbas.append(rgba)
        eyes.append(eye)
    (root / name).write_text(json.dumps({**(intr or {"camera_angle_x": 0.69}), "frames": frames}, indent=2))
    return rgbas, np.array(eyes)


def test_nerf_roundtrip_compositing_and_gl_to_cv(tmp_path):
    root = tmp_path / "lego"
    rgbas, eyes = make_nerf(root, n=4)
    assert detect_kind(root) == "nerf"
    ds = open_dataset(root)
    assert ds.kind == "nerf" and len(ds) == 4 and ds.depth_scale is None
    f_expected = 0.5 * W / math.tan(0.5 * 0.69)
    assert ds.camera.fx == pytest.approx(f_expected) and ds.camera.fy == pytest.approx(f_expected)
    assert (ds.camera.cx, ds.camera.cy) == ((W - 1) / 2, (H - 1) / 2)  # the exact image centre
    np.testing.assert_array_equal(ds.timestamps, np.arange(4))
    for i in range(4):
        f = ds[i]
        a = rgbas[i][..., 3:].astype(float) / 255
        np.testing.assert_allclose(f.rgb, np.rint(rgbas[i][..., :3] * a + 255 * (1 - a)), atol=1)
        assert f.rgb[0, 0].tolist() == [255, 255, 255] and f.rgb[0, 1].tolist() == rgbas[i][0, 1, :3].tolist()
        assert f.depth is None
        # project world points with the converted pose: the origin (looked at) lands on the
        # principal point in front of the camera; the world's "up" lands above it
        c2w = torch.as_tensor(f.c2w)
        w2c = g.se3_inverse(c2w)
        dist = np.linalg.norm(eyes[i])
        cam_up = torch.as_tensor(_look_at_gl(eyes[i])[:3, 1])
        cam_right = torch.as_tensor(_look_at_gl(eyes[i])[:3, 0])
        pts = torch.stack([torch.zeros(3, dtype=torch.float64), 0.3 * cam_up, 0.3 * cam_right])
        uv, z = ds.camera.project(g.transform_points(w2c, pts))
        cx, cy, fx = ds.camera.cx, ds.camera.cy, ds.camera.fx
        want = torch.tensor([[cx, cy], [cx, cy - fx * 0.3 / dist], [cx + fx * 0.3 / dist, cy]], dtype=torch.float64)
        np.testing.assert_allclose(uv.numpy(), want.numpy(), atol=1e-9)
        np.testing.assert_allclose(z.numpy(), dist, rtol=1e-12)
    black = open_dataset(root / "transforms.json", background=(0, 0, 0))
    assert black[0].rgb[0, 0].tolist() == [0, 0, 0]


def test_nerfstudio_intrinsics_and_train_split(tmp_path):
    root = tmp_path / "ns"
    make_nerf(root, n=2, name="transforms_train.json", intr={"fl_x": 30.0, "fl_y": 31.0, "cx": 16.0, "cy": 12.0,
                                                             "w": W, "h": H, "k1": 0.05})
    ds = open_dataset(root, max_frames=1)
    assert len(ds) == 1 and ds.meta["transforms"].endswith("transforms_train.json")
    # file principal point is in the pixel-corner convention: ours = file - 0.5
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy) == (30.0, 31.0, 15.5, 11.5)
    assert ds.raw_camera.dist == (0.05, 0.0, 0.0, 0.0, 0.0) and ds.camera.dist is None


# ---------------------------------------------------------------------- bad input
def _raises(match_parts, fn, *a, **k):
    with pytest.raises(DatasetError) as ei:
        fn(*a, **k)
    msg = str(ei.value)
    for part in match_parts:
        assert part in msg, f"{part!r} not in error message {msg!r}"
    return msg


def test_missing_folder_and_unknown_format(tmp_path):
    _raises([str(tmp_path / "nope")], open_dataset, tmp_path / "nope")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "readme.md").write_text("hi")
    msg = _raises(["rgb.txt", "traj.txt", "color.png", "transforms.json", "readme.md"], open_dataset, tmp_path / "junk")
    assert str(tmp_path / "junk") in msg
    _raises(["unknown dataset kind"], open_dataset, tmp_path / "junk", kind="kitti")


def test_malformed_tum_text_files_name_file_and_line(tmp_path):
    root = tmp_path / "fr3"
    make_tum(root, n=3)
    good = (root / "rgb.txt").read_text()
    lines = good.splitlines()
    (root / "rgb.txt").write_text("\n".join(lines[:3] + [lines[3] + " extra"] + lines[4:]) + "\n")
    _raises([f"{root / 'rgb.txt'}:4"], open_dataset, root)
    (root / "rgb.txt").write_text("\n".join(lines[:2] + ["abc rgb/x.png"] + lines[3:]) + "\n")
    _raises([f"{root / 'rgb.txt'}:3", "abc"], open_dataset, root)
    (root / "rgb.txt").write_text("# nothing here\n\n")
    _raises([str(root / "rgb.txt"), "empty"], open_dataset, root)
    (root / "rgb.txt").write_text(good)
    gt_lines = (root / "groundtruth.txt").read_text().splitlines()
    gt_lines[2] = " ".join(gt_lines[2].split()[:7])
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    _raises([f"{root / 'groundtruth.txt'}:3"], open_dataset, root)


def test_bad_calib_txt_is_named(tmp_path):
    root = tmp_path / "custom"
    make_tum(root, n=2)
    calib = root / "calib.txt"
    calib.write_text("# intrinsics\n-30 30 15.5 11.5\n")
    _raises([f"{calib}:2", "positive"], open_dataset, root)
    calib.write_text("30 30 15.5\n")
    _raises([f"{calib}:1", "got 3"], open_dataset, root)
    calib.write_text("30 30 400 11.5\n")  # principal point outside a 32x24 image
    _raises([f"{calib}:1", "principal point"], open_dataset, root)
    calib.write_text("30 30 15.5 11.5\ndepth_factor zero\n")
    _raises([f"{calib}:2", "depth_factor"], open_dataset, root)
    calib.write_text("30 30 15.5 11.5\nbaseline 0.1\n")
    _raises([f"{calib}:2"], open_dataset, root)


def test_corrupt_and_missized_images_named_at_getitem(tmp_path):
    root = tmp_path / "fr3"
    ts, *_ = make_tum(root, n=3)
    bad = root / "rgb" / f"{ts[1]:.6f}.png"
    bad.write_bytes(b"\x89PNG not really")
    ds = open_dataset(root)  # construction only decodes the first image
    _raises([str(bad), "corrupt"], ds.__getitem__, 1)
    _write_rgb(bad, _rgb(np.random.default_rng(0), H + 2, W))
    _raises([str(bad), f"{W}x{H + 2}", f"{W}x{H}"], ds.__getitem__, 1)
    depth_file = sorted((root / "depth").iterdir())[2]
    _write_u16(depth_file, np.zeros((H, W + 1)))
    _raises([str(depth_file), f"{W + 1}x{H}"], ds.__getitem__, 2)
    # the first image unreadable: construction itself fails, naming it
    first = root / "rgb" / f"{ts[0]:.6f}.png"
    first.write_bytes(b"")
    _raises([str(first)], open_dataset, root)


def test_malformed_replica_sevenscenes_nerf_files(tmp_path):
    make_replica(tmp_path / "r", n=3)
    traj = tmp_path / "r" / "traj.txt"
    lines = traj.read_text().splitlines()
    lines[1] = " ".join(lines[1].split()[:15])
    traj.write_text("\n".join(lines) + "\n")
    _raises([f"{traj}:2", "16"], open_dataset, tmp_path / "r")

    seq = tmp_path / "seq-01"
    make_seq(seq, n=2)
    pose = seq / "frame-000001.pose.txt"
    rows = pose.read_text().splitlines()
    rows[1] = "1 2 3"
    pose.write_text("\n".join(rows) + "\n")
    _raises([f"{pose}:2"], open_dataset, seq)

    make_nerf(tmp_path / "n", n=2)
    tj = tmp_path / "n" / "transforms.json"
    text = tj.read_text()
    tj.write_text(text.replace('"rotation": 0.1,', '"rotation": 0.1,,', 1))
    _raises([str(tj), ":"], open_dataset, tmp_path / "n")
    d = json.loads(text)
    d["frames"][1]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    tj.write_text(json.dumps(d))
    _raises([str(tj), "frames[1]", "transform_matrix"], open_dataset, tmp_path / "n")
    d = json.loads(text)
    d["frames"] = []
    tj.write_text(json.dumps(d))
    _raises([str(tj), "empty"], open_dataset, tmp_path / "n")


def test_cli_info(tmp_path, capsys):
    root = tmp_path / "fr3"
    make_tum(root, n=4)
    assert cli_main(["info", "--data", str(root), "--max-frames", "2", "--camera", "20,20,15.5,11.5"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 2 and out["kind"] == "tum" and out["camera"]["fx"] == 20.0 and out["depth_scale"] == 5000.0
    assert cli_main(["info", "--data", str(tmp_path / "missing")]) == 2
    assert "missing" in capsys.readouterr().err


# ------------------------------------------------------------- optional real data
@pytest.mark.skipif(not (DATA / "tum_fr1_rpy").is_dir(), reason="shared TUM fr1_rpy subset not present")
def test_real_tum_fr1_rpy():
    ds = open_dataset(DATA / "tum_fr1_rpy")
    assert ds.kind == "tum" and len(ds) == 60 and ds.camera.size == (640, 480)
    assert (ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy) == (517.3, 516.5, 318.6, 255.3)
    assert ds.meta["camera_source"].endswith("calib.txt") and ds.camera.dist is None
    # its calib.txt holds only fr1's fx fy cx cy: the raw images get fr1's distortion removed
    assert ds.raw_camera.dist == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633) and ds.meta["undistorted"]
    assert "freiburg1" in ds.meta["camera_note"]
    assert all(p is not None for p in ds.gt_poses) and ds.depth_scale == 5000.0
    f = ds[59]
    assert f.rgb.shape == (480, 640, 3) and f.depth.shape == (480, 640)
    valid = f.depth[f.depth > 0]
    assert valid.size > 0.5 * f.depth.size and 0.3 < np.median(valid) < 5.0  # an office scene, metres
    np.testing.assert_allclose(f.c2w[:3, :3] @ f.c2w[:3, :3].T, np.eye(3), atol=1e-3)


@pytest.mark.skipif(not (DATA / "nerf_synthetic_lego").is_dir(), reason="shared NeRF lego subset not present")
def test_real_nerf_lego():
    ds = open_dataset(DATA / "nerf_synthetic_lego")
    assert ds.kind == "nerf" and len(ds) == 50 and ds.camera.size == (800, 800)
    assert ds.camera.fx == pytest.approx(1111.11, abs=0.01) and ds.camera.fy == pytest.approx(1111.11, abs=0.01)
    poses = np.stack(ds.gt_poses)
    centres = poses[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 4.031, atol=0.01)
    # the optical axis (+z in OpenCV axes) points at the origin
    to_origin = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("ni,ni->n", poses[:, :3, 2], to_origin), 1.0, atol=1e-3)
    f = ds[0]
    assert f.rgb.shape == (800, 800, 3) and f.rgb[0, 0].tolist() == [255, 255, 255]
