"""NeRF / nerfstudio / instant-ngp ``transforms.json`` (also ``transforms_train.json``).

* Intrinsics: ``fl_x`` [``fl_y``] ``cx cy w h`` (nerfstudio), or ``camera_angle_x``
  [``camera_angle_y``] (Blender NeRF: ``f = 0.5 W / tan(0.5 angle)``); sizes default to
  the first image's. OpenCV distortion ``k1 k2 p1 p2 [k3]`` is read for
  ``camera_model`` ``OPENCV`` / absent; other models are rejected.
* Pixel convention: these files put the first pixel's centre at (0.5, 0.5); ours is
  (0, 0), so ``cx = cx_file - 0.5`` (and ``W / 2 - 0.5`` when no ``cx`` is given, the
  exact image centre of a Blender render). ``meta["principal_point_convention"]``
  says so.
* ``frames[i].file_path`` is relative to the json's folder, with or without an image
  suffix; ``transform_matrix`` is camera-to-world in OpenGL/Blender camera axes (x
  right, y up, z backward), converted with ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``.
* Frames keep the file's order; timestamps are the frame index. RGBA images are
  composited over ``background`` (white by default, the NeRF practice). No depth.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.datasets._io import (
    WHITE, Background, CameraArg, build_sequence, check_max_frames, image_size, make_camera,
    resolve_camera, resolve_image_path,
)
from fmapping.datasets.base import DatasetError

TRANSFORMS_FILES = ("transforms.json", "transforms_train.json")
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                   "k1", "k2", "k3", "p1", "p2")


def find_transforms(root: Path) -> Optional[Path]:
    if root.is_file() and root.suffix == ".json":
        return root
    return next((root / n for n in TRANSFORMS_FILES if (root / n).is_file()), None)


def is_nerf(root: Path) -> bool:
    return find_transforms(root) is not None


def _num(d: dict, key: str, where: str) -> Optional[float]:
    if key not in d or d[key] is None:
        return None
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise DatasetError(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)


def _pose(frame: dict, where: str) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise DatasetError(f"{where}: missing transform_matrix")
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: transform_matrix is not a numeric matrix") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise DatasetError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise DatasetError(f"{where}: transform_matrix has NaN or Inf")
    return m @ GL_TO_CV


def load_nerf(root, camera: CameraArg = None, max_frames: Optional[int] = None, background: Background = WHITE):
    root = Path(root)
    max_frames = check_max_frames(max_frames)
    path = find_transforms(root)
    if path is None:
        raise DatasetError(f"{root}: no {' or '.join(TRANSFORMS_FILES)}")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}:{e.lineno}: invalid JSON: {e.msg}") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise DatasetError(f"{path}: expected an object with a 'frames' list")
    frames = data["frames"]
    if not frames:
        raise DatasetError(f"{path}: empty sequence, 'frames' is empty")
    model = data.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise DatasetError(f"{path}: camera_model {model!r} is not supported (only pinhole / OPENCV)")

    # intrinsics: global keys, else those of the first frame; per-frame differences are unsupported
    intr = {k: data[k] for k in _INTRINSIC_KEYS if k in data}
    if not intr:
        intr = {k: frames[0][k] for k in _INTRINSIC_KEYS if isinstance(frames[0], dict) and k in frames[0]}
    base = path.parent
    rgb_paths, gt = [], []
    for i, fr in enumerate(frames):
        where = f"{path}: frames[{i}]"
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str) or not fr["file_path"]:
            raise DatasetError(f"{where}: missing file_path")
        for k in _INTRINSIC_KEYS:
            if k in fr and k in intr and fr[k] != intr[k]:
                raise DatasetError(f"{where}: per-frame intrinsics ({k}) differ from the others; not supported")
        rgb_paths.append(base / fr["file_path"])
        gt.append(_pose(fr, where))

    first = resolve_image_path(rgb_paths[0])
    size = image_size(first)
    w, h = _num(intr, "w", str(path)), _num(intr, "h", str(path))
    if camera is None and w is not None and h is not None and (int(w), int(h)) != size:
        raise DatasetError(f"{path}: w, h = {int(w)}x{int(h)} but the first image is {size[0]}x{size[1]}: {first}")
    W, H = size
    fx, fy = _num(intr, "fl_x", str(path)), _num(intr, "fl_y", str(path))
    ax, ay = _num(intr, "camera_angle_x", str(path)), _num(intr, "camera_angle_y", str(path))
    if fx is None and ax is not None:
        fx = 0.5 * W / math.tan(0.5 * ax)
    if fy is None and ay is not None:
        fy = 0.5 * H / math.tan(0.5 * ay)
    if fx is None and fy is None and camera is None:
        raise DatasetError(f"{path}: no focal length (fl_x or camera_angle_x); pass --camera fx,fy,cx,cy")
    fx = fx if fx is not None else fy
    fy = fy if fy is not None else fx
    cx, cy = _num(intr, "cx", str(path)), _num(intr, "cy", str(path))
    cx = (cx if cx is not None else W / 2.0) - 0.5
    cy = (cy if cy is not None else H / 2.0) - 0.5
    dist = [_num(intr, k, str(path)) or 0.0 for k in ("k1", "k2", "p1", "p2", "k3")]
    default = None
    if fx is not None:
        default = make_camera([fx, fy, cx, cy] + (dist if any(dist) else []), size, str(path))
    cam, source = resolve_camera(camera, default, size, str(path))
    meta = {
        "camera_source": source,
        "transforms": str(path),
        "principal_point_convention": "pixel centres at integers: cx = cx_file - 0.5 (W/2 - 0.5 when absent)",
        "pose_convention": "transform_matrix (OpenGL camera axes) @ diag(1,-1,-1,1)",
        "background": list(background),
    }
    splits = [n for n in ("transforms_train.json", "transforms_val.json", "transforms_test.json")
              if (base / n).is_file() and base / n != path]
    if splits:
        meta["other_splits"] = splits
    return build_sequence(
        root=base, kind="nerf", raw_camera=cam, timestamps=np.arange(len(frames), dtype=np.float64),
        rgb_paths=rgb_paths, depth_paths=None, gt_poses=gt, depth_scale=None, meta=meta,
        max_frames=max_frames, background=background,
    )
