"""Calibration files for sources that carry no intrinsics (image folders, videos, webcams).

Looked for next to the images (``find_calib``), or named by ``--camera PATH``:

* ``calib.txt``: first line ``fx fy cx cy [k1 k2 p1 p2 [k3]]`` (the TUM-layout file, see
  :func:`fmapping.datasets.tum.read_calib`);
* ``camera.yaml`` / ``camera.yml`` / ``*.json``: flat keys ``fx fy cx cy`` [``width
  height``] [``k1 k2 p1 p2 k3``] [``fps``] (as Replica's ``cam.yaml``), or the ROS
  ``camera_info`` yaml that ``camera_calibration`` writes (``camera_matrix.data``,
  ``distortion_model``, ``distortion_coefficients.data``, ``image_width``, ``image_height``).

Pixel centres are at integer coordinates in all of them (OpenCV / ROS convention, ours too).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import make_camera, no_intrinsics_message
from fmapping.datasets.base import DatasetError

CALIB_FILES = ("calib.txt", "camera.yaml", "camera.yml")
# ROS distortion models that are OpenCV's k1 k2 p1 p2 [k3 [k4 k5 k6]]
ROS_OPENCV_MODELS = ("plumb_bob", "rational_polynomial", "")


def find_calib(folder: Path) -> Optional[Path]:
    return next((folder / n for n in CALIB_FILES if (folder / n).is_file()), None)


def camera_from_ros(k: Sequence[float], d: Sequence[float], model: str, width: int, height: int,
                    size: tuple[int, int], where: str) -> PinholeCamera:
    """ROS ``CameraInfo`` fields (K row-major 3x3, D, distortion_model, size) -> camera for ``size`` images."""
    k = [float(v) for v in k]
    if len(k) != 9:
        raise DatasetError(f"{where}: camera matrix must have 9 numbers, got {len(k)}")
    if k[0] <= 0 or k[4] <= 0:
        # camera drivers publish an all-zero K until the camera is calibrated
        raise DatasetError(no_intrinsics_message(f"{where} (the camera matrix is zero: camera not calibrated)"))
    if width and height and (int(width), int(height)) != tuple(size):
        raise DatasetError(f"{where}: calibration is for {int(width)}x{int(height)} images but the images are "
                           f"{size[0]}x{size[1]}; pass --camera to set intrinsics for this size")
    dist = tuple(float(v) for v in d)
    if not any(dist):
        dist = None
    elif (model or "") not in ROS_OPENCV_MODELS:
        raise DatasetError(f"{where}: distortion model {model!r} is not supported (plumb_bob / rational_polynomial "
                           "only); undistort the images first or pass --camera")
    elif len(dist) not in (4, 5, 8):
        raise DatasetError(f"{where}: expected 4, 5 or 8 distortion coefficients, got {len(dist)}")
    try:
        return PinholeCamera(k[0], k[4], k[2], k[5], size[0], size[1], dist)
    except ValueError as e:
        raise DatasetError(f"{where}: invalid intrinsics: {e}") from None


def _ros_yaml_camera(d: dict, size: tuple[int, int], where: str) -> PinholeCamera:
    def data(key: str) -> list:
        block = d.get(key) or {}
        vals = block.get("data") if isinstance(block, dict) else block
        if not isinstance(vals, list):
            raise DatasetError(f"{where}: {key} must hold a 'data' list")
        return vals

    try:
        return camera_from_ros(data("camera_matrix"), data("distortion_coefficients") if "distortion_coefficients" in d
                               else [], str(d.get("distortion_model", "")), int(d.get("image_width") or 0),
                               int(d.get("image_height") or 0), size, where)
    except (TypeError, ValueError) as e:
        if isinstance(e, DatasetError):
            raise
        raise DatasetError(f"{where}: non-numeric calibration value: {e}") from None


def load_camera_file(path: Path, size: tuple[int, int]) -> tuple[PinholeCamera, Optional[float]]:
    """A calibration file -> (camera for ``size`` images, frame rate or None)."""
    from fmapping.datasets.replica import camera_from_cam_file, read_cam_file
    from fmapping.datasets.tum import read_calib

    if path.suffix.lower() == ".txt":
        vals, lineno, _ = read_calib(path)
        return make_camera(vals, size, f"{path}:{lineno}"), None
    if path.suffix.lower() not in (".yaml", ".yml", ".json"):
        raise DatasetError(f"{path}: unknown calibration file type (expected calib.txt, .yaml, .yml or .json)")
    d = read_cam_file(path)
    fps = d.get("fps")
    if fps is not None:
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            fps = float("nan")
        if not np.isfinite(fps) or fps <= 0:
            raise DatasetError(f"{path}: fps must be a positive number, got {d.get('fps')!r}")
    if "camera_matrix" in d:
        return _ros_yaml_camera(d, size, str(path)), fps
    cam, _ = camera_from_cam_file(path, size)
    return cam, fps


def read_camera_file(path: Path, size: tuple[int, int]) -> PinholeCamera:
    return load_camera_file(path, size)[0]


def camera_next_to(folder: Path, override, size: tuple[int, int],
                   what: str) -> tuple[PinholeCamera, str, Optional[float]]:
    """Intrinsics of a source without its own: ``override`` (``--camera``), else a calibration file
    in ``folder``, else a :class:`DatasetError` that says how to give them (never a guess).

    Returns (camera of the stored images, where it came from, fps from the file or None).
    """
    from fmapping.datasets._io import resolve_camera

    calib = find_calib(folder)
    default, source, fps = None, what, None
    if calib is not None:
        cam, fps = load_camera_file(calib, size)
        if override is None:
            default, source = cam, str(calib)
    cam, source = resolve_camera(override, default, size, source)
    return cam, source, fps
