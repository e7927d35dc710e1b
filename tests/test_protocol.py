"""Wire protocol: round trips (arrays bit-exact) and every malformed variant -> ProtocolError."""
from __future__ import annotations

import pickle

import msgpack
import numpy as np
import pytest

from fmapping import protocol as P
from service_helpers import pack, raw_message, wire_array


def _frame(h=6, w=8, depth=True, seq=3) -> P.Frame:
    rng = np.random.default_rng(seq)
    return P.Frame(seq=seq, timestamp=12.5, rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
                   camera={"fx": 10.0, "fy": 11.0, "cx": (w - 1) / 2, "cy": (h - 1) / 2, "width": w, "height": h},
                   depth=rng.uniform(0.0, 4.0, (h, w)).astype(np.float32) if depth else None)


def _pose(seq=3, source="gt") -> P.Pose:
    a = 0.3
    c2w = np.array([[np.cos(a), -np.sin(a), 0, 1.0], [np.sin(a), np.cos(a), 0, -2.0], [0, 0, 1, 0.5], [0, 0, 0, 1]])
    return P.Pose(seq=seq, timestamp=1.25, c2w=c2w, source=source)


def _field() -> P.FieldSnapshot:
    rng = np.random.default_rng(0)
    return P.FieldSnapshot(
        version=7, kind="cp", config={"field": {"kind": "cp", "resolution": 16}, "near": 0.1, "far": 6.0},
        aabb=np.array([[-1.0, -2.0, 0.0], [1.0, 2.0, 3.0]]),
        arrays={"density_lines": rng.standard_normal((3, 4, 16)).astype(np.float32),
                "app_lines": rng.standard_normal((3, 5, 16)).astype(np.float32),
                "basis.weight": rng.standard_normal((8, 15)).astype(np.float32),
                "aabb": np.array([[-1, -2, 0], [1, 2, 3]], np.float32)},
        frame_seq=41, timestamp=100.0)


def _points(n=50) -> P.PointsSnapshot:
    rng = np.random.default_rng(1)
    return P.PointsSnapshot(version=2, points=rng.standard_normal((n, 3)).astype(np.float32),
                            colors=rng.integers(0, 256, (n, 3), dtype=np.uint8), frame_seq=9)


def _status() -> P.Status:
    return P.Status(service="mapper", seq=5, time=1700000000.5, state="running", frame_seq=12, lag=0.25,
                    counters={"frames_processed": 13, "window_s": 1.5}, last_error="")


def _control() -> P.Control:
    return P.Control("stop", {"reason": "end", "last_seq": 199, "nested": {"a": [1, 2.5, None, True]}})


ALL = [_frame, lambda: _frame(depth=False), _pose, _field, _points, _status, _control]


@pytest.mark.parametrize("make", ALL)
def test_round_trip_every_message_type(make):
    msg = make()
    back = P.decode(P.encode(msg))
    assert type(back) is type(msg)
    for name in msg.__dataclass_fields__:
        a, b = getattr(msg, name), getattr(back, name)
        if isinstance(a, np.ndarray):
            assert b.dtype == a.dtype and b.shape == a.shape
            assert a.tobytes() == b.tobytes()  # bit-exact
        elif isinstance(a, dict) and name == "arrays":
            assert set(a) == set(b)
            for k in a:
                assert a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes()
        elif name == "camera":
            assert {k: v for k, v in b.items() if k != "dist"} == {k: float(v) if k not in ("width", "height") else v
                                                                   for k, v in a.items() if k != "dist"}
        else:
            assert a == b, name


def test_decode_with_expected_type_and_readonly_zero_copy_arrays():
    data = P.encode(_frame())
    f = P.decode_as(data, P.Frame)
    assert not f.rgb.flags.writeable  # a view of the received buffer
    with pytest.raises(P.ProtocolError, match="expected a Pose message, got Frame"):
        P.decode(data, expect=P.Pose)


def test_big_endian_and_noncontiguous_arrays_are_normalised():
    f = _frame()
    f.depth = f.depth.astype(">f4")  # a big-endian float32: sent little-endian, same values
    f.rgb = np.asfortranarray(f.rgb)
    back = P.decode(P.encode(f))
    np.testing.assert_array_equal(back.depth, f.depth.astype("<f4"))
    np.testing.assert_array_equal(back.rgb, f.rgb)


def test_keys_layout_and_channel_parsing():
    k = P.Keys("lab1")
    assert k.frames == "fmapping/lab1/frames"
    assert k.poses("gt") == "fmapping/lab1/poses/gt" and k.poses() == "fmapping/lab1/poses/*"
    assert k.field == "fmapping/lab1/map/field" and k.points == "fmapping/lab1/map/points"
    assert k.latest == "fmapping/lab1/map/latest"
    assert k.status("mapper") == "fmapping/lab1/status/mapper" and k.control == "fmapping/lab1/control"
    assert [k.channel(x) for x in (k.frames, k.poses("tracker"), k.field, k.points, k.latest, k.status("io"),
                                   k.control, "fmapping/other/frames")] == \
        ["frames", "poses", "field", "points", "latest", "status", "control", ""]
    for bad in ("", "a/b", "x*", "has space", "a" * 65):
        with pytest.raises(ValueError):
            P.Keys(bad)
    with pytest.raises(P.ProtocolError):
        k.poses("gt/../x")


