"""A hostile (or buggy) peer against the service shells and cores, in-process: nothing a flood can
evict, messages checked before they are queued, payloads not trusted blindly.

The shells run on a fake session whose subscriptions the test calls directly, the way zenoh
calls them, so a flood of 10,000 messages is delivered deterministically and quickly.
"""
from __future__ import annotations

import argparse

import numpy as np
import pytest

from fakes import FakeSession
from fmapping import protocol as P
from service_helpers import feed, gt_messages, small_cfg
from services.core_support import MAX_SEQ_AHEAD, Inbox, snapshot_problem
from services.process import EXIT_STALLED
from services.transport import Service
from services.zenoh_session import add_common_args

KEYS = P.Keys("hostile")


def service(name: str, capacities: dict, max_bytes: dict = None, thin=()) -> tuple[Service, FakeSession]:
    s = FakeSession()
    args = add_common_args(argparse.ArgumentParser()).parse_args([])
    return Service(name, args, capacities=capacities, max_bytes=max_bytes, session=s, keys=KEYS,
                   install_signals=False, thin=thin), s


def drain(inbox: Inbox) -> list:
    out = []
    while (item := inbox.get(timeout=0)) is not None:
        out.append(item)
    return out


# ---------------------------------------------------------------------------- inbox bounds
@pytest.mark.parametrize("thin", [(), ("frames",)])
def test_inbox_is_bounded_in_bytes_as_well_as_items(thin):
    box = Inbox({"control": 4, "frames": 1000}, thin=thin, max_bytes={"frames": 10_000})
    for i in range(100):
        box.put("frames", (f"k{i}", bytes(3000)))
        assert box.nbytes("frames") <= 10_000 and box.size("frames") <= 3
    assert box.counters.get("dropped_frames") == 97
    # one item larger than the bound stays alone (never evicted by itself); other channels untouched
    box.put("control", b"stop")
    box.put("frames", ("big", bytes(50_000)))
    assert box.size("frames") == 1 and box.nbytes("frames") == 50_000 and box.size("control") == 1
    got = drain(box)
    assert got[0] == ("control", b"stop") and got[1][1][0] == "big" and box.nbytes() == 0


def test_flooded_controls_never_evict_the_end_of_sequence_stop():
    """The issue's run: 1,005 hostile controls pushed the real end-of-run stop out of the control
    queue. Stops now have their own queue, and undecodable ones are never queued."""
    svc, s = service("mapper", {"control": 64, "poses": 8192, "frames": 32})
    svc.subscribe_control()
    s.deliver(KEYS.control, P.encode(P.Control("stop", {"reason": "end", "last_seq": 13})))
    rng = np.random.default_rng(0)
    for i in range(10_000):
        kind = i % 3
        data = (rng.bytes(int(rng.integers(1, 200))) if kind == 0 else
                P.encode(P.Control("save")) if kind == 1 else P.encode(P.Control("pause", {"target": "tracker"})))
        s.deliver(KEYS.control, data)
    c = svc.counters.snapshot()
    assert c["decode_errors"] == 3334 and c["received_end"] == 1
    assert c["received_control"] == 3333 and c["dropped_control"] == 3333 - 64  # addressed to others: not queued
    first = svc.inbox.get(timeout=0)
    assert first[0] == "end" and first[1][1].command == "stop" and first[1][1].args["last_seq"] == 13


