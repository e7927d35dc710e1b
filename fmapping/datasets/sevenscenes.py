"""Microsoft 7-Scenes.

A sequence folder ``seq-XX`` holds ``frame-XXXXXX.color.png``, ``frame-XXXXXX.depth.png``
(uint16 millimetres, 65535 = no reading) and ``frame-XXXXXX.pose.txt`` (4x4
camera-to-world, OpenCV axes, metres). A scene folder holding ``seq-XX`` folders
reads its first sequence (the list is in ``meta["sequences"]``). Intrinsics are the
nominal Kinect values fx = fy = 585, cx = 320, cy = 240 (640x480), rescaled if the
images have another size. Timestamps are ``index / 30``.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import (
    WHITE, Background, CameraArg, build_sequence, check_max_frames, image_size, log,
    parse_floats, resolve_camera, scaled_default, text_lines,
)
from fmapping.datasets.base import DatasetError

SEVEN_SCENES_FPS = 30.0
SEVEN_SCENES_DEPTH_SCALE = 1000.0
SEVEN_SCENES_INVALID = 65535
SEVEN_SCENES_CAMERA = PinholeCamera(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
_COLOR_RE = re.compile(r"^frame-(\d+)\.color\.png$")


def _has_frames(folder: Path) -> bool:
    return folder.is_dir() and any(_COLOR_RE.match(p.name) for p in folder.iterdir())


def sequence_folders(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith("seq") and _has_frames(p))


def is_sevenscenes(root: Path) -> bool:
    return _has_frames(root) or bool(sequence_folders(root))


def read_pose_file(path: Path) -> Optional[np.ndarray]:
    """A 4x4 matrix text file -> c2w (None when it holds non-finite values). Errors name file:line."""
    lines = text_lines(path)
    rows = [parse_floats(s, path, lineno, (4,), "one row of a 4x4 pose") for lineno, s in lines]
    if len(rows) != 4:
        raise DatasetError(f"{path}: expected 4 rows of 4 numbers (a 4x4 camera-to-world), got {len(rows)} rows")
    m = np.asarray(rows, np.float64)
    if not np.all(np.isfinite(m)):
        return None
    return m


def load_sevenscenes(
    root, camera: CameraArg = None, max_frames: Optional[int] = None, background: Background = WHITE
):
    root = Path(root)
    max_frames = check_max_frames(max_frames)
    meta: dict = {}
    seq = root
    if not _has_frames(root):
        seqs = sequence_folders(root)
        if not seqs:
            raise DatasetError(f"{root}: no 7-Scenes frames (frame-XXXXXX.color.png) and no seq-XX folders with them")
        seq = seqs[0]
        meta["sequences"] = [p.name for p in seqs]
        log.info("%s: reading the first sequence %s of %d", root, seq.name, len(seqs))
    meta["sequence"] = seq.name

    ids = sorted(int(m.group(1)) for p in seq.iterdir() if (m := _COLOR_RE.match(p.name)))
    rgb_paths = [seq / f"frame-{i:06d}.color.png" for i in ids]
    depth_paths = [seq / f"frame-{i:06d}.depth.png" for i in ids]
    depth_paths = [p if p.is_file() else None for p in depth_paths]
    size = image_size(rgb_paths[0])
    default, note = None, None
    if camera is None:
        default, note = scaled_default(SEVEN_SCENES_CAMERA, size, "7-Scenes nominal")
    if note:
        meta["camera_note"] = note
    cam, source = resolve_camera(camera, default, size, "7-Scenes nominal intrinsics (fx=fy=585, cx=320, cy=240)")
    meta["camera_source"] = source

    n = len(ids) if max_frames is None else min(len(ids), max_frames)
    gt: list = []
    for i in ids[:n]:  # pose files are only read for the frames kept
        p = seq / f"frame-{i:06d}.pose.txt"
        gt.append(read_pose_file(p) if p.is_file() else None)
    missing = n - sum(g is not None for g in gt)
    if missing:
        meta["gt_note"] = f"{missing} of {n} frames have no (finite) pose file"

    has_depth = any(p is not None for p in depth_paths)
    return build_sequence(
        root=seq, kind="7scenes", raw_camera=cam, timestamps=np.asarray(ids[:n], np.float64) / SEVEN_SCENES_FPS,
        rgb_paths=rgb_paths[:n], depth_paths=depth_paths[:n], gt_poses=gt,
        depth_scale=SEVEN_SCENES_DEPTH_SCALE if has_depth else None, meta=meta, max_frames=max_frames,
        depth_invalid=SEVEN_SCENES_INVALID, background=background,
    )
