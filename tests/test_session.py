"""The incremental session (fmapping.session): the front end's pose policy, and the drivers that use it."""
import numpy as np
import pytest

from fmapping import protocol as P


@pytest.fixture(scope="module")
def room(room320):
    from fmapping.datasets import open_dataset

    return open_dataset(room320)


def _anchored_session(ds, **policy):
    from fmapping.session import PoseSession, SessionConfig
    from fmapping.tracking.direct_tracker import TrackerConfig

    return PoseSession(ds.camera, TrackerConfig(), None, SessionConfig(**policy))


def _run(sess, ds, anchors=True):
    """Push every frame (its GT pose given as anchor first, as io play sends it): the updates per push."""
    per_push = []
    for i in range(len(ds)):
        f = ds[i]
        if anchors:
            sess.add_anchor(i, f.c2w)
        per_push.append(sess.push(i, f.rgb, f.timestamp))
    per_push.append(sess.finish())
    return per_push


def test_pose_session_buffers_the_bootstrap_and_holds_until_the_late_anchor(room):
    """Nothing leaves before the late anchor at frame 14; then frames 0-14 leave in order at the fixed
    scale, and every later push gives its own frame first, then only refined poses of frames given before
    that moved by more than the thresholds."""
    from fmapping.metrics import ate
    from fmapping.geometry import pose_distance

    sess = _anchored_session(room, restart_failed_bootstrap=True)
    per_push = _run(sess, room)
    n = len(room)
    assert all(ups == [] for ups in per_push[:14])
    assert [u.index for u in per_push[14]] == list(range(15)) and all(u.kind == "tracked" for u in per_push[14])
    assert sess.frontend.late_anchor["frame"] == 14
    given = {u.index: u for u in per_push[14]}
    refined = 0
    for i in range(15, n):
        ups = per_push[i]
        assert ups[0].index == i and ups[0].kind in ("tracked", "lost")
        given[i] = ups[0]
        for u in ups[1:]:  # the BA of a new keyframe may move it too
            assert u.kind == "refined" and u.index in given
            dt, dr = pose_distance(given[u.index].c2w, u.c2w)
            assert dt > 1e-3 or dr > 0.05  # moved enough to be worth sending
            assert (u.timestamp, u.quality) == (given[u.index].timestamp, given[u.index].quality)
            given[u.index] = u
            refined += 1
    assert refined > 0 and per_push[-1] == []  # nothing was held at the end
    est = np.stack([given[k].c2w for k in range(n)])
    gt = np.stack([room[k].c2w for k in range(n)])
    assert ate(est, gt, "none")["rmse_m"] < 0.02  # GT world frame and scale from the anchors


def test_a_bootstrap_left_with_too_few_landmarks_to_track_against_fails_and_starts_again(room):
    """The two-view start succeeds but its bundle adjustment leaves fewer landmarks than a reference needs
    (``min_ref_points``, here out of reach): the attempt counts as a failed bootstrap, its frames are answered
    unusable and the next frame starts again, instead of an exception out of the session."""
    from fmapping.session import SKIPPED, PoseSession, SessionConfig
    from fmapping.tracking.direct_tracker import TrackerConfig
    from fmapping.tracking.mono import MonoConfig

    sess = PoseSession(room.camera, TrackerConfig(), MonoConfig(min_ref_points=100_000),
                       SessionConfig(restart_failed_bootstrap=True))
    per_push = _run(sess, room)
    assert sess.bootstrap_failures >= 1 and not sess.frontend.initialized
    answered = [u for ups in per_push for u in ups]
    assert answered and all(u.kind == SKIPPED and u.quality == 0.0 for u in answered)
    assert len({u.index for u in answered}) == len(answered)  # each frame answered once
    # the same frames with a reference in reach start at the first attempt
    ok = _anchored_session(room, restart_failed_bootstrap=True)
    _run(ok, room)
    assert ok.bootstrap_failures == 0 and ok.frontend.initialized


def test_pose_session_finish_releases_what_the_late_anchor_held(room):
    """A stream that ends before frame 14: ``finish`` gives the held frames at the bootstrap's scale."""
    sess = _anchored_session(room)
    for i in range(11):
        sess.add_anchor(i, room[i].c2w)
        assert sess.push(i, room[i].rgb, room[i].timestamp) == []
    assert sess.initialized and sess.scale_pending and sess.holds(10) and not sess.holds(11)
    out = sess.finish("stopped")
    assert [u.index for u in out] == list(range(11)) and all(u.usable for u in out)
    assert sess.frontend.late_anchor == {"frame": None, "factor": 1.0, "refused": "stopped"}
    np.testing.assert_allclose(out[0].c2w, room[0].c2w, atol=1e-9)
    assert sess.finish() == []


