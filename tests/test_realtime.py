"""Real time without a real clock: the service cores driven in-process at 30 fps on a fake clock.

The player publishes frame k at k / 30 s whether the mapper is ready or not; the tracker answers at
once (its per-frame time is far below a frame's); a mapper update blocks the mapper for a fixed number
of fake seconds (init 1.0 s, a window 0.25 s), during which frames and poses pile up in the mapper's
bounded inbox (:mod:`services.mapper.intake`). No timing is measured: the same schedule runs on any
machine. Also the pieces: the ranked eviction order and the mapper's own keyframe rule.
"""
from __future__ import annotations

import numpy as np
import pytest

from fmapping import protocol as P
from service_helpers import small_cfg

FPS = 30.0
COST_S = {"init": 1.0, "window": 0.25, "final": 0.5}  # fake seconds one mapper update keeps the mapper busy


# ---------------------------------------------------------------------------- pieces
def test_ranked_inbox_evicts_non_keyframes_first_then_unknown_and_thins_evenly():
    from services.core_support import Inbox, ranked_victim
    from services.mapper.intake import KeyframeBook, frame_rank

    book = KeyframeBook(source_flags=True)
    inbox = Inbox({"frames": 6}, thin=("frames",), rank={"frames": frame_rank(book)})
    frame = lambda s: ("k", P.Pose(seq=s, timestamp=0.0, c2w=np.eye(4)))  # noqa: E731  (anything with .seq)
    for s in range(10):  # poses of 0..9 known: keyframes 0, 4, 8; 10.. unknown
        book.note(P.Pose(seq=s, timestamp=0.0, c2w=np.eye(4), source="tracker", keyframe=s % 4 == 0))
    for s in range(14):
        inbox.put("frames", frame(s))
    kept = []
    while (it := inbox.get(timeout=0)) is not None:
        kept.append(it[1][1].seq)
    # 14 in, 6 kept: the 7 non-keyframes went first, then one of the unknown 10..13; the keyframes stay
    assert {0, 4, 8} <= set(kept) and len(kept) == 6 and inbox.counters.get("dropped_frames") == 8
    assert inbox.counters.get("dropped_frames_rank2") == 0
    assert set(kept) - {0, 4, 8} <= {10, 11, 12, 13} and len(set(kept) & {10, 11, 12, 13}) == 3
    # within the lowest rank the evenly spread survive: its oldest and newest stay, the victim leaves the
    # smallest gap (the oldest of equals)
    assert ranked_victim([1, 2, 3, 7, 8], [1, 0, 0, 0, 2]) == (2, 0)
    assert ranked_victim([1, 2, 4, 5, 9], [0, 0, 0, 0, 0]) == (1, 0)  # 2 leaves gap 3 (1..4), 4 too: the older
    assert ranked_victim([1, 2, 3], [2, 2, 1]) == (2, 1)  # the new item itself when it is the least


def test_keyframe_book_motion_rule_for_sources_without_flags():
    from fmapping.geometry import se3_exp_np
    from services.mapper.intake import KeyframeBook

    book = KeyframeBook(source_flags=False, every=5, min_move_m=0.05, min_turn_deg=5.0)
    c2w, flags = np.eye(4), []
    for s in range(12):  # 1 cm per frame: every 5th frame by count; then a 6 cm jump at 12
        c2w = c2w @ se3_exp_np(np.array([0.01, 0, 0, 0, 0, 0]))
        flags.append(book.note(P.Pose(seq=s, timestamp=0.0, c2w=c2w, source="gt")))
    assert [s for s, f in enumerate(flags) if f] == [0, 5, 10]
    jump = c2w @ se3_exp_np(np.array([0.06, 0, 0, 0, 0, 0]))
    assert book.note(P.Pose(seq=12, timestamp=0.0, c2w=jump, source="gt"))
    turn = jump @ se3_exp_np(np.array([0, 0, 0, 0, np.radians(6.0), 0]))
    assert book.note(P.Pose(seq=13, timestamp=0.0, c2w=turn, source="gt"))
    assert not book.note(P.Pose(seq=14, timestamp=0.0, c2w=turn, source="gt", quality=0.0))  # unusable
    # a source that flags its own: the flag is taken as is
    src = KeyframeBook(source_flags=True)
    assert not src.note(P.Pose(seq=0, timestamp=0.0, c2w=np.eye(4), source="tracker"))
    assert src.note(P.Pose(seq=1, timestamp=0.0, c2w=np.eye(4), source="tracker", keyframe=True))


