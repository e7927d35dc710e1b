"""EuRoC MAV (ASL folder layout), left camera ``cam0``.

* Frames: ``mav0/cam0/data.csv`` rows ``timestamp_ns,filename`` with the images in
  ``mav0/cam0/data/`` (8-bit greyscale, delivered as 3 equal channels); timestamps in seconds.
* Intrinsics: ``mav0/cam0/sensor.yaml`` (``intrinsics: [fu, fv, cu, cv]``,
  ``distortion_model: radial-tangential`` with ``[k1, k2, p1, p2]``, ``resolution``);
  frames are undistorted. ``T_BS`` there is the camera-to-body extrinsic.
* Ground truth: ``mav0/state_groundtruth_estimate0/data.csv`` (``timestamp_ns, p_x, p_y,
  p_z, q_w, q_x, q_y, q_z, ...``) is the *body* (IMU) pose in the world; it is
  interpolated at each image timestamp (as TUM ground truth, 0.02 s tolerance) and
  composed with the extrinsic: ``c2w = T_WB @ T_BS``.

The folder may be given as the sequence folder (holding ``mav0/``) or as ``mav0/`` itself.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import (
    WHITE, Background, CameraArg, build_sequence, check_max_frames, image_size, parse_floats,
    resolve_camera, text_lines,
)
from fmapping.datasets.base import DatasetError
from fmapping.trajectory import interpolate_poses, tum_rows_to_poses

MAX_DT = 0.02  # seconds between bracketing ground-truth rows (they come at 200 Hz)


def euroc_mav(root: Path) -> Optional[Path]:
    """The ``mav0`` folder of a EuRoC sequence given as ``root`` or ``root/mav0``."""
    for mav in (root / "mav0", root):
        if (mav / "cam0" / "data.csv").is_file():
            return mav
    return None


def is_euroc(root: Path) -> bool:
    return euroc_mav(root) is not None


def read_sensor_yaml(path: Path, size: tuple[int, int]) -> tuple[PinholeCamera, np.ndarray]:
    """``cam0/sensor.yaml`` -> (camera of the stored images, T_BS camera-to-body 4x4)."""
    import yaml

    if not path.is_file():
        raise DatasetError(f"EuRoC camera calibration not found: {path}")
    # some ASL yaml files start with OpenCV's '%YAML:1.0' directive, which is not YAML
    text = "\n".join(s for s in path.read_text().splitlines() if not s.startswith("%YAML"))
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise DatasetError(f"{path}: cannot parse: {e}") from None
    if not isinstance(d, dict):
        raise DatasetError(f"{path}: expected a mapping with intrinsics, T_BS")
    model = str(d.get("camera_model", "pinhole"))
    if model != "pinhole":
        raise DatasetError(f"{path}: camera_model {model!r} is not supported (pinhole only)")
    try:
        k = [float(v) for v in d["intrinsics"]]
        t_bs = np.asarray([float(v) for v in d["T_BS"]["data"]], np.float64)
        dist = [float(v) for v in d.get("distortion_coefficients") or []]
        res = d.get("resolution")
    except KeyError as e:
        raise DatasetError(f"{path}: missing key {e.args[0]}") from None
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{path}: malformed intrinsics / T_BS / distortion: {e}") from None
    if len(k) != 4:
        raise DatasetError(f"{path}: intrinsics must be [fu, fv, cu, cv], got {len(k)} numbers")
    if t_bs.size != 16:
        raise DatasetError(f"{path}: T_BS must hold 16 numbers (row-major 4x4), got {t_bs.size}")
    t_bs = t_bs.reshape(4, 4)
    if not np.allclose(t_bs[3], [0, 0, 0, 1], atol=1e-6):
        raise DatasetError(f"{path}: last row of T_BS must be 0 0 0 1, got {t_bs[3].tolist()}")
    dmodel = str(d.get("distortion_model", "radial-tangential"))
    if any(dist) and dmodel not in ("radial-tangential", "radtan", "plumb_bob"):
        raise DatasetError(f"{path}: distortion_model {dmodel!r} is not supported (radial-tangential only)")
    if any(dist) and len(dist) not in (4, 5):
        raise DatasetError(f"{path}: radial-tangential needs 4 (k1 k2 p1 p2) or 5 coefficients, got {len(dist)}")
    if res is not None and tuple(int(v) for v in res) != tuple(size):
        raise DatasetError(f"{path}: resolution {list(res)} but the images are {size[0]}x{size[1]}")
    try:
        cam = PinholeCamera(k[0], k[1], k[2], k[3], size[0], size[1], tuple(dist) if any(dist) else None)
    except ValueError as e:
        raise DatasetError(f"{path}: invalid intrinsics: {e}") from None
    return cam, t_bs


def read_body_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``state_groundtruth_estimate0/data.csv`` -> (timestamps in integer ns, T_WB (N, 4, 4))."""
    ts, rows = [], []
    for lineno, s in text_lines(path):
        vals = parse_floats(s, path, lineno, None)
        if len(vals) < 8:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z, ...', "
                               f"got {len(vals)} numbers")
        if not np.all(np.isfinite(vals[:8])) or np.linalg.norm(vals[4:8]) < 1e-6:
            raise DatasetError(f"{path}:{lineno}: non-finite position or zero quaternion")
        first = s.replace(",", " ").split()[0]
        ts.append(int(first) if first.isdigit() else int(round(vals[0])))
        w, x, y, z = vals[4:8]  # EuRoC writes the quaternion w first
        rows.append([0.0, *vals[1:4], x, y, z, w])
    if not rows:
        raise DatasetError(f"{path}: no poses in the file")
    return np.asarray(ts, np.int64), tum_rows_to_poses(np.asarray(rows, np.float64))