def test_the_tracker_service_publishes_exactly_the_session_updates(room):
    """TrackerCore (mono) is a thin shell: its pose messages are the session's updates, in order."""
    from services.tracker.core import TrackerCore

    core = TrackerCore()
    msgs = []
    for i in range(len(room)):
        f = room[i]
        core.handle("poses", P.encode(P.Pose(seq=i, timestamp=f.timestamp, c2w=f.c2w, source="gt")))
        msgs += [m for _, m in core.handle("frames", P.encode(P.frame_from_dataset(f, seq=i)))]
    msgs += [m for _, m in core.handle("control", P.encode(P.Control(command="stop")))]
    sess = _anchored_session(room, restart_failed_bootstrap=True, max_poses=4096)
    ups = [u for push in _run(sess, room) for u in push]
    assert [m.seq for m in msgs] == [u.index for u in ups]
    for m, u in zip(msgs, ups):
        np.testing.assert_allclose(m.c2w, u.c2w, atol=1e-9)  # the wire keeps float64 rotations orthonormal
        assert m.quality == pytest.approx(u.quality) and m.timestamp == pytest.approx(u.timestamp)
    assert core.counters.get("republished") == sum(u.kind == "refined" for u in ups) > 0
    first = {}
    for m in msgs:
        first.setdefault(m.seq, m.quality)
    assert core.counters.get("frames_posed") == sum(q > 0 for q in first.values()) >= len(room) - 2


def test_the_tracker_service_counts_the_frames_it_answered_without_a_pose(room):
    """``frames_posed``: the frames whose (first) answer carries a pose. A camera that starts on blank frames
    (no texture: the monocular start cannot begin) has no pose for them, and ``fmapping up``'s warnings say
    how many (``services.launcher.supervise.tracker_warnings``); the clean run above has none."""
    import dataclasses

    from services.launcher.supervise import tracker_warnings
    from services.tracker.core import TrackerCore

    blank = 10
    core = TrackerCore()
    first = {}
    for i in range(len(room)):
        f = room[i]
        if i < blank:
            f = dataclasses.replace(f, rgb=np.full_like(f.rgb, 128))
        core.handle("poses", P.encode(P.Pose(seq=i, timestamp=f.timestamp, c2w=f.c2w, source="gt")))
        for _, m in core.handle("frames", P.encode(P.frame_from_dataset(f, seq=i))):
            first.setdefault(m.seq, m.quality)
    for _, m in core.handle("control", P.encode(P.Control(command="stop"))):
        first.setdefault(m.seq, m.quality)
    c = core.counters.snapshot()
    posed = sum(q > 0 for q in first.values())
    assert len(first) == c["frames_received"] == len(room)
    assert c["frames_posed"] == posed and blank <= len(room) - posed < len(room)
    assert all(first[i] == 0 for i in range(blank))
    assert tracker_warnings({"counters": c})[0] == (
        f"{len(room) - posed} of {len(room)} frames have no pose: the monocular start needs texture and camera "
        f"translation (not only rotation) in its first frames")


class _RecordingMapper:
    """Records what a SlamSession integrates; a window every ``every`` frames."""

    def __init__(self, every=5):
        self.added, self.moved, self.every = [], [], every

    def add_frame(self, rgb, c2w, ts, depth):
        self.added.append((ts, np.array(c2w)))
        if len(self.added) % self.every:
            return None

        class _Stats:
            def to_dict(s):
                return {"kind": "window", "frames": len(self.added)}
        return _Stats()

    def set_poses(self, poses):
        self.moved.append(dict(poses))
        return len(poses)


def test_slam_session_integrates_each_released_frame_once_and_moves_refined_poses(room):
    """Every usable released pose reaches the mapper once, with its frame, in release order; a refined
    pose moves the mapper's copy of that frame (by its mapper id); windows are reported with the frame
    that completed them."""
    from fmapping.session import SlamSession

    poses = _anchored_session(room)
    m = _RecordingMapper()
    seen = []
    sess = SlamSession(poses, lambda: m, on_window=seen.append)
    released = []
    for i in range(len(room)):
        poses.add_anchor(i, room[i].c2w)
        released += sess.push(room[i])
    released += sess.finish()
    first = [u for u in released if u.kind != "refined" and u.usable]
    assert [ts for ts, _ in m.added] == [u.timestamp for u in first]
    assert list(sess.fid_of) == [u.index for u in first] and list(sess.fid_of.values()) == list(range(len(first)))
    for (_, c2w), u in zip(m.added, first):
        np.testing.assert_allclose(c2w, u.c2w, atol=0)
    moved = {sess.fid_of[u.index]: u.c2w for u in released if u.kind == "refined"}
    assert moved and sess.pose_updates == sum(len(d) for d in m.moved)
    got = {}
    for d in m.moved:
        got.update(d)
    assert set(got) == set(moved)
    for k in moved:
        np.testing.assert_allclose(got[k], moved[k], atol=0)  # the newest refined pose of each frame
    wins = sess.map_updates()
    assert wins == seen and [w["frames"] for w in wins] == list(range(5, len(first) + 1, 5))
    assert all(w["after_frame"] in sess.fid_of for w in wins) and sess.map_updates() == []


