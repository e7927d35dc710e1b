"""Reliability (issue 6, "Faults and load"): fuzzed input to every service core and through
zenoh, overload with bounded queues and flat memory, kill -9 and restart of the mapper and the
tracker, SIGTERM / SIGINT shutdown of every service, CPU determinism.

Numbers these tests measure are printed (``pytest -s``) and summarised in docs/reliability.md.
Every wait is a poll of a file / status / queue against a deadline, never a bare sleep.
"""
from __future__ import annotations

import collections
import dataclasses
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

zenoh = pytest.importorskip("zenoh")

from fmapping import protocol as P  # noqa: E402
from fuzz_helpers import (N_FUZZ, Fuzzer, decode_level, frame_semantics, fuzz_handler, io_service,  # noqa: E402
                          mapper_state, report_fuzz, run_fuzz, snapshot_semantics, tracker_state)
from reliability_helpers import TIMEOUT, Producer, StatusWatch, Svc, map_digest, rss_kb  # noqa: E402
from service_helpers import (ROOT, GtProducer, feed, import_example, loopback_endpoint, mapper_yaml,  # noqa: E402
                             peer_conf, small_cfg, start_thread, subprocess_env, wait_matching)
from services.transport import Peers  # noqa: E402
from services.zenoh_session import payload_bytes, query_latest  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")  # scene, dataset, zpair: conftest.py


# ============================================================================ 1. fuzz: service cores
@pytest.fixture(scope="module")
def mapped(dataset):
    """A MapperCore with a map (init + one window over frames 0..5) and frame 6 waiting for its pose."""
    from services.mapper.core import MapperCore, MapperServiceOptions

    core = MapperCore(small_cfg(), MapperServiceOptions(pose_source="gt", points_interval=1e9, checkpoint_every=0))
    feed(core, dataset, range(6))
    core.handle("frames", P.encode(P.frame_from_dataset(dataset[6], seq=6)))
    assert core.mapper.initialized and core.ack == 5 and list(core.frames) == [6] and core.version == 2
    return core


def test_fuzz_mapper_core_10k_malformed_messages(mapped, dataset):
    core = mapped
    base_frame = P.decode(P.encode(P.frame_from_dataset(dataset[7], seq=7)))
    bases = {"frames": base_frame, "poses": P.Pose(seq=7, timestamp=dataset.timestamps[7], c2w=dataset[7].c2w,
                                                   source="gt", covariance=np.eye(6) * 1e-4, quality=0.9),
             "control": P.Control("pause", {"reason": "test", "n": [1, 2.5]})}
    fz = Fuzzer(1234, bases, semantic={"frames": frame_semantics(base_frame)})
    stream = fz.stream(N_FUZZ, ["frames", "poses", "control"])
    before, c0 = mapper_state(core), core.counters.snapshot()
    cats, secs = run_fuzz(lambda ch, data: core.handle(ch, data, key=f"fuzz/{ch}"), stream)
    c1 = core.counters.snapshot()
    assert mapper_state(core) == before  # compared exactly: field bytes, poses, queues, versions
    delta = {k: c1.get(k, 0) - c0.get(k, 0) for k in set(c1) | set(c0) if c1.get(k, 0) != c0.get(k, 0)}
    n_decode = sum(v for k, v in cats.items() if decode_level(k))
    assert delta.get("bad_input") == N_FUZZ, delta
    assert delta.get("decode_errors") == n_decode and delta.get("rejected_frames") == N_FUZZ - n_decode, delta
    assert set(delta) == {"bad_input", "decode_errors", "rejected_frames"}, delta  # nothing else moved
    assert len(cats) >= 25, cats
    report_fuzz("MapperCore.handle", cats, secs)
    # and it still works: the waiting frame 6 gets its pose, 7 completes a window
    outs = feed(core, dataset, [6, 7])
    assert core.ack == 7 and any(ch == "field" for ch, _ in outs)