def test_hostile_frames_are_refused_before_queueing_and_never_displace_real_ones(dataset):
    """Undecodable frames, frames with an implausible number and frames far too large for the
    stream reach neither the inbox nor the core; the real frames all stay queued up to the inbox's ceiling."""
    from services.mapper.__main__ import CAPACITIES, MAX_BYTES
    from services.mapper.core import MapperCore

    svc, s = service("mapper", CAPACITIES, MAX_BYTES, thin=("frames",))
    core = MapperCore(small_cfg(), counters=svc.counters)
    svc.subscribe(KEYS.frames, "frames", admit=lambda k, d: core.admit("frames", d, k))
    svc.subscribe(KEYS.poses("gt"), "poses", admit=lambda k, d: core.admit("poses", d, k))
    real = [gt_messages(dataset, i % len(dataset)) for i in range(2)]
    pose, frame = real[0]
    s.deliver(KEYS.poses("gt"), pose)
    s.deliver(KEYS.frames, frame)
    core.took_frame(0)  # the worker took frame 0: the head of the stream
    ahead = P.frame_from_dataset(dataset[1], seq=10 ** 9)
    hostile = [b"\x00" * 100, P.encode(ahead), P.encode(P.Pose(seq=-1, timestamp=0.0, c2w=np.eye(4), source="gt")),
               P.encode(P.Pose(seq=10 ** 9, timestamp=0.0, c2w=np.eye(4), source="gt"))]
    for i in range(4000):
        s.deliver(KEYS.frames if i % 4 < 2 else KEYS.poses("gt"), hostile[i % 4])
    c = svc.counters.snapshot()
    assert c["decode_errors"] == 1000 and c["rejected_seq"] == 3000 and c["bad_input"] == 4000
    assert c.get("dropped_frames", 0) == 0 and svc.inbox.size("frames") == 1 and svc.inbox.size("poses") == 1
    cap = CAPACITIES["frames"]
    for i in range(1, cap + 1):
        f = P.frame_from_dataset(dataset[i % len(dataset)], seq=i)
        s.deliver(KEYS.frames, P.encode(f))
    assert svc.inbox.size("frames") == cap and svc.counters.get("dropped_frames") == 1  # one real frame too many


def test_mapper_core_refuses_implausible_frame_numbers_and_keeps_its_acknowledgement(dataset):
    from services.mapper.core import MapperCore

    core = MapperCore(small_cfg())
    feed(core, dataset, range(6))
    ack = core.ack
    assert ack == 5
    pose, frame = gt_messages(dataset, 6)
    far = P.frame_from_dataset(dataset[6], seq=ack + MAX_SEQ_AHEAD + 1)
    assert core.handle("frames", P.encode(far)) == []
    assert core.handle("poses", P.encode(P.Pose(seq=far.seq, timestamp=0.0, c2w=np.eye(4), source="gt"))) == []
    assert core.handle("poses", P.encode(P.Pose(seq=-1, timestamp=0.0, c2w=np.eye(4), source="gt"))) == []
    assert core.counters.get("rejected_seq") == 3 and core.ack == ack and far.seq not in core.frames
    feed(core, dataset, [6, 7])  # the real stream goes on
    assert core.ack == 7
    # a frame within reach of the stream is taken (a gap in the numbering is not an attack)
    near = P.frame_from_dataset(dataset[8], seq=ack + 1000)
    core.handle("frames", P.encode(near))
    assert near.seq in core.frames or core.ack == near.seq


def test_tracker_core_refuses_a_snapshot_version_that_cannot_be():
    from services.tracker.core import TrackerCore

    core = TrackerCore()
    forged = P.FieldSnapshot(version=10 ** 9, kind="cp", config={}, aabb=np.array([[0, 0, 0], [1, 1, 1]], np.float64),
                             arrays={}, frame_seq=5)
    assert core.handle("field", P.encode(forged)) == []
    assert core.counters.get("rejected_snapshots") == 1 and core.version == 0 and "cannot follow" in core.last_error
    assert snapshot_problem(7, 5, 3, 10) == "" and snapshot_problem(2, 5, 3, 10) != ""
    assert snapshot_problem(7, 5 + MAX_SEQ_AHEAD * 2, 3, 10) != ""


def test_recorder_ignores_unplayed_and_negative_poses_and_implausible_points(tmp_path):
    from fmapping.trajectory import read_tum_trajectory
    from services.io.record import Recorder

    rec = Recorder(tmp_path, source="tracker")
    for s in range(10):
        assert rec.on_pose(P.Pose(seq=s, timestamp=float(s), c2w=np.eye(4), source="tracker"))
    rec.on_played(7, end=True)  # the end-of-sequence stop: frames 0..7 were played
    assert not rec.on_pose(P.Pose(seq=-1, timestamp=0.0, c2w=np.eye(4), source="tracker"))  # the ATE 12.67 cm
    assert not rec.on_pose(P.Pose(seq=7 + MAX_SEQ_AHEAD + 1, timestamp=0.0, c2w=np.eye(4), source="tracker"))
    pts = np.zeros((4, 3), np.float32)
    cols = np.zeros((4, 3), np.uint8)
    assert rec.on_points(P.PointsSnapshot(version=3, points=pts, colors=cols, frame_seq=7))
    assert not rec.on_points(P.PointsSnapshot(version=10 ** 9, points=pts[:1], colors=cols[:1], frame_seq=7))
    assert not rec.on_points(P.PointsSnapshot(version=2, points=pts[:1], colors=cols[:1], frame_seq=7))
    assert rec.on_points(P.PointsSnapshot(version=4, points=pts[:2], colors=cols[:2], frame_seq=9))
    summary = rec.write()
    ts, _ = read_tum_trajectory(tmp_path / "traj.txt")
    assert list(ts) == list(range(8)) and summary["unplayed_poses"] == 2  # frames 8, 9 were never played
    assert summary["points"] == 2 and summary["rejected"] == {"rejected_poses": 2, "rejected_points": 2}


