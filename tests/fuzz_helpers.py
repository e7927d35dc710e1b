"""The fuzz scaffolding of the reliability tests (test_reliability.py): a seeded generator of
malformed payloads for every message type (``Fuzzer``) and of payloads that decode but do not fit a
service's state, the state of the service cores as comparable values, and the fuzz drivers.

Importable as a plain module (``tests/`` is on ``sys.path`` under pytest).
"""
from __future__ import annotations

import collections
import dataclasses
import hashlib
import json
import pickle
import time
from typing import Callable, Optional

import msgpack
import numpy as np

from fakes import FakeSession
from fmapping import protocol as P
from service_helpers import pack, raw_message, wire_array
from services.transport import Service

N_FUZZ = 10_000


# ============================================================================ fuzz generator
NAN, INF = float("nan"), float("inf")
BAD_INT = [-7, -(2 ** 63), 2 ** 63, 2 ** 64 - 1, "3", 1.5, None, True, [1], {"a": 1}, b"\x01"]
BAD_FLOAT = [NAN, INF, -INF, "1.0", None, True, [0.5], {"x": 1.0}, b"\x00"]
BAD_NAME = ["", "gt/evil", "a" * 65, "white space", "*", "**", "\u00e9t\u00e9", 5, None, ["gt"], b"gt"]
BAD_DTYPE = ["float16", "object", "complex64", "int8", "<f4", "bool", "O", "V8", "", 5, None, ["uint8"]]
# the fields of each message and how to spoil them (None marks an optional field: None is valid there)
SCHEMA = {
    "Frame": {"seq": "int0", "timestamp": "float", "rgb": "array", "camera": "camera", "depth": "array?"},
    "Pose": {"seq": "int-1", "timestamp": "float", "c2w": "pose", "source": "name", "covariance": "array?",
             "quality": "float?"},
    "FieldSnapshot": {"version": "int0", "kind": "name", "config": "map", "aabb": "aabb", "arrays": "arrays",
                      "frame_seq": "int-1", "timestamp": "float", "frame_c2w": "pose?"},
    "PointsSnapshot": {"version": "int0", "points": "array", "colors": "array", "frame_seq": "int-1"},
    "Status": {"service": "name", "seq": "int0", "time": "float", "state": "name", "frame_seq": "int-1",
               "lag": "float", "counters": "counters", "last_error": "text"},
    "Control": {"command": "command", "args": "map"},
}
REQUIRED = {"Frame": ("seq", "timestamp", "rgb", "camera"), "Pose": ("seq", "timestamp", "c2w"),
            "FieldSnapshot": ("version", "kind", "config", "aabb", "arrays"),
            "PointsSnapshot": ("version", "points", "colors"), "Status": ("service",), "Control": ("command",)}
DEFAULT_ARRAYS = {("Frame", "depth"): lambda m: np.ones(m.rgb.shape[:2], np.float32),
                  ("Pose", "covariance"): lambda m: np.eye(6),
                  ("FieldSnapshot", "frame_c2w"): lambda m: np.eye(4)}


def _deep(n: int):
    d: dict = {"leaf": 1}
    for _ in range(n):
        d = {"a": d}
    return d