# ---------------------------------------------------------------------------- 30 fps on a fake clock
def _tracker_stream(ds) -> tuple[list[bytes], list[list[bytes]]]:
    """The frames as the player sends them and, per frame, the poses the mono tracker core publishes
    when it has handled that frame (the last list also holds what it releases at the end)."""
    from services.tracker.core import TrackerCore

    core = TrackerCore()
    frames, poses = [], []
    for k in range(len(ds)):
        fb = P.encode(P.frame_from_dataset(ds[k], seq=k, with_depth=False))
        frames.append(fb)
        poses.append([P.encode(m) for ch, m in core.handle("frames", fb) if ch == "poses"])
    poses[-1] += [P.encode(m) for ch, m in core.apply(P.Control("stop", {"reason": "end"})) if ch == "poses"]
    return frames, poses


def _run_mapper_at_30fps(frames, poses, capacity: int, ranked: bool, cost: dict = COST_S, **opts_kw):
    """The mapper's shell loop on a fake clock (see the module docstring); returns the core after the
    end of the stream (its closing stage run) and the fake time it finished. The core's ``stream_idle``
    is the fake time since the newest frame was published; frames it thinned while the stream was idle
    (``stream_idle_s``) are counted as ``thinned_while_idle``."""
    from services.core_support import Counters, Inbox
    from services.mapper.core import MapperCore, MapperServiceOptions
    from services.mapper.intake import book_for, frame_rank

    now = [0.0]
    opts = MapperServiceOptions(pose_source="tracker", points_interval=1e9, checkpoint_every=0, pose_timeout=0,
                                **opts_kw)
    book = book_for(opts.validate())
    counters = Counters()  # shared by the inbox and the core, as in the service
    inbox = Inbox({"poses": 8192, "frames": capacity}, counters, thin=("frames",),
                  rank={"frames": frame_rank(book)} if ranked else None)
    core = MapperCore(small_cfg(final_global_iters=4), opts, counters=counters, book=book, clock=lambda: now[0])
    core.backlog = lambda: inbox.size("frames")
    n, k = len(frames), 0
    core.stream_idle = lambda: now[0] - (k - 1) / FPS
    while True:
        while k < n and k / FPS <= now[0]:  # everything published while the mapper was busy
            for pb in poses[k]:
                msg = core.admit_pose(pb, "poses/tracker")
                if msg is not None:
                    inbox.put("poses", ("poses/tracker", msg))
            inbox.put("frames", ("frames", core.admit("frames", frames[k])))
            k += 1
        item = inbox.get(timeout=0)
        if item is None:
            if k == n:
                break  # the player saw the last acknowledgement: the end-of-sequence stop comes
            now[0] = k / FPS  # idle until the next frame
            continue
        before = {kind: core.counters.get(f"updates_{kind}") for kind in cost}
        thinned, idle = core.counters.get("frames_thinned"), core.stream_idle() >= opts.stream_idle_s
        core.apply(item[1][1])
        if idle and core.counters.get("frames_thinned") > thinned:
            core.counters.inc("thinned_while_idle")
        now[0] += sum(cost[kd] for kd in cost if core.counters.get(f"updates_{kd}") > before[kd])
    core.apply(P.Control("stop", {"reason": "end"}))
    return core, now[0]


