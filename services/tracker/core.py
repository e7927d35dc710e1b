"""Tracker service core (zenoh-free): frames + field snapshots in, ``Pose(source="tracker")`` out.

Two front ends (``TrackerServiceOptions.frontend``):

* ``mono`` (default; the same tracking as ``fmapping slam``): a
  :class:`fmapping.tracking.mono.MonoFrontend` runs from the first frame on RGB alone, so
  no frame waits for a map. Frames are held until its two-view bootstrap succeeds; then
  every held frame gets its pose at once and every later frame is tracked as it comes.
  The world frame and the metric scale come from the *anchor* poses (``poses/gt`` when the
  player publishes them): frame 0 is put at its anchor pose and the bootstrap baseline
  takes the anchor's length (the DIM-SLAM convention); without anchors frame 0 is the
  identity and the median bootstrap depth is the unit (evaluate with Sim3). Anchors keep
  being read until the front end's late anchor (``MonoConfig.late_anchor_frames``, frame 14)
  has taken the scale again; until then poses are held, so that no consumer integrates a
  pose at a scale about to change (a ``stop`` control releases them). When a field
  snapshot is held, new keyframes add depth rendered from it (only where the mapped frames
  looked, and only when it agrees with the landmarks). A bootstrap that fails (no parallax
  within ``MonoConfig.init_max_frames`` frames) restarts at the next frame; the frames it
  held are answered with ``quality = 0``. The mapper maps with these poses as given.
  After each keyframe's bundle adjustment, the poses it moved are published again (same
  ``seq``, ``republish_min_m`` / ``republish_min_deg``): the mapper replaces the poses of
  frames it has integrated, the recorder keeps the newest, as ``fmapping slam`` does in-process.
  With ``state_path`` (``--state``; ``fmapping up``: OUT/tracker/state.npz) the newest keyframes
  are saved after each keyframe; a tracker started with that file (a restart, ``fmapping up
  --resume``) re-localises its first frames against them (:meth:`MonoFrontend.resume`) and goes
  on in the same world frame and scale instead of bootstrapping; a frame it answered before that
  comes again (sent to a restarted mapper) gets the same answer again.
* ``map`` (the paper-style loop): direct alignment against keyframes whose depth is
  rendered from the mapper's field. Protocol with the mapper (``services.mapper
  --poses tracker --unposed-init yes``):

  * Before the first FieldSnapshot there is no map to track against: frames wait in a
    bounded buffer (the mapper builds its init stage without tracker poses).
  * The mapper publishes a FieldSnapshot (``frame_seq`` = newest frame it integrated)
    after every update, then the refined poses of its window frames as
    ``Pose(source="mapper")``. Frames up to that newest mapped frame take the mapper's
    pose (republished as the tracker's, so ``traj`` covers every frame); the reference
    keyframe is re-made at the newest mapped frame with depth rendered from the new map.
  * Later frames are tracked. When the tracker asks for a keyframe, the current frame
    becomes the reference (tracked pose, depth rendered from the current map).

  A late (or restarted) tracker asks the mapper's ``map/latest`` queryable for the
  newest snapshot (the shell does it) and continues from there: its first reference is a
  view rendered from the map at the snapshot's ``frame_c2w`` (it never saw that frame).

In both, ``quality`` is the inlier ratio; a lost frame is published with the motion-model
prediction and ``quality = 0`` (the mapper skips such frames). The acknowledgement
``ack`` is the newest frame number answered with a pose (or dropped).

The ``map`` front end (and the field snapshots) is the mixin :mod:`services.tracker.map_frontend`;
the saved keyframes' file is read and written by :mod:`services.tracker.resume_state`.
"""
from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Optional

import numpy as np

from fmapping import protocol as P
from fmapping.geometry import orthonormalize
from fmapping.session import REFINED, SKIPPED
from services.core_support import ServiceCore
from services.tracker.map_frontend import MapFrontend
from services.tracker.resume_state import StateWriter, load_resume_state

# the front end's rare events (re-localisation, loop closures, re-initialisations), one line each with its frame:
# what a failed run's post-mortem needs beside the poses (OUT/logs/tracker.log in fmapping up)
log = logging.getLogger("fmapping.tracker")