def test_a_keyframes_pose_leaves_before_its_keyframe_work_and_the_run_stays_the_same(room):
    """``push(keyframe_later=True)`` (the tracker service at a camera's rate): a frame that becomes a keyframe
    gives its pose, flagged as a keyframe, while its keyframe work waits; :meth:`PoseSession.finish_keyframe`
    does that work. The front end's poses are those of the run that does the work at once (no bundle
    adjustment in a worker: both runs deterministic), to rounding."""
    runs = {}
    for later in (False, True):
        sess = _anchored_session(room, max_poses=4096)
        waited = 0
        for i in range(len(room)):
            f = room[i]
            sess.add_anchor(i, f.c2w)
            ups = sess.push(i, f.rgb, f.timestamp, keyframe_later=later)
            fe = sess.frontend
            if fe.initialized and fe.keyframe_pending:
                waited += 1
                own = [u for u in ups if u.index == i]
                assert own and own[0].keyframe and fe.is_keyframe(i) and i not in fe.store.kf_pose
                sess.finish_keyframe()
                assert i in fe.store.kf_pose and not fe.keyframe_pending
        sess.finish()
        runs[later] = (sess.frontend.poses(), waited, sorted(sess.frontend.store.kf_pose))
    (p_now, n_now, kf_now), (p_later, n_later, kf_later) = runs[False], runs[True]
    assert n_now == 0 and n_later >= 2 and kf_now == kf_later, (n_later, kf_now, kf_later)
    assert sorted(p_now) == sorted(p_later)
    for k in p_now:
        np.testing.assert_allclose(p_later[k], p_now[k], atol=1e-6)  # (BA iterations amplify the rounding)


def test_the_tracker_service_sends_a_keyframes_pose_before_its_keyframe_work(room):
    """``TrackerServiceOptions.keyframe_after_pose``: ``apply`` answers a new keyframe with its pose (flagged as a
    keyframe) and leaves the keyframe work to ``finish_frame``, which the shell calls after publishing; the poses
    it moved go out then. The front end ends with the poses of the run without it, to rounding; the last pose
    sent for each frame is within the republishing thresholds of that run's (a keyframe's first pose now leaves
    before the bundle adjustment merged at the keyframe moves it, by less than them or it would go out again)."""
    from fmapping.geometry import pose_distance
    from fmapping.session import SessionConfig
    from services.tracker.core import TrackerCore, TrackerServiceOptions

    last, early, poses = {}, {}, {}
    for later in (False, True):
        core = TrackerCore(opts=TrackerServiceOptions(keyframe_after_pose=later))
        final, waited = {}, []
        for i in range(len(room)):
            f = room[i]
            core.handle("poses", P.encode(P.Pose(seq=i, timestamp=f.timestamp, c2w=f.c2w, source="gt")))
            answered = [m for _, m in core.handle("frames", P.encode(P.frame_from_dataset(f, seq=i)))]
            fe = core.mono
            if fe is not None and fe.initialized and fe.keyframe_pending:
                assert any(m.seq == i and m.keyframe for m in answered) and i not in fe.store.kf_pose
                waited.append(i)
            answered += [m for _, m in core.finish_frame()]
            assert fe is None or not fe.keyframe_pending
            final.update({m.seq: m.c2w for m in answered if m.quality > 0})
        final.update({m.seq: m.c2w for _, m in core.handle("control", P.encode(P.Control(command="stop")))
                      if m.quality > 0})
        last[later], early[later], poses[later] = final, waited, core.mono.poses()
    assert not early[False] and len(early[True]) >= 2, early
    assert sorted(poses[False]) == sorted(poses[True]) and sorted(last[False]) == sorted(last[True])
    for k in poses[False]:
        np.testing.assert_allclose(poses[True][k], poses[False][k], atol=1e-6)
    cfg = SessionConfig()
    for k in last[False]:
        dt, dr = pose_distance(last[True][k], last[False][k])
        assert dt <= 2 * cfg.republish_min_m and dr <= 2 * cfg.republish_min_deg, (k, dt, dr)