@pytest.mark.slow
def test_mapper_core_at_30fps_integrates_every_keyframe_and_runs_the_closing_refinement(room320):
    """40 frames at 30 fps (1.3 s) against a mapper whose init alone takes 1 s: frames pile up behind it.
    With the keyframe-ranked inbox (12 frames) every frame the tracker flagged as a keyframe is mapped, the
    mapper catches up by skipping non-keyframes, and the end-of-stream refinement runs once. The same
    schedule with the plain evenly thinned inbox loses keyframes (the test can fail)."""
    from fmapping.datasets import open_dataset

    ds = open_dataset(room320)
    frames, poses = _tracker_stream(ds)
    first: dict[int, P.Pose] = {}
    for ps in poses:
        for pb in ps:
            m = P.decode(pb)
            first.setdefault(m.seq, m)
    keyframes = {s for s, m in first.items() if m.keyframe and m.quality > 0}
    assert len(first) == len(ds) and 5 <= len(keyframes) < len(ds) // 2, sorted(keyframes)

    core, t_end = _run_mapper_at_30fps(frames, poses, capacity=12, ranked=True)
    mapped = set(core.seq_of_fid)
    assert keyframes <= mapped, sorted(keyframes - mapped)
    c = core.counters
    assert c.get("keyframes_integrated") == len(keyframes)
    assert c.get("updates_final") == 1 and core.finished  # the closing refinement over the keyframes
    # ... which also spends the window iterations catching up skipped (a paced run's 1 per frame after the init),
    # owed_iters_factor global iterations for each
    cfg = core.cfg
    after_init = len(ds) - 1 - core.init_seq
    windows = c.get("updates_window")
    owed = after_init * cfg.iters_per_window / cfg.new_frames_per_window - windows * cfg.iters_per_window
    f = cfg.owed_iters_factor
    assert f > 1 and c.get("closing_extra_iters") > 0
    assert abs(c.get("closing_extra_iters") - f * owed) <= f * cfg.iters_per_window
    assert core.mapper.stats()["iterations"] >= cfg.final_global_iters + c.get("closing_extra_iters")
    assert c.get("frames_thinned") > 0 and c.get("dropped_frames") > 0  # it really was behind
    assert c.get("dropped_frames_rank2") == 0
    assert core.ack == len(ds) - 1 and not core.frames
    assert t_end > len(ds) / FPS  # the stream ended while the mapper still had work

    plain, _ = _run_mapper_at_30fps(frames, poses, capacity=12, ranked=False)
    assert keyframes - set(plain.seq_of_fid), "the plain inbox kept every keyframe too: the scenario is too easy"

    # once no frame has come for stream_idle_s (the stream ended) the mapper stops skipping non-keyframes:
    # every posed frame it still holds is mapped, in deferred windows. An init of 2 s outlasts the stream.
    slow = {**COST_S, "init": 2.0}
    busy, _ = _run_mapper_at_30fps(frames, poses, capacity=40, ranked=True, cost=slow, stream_idle_s=1e9)
    idle, _ = _run_mapper_at_30fps(frames, poses, capacity=40, ranked=True, cost=slow, stream_idle_s=0.1)
    assert busy.counters.get("frames_thinned") > 0 and busy.counters.get("thinned_while_idle") == 0
    assert idle.counters.get("frames_thinned") == idle.counters.get("thinned_while_idle") == 0
    usable = {s for s, m in first.items() if m.quality > 0}
    assert set(idle.seq_of_fid) == usable and set(busy.seq_of_fid) < usable  # every posed frame mapped
    assert idle.counters.get("updates_final") == 1 and idle.ack == len(ds) - 1