@dataclass
class TrackerServiceOptions:
    max_buffer: int = 64  # frames waiting for a map / a reference (drop-oldest beyond)
    keep_frames: int = 64  # recent frames kept for making references
    max_poses: int = 4096  # remembered mapper / own poses
    use_depth: bool = False  # reference depth from the sensor when frames carry it (else rendered from the map)
    min_acc: float = 0.5  # rendered opacity below which a pixel has no depth
    render_chunk: int = 4096
    seen_only: bool = True  # rendered reference depth only where a mapped frame looked (see seen_by)
    frontend: str = "mono"  # "mono" (RGB-only front end from frame 0) | "map" (track against the mapper's field)
    anchor_source: str = "gt"  # poses fixing world frame and scale of the mono bootstrap ("" = none)
    anchor_wait: int = 2  # mono bootstrap: later frames a frame waits for its anchor pose (the first one always)
    # mono: after each keyframe bundle adjustment, publish again (same seq) the poses it moved by more
    # than this, so the mapper trains on them and the recorder keeps them ("republished" counter)
    republish_min_m: float = 1e-3
    republish_min_deg: float = 0.05
    republish: bool = True
    # mono: the current keyframe (image, pose, the landmarks it saw) is saved here after each keyframe; a
    # restarted tracker finding it re-localises the first frames it gets against it and goes on in the
    # same world frame and scale (:meth:`MonoFrontend.resume`) instead of a new bootstrap (None: not kept)
    state_path: Optional[str] = None
    resume_tries: int = 5  # frames a restarted tracker tries to re-localise before it bootstraps anew
    # newest keyframes kept (the nearest in frame number to the first new frame is tried first)
    resume_keyframes: int = 5
    # mono, real time: a tracked frame with at least this many newer frames waiting (here and in the shell's
    # inbox) is not tracked ("frames_skipped_behind"; see interpolate_skipped for its answer), never two in a row and
    # never the frame after a lost one, so that the answers keep pace with the camera (0: never skip). A
    # keyframe is decided by tracking its frame, so a skipped frame is never one.
    skip_behind: int = 1
    # ... while frames keep coming: once none has arrived for this long (the stream ended or paused), every
    # frame waiting is tracked
    stream_idle_s: float = 2.0
    # mono: a frame skipped to keep pace gets the pose between its tracked neighbours', published just before the
    # next one (SessionConfig.interpolate_skipped; off: answered at once with quality 0, no pose)
    interpolate_skipped: bool = True
    # mono: the keyframe bundle adjustment and the loop search in worker threads, merged between frames
    # (MonoConfig.ba_thread, loop_thread): a keyframe no longer holds up its frame's pose. Off here (the poses then
    # equal fmapping slam's exactly); the service's CLI turns it on unless playback is paced.
    ba_thread: bool = False
    loop_thread: Optional[bool] = None  # the loop search's worker alone (None: with ba_thread)
    # mono: a new keyframe's pose goes out before its keyframe work (landmarks, handing its BA and loop search to
    # the workers, the new reference), which the shell runs right after publishing (finish_frame), as ORB-SLAM's
    # tracking hands keyframes to its mapping thread. None: with ba_thread (off: the poses equal fmapping slam's)
    keyframe_after_pose: Optional[bool] = None
    # mono: where a frame's pose comes from first (MonoConfig.frame_pose): "pnp" fits it to the KLT-tracked landmarks
    # and aligns photometrically only the frames that fail, 20-30 % less time a frame; None: the mono config's own
    # ("direct", as fmapping slam). The service's CLI picks "pnp" unless playback is paced.
    frame_pose: Optional[str] = None

    def validate(self) -> "TrackerServiceOptions":
        if self.frontend not in ("mono", "map"):
            raise ValueError(f"tracker frontend must be 'mono' or 'map', got {self.frontend!r}")
        if self.frame_pose not in (None, "direct", "pnp"):
            raise ValueError(f"tracker frame_pose must be 'direct' or 'pnp', got {self.frame_pose!r}")
        if self.loop_thread and not self.ba_thread:
            raise ValueError("tracker loop_thread needs ba_thread (the loop's bundle adjustment goes to its worker)")
        if self.skip_behind < 0 or not self.stream_idle_s >= 0:
            raise ValueError(f"skip_behind and stream_idle_s must be >= 0, got {self.skip_behind} and "
                             f"{self.stream_idle_s}")
        return self


Output = tuple[str, Any]


