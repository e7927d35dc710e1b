"""A plain folder of images (``*.png`` / ``*.jpg`` / ``*.jpeg``): one frame per file.

Frames are the folder's images sorted by name, numbers in names compared as numbers
(``frame2`` before ``frame10``). Timestamps are ``index / fps``: ``fps`` from the
``fps=`` option, else an ``fps`` key in ``camera.yaml``, else 30. Intrinsics come from
``--camera`` or a ``calib.txt`` / ``camera.yaml`` in the folder (see
:mod:`fmapping.datasets.calib`); with neither the folder is rejected with an error that
says how to give them. No depth, no ground truth.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.datasets._io import WHITE, Background, CameraArg, build_sequence, check_max_frames, image_size
from fmapping.datasets.base import DatasetError
from fmapping.datasets.calib import camera_next_to

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
DEFAULT_FPS = 30.0
_DIGITS = re.compile(r"(\d+)")


def _natural_key(name: str) -> list:
    return [(0, int(t), t) if t.isdigit() else (1, 0, t.lower()) for t in _DIGITS.split(name) if t]


def image_files(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS]
    return sorted(files, key=lambda p: _natural_key(p.name))


def is_image_folder(root: Path) -> bool:
    return root.is_dir() and any(p.is_file() and p.suffix.lower() in IMAGE_EXTS for p in root.iterdir())


def check_fps(fps: Optional[float], where: str) -> Optional[float]:
    if fps is None:
        return None
    try:
        f = float(fps)
    except (TypeError, ValueError):
        f = float("nan")
    if not np.isfinite(f) or f <= 0:
        raise DatasetError(f"{where}: fps must be a positive number, got {fps!r}")
    return f


def load_images(root, camera: CameraArg = None, max_frames: Optional[int] = None,
                background: Background = WHITE, fps: Optional[float] = None):
    root = Path(root)
    max_frames = check_max_frames(max_frames)
    fps = check_fps(fps, str(root))
    if not root.is_dir():
        raise DatasetError(f"image folder not found: {root}")
    files = image_files(root)
    if not files:
        raise DatasetError(f"{root}: no {'/'.join(IMAGE_EXTS)} images in the folder")
    size = image_size(files[0])
    cam, source, file_fps = camera_next_to(root, camera, size, f"{root} (a plain image folder)")
    rate = fps or file_fps or DEFAULT_FPS
    meta = {
        "camera_source": source,
        "fps": rate,
        "fps_source": "fps option" if fps else ("calibration file" if file_fps else f"default {DEFAULT_FPS:g}"),
        "order": "file names, numbers compared as numbers",
    }
    return build_sequence(
        root=root, kind="images", raw_camera=cam, timestamps=np.arange(len(files), dtype=np.float64) / rate,
        rgb_paths=files, depth_paths=None, gt_poses=[None] * len(files), depth_scale=None, meta=meta,
        max_frames=max_frames, background=background,
    )
