"""Helpers shared by the service and wire tests (test_services.py, test_reliability.py,
test_protocol.py): raw message maps for spoiling payloads, a small mapper configuration,
feeding a service core, zenoh peer configs on loopback, a ground-truth frame producer,
threads, subprocess environments and the examples. The fixtures built on them are in conftest.py.

Importable as a plain module (``tests/`` is on ``sys.path`` under pytest, and the determinism
test puts it there for a fresh interpreter). zenoh is imported only by what needs it.
"""
from __future__ import annotations

import importlib
import os
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np

from fmapping import protocol as P
from services.zenoh_session import free_port

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------- wire level
def raw_message(msg: P.Message) -> dict:
    """The msgpack map of an encoded message (to spoil a field and :func:`pack` it again)."""
    return msgpack.unpackb(P.encode(msg), raw=False)


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def wire_array(a: np.ndarray) -> dict:
    """An array in the protocol's wire form."""
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


# ---------------------------------------------------------------------------- services

# a mapper that maps the 64x48 test scene in well under a second per update on one thread
SMALL_MAPPER = {
    "init_frames": 4, "init_rounds": [[0, 16], [3, 16]], "init_iters_per_round": 4,
    "window_size": 6, "n_global_keyframes": 2, "new_frames_per_window": 2, "iters_per_window": 2,
    "keyframe_every": 2, "rays_per_iter": 96, "init_rays_per_iter": 96, "n_coarse": 12, "n_fine": 4,
    "final_global_iters": 2,
    "device": "cpu", "seed": 0,
    "field": {"resolution": 12, "density_components": 4, "appearance_components": 4, "app_features": 8, "hidden": 8},
}


def small_cfg(**over):
    """MapperConfig of SMALL_MAPPER with top-level ``over`` rides."""
    from fmapping.config import merge
    from fmapping.mapping import MapperConfig

    return merge(MapperConfig(), dict(SMALL_MAPPER, **over))


def mapper_yaml(folder: Path, name: str = "m.yaml", **over) -> Path:
    """``folder/name``: SMALL_MAPPER with top-level ``over`` rides as a YAML file (``--config``)."""
    import yaml

    path = Path(folder) / name
    path.write_text(yaml.safe_dump(dict(SMALL_MAPPER, **over)))
    return path


def gt_messages(ds, i: int, source: str = "gt") -> tuple[bytes, bytes]:
    """Encoded (Pose, Frame) of dataset frame ``i`` as frame number ``i``, its GT pose as ``source``."""
    f = ds[i]
    return (P.encode(P.Pose(seq=i, timestamp=f.timestamp, c2w=f.c2w, source=source)),
            P.encode(P.frame_from_dataset(f, seq=i)))


def feed(core, ds, ids, source: str = "gt", pose_first: bool = True) -> list:
    """Hand frames ``ids`` of ``ds`` and their GT poses (as ``source``) to a service core;
    returns everything it output."""
    outs = []
    for i in ids:
        pose, frame = gt_messages(ds, i, source)
        for ch, data in ((("poses", pose), ("frames", frame)) if pose_first else (("frames", frame), ("poses", pose))):
            outs += core.handle(ch, data)
    return outs


def peer_conf(listen=None, connect=None):
    """A zenoh peer config on explicit endpoints, multicast scouting off."""
    from services.zenoh_session import zenoh_config

    return zenoh_config("peer", listen=listen or [], connect=connect or [], multicast=False)


def loopback_endpoint() -> str:
    """``tcp/127.0.0.1:<a free port>``."""
    return f"tcp/127.0.0.1:{free_port()}"


def wait_matching(*pubs, timeout: float = 60.0, what: str = "subscriber") -> None:
    """Poll until every publisher has a matching subscriber (fails after ``timeout``)."""
    end = time.monotonic() + timeout
    while not all(p.matching_status.matching for p in pubs):
        assert time.monotonic() < end, f"{what} never matched"
        time.sleep(0.01)


class GtProducer:
    """The test as a frame + GT pose source on ``session`` (blocking publishers)."""

    def __init__(self, session, keys: P.Keys, dataset):
        import zenoh

        block = zenoh.CongestionControl.BLOCK
        self.ds = dataset
        self.pf = session.declare_publisher(keys.frames, congestion_control=block)
        self.pp = session.declare_publisher(keys.poses("gt"), congestion_control=block)
        self.pc = session.declare_publisher(keys.control, congestion_control=block)

    def wait_matched(self, timeout: float = 60.0) -> None:
        wait_matching(self.pf, self.pp, timeout=timeout, what="frames / poses subscriber")

    def send(self, i: int) -> None:
        pose, frame = gt_messages(self.ds, i)
        self.pp.put(pose)
        self.pf.put(frame)


def start_thread(target, *args, **kw) -> tuple[threading.Thread, list]:
    """Run ``target(*args, **kw)`` in a daemon thread; returns it and the list that collects what it raised."""
    errors: list = []

    def run():
        try:
            target(*args, **kw)
        except BaseException as e:  # noqa: BLE001 - surfaced by the test
            errors.append(e)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, errors


def subprocess_env() -> dict:
    """The environment of a service subprocess: the repository first on PYTHONPATH, unbuffered output."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def import_example(name: str):
    """Import ``examples/<name>.py`` as a module."""
    sys.path.insert(0, str(ROOT / "examples"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.pop(0)
