"""ROS bags: rosbag2 folders, ``.mcap`` / ``.db3`` files, ROS1 ``.bag`` files.

Read with the optional ``rosbags`` package (``pip install 'fmapping[ros]'``), imported only
when a bag is opened.

* Images: one ``sensor_msgs/msg/Image`` or ``CompressedImage`` topic. ``topic=`` names
  it; otherwise the image topic with the most messages among those without ``depth``
  in their name (the others are listed in ``meta["image_topics"]``). Encodings: rgb8,
  bgr8, rgba8, bgra8, mono8, mono16, 16-bit colour, bayer_*8, yuv422 (uyvy / yuyv), and
  any JPEG / PNG compressed image. Colour only: a depth topic is not read.
* Timestamps: the messages' ``header.stamp`` (capture time) when every image has one,
  else the bag's receive time (``meta["timestamps"]`` says which).
* Intrinsics: the first ``sensor_msgs/msg/CameraInfo`` in the image topic's namespace
  (``/cam/image_raw`` -> ``/cam/camera_info``), or the only CameraInfo topic of the bag;
  ``plumb_bob`` / ``rational_polynomial`` distortion is removed from the frames. A bag
  without CameraInfo (or with an all-zero K) needs ``--camera``.
* Access: ``bag[i]`` reads the one message at that frame's receive time (the storage
  indexes by time), so sequential and random access cost the same.
"""
from __future__ import annotations

import threading
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import WHITE, Background, CameraArg, check_max_frames, log, resolve_camera
from fmapping.datasets.base import Dataset, DatasetError, Frame
from fmapping.datasets.calib import camera_from_ros
from fmapping.datasets.video import frame_from_bgr

BAG_EXTS = (".mcap", ".db3", ".bag")
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
MISSING = "reading ROS bags needs the optional 'rosbags' package: pip install 'fmapping[ros]' (or pip install rosbags)"

# ROS encoding -> (numpy dtype, channels, cv2 conversion to BGR or None)
_ENCODINGS = {
    "bgr8": ("u1", 3, None), "rgb8": ("u1", 3, "rgb"), "bgra8": ("u1", 4, None), "rgba8": ("u1", 4, "rgba"),
    "mono8": ("u1", 1, None), "8uc1": ("u1", 1, None), "mono16": ("u2", 1, None), "16uc1": ("u2", 1, None),
    "bgr16": ("u2", 3, None), "rgb16": ("u2", 3, "rgb"), "bgra16": ("u2", 4, None), "rgba16": ("u2", 4, "rgba"),
    "8uc3": ("u1", 3, None), "8uc4": ("u1", 4, None),
    # the Bayer names of ROS and OpenCV are offset by one pixel: ROS rggb is OpenCV's BG
    "bayer_rggb8": ("u1", 1, "BayerBG"), "bayer_bggr8": ("u1", 1, "BayerRG"),
    "bayer_gbrg8": ("u1", 1, "BayerGR"), "bayer_grbg8": ("u1", 1, "BayerGB"),
    "yuv422": ("u1", 2, "UYVY"), "uyvy": ("u1", 2, "UYVY"), "yuv422_yuy2": ("u1", 2, "YUYV"), "yuyv": ("u1", 2, "YUYV"),
}


def is_rosbag(path: Path) -> bool:
    if path.is_file():
        return path.suffix.lower() in BAG_EXTS
    return (path / "metadata.yaml").is_file() and any(p.suffix in (".mcap", ".db3") for p in path.iterdir())


def _rosbags():
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise DatasetError(MISSING) from None
    return AnyReader, Stores, get_typestore


def _bag_paths(path: Path) -> list[Path]:
    # a storage file of a rosbag2 folder is read through its folder (split bags have several files)
    if path.is_file() and path.suffix.lower() != ".bag" and (path.parent / "metadata.yaml").is_file():
        return [path.parent]
    return [path]


def _open_reader(paths: list[Path]):
    AnyReader, Stores, get_typestore = _rosbags()
    # bags that embed no message definitions (older rosbag2 sqlite3) need a default type store
    reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as e:  # AnyReaderError and the storage errors under it
        raise DatasetError(f"cannot read ROS bag {paths[0]}: {e}") from None
    return reader