# ---------------------------------------------------------------------------- malformed payloads
def _with(msg, path, value):
    d = raw_message(msg)
    node = d
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value
    return pack(d)


def _without(msg, field):
    d = raw_message(msg)
    del d[field]
    return pack(d)


MALFORMED = {
    "empty": (b"", "empty message"),
    "truncated": (P.encode(_frame())[:-7], "not a valid msgpack"),
    "truncated_header": (P.encode(_pose())[:3], "not a valid msgpack"),
    "trailing_bytes": (P.encode(_pose()) + b"\x00", "trailing bytes"),
    "not_a_map": (pack([1, 2, 3]), "must be a msgpack map"),
    "not_a_map_int": (pack(5), "must be a msgpack map"),
    "pickle": (pickle.dumps({"schema": "Pose"}), "pickle"),
    "pickle_protocol2": (pickle.dumps([1, 2], protocol=2), "pickle"),
    "unknown_schema": (_with(_pose(), ["schema"], "Evil"), "unknown schema"),
    "schema_not_str": (_with(_pose(), ["schema"], 3), "unknown schema"),
    "wrong_version": (_with(_pose(), ["v"], 2), "unsupported protocol version"),
    "version_missing": (_without(_pose(), "v"), "unsupported protocol version"),
    "version_bool": (_with(_pose(), ["v"], True), "unsupported protocol version"),
    "missing_field": (_without(_pose(), "c2w"), "missing field 'c2w'"),
    "unknown_field": (_with(_pose(), ["extra"], 1), "unknown fields"),
    "seq_not_int": (_with(_pose(), ["seq"], "3"), "seq: expected an integer"),
    "seq_negative_frame": (_with(_frame(), ["seq"], -1), "seq: -1 outside"),
    "timestamp_nan": (_with(_pose(), ["timestamp"], float("nan")), "timestamp: must be finite"),
    "pose_nan": (_with(_pose(), ["c2w"], wire_array(np.full((4, 4), np.nan))), "NaN or Inf"),
    "pose_inf": (_with(_pose(), ["c2w"], wire_array(np.where(np.eye(4) > 0, np.inf, 0.0))), "NaN or Inf"),
    "pose_not_rigid": (_with(_pose(), ["c2w"], wire_array(np.diag([2.0, 1, 1, 1]))), "not a proper rotation"),
    "pose_reflection": (_with(_pose(), ["c2w"], wire_array(np.diag([-1.0, 1, 1, 1]))), "not a proper rotation"),
    "pose_bad_last_row": (_with(_pose(), ["c2w"], wire_array(np.ones((4, 4)))), "last row"),
    "pose_wrong_shape": (_with(_pose(), ["c2w"], wire_array(np.eye(3))), "shape"),
    "pose_wrong_dtype": (_with(_pose(), ["c2w"], wire_array(np.eye(4, dtype=np.float32))), "expected dtype float64"),
    "pose_source_bad": (_with(_pose(), ["source"], "gt/evil"), "source"),
    "dtype_not_allowed": (_with(_frame(), ["rgb", "dtype"], "object"), "not allowed"),
    "dtype_complex": (_with(_frame(), ["rgb", "dtype"], "complex64"), "not allowed"),
    "rgb_wrong_dtype": (_with(_frame(), ["rgb"], wire_array(np.zeros((6, 8, 3), np.uint16))), "expected dtype uint8"),
    "rgb_wrong_shape": (_with(_frame(), ["rgb"], wire_array(np.zeros((6, 8, 4), np.uint8))), "shape"),
    "rgb_gray": (_with(_frame(), ["rgb"], wire_array(np.zeros((6, 8), np.uint8))), "3 dimensions"),
    "data_size_mismatch": (_with(_frame(), ["rgb", "shape"], [6, 9, 3]), "do not match shape"),
    "negative_dim": (_with(_frame(), ["rgb", "shape"], [6, -8, 3]), "outside"),
    "shape_not_list": (_with(_frame(), ["rgb", "shape"], "6x8"), "shape must be a list"),
    "data_not_bytes": (_with(_frame(), ["rgb", "data"], "abc"), "raw bytes"),
    "array_extra_key": (_with(_frame(), ["rgb", "strides"], [1]), "exactly dtype, shape, data"),
    "oversized_frame": (_with(_frame(), ["rgb", "shape"], [5000, 5000, 3]), "exceeds"),
    "oversized_points": (_with(_points(), ["points", "shape"], [P.MAX_POINTS + 1, 3]), "exceeds"),
    "too_many_dims": (_with(_frame(), ["rgb", "shape"], [1] * 9), "at most"),
    "depth_size_mismatch": (_with(_frame(), ["depth"], wire_array(np.ones((5, 8), np.float32))), "does not match rgb"),
    "depth_nan": (_with(_frame(), ["depth"], wire_array(np.full((6, 8), np.nan, np.float32))), "finite"),
    "depth_negative": (_with(_frame(), ["depth"], wire_array(np.full((6, 8), -1.0, np.float32))), ">= 0"),
    "depth_wrong_dtype": (_with(_frame(), ["depth"], wire_array(np.ones((6, 8), np.float64))),
                          "expected dtype float32"),
    "camera_missing_fx": (_with(_frame(), ["camera"], {"fy": 1.0, "cx": 1, "cy": 1, "width": 8, "height": 6}),
                          "missing fx"),
    "camera_nan": (_with(_frame(), ["camera", "fx"], float("inf")), "finite"),
    "camera_negative_focal": (_with(_frame(), ["camera", "fx"], -5.0), "positive"),
    "camera_size_mismatch": (_with(_frame(), ["camera", "width"], 9), "does not match the image"),
    "camera_not_map": (_with(_frame(), ["camera"], [1, 2]), "expected a map"),
    "points_colors_mismatch": (_with(_points(), ["colors"], wire_array(np.zeros((3, 3), np.uint8))), "colours for"),
    "points_nan": (_with(_points(), ["points"], wire_array(np.full((4, 3), np.nan, np.float32))), "NaN"),
    "field_aabb_inverted": (_with(_field(), ["aabb"], wire_array(np.array([[1.0, 1, 1], [0, 0, 0]]))), "below max"),
    "field_array_nan": (_with(_field(), ["arrays", "app_lines"], wire_array(np.full((2, 2), np.inf, np.float32))),
                        "NaN or Inf"),
    "field_arrays_not_map": (_with(_field(), ["arrays"], [1]), "map of name"),
    "field_bad_array_name": (_with(_field(), ["arrays", "../x"], wire_array(np.ones(2, np.float32))), "bad array name"),
    "field_config_not_map": (_with(_field(), ["config"], "cp"), "expected a map"),
    "status_counter_text": (_with(_status(), ["counters", "x"], "many"), "expected a number"),
    "control_unknown_command": (_with(_control(), ["command"], "rm -rf"), "is not one of"),
    "control_args_not_map": (_with(_control(), ["args"], [1, 2]), "expected a map"),
    "ext_type": (pack({"schema": "Control", "v": 1, "command": "stop", "args": msgpack.ExtType(5, b"xx")}),
                 "not a valid msgpack"),
    "int_keys": (b"\x81\x01\x02", "not a valid msgpack"),
}


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_raises_protocol_error(name):
    data, match = MALFORMED[name]
    with pytest.raises(P.ProtocolError, match=match):
        P.decode(data)