class Fuzzer:
    """A seeded generator of payloads that every service must reject.

    ``bases`` maps a channel to a valid message of the type that channel carries. Each
    payload is a valid encoding spoiled in one way (a *category*); ``semantic`` maps a channel
    to extra generators of messages that decode but are inconsistent with the service's
    state (a frame of another size, a snapshot whose arrays do not fit its config, ...).
    ``next(channel)`` returns (category, payload); ``decode_level(category)`` tells whether
    :func:`fmapping.protocol.decode` itself must refuse it."""

    def __init__(self, seed: int, bases: dict, semantic: Optional[dict] = None):
        self.rng = np.random.default_rng(seed)
        self.bases = bases
        self.semantic = semantic or {}
        self.encoded = {ch: P.encode(m) for ch, m in bases.items()}
        self.raws = {ch: raw_message(m) for ch, m in bases.items()}
        others = [P.Pose(seq=1, timestamp=0.0, c2w=np.eye(4), source="gt"), P.Control("stop"),
                  P.Status(service="x"), P.PointsSnapshot(version=1, points=np.zeros((2, 3), np.float32),
                                                          colors=np.zeros((2, 3), np.uint8)),
                  P.Frame(seq=0, timestamp=0.0, rgb=np.zeros((2, 3, 3), np.uint8),
                          camera={"fx": 1.0, "fy": 1.0, "cx": 1.0, "cy": 0.5, "width": 3, "height": 2})]
        self.others = {type(m).__name__: P.encode(m) for m in others}
        self.generic = [self.truncated, self.random_bytes, self.not_a_map, self.pickled, self.trailing, self.ext_type,
                        self.int_keys, self.wrong_schema, self.other_message, self.wrong_version,
                        self.missing_field, self.unknown_field, self.bad_value, self.bad_value, self.bad_array,
                        self.bad_array, self.bad_array, self.nonfinite, self.nonfinite]

    # -- helpers
    def pick(self, seq):
        return seq[int(self.rng.integers(len(seq)))]

    def _copy(self, channel: str) -> dict:
        return msgpack.unpackb(pack(self.raws[channel]), raw=False)  # deep copy

    def schema(self, channel: str) -> str:
        return type(self.bases[channel]).__name__

    # -- generic spoilers: (category, payload)
    def truncated(self, ch):
        enc = self.encoded[ch]
        return "truncated", enc[: int(self.rng.integers(0, len(enc)))]

    def random_bytes(self, ch):
        data = self.rng.bytes(int(self.rng.integers(1, 300)))
        if data[:2] in (b"\x80\x02", b"\x80\x03", b"\x80\x04", b"\x80\x05"):
            data = b"\x00" + data
        return "random_bytes", data

    def not_a_map(self, ch):
        v = self.pick([[1, 2, 3], 5, -1, 2.5, "Frame", b"\x00\x01", None, True, [self.raws[ch]]])
        return "not_a_map", pack(v)

    def pickled(self, ch):
        return "pickle", pickle.dumps(self.raws[ch], protocol=int(self.rng.integers(2, 6)))

    def trailing(self, ch):
        return "trailing_bytes", self.encoded[ch] + self.rng.bytes(int(self.rng.integers(1, 9)))

    def ext_type(self, ch):
        d = self._copy(ch)
        d[self.pick(list(SCHEMA[self.schema(ch)]))] = msgpack.ExtType(int(self.rng.integers(0, 128)), b"xx")
        return "ext_type", pack(d)

    def int_keys(self, ch):
        d = self._copy(ch)
        return "int_keys", pack({**d, 7: 1})

    def wrong_schema(self, ch):
        d = self._copy(ch)
        d["schema"] = self.pick(["Evil", "", "frame", "Frames", 3, None, ["Frame"], "Pose\x00"])
        return "wrong_schema", pack(d)

    def other_message(self, ch):
        name = self.pick(sorted(k for k in self.others if k != self.schema(ch)))
        return "other_message", self.others[name]

    def wrong_version(self, ch):
        d = self._copy(ch)
        if self.rng.random() < 0.15:
            del d["v"]
        else:
            d["v"] = self.pick([0, 2, 99, -1, 2 ** 32, "1", 1.0, None, True, [1]])
        return "wrong_version", pack(d)

    def missing_field(self, ch):
        d = self._copy(ch)
        del d[self.pick(list(REQUIRED[self.schema(ch)]) + ["schema"])]
        return "missing_field", pack(d)

    def unknown_field(self, ch):
        d = self._copy(ch)
        d[self.pick(["extra", "__class__", "c2w_", "Seq", "data"])] = self.pick([1, "x", None, [1, 2]])
        return "unknown_field", pack(d)

    def bad_value(self, ch):
        """A scalar / map field given a value of the wrong type or out of range."""
        d = self._copy(ch)
        schema = self.schema(ch)
        name, kind = self.pick([(k, v) for k, v in SCHEMA[schema].items() if "array" not in v and v not in
                                ("pose", "pose?", "aabb", "arrays")])
        opt = kind.endswith("?")
        kind = kind.rstrip("?")
        if kind in ("int0", "int-1"):
            v = self.pick(BAD_INT)
            kind = "int"
        elif kind == "float":
            v = self.pick([x for x in BAD_FLOAT if not (opt and x is None)])
        elif kind == "name":
            v = self.pick(BAD_NAME)
        elif kind == "text":
            v = self.pick(["x" * (P.MAX_STRING + 1), 5, None, ["a"]])
        elif kind == "command":
            v = self.pick(["explode", "STOP", "", "stop ", 5, None, ["stop"], "rm -rf /"])
        elif kind == "counters":
            v = self.pick([[1], "x", {"a b": 1}, {"ok": "many"}, {"ok": NAN}, {"ok": None}, {"ok": [1]}])
        elif kind == "camera":
            v = self._bad_camera(d["camera"])
        else:  # map
            v = self.pick([[1], "x", 5, None, _deep(P.MAX_NESTING + 1), {"s": "x" * (P.MAX_STRING + 1)},
                           {"f": NAN}, {"f": INF}, {"b": b"raw"}])
        d[name] = v
        return f"bad_{kind}", pack(d)

    def _bad_camera(self, cam: dict):
        cam = dict(cam)
        how = int(self.rng.integers(12))
        if how == 0:
            del cam[self.pick(["fx", "fy", "cx", "cy", "width", "height"])]
        elif how == 1:
            cam[self.pick(["fx", "fy"])] = self.pick([0.0, -5.0, -1e-9])
        elif how == 2:
            cam[self.pick(["width", "height"])] += int(self.rng.integers(1, 5))
        elif how == 3:
            cam["dist"] = self.pick([[0.1], [0.1, 0.2, 0.3], [0.0] * 6, "none", [NAN, 0, 0, 0], 5])
        elif how == 4:
            cam["skew"] = 0.0
        elif how == 5:
            cam[self.pick(["fx", "fy", "cx", "cy"])] = self.pick([NAN, INF, -INF, "100", None, [1.0]])
        elif how == 6:
            cam["width"] = float(cam["width"])
        elif how == 7:
            cam[self.pick(["width", "height"])] = self.pick([0, -1, P.MAX_IMAGE_SIDE + 1, True])
        elif how == 8:
            return self.pick([[1, 2], "pinhole", 5, None])
        elif how == 9:
            return {}
        elif how == 10:
            cam["dist"] = {"k1": 0.1}
        else:
            cam = {"fx": cam["fx"]}
        return cam

    def _array_field(self, ch, float_only: bool = False):
        schema = self.schema(ch)
        names = [k for k, v in SCHEMA[schema].items() if v.rstrip("?") in ("array", "pose", "aabb")]
        if float_only:
            names = [n for n in names if n not in ("rgb", "colors")]
        name = self.pick(names)
        base = getattr(self.bases[ch], name)
        if base is None:
            base = DEFAULT_ARRAYS[(schema, name)](self.bases[ch])
        return name, np.array(base)

    def bad_array(self, ch):
        """An array field spoiled: dtype, shape, data, size, container."""
        d = self._copy(ch)
        name, a = self._array_field(ch)
        enc = wire_array(a)
        how = int(self.rng.integers(12))
        if how == 0:
            enc["dtype"] = self.pick(BAD_DTYPE)
            cat = "bad_dtype"
        elif how == 1:  # an allowed dtype, but not the one this field has (data consistent with it)
            want = a.dtype.name
            other = self.pick([t for t in P.ALLOWED_DTYPES if t != want and not (want.startswith("float") and
                                                                                   t.startswith("float"))])
            if name == "aabb":
                other = self.pick(["uint8", "int32", "int64", "uint16"])
            enc = wire_array(a.astype(other))
            cat = "wrong_dtype"
        elif how == 2:  # shape does not match the number of data bytes
            shape = list(a.shape)
            i = int(self.rng.integers(len(shape)))
            shape[i] += int(self.rng.integers(1, 4))
            enc["shape"] = shape
            cat = "shape_data_mismatch"
        elif how == 3:  # consistent data, wrong number of dimensions / wrong fixed dimension
            b = a.reshape(-1) if a.ndim > 1 else a.reshape(1, -1, 1)
            if name in ("rgb",) and self.rng.random() < 0.5:
                b = np.concatenate([a, a[..., :1]], -1)  # RGBA
            enc = wire_array(b)
            cat = "wrong_shape"
        elif how == 4:
            enc["shape"] = [int(x) for x in self.rng.integers(-5, 0, size=max(1, a.ndim))]
            cat = "negative_dim"
        elif how == 5:
            enc["shape"] = [1] * int(self.rng.integers(P.MAX_ARRAY_NDIM + 1, 12))
            cat = "too_many_dims"
        elif how == 6:  # the size claim alone exceeds the limits (data would be gigabytes)
            enc["shape"] = self.pick([[100_000, 100_000, 3], [2 ** 31] * 6, [0] + [2 ** 31] * 5, [2 ** 31, 2 ** 31],
                                      [P.MAX_POINTS + 1, 3], [P.MAX_IMAGE_SIDE + 1, P.MAX_IMAGE_SIDE + 1, 3]])
            cat = "oversized"
        elif how == 7:
            enc["shape"] = self.pick(["4x4", 16, None, {"0": 4}, [4.0, 4.0], [True, 4]])
            cat = "bad_shape_type"
        elif how == 8:
            enc["data"] = self.pick([a.tobytes().hex(), list(a.reshape(-1)[:8].tolist()), 5, None])
            cat = "data_not_bytes"
        elif how == 9:
            if self.rng.random() < 0.5:
                del enc[self.pick(["dtype", "shape", "data"])]
            else:
                enc[self.pick(["strides", "order", "byteorder"])] = self.pick([[1], "C", "<"])
            cat = "array_keys"
        elif how == 10:
            enc = self.pick([[1, 2, 3], "array", 5, a.tobytes()[:64]])
            cat = "array_not_map"
        else:  # a real array just over a size limit (cheap: one long row)
            if name == "rgb":
                b = np.zeros((1, P.MAX_IMAGE_SIDE + 1, 3), np.uint8)
            elif name == "depth":
                b = np.zeros((1, P.MAX_IMAGE_SIDE + 1), np.float32)  # also mismatches the rgb size
            else:
                b = np.zeros((a.shape[0] + 1,) + a.shape[1:], a.dtype) if a.ndim else np.zeros(2, a.dtype)
                if name in ("c2w", "frame_c2w", "covariance", "aabb"):
                    b = np.zeros((4, 4) if name != "covariance" else (7, 7)) if name != "aabb" else np.zeros((3, 3))
                elif name in ("points", "colors"):
                    b = np.zeros((len(a) + 1, 3), a.dtype)  # points / colours counts differ
            enc = wire_array(b)
            cat = "over_limit"
        d[name] = enc
        return cat, pack(d)

    def nonfinite(self, ch):
        """NaN / Inf (or a negative depth / a non-rigid pose) in a float field."""
        d = self._copy(ch)
        name, a = self._array_field(ch, float_only=True)
        a = np.array(a, dtype=a.dtype)
        flat = a.reshape(-1)
        if name in ("c2w", "frame_c2w") and self.rng.random() < 0.5:
            m = np.array(a)
            how = int(self.rng.integers(5))
            if how == 0:
                m[:3, :3] *= self.pick([2.0, 0.5, 1.01])  # scaled
            elif how == 1:
                m[0, 1] += 0.3  # sheared
            elif how == 2:
                m[:3, 0] *= -1  # a reflection (det -1)
            elif how == 3:
                m[3] = self.pick([[0, 0, 0, 2.0], [1.0, 0, 0, 1], [0, 0, 0, 0]])
            else:
                m[:3, :3] = 0
            d[name] = wire_array(m)
            return "non_rigid_pose", pack(d)
        if name == "depth" and self.rng.random() < 0.3:
            flat[int(self.rng.integers(flat.size))] = -self.rng.uniform(1e-6, 10)
            d[name] = wire_array(a)
            return "negative_depth", pack(d)
        if name == "aabb" and self.rng.random() < 0.3:
            d[name] = wire_array(a[::-1].copy())  # min above max
            return "inverted_aabb", pack(d)
        k = int(self.rng.integers(1, 4))
        flat[self.rng.integers(flat.size, size=k)] = self.pick([NAN, INF, -INF])
        d[name] = wire_array(a)
        return "nonfinite", pack(d)

    def field_arrays(self, ch):
        """FieldSnapshot.arrays spoiled at the protocol level (decode must refuse)."""
        d = self._copy(ch)
        arrays = d["arrays"]
        how = int(self.rng.integers(5))
        if how == 0:
            k = self.pick(sorted(arrays))
            a = np.frombuffer(arrays[k]["data"], arrays[k]["dtype"]).reshape(arrays[k]["shape"]).copy()
            a.reshape(-1)[0] = self.pick([NAN, INF])
            arrays[k] = wire_array(a)
        elif how == 1:
            arrays[self.pick(["../x", "a b", "", "x" * 200, "k/../../etc"])] = wire_array(np.ones(2, np.float32))
        elif how == 2:
            d["arrays"] = self.pick([[1], "x", None, 5])
        elif how == 3:
            for i in range(P.MAX_FIELD_ARRAYS + 1):
                arrays[f"x{i}"] = wire_array(np.ones(1, np.float32))
        else:
            arrays[self.pick(sorted(arrays))]["dtype"] = self.pick(BAD_DTYPE)
        return "bad_field_arrays", pack(d)

    # -- driver
    def next(self, channel: str) -> tuple[str, bytes]:
        gens = list(self.generic)
        if not any(v.rstrip("?") in ("array", "pose", "aabb") for v in SCHEMA[self.schema(channel)].values()):
            gens = [g for g in gens if g not in (self.bad_array, self.nonfinite)]
        if self.schema(channel) == "FieldSnapshot":
            gens += [self.field_arrays] * 2
        sem = self.semantic.get(channel, [])
        if sem and self.rng.random() < 0.2:
            return self.pick(sem)(self.rng)
        return self.pick(gens)(channel)

    def stream(self, n: int, channels: list) -> list[tuple[str, str, bytes]]:
        """``n`` (channel, category, payload) triples over ``channels`` in a seeded random order."""
        out = []
        for _ in range(n):
            ch = self.pick(channels)
            cat, data = self.next(ch)
            out.append((ch, cat, data))
        return out


