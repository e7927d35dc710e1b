"""Wire protocol of the multi-process system: typed messages, msgpack encoding, key expressions.

Every message is one msgpack map ``{"schema": <name>, "v": <version>, ...fields}``.
Arrays travel as ``{"dtype": <name>, "shape": [..], "data": <raw little-endian bytes>}``
with a dtype whitelist (uint8, uint16, int32, int64, float32, float64) and per-message
shape / size limits. Nothing here unpickles, evals or imports a transport: this module
is pure msgpack + numpy, so any producer (C++, Rust, another Python process) can speak it.

Decoding validates schema, version, field types, array dtypes and shapes, sizes and
finiteness, and raises :class:`ProtocolError` (naming the message, the field and what
was wrong) for anything else. Arrays of decoded messages are read-only views of the
received buffer (no copy); ``np.array(x)`` them before writing in place.

Conventions (see :mod:`fmapping.geometry`): poses are 4x4 camera-to-world float64
matrices in metres, OpenCV camera axes; depth is float32 metres with 0 = invalid;
``seq`` is the frame sequence number assigned by the player and is how frames,
poses and acknowledgements are matched across services.

Key expressions live under ``fmapping/<ns>/`` (see :class:`Keys`)::

    fmapping/<ns>/frames             Frame
    fmapping/<ns>/poses/<source>     Pose (source: tracker | gt | external | ...)
    fmapping/<ns>/map/field          FieldSnapshot after every mapping window
    fmapping/<ns>/map/points         PointsSnapshot at a bounded rate
    fmapping/<ns>/map/latest         queryable: the latest FieldSnapshot (late joiners)
    fmapping/<ns>/status/<service>   Status
    fmapping/<ns>/control            Control
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Any, Optional, Union

import msgpack
import numpy as np

PROTOCOL_VERSION = 1

ALLOWED_DTYPES = ("uint8", "uint16", "int32", "int64", "float32", "float64")
MAX_IMAGE_SIDE = 4096  # frames up to 4096 x 4096
MAX_POINTS = 2_000_000  # points per PointsSnapshot
MAX_FIELD_BYTES = 128 * 1024 * 1024  # all arrays of one FieldSnapshot together
MAX_FIELD_ARRAYS = 64
MAX_ARRAY_NDIM = 6
MAX_STRING = 4096  # text fields (errors, names, config strings)
MAX_NESTING = 8  # config / args dictionaries
MAX_MESSAGE_BYTES = 160 * 1024 * 1024  # a whole encoded message
POSE_ORTHO_TOL = 1e-3  # |R^T R - I|_max accepted for a rotation block
CONTROL_COMMANDS = ("start", "stop", "reset", "save", "pause", "resume", "refine")

_NAME_RE = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # safe inside a key expression
_PICKLE_PROTOCOLS = (2, 3, 4, 5)


class ProtocolError(ValueError):
    """A message that cannot be decoded or fails validation. The text says which field and why."""


# ---------------------------------------------------------------------------- messages
@dataclass
class Frame:
    """One camera image. ``camera``: fx, fy, cx, cy, width, height (pixels) and optional dist."""

    seq: int
    timestamp: float
    rgb: np.ndarray  # (H, W, 3) uint8
    camera: dict
    depth: Optional[np.ndarray] = None  # (H, W) float32 metres, 0 = invalid


@dataclass
class Pose:
    """Camera-to-world pose of frame ``seq``, produced by ``source``."""

    seq: int
    timestamp: float
    c2w: np.ndarray  # (4, 4) float64
    source: str = "external"
    covariance: Optional[np.ndarray] = None  # (6, 6) float64 over the twist (rho, phi)
    quality: Optional[float] = None  # producer-defined score (e.g. photometric residual)
    # the producer chose this frame as a keyframe (parallax / overlap): a mapper behind the stream keeps
    # every keyframe and thins the other frames first (services.mapper.intake)
    keyframe: bool = False


@dataclass
class FieldSnapshot:
    """The factorized field's tensors, enough for a tracker to render from the map.

    ``kind`` and ``config`` say how to rebuild the field (``fmapping.field``); ``arrays``
    are its parameter tensors by name; ``aabb`` is ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``.
    ``frame_seq`` is the newest frame integrated (-1 before any) and ``frame_c2w`` its pose
    in the map, so that a (re)starting tracker can render a reference view from the map alone.
    """

    version: int
    kind: str
    config: dict
    aabb: np.ndarray  # (2, 3) float
    arrays: dict  # name -> np.ndarray
    frame_seq: int = -1
    timestamp: float = 0.0
    frame_c2w: Optional[np.ndarray] = None  # (4, 4) float64


@dataclass
class PointsSnapshot:
    """Coloured points sampled from the map (bounded size) for viewers and recorders."""

    version: int
    points: np.ndarray  # (N, 3) float32
    colors: np.ndarray  # (N, 3) uint8
    frame_seq: int = -1


@dataclass
class Status:
    """Heartbeat of a service. ``frame_seq`` is the newest frame it has consumed (the
    acknowledgement the player's flow control waits for), -1 before any.
    ``state``: starting | running | paused | finishing | done | error."""

    service: str
    seq: int = 0  # status message counter
    time: float = 0.0  # sender wall clock (seconds since epoch)
    state: str = "running"
    frame_seq: int = -1
    lag: float = 0.0  # seconds behind the newest input it knows about
    counters: dict = field(default_factory=dict)  # name -> int | float
    last_error: str = ""


@dataclass
class Control:
    """A command to all services: start | stop | reset | save | pause | resume | refine (the mapper's
    global refinement over all its keyframes now, as at the end of the stream).

    ``args`` is a small JSON-like dict, e.g. ``{"reason": "end", "last_seq": 199}`` for the
    end-of-sequence stop, or ``{"target": "mapper"}`` to address one service.
    """

    command: str
    args: dict = field(default_factory=dict)


Message = Union[Frame, Pose, FieldSnapshot, PointsSnapshot, Status, Control]
MESSAGE_TYPES = {cls.__name__: cls for cls in (Frame, Pose, FieldSnapshot, PointsSnapshot, Status, Control)}


# ---------------------------------------------------------------------------- key expressions
class Keys:
    """Key expressions of one namespace (``fmapping/<ns>/...``)."""

    def __init__(self, ns: str = "default"):
        if not isinstance(ns, str) or not _NAME_RE.match(ns):
            raise ValueError(f"namespace must match [A-Za-z0-9_-]{{1,64}}, got {ns!r}")
        self.ns = ns
        self.root = f"fmapping/{ns}"

    @property
    def frames(self) -> str:
        return f"{self.root}/frames"

    def poses(self, source: str = "*") -> str:
        if source != "*":
            _check_name(source, "pose source")
        return f"{self.root}/poses/{source}"

    @property
    def field(self) -> str:
        return f"{self.root}/map/field"

    @property
    def points(self) -> str:
        return f"{self.root}/map/points"

    @property
    def latest(self) -> str:
        return f"{self.root}/map/latest"

    def status(self, service: str = "*") -> str:
        if service != "*":
            _check_name(service, "service name")
        return f"{self.root}/status/{service}"

    @property
    def control(self) -> str:
        return f"{self.root}/control"

    @property
    def all(self) -> str:
        return f"{self.root}/**"

    def channel(self, key: str) -> str:
        """The channel of a received key: frames | poses | field | points | latest | status | control,
        or '' when the key is not in this namespace."""
        key = str(key)
        if not key.startswith(self.root + "/"):
            return ""
        rest = key[len(self.root) + 1:]
        head = rest.split("/", 1)[0]
        if head == "map":
            return {"map/field": "field", "map/points": "points", "map/latest": "latest"}.get(rest, "")
        return head if head in ("frames", "poses", "status", "control") else ""

    def last_part(self, key: str) -> str:
        return str(key).rsplit("/", 1)[-1]


# ---------------------------------------------------------------------------- helpers
def _check_name(s: Any, what: str) -> str:
    if not isinstance(s, str) or not _NAME_RE.match(s):
        raise ProtocolError(f"{what} must match [A-Za-z0-9_-]{{1,64}}, got {s!r}")
    return s


def _where(schema: str, name: str) -> str:
    return f"{schema}.{name}"


def _int(v: Any, where: str, lo: int = -(2 ** 63), hi: int = 2 ** 63 - 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
        raise ProtocolError(f"{where}: expected an integer, got {type(v).__name__}")
    v = int(v)
    if not lo <= v <= hi:
        raise ProtocolError(f"{where}: {v} outside [{lo}, {hi}]")
    return v


def _float(v: Any, where: str, finite: bool = True) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ProtocolError(f"{where}: expected a number, got {type(v).__name__}")
    v = float(v)
    if finite and not math.isfinite(v):
        raise ProtocolError(f"{where}: must be finite, got {v}")
    return v


def _str(v: Any, where: str, max_len: int = MAX_STRING) -> str:
    if not isinstance(v, str):
        raise ProtocolError(f"{where}: expected a string, got {type(v).__name__}")
    if len(v) > max_len:
        raise ProtocolError(f"{where}: string of {len(v)} characters exceeds {max_len}")
    return v


def _plain(v: Any, where: str, depth: int = 0) -> Any:
    """Validate a JSON-like value (None, bool, int, float, str, list, dict with str keys)."""
    if depth > MAX_NESTING:
        raise ProtocolError(f"{where}: nested deeper than {MAX_NESTING} levels")
    if v is None or isinstance(v, (bool, str)):
        if isinstance(v, str):
            _str(v, where)
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(float(v)):
            raise ProtocolError(f"{where}: must be finite, got {v}")
        return float(v)
    if isinstance(v, (list, tuple)):
        return [_plain(x, f"{where}[{i}]", depth + 1) for i, x in enumerate(v)]
    if isinstance(v, dict):
        out = {}
        for k, x in v.items():
            if not isinstance(k, str):
                raise ProtocolError(f"{where}: keys must be strings, got {type(k).__name__}")
            out[k] = _plain(x, f"{where}.{k}", depth + 1)
        return out
    raise ProtocolError(f"{where}: unsupported value type {type(v).__name__} (JSON-like values only)")


def _dict(v: Any, where: str) -> dict:
    if not isinstance(v, dict):
        raise ProtocolError(f"{where}: expected a map, got {type(v).__name__}")
    return _plain(v, where)


def _check_array(a: Any, where: str, dtype: Optional[str] = None, ndim: Optional[int] = None,
                 shape: Optional[tuple] = None, finite: bool = False) -> np.ndarray:
    """Validate an ndarray in memory (encode side and after decoding)."""
    if not isinstance(a, np.ndarray):
        raise ProtocolError(f"{where}: expected a numpy array, got {type(a).__name__}")
    if a.dtype.name not in ALLOWED_DTYPES:
        raise ProtocolError(f"{where}: dtype {a.dtype} not allowed (allowed: {', '.join(ALLOWED_DTYPES)})")
    if dtype is not None and a.dtype.name != dtype:
        raise ProtocolError(f"{where}: expected dtype {dtype}, got {a.dtype.name}")
    if ndim is not None and a.ndim != ndim:
        raise ProtocolError(f"{where}: expected {ndim} dimensions, got shape {tuple(a.shape)}")
    if a.ndim > MAX_ARRAY_NDIM:
        raise ProtocolError(f"{where}: {a.ndim} dimensions exceed {MAX_ARRAY_NDIM}")
    if shape is not None:
        for i, (got, want) in enumerate(zip(a.shape, shape)):
            if want is not None and got != want:
                raise ProtocolError(f"{where}: expected shape {_fmt_shape(shape)}, got {tuple(a.shape)}")
    if finite and a.dtype.kind == "f" and a.size and not np.isfinite(a).all():
        raise ProtocolError(f"{where}: contains NaN or Inf")
    return a


def _fmt_shape(shape: tuple) -> str:
    return "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"


def _pack_array(a: np.ndarray) -> dict:
    le = a.dtype.newbyteorder("<")
    buf = np.ascontiguousarray(a, dtype=le)
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": buf.data.cast("B") if buf.size else b""}


def _unpack_array(d: Any, where: str, max_bytes: int) -> np.ndarray:
    if not isinstance(d, dict):
        raise ProtocolError(f"{where}: expected an array map {{dtype, shape, data}}, got {type(d).__name__}")
    if set(d) != {"dtype", "shape", "data"}:
        raise ProtocolError(f"{where}: array map must have exactly dtype, shape, data; got {sorted(map(str, d))}")
    name = d["dtype"]
    if not isinstance(name, str) or name not in ALLOWED_DTYPES:
        raise ProtocolError(f"{where}: dtype {name!r} not allowed (allowed: {', '.join(ALLOWED_DTYPES)})")
    shape = d["shape"]
    if not isinstance(shape, list) or len(shape) > MAX_ARRAY_NDIM:
        raise ProtocolError(f"{where}: shape must be a list of at most {MAX_ARRAY_NDIM} integers, got {shape!r}")
    dims = [_int(s, f"{where}.shape", 0, 2 ** 31) for s in shape]
    dt = np.dtype(name).newbyteorder("<")
    # Python integers: an int64 product of six 2**31 dimensions would wrap around (to 0)
    count = math.prod(dims)
    nbytes = count * dt.itemsize
    if nbytes > max_bytes:
        raise ProtocolError(f"{where}: array of shape {tuple(dims)} {name} ({nbytes} bytes) "
                            f"exceeds the {max_bytes}-byte limit")
    if math.prod(d for d in dims if d) * dt.itemsize > max_bytes:  # e.g. (0, 2**31, 2**31): empty but unrepresentable
        raise ProtocolError(f"{where}: empty array of shape {tuple(dims)} "
                            f"has dimensions beyond the {max_bytes}-byte limit")
    data = d["data"]
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"{where}.data: expected raw bytes, got {type(data).__name__}")
    if len(data) != nbytes:
        raise ProtocolError(f"{where}: {len(data)} data bytes do not match shape {tuple(dims)} {name} ({nbytes} bytes)")
    arr = np.frombuffer(data, dtype=dt, count=count).reshape(dims)
    return arr.astype(np.dtype(name), copy=False) if dt != np.dtype(name) else arr


# ---------------------------------------------------------------------------- validation
def _check_camera(cam: Any, where: str, width: int, height: int) -> dict:
    cam = _dict(cam, where)
    out = {}
    for k in ("fx", "fy", "cx", "cy"):
        if k not in cam:
            raise ProtocolError(f"{where}: missing {k}")
        out[k] = _float(cam[k], f"{where}.{k}")
    if out["fx"] <= 0 or out["fy"] <= 0:
        raise ProtocolError(f"{where}: focal lengths must be positive, got fx={out['fx']}, fy={out['fy']}")
    for k, want in (("width", width), ("height", height)):
        if k not in cam:
            raise ProtocolError(f"{where}: missing {k}")
        got = _int(cam[k], f"{where}.{k}", 1, MAX_IMAGE_SIDE)
        if got != want:
            raise ProtocolError(f"{where}.{k} = {got} does not match the image ({width}x{height})")
        out[k] = got
    dist = cam.get("dist")
    if dist is not None:
        if not isinstance(dist, list) or len(dist) not in (4, 5, 8):
            raise ProtocolError(f"{where}.dist: expected 4, 5 or 8 coefficients, got {dist!r}")
        dist = [_float(x, f"{where}.dist") for x in dist]
    out["dist"] = dist
    extra = set(cam) - {"fx", "fy", "cx", "cy", "width", "height", "dist"}
    if extra:
        raise ProtocolError(f"{where}: unknown keys {sorted(extra)}")
    return out


def check_camera(cam: Any, where: str = "camera") -> dict:
    """Validate a camera dict on its own (a Frame checks it against its image size); returns its
    normal form (floats, ints, ``dist`` None or a list) or raises ProtocolError."""
    if not isinstance(cam, dict):
        raise ProtocolError(f"{where}: expected a map, got {type(cam).__name__}")
    size = [_int(cam.get(k), f"{where}.{k}", 1, MAX_IMAGE_SIDE) for k in ("width", "height")]
    return _check_camera(cam, where, *size)


def _check_pose_matrix(m: np.ndarray, where: str) -> np.ndarray:
    _check_array(m, where, dtype="float64", shape=(4, 4), ndim=2, finite=True)
    if np.abs(m[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise ProtocolError(f"{where}: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    r = m[:3, :3]
    err = np.abs(r.T @ r - np.eye(3)).max()
    if err > POSE_ORTHO_TOL or np.linalg.det(r) <= 0:
        raise ProtocolError(f"{where}: rotation block is not a proper rotation (|R^T R - I| = {err:.2e})")
    return m


def validate(msg: Message) -> Message:
    """Check a message in memory; returns it (normalised scalars) or raises ProtocolError."""
    if isinstance(msg, Frame):
        w = "Frame"
        msg.seq = _int(msg.seq, f"{w}.seq", 0)
        msg.timestamp = _float(msg.timestamp, f"{w}.timestamp")
        rgb = _check_array(msg.rgb, f"{w}.rgb", dtype="uint8", ndim=3, shape=(None, None, 3))
        h, wd = rgb.shape[:2]
        if not (1 <= h <= MAX_IMAGE_SIDE and 1 <= wd <= MAX_IMAGE_SIDE):
            raise ProtocolError(f"{w}.rgb: size {wd}x{h} outside 1..{MAX_IMAGE_SIDE}")
        if msg.depth is not None:
            d = _check_array(msg.depth, f"{w}.depth", dtype="float32", ndim=2)
            if d.shape != (h, wd):
                raise ProtocolError(f"{w}.depth: shape {tuple(d.shape)} does not match rgb ({h}, {wd})")
            if d.size and not (np.isfinite(d).all() and (d >= 0).all()):
                raise ProtocolError(f"{w}.depth: must be finite and >= 0 (0 = invalid)")
        msg.camera = _check_camera(msg.camera, f"{w}.camera", wd, h)
    elif isinstance(msg, Pose):
        w = "Pose"
        msg.seq = _int(msg.seq, f"{w}.seq", -1)
        msg.timestamp = _float(msg.timestamp, f"{w}.timestamp")
        _check_pose_matrix(msg.c2w, f"{w}.c2w")
        msg.source = _check_name(msg.source, f"{w}.source")
        if msg.covariance is not None:
            _check_array(msg.covariance, f"{w}.covariance", dtype="float64", ndim=2, shape=(6, 6), finite=True)
        if msg.quality is not None:
            msg.quality = _float(msg.quality, f"{w}.quality")
        if not isinstance(msg.keyframe, (bool, np.bool_)):
            raise ProtocolError(f"{w}.keyframe: expected true or false, got {type(msg.keyframe).__name__}")
        msg.keyframe = bool(msg.keyframe)
    elif isinstance(msg, FieldSnapshot):
        w = "FieldSnapshot"
        msg.version = _int(msg.version, f"{w}.version", 0)
        msg.kind = _check_name(msg.kind, f"{w}.kind")
        msg.config = _dict(msg.config, f"{w}.config")
        aabb = _check_array(msg.aabb, f"{w}.aabb", ndim=2, shape=(2, 3), finite=True)
        if aabb.dtype.kind != "f":
            raise ProtocolError(f"{w}.aabb: expected float32 or float64, got {aabb.dtype.name}")
        if not (aabb[0] < aabb[1]).all():
            raise ProtocolError(f"{w}.aabb: min {aabb[0].tolist()} must be below max {aabb[1].tolist()}")
        if not isinstance(msg.arrays, dict):
            raise ProtocolError(f"{w}.arrays: expected a map of name -> array, got {type(msg.arrays).__name__}")
        if len(msg.arrays) > MAX_FIELD_ARRAYS:
            raise ProtocolError(f"{w}.arrays: {len(msg.arrays)} arrays exceed {MAX_FIELD_ARRAYS}")
        total = 0
        for k, a in msg.arrays.items():
            if not isinstance(k, str) or not re.match(r"^[A-Za-z0-9_.\-]{1,128}$", k):
                raise ProtocolError(f"{w}.arrays: bad array name {k!r}")
            _check_array(a, f"{w}.arrays[{k}]", finite=True)
            total += a.nbytes
        if total > MAX_FIELD_BYTES:
            raise ProtocolError(f"{w}.arrays: {total} bytes exceed the {MAX_FIELD_BYTES}-byte limit")
        msg.frame_seq = _int(msg.frame_seq, f"{w}.frame_seq", -1)
        msg.timestamp = _float(msg.timestamp, f"{w}.timestamp")
        if msg.frame_c2w is not None:
            _check_pose_matrix(msg.frame_c2w, f"{w}.frame_c2w")
    elif isinstance(msg, PointsSnapshot):
        w = "PointsSnapshot"
        msg.version = _int(msg.version, f"{w}.version", 0)
        p = _check_array(msg.points, f"{w}.points", dtype="float32", ndim=2, shape=(None, 3), finite=True)
        c = _check_array(msg.colors, f"{w}.colors", dtype="uint8", ndim=2, shape=(None, 3))
        if len(p) > MAX_POINTS:
            raise ProtocolError(f"{w}.points: {len(p)} points exceed {MAX_POINTS}")
        if len(c) != len(p):
            raise ProtocolError(f"{w}.colors: {len(c)} colours for {len(p)} points")
        msg.frame_seq = _int(msg.frame_seq, f"{w}.frame_seq", -1)
    elif isinstance(msg, Status):
        w = "Status"
        msg.service = _check_name(msg.service, f"{w}.service")
        msg.seq = _int(msg.seq, f"{w}.seq", 0)
        msg.time = _float(msg.time, f"{w}.time")
        msg.state = _check_name(msg.state, f"{w}.state")
        msg.frame_seq = _int(msg.frame_seq, f"{w}.frame_seq", -1)
        msg.lag = _float(msg.lag, f"{w}.lag")
        if not isinstance(msg.counters, dict):
            raise ProtocolError(f"{w}.counters: expected a map, got {type(msg.counters).__name__}")
        counters = {}
        for k, v in msg.counters.items():
            _check_name(k, f"{w}.counters key")
            counters[k] = _int(v, f"{w}.counters.{k}") if isinstance(v, (int, np.integer)) and not isinstance(v, bool) \
                else _float(v, f"{w}.counters.{k}")
        msg.counters = counters
        msg.last_error = _str(msg.last_error, f"{w}.last_error")
    elif isinstance(msg, Control):
        w = "Control"
        msg.command = _str(msg.command, f"{w}.command", 64)
        if msg.command not in CONTROL_COMMANDS:
            raise ProtocolError(f"{w}.command: {msg.command!r} is not one of {', '.join(CONTROL_COMMANDS)}")
        msg.args = _dict(msg.args, f"{w}.args")
    else:
        raise ProtocolError(f"not a protocol message: {type(msg).__name__}")
    return msg


# ---------------------------------------------------------------------------- encode / decode
_ARRAY_FIELDS = {
    "Frame": ("rgb", "depth"),
    "Pose": ("c2w", "covariance"),
    "FieldSnapshot": ("aabb", "frame_c2w"),
    "PointsSnapshot": ("points", "colors"),
    "Status": (),
    "Control": (),
}


def encode(msg: Message) -> bytes:
    """Validate ``msg`` and pack it to bytes (raises ProtocolError when invalid)."""
    validate(msg)
    name = type(msg).__name__
    out: dict[str, Any] = {"schema": name, "v": PROTOCOL_VERSION}
    for f in msg.__dataclass_fields__:
        v = getattr(msg, f)
        if f in _ARRAY_FIELDS[name]:
            out[f] = None if v is None else _pack_array(v)
        elif name == "FieldSnapshot" and f == "arrays":
            out[f] = {k: _pack_array(a) for k, a in v.items()}
        else:
            out[f] = v
    return msgpack.packb(out, use_bin_type=True)


def _unpack(data: Any) -> dict:
    if isinstance(data, (bytearray, memoryview)):
        data = bytes(data)
    if not isinstance(data, bytes):
        raise ProtocolError(f"expected bytes, got {type(data).__name__}")
    if len(data) == 0:
        raise ProtocolError("empty message")
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    if len(data) >= 2 and data[0] == 0x80 and data[1] in _PICKLE_PROTOCOLS:
        raise ProtocolError("payload looks like a Python pickle; only msgpack messages are accepted")
    try:
        obj = msgpack.unpackb(
            data, raw=False, strict_map_key=True, use_list=True,
            max_bin_len=MAX_MESSAGE_BYTES, max_str_len=1024 * 1024, max_array_len=100_000,
            max_map_len=10_000, max_ext_len=0,
        )
    except msgpack.ExtraData:
        raise ProtocolError("trailing bytes after the message (not a single msgpack object)") from None
    except (ValueError, TypeError, msgpack.UnpackException, RecursionError) as e:
        raise ProtocolError(f"not a valid msgpack message: {type(e).__name__}: {e}") from None
    if not isinstance(obj, dict):
        raise ProtocolError(f"message must be a msgpack map, got {type(obj).__name__}")
    return obj


def decode(data: Any, expect: Optional[type] = None) -> Message:
    """Unpack and validate one message; ``expect`` (a message class) rejects any other schema."""
    obj = _unpack(data)
    schema = obj.get("schema")
    if not isinstance(schema, str) or schema not in MESSAGE_TYPES:
        raise ProtocolError(f"unknown schema {schema!r} (known: {', '.join(MESSAGE_TYPES)})")
    if expect is not None and schema != expect.__name__:
        raise ProtocolError(f"expected a {expect.__name__} message, got {schema}")
    ver = obj.get("v")
    if isinstance(ver, bool) or not isinstance(ver, int) or ver != PROTOCOL_VERSION:
        raise ProtocolError(f"{schema}: unsupported protocol version {ver!r} (this build speaks {PROTOCOL_VERSION})")
    cls = MESSAGE_TYPES[schema]
    fields = cls.__dataclass_fields__
    extra = set(obj) - set(fields) - {"schema", "v"}
    if extra:
        raise ProtocolError(f"{schema}: unknown fields {sorted(map(str, extra))}")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in obj:
            if _has_default(f):
                continue
            raise ProtocolError(f"{schema}: missing field {name!r}")
        v = obj[name]
        if name in _ARRAY_FIELDS[schema]:
            kwargs[name] = None if v is None else _unpack_array(v, f"{schema}.{name}", _array_limit(schema, name))
        elif schema == "FieldSnapshot" and name == "arrays":
            if not isinstance(v, dict):
                raise ProtocolError(f"{schema}.arrays: expected a map of name -> array, got {type(v).__name__}")
            if len(v) > MAX_FIELD_ARRAYS:
                raise ProtocolError(f"{schema}.arrays: {len(v)} arrays exceed {MAX_FIELD_ARRAYS}")
            kwargs[name] = {k: _unpack_array(a, f"{schema}.arrays[{k}]", MAX_FIELD_BYTES) for k, a in v.items()}
        else:
            kwargs[name] = v
    msg = cls(**kwargs)
    if isinstance(msg, Frame) and msg.rgb is None:
        raise ProtocolError("Frame.rgb: missing image")
    for name in ("c2w", "aabb", "points", "colors"):
        if hasattr(msg, name) and getattr(msg, name) is None:
            raise ProtocolError(f"{schema}.{name}: must not be null")
    return validate(msg)


def _has_default(f) -> bool:
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def _array_limit(schema: str, name: str) -> int:
    side = MAX_IMAGE_SIDE * MAX_IMAGE_SIDE
    return {
        ("Frame", "rgb"): side * 3,
        ("Frame", "depth"): side * 4,
        ("Pose", "c2w"): 16 * 8,
        ("Pose", "covariance"): 36 * 8,
        ("FieldSnapshot", "aabb"): 6 * 8,
        ("FieldSnapshot", "frame_c2w"): 16 * 8,
        ("PointsSnapshot", "points"): MAX_POINTS * 12,
        ("PointsSnapshot", "colors"): MAX_POINTS * 3,
    }[(schema, name)]


def decode_as(data: Any, cls: type) -> Message:
    """:func:`decode` that only accepts messages of class ``cls``."""
    return decode(data, expect=cls)


# ---------------------------------------------------------------------------- conveniences
def frame_from_dataset(f, seq: Optional[int] = None, with_depth: bool = True) -> Frame:
    """A protocol Frame from a :class:`fmapping.datasets.base.Frame` (NaN / negative depth -> 0)."""
    depth = None
    if with_depth and f.depth is not None:
        depth = np.asarray(f.depth, dtype=np.float32)
        bad = ~np.isfinite(depth) | (depth < 0)
        if bad.any():
            depth = np.where(bad, np.float32(0), depth)
    cam = f.camera.to_dict()
    return Frame(seq=int(f.index if seq is None else seq), timestamp=float(f.timestamp),
                 rgb=np.ascontiguousarray(f.rgb, dtype=np.uint8), camera=cam, depth=depth)


def camera_of(frame: Frame):
    """The :class:`fmapping.camera.PinholeCamera` of a protocol Frame."""
    from fmapping.camera import PinholeCamera

    return PinholeCamera.from_dict(frame.camera)