def test_fuzz_tracker_core_10k_malformed_messages(mapped, dataset):
    from services.tracker.core import TrackerCore, TrackerServiceOptions

    snap = P.decode(mapped.latest_field_bytes, P.FieldSnapshot)
    core = TrackerCore(opts=TrackerServiceOptions(frontend="map", use_depth=True))  # references from the sensor depth
    core.handle("frames", P.encode(P.frame_from_dataset(dataset[snap.frame_seq], seq=snap.frame_seq)))
    core.handle("field", mapped.latest_field_bytes)
    for p in mapped.window_poses():
        core.handle("poses", P.encode(p))
    first = snap.frame_seq + 1
    for i in range(first, first + 3):
        core.handle("frames", P.encode(P.frame_from_dataset(dataset[i], seq=i)))
    assert core.ack == first + 2 and core.field is not None and core.tracker.reference is not None
    versions = iter(range(snap.version + 1, 10 ** 9))
    base_frame = P.decode(P.encode(P.frame_from_dataset(dataset[first + 3], seq=first + 3)))
    bases = {"frames": base_frame, "field": dataclasses.replace(snap, version=snap.version + 1),
             "poses": P.Pose(seq=first + 3, timestamp=0.5, c2w=dataset[first + 3].c2w, source="mapper"),
             "control": P.Control("reset", {"target": "tracker"})}
    fz = Fuzzer(4321, bases, semantic={"frames": frame_semantics(base_frame),
                                       "field": snapshot_semantics(snap, lambda: next(versions))})
    stream = fz.stream(N_FUZZ, ["frames", "field", "poses", "control"])
    before, c0 = tracker_state(core), core.counters.snapshot()
    cats, secs = run_fuzz(lambda ch, data: core.handle(ch, data, key=f"fuzz/{ch}"), stream)
    c1 = core.counters.snapshot()
    assert tracker_state(core) == before
    delta = {k: c1.get(k, 0) - c0.get(k, 0) for k in set(c1) | set(c0) if c1.get(k, 0) != c0.get(k, 0)}
    n_decode = sum(v for k, v in cats.items() if decode_level(k))
    n_snap = sum(v for k, v in cats.items() if k.startswith("snapshot_"))
    assert delta.get("bad_input") == N_FUZZ, delta
    assert delta.get("decode_errors") == n_decode and delta.get("rejected_snapshots") == n_snap, delta
    assert delta.get("rejected_frames") == N_FUZZ - n_decode - n_snap, delta
    assert set(delta) == {"bad_input", "decode_errors", "rejected_frames", "rejected_snapshots"}, delta
    report_fuzz("TrackerCore.handle", cats, secs)
    # still tracking
    outs = core.handle("frames", P.encode(P.frame_from_dataset(dataset[first + 3], seq=first + 3)))
    assert [m.seq for _, m in outs] == [first + 3] and core.ack == first + 3



def test_fuzz_io_handlers_10k_malformed_messages_each(mapped, dataset, tmp_path):
    """io record, io view and io play decode what they hear in their handlers: 10,000 bad
    payloads each are all counted (decode_errors = bad_input = sent) and change nothing."""
    import rerun as rr

    from services.io import play, record, view

    frame = P.decode(P.encode(P.frame_from_dataset(dataset[3], seq=3)))
    snap = P.decode(mapped.latest_field_bytes, P.FieldSnapshot)
    bases = {"frames": frame, "poses": P.Pose(seq=3, timestamp=0.1, c2w=dataset[3].c2w, source="tracker",
                                              quality=0.5),
             "points": P.PointsSnapshot(version=2,
                                        points=np.random.default_rng(0).normal(size=(40, 3)).astype(np.float32),
                                        colors=np.full((40, 3), 9, np.uint8), frame_seq=3),
             "field": snap,
             "status": P.Status(service="mapper", seq=4, time=1.0e9, state="running", frame_seq=3, lag=0.1,
                                counters={"frames_processed": 4, "last_window_s": 0.25}, last_error="none"),
             "control": P.Control("save", {"target": "all"})}

    # io record: a Recorder with some poses and points already
    svc, _ = io_service("record", ["--out", str(tmp_path / "rec")], record.add_args)
    rec, peers = record.Recorder(tmp_path / "rec"), Peers()
    for i in range(3):
        record.handle_message(svc, rec, peers, "poses", "k", P.encode(P.Pose(seq=i, timestamp=float(i), c2w=np.eye(4),
                                                                           source="tracker")))
    record.handle_message(svc, rec, peers, "points", "k", P.encode(bases["points"]))

    def rec_state():
        return ({s: {k: (t, c.tobytes()) for k, (t, c) in d.items()} for s, d in rec.poses.items()},
                rec.points.version, rec.points.points.tobytes(), peers.services())

    fuzz_handler("io record handle_message", svc, rec_state,
                  lambda ch, d: record.handle_message(svc, rec, peers, ch, "fuzz", d, ["mapper"]), 11, bases,
                  ["poses", "points", "status", "control"])
    assert not (tmp_path / "rec" / "record.json").exists()

    # io view: a Viewer on a recording stream without a sink
    svc, _ = io_service("view", ["--save", str(tmp_path / "x.rrd")], view.add_args)
    stream_rr = rr.RecordingStream("fuzz")
    viewer, peers = view.Viewer(stream_rr), Peers()
    for ch in ("frames", "poses", "points", "field", "status"):
        view.handle_message(svc, viewer, peers, ch, "k", P.encode(bases[ch]))
    assert svc.counters.get("log_errors") == 0 and viewer.frames == 1

    def view_state():
        return ({s: [p.tobytes() for p in v] for s, v in viewer.traj.items()}, viewer.frames, viewer._camera,
                peers.services(), svc.counters.get("log_errors"), sorted(k for k in svc.counters.snapshot()
                                                                         if k.startswith("logged_")),
                {k: svc.counters.get(k) for k in svc.counters.snapshot() if k.startswith("logged_")})

    fuzz_handler("io view handle_message", svc, view_state,
                  lambda ch, d: view.handle_message(svc, viewer, peers, ch, "fuzz", d, ["mapper"]), 12, bases,
                  ["frames", "poses", "points", "field", "status", "control"])

    # io play: its status and control callbacks (flow control, pause / stop / reset)
    svc, args = io_service("play", ["--data", "unused"], play.add_args)
    player = play.Player(svc, dataset, args)
    player._on_status("k", P.encode(bases["status"]))

    def play_state():
        return (player.peers.services(), player.peers.acked("mapper"), dict(player.floor), player.paused.is_set(),
                player.stop_requested.is_set(), player.reset_requested.is_set())

    handlers = {"status": player._on_status, "control": player._on_control}
    fuzz_handler("io play status/control callbacks", svc, play_state, lambda ch, d: handlers[ch]("fuzz", d), 13,
                  bases, ["status", "control"])