SEMANTIC = ("other_size", "other_intrinsics", "distorted_camera", "snapshot_")


def decode_level(category: str) -> bool:
    """Whether protocol.decode itself refuses payloads of this category (else the service does)."""
    return not category.startswith(SEMANTIC)


def frame_semantics(base: P.Frame) -> list[Callable]:
    """Frames that decode but do not belong to the stream the service is in (size / intrinsics)."""

    def other_size(rng):
        h, w = base.rgb.shape[:2]
        while True:
            h2, w2 = int(rng.integers(1, 2 * h)), int(rng.integers(1, 2 * w))
            if (h2, w2) != (h, w):
                break
        cam = dict(base.camera, width=w2, height=h2, cx=(w2 - 1) / 2, cy=(h2 - 1) / 2)
        cam.pop("dist", None)
        f = P.Frame(seq=base.seq + 1 + int(rng.integers(1000)), timestamp=base.timestamp + 1.0,
                    rgb=rng.integers(0, 256, (h2, w2, 3), dtype=np.uint8), camera=cam,
                    depth=np.ones((h2, w2), np.float32) if rng.random() < 0.5 else None)
        return "other_size", P.encode(f)

    def other_intrinsics(rng):
        cam = dict(base.camera)
        cam.pop("dist", None)
        k = str(rng.choice(["fx", "fy", "cx", "cy"]))
        cam[k] = float(cam[k]) * float(rng.choice([0.5, 0.9, 1.001, 2.0]))
        f = dataclasses.replace(base, seq=base.seq + 1 + int(rng.integers(1000)), camera=cam)
        return "other_intrinsics", P.encode(f)

    def distorted(rng):
        cam = dict(base.camera)
        cam["dist"] = [float(x) for x in rng.uniform(-0.2, 0.2, int(rng.choice([4, 5, 8])))]
        f = dataclasses.replace(base, seq=base.seq + 1 + int(rng.integers(1000)), camera=cam)
        return "distorted_camera", P.encode(f)

    return [other_size, other_intrinsics, distorted]