def test_tracker_core_behind_the_camera_skips_every_other_frame_at_most_and_keeps_tracking(room320):
    """A tracker that always finds a newer frame waiting (it tracks slower than the camera) skips frames: never
    two in a row, so every gap is one frame; the frames it tracks keep their accuracy (Sim3 ATE against the
    GT; measured 0.31 cm, 0.25 cm with every frame tracked) and its keyframes are among them. A skipped frame's
    answer comes with the next frame's, just before it: the pose between its neighbours' (``interpolate_skipped``;
    measured 0.42 cm median, 0.76 cm max from the GT after the tracked frames' Sim3, which leaves those 0.26 /
    0.68 cm); without that, at once with quality 0."""
    from fmapping.datasets import open_dataset
    from fmapping.metrics import ate, umeyama
    from services.tracker.core import TrackerCore, TrackerServiceOptions

    ds = open_dataset(room320)
    for interpolate in (True, False):
        core = TrackerCore(opts=TrackerServiceOptions(interpolate_skipped=interpolate))
        core.backlog = lambda: 1
        first: dict[int, P.Pose] = {}
        answered_with: dict[int, int] = {}  # frame -> the frame whose handling answered it
        order = []
        for k in range(len(ds)):
            for _, m in core.handle("frames", P.encode(P.frame_from_dataset(ds[k], seq=k, with_depth=False))):
                if m.seq not in first:
                    first[m.seq], answered_with[m.seq] = m, k
                    order.append(m.seq)
        for _, m in core.apply(P.Control("stop", {"reason": "end"})):
            if m.seq not in first:
                first[m.seq], answered_with[m.seq] = m, len(ds)
                order.append(m.seq)
        assert order == list(range(len(ds)))  # every frame answered once, in order
        held = answered_with[0]  # the bootstrap and the late anchor hold the first frames' poses until then
        skipped = [s for s in first if s > held and answered_with[s] != s] if interpolate else \
            [s for s, m in first.items() if m.quality == 0]
        assert core.counters.get("frames_skipped_behind") == len(skipped) >= 10
        assert not any(b - a == 1 for a, b in zip(skipped, skipped[1:])), skipped
        assert core.counters.get("frames_lost") == 0
        tracked = [s for s in first if s not in skipped]
        assert all(first[s].quality > 0 for s in tracked)
        assert {s for s, m in first.items() if m.keyframe} <= set(tracked)
        r = ate(np.stack([first[s].c2w for s in tracked]), np.stack([ds[s].c2w for s in tracked]), "sim3")
        assert r["rmse_m"] < 0.01, r
        if not interpolate:
            assert core.counters.get("frames_interpolated") in (None, 0)
            continue
        inner = [s for s in skipped if s + 1 < len(ds)]  # the last frame, if skipped, has no successor ...
        assert all(answered_with[s] == s + 1 and first[s].quality > 0 for s in inner)
        assert all(first[s].quality == 0 for s in skipped if s not in inner)  # ... and no pose at the stop
        assert core.counters.get("frames_interpolated") == len(inner)
        s_, rot, t = umeyama(np.stack([first[s].c2w[:3, 3] for s in tracked]),
                             np.stack([ds[s].c2w[:3, 3] for s in tracked]), with_scale=True)
        err = [np.linalg.norm(s_ * rot @ first[s].c2w[:3, 3] + t - ds[s].c2w[:3, 3]) for s in inner]
        assert max(err) < 0.01, err
    # the same backlog after the stream has gone quiet (no frame for stream_idle_s): nothing to keep pace
    # with, every frame waiting is tracked
    quiet = TrackerCore()
    quiet.backlog, quiet.stream_idle = (lambda: 1), (lambda: quiet.opts.stream_idle_s + 1.0)
    answers = [m for k in range(len(ds))
               for _, m in quiet.handle("frames", P.encode(P.frame_from_dataset(ds[k], seq=k, with_depth=False)))]
    assert quiet.counters.get("frames_skipped_behind") == 0 and all(m.quality > 0 for m in answers)
    assert {m.seq for m in answers} == set(range(len(ds)))


