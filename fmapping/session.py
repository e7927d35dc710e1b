"""The incremental SLAM session: what the monocular front end's poses become, written once.

:class:`PoseSession` takes frames one at a time (``push``) and returns the :class:`PoseUpdate` records
a consumer acts on. It owns the policy between the front end and whoever uses its poses:

* **bootstrap buffering**: frames go to the two-view bootstrap until it succeeds; then every buffered
  frame gets its pose at once. The world frame is the anchor pose of the first frame (``add_anchor``,
  e.g. GT or an external pose stream) or the identity, and the anchors' baselines fix the scale.
* **late-anchor hold and release**: while the front end waits for its late scale anchor
  (``MonoFrontend.scale_pending``) nothing leaves; once the scale is fixed (or given up at ``finish``),
  the held poses leave as the front end has them then (rescaled).
* **republishing bundle-adjusted poses**: after a keyframe's bundle adjustment, the poses it moved by
  more than ``republish_min_m`` / ``republish_min_deg`` leave again (``kind == "refined"``).
* **skipped frames** (``skip``: a caller keeping pace with a camera does not track every frame): with
  ``interpolate_skipped`` such a frame between two tracked ones leaves just before the next one, its pose
  on the way between theirs, and is kept like a tracked frame (bundle adjustments move it); otherwise, and
  when the next frame is lost, it leaves with no pose (``kind == "skipped"``).

:class:`SlamSession` adds the mapper: it integrates every released pose with its frame, hands refined
poses to the mapper and runs the closing optimisation at ``finish``. ``fmapping slam``
(:class:`fmapping.slam.SlamRun`) drives a :class:`SlamSession`; the tracker service drives a
:class:`PoseSession` and publishes its updates, which the mapper service integrates.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from fmapping.tracking.mono import MonoFrontend, moved_poses

SKIPPED, TRACKED, LOST, REFINED = "skipped", "tracked", "lost", "refined"


@dataclass
class SessionConfig:
    republish: bool = True  # hand on the poses a keyframe's bundle adjustment moved (``kind == "refined"``)
    republish_min_m: float = 1e-3  # ... by more than this many metres
    republish_min_deg: float = 0.05  # ... or degrees
    restart_failed_bootstrap: bool = False  # a failed bootstrap starts again at the next frame (else ``failed``)
    max_poses: Optional[int] = None  # handed-out poses remembered for the republish check (None: all)
    # a frame given to ``skip`` between two tracked frames gets the pose between theirs (else no pose): at 30 fps
    # the live tracker skips ~40 % of the frames, and mapping those too gave 96.3 % against 94.2 % (the 200-frame
    # room, GT poses, bench/results/probes_2026-12-05b/)
    interpolate_skipped: bool = True

    def validate(self) -> "SessionConfig":
        if self.republish_min_m < 0 or self.republish_min_deg < 0:
            raise ValueError("session republish thresholds must be >= 0")
        if self.max_poses is not None and self.max_poses < 1:
            raise ValueError(f"session.max_poses must be >= 1 or None, got {self.max_poses}")
        return self


@dataclass(frozen=True)
class PoseUpdate:
    """A pose for frame ``index``. ``kind``: ``tracked``; ``lost`` (a prediction, ``quality == 0``);
    ``skipped`` (no pose at all, e.g. a frame of a failed bootstrap: ``c2w`` is the identity); ``refined``
    (a pose handed out before, moved by the bundle adjustment; ``timestamp`` / ``quality`` as before).
    ``keyframe``: the front end made this frame a keyframe (parallax / overlap; the bootstrap's keyframes
    too): a consumer that cannot keep up keeps these and thins the others."""
    index: int
    timestamp: float
    c2w: np.ndarray
    quality: float
    kind: str = TRACKED
    keyframe: bool = False

    @property
    def usable(self) -> bool:
        return self.quality > 0


def no_pose(index: int, timestamp: float) -> PoseUpdate:
    """The answer for frame ``index`` that has no pose (``kind == "skipped"``, ``quality = 0``, identity ``c2w``)."""
    return PoseUpdate(index, timestamp, np.eye(4), 0.0, SKIPPED)


class PoseSession:
    """The front end's poses under the session policy (module docstring). ``c2w0`` / ``baseline``
    fix world frame and scale anchor explicitly (``fmapping slam`` with GT); without them they come from
    the poses given to :meth:`add_anchor`."""

    def __init__(self, camera, tracker_cfg, mono_cfg=None, cfg: Optional[SessionConfig] = None,
                 c2w0: Optional[np.ndarray] = None, baseline: Optional[Callable[[int], Optional[float]]] = None,
                 anchors: Optional[dict] = None):
        self.camera, self.tracker_cfg, self.mono_cfg = camera, tracker_cfg, mono_cfg
        self.cfg = (cfg or SessionConfig()).validate()
        self._given_c2w0, self._given_baseline = c2w0, baseline
        # anchor poses of the frames the bootstrap may still use (``anchors``: a dict the caller fills and bounds)
        self.anchors: dict[int, np.ndarray] = {} if anchors is None else anchors
        self.published: dict[int, PoseUpdate] = {}  # usable poses handed out (the republish check's reference)
        self.last = None  # TrackResult of the newest tracked frame (None while bootstrapping)
        self.bootstrap_failures = 0
        self.bootstrapped: list[int] = []  # the frames the successful bootstrap gave poses to
        self.failed = False  # the bootstrap failed and is not restarted (``restart_failed_bootstrap`` off)
        self._held: list[PoseUpdate] = []
        self._merges_seen = 0  # the front end's background BAs merged, when last republished
        self.interpolated = 0  # skipped frames given an interpolated pose
        self._new_frontend()

    def _new_frontend(self) -> None:
        self.frontend = MonoFrontend(self.camera, self.tracker_cfg, self.mono_cfg)
        self._merges_seen = 0
        self.c2w0: Optional[np.ndarray] = None  # world pose of the bootstrap's first frame
        self._first_anchored: Optional[np.ndarray] = None
        self._boot: dict[int, float] = {}  # frames held by the bootstrap -> timestamp
        self._tracked: Optional[tuple[int, float]] = None  # (frame, timestamp) of the newest tracked frame
        self._skipped: Optional[tuple[int, float, int, float]] = None  # a skipped frame waiting for the next

    # ------------------------------------------------------------ state
    @property
    def initialized(self) -> bool:
        return self.frontend.initialized

    @property
    def scale_pending(self) -> bool:
        return self.frontend.scale_pending

    def holds(self, index: int) -> bool:
        """Is frame ``index`` waiting in the session (bootstrap buffer or held for the late anchor)?"""
        return (index in self._boot or any(u.index == index for u in self._held)
                or (self._skipped is not None and self._skipped[0] == index))

    def add_anchor(self, index: int, c2w: np.ndarray) -> None:
        """The anchor pose of frame ``index`` (world frame and scale of the bootstrap)."""
        self.anchors[index] = np.array(c2w)

    def anchor_baseline(self, index: int) -> Optional[float]:
        a = self.anchors.get(index)
        if a is None or self._first_anchored is None:
            return None
        return float(np.linalg.norm(a[:3, 3] - self._first_anchored[:3, 3]))

    # ------------------------------------------------------------ frames
    def push(self, index: int, rgb: np.ndarray, timestamp: float = 0.0, extra_depth=None,
             keyframe_later: bool = False) -> list[PoseUpdate]:
        """Frame ``index``: the pose updates it releases (possibly none while bootstrapping or holding). With
        ``keyframe_later`` a new keyframe's pose leaves before its keyframe work, which waits for
        :meth:`finish_keyframe` (or the next frame): what a caller at a camera's rate wants."""
        if not self.frontend.initialized:
            return self._bootstrap(index, rgb, timestamp)
        out = self.finish_keyframe()
        r = self.frontend.track(index, rgb, extra_depth=extra_depth, keyframe_later=keyframe_later)
        self.last = r
        out += self.release()  # the late anchor may have fixed the scale with this frame
        out += self._after_skipped(index, timestamp, r)
        self._tracked = None if r.lost else (index, timestamp)
        if r.lost:
            out += self._give(PoseUpdate(index, timestamp, np.array(r.c2w), 0.0, LOST))
        else:
            out += self._give(PoseUpdate(index, timestamp, np.array(r.c2w), float(max(r.inlier_ratio, 1e-6)),
                                         keyframe=self.frontend.is_keyframe(index)))
        merged = self.frontend.ba_merges != self._merges_seen  # a background BA (ba_thread) moved poses
        if (r.need_keyframe or merged) and not r.lost and self.cfg.republish and not self.frontend.keyframe_pending:
            out += self._refined()
        return out

    def finish_keyframe(self) -> list[PoseUpdate]:
        """The work of the keyframe the last :meth:`push` left for later (``keyframe_later``), and the poses it
        (and a bundle adjustment merged with it) moved; nothing when none waits."""
        if not self.frontend.initialized or self.frontend.finish_keyframe() is None or not self.cfg.republish:
            return []
        return self._refined()

    def skip(self, index: int, timestamp: float = 0.0) -> list[PoseUpdate]:
        """Frame ``index`` is not tracked (the caller keeps pace with a camera; never two in a row): what leaves
        now. With ``interpolate_skipped``, right after a tracked frame and with the scale fixed, nothing: the
        frame leaves with the next one, its pose interpolated. Else it leaves now with no pose."""
        prev = self._tracked
        self._tracked = None
        if (self.cfg.interpolate_skipped and prev is not None and self._skipped is None and self.initialized
                and not self.frontend.scale_pending):
            self._skipped = (index, timestamp, prev[0], prev[1])
            return []
        return [no_pose(index, timestamp)]

    def _after_skipped(self, index: int, timestamp: float, r) -> list[PoseUpdate]:
        """The frame skipped before frame ``index`` (tracked as ``r``): its pose between its neighbours', on
        the geodesic at its time between theirs, or no pose when ``index`` was lost."""
        if self._skipped is None:
            return []
        (k, t_k, before, t_b), self._skipped = self._skipped, None
        c2w = None
        if not r.lost:
            w = (t_k - t_b) / (timestamp - t_b) if timestamp > t_b else 0.5
            c2w = self.frontend.interpolate_frame(k, before, index, min(max(w, 0.0), 1.0))
        if c2w is None:
            return [no_pose(k, t_k)]
        self.interpolated += 1
        q = self.published[before].quality if before in self.published else 1.0
        return self._give(PoseUpdate(k, t_k, c2w, float(max(min(q, r.inlier_ratio), 1e-6))))

    def _bootstrap(self, index: int, rgb: np.ndarray, timestamp: float) -> list[PoseUpdate]:
        fe = self.frontend
        if self.c2w0 is None:
            self._first_anchored = self.anchors.get(index)
            given = self._given_c2w0
            self.c2w0 = given if given is not None else (
                self._first_anchored if self._first_anchored is not None else np.eye(4))
        self._boot[index] = timestamp
        baseline = self._given_baseline if self._given_c2w0 is not None else self.anchor_baseline
        poses = fe.bootstrap(index, np.asarray(rgb), self.c2w0, baseline)
        if fe.failed:
            self.bootstrap_failures += 1
            boot = self._boot
            if not self.cfg.restart_failed_bootstrap:
                self.failed = True
                return []
            self._new_frontend()
            return [no_pose(s, boot[s]) for s in sorted(boot)]
        if poses is None:
            return []
        out: list[PoseUpdate] = []
        self.bootstrapped = sorted(poses)
        self._tracked = (index, timestamp)
        for s in sorted(poses):
            out += self._give(PoseUpdate(s, self._boot.get(s, 0.0), np.array(poses[s]), 1.0,
                                         keyframe=fe.is_keyframe(s)))
        self._boot.clear()
        return out + self.release()

    def resume(self, index: int, rgb: np.ndarray, timestamp: float, states: list) -> Optional[list[PoseUpdate]]:
        """A restarted front end: re-localise frame ``index`` against saved keyframe ``states``
        (:meth:`MonoFrontend.keyframe_states`) and go on in their world frame and scale; None on a miss."""
        c2w = self.frontend.resume(index, np.asarray(rgb), states)
        if c2w is None:
            return None
        return self._give(PoseUpdate(index, timestamp, np.array(c2w), 1.0, keyframe=self.frontend.is_keyframe(index)))

    def _give(self, u: PoseUpdate) -> list[PoseUpdate]:
        """Hand ``u`` out, or hold it while the scale is about to change (a mapper would have integrated it)."""
        if self.frontend.scale_pending:
            self._held.append(u)
            return []
        if u.usable:
            self._remember(u)
        return [u]

    def _remember(self, u: PoseUpdate) -> None:
        self.published[u.index] = u
        if self.cfg.max_poses is not None:
            while len(self.published) > self.cfg.max_poses:
                self.published.pop(min(self.published))

    def release(self, settle: Optional[str] = None) -> list[PoseUpdate]:
        """Once the scale is fixed (or ``settle``: given up, for that reason), the held poses as the front
        end has them now (a lost frame's prediction moved with the rescale)."""
        fe = self.frontend
        if fe.scale_pending and settle is None:
            return []
        if fe.scale_pending:
            fe.settle_scale(settle)
        if not self._held and not self.anchors:
            return []  # released before (the usual case: every frame after the late anchor)
        self.anchors.clear()
        held, self._held = self._held, []
        now = fe.poses_for({u.index: u.c2w for u in held})
        out: list[PoseUpdate] = []
        for u in held:
            out += self._give(dataclasses.replace(u, c2w=np.array(now[u.index])))
        return out

    def _refined(self) -> list[PoseUpdate]:
        refined = self.frontend.refined_poses()
        self._merges_seen = self.frontend.ba_merges
        was = {s: self.published[s].c2w for s in refined if s in self.published}
        moved = moved_poses(was, refined, self.cfg.republish_min_m, self.cfg.republish_min_deg)
        out = []
        for s, c2w in sorted(moved.items()):
            u = dataclasses.replace(self.published[s], c2w=np.array(c2w), kind=REFINED)
            self.published[s] = dataclasses.replace(u, kind=self.published[s].kind)
            out.append(u)
        return out

    def finish(self, why: str = "the sequence ended before it") -> list[PoseUpdate]:
        """The stream ended: a bundle adjustment still in the worker (``MonoConfig.ba_thread``) is
        merged, the final one of all keyframes runs (``MonoConfig.final_ba``) and the poses they moved leave
        again, then the held poses leave (the late anchor is given up, for ``why``). Frames a bootstrap still
        holds are answered as skipped (no pose)."""
        out: list[PoseUpdate] = []
        if self._skipped is not None:  # no frame after it: no pose
            (k, t_k, _, _), self._skipped = self._skipped, None
            out.append(no_pose(k, t_k))
        if self.frontend.initialized and self.frontend.final_ba() and self.cfg.republish:
            out += self._refined()
        if not self.frontend.initialized and self._boot:
            boot, self._boot = self._boot, {}
            out += [no_pose(s, boot[s]) for s in sorted(boot)]
        return out + self.release(settle=why)