class OwnPose(NamedTuple):
    """A pose the tracker published for a frame (kept to republish it when the BA moves it)."""
    c2w: np.ndarray
    timestamp: float
    quality: float
    keyframe: bool = False


class TrackerCore(MapFrontend, ServiceCore):
    """See the module docstring. Single-threaded."""

    CHANNELS = {"frames": P.Frame, "field": P.FieldSnapshot, "poses": P.Pose, "control": P.Control}

    def __init__(self, cfg=None, opts: Optional[TrackerServiceOptions] = None, counters=None, on_bad_input=None,
                 mono_cfg=None):
        from fmapping.tracking.direct_tracker import TrackerConfig

        super().__init__(counters, on_bad_input)
        self.cfg = cfg if cfg is not None else TrackerConfig()
        self.mono_cfg = mono_cfg  # MonoConfig of the mono front end (None: its defaults)
        self.opts = (opts or TrackerServiceOptions()).validate()
        self.session = None  # PoseSession of the mono front end (frontend "mono"): the pose policy
        self.anchors: dict[int, np.ndarray] = {}  # anchor poses of the frames the bootstrap may still use
        self._stopped = False  # a stop control came: no frame waits for its anchor any more
        self.camera = None
        self.tracker = None
        self.field = None
        self.render_cfg: dict = {}
        self.version = 0
        self.map_seq = -1  # newest frame integrated into the map we hold
        self.waiting: "OrderedDict[int, P.Frame]" = OrderedDict()  # frames to answer, in order
        self.recent: "OrderedDict[int, P.Frame]" = OrderedDict()  # images for references
        self.mapper_poses: dict[int, np.ndarray] = {}
        self.own_poses: dict[int, OwnPose] = {}  # tracked (not lost) poses, as published
        self.snapshot_pose: Optional[tuple[int, np.ndarray]] = None  # (frame_seq, c2w) of the newest snapshot
        self.last_seq = -1
        self.ref_seq = -1
        self._ref_target: Optional[int] = None  # frame to make the next reference at
        self._motion_seq = -1  # frame of the newest pose in the tracker's motion model
        self.last_track: dict = {}
        self.backlog: Callable[[], int] = lambda: 0  # frames queued before the core (the shell's inbox)
        self._skipped_last = False  # the previous frame was skipped to keep pace
        # saved keyframes of the process before a restart (oldest first), None once used or given up
        self.resume_state: Optional[list] = load_resume_state(self.opts.state_path) if self.opts.state_path else None
        self._saved_keyframe = -1  # newest keyframe of the state handed to the writer
        self._writer: Optional[StateWriter] = StateWriter(self.opts.state_path) if self.opts.state_path else None
        if self.resume_state is not None:
            self.counters.set("resume_keyframe", int(self.resume_state[-1]["index"]))
        # which front end answers (for the launcher's warnings: a status carries numbers only)
        self.counters.set("frontend_mono", int(self.opts.frontend == "mono"))

    @property
    def ack(self) -> int:
        return self.last_seq

    @property
    def mono(self):
        """The mono front end (MonoFrontend) of the session, None before the first frame."""
        return None if self.session is None else self.session.frontend

    # ------------------------------------------------------------ inputs
    def apply(self, msg) -> list[Output]:
        if isinstance(msg, P.Frame):
            return self.on_frame(msg)
        if isinstance(msg, P.FieldSnapshot):
            return self.on_field(msg)
        if isinstance(msg, P.Pose):
            return self.on_pose(msg)
        if isinstance(msg, P.Control):
            if msg.command == "reset":
                self.reset()
            elif msg.command == "stop":
                if self.session is None:  # the stream ended: nothing stays unanswered
                    return []
                self._stopped = True  # frames held for their anchor pose go on without it
                out = self._advance()
                out += self._publish(self.session.finish("the stream stopped before it"))
                self.flush_state()
                return out
            return []
        raise ValueError(f"TrackerCore: unexpected message {type(msg).__name__}")

    def on_frame(self, f: P.Frame) -> list[Output]:
        cam = self.frame_camera(f, undistorted=self.opts.frontend == "mono")  # KLT / BA model a pinhole camera
        if cam is None:
            return []
        if self.camera_dict is None:
            try:
                self._set_camera(cam)
            except (TypeError, ValueError, KeyError) as e:
                self.camera_dict = self.camera = self.tracker = None
                self.bad_input(f"frame {f.seq}: unusable camera {f.camera}: {e}", "rejected_frames")
                return []
        if f.seq <= self.last_seq and f.seq not in self.waiting:
            return self._answer_again(f)
        if f.seq in self.waiting or (self.session is not None and self.session.holds(f.seq)):
            self.counters.inc("stale_frames")  # e.g. sent again while the bootstrap or the late anchor holds it
            return []
        self.took_frame(f.seq)
        self.counters.inc("frames_received")
        self.waiting[f.seq] = f
        if len(self.waiting) > 1 and f.seq < next(reversed(self.waiting)):
            self.waiting = OrderedDict(sorted(self.waiting.items()))
        if self.opts.frontend == "map":  # images for references (the mono front end keeps its own keyframes)
            self.recent[f.seq] = f
            while len(self.recent) > self.opts.keep_frames:
                self.recent.popitem(last=False)
        return self._advance()


    def on_pose(self, p: P.Pose) -> list[Output]:
        if self.opts.frontend == "mono" and p.source and p.source == self.opts.anchor_source:
            return self._on_anchor(p)
        if p.source != "mapper":
            return []
        return self._remember(self.mapper_poses, p, "mapper_poses")

    def _remember(self, store: dict, p: P.Pose, counter: str) -> list[Output]:
        """Keep pose ``p`` in ``store``, count it, move on."""
        self._bounded_put(store, p.seq, np.array(p.c2w))
        self.counters.inc(counter)
        return self._advance()

    def _bounded_put(self, store: dict, seq: int, value) -> None:
        """``store[seq] = value``, at most ``max_poses`` entries (the oldest frames go)."""
        store[seq] = value
        while len(store) > self.opts.max_poses:
            store.pop(min(store))

    def reset(self) -> None:
        self.tracker = None
        self.field = None
        self.camera_dict = None
        self.camera = None
        self.version = 0
        self.map_seq = -1
        self.waiting.clear()
        self.recent.clear()
        self.mapper_poses.clear()
        self.own_poses.clear()
        self.snapshot_pose = None
        self.ref_seq = -1
        self._ref_target = None
        self._motion_seq = -1
        self.session = None
        self.anchors.clear()
        self._stopped = False
        self._skipped_last = False
        self.counters.inc("resets")

    def _set_camera(self, cam: dict) -> None:
        from fmapping.camera import PinholeCamera
        from fmapping.tracking.direct_tracker import DirectTracker

        self.camera_dict = dict(cam)
        self.camera = PinholeCamera.from_dict(cam)
        self.tracker = DirectTracker(self.camera, self.cfg)
        if self.opts.frontend == "mono":
            self._new_mono()

    # ------------------------------------------------------------ mono front end
    def _new_mono(self) -> None:
        from fmapping.session import PoseSession, SessionConfig

        o = self.opts
        policy = SessionConfig(republish=o.republish, republish_min_m=o.republish_min_m,
                               republish_min_deg=o.republish_min_deg, restart_failed_bootstrap=True,
                               max_poses=o.max_poses, interpolate_skipped=o.interpolate_skipped)
        import dataclasses

        from fmapping.tracking.mono import MonoConfig

        mono = dataclasses.replace(self.mono_cfg or MonoConfig(), ba_thread=o.ba_thread,
                                   loop_thread=o.ba_thread if o.loop_thread is None else o.loop_thread)
        if o.frame_pose is not None:
            mono = dataclasses.replace(mono, frame_pose=o.frame_pose)
        self.session = PoseSession(self.camera, self.cfg, mono, policy, anchors=self.anchors)

    def _on_anchor(self, p: P.Pose) -> list[Output]:
        done = self.mono is not None and self.mono.initialized and not self.mono.scale_pending
        if done or p.seq <= self.last_seq:
            return []
        return self._remember(self.anchors, p, "anchor_poses")

    def _extra_depth(self):
        """Depth rendered from the map we hold, for new keyframes (None before the first snapshot);
        the view is built only when the front end asks (``MonoConfig.dense_extra``)."""
        if self.field is None or self.camera is None:
            return None
        return lambda c2w: self._map_view().depth_fn(c2w)

    def _answer_again(self, f: P.Frame) -> list[Output]:
        """A frame answered before comes again (the player resends frames to a restarted mapper): the
        same answer again, so that nobody waits for it (``quality = 0`` when it was lost or skipped)."""
        self.counters.inc("frames_answered_again")
        own = self.own_poses.get(f.seq)
        if own is None:
            return [self._skip(f.seq, f.timestamp)]
        return [("poses", P.Pose(seq=f.seq, timestamp=own.timestamp, c2w=orthonormalize(own.c2w), source="tracker",
                                 quality=own.quality, keyframe=own.keyframe))]

    def _resume_mono(self, seq: int, f: P.Frame) -> list[Output]:
        """A restarted tracker: re-localise frame ``seq`` against the saved keyframes (``resume_state``)
        and go on from there in their world frame and scale; after ``resume_tries`` misses, bootstrap
        anew (the frames missed are answered with ``quality = 0``)."""
        t0 = time.perf_counter()
        ups = self.session.resume(seq, np.asarray(f.rgb), f.timestamp, self.resume_state)
        self.counters.set("track_ms", round((time.perf_counter() - t0) * 1e3, 2))
        if ups is None:
            self.counters.inc("resume_misses")
            if self.counters.get("resume_misses") >= self.opts.resume_tries:
                self.resume_state = None
                self.last_error = f"could not re-localise against the saved keyframes (newest: " \
                                  f"{self.counters.get('resume_keyframe')}): bootstrapping anew"
            return [self._skip(seq, f.timestamp)]
        self.resume_state = None
        self.counters.set("resumed_at", seq)
        self.counters.set("resume_keyframe", int(self.mono.init_info["resumed_from"]))
        self.counters.set("resume_points", int(self.mono.init_info.get("points", 0)))
        self.counters.set("resume_keyframes", int(self.mono.init_info.get("keyframes_restored", 0)))
        self.counters.inc("frames_tracked")
        self._save_state()
        return self._publish(ups)

    def _resume_fits(self) -> bool:
        """Are there saved keyframes to re-localise against, of the frames' size? (A misfit is dropped.)"""
        st = self.resume_state
        if st is not None and st[0]["gray"].shape != (self.camera.height, self.camera.width):
            self.last_error = (f"the saved keyframes' images are {st[0]['gray'].shape}, not the frames' size: "
                               "not resuming")
            self.resume_state = st = None
        return st is not None

    def _save_state(self) -> None:
        """The front end's newest keyframes to ``state_path`` (atomically, by the writer thread), when they changed."""
        if not self.opts.state_path or self.mono is None or self.mono.keyframe_index == self._saved_keyframe:
            return
        state = self.mono.keyframe_states(self.opts.resume_keyframes)
        if not state:
            return
        self._writer.put(state)  # written off the frame path (StateWriter)
        self._saved_keyframe = self.mono.keyframe_index
        self._writer_counts()

    def _writer_counts(self) -> None:
        """The state writer's count and last failure into the counters and ``last_error``."""
        if self._writer is None:
            return
        self.counters.set("states_saved", self._writer.saved)
        if self._writer.error:
            self.last_error = self._writer.error

    def flush_state(self, timeout: float = 30.0) -> bool:
        """Wait until the keyframes handed to the state writer are on disk (True when they are)."""
        if self._writer is None:
            return True
        done = self._writer.flush(timeout)
        self._writer_counts()
        return done

    def close(self) -> None:
        """Write what the state writer holds and stop it (the end of the process)."""
        if self._writer is not None:
            self._writer.close()
            self._writer_counts()

    def _advance_mono(self) -> list[Output]:
        out: list[Output] = []
        sess = self.session
        while self.waiting:
            seq, f = next(iter(self.waiting.items()))
            if not sess.initialized and self._resume_fits():
                self.waiting.popitem(last=False)
                out += self._resume_mono(seq, f)
                continue
            if (not sess.initialized or sess.scale_pending) and self._wait_for_anchor(seq):
                break  # this frame's anchor pose is on its way (the bootstrap or the late anchor may use it)
            if not sess.initialized:
                self.waiting.popitem(last=False)
                failures = sess.bootstrap_failures
                t0 = time.perf_counter()
                ups = sess.push(seq, np.asarray(f.rgb), f.timestamp)
                self.counters.set("track_ms", round((time.perf_counter() - t0) * 1e3, 2))
                if sess.bootstrap_failures > failures:
                    self.counters.inc("bootstrap_failures")
                    self.last_error = f"monocular bootstrap failed at frame {seq}; restarting at the next frame"
                    out += self._publish(ups)
                    continue
                if sess.initialized:
                    self.counters.set("bootstrap_frame", seq)
                    anchored = sess.frontend.init_info.get("scale_from") == "anchor"
                    self.counters.set("bootstrap_anchored", int(anchored))
                    self.counters.inc("frames_tracked", len(sess.bootstrapped))
                    out += self._publish(ups)
                    self._save_state()
                continue
            self.waiting.popitem(last=False)
            if self._keep_pace():
                self.counters.inc("frames_skipped_behind")
                out += self._publish(sess.skip(seq, f.timestamp))  # now without a pose, or interpolated later
                continue
            fe = sess.frontend
            loops, refused, reinits = len(fe.loops), len(fe.loops_refused), len(fe.reinits)
            later = self.opts.ba_thread if self.opts.keyframe_after_pose is None else self.opts.keyframe_after_pose
            ups = sess.push(seq, np.asarray(f.rgb), f.timestamp, extra_depth=self._extra_depth(), keyframe_later=later)
            self._count(f, sess.last)
            out += self._publish(ups)
            self._save_state()
            self._log_events(seq, fe.loops[loops:], fe.loops_refused[refused:], fe.reinits[reinits:])
            self.counters.set("loop_closures", len(fe.loops))
            self.counters.set("keyframes_deferred", fe.keyframes_deferred)
            self.counters.set("frames_posed_by_pnp", fe.frames_pnp)  # (--frame-pose pnp)
            self.counters.set("frames_interpolated", sess.interpolated)
        self.counters.set("waiting_frames", len(self.waiting))
        return out

    def _wait_for_anchor(self, seq: int) -> bool:
        """Hold frame ``seq`` (bootstrap, or scale pending) for its anchor pose? While anchors flow, and
        for the bootstrap's first frame whenever an anchor source is set. Frames and anchor poses travel
        on different keys, so a frame may come before its anchor: bootstrapping without it would put the
        world frame at the identity, and a late anchor that never sees one gives up after
        2 x ``late_anchor_frames``. At most until ``anchor_wait`` later frames have come, and not once
        the stream has stopped. Poses are held while the scale is pending anyway: the wait costs no latency."""
        if seq in self.anchors or self._stopped or len(self.waiting) > self.opts.anchor_wait:
            return False
        return bool(self.anchors) or (bool(self.opts.anchor_source) and self.session.c2w0 is None)

    def _keep_pace(self) -> bool:
        """Skip the frame at hand (see ``TrackerServiceOptions.skip_behind``)? Called once per tracked frame."""
        last = self.session.last
        skip = (self.opts.skip_behind > 0 and not self._skipped_last and last is not None and not last.lost
                and len(self.waiting) + self.backlog() >= self.opts.skip_behind
                and self.stream_idle() < self.opts.stream_idle_s)
        self._skipped_last = skip
        return skip

    def _publish(self, ups: list) -> list[Output]:
        """The session's pose updates as messages: a refined pose goes out again under its frame's number
        ("republished"), a skipped frame with ``quality = 0``, the rest in order (:meth:`_emit`)."""
        out: list[Output] = []
        for u in ups:
            if u.kind == SKIPPED:
                out.append(self._skip(u.index, u.timestamp))
            elif u.kind == REFINED:
                was = self.own_poses.get(u.index)
                if was is not None:
                    self.own_poses[u.index] = was._replace(c2w=np.array(u.c2w))
                self.counters.inc("republished")
                out.append(("poses", P.Pose(seq=u.index, timestamp=u.timestamp, c2w=orthonormalize(u.c2w),
                                            source="tracker", quality=u.quality, keyframe=u.keyframe)))
            else:
                if u.quality > 0:
                    self._keep_own(u.index, u.c2w, u.timestamp, u.quality, u.keyframe)
                out += self._emit(u.index, u.timestamp, u.c2w, u.quality, u.keyframe)
        la = self.mono.late_anchor if self.mono is not None else None
        if la is not None and not self.anchors:
            self.counters.set("late_anchor_factor", round(float(la["factor"]), 6))
        return out

    def _keep_own(self, seq: int, c2w: np.ndarray, stamp: float, quality: float, keyframe: bool = False) -> None:
        """Remember a tracked pose as published."""
        self._bounded_put(self.own_poses, seq, OwnPose(np.array(c2w), float(stamp), float(quality), bool(keyframe)))

    # ------------------------------------------------------------ tracking
    def _emit(self, seq: int, stamp: float, c2w: np.ndarray, quality: Optional[float],
              keyframe: bool = False) -> list[Output]:
        """The pose of frame ``seq`` (``keyframe``: the front end made it one), preceded by ``quality = 0``
        answers for frames that never reached us (dropped upstream), so that nobody waits for them."""
        out: list[Output] = []
        if 0 <= self.last_seq < seq - 1 and seq - self.last_seq <= 1024:
            for s in range(self.last_seq + 1, seq):
                out.append(self._skip(s))
        self.last_seq = max(self.last_seq, seq)
        if quality is None or quality > 0:
            self.counters.inc("frames_posed")  # each frame is answered here once (again: _answer_again)
        out.append(("poses", P.Pose(seq=seq, timestamp=stamp, c2w=orthonormalize(c2w), source="tracker",
                                    quality=quality, keyframe=bool(keyframe))))
        return out

    def _skip(self, seq: int, stamp: float = 0.0) -> Output:
        """An unusable pose (``quality = 0``) for a frame this tracker will not track."""
        self.counters.inc("frames_skipped")
        self.last_seq = max(self.last_seq, seq)
        return ("poses", P.Pose(seq=seq, timestamp=stamp, c2w=np.eye(4), source="tracker", quality=0.0))

    def _drop_oldest(self) -> Output:
        seq, f = self.waiting.popitem(last=False)
        self.counters.inc("dropped_frames")
        return self._skip(seq, f.timestamp)

    def _advance(self) -> list[Output]:
        if self.opts.frontend == "mono":
            if self.mono is None:
                return []  # no frame yet (the first one fixes the camera)
            return self._advance_mono()
        return self._advance_map()

    def finish_frame(self) -> list[Output]:
        """The keyframe work the last frame left for after its pose went out (``keyframe_after_pose``; the shell
        calls this right after publishing), and the poses it moved. Nothing when none waits (the next frame
        would do it first)."""
        fe = self.mono
        if self.opts.frontend != "mono" or fe is None or not fe.initialized or not fe.keyframe_pending:
            return []
        loops, refused, reinits = len(fe.loops), len(fe.loops_refused), len(fe.reinits)
        out = self._publish(self.session.finish_keyframe())
        self._save_state()
        self._log_events(fe.keyframe_index, fe.loops[loops:], fe.loops_refused[refused:], fe.reinits[reinits:])
        self.counters.set("loop_closures", len(fe.loops))
        return out

    @staticmethod
    def _log_events(seq: int, loops: list, refused: list, reinits: list) -> None:
        """One log line per loop closed or refused and per re-initialisation while frame ``seq`` was tracked."""
        for r in loops:
            log.info("frame %d: loop closed at keyframe %d onto keyframe %d (%d inliers, moved %.3g m / %.2f deg)",
                     seq, r["frame"], r["keyframe"], r["inliers"], r["moved_m"], r["moved_deg"])
        for r in refused:
            log.info("frame %d: loop at keyframe %d onto keyframe %d refused: %s", seq, r["frame"], r["keyframe"],
                     r.get("why", ""))
        for i in reinits:
            log.info("frame %d: re-initialised at frame %d (the track was lost)", seq, i)

    def _count(self, f: P.Frame, res) -> float:
        """Count a tracking result; its pose's quality (0 when lost)."""
        self.counters.inc("frames_tracked")
        self.counters.set("track_ms", round(res.ms, 2))
        self.last_track = res.to_dict()
        if res.lost:
            self.counters.inc("frames_lost")
            self.last_error = f"frame {f.seq} lost: {res.reason}"
            return 0.0
        if res.relocalised:
            self.counters.inc("relocalised")
            log.info("frame %d re-localised%s", f.seq, f": {res.reason}" if res.reason else "")
        self._motion_seq = f.seq
        return float(max(res.inlier_ratio, 1e-6))


def load_tracker_config(path=None):
    from fmapping.config import load_config
    from fmapping.tracking.direct_tracker import TrackerConfig

    return load_config(TrackerConfig(), path)
