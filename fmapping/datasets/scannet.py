"""ScanNet, in the layout its ``.sens`` exporter writes.

* ``color/N.jpg`` (frames ordered by N, timestamps ``N / 30``), ``pose/N.txt`` (4x4
  camera-to-world, OpenCV axes, metres; ScanNet writes ``-inf`` where tracking failed:
  no ground truth for that frame), ``intrinsic/intrinsic_color.txt`` (4x4, K in the top
  left).
* Optional ``depth/N.png`` (uint16, 1000 per metre, 0 = no reading) with
  ``intrinsic/intrinsic_depth.txt``. ScanNet's depth camera is smaller than its colour
  camera (640x480 against 1296x968) and registered to it, so each depth map is resampled
  onto the colour pixels through the two intrinsics (nearest neighbour, 0 outside the
  depth camera's view); the frames keep the colour resolution. Depth of another size with
  no ``intrinsic_depth.txt`` cannot be placed and is ignored (noted in ``meta``).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import (
    WHITE, Background, CameraArg, ImageSequence, build_sequence, check_max_frames, image_size, log,
    parse_floats, read_depth, resolve_camera, text_lines,
)
from fmapping.datasets.base import DatasetError
from fmapping.datasets.sevenscenes import read_pose_file

SCANNET_FPS = 30.0
SCANNET_DEPTH_SCALE = 1000.0
_NUM_RE = re.compile(r"^(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)


def is_scannet(root: Path) -> bool:
    return (root / "color").is_dir() and ((root / "intrinsic").is_dir() or (root / "pose").is_dir())


def read_intrinsic(path: Path, size: tuple[int, int]) -> PinholeCamera:
    """A ScanNet ``intrinsic_*.txt`` (4x4 or 3x3, K top left) -> camera for ``size`` images."""
    rows = [parse_floats(s, path, lineno, (3, 4), "one row of the intrinsic matrix") for lineno, s in text_lines(path)]
    if len(rows) not in (3, 4) or len({len(r) for r in rows}) != 1:
        raise DatasetError(f"{path}: expected a 4x4 (or 3x3) intrinsic matrix, got {len(rows)} rows")
    k = np.asarray(rows, np.float64)
    try:
        return PinholeCamera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], size[0], size[1])
    except ValueError as e:
        raise DatasetError(f"{path}: invalid intrinsics: {e}") from None


@dataclass(eq=False)
class ScanNetSequence(ImageSequence):
    depth_camera: Optional[PinholeCamera] = None  # intrinsics of the depth images when they differ from colour
    _maps: Optional[tuple] = field(default=None, init=False, repr=False)

    def _read_depth(self, path: Path) -> np.ndarray:
        import cv2

        depth = read_depth(path, self.depth_scale, self.depth_invalid)
        dc = self.depth_camera
        if dc is None:
            return depth
        if depth.shape != (dc.height, dc.width):
            raise DatasetError(f"depth image is {depth.shape[1]}x{depth.shape[0]}, "
                               f"the first was {dc.width}x{dc.height}: {path}")
        if self._maps is None:
            # colour pixel -> its ray -> the depth pixel on that ray (the cameras are registered)
            cam = self.raw_camera
            u = (np.arange(cam.width) - cam.cx) / cam.fx * dc.fx + dc.cx
            v = (np.arange(cam.height) - cam.cy) / cam.fy * dc.fy + dc.cy
            mx = np.broadcast_to(u[None, :], (cam.height, cam.width)).astype(np.float32)
            my = np.broadcast_to(v[:, None], (cam.height, cam.width)).astype(np.float32)
            self._maps = (mx, my)
        return cv2.remap(depth, self._maps[0], self._maps[1], cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def load_scannet(root, camera: CameraArg = None, max_frames: Optional[int] = None, background: Background = WHITE):
    root = Path(root)
    max_frames = check_max_frames(max_frames)
    color = root / "color"
    if not color.is_dir():
        raise DatasetError(f"not a ScanNet export, color/ not found: {color}")
    frames = {int(m.group(1)): p for p in color.iterdir() if (m := _NUM_RE.match(p.name))}
    if not frames:
        raise DatasetError(f"{color}: empty sequence, no N.jpg images")
    ids = sorted(frames)
    n = len(ids) if max_frames is None else min(len(ids), max_frames)
    ids = ids[:n]
    rgb_paths = [frames[i] for i in ids]
    size = image_size(rgb_paths[0])
    meta: dict = {}

    intr = root / "intrinsic" / "intrinsic_color.txt"
    default = read_intrinsic(intr, size) if intr.is_file() and camera is None else None
    what = str(intr) if intr.is_file() else f"{root} (ScanNet export without intrinsic/intrinsic_color.txt)"
    cam, source = resolve_camera(camera, default, size, what)
    meta["camera_source"] = source

    gt: list = []
    for i in ids:  # pose files are only read for the frames kept
        p = root / "pose" / f"{i}.txt"
        gt.append(read_pose_file(p) if p.is_file() else None)
    missing = n - sum(g is not None for g in gt)
    if missing:
        meta["gt_note"] = f"{missing} of {n} frames have no (finite) pose file"

    depth_paths = [root / "depth" / f"{i}.png" for i in ids]
    depth_paths = [p if p.is_file() else None for p in depth_paths]
    depth_camera = None
    first_depth = next((p for p in depth_paths if p is not None), None)
    if first_depth is not None:
        dsize = image_size(first_depth)
        intr_d = root / "intrinsic" / "intrinsic_depth.txt"
        if intr_d.is_file():
            depth_camera = read_intrinsic(intr_d, dsize)
            meta["depth_camera"] = depth_camera.to_dict()
            meta["depth_note"] = "depth resampled onto the colour pixels through intrinsic_depth.txt (nearest)"
        elif dsize != size:
            note = (f"depth is {dsize[0]}x{dsize[1]}, colour {size[0]}x{size[1]}, and there is no "
                    "intrinsic/intrinsic_depth.txt to register them: depth ignored")
            log.warning("%s: %s", root, note)
            meta["depth_note"] = note
            depth_paths = [None] * n
    has_depth = any(p is not None for p in depth_paths)
    return build_sequence(
        root=root, kind="scannet", raw_camera=cam, timestamps=np.asarray(ids, np.float64) / SCANNET_FPS,
        rgb_paths=rgb_paths, depth_paths=depth_paths, gt_poses=gt,
        depth_scale=SCANNET_DEPTH_SCALE if has_depth else None, meta=meta, max_frames=max_frames,
        background=background, cls=ScanNetSequence, extra={"depth_camera": depth_camera},
    )
