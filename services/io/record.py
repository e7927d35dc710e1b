"""``io record``: write the trajectories and the latest map points to disk.

Keeps every Pose it hears (per source, latest per frame number) and the newest
PointsSnapshot. On the end-of-sequence stop it waits (``--final-timeout``) until the
services in ``--wait-done`` report state ``done`` (so the mapper's final map is in),
then writes and exits; on any other stop, SIGINT or SIGTERM it writes what it has.

Outputs in ``--out``: ``traj.txt`` (TUM, the ``--source`` poses), ``traj_<source>.txt``
for every source seen, ``points.ply`` (the latest map points) and ``record.json``.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping import protocol as P
from fmapping.ply import write_ply
from fmapping.trajectory import write_tum_trajectory  # imports torch: at start-up, not at the end
from services.common import (Peers, Service, add_common_args, names, serve_until_end, service_parser, setup_logging,
                             stop_kind, write_json_atomic)


def add_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--source", default="tracker", help="pose source written as traj.txt (tracker | gt | external | ...)")
    p.add_argument("--wait-done", default="mapper", help="services whose 'done' status ends the recording at the end of a sequence")
    p.add_argument("--final-timeout", type=float, default=120.0)
    p.add_argument("--max-poses", type=int, default=1_000_000, help="per source")
    return add_common_args(p)


class Recorder:
    """Zenoh-free state of the recorder: feed it decoded messages, then :meth:`write`."""

    def __init__(self, out, source: str = "tracker", max_poses: int = 1_000_000):
        self.out = Path(out)
        self.source = source
        self.max_poses = max_poses
        self.poses: dict[str, dict[int, tuple[float, np.ndarray]]] = {}
        self.points: Optional[P.PointsSnapshot] = None

    def on_pose(self, pose: P.Pose) -> None:
        d = self.poses.setdefault(pose.source, {})
        if len(d) >= self.max_poses and pose.seq not in d:
            d.pop(next(iter(d)))
        d[pose.seq] = (pose.timestamp, np.array(pose.c2w))

    def on_points(self, snap: P.PointsSnapshot) -> None:
        if self.points is None or snap.version >= self.points.version:
            self.points = snap

    def write(self) -> dict:
        self.out.mkdir(parents=True, exist_ok=True)
        summary: dict = {"poses": {}, "points": 0, "files": []}
        for src, d in sorted(self.poses.items()):
            if not d:
                continue
            seqs = sorted(d)
            ts = np.array([d[s][0] for s in seqs])
            c2w = np.stack([d[s][1] for s in seqs])
            path = write_tum_trajectory(self.out / f"traj_{src}.txt", ts, c2w)
            summary["files"].append(str(path))
            summary["poses"][src] = len(seqs)
            if src == self.source:
                summary["files"].append(str(write_tum_trajectory(self.out / "traj.txt", ts, c2w)))
        if self.points is not None and len(self.points.points):
            path = write_ply(self.out / "points.ply", self.points.points, self.points.colors)
            summary["files"].append(str(path))
            summary["points"] = int(len(self.points.points))
            summary["points_version"] = int(self.points.version)
        write_json_atomic(self.out / "record.json", summary)
        return summary


def handle_message(svc: Service, rec: Recorder, peers: Peers, channel: str, key: str, data: bytes,
                   wait_done=()) -> Optional[str]:
    """Decode and apply one payload of ``channel`` (poses | points | status | control); a bad one is
    counted (``decode_errors``, ``bad_input``) and changes nothing. Returns 'end' or 'stop' when the
    recording should finish."""
    if channel == "poses":
        msg = svc.decode(data, P.Pose, key)
        if msg is not None:
            rec.on_pose(msg)
            svc.counters.inc(f"poses_{msg.source}")
            svc.status.update(frame_seq=msg.seq)
    elif channel == "points":
        msg = svc.decode(data, P.PointsSnapshot, key)
        if msg is not None:
            rec.on_points(msg)
            svc.counters.set("points", len(msg.points))
    elif channel == "status":
        msg = svc.decode(data, P.Status, key)
        if msg is not None:
            peers.update(msg)
    elif channel == "control":
        msg = svc.control(data, key)
        if msg is not None:
            if msg.command == "save":
                rec.write()
            return stop_kind(msg, wait_done)
    return None


def run(svc: Service, args) -> int:
    rec = Recorder(args.out, args.source, args.max_poses)
    peers = Peers()
    wait_done = names(args.wait_done)
    svc.subscribe(svc.keys.poses(), "poses")
    svc.subscribe(svc.keys.points, "points")
    svc.subscribe(svc.keys.status(), "status")
    svc.subscribe(svc.keys.control, "control")
    svc.start()
    serve_until_end(svc, peers, lambda ch, key, data: handle_message(svc, rec, peers, ch, key, data, wait_done),
                    wait_done, args.final_timeout)
    summary = rec.write()
    svc.log.info("wrote %s", ", ".join(summary["files"]) or "nothing (no poses, no points)")
    return 0


def main(argv=None, session=None, keys=None) -> int:
    args = add_args(service_parser("services.io record", __doc__)).parse_args(argv)
    setup_logging(args.log_level, "record")
    with Service("record", args, capacities={"control": 64, "status": 256, "poses": 100_000, "points": 2},
                 session=session, keys=keys) as svc:
        return run(svc, args)