def snapshot_semantics(base: P.FieldSnapshot, next_version: Callable[[], int]) -> list[Callable]:
    """Field snapshots that decode but cannot be (or must not be) used: arrays that do not fit the
    config, configs asking for huge fields, unusable render settings, another camera. Each has a
    version above the tracker's (an older one would only be counted as stale)."""

    def spoil(rng, cat, fn):
        s = dataclasses.replace(base, version=next_version(), config=json.loads(json.dumps(base.config)),
                                arrays={k: np.array(v) for k, v in base.arrays.items()})
        fn(s, rng)
        return f"snapshot_{cat}", P.encode(s)

    def arrays(rng):
        def f(s, rng):
            k = str(rng.choice(sorted(k for k in s.arrays if k != "aabb")))
            how = int(rng.integers(4))
            if how == 0:
                del s.arrays[k]
            elif how == 1:
                s.arrays[k + "_x"] = s.arrays.pop(k)
            elif how == 2:
                a = s.arrays[k]
                s.arrays[k] = np.concatenate([a.reshape(-1), a.reshape(-1)[:1]]).astype(a.dtype)
            else:
                s.arrays["extra"] = np.ones(3, np.float32)
        return spoil(rng, "arrays", f)

    def oversized(rng):
        def f(s, rng):
            s.config["field"].update(rng.choice([
                {"resolution": 10 ** 7}, {"density_components": 10 ** 6, "resolution": 4096},
                {"kind": "grid", "grid_resolution": 10 ** 5}, {"kind": "vm", "resolution": 10 ** 5},
                {"kind": "mlp", "mlp_width": 10 ** 6, "mlp_layers": 8}, {"hidden": 10 ** 8, "app_features": 10 ** 8},
                {"kind": "mlp", "pe_freqs": 10 ** 9}]))
        return spoil(rng, "oversized_config", f)

    def bad_config(rng):
        def f(s, rng):
            how = int(rng.integers(7))
            if how == 0:
                s.config["field"]["unknown_knob"] = 1
            elif how == 1:
                s.config["field"]["kind"] = str(rng.choice(["evil", "", "CP"]))
            elif how == 2:
                s.config["field"]["resolution"] = [None, "12", 1.5, -3, 0][int(rng.integers(5))]
            elif how == 3:
                s.config["field"] = [None, "cp", 5, [1]][int(rng.integers(4))]
            elif how == 4:
                s.config["field"]["seed"] = ["0", None, [1]][int(rng.integers(3))]
            elif how == 5:
                s.config["field"]["init_scale"] = [0.0, -1.0, "x"][int(rng.integers(3))]
            else:
                s.config["field"]["alpha_mode"] = "maybe"
        return spoil(rng, "bad_config", f)

    def render(rng):
        def f(s, rng):
            k, v = [("n_coarse", 10 ** 9), ("n_coarse", 0), ("n_coarse", 1.5), ("n_coarse", "32"), ("n_fine", -1),
                    ("n_fine", 10 ** 6), ("near", -1.0), ("near", "0.1"), ("far", 0.0), ("far", 1e9), ("near", 100.0),
                    ("near", None), ("n_coarse", True)][int(rng.integers(13))]
            s.config[k] = v
        return spoil(rng, "render_config", f)

    def camera(rng):
        def f(s, rng):
            cam = dict(s.config["camera"])
            how = int(rng.integers(5))
            if how == 0:
                cam["fx"] = cam["fx"] * 1.5  # valid on its own, but not the frames' camera
            elif how == 1:
                cam["width"] = cam["width"] * 2
            elif how == 2:
                cam["width"] = 10 ** 9
            elif how == 3:
                del cam["fy"]
            else:
                cam = [1, 2]
            s.config["camera"] = cam
        return spoil(rng, "camera", f)

    return [arrays, oversized, bad_config, render, camera]