def load_euroc(root, camera: CameraArg = None, max_frames: Optional[int] = None, background: Background = WHITE):
    root = Path(root)
    max_frames = check_max_frames(max_frames)
    mav = euroc_mav(root)
    if mav is None:
        raise DatasetError(f"not a EuRoC folder, mav0/cam0/data.csv not found under {root}")
    cam_dir = mav / "cam0"
    csv = cam_dir / "data.csv"
    ns, paths = [], []
    for lineno, s in text_lines(csv):
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 2 or not parts[0].isdigit():
            raise DatasetError(f"{csv}:{lineno}: expected 'timestamp_ns,filename', got {s!r}")
        ns.append(int(parts[0]))
        paths.append(cam_dir / "data" / parts[1])
    if not paths:
        raise DatasetError(f"{csv}: empty sequence, no images listed")
    ns = np.asarray(ns, np.int64)
    ts = ns / 1e9
    size = image_size(paths[0])
    sensor = cam_dir / "sensor.yaml"
    default, t_bs = read_sensor_yaml(sensor, size)
    cam, source = resolve_camera(camera, default, size, str(sensor))
    meta: dict = {"camera_source": source, "camera": "cam0", "T_BS": t_bs.tolist()}

    gt: list = [None] * len(ts)
    gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.is_file():
        g_ns, t_wb = read_body_groundtruth(gt_csv)
        # seconds since the first image, from integer ns: epoch seconds in float64 are only good to
        # ~0.2 us, a 5e-5 error on the weight between 200 Hz ground-truth rows
        body, how = interpolate_poses((ns - ns[0]) / 1e9, (g_ns - ns[0]) / 1e9, t_wb, MAX_DT)
        gt = [body[i] @ t_bs if h != "none" else None for i, h in enumerate(how)]
        meta["groundtruth"] = str(gt_csv)
        meta["groundtruth_association"] = {k: int((how == k).sum()) for k in ("interpolated", "nearest", "none")}
        meta["pose_convention"] = "c2w = T_WB (ground truth, interpolated) @ T_BS (cam0 extrinsic)"
    return build_sequence(
        root=mav.parent if mav.name == "mav0" else mav, kind="euroc", raw_camera=cam, timestamps=ts,
        rgb_paths=paths, depth_paths=None, gt_poses=gt, depth_scale=None, meta=meta,
        max_frames=max_frames, background=background,
    )
