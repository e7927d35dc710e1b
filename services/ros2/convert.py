"""Our messages <-> ROS 2 messages in CDR, the bytes zenoh-bridge-ros2dds and rmw_zenoh carry.

Zenoh-free and ROS-free: the message classes and the CDR (de)serialisers are those of the
``rosbags`` type store (``pip install 'fmapping[ros]'``), no ROS installation is needed.

Conventions:

* Our camera frame is OpenCV's (x right, y down, z forward), which is what ROS calls an
  ``*_optical_frame`` (REP 103). A ``Pose`` (camera-to-world ``c2w``) becomes a
  ``geometry_msgs/msg/PoseStamped`` whose pose is the optical frame's in the world frame:
  ``position = c2w[:3, 3]``, ``orientation = quaternion(c2w[:3, :3])``, ``header.frame_id`` the
  world frame (default ``map``). No axis swap happens: the ``map`` frame is the SLAM world frame
  as the tracker defines it (anchored on the first ground-truth pose, else the first camera),
  not necessarily z-up; publish a static transform to a gravity-aligned frame when you need one.
* Stamps: ``header.stamp`` is the frame's timestamp (seconds as given by the dataset or the
  camera), split into ``sec`` / ``nanosec``.
* Point clouds: ``sensor_msgs/msg/PointCloud2`` with fields x, y, z (float32) and rgb (a float32
  whose bits are the packed ``0x00RRGGBB``, the PCL / RViz convention), 16 bytes per point,
  little endian, one row.
* Images in: ``sensor_msgs/msg/Image`` with an 8-bit encoding (rgb8, bgr8, mono8 and the other
  8-bit ones :func:`fmapping.datasets.rosbag.image_to_cv` reads) plus the ``CameraInfo`` of the
  stream; ``plumb_bob`` / ``rational_polynomial`` distortion is removed (our frames are
  undistorted, their camera carries no distortion).
"""
from __future__ import annotations

import functools
import math
import struct
from typing import Optional, Sequence

import numpy as np

from fmapping import protocol as P

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
PATH = "nav_msgs/msg/Path"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

WORLD_FRAME = "map"
CAMERA_FRAME = "camera_optical_frame"
DISTROS = ("humble", "iron", "jazzy", "kilted")
MISSING = "the ROS 2 bridge needs the optional 'rosbags' package: pip install 'fmapping[ros]' (or pip install rosbags)"
_FLOAT32 = 7  # sensor_msgs/msg/PointField.FLOAT32


class RosConversionError(ValueError):
    """A ROS message that cannot become one of ours (the text says why)."""


@functools.lru_cache(maxsize=None)
def typestore(distro: str = "jazzy"):
    """The rosbags type store of ROS 2 ``distro`` (message classes, CDR serialisers, type hashes)."""
    if distro not in DISTROS:
        raise ValueError(f"ROS 2 distro must be one of {', '.join(DISTROS)}, got {distro!r}")
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ImportError(MISSING) from None
    return get_typestore(getattr(Stores, f"ROS2_{distro.upper()}"))


def to_cdr(msg, typename: str, distro: str = "jazzy") -> bytes:
    """CDR bytes (with the 4-byte encapsulation header DDS and rmw_zenoh put first)."""
    return bytes(typestore(distro).serialize_cdr(msg, typename))


def from_cdr(data: bytes, typename: str, distro: str = "jazzy"):
    """The ``typename`` message in CDR ``data``; RosConversionError when it does not parse."""
    try:
        return typestore(distro).deserialize_cdr(bytes(data), typename)
    except Exception as e:  # rosbags raises several error types (struct, index, its own)
        raise RosConversionError(f"not a valid CDR {typename}: {type(e).__name__}: {e}") from None


# ---------------------------------------------------------------------------- small pieces
def ros_time(t: float, distro: str = "jazzy"):
    """``builtin_interfaces/msg/Time`` of ``t`` seconds (nanoseconds rounded, never 1e9)."""
    ns = int(round(float(t) * 1e9)) if math.isfinite(t) else 0
    sec, nanosec = divmod(ns, 1_000_000_000)
    return typestore(distro).types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nanosec))


def seconds(stamp) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def header(t: float, frame_id: str, distro: str = "jazzy"):
    return typestore(distro).types["std_msgs/msg/Header"](stamp=ros_time(t, distro), frame_id=str(frame_id))


def quaternion_xyzw(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), the ROS order, of a rotation matrix; w >= 0."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(rot, np.float64)).as_quat()
    return -q if q[3] < 0 else q