# ============================================================================ 1b. fuzz through zenoh

def test_fuzz_500_malformed_messages_through_zenoh_to_a_running_mapper(dataset, tmp_path, zpair):
    """The zenoh shell of the mapper (a real service, in-process peer) survives 500 bad payloads on
    frames / poses / control, counts every one in its published Status, and its map is untouched
    (the map/latest answer is byte-identical before and after); then it maps on."""
    from services.mapper.__main__ import main as mapper_main

    a, b, _ = zpair
    keys = P.Keys("fz")
    cfg = mapper_yaml(tmp_path)
    watch = StatusWatch(b, keys.status("mapper"))
    thread, errors = start_thread(mapper_main, ["--poses", "gt", "--config", str(cfg), "--points-interval", "1000",
                                                "--checkpoint-every", "0", "--status-interval", "0.1"],
                                  session=a, keys=keys)
    watch.wait(lambda s: s.state == "running", what="mapper up")
    prod = GtProducer(b, keys, dataset)
    pubs = {"frames": prod.pf, "poses": prod.pp, "control": prod.pc}
    wait_matching(*pubs.values(), timeout=TIMEOUT, what="mapper subscriptions")

    def send_valid(ids):
        for i in ids:
            prod.send(i)

    send_valid(range(6))  # init (4 frames) + one window
    st = watch.wait(lambda s: s.frame_seq == 5 and s.counters.get("windows") == 2, what="first map")
    latest = query_latest(b, keys.latest, timeout=TIMEOUT)
    assert latest is not None and P.decode(latest, P.FieldSnapshot).version == 2
    c0 = st.counters

    base_frame = P.decode(P.encode(P.frame_from_dataset(dataset[6], seq=6)))
    fz = Fuzzer(99, {"frames": base_frame, "poses": P.Pose(seq=6, timestamp=0.2, c2w=dataset[6].c2w, source="gt"),
                     "control": P.Control("pause")}, semantic={"frames": frame_semantics(base_frame)})
    stream = fz.stream(500, ["frames", "poses", "control"])
    sent = collections.Counter()
    t0 = time.perf_counter()
    for k in range(0, len(stream), 25):  # bursts within the inbox capacity (32 frames): nothing is dropped
        for ch, _, data in stream[k:k + 25]:
            pubs[ch].put(data)
            sent[ch] += 1
        n = k + len(stream[k:k + 25])
        watch.wait(lambda s: s.counters.get("bad_input", 0) - c0.get("bad_input", 0) >= n, what=f"{n} counted")
    secs = time.perf_counter() - t0
    st = watch.wait(lambda s: s.counters.get("bad_input", 0) - c0.get("bad_input", 0) >= 500)
    c1 = st.counters
    delta = {k: c1.get(k, 0) - c0.get(k, 0) for k in ("bad_input", "decode_errors", "rejected_frames",
                                                       "received_frames", "received_poses", "received_control",
                                                       "dropped_frames", "dropped_poses", "errors", "windows",
                                                       "frames_processed")}
    cats = collections.Counter(c for _, c, _ in stream)
    n_decode = sum(v for k, v in cats.items() if decode_level(k))
    assert delta["bad_input"] == 500 and delta["decode_errors"] == n_decode, delta
    assert delta["rejected_frames"] == 500 - n_decode, delta
    # checked before queueing: what fails to decode never enters the inbox (it cannot displace a real
    # frame); only the decodable frames of another camera are queued, and the core refuses them
    assert (delta["received_frames"], delta["received_poses"], delta["received_control"]) == \
        (500 - n_decode, 0, 0), (delta, sent)
    assert delta["dropped_frames"] == delta["errors"] == delta["windows"] == delta["frames_processed"] == 0, delta
    assert st.frame_seq == 5 and thread.is_alive()
    assert query_latest(b, keys.latest, timeout=TIMEOUT) == latest  # the map did not change by a bit
    print(f"\n[fuzz/zenoh] 500 payloads ({dict(sent)}) in {secs:.2f} s; status counted bad_input "
          f"{delta['bad_input']} (decode_errors {delta['decode_errors']}, rejected_frames "
          f"{delta['rejected_frames']}), dropped 0, errors 0")
    # it maps on: frames 6, 7 complete the next window
    send_valid([6, 7])
    watch.wait(lambda s: s.frame_seq == 7 and s.counters.get("windows") == 3, what="next window")
    pubs["control"].put(P.encode(P.Control("stop", {"reason": "end", "last_seq": 7})))
    thread.join(timeout=TIMEOUT)
    assert not thread.is_alive() and not errors
    watch.sub.undeclare()


# ============================================================================ 2. overload
OVERLOAD_FPS = 50.0  # the mapper below does ~4-8 frames/s on one thread here: playback ~10x faster
# The mapper's inbox is set to 64 frames (--inbox-frames; 8 MB of these frames): it is full within ~2 s, before
# the warm-up ends. With the default 512 frames it took ~12 s, and the test 32 s to outgrow it.
OVERLOAD_INBOX = 64
OVERLOAD_SECONDS = 20.0  # long enough that an unbounded queue would outgrow the bound (~50 MB here)
WARMUP_SECONDS = 6.0


