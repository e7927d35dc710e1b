"""ROS 2 bridge core (zenoh-free): our messages <-> ROS 2 CDR on zenoh keys.

Out: each tracker ``Pose`` becomes a ``geometry_msgs/msg/PoseStamped`` and the ``nav_msgs/msg/Path``
of every pose so far (newest pose per frame, in frame order); each ``PointsSnapshot`` becomes a
``sensor_msgs/msg/PointCloud2``. In: ``sensor_msgs/msg/Image`` + ``sensor_msgs/msg/CameraInfo``
become our ``Frame`` messages. :class:`BridgeCore` turns payloads into ``Output`` tuples
(key, bytes, attachment or None); ``python -m services.ros2`` (``__main__.py``) is the zenoh
shell. Conversions and conventions: :mod:`services.ros2.convert`.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional

from fmapping import protocol as P
from services.core_support import Counters
from services.ros2 import convert as C

MAX_PATH_POSES = 100_000  # a Path message of 100k poses is ~6 MB: beyond that only the newest are sent


class Output(NamedTuple):
    key: str
    payload: bytes
    attachment: Optional[bytes] = None
    droppable: bool = False  # big and superseded by the next one (clouds, frames): drop under congestion


@dataclass
class Topics:
    """ROS topic names of what the bridge publishes and reads (defaults are ``/fmapping/...`` and
    the camera drivers' usual ``/camera/image_raw`` + ``/camera/camera_info``)."""

    pose: str = "/fmapping/pose"
    path: str = "/fmapping/path"
    points: str = "/fmapping/points"
    image: str = "/camera/image_raw"
    camera_info: str = "/camera/camera_info"


class _RmwPublisherState:
    """Sequence numbers and a gid per published topic: what rmw_zenoh's attachment carries."""

    def __init__(self) -> None:
        self.seq: dict[str, int] = {}
        self.gid: dict[str, bytes] = {}

    def attachment(self, key: str, now_ns: int) -> bytes:
        self.seq[key] = self.seq.get(key, 0) + 1
        gid = self.gid.setdefault(key, os.urandom(16))
        return C.rmw_attachment(self.seq[key], now_ns, gid)


class BridgeCore:
    """Decode, convert, count; never raises on bad input (counted as ``bad_input`` plus a
    specific counter, kept in ``last_error``, passed to ``on_bad_input``)."""

    def __init__(self, keys: P.Keys, topics: Optional[Topics] = None, ros: Optional[C.TopicKeys] = None,
                 world_frame: str = C.WORLD_FRAME, pose_source: str = "tracker", camera_override=None,
                 counters: Optional[Counters] = None, on_bad_input: Optional[Callable[[str], None]] = None,
                 clock: Callable[[], int] = time.time_ns, path_interval: float = 0.2):
        self.keys = keys
        self.topics = topics or Topics()
        self.ros = ros or C.TopicKeys()
        self.distro = self.ros.distro
        self.world_frame = world_frame
        self.pose_source = pose_source
        self.camera_override = camera_override
        self.counters = counters if counters is not None else Counters()
        self.on_bad_input = on_bad_input
        self.clock = clock
        # the Path grows with the run: re-sent at most every ``path_interval`` s (and by flush())
        self.path_interval = float(path_interval)
        self._path_sent_ns: Optional[int] = None
        self._path_dirty = False
        self.last_error = ""
        self.path: dict[int, P.Pose] = {}  # newest pose per frame number
        self.info = None  # latest CameraInfo
        self.next_seq = 0
        self._rmw = _RmwPublisherState()

    # ------------------------------------------------------------------ keys
    def out_key(self, what: str) -> str:
        topic, typename = {"pose": (self.topics.pose, C.POSE_STAMPED), "path": (self.topics.path, C.PATH),
                           "points": (self.topics.points, C.POINT_CLOUD2)}[what]
        return self.ros.publish_key(topic, typename)

    def in_key(self, what: str) -> str:
        topic, typename = {"image": (self.topics.image, C.IMAGE),
                           "camera_info": (self.topics.camera_info, C.CAMERA_INFO)}[what]
        return self.ros.subscribe_key(topic, typename)

    def _out(self, what: str, msg, typename: str) -> Output:
        key = self.out_key(what)
        att = self._rmw.attachment(key, self.clock()) if self.ros.style == "rmw" else None
        self.counters.inc(f"sent_{what}")
        return Output(key, C.to_cdr(msg, typename, self.distro), att, droppable=what == "points")

    def bad_input(self, why: str, counter: str) -> None:
        self.counters.inc(counter)
        self.counters.inc("bad_input")
        self.last_error = why
        if self.on_bad_input is not None:
            self.on_bad_input(why)

    # ------------------------------------------------------------------ ours -> ROS
    def on_pose(self, data: bytes, key: str = "") -> list[Output]:
        """A ``Pose`` payload -> PoseStamped + the grown Path (poses of other sources: nothing)."""
        try:
            pose = P.decode(data, P.Pose)
        except P.ProtocolError as e:
            self.bad_input(f"{key or 'poses'}: {e}", "decode_errors")
            return []
        if self.pose_source and pose.source != self.pose_source:
            return []
        self.path[pose.seq] = pose  # a later pose of the same frame (a refinement) replaces it
        self._path_dirty = True
        out = [self._out("pose", C.pose_stamped(pose, self.world_frame, self.distro), C.POSE_STAMPED)]
        now = self.clock()
        if self._path_sent_ns is None or (now - self._path_sent_ns) >= self.path_interval * 1e9:
            out += self.flush()
        return out

    def flush(self) -> list[Output]:
        """The Path when poses came since it was last sent (the shell calls this when idle)."""
        if not self._path_dirty:
            return []
        self._path_dirty = False
        self._path_sent_ns = self.clock()
        ordered = [self.path[s] for s in sorted(self.path)][-MAX_PATH_POSES:]
        return [self._out("path", C.path_msg(ordered, self.world_frame, self.distro), C.PATH)]

    def on_points(self, data: bytes, key: str = "") -> list[Output]:
        """A ``PointsSnapshot`` payload -> PointCloud2, stamped with the newest pose's time at or
        before the snapshot's frame (the snapshot has no time of its own)."""
        try:
            s = P.decode(data, P.PointsSnapshot)
        except P.ProtocolError as e:
            self.bad_input(f"{key or 'points'}: {e}", "decode_errors")
            return []
        stamp = max((p.timestamp for q, p in self.path.items() if q <= s.frame_seq), default=0.0)
        return [self._out("points", C.cloud_from_snapshot(s, stamp, self.world_frame, self.distro), C.POINT_CLOUD2)]

    # ------------------------------------------------------------------ ROS -> ours
    def on_camera_info(self, data: bytes, key: str = "") -> list[Output]:
        try:
            self.info = C.from_cdr(data, C.CAMERA_INFO, self.distro)
            self.counters.inc("camera_infos")
        except C.RosConversionError as e:
            self.bad_input(f"{key or 'camera_info'}: {e}", "decode_errors")
        return []

    def on_image(self, data: bytes, key: str = "") -> list[Output]:
        """An Image -> our Frame (the next frame number) once the stream's CameraInfo (or
        ``--camera``) is known; before that the image is counted as ``frames_without_info``."""
        if self.info is None and self.camera_override is None:
            self.counters.inc("frames_without_info")
            return []
        try:
            img = C.from_cdr(data, C.IMAGE, self.distro)
            frame = C.frame_from_ros(img, self.info, self.next_seq, self.camera_override)
        except C.RosConversionError as e:
            self.bad_input(f"{key or 'image'}: {e}", "rejected_images")
            return []
        self.next_seq += 1
        self.counters.inc("frames_sent")
        return [Output(self.keys.frames, P.encode(frame), droppable=True)]

    def handle(self, channel: str, data: bytes, key: str = "") -> list[Output]:
        fn = {"poses": self.on_pose, "points": self.on_points, "image": self.on_image,
              "camera_info": self.on_camera_info}.get(channel)
        if fn is None:
            raise ValueError(f"BridgeCore.handle: unknown channel {channel!r}")
        return fn(data, key)