def test_the_tracker_service_at_a_cameras_rate_poses_frames_from_their_tracks(room320):
    """The tracker service's CLI runs ``--frame-pose pnp`` unless told otherwise (the launcher says ``direct``
    for paced playback): its front end then poses frames from their KLT-tracked landmarks and aligns only those
    that fail. Through the service core every frame is answered, nearly all tracked frames come from PnP, and
    the poses stay within 1 cm of the GT after a Sim3 (measured 0.26 cm)."""
    from fmapping.datasets import open_dataset
    from fmapping.metrics import ate
    from services.tracker.__main__ import build_parser
    from services.tracker.core import TrackerCore, TrackerServiceOptions

    assert build_parser().parse_args([]).frame_pose == "pnp"
    with pytest.raises(ValueError, match="frame_pose"):
        TrackerServiceOptions(frame_pose="icp").validate()
    ds = open_dataset(room320)
    core = TrackerCore(opts=TrackerServiceOptions(frame_pose="pnp"))
    got = {m.seq: m for k in range(len(ds))
           for _, m in core.handle("frames", P.encode(P.frame_from_dataset(ds[k], seq=k, with_depth=False)))}
    got.update({m.seq: m for _, m in core.apply(P.Control("stop", {"reason": "end"}))})
    fe = core.session.frontend
    assert fe.cfg.frame_pose == "pnp" and sorted(got) == list(range(len(ds)))
    tracked = core.counters.get("frames_tracked")
    assert fe.frames_pnp >= 0.7 * tracked, (fe.frames_pnp, tracked)
    assert core.counters.get("frames_posed_by_pnp") == fe.frames_pnp  # in the service's status
    ks = sorted(k for k, m in got.items() if m.quality > 0)
    assert ate(np.stack([got[k].c2w for k in ks]), np.stack([ds[k].c2w for k in ks]), "sim3")["rmse_m"] < 0.01


def test_fmapping_up_paced_playback_neither_skips_nor_thins_and_fixed_rate_does(scene, tmp_path, monkeypatch):
    """Paced playback (``--fps 0``: the player waits for the mapper) asks the tracker to track every frame
    (``--skip-behind 0``) with its bundle adjustment on the frame path (``--ba-thread off``) and every frame
    aligned photometrically first (``--frame-pose direct``), as ``fmapping slam``, and the mapper to map every
    frame (``--behind-frames 0``); at a fixed rate all keep their real-time defaults."""
    from fakes import fake_up
    from services.cli import main

    for fps, paced in (("0", True), ("30", False)):
        started = fake_up(monkeypatch)
        assert main(["up", "--data", str(scene), "--poses", "tracker", "--fps", fps, "--view", "save", "--insecure",
                     "--out", str(tmp_path / f"up{fps}")]) == 0
        tracker, mapper = started["tracker"], started["mapper"]
        assert ("--skip-behind" in tracker and tracker[tracker.index("--skip-behind") + 1] == "0") == paced
        assert ("--ba-thread" in tracker and tracker[tracker.index("--ba-thread") + 1] == "off") == paced
        assert ("--frame-pose" in tracker and tracker[tracker.index("--frame-pose") + 1] == "direct") == paced
        assert ("--behind-frames" in mapper and mapper[mapper.index("--behind-frames") + 1] == "0") == paced


def test_mapper_core_refines_on_request_and_goes_on(dataset):
    """``Control(refine)``: the global refinement over the keyframes now; frames still come and the end of
    the stream still runs its own. A refine before the map exists, or with a bad iteration count, does
    nothing (the latter counted as bad input)."""
    from service_helpers import feed
    from services.mapper.core import MapperCore, MapperServiceOptions

    core = MapperCore(small_cfg(), MapperServiceOptions(pose_source="gt", points_interval=1e9, checkpoint_every=0))
    assert core.apply(P.Control("refine")) == [] and core.counters.get("refinements") == 0
    feed(core, dataset, range(8))
    it = core.mapper.stats()["iterations"]
    out = core.apply(P.Control("refine", {"iters": 3}))
    assert core.counters.get("refinements") == 1 and [c for c, _ in out].count("field") == 1
    assert core.mapper.stats()["iterations"] == it + 3 and not core.finished
    assert core.apply(P.Control("refine", {"iters": -1})) == [] and core.counters.get("rejected_controls") == 1
    feed(core, dataset, range(8, 12))
    assert core.ack == 11
    core.apply(P.Control("stop", {"reason": "end"}))
    assert core.finished and core.counters.get("updates_final") == 2  # the one asked for and the closing one


