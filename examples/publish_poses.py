"""Stream a TUM trajectory file as ``Pose(source="external")`` messages in sync with ``io play``.

Any pose producer (ORB-SLAM, kiss-icp, a motion-capture system, ...) can drive the mapper
this way: run the mapper with ``--poses external`` and publish, for every frame, a Pose
with that frame's ``seq`` on ``fmapping/<ns>/poses/external``. This script does it from a
file: it listens to ``fmapping/<ns>/frames`` and answers each frame with the trajectory
pose nearest in time (within ``--max-dt`` seconds). A frame without a pose gets
``quality = 0`` (the mapper skips it instead of waiting). It publishes its status under
the name of the pose source, ``fmapping/<ns>/status/external`` (``fmapping up --poses
external`` makes play wait for a service called ``external``; with TLS access control the
producer's certificate must be allowed to put ``poses/external`` and ``status/external``),
and stops on the end-of-sequence control.

    python examples/publish_poses.py --traj traj.txt --connect tcp/127.0.0.1:7447 --ns myrun

The Pose message (see ``fmapping/protocol.py``): ``seq`` (frame number), ``timestamp``
(seconds), ``c2w`` (4x4 float64 camera-to-world, metres, OpenCV camera axes: x right,
y down, z forward), ``source`` ("external"), optional ``covariance`` (6x6) and ``quality``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fmapping import protocol as P  # noqa: E402
from fmapping.trajectory import associate, read_tum_trajectory  # noqa: E402


class PoseFeeder:
    """Zenoh-free: the pose (or an unusable placeholder) to publish for each frame."""

    def __init__(self, timestamps: np.ndarray, c2w: np.ndarray, max_dt: float = 0.02, source: str = "external"):
        self.ts, self.c2w = np.asarray(timestamps, np.float64), np.asarray(c2w)
        self.max_dt, self.source = max_dt, source
        self.matched = 0
        self.missing = 0

    def pose_for(self, frame_seq: int, frame_ts: float) -> P.Pose:
        j = int(associate(np.array([frame_ts]), self.ts, self.max_dt)[0])
        if j < 0:
            self.missing += 1
            last = self.c2w[0] if len(self.c2w) else np.eye(4)
            return P.Pose(seq=frame_seq, timestamp=frame_ts, c2w=np.array(last, np.float64), source=self.source,
                          quality=0.0)
        self.matched += 1
        return P.Pose(seq=frame_seq, timestamp=frame_ts, c2w=np.array(self.c2w[j], np.float64), source=self.source)


def status_name(source: str) -> str:
    """The service name this producer reports as: its pose source (status/<source> next to poses/<source>,
    the name ``fmapping up --poses external`` makes play wait for)."""
    P.Keys().poses(source)  # a valid key part, or ProtocolError
    return source


def main(argv=None) -> int:
    from services.process import setup_logging
    from services.transport import Service
    from services.zenoh_session import add_common_args

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--traj", required=True, help="TUM trajectory: timestamp tx ty tz qx qy qz qw")
    ap.add_argument("--max-dt", type=float, default=0.02, help="max |frame time - pose time| in seconds")
    ap.add_argument("--source", default="external",
                    help="pose source: poses on poses/<source>, status on status/<source> (the mapper's --poses)")
    args = add_common_args(ap).parse_args(argv)
    setup_logging(args.log_level, "external")
    ts, c2w = read_tum_trajectory(args.traj)
    feeder = PoseFeeder(ts, c2w, args.max_dt, args.source)
    svc = Service(status_name(args.source), args, capacities={"control": 16, "frames": 64})
    try:
        svc.subscribe(svc.keys.control, "control")
        svc.subscribe(svc.keys.frames, "frames")
        svc.status.update(state="running")
        svc.publish_status()
        svc.start_heartbeat()
        svc.log.info("%d poses from %s; answering frames on %s", len(ts), args.traj, svc.keys.frames)
        while not svc.shutdown.requested:
            item = svc.inbox.get(timeout=0.1)
            if item is None:
                continue
            channel, (key, data) = item
            if channel == "control":
                ctl = svc.decode(data, P.Control, key)
                if ctl is not None and ctl.command == "stop":
                    break
                continue
            frame = svc.decode(data, P.Frame, key)
            if frame is None:
                continue
            svc.publish(svc.keys.poses(args.source), feeder.pose_for(frame.seq, frame.timestamp))
            svc.counters.set("matched", feeder.matched)
            svc.counters.set("missing", feeder.missing)
            svc.status.update(frame_seq=frame.seq)
        svc.log.info("done: %d frames matched, %d without a pose", feeder.matched, feeder.missing)
        return 0
    finally:
        svc.close("done")


if __name__ == "__main__":
    sys.exit(main())