# ---------------------------------------------------------------------------- every wait has a timeout
def test_play_gives_up_when_a_live_consumer_stops_acknowledging(dataset):
    """The issue's run: the mapper's acknowledgement stuck at 185 of 200 while its heartbeat went
    on, and play waited forever. Now play names the consumer and the frame, still sends the
    end-of-sequence stop (the consumers write their outputs) and exits with code 3."""
    import threading
    import time

    from services.io import play

    s = FakeSession()
    args = play.add_args(argparse.ArgumentParser()).parse_args(
        ["--data", "x", "--window", "2", "--stall-timeout", "1.0", "--start-timeout", "5"])
    svc = Service("play", args, session=s, keys=KEYS, install_signals=False)
    player = play.Player(svc, dataset, args)
    stop = threading.Event()

    def mapper_beats():  # alive, but its acknowledgement stays at frame 1
        k = 0
        while not stop.wait(0.05):
            k += 1
            st = P.Status(service="mapper", seq=k, time=time.time(), frame_seq=1)
            s.deliver(KEYS.status("mapper"), P.encode(st), sub_key=KEYS.status())

    t = threading.Thread(target=mapper_beats, daemon=True)
    t.start()
    try:
        t0 = time.monotonic()
        assert player.run() == EXIT_STALLED
        assert time.monotonic() - t0 < 10
    finally:
        stop.set()
        t.join()
    assert player.seq == 3  # window 2 beyond the stuck acknowledgement
    assert "no acknowledgement from mapper beyond frame 1" in svc.status.last_error
    end = P.decode(s.published[KEYS.control][-1], P.Control)
    assert end.command == "stop" and end.args == {"reason": "end", "last_seq": 3}
    assert svc.counters.get("stalls") == 1


def test_mapper_without_any_frame_gives_up_with_its_outputs_written(tmp_path):
    from services.mapper.__main__ import main

    out = tmp_path / "m"
    code = main(["--poses", "gt", "--out", str(out), "--first-message-timeout", "0.5", "--status-interval", "0.1",
                 "--status-file", str(tmp_path / "status.json")], session=FakeSession(), keys=KEYS)
    assert code == EXIT_STALLED
    import json

    status = json.loads((tmp_path / "status.json").read_text())
    assert "no frame on fmapping/hostile/frames within 0.5 s" in status["last_error"]
    assert (out / "stats.json").is_file()


def test_record_without_any_pose_gives_up(tmp_path):
    from services.io import record

    args = record.add_args(argparse.ArgumentParser()).parse_args(
        ["--out", str(tmp_path / "r"), "--first-message-timeout", "0.3"])
    s = FakeSession()
    with Service("record", args, capacities={"control": 4, "status": 4, "poses": 4, "points": 2}, session=s,
                   keys=KEYS, install_signals=False) as svc:
        for _ in range(3):  # heartbeats of others are not what it waits for
            svc.inbox.put("status", (KEYS.status("mapper"), P.encode(P.Status(service="mapper"))))
        assert record.run(svc, args) == EXIT_STALLED
        assert "no pose on fmapping/hostile/poses/*" in svc.status.last_error
    assert (tmp_path / "r" / "record.json").is_file()


def test_recorder_without_the_end_stop_keeps_the_poses_a_late_status_may_not_show(tmp_path):
    """An interrupted run has no end stop, and play's last status may be half a second old: poses just
    beyond it are kept (STATUS_MARGIN), those far beyond are not."""
    from services.io.record import STATUS_MARGIN, Recorder

    rec = Recorder(tmp_path, source="gt")
    for s in (0, 5, 5 + STATUS_MARGIN, 6 + STATUS_MARGIN):
        rec.on_pose(P.Pose(seq=s, timestamp=float(s), c2w=np.eye(4), source="gt"))
    rec.on_played(5)
    assert rec.played_poses(rec.poses["gt"]) == [0, 5, 5 + STATUS_MARGIN]