def image_to_cv(msg, msgtype: str, where: str) -> np.ndarray:
    """An Image / CompressedImage message -> an OpenCV image (BGR / BGRA / grey, 8 or 16 bit)."""
    import cv2

    data = np.asarray(msg.data, np.uint8)
    if msgtype == COMPRESSED:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"{where}: cannot decode the compressed image (format {msg.format!r})")
        return img
    enc = str(msg.encoding).lower()
    if enc not in _ENCODINGS:
        raise DatasetError(f"{where}: image encoding {msg.encoding!r} is not supported "
                           f"(supported: {', '.join(sorted(_ENCODINGS))})")
    kind, ch, conv = _ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(kind).itemsize
    if step < w * ch * itemsize or data.size < h * step:
        raise DatasetError(f"{where}: {data.size} bytes for a {w}x{h} {enc} image with row step {step}")
    rows = data[: h * step].reshape(h, step)[:, : w * ch * itemsize]  # rows may be padded to step
    dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    img = np.ascontiguousarray(rows).view(dtype).astype(kind).reshape(h, w, ch)
    if conv == "rgb":
        return np.ascontiguousarray(img[..., ::-1])
    if conv == "rgba":
        return np.ascontiguousarray(img[..., [2, 1, 0, 3]])
    if conv is not None:
        return cv2.cvtColor(img, getattr(cv2, f"COLOR_{conv}2BGR"))
    return img[..., 0] if ch == 1 else img


def _stamp_ns(msg) -> int:
    st = getattr(getattr(msg, "header", None), "stamp", None)
    if st is None:
        return 0
    sec = getattr(st, "sec", getattr(st, "secs", 0))
    nsec = getattr(st, "nanosec", getattr(st, "nsecs", 0))
    return int(sec) * 1_000_000_000 + int(nsec)


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


def _pick_topic(reader, topic: Optional[str], where: str):
    topics = {c.topic: c.msgtype for c in reader.connections}
    images = {t: m for t, m in topics.items() if m in (IMAGE, COMPRESSED)}
    if topic is not None:
        if topic not in topics:
            raise DatasetError(f"{where}: no topic {topic!r}; image topics: {sorted(images) or 'none'}")
        if topic not in images:
            raise DatasetError(f"{where}: {topic} carries {topics[topic]}, not an Image / CompressedImage")
        return topic, sorted(images)
    if not images:
        raise DatasetError(f"{where}: no sensor_msgs/msg/Image or CompressedImage topic "
                           f"(topics: {sorted(topics) or 'none'})")
    counts = {t: sum(c.msgcount for c in reader.connections if c.topic == t) for t in images}
    colour = [t for t in images if "depth" not in t.lower()] or list(images)
    best = max(sorted(colour), key=lambda t: counts[t])
    if len(images) > 1:
        log.warning("%s: image topics %s; reading %s (pass topic= to choose)", where, sorted(images), best)
    return best, sorted(images)


def _camera_info(reader, image_topic: str, where: str):
    """The first CameraInfo message for ``image_topic`` and its topic, or (None, None)."""
    infos = sorted({c.topic for c in reader.connections if c.msgtype == CAMERA_INFO})
    same = [t for t in infos if _namespace(t) == _namespace(image_topic)]
    chosen = same[0] if same else (infos[0] if len(infos) == 1 else None)
    if chosen is None:
        if infos:
            log.warning("%s: CameraInfo topics %s, none in %s's namespace", where, infos, image_topic)
        return None, None
    conns = [c for c in reader.connections if c.topic == chosen]
    with closing(reader.messages(connections=conns)) as messages:
        for conn, _, raw in messages:
            return reader.deserialize(raw, conn.msgtype), chosen
    return None, None