def test_mapper_core_keeps_the_bootstrap_frame_while_the_tracker_holds_its_pose(dataset):
    """The mono tracker holds its bootstrap's poses until the late anchor; at a camera's rate more than
    ``max_pending`` frames come meanwhile. The waiting frames are thinned evenly, frames known not to be
    keyframes first, and the oldest stays: the bootstrap's first frame, a keyframe, is mapped when its pose
    comes (it used to be dropped as the oldest, so the map lost its first keyframe)."""
    from services.mapper.core import MapperCore, MapperServiceOptions

    opts = MapperServiceOptions(pose_source="tracker", points_interval=1e9, checkpoint_every=0, pose_timeout=0,
                                max_pending=4)
    core = MapperCore(small_cfg(), opts)
    pose = lambda k, kf: P.Pose(seq=k, timestamp=float(k), c2w=dataset[k].c2w, source="tracker",  # noqa: E731
                                keyframe=kf)
    core.apply(pose(9, False))  # a later frame's pose before the held ones: it goes first when over the bound
    held = []
    for k in range(12):  # frames 0..11 come, no pose for 0..8 yet
        core.apply(P.frame_from_dataset(dataset[k], seq=k, with_depth=False))
        held.append(len(core.frames))
    assert max(held) == opts.max_pending and 9 not in core.frames and 0 in core.frames
    kept = sorted(core.frames)
    assert kept[0] == 0 and kept[-1] == 11 and core.counters.get("frames_without_pose") == 12 - 4
    assert core.ack < 0 and core.mapper is None  # nothing consumed: the first frame still waits
    for k in range(9):  # the bootstrap's poses, released at once: 0 is a keyframe
        core.apply(pose(k, k == 0))
    core.apply(pose(10, True))
    core.apply(pose(11, False))
    assert core.seq_of_fid == kept and core.counters.get("keyframes_integrated") == 1 + (10 in kept)
    core.apply(P.Control("stop", {"reason": "end"}))
    assert core.finished and core.ack == 11