def rotation_of(q_xyzw: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a quaternion (x, y, z, w); RosConversionError for a zero or non-finite one."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q_xyzw, np.float64)
    n = float(np.linalg.norm(q))
    if not np.isfinite(q).all() or n < 1e-9:
        raise RosConversionError(f"orientation {q.tolist()} is not a rotation quaternion")
    return Rotation.from_quat(q / n).as_matrix()


# ---------------------------------------------------------------------------- poses
def pose_msg(c2w: np.ndarray, distro: str = "jazzy"):
    """``geometry_msgs/msg/Pose`` of a 4x4 camera-to-world matrix."""
    t = typestore(distro).types
    q = quaternion_xyzw(c2w[:3, :3])
    p = np.asarray(c2w, np.float64)[:3, 3]
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=t["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def pose_stamped(pose: P.Pose, frame_id: str = WORLD_FRAME, distro: str = "jazzy"):
    """``geometry_msgs/msg/PoseStamped`` of our Pose: the camera optical frame in ``frame_id``."""
    return typestore(distro).types[POSE_STAMPED](header=header(pose.timestamp, frame_id, distro),
                                                  pose=pose_msg(pose.c2w, distro))


def c2w_of(pose_msg_) -> np.ndarray:
    """4x4 camera-to-world matrix of a ``geometry_msgs/msg/Pose``."""
    o, p = pose_msg_.orientation, pose_msg_.position
    m = np.eye(4)
    m[:3, :3] = rotation_of([o.x, o.y, o.z, o.w])
    m[:3, 3] = [p.x, p.y, p.z]
    if not np.isfinite(m).all():
        raise RosConversionError(f"position {m[:3, 3].tolist()} is not finite")
    return m


def pose_from_stamped(msg, seq: int = -1, source: str = "external") -> P.Pose:
    """Our Pose of a PoseStamped (``seq`` is ours to give: ROS messages carry none)."""
    return P.Pose(seq=int(seq), timestamp=seconds(msg.header.stamp), c2w=c2w_of(msg.pose), source=source)


def path_msg(poses: Sequence[P.Pose], frame_id: str = WORLD_FRAME, distro: str = "jazzy"):
    """``nav_msgs/msg/Path`` through ``poses`` in order, stamped with the newest one's time."""
    stamped = [pose_stamped(p, frame_id, distro) for p in poses]
    t = max((p.timestamp for p in poses), default=0.0)
    return typestore(distro).types[PATH](header=header(t, frame_id, distro), poses=stamped)


# ---------------------------------------------------------------------------- point clouds
def _point_field(name: str, offset: int, distro: str):
    return typestore(distro).types["sensor_msgs/msg/PointField"](name=name, offset=offset, datatype=_FLOAT32, count=1)


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 -> (N,) float32 whose bits are 0x00RRGGBB (what RViz's RGB8 reads)."""
    c = np.asarray(colors, np.uint32)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).astype("<u4").view("<f4")


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """(N,) float32 packed 0x00RRGGBB (or uint32) -> (N, 3) uint8."""
    u = np.ascontiguousarray(packed).view("<u4")
    return np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], axis=1).astype(np.uint8)