# ============================================================================ state of the cores
def mapper_state(core) -> dict:
    """Everything a bad input must not touch, as plain comparable values (tensors by their bytes)."""
    m = core.mapper
    return {
        "field": {k: (v.dtype, tuple(v.shape), v.detach().cpu().numpy().tobytes()) for k, v in
                  m.field.state_dict().items()},
        "poses": {k: v.tobytes() for k, v in m.frame_poses().items()},
        "frames_mapped": len(m.frame_poses()), "keyframes": list(m.keyframe_ids()),
        "seq_of_fid": list(core.seq_of_fid), "ack": core.ack, "version": core.version, "windows": core.windows,
        "pending_frames": list(core.frames), "pending_poses": {k: v.c2w.tobytes() for k, v in core.poses.items()},
        "anchors": sorted(core.anchors), "camera": dict(core.camera_dict), "paused": core.paused,
        "latest": hashlib.sha256(core.latest_field_bytes).hexdigest(), "finished": core.finished,
    }


def tracker_state(core) -> dict:
    return {
        "field": {k: v.detach().cpu().numpy().tobytes() for k, v in core.field.state_dict().items()},
        "version": core.version, "map_seq": core.map_seq, "ack": core.ack, "ref_seq": core.ref_seq,
        "waiting": list(core.waiting), "recent": list(core.recent), "camera": dict(core.camera_dict),
        "mapper_poses": {k: v.tobytes() for k, v in core.mapper_poses.items()},
        "own_poses": {k: (v.c2w.tobytes(), v.timestamp, v.quality) for k, v in core.own_poses.items()},
        "snapshot_pose": None if core.snapshot_pose is None else
                         (core.snapshot_pose[0], core.snapshot_pose[1].tobytes()),
        "render_cfg": dict(core.render_cfg),
        "reference": None if core.tracker.reference is None else core.tracker.reference.frame_index,
    }


