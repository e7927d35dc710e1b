"""A video file (``.mp4`` / ``.avi`` / ``.mkv`` / ``.mov``) read with ``cv2.VideoCapture``.

* Frames: every decoded frame, counted once at open by decoding the file up to
  ``max_frames`` (container frame counts are estimates, and a wrong length would stop a
  run midway). Timestamps are ``index / fps`` with the container's frame rate, or the
  ``fps=`` option when given (required when the container has none).
* Access: sequential reads are plain decodes; going back reopens the file and skips
  forward (seeking is inexact for many codecs, and a wrong frame would be silent).
* Intrinsics: ``--camera`` or a ``calib.txt`` / ``camera.yaml`` in the video's folder
  (see :mod:`fmapping.datasets.calib`); with neither the video is rejected with an error
  that says how to give them. No depth, no ground truth.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import WHITE, Background, CameraArg, check_max_frames, to_rgb8
from fmapping.datasets.base import Dataset, DatasetError, Frame
from fmapping.datasets.calib import camera_next_to
from fmapping.datasets.images import check_fps

VIDEO_EXTS = (".mp4", ".avi", ".mkv", ".mov")


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_EXTS


def open_capture(source, where: str):
    """A ``cv2.VideoCapture`` on a file or device index, opened or a :class:`DatasetError`."""
    import cv2

    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_ERROR)  # a failed open is the one line below, not OpenCV's warnings too
    try:
        cap = cv2.VideoCapture(source)
    finally:
        log.setLogLevel(level)
    if not cap.isOpened():
        cap.release()
        raise DatasetError(f"cannot open {where} with OpenCV (missing file or device, or a codec this build lacks)")
    return cap


def frame_from_bgr(img: np.ndarray, index: int, timestamp: float, raw_camera: PinholeCamera,
                   camera: PinholeCamera, where: str) -> Frame:
    """A decoded capture image -> undistorted RGB :class:`Frame` (no depth, no pose)."""
    rgb = to_rgb8(img, Path(where))
    if rgb.shape[:2] != (raw_camera.height, raw_camera.width):
        raise DatasetError(f"{where}: frame {index} is {rgb.shape[1]}x{rgb.shape[0]}, "
                           f"the first frame was {raw_camera.width}x{raw_camera.height}")
    return Frame(index=index, timestamp=timestamp, rgb=raw_camera.undistort_image(rgb), camera=camera)


@dataclass(eq=False)
class VideoFrames(Dataset):
    path: Optional[Path] = None
    raw_camera: Optional[PinholeCamera] = None  # camera of the stored frames (may be distorted)
    _cap: object = field(default=None, init=False, repr=False)
    _next: int = field(default=0, init=False, repr=False)  # index of the frame the capture decodes next
    _lock: object = field(default_factory=threading.Lock, init=False, repr=False)

    def _decode(self, i: int) -> np.ndarray:
        with self._lock:  # one capture, one position: readers from several threads take turns
            if self._cap is None or i < self._next:
                self.close()
                self._cap, self._next = open_capture(str(self.path), f"video {self.path}"), 0
            while self._next < i:
                if not self._cap.grab():
                    raise DatasetError(f"{self.path}: the video ended at frame {self._next}, before frame {i}")
                self._next += 1
            ok, img = self._cap.read()
            if not ok or img is None:
                raise DatasetError(f"{self.path}: cannot decode frame {i}")
            self._next += 1
            return img

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an int, got {type(i).__name__}")
        i = int(i) + n if i < 0 else int(i)
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        return frame_from_bgr(self._decode(i), i, float(self.timestamps[i]), self.raw_camera, self.camera,
                              str(self.path))

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __getstate__(self) -> dict:  # the capture and the lock stay with this process
        state = dict(self.__dict__)
        state.update(_cap=None, _next=0, _lock=None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()


def load_video(path, camera: CameraArg = None, max_frames: Optional[int] = None,
               background: Background = WHITE, fps: Optional[float] = None) -> VideoFrames:
    import cv2

    path = Path(path)
    max_frames = check_max_frames(max_frames)
    fps = check_fps(fps, str(path))
    if not path.is_file():
        raise DatasetError(f"video file not found: {path}")
    cap = open_capture(str(path), f"video {path}")
    try:
        container_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        ok, first = cap.read()
        if not ok or first is None:
            raise DatasetError(f"{path}: no decodable frame in the video")
        n = 1
        while (max_frames is None or n < max_frames) and cap.grab():
            n += 1
    finally:
        cap.release()
    size = (int(first.shape[1]), int(first.shape[0]))
    cam, source, file_fps = camera_next_to(path.parent, camera, size, f"{path} (a video file)")
    valid_container = np.isfinite(container_fps) and 0 < container_fps < 10000
    rate = fps or (container_fps if valid_container else None) or file_fps
    if rate is None:
        raise DatasetError(f"{path}: the container gives no frame rate; "
                           "pass fps= (open_dataset) or an fps key in camera.yaml")
    meta = {
        "camera_source": source,
        "video": str(path),
        "fps": rate,
        "fps_source": "fps option" if fps else ("container" if valid_container else "calibration file"),
        "undistorted": cam.dist is not None,
    }
    if cam.dist is not None:
        meta["distortion"] = list(cam.dist)
    return VideoFrames(
        root=path, camera=cam.undistorted(), timestamps=np.arange(n, dtype=np.float64) / rate,
        gt_poses=[None] * n, kind="video", depth_scale=None, meta=meta, path=path, raw_camera=cam,
    )
