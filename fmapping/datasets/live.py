"""A live camera, ``camera:N`` (``cv2.VideoCapture(N)``).

A live stream has no length, no random access, no timestamps known in advance and no
ground truth, so it is not a :class:`~fmapping.datasets.base.Dataset`: ``fmapping map`` /
``slam`` / ``info`` (which index frames, read ``len``, ``timestamps`` and ``gt_poses``)
refuse it, and only ``python -m services.io play`` streams it (``open_dataset(...,
live=True)``), frame after frame until the device stops or ``max_frames`` is reached.
To map offline, record a video or an image folder and open that instead.

``stream[i]`` reads the next frame from the device and labels it ``i`` (a live camera
cannot go back); it raises :class:`IndexError` when the stream has ended. Timestamps are
the wall-clock time (``time.time()``) at which each frame was read. Intrinsics come
only from ``camera=`` (``--camera fx,fy,cx,cy[,dist]`` or ``--camera path/to/camera.yaml``):
without them the device is not even opened.
"""
from __future__ import annotations

import re
import threading
import time
from typing import Iterator, Optional, Union

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import CameraArg, check_max_frames, no_intrinsics_message, resolve_camera
from fmapping.datasets.base import DatasetError, Frame
from fmapping.datasets.video import frame_from_bgr, open_capture

LIVE_PREFIX = "camera:"
_LIVE_RE = re.compile(r"^camera:(\d+)$")


def live_index(path) -> Optional[int]:
    """``"camera:0"`` -> 0; None for anything else (a path)."""
    m = _LIVE_RE.match(str(path)) if isinstance(path, str) else None
    return int(m.group(1)) if m else None


def is_live_spec(path) -> bool:
    return isinstance(path, str) and path.startswith(LIVE_PREFIX)


def refuse_live(path: str) -> DatasetError:
    return DatasetError(
        f"{path} is a live camera stream: this command needs a recorded sequence (a known number of frames, "
        "random access, timestamps). Stream it with `python -m services.io play --data "
        f"{path} --camera fx,fy,cx,cy` (the live system), or record a video / image folder and map that"
    )


class LiveCamera:
    """Frames read from a capture device as they come (see the module docstring)."""

    live = True
    kind = "camera"
    depth_scale = None
    has_depth = False

    def __init__(self, source: Union[int, str], camera: CameraArg, max_frames: Optional[int] = None,
                 name: Optional[str] = None):
        self.name = name or f"{LIVE_PREFIX}{source}"
        self.max_frames = check_max_frames(max_frames)
        if camera is None:
            raise DatasetError(no_intrinsics_message(f"{self.name} (a live camera)"))
        self._cap = open_capture(source, self.name)
        ok, first = self._cap.read()
        if not ok or first is None:
            self.close()
            raise DatasetError(f"{self.name}: the device opened but delivered no frame")
        self._pending = (first, time.time())  # the frame read to learn the size is the first one served
        size = (int(first.shape[1]), int(first.shape[0]))
        try:
            self.raw_camera, self.camera_source = resolve_camera(camera, None, size, self.name)
        except DatasetError:
            self.close()
            raise
        self.camera: PinholeCamera = self.raw_camera.undistorted()
        self.count = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        raise TypeError(f"{self.name} is a live stream: it has no length (read frames until IndexError)")

    def __getitem__(self, i: int) -> Frame:
        with self._lock:
            if self._cap is None or (self.max_frames is not None and self.count >= self.max_frames):
                raise IndexError(f"{self.name}: end of stream after {self.count} frames")
            if self._pending is not None:
                (img, t), self._pending = self._pending, None
            else:
                ok, img = self._cap.read()
                t = time.time()
                if not ok or img is None:
                    self.close()
                    raise IndexError(f"{self.name}: the device stopped delivering frames after {self.count}")
            self.count += 1
        return frame_from_bgr(img, int(i), t, self.raw_camera, self.camera, self.name)

    def __iter__(self) -> Iterator[Frame]:
        i = 0
        while True:
            try:
                yield self[i]
            except IndexError:
                return
            i += 1

    def close(self) -> None:
        if getattr(self, "_cap", None) is not None:
            self._cap.release()
            self._cap = None

    def describe(self) -> dict:
        d = {
            "root": self.name, "kind": self.kind, "live": True, "frames": None,
            "camera": self.camera.to_dict(), "depth_scale": None, "gt_poses": 0,
            "camera_source": self.camera_source, "undistorted": self.raw_camera.dist is not None,
        }
        if self.raw_camera.dist is not None:
            d["distortion"] = list(self.raw_camera.dist)
        return d


def open_live(path: str, camera: CameraArg = None, max_frames: Optional[int] = None) -> LiveCamera:
    idx = live_index(path)
    if idx is None:
        raise DatasetError(f"{path!r}: a live camera is written camera:N with N the device index (camera:0)")
    return LiveCamera(idx, camera, max_frames, name=path)


__all__ = ["LiveCamera", "open_live", "live_index", "is_live_spec", "refuse_live", "LIVE_PREFIX"]