def run_fuzz(handle, stream) -> tuple[collections.Counter, float]:
    """Feed every payload; an exception escaping ``handle`` fails the test with the payload's category."""
    cats: collections.Counter = collections.Counter()
    t0 = time.perf_counter()
    for ch, cat, data in stream:
        try:
            out = handle(ch, data)
        except Exception as e:  # noqa: BLE001 - the point of the test
            raise AssertionError(f"{type(e).__name__} escaped on a {cat!r} payload on {ch!r}: {e}") from e
        assert not out, (cat, out)
        cats[cat] += 1
    return cats, time.perf_counter() - t0


def report_fuzz(name: str, cats: collections.Counter, seconds: float) -> None:
    n = sum(cats.values())
    print(f"\n[fuzz] {name}: {n} payloads in {seconds:.2f} s ({n / seconds:.0f}/s), {len(cats)} categories: "
          + ", ".join(f"{k} {v}" for k, v in sorted(cats.items())))


# ============================================================================ fuzz drivers for the io handlers
def io_service(name: str, parser_args: list, add_args) -> tuple:
    """(service, args) of an io command on a fake session: only decoding is exercised (no subscriber
    is ever called)."""
    import argparse

    args = add_args(argparse.ArgumentParser()).parse_args(parser_args)
    return Service(name, args, session=FakeSession(), keys=P.Keys("fuzz"), install_signals=False), args


def fuzz_handler(name: str, svc, state: Callable[[], object], handle, seed: int, bases: dict, chans: list) -> None:
    """N_FUZZ bad payloads on ``chans`` through ``handle(channel, data)``: all counted by ``svc``
    (decode_errors = bad_input = sent) and ``state()`` unchanged."""
    fz = Fuzzer(seed, {k: bases[k] for k in chans})
    before, c0 = state(), svc.counters.snapshot()
    cats, secs = run_fuzz(handle, fz.stream(N_FUZZ, chans))
    c1 = svc.counters.snapshot()
    assert state() == before
    assert c1["bad_input"] - c0.get("bad_input", 0) == N_FUZZ == c1["decode_errors"] - c0.get("decode_errors", 0)
    report_fuzz(name, cats, secs)
