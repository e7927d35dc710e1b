"""Replica in the NICE-SLAM layout.

``results/frameXXXXXX.jpg`` (rgb), ``results/depthXXXXXX.png`` (uint16, 6553.5 units
per metre), ``traj.txt`` (one row-major 4x4 camera-to-world matrix per line, 16
numbers, OpenCV axes), frames ordered by their number, timestamps ``index / 30``.
Intrinsics come from ``cam.yaml`` / ``cam.yml`` / ``cam.json`` in the folder (keys
``fx fy cx cy`` and ``W H`` / ``w h`` / ``width height``, optional ``png_depth_scale``
or ``depth_scale`` and ``k1 k2 p1 p2 k3``; the keys may sit under a ``cam:`` section
as in NICE-SLAM configs), else NICE-SLAM's Replica defaults (noted in ``meta``).
"""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import (
    WHITE, Background, CameraArg, build_sequence, check_max_frames, image_size, log,
    make_camera, parse_floats, resolve_camera, scaled_default, text_lines,
)
from fmapping.datasets.base import DatasetError

REPLICA_FPS = 30.0
REPLICA_DEPTH_SCALE = 6553.5
REPLICA_DEFAULT = PinholeCamera(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)
CAM_FILES = ("cam.yaml", "cam.yml", "cam.json")
_FRAME_RE = re.compile(r"^frame(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)


def is_replica(root: Path) -> bool:
    res = root / "results"
    if not res.is_dir():
        return False
    return (root / "traj.txt").is_file() or any(_FRAME_RE.match(p.name) for p in res.iterdir())


def read_cam_file(path: Path) -> dict:
    """A small intrinsics file -> flat dict (a nested ``cam`` section is flattened)."""
    try:
        if path.suffix == ".json":
            data = json.loads(path.read_text())
        else:
            import yaml

            data = yaml.safe_load(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}:{e.lineno}: invalid JSON: {e.msg}") from None
    except Exception as e:  # yaml.YAMLError and friends
        raise DatasetError(f"{path}: cannot parse: {e}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping with fx, fy, cx, cy, W, H")
    if isinstance(data.get("cam"), dict):
        data = {**data, **data["cam"]}
    return data


def camera_from_cam_file(
    path: Path, size: tuple[int, int], want_camera: bool = True
) -> tuple[Optional[PinholeCamera], Optional[float]]:
    """A cam file -> (camera for ``size`` images or None when not wanted, depth scale or None)."""
    d = read_cam_file(path)

    def num(*keys, required=True):
        for k in keys:
            if k in d and d[k] is not None:
                try:
                    return float(d[k])
                except (TypeError, ValueError):
                    raise DatasetError(f"{path}: {k} must be a number, got {d[k]!r}") from None
        if required:
            raise DatasetError(f"{path}: missing key {' / '.join(keys)}")
        return None

    scale = num("png_depth_scale", "depth_scale", required=False)
    if scale is not None and scale <= 0:
        raise DatasetError(f"{path}: depth scale must be positive, got {scale}")
    if not want_camera:
        return None, scale
    fx, fy, cx, cy = num("fx"), num("fy"), num("cx"), num("cy")
    w, h = num("W", "w", "width", required=False), num("H", "h", "height", required=False)
    if w is not None and h is not None and (int(w), int(h)) != tuple(size):
        raise DatasetError(f"{path}: intrinsics are for {int(w)}x{int(h)} images "
                           f"but the images are {size[0]}x{size[1]}")
    dist = [num(k, required=False) or 0.0 for k in ("k1", "k2", "p1", "p2", "k3")]
    cam = make_camera([fx, fy, cx, cy] + (dist if any(dist) else []), size, str(path))
    return cam, scale


def read_matrix_lines(path: Path) -> list[Optional[np.ndarray]]:
    """``traj.txt``: 16 numbers per line -> 4x4 c2w (None when non-finite). Errors name file:line."""
    poses: list[Optional[np.ndarray]] = []
    for lineno, s in text_lines(path):
        vals = parse_floats(s, path, lineno, (16,), "row-major 4x4 camera-to-world")
        m = np.asarray(vals, np.float64).reshape(4, 4)
        if not np.all(np.isfinite(m)):
            poses.append(None)
            continue
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise DatasetError(f"{path}:{lineno}: last row of the 4x4 pose must be 0 0 0 1, got {m[3].tolist()}")
        poses.append(m)
    return poses


def load_replica(
    root, camera: CameraArg = None, max_frames: Optional[int] = None, background: Background = WHITE
):
    root = Path(root)
    max_frames = check_max_frames(max_frames)
    res = root / "results"
    if not res.is_dir():
        raise DatasetError(f"not a Replica (NICE-SLAM) folder, results/ not found: {res}")
    frames: dict[int, Path] = {}
    depths: dict[int, Path] = {}
    for p in res.iterdir():
        m = _FRAME_RE.match(p.name)
        if m:
            frames[int(m.group(1))] = p
        elif p.name.startswith("depth") and p.suffix.lower() == ".png" and p.stem[5:].isdigit():
            depths[int(p.stem[5:])] = p
    if not frames:
        raise DatasetError(f"{res}: empty sequence, no frameXXXXXX.jpg images")
    ids = sorted(frames)
    rgb_paths = [frames[i] for i in ids]
    depth_paths = [depths.get(i) for i in ids]
    size = image_size(rgb_paths[0])
    meta: dict = {}

    depth_scale = REPLICA_DEPTH_SCALE
    cam_file = next((root / n for n in CAM_FILES if (root / n).is_file()), None)
    default, source = None, "--camera"
    if cam_file is not None:
        default, scale = camera_from_cam_file(cam_file, size, want_camera=camera is None)
        depth_scale = scale or depth_scale
        source = str(cam_file)
    elif camera is None:
        default, note = scaled_default(REPLICA_DEFAULT, size, "NICE-SLAM Replica default")
        source = "default: NICE-SLAM Replica intrinsics (no cam.yaml / cam.json)"
        if note:
            meta["camera_note"] = note
    cam, source = resolve_camera(camera, default, size, source)
    meta["camera_source"] = source

    gt: list = [None] * len(ids)
    traj = root / "traj.txt"
    if traj.is_file():
        poses = read_matrix_lines(traj)
        if len(poses) < len(ids):
            log.warning("%s: %d poses for %d frames; the last frames have no ground truth", traj, len(poses), len(ids))
            meta["gt_note"] = f"{traj} has {len(poses)} poses for {len(ids)} frames"
        # NICE-SLAM: line k of traj.txt is the pose of frame k
        gt = [poses[i] if i < len(poses) else None for i in ids]
        meta["groundtruth"] = str(traj)

    has_depth = any(p is not None for p in depth_paths)
    return build_sequence(
        root=root, kind="replica", raw_camera=cam, timestamps=np.asarray(ids, np.float64) / REPLICA_FPS,
        rgb_paths=rgb_paths, depth_paths=depth_paths, gt_poses=gt,
        depth_scale=depth_scale if has_depth else None, meta=meta, max_frames=max_frames, background=background,
    )