def test_not_bytes_and_oversized_buffer():
    with pytest.raises(P.ProtocolError, match="expected bytes"):
        P.decode("a string")  # type: ignore[arg-type]
    with pytest.raises(P.ProtocolError, match="exceeds"):
        P.decode(b"\x80" + bytes(P.MAX_MESSAGE_BYTES))


def test_every_truncation_of_a_frame_is_rejected():
    data = P.encode(_frame(h=2, w=3))
    for n in range(len(data)):
        with pytest.raises(P.ProtocolError):
            P.decode(data[:n])


def test_encode_validates_too():
    f = _frame()
    f.depth = f.depth[:-1]
    with pytest.raises(P.ProtocolError, match="does not match rgb"):
        P.encode(f)
    with pytest.raises(P.ProtocolError, match="not a protocol message"):
        P.encode({"schema": "Frame"})  # type: ignore[arg-type]


def test_frame_from_dataset_frame_cleans_depth():
    from fmapping.camera import PinholeCamera
    from fmapping.datasets.base import Frame as DsFrame

    cam = PinholeCamera(10, 10, 3.5, 2.5, 8, 6)
    depth = np.ones((6, 8), np.float32)
    depth[0, 0], depth[1, 1] = np.nan, -2.0
    f = P.frame_from_dataset(DsFrame(4, 0.5, np.zeros((6, 8, 3), np.uint8), cam, depth, np.eye(4)))
    back = P.decode(P.encode(f))
    assert back.depth[0, 0] == 0 and back.depth[1, 1] == 0 and back.depth[2, 2] == 1
    assert P.camera_of(back) == cam


def test_pose_keyframe_flag_round_trips_defaults_to_false_and_must_be_a_bool():
    p = P.Pose(seq=3, timestamp=0.1, c2w=np.eye(4), source="tracker", quality=0.5, keyframe=True)
    assert P.decode(P.encode(p)).keyframe is True
    raw = msgpack.unpackb(P.encode(p), raw=False)
    del raw["keyframe"]  # a producer of before the flag
    assert P.decode(msgpack.packb(raw, use_bin_type=True)).keyframe is False
    raw["keyframe"] = 1
    with pytest.raises(P.ProtocolError, match="keyframe"):
        P.decode(msgpack.packb(raw, use_bin_type=True))
    assert P.decode(P.encode(P.Control("refine", {"iters": 5}))).command == "refine"