@pytest.mark.slow
def test_overload_playback_faster_than_the_mapper_drops_frames_and_rss_stays_flat(tmp_path):
    """``io play --fps 50 --loop`` (no flow control) into a mapper that maps a few frames/s:
    most frames are not mapped (the mapper's bounded inbox drops them, or the mapper, behind,
    skips non-keyframes: both counted), every frame received is accounted for (dropped +
    consumed + still queued), and the mapper's RSS stays within its documented ceiling after
    warm-up (it levels off once the inbox is full) while an unbounded queue would outgrow it."""
    from fmapping.synthetic import generate_scene
    from services.mapper.__main__ import MAX_BYTES

    scene = tmp_path / "scene"
    generate_scene(scene, seed=3, frames=16, size=(160, 120), max_cloud_points=2000, mesh_spacing=0.2)
    frame_bytes = 160 * 120 * 3 + 160 * 120 * 4  # rgb uint8 + depth float32 per Frame message
    cfg = mapper_yaml(tmp_path, iters_per_window=20)
    ep_m, ep_p = loopback_endpoint(), loopback_endpoint()
    mapper = Svc("mapper", ["services.mapper", "--poses", "gt", "--config", str(cfg), "--out", str(tmp_path / "out"),
                            "--threads", "1", "--no-mesh", "--points-interval", "2",
                            "--inbox-frames", str(OVERLOAD_INBOX)], tmp_path, ep_m, interval=0.25)
    play = None
    try:
        mapper.wait_for(lambda s: s.get("state") == "running", 120, "mapper up")
        play = Svc("play", ["services.io", "play", "--data", str(scene), "--fps", str(OVERLOAD_FPS), "--loop",
                            "--ack-from=", "--wait-for", "mapper", "--no-end-stop"], tmp_path, ep_p, [ep_m],
                   interval=0.25)
        mapper.wait_for(lambda s: s["counters"].get("windows", 0) >= 1, 120, "first mapping update")
        t0 = time.monotonic()
        samples = []  # (t, rss kB, mapper counters, play counters)
        tick = threading.Event()
        while time.monotonic() - t0 < OVERLOAD_SECONDS:
            assert mapper.popen.poll() is None and play.popen.poll() is None, mapper.log()[-2000:] + play.log()[-2000:]
            samples.append((time.monotonic() - t0, rss_kb(mapper.pid), mapper.counters(), play.counters()))
            tick.wait(1.0)  # the sampling period (not a synchronisation)
        rc_play, _ = play.stop(signal.SIGINT)
        end = play.counters()
        rc_map, took = mapper.stop(signal.SIGTERM)
        final = mapper.status()
    finally:
        for s in (play, mapper):
            if s is not None:
                s.kill()
    assert rc_play == 0 and rc_map == 0, mapper.log()[-3000:]
    c = final["counters"]
    sent = int(end.get("frames_sent", 0))
    received, dropped = int(c.get("received_frames", 0)), int(c.get("dropped_frames", 0))
    consumed, processed = int(c.get("frames_received", 0)), int(c.get("frames_processed", 0))
    queued = int(c.get("queued_frames", 0))
    # every frame is accounted for: zenoh delivered them all, the inbox dropped or passed each
    assert received == sent, (received, sent)
    assert received == dropped + consumed + queued + int(c.get("rejected_frames", 0)) + \
        int(c.get("stale_frames", 0)), c
    thinned = int(c.get("frames_thinned", 0))
    # at most one frame waits for its pose
    assert consumed - processed - int(c.get("frames_without_pose", 0)) - thinned <= 1, c
    assert queued <= OVERLOAD_INBOX  # the inbox capacity
    # overloaded: most frames were not mapped (the mapper maps a few frames/s; measured 185-225 of 1,014-1,015:
    # 676-742 evicted from the full inbox, 23-48 skipped behind, 64 still queued at the stop): the inbox overflowed
    assert processed < 0.5 * sent and dropped > 0, (sent, processed, dropped, thinned, queued)
    # memory: flat after warm-up
    warm = [s for s in samples if s[0] >= WARMUP_SECONDS]
    assert len(warm) >= 8, samples
    base = warm[0][1]
    growth_mb = (max(s[1] for s in warm) - base) / 1024
    not_mapped_after = (sent - processed) - (int(warm[0][3].get("frames_sent", 0))
                                             - int(warm[0][2].get("frames_processed", 0)))
    offered_mb = not_mapped_after * frame_bytes / 2 ** 20  # what an unbounded queue would have kept
    # justified bound: the mapper keeps every keyframe's image + depth (keyframe_every = 2) and
    # one checkpoint / snapshot in flight; its inbox fills up to its ceiling (CAPACITIES frames, the
    # mapper's keyframe-keeping intake); 24 MB for allocator and zenoh buffer slack
    processed_after = processed - int(warm[0][2].get("frames_processed", 0))
    inbox_mb = min(OVERLOAD_INBOX * frame_bytes, MAX_BYTES["frames"]) / 2 ** 20
    bound_mb = 24 + processed_after / 2 * frame_bytes / 2 ** 20 * 2 + inbox_mb
    print(f"\n[overload] {OVERLOAD_SECONDS:.0f} s at {OVERLOAD_FPS:.0f} fps: play sent {sent}, "
          f"mapper received {received}, "
          f"dropped {dropped} (inbox), consumed {consumed}, skipped behind {thinned}, mapped {processed} "
          f"({processed / OVERLOAD_SECONDS:.1f} fps), still queued {queued}, windows {c.get('windows')}; "
          f"stop took {took:.2f} s")
    print("[overload] mapper RSS MB by second: " + ", ".join(f"{t:.0f}:{r / 1024:.0f}" for t, r, _, _ in samples))
    print(f"[overload] growth after {WARMUP_SECONDS:.0f} s warm-up {growth_mb:.1f} MB (bound {bound_mb:.1f} MB); "
          f"an unbounded queue would have held {offered_mb:.0f} MB more")
    # and the bound tells: with an unbounded queue the growth would have been offered_mb more than it was (a fast
    # machine maps more frames, which raises the bound and lowers offered_mb: 62.1 against 60.4 + 12.4 MB once)
    assert growth_mb < bound_mb < growth_mb + offered_mb, (growth_mb, bound_mb, offered_mb)