@dataclass(eq=False)
class RosbagFrames(Dataset):
    bag_paths: list = field(default_factory=list)
    topic: str = ""
    log_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # receive time of each frame
    occurrence: list = field(default_factory=list)  # k-th message of the topic at that receive time
    raw_camera: Optional[PinholeCamera] = None
    _reader: object = field(default=None, init=False, repr=False)
    _lock: object = field(default_factory=threading.Lock, init=False, repr=False)

    def _message(self, i: int):
        t, k = int(self.log_ns[i]), int(self.occurrence[i])
        with self._lock:  # one open reader, shared by the threads that read frames
            if self._reader is None:
                self._reader = _open_reader(self.bag_paths)
            conns = [c for c in self._reader.connections if c.topic == self.topic]
            with closing(self._reader.messages(connections=conns, start=t, stop=t + 1)) as messages:
                for j, (conn, _, raw) in enumerate(messages):
                    if j == k:
                        return self._reader.deserialize(raw, conn.msgtype), conn.msgtype
        raise DatasetError(f"{self.root}: message {i} of {self.topic} is no longer in the bag")

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an int, got {type(i).__name__}")
        i = int(i) + n if i < 0 else int(i)
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        msg, msgtype = self._message(i)
        where = f"{self.root} {self.topic} #{i}"
        return frame_from_bgr(image_to_cv(msg, msgtype, where), i, float(self.timestamps[i]),
                              self.raw_camera, self.camera, where)

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def __getstate__(self) -> dict:  # the open reader and the lock stay with this process
        state = dict(self.__dict__)
        state.update(_reader=None, _lock=None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()


def load_rosbag(path, camera: CameraArg = None, max_frames: Optional[int] = None,
                background: Background = WHITE, topic: Optional[str] = None) -> RosbagFrames:
    path = Path(path)
    max_frames = check_max_frames(max_frames)
    paths = _bag_paths(path)
    where = str(paths[0])
    reader = _open_reader(paths)
    try:
        image_topic, all_images = _pick_topic(reader, topic, where)
        conns = [c for c in reader.connections if c.topic == image_topic]
        log_ns, stamps, occurrence = [], [], []
        first = None
        with closing(reader.messages(connections=conns)) as messages:
            for conn, t, raw in messages:
                msg = reader.deserialize(raw, conn.msgtype)
                if first is None:
                    first = image_to_cv(msg, conn.msgtype, f"{where} {image_topic} #0")
                occurrence.append(occurrence[-1] + 1 if log_ns and log_ns[-1] == t else 0)
                log_ns.append(t)
                stamps.append(_stamp_ns(msg))
                if max_frames is not None and len(log_ns) >= max_frames:
                    break
        if first is None:
            raise DatasetError(f"{where}: topic {image_topic} has no messages")
        size = (int(first.shape[1]), int(first.shape[0]))
        info, info_topic = _camera_info(reader, image_topic, where)
    finally:
        reader.close()

    default, source = None, f"{where} (a ROS bag without a CameraInfo for {image_topic})"
    if info is not None and camera is None:
        k = getattr(info, "k", None)
        d = getattr(info, "d", None)
        default = camera_from_ros(k if k is not None else info.K, d if d is not None else info.D,
                                  str(info.distortion_model), int(info.width), int(info.height), size,
                                  f"{where} {info_topic}")
        source = f"{where} {info_topic}"
    cam, source = resolve_camera(camera, default, size, source)

    use_stamps = all(s > 0 for s in stamps)
    ts = (np.asarray(stamps if use_stamps else log_ns, np.int64) / 1e9).astype(np.float64)
    n = len(log_ns)
    meta = {
        "camera_source": source,
        "topic": image_topic,
        "image_topics": all_images,
        "timestamps": "header.stamp" if use_stamps else "bag receive time",
        "undistorted": cam.dist is not None,
    }
    if cam.dist is not None:
        meta["distortion"] = list(cam.dist)
    return RosbagFrames(
        root=path, camera=cam.undistorted(), timestamps=ts, gt_poses=[None] * n, kind="rosbag", depth_scale=None,
        meta=meta, bag_paths=paths, topic=image_topic, log_ns=np.asarray(log_ns, np.int64), occurrence=occurrence,
        raw_camera=cam,
    )
