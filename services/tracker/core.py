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
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, NamedTuple, Optional

import numpy as np

from fmapping import protocol as P
from fmapping.fileio import atomic_open
from fmapping.geometry import orthonormalize
from services.core_support import ServiceCore, snapshot_problem, usable_camera

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
    anchor_wait: int = 2  # mono bootstrap: frames a frame waits for its anchor pose once anchors flow
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

    def validate(self) -> "TrackerServiceOptions":
        if self.frontend not in ("mono", "map"):
            raise ValueError(f"tracker frontend must be 'mono' or 'map', got {self.frontend!r}")
        return self


Output = tuple[str, Any]


class OwnPose(NamedTuple):
    """A pose the tracker published for a frame (kept to republish it when the BA moves it)."""
    c2w: np.ndarray
    timestamp: float
    quality: float


class TrackerCore(ServiceCore):
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
        # saved keyframes of the process before a restart (oldest first), None once used or given up
        self.resume_state: Optional[list] = load_resume_state(self.opts.state_path) if self.opts.state_path else None
        self._saved_keyframe = -1  # newest keyframe of the state on disk
        if self.resume_state is not None:
            self.counters.set("resume_keyframe", int(self.resume_state[-1]["index"]))

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
                return self._publish(self.session.finish("the stream stopped before it"))
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

    def on_field(self, s: P.FieldSnapshot) -> list[Output]:
        if s.version <= self.version and self.field is not None:
            self.counters.inc("stale_snapshots")
            return []
        why = snapshot_problem(s.version, s.frame_seq, self.version, max(self.newest_seq, self.ack))
        if why:  # e.g. a version 10**9 would shadow every real snapshot after it
            self.bad_input(f"field snapshot v{s.version}: {why}", "rejected_snapshots")
            return []
        try:  # everything is checked and built before any state changes
            field, render_cfg, cam = self._from_snapshot(s)
        except (TypeError, ValueError, KeyError, RuntimeError, OverflowError) as e:
            self.bad_input(f"field snapshot v{s.version}: {type(e).__name__}: {e}", "rejected_snapshots")
            return []
        if self.camera_dict is None and cam is not None:
            self._set_camera(cam)
        self.field = field.eval()
        self.render_cfg = render_cfg
        self.version = s.version
        self.map_seq = max(self.map_seq, s.frame_seq)
        if s.frame_c2w is not None and s.frame_seq >= 0:
            self.snapshot_pose = (s.frame_seq, np.array(s.frame_c2w))
        self._ref_target = s.frame_seq if s.frame_seq >= 0 else None
        self.counters.set("field_version", s.version)
        self.counters.inc("snapshots")
        return self._advance()

    def _from_snapshot(self, s: P.FieldSnapshot):
        """(field, render config, camera dict or None) of a snapshot, or ValueError / TypeError / KeyError
        naming what does not fit: the field config, its size against the arrays carried, the render
        settings, the camera (which must be the frames' camera once that is known)."""
        from fmapping.field import FieldConfig, field_from_snapshot, min_field_elements

        fdict = s.config.get("field", {})
        if not isinstance(fdict, dict):
            raise ValueError(f"config.field must be a map, got {type(fdict).__name__}")
        default = FieldConfig()
        for k, v in fdict.items():  # unknown keys: dataclasses.replace raises TypeError
            want = type(getattr(default, k, None))
            ok = isinstance(v, want) and (want is bool or not isinstance(v, bool)) or \
                (want is float and isinstance(v, int) and not isinstance(v, bool))
            if hasattr(default, k) and not ok:
                raise ValueError(f"config.field.{k} must be {want.__name__}, got {v!r}")
        fcfg = dataclasses.replace(default, **fdict)
        fcfg.validate()
        need, have = min_field_elements(fcfg), sum(int(a.size) for a in s.arrays.values())
        if need > have:  # checked before building: a forged config must not allocate gigabytes
            raise ValueError(f"config.field needs at least {need} parameters, the snapshot carries {have}")
        rc = {}
        for k, d, lo, hi in (("near", 0.1, 0.0, 1e4), ("far", 6.0, 0.0, 1e4)):
            v = s.config.get(k, d)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
                raise ValueError(f"config.{k} must be a number in [{lo}, {hi}], got {v!r}")
            rc[k] = float(v)
        if not rc["near"] < rc["far"]:
            raise ValueError(f"config: need near < far, got {rc['near']} and {rc['far']}")
        for k, d, lo, hi in (("n_coarse", 32, 2, 1024), ("n_fine", 16, 0, 1024)):
            v = s.config.get(k, d)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"config.{k} must be an integer in [{lo}, {hi}], got {v!r}")
            rc[k] = int(v)
        cam = s.config.get("camera")
        if cam is not None:
            cam = usable_camera(cam)
            if self.camera_dict is not None and cam != self.camera_dict:
                raise ValueError(f"config.camera {cam} is not the frames' camera {self.camera_dict}")
        field = field_from_snapshot(fcfg, {k: np.array(v) for k, v in s.arrays.items()})
        return field, rc, cam

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
                               max_poses=o.max_poses)
        self.session = PoseSession(self.camera, self.cfg, self.mono_cfg, policy, anchors=self.anchors)

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
                                 quality=own.quality))]

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
        """The front end's newest keyframes to ``state_path`` (atomically), when they changed."""
        if not self.opts.state_path or self.mono is None or self.mono.keyframe_index == self._saved_keyframe:
            return
        state = self.mono.keyframe_states(self.opts.resume_keyframes)
        if not state:
            return
        try:
            save_resume_state(self.opts.state_path, state)
        except OSError as e:
            self.last_error = f"tracker state not saved: {e}"
            return
        self._saved_keyframe = self.mono.keyframe_index
        self.counters.inc("states_saved")

    def _advance_mono(self) -> list[Output]:
        out: list[Output] = []
        sess = self.session
        while self.waiting:
            seq, f = next(iter(self.waiting.items()))
            if not sess.initialized and self._resume_fits():
                self.waiting.popitem(last=False)
                out += self._resume_mono(seq, f)
                continue
            if not sess.initialized:
                if self.anchors and seq not in self.anchors and len(self.waiting) <= self.opts.anchor_wait:
                    break  # anchors flow: this frame's is on its way
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
            ups = sess.push(seq, np.asarray(f.rgb), f.timestamp, extra_depth=self._extra_depth())
            self._count(f, sess.last)
            out += self._publish(ups)
            self._save_state()
            self.counters.set("loop_closures", len(sess.frontend.loops))
        self.counters.set("waiting_frames", len(self.waiting))
        return out

    def _publish(self, ups: list) -> list[Output]:
        """The session's pose updates as messages: a refined pose goes out again under its frame's number
        ("republished"), a skipped frame with ``quality = 0``, the rest in order (:meth:`_emit`)."""
        out: list[Output] = []
        for u in ups:
            if u.kind == "skipped":
                out.append(self._skip(u.index, u.timestamp))
            elif u.kind == "refined":
                was = self.own_poses.get(u.index)
                if was is not None:
                    self.own_poses[u.index] = was._replace(c2w=np.array(u.c2w))
                self.counters.inc("republished")
                out.append(("poses", P.Pose(seq=u.index, timestamp=u.timestamp, c2w=orthonormalize(u.c2w),
                                            source="tracker", quality=u.quality)))
            else:
                if u.quality > 0:
                    self._keep_own(u.index, u.c2w, u.timestamp, u.quality)
                out += self._emit(u.index, u.timestamp, u.c2w, u.quality)
        la = self.mono.late_anchor if self.mono is not None else None
        if la is not None and not self.anchors:
            self.counters.set("late_anchor_factor", round(float(la["factor"]), 6))
        return out

    def _keep_own(self, seq: int, c2w: np.ndarray, stamp: float, quality: float) -> None:
        """Remember a tracked pose as published."""
        self._bounded_put(self.own_poses, seq, OwnPose(np.array(c2w), float(stamp), float(quality)))

    # ------------------------------------------------------------ tracking
    def _pose_of(self, seq: int) -> Optional[np.ndarray]:
        if seq in self.mapper_poses:
            return self.mapper_poses[seq]
        if self.snapshot_pose is not None and self.snapshot_pose[0] == seq:
            return self.snapshot_pose[1]
        own = self.own_poses.get(seq)
        return None if own is None else own.c2w

    def _reference_frame(self, target: int) -> Optional[int]:
        """``target`` when its pose is known (its image, or a render of the map when we never saw
        it, e.g. after a restart), else the newest earlier frame with pose and image."""
        if self._pose_of(target) is not None:
            return target
        cands = [s for s in self.recent if s <= target and self._pose_of(s) is not None]
        return max(cands) if cands else None

    def _rechain_motion(self, target: int) -> None:
        """Re-anchor the motion model after a new reference at mapped frame ``target``.

        The map usually arrives late: by then the tracker has moved on past ``target``. Its
        motion history (the newest tracked poses) is kept, moved by the map's correction of
        ``target`` (``mapped @ inv(own estimate)``, left-multiplied as in :mod:`fmapping.geometry`),
        so the next prediction stays at the current frame. Resetting the history to the poses of
        ``target - 1`` and ``target`` would predict a pose many frames in the past: every later
        frame then fails the pose-jump / inlier checks and, lost frames never updating the
        motion model, tracking does not recover. When ``target`` is not older than the motion
        model (mapper in step with the tracker, or the tracker lost since), the history restarts
        from the mapped poses of ``target - 1`` and ``target``, extrapolated at constant velocity to
        the newest frame already answered."""
        hist = self.tracker.motion_history
        if self._motion_seq > target and hist:
            own, mapped = self.own_poses.get(target), self._pose_of(target)
            if own is not None and mapped is not None:
                corr = mapped @ np.linalg.inv(own.c2w)
                self.tracker.reset_motion([corr @ h for h in hist])
                self.counters.inc("motion_rechained")
            return
        prior = [h for h in (self._pose_of(s) for s in (target - 1, target)) if h is not None]
        ahead = self.last_seq - target  # frames already answered past target (lost ones): move the model there
        if len(prior) == 2 and 0 < ahead <= 64:
            step = np.linalg.inv(prior[0]) @ prior[1]  # the body motion of one frame (constant velocity)
            prior = [prior[1] @ np.linalg.matrix_power(step, ahead - 1), prior[1] @ np.linalg.matrix_power(step, ahead)]
        self.tracker.reset_motion(prior)
        self._motion_seq = max(target, self.last_seq) if len(prior) == 2 else target

    def _render_view(self, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """RGB (uint8) and depth (0 where the map is empty) of the map seen from ``c2w``."""
        from fmapping.render import render_image

        rc = self.render_cfg
        r = render_image(self.field, self.camera, c2w, rc["near"], rc["far"], int(rc["n_coarse"]),
                         n_importance=int(rc["n_fine"]))
        rgb = (r["rgb"].clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        depth = np.where(r["acc"].cpu().numpy() >= self.opts.min_acc, r["depth_normalized"].cpu().numpy(), 0.0)
        return rgb, depth.astype(np.float32)

    def _map_view(self):
        """Depth of the map we hold (only where the frames integrated into it looked, see
        :class:`fmapping.tracking.mapview.MapView`)."""
        from fmapping.tracking.mapview import MapView, MapViewConfig

        rc, o = self.render_cfg, self.opts
        cfg = MapViewConfig(n_coarse=int(rc["n_coarse"]), n_fine=int(rc["n_fine"]), min_acc=o.min_acc,
                            chunk=o.render_chunk, seen_only=o.seen_only)
        mapped = self._mapped_poses()
        return MapView(self.field, self.field.aabb, self.camera, rc["near"], rc["far"], cfg,
                       mapped if (o.seen_only and mapped) else None)

    def _mapped_poses(self) -> list:
        """Poses of the frames integrated into the map we hold (the mapper's, up to ``map_seq``)."""
        out = [c for s, c in self.mapper_poses.items() if s <= self.map_seq]
        if self.snapshot_pose is not None and self.snapshot_pose[0] not in self.mapper_poses:
            out.append(self.snapshot_pose[1])
        return out

    def _make_reference(self, seq: int) -> bool:
        f = self.recent.get(seq)
        c2w = self._pose_of(seq)
        if c2w is None or self.field is None:
            return False
        t0 = time.perf_counter()
        if f is None:  # never saw this frame (restart / late join): a view rendered from the map
            rgb, depth = self._render_view(c2w)
            what, counter = "rendered reference", "references_rendered"
        else:
            rgb, what, counter = np.asarray(f.rgb), "reference", "references"
            if self.opts.use_depth and f.depth is not None:
                depth = np.asarray(f.depth)
            else:
                depth = self._map_view().depth_fn(c2w)
        try:
            self.tracker.set_reference(rgb, depth, c2w, frame_index=seq)
        except ValueError as e:
            self.counters.inc("reference_failures")
            self.last_error = f"{what} at frame {seq}: {e}"
            return False
        self.ref_seq = seq
        self.counters.inc(counter)
        self.counters.set("reference_ms", round((time.perf_counter() - t0) * 1e3, 1))
        return True

    def _emit(self, seq: int, stamp: float, c2w: np.ndarray, quality: Optional[float]) -> list[Output]:
        """The pose of frame ``seq``, preceded by ``quality = 0`` answers for frames that never
        reached us (dropped upstream), so that nobody waits for them."""
        out: list[Output] = []
        if 0 <= self.last_seq < seq - 1 and seq - self.last_seq <= 1024:
            for s in range(self.last_seq + 1, seq):
                out.append(self._skip(s))
        self.last_seq = max(self.last_seq, seq)
        out.append(("poses", P.Pose(seq=seq, timestamp=stamp, c2w=orthonormalize(c2w), source="tracker",
                                    quality=quality)))
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
        out: list[Output] = []
        while self.waiting:
            seq, f = next(iter(self.waiting.items()))
            if self.field is None or self.tracker is None:
                if len(self.waiting) > self.opts.max_buffer:
                    out.append(self._drop_oldest())
                    continue
                break
            if seq <= self.map_seq:
                # mapped already (e.g. the init frames): its pose comes from the mapper, right after the snapshot
                c2w = self.mapper_poses.get(seq)
                if c2w is not None:
                    self.waiting.popitem(last=False)
                    self.tracker.observe(c2w)
                    self._motion_seq = seq
                    self.counters.inc("poses_from_mapper")
                    out += self._emit(seq, f.timestamp, c2w, None)
                    continue
                if self.map_seq not in self.mapper_poses and len(self.waiting) <= self.opts.max_buffer:
                    break  # the window's poses are on their way
                # not in the mapper's window (e.g. the mapper follows GT poses): track it like any frame
            if self._ref_target is not None:
                target = self._reference_frame(self._ref_target)
                if target is None and len(self.waiting) <= self.opts.max_buffer:
                    break  # the mapper's pose of its newest frame is on its way
                self._ref_target = None
                if target is not None and self._make_reference(target):
                    self._rechain_motion(target)
            self.waiting.popitem(last=False)
            if self.tracker.reference is None:
                # a map but no usable reference (e.g. the map is still empty there): answer, never stall
                self.counters.inc("frames_lost")
                self.counters.inc("frames_without_reference")
                out += self._emit(seq, f.timestamp, self.tracker.predict(), 0.0)
                continue
            out += self._track(f)
        self.counters.set("waiting_frames", len(self.waiting))
        return out

    def _track(self, f: P.Frame) -> list[Output]:
        res = self.tracker.track(np.asarray(f.rgb))
        out = self._answer(f, res)
        if not res.lost and res.need_keyframe:
            self.counters.inc("keyframe_requests")
            self._make_reference(f.seq)
        return out

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
        self._motion_seq = f.seq
        return float(max(res.inlier_ratio, 1e-6))

    def _answer(self, f: P.Frame, res) -> list[Output]:
        """Count a tracking result of the map front end and publish its pose (``quality = 0`` when lost)."""
        quality = self._count(f, res)
        if quality <= 0:
            return self._emit(f.seq, f.timestamp, res.c2w, 0.0)
        self._keep_own(f.seq, res.c2w, f.timestamp, quality)
        return self._emit(f.seq, f.timestamp, res.c2w, quality)


RESUME_KEYS = {"index": 0, "gray": 2, "c2w": 2, "world": 2, "uv": 2, "prev_index": 0, "prev_c2w": 2}  # key: ndim


def save_resume_state(path, states: list) -> None:
    """``states`` (:meth:`MonoFrontend.keyframe_states`) as one .npz (``k<i>_<key>``), written
    atomically (temp file, fsync, rename)."""
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, fsync=True) as fh:
        np.savez(fh, **{f"k{i}_{k}": np.asarray(st[k]) for i, st in enumerate(states) for k in RESUME_KEYS})


def _resume_entry(z, i: int) -> dict:
    """Keyframe ``i`` of a loaded state file, checked (ValueError / KeyError when it is not one)."""
    st = {k: np.array(z[f"k{i}_{k}"]) for k in RESUME_KEYS}
    bad = [k for k, nd in RESUME_KEYS.items() if st[k].ndim != nd]
    n = len(st["world"])
    if bad or st["c2w"].shape != (4, 4) or st["world"].shape != (n, 3) or st["uv"].shape != (n, 2) \
            or not all(np.isfinite(st[k]).all() for k in ("c2w", "world", "uv", "prev_c2w")):
        raise ValueError(f"keyframe {i}: unexpected arrays {bad or 'shapes'}")
    st["index"], st["prev_index"] = int(st["index"]), int(st["prev_index"])
    return st


def load_resume_state(path) -> Optional[list]:
    """The keyframes :func:`save_resume_state` wrote (oldest first), or None when there is no such file
    or it is not one (logged)."""
    from pathlib import Path

    if not Path(path).is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            count = len({name.split("_", 1)[0] for name in z.files})
            states = [_resume_entry(z, i) for i in range(count)]
        if not states or len({st["gray"].shape for st in states}) != 1:
            raise ValueError("no keyframes, or images of different sizes")
    except (OSError, ValueError, KeyError, EOFError) as e:
        log.warning("ignoring the tracker state %s: %s", path, e)
        return None
    return states


def load_tracker_config(path=None):
    from fmapping.config import load_config
    from fmapping.tracking.direct_tracker import TrackerConfig

    return load_config(TrackerConfig(), path)
