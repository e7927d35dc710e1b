"""``io record``: write the trajectories and the latest map points to disk.

Keeps every Pose it hears (per source, latest per frame number) and the newest
PointsSnapshot. It does not trust a peer blindly: a pose with a negative frame number or one
far beyond the frames played (``services.core_support.MAX_SEQ_AHEAD``) is refused at once, and poses
of frames that were never played (beyond the last frame of the end-of-sequence stop; without
that stop, as when the run is interrupted, beyond the newest frame play's status reported plus
``STATUS_MARGIN``, since a status is up to half a second old) are left out of the files
(``unplayed_poses``); a points snapshot
must follow the last one plausibly (``services.core_support.snapshot_problem``). On the end-of-sequence stop
it waits (``--final-timeout``) until the
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
from services.core_support import MIB, seq_problem, snapshot_problem
from services.process import FirstMessage, add_first_message_arg, service_parser, setup_logging
from services.transport import FINAL_TIMEOUT_HELP, Peers, Service, serve_until_end, stop_kind, write_json_atomic
from services.zenoh_session import add_common_args, names


def add_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--source", default="tracker",
                   help="pose source written as traj.txt (tracker | gt | external | ...)")
    p.add_argument("--wait-done", default="mapper",
                   help="services whose 'done' status ends the recording at the end of a sequence")
    p.add_argument("--final-timeout", type=float, default=120.0, help=FINAL_TIMEOUT_HELP)
    p.add_argument("--max-poses", type=int, default=1_000_000, help="per source")
    p.add_argument("--append", action="store_true",
                   help="keep the poses of the traj_<source>.txt files already in --out (a resumed run): the "
                        "files are written with them, the poses of this run replacing those of the same frames")
    add_first_message_arg(p, "pose")
    return add_common_args(p)


STATUS_MARGIN = 64  # frames play may have sent after its last status (0.5 s apart): 2 s at 30 fps


class Recorder:
    """Zenoh-free state of the recorder: feed it decoded messages, then :meth:`write`."""

    def __init__(self, out, source: str = "tracker", max_poses: int = 1_000_000, player: str = "play"):
        self.out = Path(out)
        self.source = source
        self.max_poses = max_poses
        self.player = player  # the service whose frames the poses belong to
        self.played = -1  # the newest frame number the player reported (-1: none seen, keep every pose)
        self.ended = False  # the end-of-sequence stop told the last frame exactly
        self.poses: dict[str, dict[int, tuple[float, np.ndarray]]] = {}
        self.points: Optional[P.PointsSnapshot] = None
        self.rejected: dict[str, int] = {}  # reason -> count
        self.unposed = 0  # answers without a pose (quality 0), not written
        self.last_rejection = ""
        self.earlier: dict[str, dict[float, np.ndarray]] = {}  # --append: source -> {timestamp: c2w} on disk

    def load_earlier(self) -> int:
        """--append: the poses of the trajectories an earlier part of the run wrote to ``out``
        (``traj_<source>.txt``); returns how many."""
        from fmapping.trajectory import read_tum_trajectory

        for path in sorted(self.out.glob("traj_*.txt")):
            ts, c2w = read_tum_trajectory(path)
            self.earlier[path.stem[len("traj_"):]] = {round(float(t), 6): np.asarray(p) for t, p in zip(ts, c2w)}
        return sum(len(d) for d in self.earlier.values())

    def _reject(self, counter: str, why: str) -> bool:
        self.rejected[counter] = self.rejected.get(counter, 0) + 1
        self.last_rejection = why
        return False

    def on_pose(self, pose: P.Pose) -> bool:
        """Keep ``pose`` unless its frame number is implausible; False (counted) when refused. An answer
        without a pose (``quality`` 0: a frame skipped or lost, its ``c2w`` meaningless) is not written:
        counted as ``unposed_answers``, and a usable pose the frame had stays."""
        why = seq_problem(pose, self.played)
        if why:
            return self._reject("rejected_poses", why)
        if pose.quality is not None and not pose.quality > 0:
            self.unposed += 1
            return True
        d = self.poses.setdefault(pose.source, {})
        if len(d) >= self.max_poses and pose.seq not in d:
            d.pop(next(iter(d)))
        d[pose.seq] = (pose.timestamp, np.array(pose.c2w))
        return True

    def on_played(self, seq: int, end: bool = False) -> None:
        """The player has sent frames up to ``seq`` (its status; ``end``: the end-of-sequence stop's last_seq)."""
        self.played = max(self.played, int(seq))
        self.ended = self.ended or end

    def on_points(self, snap: P.PointsSnapshot) -> bool:
        current = -1 if self.points is None else self.points.version
        why = snapshot_problem(snap.version, snap.frame_seq, current, self.played)
        if why:
            return self._reject("rejected_points", f"points v{snap.version}: {why}")
        self.points = snap
        return True

    def played_poses(self, d: dict) -> list[int]:
        """Frame numbers of ``d`` that were played (all of them while no player was heard)."""
        last = self.played if self.ended else self.played + STATUS_MARGIN
        return sorted(s for s in d if self.played < 0 or s <= last)

    def write(self) -> dict:
        self.out.mkdir(parents=True, exist_ok=True)
        summary: dict = {"poses": {}, "points": 0, "files": []}
        unplayed = 0
        for src in sorted(set(self.poses) | set(self.earlier)):
            d = self.poses.get(src, {})
            seqs = self.played_poses(d)
            unplayed += len(d) - len(seqs)
            merged = dict(self.earlier.get(src, {}))
            merged.update({round(float(d[s][0]), 6): d[s][1] for s in seqs})  # this run's pose of a frame wins
            if not merged:
                continue
            ts = np.array(sorted(merged))
            c2w = np.stack([merged[t] for t in ts])
            path = write_tum_trajectory(self.out / f"traj_{src}.txt", ts, c2w)
            summary["files"].append(str(path))
            summary["poses"][src] = len(merged)
            if src == self.source:
                summary["files"].append(str(write_tum_trajectory(self.out / "traj.txt", ts, c2w)))
        if self.points is not None and len(self.points.points):
            path = write_ply(self.out / "points.ply", self.points.points, self.points.colors)
            summary["files"].append(str(path))
            summary["points"] = int(len(self.points.points))
            summary["points_version"] = int(self.points.version)
        summary["unplayed_poses"] = unplayed
        summary["played"] = self.played
        summary["rejected"] = dict(self.rejected)
        summary["unposed_answers"] = self.unposed
        write_json_atomic(self.out / "record.json", summary)
        return summary


def handle_message(svc: Service, rec: Recorder, peers: Peers, channel: str, key: str, data: bytes,
                   wait_done=()) -> Optional[str]:
    """Decode and apply one payload of ``channel`` (poses | points | status | control); a bad one is
    counted (``decode_errors``, ``bad_input``) and changes nothing. Returns 'end' or 'stop' when the
    recording should finish."""
    if channel == "poses":
        msg = _decoded(svc, data, P.Pose, key)
        if msg is not None and _kept(svc, rec, rec.on_pose(msg)):
            svc.counters.inc(f"poses_{msg.source}")
            svc.counters.set("unposed_answers", rec.unposed)
            svc.status.update(frame_seq=msg.seq)
    elif channel == "points":
        msg = _decoded(svc, data, P.PointsSnapshot, key)
        if msg is not None and _kept(svc, rec, rec.on_points(msg)):
            svc.counters.set("points", len(msg.points))
    elif channel == "status":
        msg = _decoded(svc, data, P.Status, key)
        if msg is not None:
            peers.update(msg)
            if msg.service == rec.player:
                rec.on_played(msg.frame_seq)
    elif channel in ("end", "control"):
        msg = data if isinstance(data, P.Control) else svc.control(data, key)
        if msg is not None:
            if msg.command == "stop" and msg.args.get("reason") == "end":
                last = msg.args.get("last_seq")
                if isinstance(last, int) and not isinstance(last, bool):
                    rec.on_played(last, end=True)
            if msg.command == "save":
                rec.write()
            return stop_kind(msg, wait_done)
    return None


def _decoded(svc: Service, data, expect: type, key: str):
    """``data`` when the subscription decoded it already (``admit``), else its decoded message or None."""
    return data if isinstance(data, expect) else svc.decode(data, expect, key)


def _kept(svc: Service, rec: Recorder, kept: bool) -> bool:
    """Count and report a message the recorder refused (``bad_input`` and the reason's counter)."""
    if not kept:
        for name, n in rec.rejected.items():
            svc.counters.set(name, n)
        svc.counters.inc("bad_input")
        svc.report_bad_input(rec.last_rejection)
    return kept


def run(svc: Service, args) -> int:
    rec = Recorder(args.out, args.source, args.max_poses)
    if getattr(args, "append", False):
        svc.log.info("appending to the %d poses already in %s", rec.load_earlier(), args.out)
    peers = Peers()
    wait_done = names(args.wait_done)
    # decoded before queueing: a bad message is counted in the callback and never displaces a real one
    for key, channel, expect in ((svc.keys.poses(), "poses", P.Pose), (svc.keys.points, "points", P.PointsSnapshot),
                                 (svc.keys.status(), "status", P.Status)):
        svc.subscribe(key, channel, admit=lambda k, d, expect=expect: svc.decode(d, expect, k))
    svc.subscribe_control()
    svc.start()
    first = FirstMessage(getattr(args, "first_message_timeout", 0), f"pose on {svc.keys.poses()}")
    code = serve_until_end(svc, peers, lambda ch, key, data: handle_message(svc, rec, peers, ch, key, data, wait_done),
                           wait_done, args.final_timeout, first=first, data_channels=("poses",))
    summary = rec.write()
    svc.log.info("wrote %s", ", ".join(summary["files"]) or "nothing (no poses, no points)")
    return code


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m services.io record``."""
    return add_args(service_parser("services.io record", __doc__))


def main(argv=None, session=None, keys=None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, "record")
    # bounded in items and bytes: ~102 MiB at most (the stop queue "end" comes first, see services.transport)
    with Service("record", args, capacities={"end": 8, "control": 64, "status": 256, "poses": 100_000, "points": 2},
                 max_bytes={"end": MIB, "control": MIB, "status": 4 * MIB, "poses": 32 * MIB, "points": 64 * MIB},
                 session=session, keys=keys) as svc:
        return run(svc, args)