class SlamSession:
    """A :class:`PoseSession` feeding a mapper in the same process: every released usable pose is
    integrated with its frame (lost ones too with ``feed_lost``), refined poses move the mapper's
    (:meth:`Mapper.set_poses`), ``finish`` releases what is held and runs the mapper's closing stage.
    ``new_mapper()`` makes the mapper once the bootstrap succeeded; ``on_window(stats)`` is called after
    each mapping window (its stats dict, with ``after_frame``)."""

    def __init__(self, poses: PoseSession, new_mapper: Callable[[], object], feed_lost: bool = False,
                 use_depth: bool = False, on_window: Optional[Callable[[dict], None]] = None):
        self.poses = poses
        self.new_mapper = new_mapper
        self.feed_lost = feed_lost
        self.use_depth = use_depth
        self.on_window = on_window
        self.mapper = None
        self.fid_of: dict[int, int] = {}  # frame index -> mapper frame id
        self.pose_updates = 0  # mapper poses replaced by bundle-adjusted ones
        self._frames: dict = {}  # frames whose pose is not out yet (bootstrap, late anchor)
        self._windows: list[dict] = []

    def push(self, frame, extra_depth=None) -> list[PoseUpdate]:
        """Frame ``frame`` (``index``, ``rgb``, ``timestamp``, ``depth``): the pose updates it released,
        applied to the mapper."""
        self._frames[frame.index] = frame
        ups = self.poses.push(frame.index, frame.rgb, frame.timestamp, extra_depth)
        self._apply(ups)
        return ups

    def finish(self, why: str = "the sequence ended before it") -> list[PoseUpdate]:
        """Release what is held (the pose stream ended). The mapper's closing optimisation stays with the
        caller (``mapper.finish()``): a run stopped on request skips it."""
        ups = self.poses.finish(why)
        self._apply(ups)
        return ups

    def map_updates(self) -> list[dict]:
        """The mapping windows' stats since the last call."""
        out, self._windows = self._windows, []
        return out

    def _apply(self, ups: list[PoseUpdate]) -> None:
        if self.mapper is None and self.poses.initialized:
            self.mapper = self.new_mapper()
        refined = {}
        for u in ups:
            if u.kind == REFINED:
                if u.index in self.fid_of:
                    refined[self.fid_of[u.index]] = u.c2w
                continue
            f = self._frames.pop(u.index, None)
            if f is not None and u.kind != SKIPPED and (u.usable or self.feed_lost):
                self._add(f, u.c2w)
        if refined:
            self.pose_updates += self.mapper.set_poses(refined)
        for k in [k for k in self._frames if not self.poses.holds(k)]:
            del self._frames[k]  # answered without a pose the mapper takes (e.g. lost)

    def _add(self, f, c2w: np.ndarray) -> None:
        fid = len(self.fid_of)
        st = self.mapper.add_frame(f.rgb, c2w, f.timestamp, f.depth if self.use_depth else None)
        self.fid_of[f.index] = fid
        if st is not None:
            d = st.to_dict()
            d["after_frame"] = f.index
            self._windows.append(d)
            if self.on_window is not None:
                self.on_window(d)


def session_config_from(slam_cfg) -> SessionConfig:
    """The session policy of ``fmapping slam`` (:class:`fmapping.slam.SlamConfig`): a failed bootstrap
    starts again at the next frame, as in the tracker service."""
    return SessionConfig(republish=bool(slam_cfg.mapper_follows_ba), restart_failed_bootstrap=True)


__all__ = ["PoseSession", "PoseUpdate", "SessionConfig", "SlamSession", "session_config_from"]