def test_the_mapper_takes_the_sources_final_poses_before_its_closing_stage(room320):
    """At the stop the tracker still sends its last poses: a bundle adjustment merged at the end moves frames the
    mapper has integrated. ``await_source_final`` takes them (and frames queued behind the stop) until the tracker
    reports done, so that the closing stage maps on them; a source that never says done is waited for at most the
    timeout, one that never reported a status not at all."""
    from fmapping.datasets import open_dataset
    from fmapping.geometry import se3_exp_np
    from services.core_support import Counters
    from services.mapper.core import MapperCore, MapperServiceOptions, await_source_final

    ds = open_dataset(room320)
    n, late = 16, 10
    drift = se3_exp_np(np.array([0.03, -0.02, 0.01, 0.0, 0.02, 0.0]))  # 3.7 cm and 1.1 deg off, frames >= late
    now = [0.0]

    def make() -> MapperCore:
        opts = MapperServiceOptions(pose_source="tracker", points_interval=1e9, checkpoint_every=0, pose_timeout=0)
        core = MapperCore(small_cfg(final_global_iters=2), opts, counters=Counters(), clock=lambda: now[0])
        for k in range(n - 1):  # frame n - 1 comes after the stop, behind it in the inbox
            c2w = ds[k].c2w @ drift if k >= late else ds[k].c2w
            core.apply(P.Pose(seq=k, timestamp=float(ds[k].timestamp), c2w=c2w, source="tracker"))
            core.apply(P.frame_from_dataset(ds[k], seq=k, with_depth=False))
        return core

    def inbox(items, late_after: int = 10**9, delay: float = 0.0):
        """get(timeout) over ``items``; those from index ``late_after`` on arrive ``delay`` fake seconds late."""
        start, taken = now[0], [0]

        def get(timeout):
            if items:
                due = start + (delay if taken[0] >= late_after else 0.0)
                if due <= now[0] + timeout:
                    now[0] = max(now[0], due)
                    taken[0] += 1
                    return items.pop(0)
            now[0] += timeout  # the fake clock runs while nothing comes
            return None
        return get

    def status(state):
        return ("status", ("status/tracker", P.Status(service="tracker", seq=9, state=state)))

    core = make()
    core.on_source_status(P.Status(service="tracker", seq=8, state="running"))
    mapped = list(core.seq_of_fid)
    assert set(range(late, n - 1)) <= set(mapped)
    last = n - 1
    items = [("end", ("control", P.Control("stop", {"reason": "end"})))]  # a second stop: dropped
    items += [("poses", ("poses/tracker", P.Pose(seq=k, timestamp=float(ds[k].timestamp), c2w=ds[k].c2w,
                                                 source="tracker"))) for k in range(late, n)]
    items += [("frames", ("frames", P.frame_from_dataset(ds[last], seq=last, with_depth=False))), status("done")]
    items[-4:] = items[-2:] + items[-4:-2]  # the status overtook the last two poses (seen in fmapping up)
    out = []
    get = inbox(items, late_after=len(items) - 2, delay=0.2)  # ... and came 0.2 s after it
    assert await_source_final(get, core, out.extend, timeout=5.0, clock=lambda: now[0]) and not items
    assert core.counters.get("stops_while_ending") == 1
    poses = core.mapper.frame_poses()
    for fid, seq in enumerate(core.seq_of_fid):  # the moved frames carry the source's final poses
        np.testing.assert_allclose(poses[fid], ds[seq].c2w, atol=1e-5)
    assert last in core.seq_of_fid or last in core.frames  # the frame behind the stop was taken in
    core.apply(P.Control("stop", {"reason": "end"}))
    assert core.finished and core.counters.get("frames_without_pose", 0) == 0

    # a source that stays silent: at most the timeout (fake seconds), then the closing goes ahead
    silent = make()
    silent.on_source_status(P.Status(service="tracker", seq=8, state="running"))
    t0 = now[0]
    assert not await_source_final(inbox([]), silent, lambda o: None, timeout=3.0, clock=lambda: now[0])
    assert 3.0 <= now[0] - t0 < 3.5
    t0 = now[0]  # a signal ends the wait at once
    assert not await_source_final(inbox([]), silent, lambda o: None, timeout=3.0, clock=lambda: now[0],
                                  should_stop=lambda: True) and now[0] == t0
    # a source without a status (GT, an external producer): nothing to wait for
    plain = MapperCore(small_cfg(), MapperServiceOptions(pose_source="external"), counters=Counters())
    t0 = now[0]
    assert await_source_final(inbox([]), plain, lambda o: None, timeout=3.0, clock=lambda: now[0]) and now[0] == t0


def test_tracker_core_logs_a_relocalisation_with_its_frame(room320, caplog):
    """The tracker service logs its front end's rare events with their frame (a failed live run has nothing
    else to read afterwards): a frame whose direct alignment is forced to fail is re-localised by PnP, and
    that frame's line is in the log, once."""
    import logging

    from fmapping.datasets import open_dataset
    from fmapping.tracking.direct_tracker import TrackResult
    from services.tracker.core import TrackerCore, TrackerServiceOptions

    ds = open_dataset(room320)
    target = 21
    core = TrackerCore(opts=TrackerServiceOptions(frame_pose="direct"))

    def feed(k):
        return core.handle("frames", P.encode(P.frame_from_dataset(ds[k], seq=k, with_depth=False)))

    for k in range(target):
        feed(k)
    fe = core.session.frontend
    assert fe.initialized
    real, calls = fe.tracker.track, []

    def failing(rgb, c2w_guess=None):
        calls.append(c2w_guess)
        if len(calls) == 1:  # the first alignment of the frame fails; the one from the PnP pose is real
            return TrackResult(fe.tracker.predict(), True, False, False, float("nan"), 0.0, 0.0, 0, 0.0,
                               fe.tracker.reference.frame_index, "forced loss")
        return real(rgb, c2w_guess)

    fe.tracker.track = failing
    with caplog.at_level(logging.INFO, logger="fmapping.tracker"):
        feed(target)
        fe.tracker.track = real
        feed(target + 1)
    assert core.counters.get("relocalised") == 1 and core.counters.get("frames_lost") == 0
    lines = [r.getMessage() for r in caplog.records if "re-localised" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith(f"frame {target} re-localised"), lines