def point_cloud(points: np.ndarray, colors: np.ndarray, stamp: float, frame_id: str = WORLD_FRAME,
                distro: str = "jazzy"):
    """``sensor_msgs/msg/PointCloud2`` (x, y, z float32 + rgb packed; 16 bytes a point, one row)."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    rec = np.empty(len(pts), dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")]))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["rgb"] = pack_rgb(colors) if len(pts) else np.zeros(0, "<f4")
    fields = [_point_field(n, 4 * i, distro) for i, n in enumerate(("x", "y", "z", "rgb"))]
    return typestore(distro).types[POINT_CLOUD2](
        header=header(stamp, frame_id, distro), height=1, width=len(pts), fields=fields, is_bigendian=False,
        point_step=16, row_step=16 * len(pts), data=rec.view(np.uint8).reshape(-1), is_dense=True)


def cloud_from_snapshot(s: P.PointsSnapshot, stamp: float, frame_id: str = WORLD_FRAME, distro: str = "jazzy"):
    return point_cloud(s.points, s.colors, stamp, frame_id, distro)


def points_of_cloud(msg) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 points and (N, 3) uint8 colours (grey 255 without an rgb/rgba field) of a
    PointCloud2 with float32 x, y, z; NaN points (organised clouds' holes) are dropped."""
    fields = {f.name: f for f in msg.fields}
    if not all(k in fields and fields[k].datatype == _FLOAT32 for k in "xyz"):
        raise RosConversionError(f"PointCloud2 needs float32 x, y, z fields, got {sorted(fields)}")
    n, step = int(msg.width) * int(msg.height), int(msg.point_step)
    rows = np.asarray(msg.data, np.uint8)
    if msg.height > 1 and msg.row_step != msg.width * step:  # rows padded: drop the padding
        rows = rows.reshape(msg.height, msg.row_step)[:, : msg.width * step]
    raw = np.ascontiguousarray(rows).reshape(-1)[: n * step]
    if raw.size != n * step:
        raise RosConversionError(f"PointCloud2 has {raw.size} data bytes for {n} points of {step} bytes")
    order = ">" if msg.is_bigendian else "<"
    rec = raw.reshape(n, step)

    def column(name: str, kind: str) -> np.ndarray:
        off = int(fields[name].offset)
        return np.ascontiguousarray(rec[:, off:off + 4]).view(order + kind).reshape(n)

    pts = np.stack([column(k, "f4") for k in "xyz"], axis=1).astype(np.float32)
    color_name = next((k for k in ("rgb", "rgba") if k in fields), None)
    cols = unpack_rgb(column(color_name, "u4").astype("<u4")) if color_name else np.full((n, 3), 255, np.uint8)
    ok = np.isfinite(pts).all(axis=1)
    return pts[ok], cols[ok]


# ---------------------------------------------------------------------------- images in
def camera_of_info(info, size: tuple[int, int], override=None):
    """The :class:`fmapping.camera.PinholeCamera` of a CameraInfo for ``size`` (w, h) images,
    or ``override`` (a PinholeCamera, or a function of the size giving one, e.g. ``--camera``)."""
    from fmapping.datasets.base import DatasetError
    from fmapping.datasets.calib import camera_from_ros

    if callable(override):
        try:
            override = override(size)
        except ValueError as e:
            raise RosConversionError(f"--camera: {e}") from None
    if override is not None:
        if tuple(override.size) != tuple(size):
            raise RosConversionError(f"--camera is for {override.width}x{override.height} images, "
                                     f"got {size[0]}x{size[1]}")
        return override
    if info is None:
        raise RosConversionError("no CameraInfo yet (and no --camera)")
    try:
        return camera_from_ros(list(info.k), list(info.d), str(info.distortion_model), int(info.width),
                               int(info.height), size, "CameraInfo")
    except DatasetError as e:
        raise RosConversionError(str(e)) from None


def rgb_of_image(msg) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an 8-bit ``sensor_msgs/msg/Image`` (grey is repeated on 3 channels)."""
    import cv2

    from fmapping.datasets.base import DatasetError
    from fmapping.datasets.rosbag import image_to_cv

    try:
        img = image_to_cv(msg, IMAGE, "Image")
    except DatasetError as e:
        raise RosConversionError(str(e)) from None
    if img.dtype != np.uint8:
        raise RosConversionError(f"Image encoding {msg.encoding!r} is not 8-bit (rgb8, bgr8, mono8, ...)")
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[..., None], 3, axis=2))
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)


def frame_from_ros(image, info, seq: int, camera_override=None) -> P.Frame:
    """Our Frame of an Image and its stream's CameraInfo (distortion removed), number ``seq``."""
    rgb = rgb_of_image(image)
    cam = camera_of_info(info, (rgb.shape[1], rgb.shape[0]), camera_override)
    if cam.dist is not None:
        rgb = cam.undistort_image(rgb)
        cam = cam.undistorted()
    frame = P.Frame(seq=int(seq), timestamp=seconds(image.header.stamp), rgb=np.ascontiguousarray(rgb),
                    camera=cam.to_dict())
    try:
        return P.validate(frame)
    except P.ProtocolError as e:
        raise RosConversionError(str(e)) from None


def image_msg(rgb: np.ndarray, stamp: float, frame_id: str = CAMERA_FRAME, encoding: str = "rgb8",
              distro: str = "jazzy"):
    """``sensor_msgs/msg/Image`` of an (H, W, 3) RGB image (rgb8 or bgr8) or (H, W) grey (mono8)."""
    img = np.asarray(rgb, np.uint8)
    if encoding == "bgr8":
        img = img[..., ::-1]
    img = np.ascontiguousarray(img)
    h, w = img.shape[:2]
    ch = 1 if img.ndim == 2 else img.shape[2]
    return typestore(distro).types[IMAGE](header=header(stamp, frame_id, distro), height=h, width=w,
                                          encoding=encoding, is_bigendian=0, step=w * ch, data=img.reshape(-1))