# ============================================================================ 3. crash and restart

def test_checkpoint_write_is_atomic_when_the_process_dies_mid_write(dataset, tmp_path, monkeypatch):
    """A crash while the next checkpoint is being written (here: torch.save raising half-way)
    leaves the previous checkpoint intact and loadable; the temp file is never the checkpoint."""
    from services.mapper.core import MapperCore, MapperServiceOptions

    opts = dict(pose_source="gt", out=str(tmp_path), points_interval=1e9, checkpoint_every=1)
    core = MapperCore(small_cfg(), MapperServiceOptions(**opts))
    feed(core, dataset, range(6))  # init + 1 window: 2 checkpoints
    ck = tmp_path / "checkpoint.pt"
    good = ck.read_bytes()
    real_save = torch.save

    def dying_save(obj, fh, *a, **kw):
        real_save(obj, fh, *a, **kw)
        fh.truncate(fh.tell() // 2)  # half the bytes are on disk when the process "dies"
        raise KeyboardInterrupt("killed mid-write")

    monkeypatch.setattr(torch, "save", dying_save)
    with pytest.raises(KeyboardInterrupt):
        feed(core, dataset, range(6, 8))  # the next window's checkpoint dies half-way
    monkeypatch.setattr(torch, "save", real_save)
    assert ck.read_bytes() == good  # untouched: the half-written bytes went to the temp file only
    leftovers = list(tmp_path.glob(".checkpoint.pt.*.tmp"))
    assert len(leftovers) == 1 and leftovers[0].stat().st_size < len(good)
    fresh = MapperCore(small_cfg(), MapperServiceOptions(**opts))
    assert fresh.load_checkpoint() and (fresh.windows, fresh.ack) == (2, 5)


def _field_of_checkpoint(path: Path) -> dict:
    """A mapper checkpoint as the service loads it (weights_only: no pickle of arbitrary objects)."""
    from services.mapper.core import read_checkpoint

    return read_checkpoint(path)


@pytest.mark.slow
def test_mapper_kill9_resumes_from_the_last_checkpoint_losing_at_most_one_window(dataset, tmp_path):
    """kill -9 of a mapper process busy in its third update; restarted with the same --out it
    resumes from the checkpoint of the second (the one in progress is the only loss), maps the
    rest, and its final map is bit-identical to an uninterrupted run (in-process reference)."""
    from services.mapper.core import MapperCore, MapperServiceOptions

    over = {"iters_per_window": 40}  # ~0.4 s updates: the kill lands inside one
    cfg = mapper_yaml(tmp_path, **over)
    out = tmp_path / "out"
    ep = loopback_endpoint()
    argv = ["services.mapper", "--poses", "gt", "--config", str(cfg), "--out", str(out), "--threads", "1", "--no-mesh",
            "--points-interval", "1000", "--keep-checkpoint"]
    keys = P.Keys("crash")
    session = zenoh.open(peer_conf(connect=[ep]))
    mapper = Svc("mapper", argv, tmp_path, ep, ns="crash", interval=0.1)
    restarted = None
    try:
        mapper.wait_for(lambda s: s.get("state") == "running", 120, "mapper up")
        prod = Producer(session, keys, dataset)
        prod.wait_matched()

        def busy_in_third_update(s):  # frame 7 arrived and triggered update 3; updates 1-2 checkpointed
            c = s.get("counters", {})
            return c.get("frames_received", 0) >= 8 and c.get("windows") == 2 and c.get("checkpoints") == 2 \
                and c.get("frames_processed") == 7

        st = prod.stream(mapper, range(14), in_flight=2, stop_when=busy_in_third_update)
        assert busy_in_third_update(st), st
        os.kill(mapper.pid, signal.SIGKILL)
        assert mapper.popen.wait(timeout=TIMEOUT) == -signal.SIGKILL
        ck = _field_of_checkpoint(out / "checkpoint.pt")
        assert ck["service"]["windows"] == 2 and ck["service"]["last_seq"] == 5
        print(f"\n[crash] killed (SIGKILL) while busy in update 3: status said windows {st['counters']['windows']}, "
              f"ack {st['frame_seq']}, frames received {st['counters']['frames_received']}; checkpoint on disk: "
              f"windows {ck['service']['windows']}, last frame {ck['service']['last_seq']}")

        restarted = Svc("mapper", argv, tmp_path, ep, ns="crash", interval=0.1)
        st2 = restarted.wait_for(lambda s: s.get("state") == "running" and s["counters"].get("resumes") == 1, 120,
                                 "resumed mapper up")
        c2 = st2["counters"]
        assert (c2["resumed_windows"], c2["resumed_at_seq"], st2["frame_seq"]) == (2, 5, 5), st2
        assert st["counters"]["windows"] - c2["resumed_windows"] <= 1  # at most one update lost
        assert "resumed from" in restarted.log()
        prod.wait_matched()
        prod.stream(restarted, range(st2["frame_seq"] + 1, 14), in_flight=2)  # the producer resends from the ack
        restarted.wait_for(lambda s: s.get("frame_seq") == 13, TIMEOUT, "all frames mapped")
        prod.pc.put(P.encode(P.Control("stop", {"reason": "end", "last_seq": 13})))
        rc = restarted.popen.wait(timeout=120)
        assert rc == 0, restarted.log()[-3000:]
    finally:
        session.close()
        for s in (mapper, restarted):
            if s is not None:
                s.kill()
    from fmapping.mapping.state_io import unpack_by_frame
    from fmapping.trajectory import read_tum_trajectory

    ts, c2w = read_tum_trajectory(out / "traj.txt")
    assert len(ts) == 14 and (out / "map.ply").is_file()
    final = _field_of_checkpoint(out / "checkpoint.pt")  # --keep-checkpoint: the final state
    # the uninterrupted reference, in this process
    ref = MapperCore(small_cfg(**over), MapperServiceOptions(pose_source="gt", points_interval=1e9,
                                                            checkpoint_every=0))
    feed(ref, dataset, range(14))
    ref.finish()
    assert final["service"]["windows"] == ref.windows
    ref_field = ref.mapper.field.state_dict()
    assert set(final["mapper"]["field"]) == set(ref_field)
    for k, v in ref_field.items():
        assert torch.equal(final["mapper"]["field"][k], v.detach().cpu()), k  # bit-identical
    ref_poses = ref.mapper.frame_poses()
    final_poses = unpack_by_frame(final["mapper"]["poses"])
    for i in range(14):  # exactly in the state; traj.txt is text (quaternions, ~1e-9 rounding)
        assert torch.equal(final_poses[i], torch.as_tensor(ref_poses[i])), i
    np.testing.assert_allclose(c2w, np.stack([ref_poses[i] for i in range(14)]), atol=1e-6)
    print(f"[crash] resumed at windows {c2['resumed_windows']} / frame {c2['resumed_at_seq']}; finished with "
          f"{len(ts)} frames, {final['service']['windows']} updates; final field bit-identical to an uninterrupted run")


@pytest.mark.slow
def test_restarted_tracker_process_resyncs_from_the_latest_snapshot_query(dataset, tmp_path):
    """A tracker process killed (-9) and started again while the mapper is idle gets the map only
    through the map/latest query: it reports the mapper's newest version at once, then answers
    the next frames (a first reference rendered from the map)."""
    cfg = mapper_yaml(tmp_path)
    ep_m, ep_t = loopback_endpoint(), loopback_endpoint()
    keys = P.Keys("trk")
    session = zenoh.open(peer_conf(connect=[ep_m]))
    tracked: "queue.Queue[P.Pose]" = queue.Queue()
    sub = session.declare_subscriber(keys.poses("tracker"), lambda s: tracked.put(P.decode(payload_bytes(s))))
    mapper = Svc("mapper", ["services.mapper", "--poses", "gt", "--config", str(cfg), "--threads", "1",
                            "--points-interval", "1000", "--checkpoint-every", "0"], tmp_path, ep_m, ns="trk")
    targv = ["services.tracker", "--frontend", "map", "--threads", "1", "--use-depth", "--query-timeout", "10"]
    tracker = Svc("tracker", targv, tmp_path, ep_t, [ep_m], ns="trk")
    again = None
    try:
        mapper.wait_for(lambda s: s.get("state") == "running", 120, "mapper up")
        tracker.wait_for(lambda s: s.get("state") == "running", 120, "tracker up")
        prod = Producer(session, keys, dataset)
        prod.wait_matched()
        prod.stream(mapper, range(8), in_flight=2)
        ms = mapper.wait_for(lambda s: s.get("frame_seq") == 7 and s["counters"].get("windows") == 3, TIMEOUT, "map")
        version = ms["counters"]["field_version"]
        tracker.wait_for(lambda s: s.get("frame_seq") == 7 and s["counters"].get("field_version") == version,
                         TIMEOUT, "tracker in sync")
        os.kill(tracker.pid, signal.SIGKILL)
        assert tracker.popen.wait(timeout=TIMEOUT) == -signal.SIGKILL
        t0 = time.monotonic()
        again = Svc("tracker", targv, tmp_path, ep_t, [ep_m], ns="trk")
        st = again.wait_for(lambda s: s["counters"].get("field_version") == version, 120, "resync by query")
        took = time.monotonic() - t0
        assert st["counters"].get("snapshots") == 1 and mapper.counters().get("field_version") == version
        assert mapper.counters().get("queries_answered", 0) >= 1
        assert f"synced to map version {version} (frame 7)" in again.log()
        while not tracked.empty():
            tracked.get_nowait()
        prod.send(8)
        prod.send(9)
        got = {}
        end = time.monotonic() + TIMEOUT
        while set(got) != {8, 9}:
            p = tracked.get(timeout=max(0.1, end - time.monotonic()))
            got[p.seq] = p
        c = again.wait_for(lambda s: s.get("frame_seq") == 9, TIMEOUT, "answers")["counters"]
        assert c.get("references_rendered", 0) + c.get("reference_failures", 0) >= 1, c
        print(f"\n[crash] tracker killed (-9) and restarted: synced to map version {version} by query "
              f"{took:.1f} s after the restart (process start included); answered frames 8, 9 "
              f"(quality {got[8].quality}, {got[9].quality})")
    finally:
        sub.undeclare()
        session.close()
        for s in (again, tracker, mapper):
            if s is not None:
                s.kill()


# ============================================================================ 4. shutdown
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_every_service_stops_within_5_seconds_on_a_signal_while_busy(scene, tmp_path, sig):
    """mapper, tracker, io play (looping), io record and io view, all busy on a live run, get the
    signal at the same moment: each exits with code 0 within 5 s; the mapper first writes its
    current map and trajectory, record its trajectories, view its recording.
    (test_services.py covers a SIGTERM inside a mapping update.)"""
    from fmapping.trajectory import read_tum_trajectory

    cfg = mapper_yaml(tmp_path)
    out = tmp_path / "out"
    eps: list = []

    def start(name, argv):
        ep = loopback_endpoint()
        s = Svc(name, argv, tmp_path, ep, list(eps), ns="sd")
        eps.append(ep)
        return s

    procs = {}
    try:
        procs["mapper"] = start("mapper", ["services.mapper", "--poses", "gt", "--config", str(cfg), "--out", str(out),
                                           "--threads", "1", "--points-interval", "1"])
        procs["tracker"] = start("tracker", ["services.tracker", "--frontend", "map", "--threads", "1", "--use-depth"])
        procs["record"] = start("record", ["services.io", "record", "--out", str(out / "record"), "--source", "gt"])
        procs["view"] = start("view", ["services.io", "view", "--save", str(out / "run.rrd")])
        procs["play"] = start("play", ["services.io", "play", "--data", str(scene), "--loop", "--ack-from", "mapper",
                                       "--wait-for", "mapper,tracker,record,view", "--start-timeout", "120"])
        # mapping under way and a live points snapshot made (what a stop inside an update writes as map.ply; the
        # windows of a backlog run in one go, so 3 windows alone did not always mean a snapshot)
        procs["mapper"].wait_for(lambda s: s["counters"].get("windows", 0) >= 3 and s["counters"].get("points", 0) > 0,
                                 180, "mapping under way")
        for name in ("tracker", "record", "view"):
            procs[name].wait_for(lambda s: s.get("frame_seq", -1) >= 0, TIMEOUT, f"{name} busy")
        before = {n: p.status() for n, p in procs.items()}
        t0 = time.monotonic()
        for p in procs.values():
            p.popen.send_signal(sig)
        took: dict = {}
        while len(took) < len(procs) and time.monotonic() - t0 < 30:
            for n, p in procs.items():
                if n not in took and p.popen.poll() is not None:
                    took[n] = time.monotonic() - t0
            time.sleep(0.01)
        rcs = {n: p.popen.poll() for n, p in procs.items()}
    finally:
        for p in procs.values():
            p.kill()
    logs = {n: p.log()[-1500:] for n, p in procs.items()}
    print(f"\n[shutdown] {sig.name} to all five at once: " + ", ".join(f"{n} {took.get(n, float('inf')):.2f} s"
                                                                    for n in procs))
    assert rcs == {n: 0 for n in procs}, (rcs, logs)
    assert max(took.values()) < 5.0, (took, logs)
    # what each wrote on the way out
    mapped = int(before["mapper"]["counters"]["frames_processed"])
    ts, _ = read_tum_trajectory(out / "traj.txt")
    assert len(ts) >= mapped, (len(ts), mapped)
    assert (out / "map.ply").is_file() and json.loads((out / "stats.json").read_text())["final"] is False
    assert json.loads(procs["mapper"].status_file.read_text())["state"] == "done"
    assert (out / "record" / "record.json").is_file() and (out / "record" / "traj.txt").is_file()
    assert (out / "run.rrd").stat().st_size > 1000


# ============================================================================ 5. determinism

def test_same_seed_input_and_config_give_the_same_map_on_cpu(scene):
    """Two runs in this process: identical field and poses, bit for bit."""
    a, b = map_digest(str(scene), 8), map_digest(str(scene), 8)
    print(f"\n[determinism] map digest: run 1 {a[:16]}, run 2 {b[:16]}")
    assert a == b


@pytest.mark.slow
def test_same_map_in_another_process(scene):
    """A fresh interpreter (same torch build, one thread) maps to the same bits as this process."""
    code = ("import sys; sys.path[:0] = [sys.argv[1], sys.argv[1] + '/tests']; import reliability_helpers as T; "
            "print(T.map_digest(sys.argv[2], 8))")
    r = subprocess.run([sys.executable, "-c", code, str(ROOT), str(scene)], cwd=ROOT, env=subprocess_env(),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    other, here = r.stdout.strip().splitlines()[-1], map_digest(str(scene), 8)
    print(f"\n[determinism] map digest: this process {here[:16]}, another process {other[:16]}")
    assert here == other


# ============================================================================ 6. external producer naming
def test_external_pose_producer_reports_the_status_name_the_launcher_waits_for(dataset, tmp_path, zpair):
    """examples/publish_poses.py over zenoh: status on status/external (what ``fmapping up --poses
    external`` makes play wait for) and poses on poses/external (what ``--poses external`` maps from)."""
    from services.launcher.commands import EXTERNAL_SOURCE, play_wait_for
    from fmapping.trajectory import write_tum_trajectory

    publish_poses = import_example("publish_poses")
    a, b, ep = zpair
    keys = P.Keys("ext")
    traj = tmp_path / "traj.txt"
    write_tum_trajectory(traj, np.asarray(dataset.timestamps), np.stack([dataset[i].c2w for i in range(len(dataset))]))
    watch = StatusWatch(a, keys.status(EXTERNAL_SOURCE))
    poses: "queue.Queue[P.Pose]" = queue.Queue()
    a.declare_subscriber(keys.poses("external"), lambda s: poses.put(P.decode(payload_bytes(s), P.Pose)))
    thread, errors = start_thread(publish_poses.main, ["--traj", str(traj), "--connect", ep, "--listen",
                                                       loopback_endpoint(), "--ns", "ext", "--status-interval", "0.1"])
    st = watch.wait(lambda s: s.state == "running", what="status/external")
    assert st.service == EXTERNAL_SOURCE and st.service in play_wait_for("external")
    assert play_wait_for("external", view=False) == ["mapper", "record", "external"]
    pub = a.declare_publisher(keys.frames, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_matching(pub, timeout=TIMEOUT)
    pub.put(P.encode(P.frame_from_dataset(dataset[4], seq=4)))
    p = poses.get(timeout=TIMEOUT)
    assert p.seq == 4 and p.source == "external" and p.quality is None
    np.testing.assert_allclose(p.c2w, dataset[4].c2w, atol=1e-6)
    a.declare_publisher(keys.control).put(P.encode(P.Control("stop", {"reason": "end", "last_seq": 4})))
    thread.join(timeout=TIMEOUT)
    assert not thread.is_alive() and not errors


# ============================================================================ fixes the fuzzing asked for
def test_a_first_frame_the_services_cannot_use_is_rejected_not_adopted(dataset):
    """The first frame fixes a service's camera. One the mapper / tracker cannot use (distortion
    coefficients, a principal point far outside the image) is counted and rejected, and the next
    good frame still starts the stream (before the fix it was adopted and every later frame failed)."""
    from services.mapper.core import MapperCore, MapperServiceOptions
    from services.tracker.core import TrackerCore

    good = P.frame_from_dataset(dataset[0], seq=0)
    distorted = dataclasses.replace(good, camera=dict(good.camera, dist=[0.1, 0.0, 0.0, 0.0]))
    far_pp = dataclasses.replace(good, camera=dict(good.camera, cx=40.0 * good.camera["width"]))
    for core in (MapperCore(small_cfg(), MapperServiceOptions(pose_source="gt", checkpoint_every=0)), TrackerCore()):
        bad = [distorted, far_pp]  # the mapper and the (default, mono) tracker model pinhole cameras
        for f in bad:
            assert core.handle("frames", P.encode(f)) == []
        assert core.camera_dict is None and core.counters.get("rejected_frames") == len(bad)
        assert core.counters.get("bad_input") == len(bad)
        core.handle("frames", P.encode(good))
        assert core.camera_dict == P.decode(P.encode(good)).camera


def test_min_field_elements_is_a_lower_bound_for_every_field_kind():
    """The tracker refuses a snapshot whose config needs more parameters than the snapshot carries
    (before building anything); for real fields of every kind the bound holds and is not loose."""
    from fmapping.field import FieldConfig, build_field, min_field_elements

    aabb = np.array([[-1.0, -1, -1], [1, 1, 1]])
    for kw in ({"kind": "cp", "resolution": 12, "density_components": 4, "appearance_components": 4},
               {"kind": "cp", "resolution": 64, "view_dependent": True},
               {"kind": "vm", "resolution": 16, "vm_density_components": 2, "vm_appearance_components": 3},
               {"kind": "grid", "grid_resolution": 12, "grid_features": 4},
               {"kind": "mlp", "mlp_width": 32, "mlp_layers": 3, "pe_freqs": 4}):
        cfg = FieldConfig(**kw)
        n = sum(v.numel() for v in build_field(cfg, aabb).state_dict().values())
        bound = min_field_elements(cfg)
        assert 0.5 * n <= bound <= n, (kw, bound, n)