def camera_info_msg(camera: dict, stamp: float, frame_id: str = CAMERA_FRAME, distro: str = "jazzy"):
    """``sensor_msgs/msg/CameraInfo`` of one of our camera dicts (fx, fy, cx, cy, size, optional dist)."""
    t = typestore(distro).types
    fx, fy, cx, cy = (float(camera[k]) for k in ("fx", "fy", "cx", "cy"))
    dist = [float(v) for v in (camera.get("dist") or [0.0] * 5)]
    k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], np.float64)
    p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], np.float64)
    return t[CAMERA_INFO](
        header=header(stamp, frame_id, distro), height=int(camera["height"]), width=int(camera["width"]),
        distortion_model="rational_polynomial" if len(dist) == 8 else "plumb_bob", d=np.array(dist, np.float64),
        k=k, r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


# ---------------------------------------------------------------------------- key expressions
def dds_type_name(typename: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs::msg::dds_::PoseStamped_`` (rmw_zenoh's type segment)."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def _strip(name: str) -> str:
    return str(name).strip("/")


class TopicKeys:
    """ROS topic name <-> zenoh key expression, for one of the two ways ROS 2 meets zenoh.

    * ``bridge`` (zenoh-bridge-ros2dds, the default): the key is the topic without its leading
      slash, under the bridge's ROS namespace when it has one: ``/fmapping/pose`` is key
      ``fmapping/pose``; a bridge started with ``namespace: /robot1`` maps it to
      ``robot1/fmapping/pose``, so pass ``prefix="robot1"``.
    * ``rmw`` (rmw_zenoh, ROS nodes speaking zenoh natively): ``<domain>/<topic without the outer
      slashes>/<DDS type name>/<RIHS01 type hash>``; a subscription matches any hash (``*``), so a
      ROS distro with a different type hash is still received. rmw_zenoh's subscribers also
      read an attachment (:func:`rmw_attachment`).
    """

    STYLES = ("bridge", "rmw")

    def __init__(self, style: str = "bridge", prefix: str = "", domain: int = 0, distro: str = "jazzy"):
        if style not in self.STYLES:
            raise ValueError(f"key style must be one of {', '.join(self.STYLES)}, got {style!r}")
        if style == "rmw" and distro in ("humble", "iron"):
            # rmw_zenoh before Jazzy has no type hashes and another attachment layout
            raise ValueError(f"rmw_zenoh keys are supported from ROS 2 Jazzy on, got {distro!r} "
                             "(use the bridge key style with zenoh-bridge-ros2dds)")
        self.style, self.prefix, self.domain, self.distro = style, _strip(prefix), int(domain), distro

    def publish_key(self, topic: str, typename: str) -> str:
        if self.style == "bridge":
            return "/".join(p for p in (self.prefix, _strip(topic)) if p)
        return f"{self.domain}/{_strip(topic)}/{dds_type_name(typename)}/{typestore(self.distro).hash_rihs01(typename)}"

    def subscribe_key(self, topic: str, typename: str) -> str:
        if self.style == "bridge":
            return self.publish_key(topic, typename)
        return f"{self.domain}/{_strip(topic)}/{dds_type_name(typename)}/*"


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _zstr(s: str) -> bytes:
    b = s.encode()
    return _varint(len(b)) + b


def rmw_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment rmw_zenoh publishers send and its subscribers require, in zenoh-ext's
    serialisation: the keys ``sequence_number`` (int64), ``source_timestamp`` (int64, ns) and
    ``source_gid`` (16 bytes), each key a length-prefixed string, the gid a length-prefixed buffer."""
    if len(gid) != 16:
        raise ValueError(f"gid must be 16 bytes, got {len(gid)}")
    return (_zstr("sequence_number") + struct.pack("<q", int(sequence_number))
            + _zstr("source_timestamp") + struct.pack("<q", int(source_timestamp_ns))
            + _zstr("source_gid") + _varint(16) + bytes(gid))


def default_distro(value: Optional[str] = None) -> str:
    """``value``, else $ROS_DISTRO when it is one we know, else jazzy."""
    import os

    d = (value or os.environ.get("ROS_DISTRO") or "jazzy").lower()
    return d if d in DISTROS else "jazzy"
