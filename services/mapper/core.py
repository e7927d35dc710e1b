"""Mapper service core (zenoh-free): frames + poses in, field / points snapshots out.

:class:`MapperCore` owns a :class:`fmapping.mapping.Mapper`. The shell
(``python -m services.mapper``) feeds it raw payloads from the bus; the core decodes
them (:mod:`fmapping.protocol`), matches frames and poses by frame number ``seq``, adds
frames to the mapper in order and returns the messages to publish:

* a :class:`~fmapping.protocol.FieldSnapshot` after every init / window / final update
  (also kept encoded for the ``map/latest`` queryable),
* the refined poses of the window frames as ``Pose(source="mapper")``,
* a :class:`~fmapping.protocol.PointsSnapshot` at most every ``points_interval`` seconds
  (and at the end).

Pose sources: ``gt`` / ``external`` / ``tracker`` (key ``poses/<source>``). Given poses are
trusted, as by ``fmapping map`` and ``fmapping slam`` (``optimize_init_poses`` off). A later pose
for a frame already integrated replaces its pose (``refined_poses``; the mono tracker sends the
poses its bundle adjustment moved). Before the map is initialised a frame may enter
without a pose when ``unposed_init`` is on (the mapper then guesses and optimises its init
poses, the first ``anchor_frames`` fixed by the anchor source): that is for the tracker's ``map`` front end,
which cannot track before there is a map; the default ``mono`` tracker poses every frame itself. A frame
waits for its pose; when more than ``max_pending`` frames wait, one of them is dropped
(``frames_without_pose``), thinned evenly, frames known not to be keyframes first, the oldest kept
(:meth:`MapperCore._thin_waiting`), and a frame whose pose has not come within ``pose_timeout`` seconds (a
dead or restarted producer) is dropped. The acknowledgement (``ack``) is the newest frame number consumed
(integrated or dropped): the player's flow control waits on it.

Bad input (undecodable payload, a frame whose size or intrinsics differ from the first
frame's) is counted and never changes the state. The state is checkpointed atomically
(``torch.save`` to a temp file, fsync, rename) every ``checkpoint_every`` windows and
restored with ``torch.load(weights_only=True)``.
"""
from __future__ import annotations

import bisect
import dataclasses
import logging
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from fmapping import protocol as P
from fmapping.fileio import atomic_open, write_json
from fmapping.geometry import orthonormalize
from fmapping.map_outputs import map_mesh, map_points
from services.core_support import ServiceCore, ranked_victim
from services.mapper.intake import KeyframeBook, book_for

log = logging.getLogger("fmapping.mapper")

POSE_SOURCES = ("tracker", "gt", "external")
CHECKPOINT_VERSION = 1


@dataclass
class MapperServiceOptions:
    pose_source: str = "gt"
    out: Optional[str] = None  # where map.ply, mesh.ply, traj.txt, stats.json go at the end
    checkpoint: Optional[str] = None  # default OUT/checkpoint.pt when out is set
    checkpoint_every: int = 1  # windows between checkpoints (0 = never)
    resume: bool = True
    keep_checkpoint: bool = False  # keep it after a completed run
    unposed_init: Optional[bool] = None  # frames may enter init without a pose (default: no)
    anchor_source: Optional[str] = None  # poses fixing the first frames (scale) of an unposed init; default gt
    anchor_frames: int = 2
    anchor_wait: int = 2  # an unposed init's frame waits for its anchor pose until this many later frames came
    points_interval: float = 2.0  # seconds between PointsSnapshots
    max_points: int = 100_000  # per PointsSnapshot
    final_points: int = 500_000  # map.ply
    max_pending: int = 64  # frames waiting for their pose
    pose_timeout: float = 30.0  # seconds a frame waits for its pose before it is skipped (0 = forever)
    # the player sends the frames a restarted pose source never handled again (io play --resend-to): the
    # frames waiting for a pose then wait for the new source's answers instead of being skipped at once
    resent_frames: bool = False
    max_poses: int = 4096  # poses waiting for their frame
    # keyframes (services.mapper.intake): "source" trusts Pose.keyframe, "motion" flags them by camera motion,
    # "auto" = source for the tracker, motion for gt / external poses (which flag none)
    keyframes: str = "auto"
    keyframe_every: int = 5  # motion rule: at least every this many frames ...
    keyframe_move_m: float = 0.05  # ... or when the camera moved this far / turned this much since the last one
    keyframe_turn_deg: float = 5.0
    # frames waiting beyond which non-keyframes are skipped and windows take more frames (0: never; paced playback)
    behind_frames: int = 10
    # ... but only while frames keep coming: once none has arrived for this long (the stream ended or
    # paused: no camera to keep up with), every posed frame it holds is integrated (deferred windows)
    stream_idle_s: float = 2.0
    # the closing refinement also runs the window iterations a paced run would have spent on the frames since the
    # init and this run did not (frames thinned or skipped, windows over more frames), times the mapper config's
    # owed_iters_factor, so that the final map matches a paced run's; at most this many extra iterations
    max_owed_iters: int = 2000
    publish_mapper_poses: bool = True
    write_mesh: bool = True
    mesh_resolution: int = 96  # marching-cubes grid per axis

    def validate(self) -> "MapperServiceOptions":
        if self.pose_source not in POSE_SOURCES:
            raise ValueError(f"pose source must be one of {', '.join(POSE_SOURCES)}, got {self.pose_source!r}")
        if self.max_pending < 1 or self.max_poses < 1:
            raise ValueError("max_pending and max_poses must be >= 1")
        if self.unposed_init is None:
            self.unposed_init = False
        if self.anchor_source is None:
            self.anchor_source = "gt" if self.unposed_init else ""
        if self.anchor_source == self.pose_source:
            self.anchor_source = ""
        if self.keyframes == "auto":
            self.keyframes = "source" if self.pose_source == "tracker" else "motion"
        if self.keyframes not in ("source", "motion"):
            raise ValueError(f"keyframes must be auto, source or motion, got {self.keyframes!r}")
        if self.keyframe_every < 1 or self.behind_frames < 0 or not self.stream_idle_s >= 0:
            raise ValueError("keyframe_every must be >= 1, behind_frames >= 0 and stream_idle_s >= 0")
        return self


Output = tuple[str, Any]  # (channel, message): channel in field | points | poses


class MapperCore(ServiceCore):
    """See the module docstring. Single-threaded: call it from one worker thread."""

    CHANNELS = {"frames": P.Frame, "poses": P.Pose, "control": P.Control}

    def __init__(self, cfg, opts: Optional[MapperServiceOptions] = None, counters=None, device=None,
                 on_bad_input=None, clock=time.monotonic, should_stop=None, book: Optional[KeyframeBook] = None):
        from fmapping.mapping import MapperConfig

        super().__init__(counters, on_bad_input)
        self.clock = clock  # for the pose timeout (injectable in tests)
        self.should_stop = should_stop  # asked between iterations and rendered views (fmapping.cancel)
        self._arrived: dict[int, float] = {}
        self._source_seq: Optional[int] = None  # the pose source's last status counter
        self.source_state: Optional[str] = None  # ... and its state (None: it never reported one)
        self._orphaned = -1  # frames up to this one wait for a pose that will never come (source restarted)
        self._source_restarted = False  # resent_frames: a restarted source has not answered a new frame yet
        self.opts = (opts or MapperServiceOptions()).validate()
        self.cfg = cfg if cfg is not None else MapperConfig()
        if not self.opts.unposed_init:  # every frame comes with its pose: trusted, as fmapping map / slam do
            self.cfg = dataclasses.replace(self.cfg, optimize_init_poses=False)
        self.device = device
        self.mapper = None
        self.frames: "OrderedDict[int, P.Frame]" = OrderedDict()
        self.poses: dict[int, P.Pose] = {}
        self.anchors: dict[int, P.Pose] = {}
        self._stopped = False  # finish() has begun: no frame waits for its anchor pose any more (as the tracker)
        self.seq_of_fid: list[int] = []
        self.last_seq = -1  # newest frame integrated or dropped (the acknowledgement)
        self.version = 0
        self.windows = 0
        self.latest_field: Optional[P.FieldSnapshot] = None
        self.latest_field_bytes: Optional[bytes] = None
        self.latest_points: Optional[P.PointsSnapshot] = None
        self.interrupted = False  # set by the shell when a stop request cancelled an update half-way
        self.paused = False
        self.finished = False
        self._last_points = time.monotonic()  # the first points snapshot comes one interval after start
        self._points_dirty = False
        self.resumed_from: Optional[str] = None
        self._newest_ts = float("-inf")
        self._acked_ts = float("-inf")
        out = Path(self.opts.out) if self.opts.out else None
        self.out = out
        ck = self.opts.checkpoint or (str(out / "checkpoint.pt") if out else None)
        self.checkpoint_path = Path(ck) if ck else None
        self.book = book if book is not None else book_for(self.opts)  # keyframe flags (shared with the inbox)
        self.backlog: Callable[[], int] = lambda: 0  # frames queued before the core (the shell's inbox)
        self.init_seq: Optional[int] = None  # the newest frame consumed when the init stage ran
        self.window_iters = 0  # iterations of the windows since

    # ------------------------------------------------------------ inputs
    @property
    def ack(self) -> int:
        return self.last_seq

    @property
    def lag(self) -> float:
        """Seconds (of sequence time) between the newest frame received and the newest integrated."""
        if not np.isfinite(self._newest_ts) or not np.isfinite(self._acked_ts):
            return 0.0
        return max(0.0, self._newest_ts - self._acked_ts)

    def apply(self, msg: P.Message) -> list[Output]:
        if isinstance(msg, P.Frame):
            return self.on_frame(msg)
        if isinstance(msg, P.Pose):
            return self.on_pose(msg)
        if isinstance(msg, P.Control):
            return self.on_control(msg)
        raise ValueError(f"MapperCore: unexpected message {type(msg).__name__}")

    def admit_pose(self, data: bytes, key: str = "") -> Optional[P.Pose]:
        """:meth:`admit` a pose and note its keyframe flag at once (the zenoh callback): the inbox asks the
        flags when it must evict a frame, before the worker reaches the pose."""
        msg = self.admit("poses", data, key)
        if msg is not None and msg.source == self.opts.pose_source and msg.seq > self.last_seq:
            self.book.note(msg)
        return msg

    def on_frame(self, f: P.Frame) -> list[Output]:
        cam = self.frame_camera(f, undistorted=True)  # the first frame fixes it: only one the mapper can use
        if cam is None:
            return []
        self.camera_dict = cam
        if f.seq <= self.last_seq or f.seq in self.frames:
            self.counters.inc("stale_frames")
            return []
        self.took_frame(f.seq)
        self.frames[f.seq] = f
        self._arrived[f.seq] = self.clock()
        self._newest_ts = max(self._newest_ts, f.timestamp)
        self.counters.inc("frames_received")
        if len(self.frames) > 1 and f.seq < next(reversed(self.frames)):
            self.frames = OrderedDict(sorted(self.frames.items()))
        return self._integrate()

    def on_pose(self, p: P.Pose) -> list[Output]:
        if p.source and p.source == self.opts.anchor_source:
            if len(self.seq_of_fid) < self.opts.anchor_frames and p.seq > self.last_seq:
                self.anchors[p.seq] = p
                while len(self.anchors) > self.opts.max_poses:
                    self.anchors.pop(min(self.anchors))
                self.counters.inc("anchor_poses")
                return self._integrate()
            return []
        if p.source != self.opts.pose_source:
            self.counters.inc("ignored_poses")
            return []
        if p.seq <= self.last_seq:
            return self._refine_pose(p)
        self.book.note(p)
        self.poses[p.seq] = p
        self.counters.inc("poses_received")
        if self._source_restarted:  # the restarted source's first answer: it will not answer earlier frames
            self._source_restarted = False
            return self._orphan_waiting(before=p.seq)
        while len(self.poses) > self.opts.max_poses:
            self.poses.pop(min(self.poses))
            self.counters.inc("dropped_poses")
        return self._integrate()

    def on_source_status(self, st: P.Status) -> list[Output]:
        """The pose source's heartbeat. When its counter starts over (a restarted tracker or
        producer), the frames already waiting for a pose will never get one: the new process never
        saw them. They are skipped now (``orphaned_frames``) instead of after ``pose_timeout``,
        which would hold the player's window that long. With ``resent_frames`` the player sends
        them to the new process again: they wait for its answers, and only those before its first
        answer are skipped (it answers in order)."""
        if st.service != self.opts.pose_source:
            return []
        self.source_state = st.state
        prev, self._source_seq = self._source_seq, st.seq
        if prev is None or st.seq >= prev:
            return []
        self.counters.inc("source_restarts")
        if self.opts.resent_frames:  # they come again: the new source answers them, in order
            self._source_restarted = True
            return []
        return self._orphan_waiting()

    def _orphan_waiting(self, before: Optional[int] = None) -> list[Output]:
        """Skip the frames waiting for a pose (those before frame ``before``): their source restarted
        and will never answer them."""
        waiting = [s for s in self.frames if s not in self.poses and (before is None or s < before)]
        if waiting:
            self._orphaned = max(self._orphaned, max(waiting))
        return self._integrate()

    def _refine_pose(self, p: P.Pose) -> list[Output]:
        """A new pose for a frame already integrated (e.g. the tracker's bundle adjustment moved
        it) replaces the mapper's; one for a frame it never integrated is stale."""
        i = bisect.bisect_left(self.seq_of_fid, p.seq)  # frames are integrated in seq order
        usable = p.quality is None or p.quality > 0.0
        if self.mapper is None or i == len(self.seq_of_fid) or self.seq_of_fid[i] != p.seq or not usable:
            self.counters.inc("stale_poses")
            return []
        try:
            self.mapper.set_poses({i: np.array(p.c2w)})
        except ValueError as e:
            self.bad_input(f"pose {p.seq}: {e}", "rejected_poses")
            return []
        self.counters.inc("refined_poses")
        return []

    def on_control(self, c: P.Control) -> list[Output]:
        self.counters.inc(f"control_{c.command}")
        if c.command == "pause":
            self.paused = True
        elif c.command in ("resume", "start"):
            self.paused = False
            return self._integrate()
        elif c.command == "reset":
            self.reset()
        elif c.command == "save":
            self.save_checkpoint()
            if self.out is not None:
                self.write_outputs(final=False)
        elif c.command == "stop":
            return self.finish()
        elif c.command == "refine":
            return self.refine(c.args.get("iters"))
        return []

    def refine(self, iters=None) -> list[Output]:
        """The global refinement over all keyframes now (``Control(refine, {iters: N})``), the run goes on."""
        if self.mapper is None or not self.mapper.initialized or self.finished:
            return []
        if iters is not None and (isinstance(iters, bool) or not isinstance(iters, int) or not 0 < iters <= 100_000):
            self.bad_input(f"refine: iters must be an integer in 1..100000, got {iters!r}", "rejected_controls")
            return []
        stats = self.mapper.refine(iters)
        if stats is None:
            return []
        self.counters.inc("refinements")
        return self._after_update(stats)

    # ------------------------------------------------------------ mapping
    def _ensure_mapper(self) -> None:
        if self.mapper is None:
            from fmapping.camera import PinholeCamera
            from fmapping.mapping import Mapper

            self.mapper = Mapper(self.cfg, PinholeCamera.from_dict(self.camera_dict), device=self.device,
                                 should_stop=self.should_stop)

    def _integrate(self) -> list[Output]:
        out: list[Output] = []
        while self.frames and not self.paused and not self.finished:
            seq, frame = next(iter(self.frames.items()))
            pose = self.poses.pop(seq, None)
            initialized = self.mapper is not None and self.mapper.initialized
            unposed_ok = self.opts.unposed_init and not initialized
            if pose is not None and pose.quality is not None and pose.quality <= 0.0:
                # the producer says this pose is unusable (e.g. the tracker lost the frame)
                self.counters.inc("unusable_poses")
                if not unposed_ok:
                    self.frames.popitem(last=False)
                    self.counters.inc("frames_skipped")
                    self.last_seq = max(self.last_seq, seq)
                    continue
                pose = None
            if pose is None and unposed_ok and len(self.seq_of_fid) < self.opts.anchor_frames:
                pose = self.anchors.pop(seq, None)
                if pose is None and self.opts.anchor_source and not self._stopped \
                        and len(self.frames) + self.backlog() <= self.opts.anchor_wait:
                    break  # its anchor is on its way: frames and anchor poses travel on different keys
            if pose is None and not unposed_ok:
                waited = self.clock() - self._arrived.get(seq, self.clock())
                timed_out = self.opts.pose_timeout > 0 and waited > self.opts.pose_timeout
                orphaned = seq <= self._orphaned
                if timed_out or orphaned:
                    if orphaned:
                        self.counters.inc("orphaned_frames")
                    self.frames.popitem(last=False)
                    self.counters.inc("frames_without_pose")
                    if timed_out:
                        self.counters.inc("pose_timeouts")
                    self.last_seq = max(self.last_seq, seq)
                    continue
                if len(self.frames) > self.opts.max_pending:
                    self._thin_waiting()
                    continue
                break
            behind = self.behind()
            streaming = self.stream_idle() < self.opts.stream_idle_s
            if pose is not None and behind and streaming and self.mapper is not None and self.mapper.initialized \
                    and not self.book.is_keyframe(seq):
                self.frames.popitem(last=False)  # catching up: keyframes only
                self.counters.inc("frames_thinned")
                self.last_seq = max(self.last_seq, seq)
                continue
            self.frames.popitem(last=False)
            out += self._add(frame, pose, defer=behind)
        for d in (self.poses, self.anchors, self._arrived):
            for s in [s for s in d if s <= self.last_seq]:
                del d[s]
        self.book.forget_before(self.last_seq + 1)
        if self.mapper is not None and self.mapper.initialized:
            self.anchors.clear()
        return out

    def _thin_waiting(self) -> None:
        """More than ``max_pending`` frames wait behind one whose pose has not come (e.g. the mono tracker
        holds its bootstrap's poses until the late anchor): drop one of them, thinned evenly among those
        of the lowest keyframe rank (:func:`services.core_support.ranked_victim`: frames known not to be
        keyframes first, then those with no pose yet; the oldest and the newest stay), so that the
        bootstrap's first frame, a keyframe whose pose comes last, is not dropped for being the oldest."""
        seqs = list(self.frames)
        i, _ = ranked_victim(seqs, [self.book.rank(s) for s in seqs])
        seq = seqs[i]
        del self.frames[seq]
        self._arrived.pop(seq, None)
        self.poses.pop(seq, None)
        self.counters.inc("frames_without_pose")
        if i == 0:
            self.last_seq = max(self.last_seq, seq)

    def behind(self) -> bool:
        """More than ``behind_frames`` frames wait (here and in the shell's inbox): catch up."""
        n = self.opts.behind_frames
        return n > 0 and len(self.frames) + self.backlog() > n

    def owed_iters(self) -> float:
        """Window iterations a paced run spends on the frames consumed since the init (``iters_per_window`` per
        ``new_frames_per_window`` frames), minus those this run spent: what catching up skipped."""
        if self.init_seq is None:
            return 0.0
        frames = self.last_seq - self.init_seq
        return frames * self.cfg.iters_per_window / self.cfg.new_frames_per_window - self.window_iters

    def _add(self, f: P.Frame, pose: Optional[P.Pose], defer: bool = False) -> list[Output]:
        self._ensure_mapper()
        t0 = time.perf_counter()
        try:
            stats = self.mapper.add_frame(np.array(f.rgb), None if pose is None else np.array(pose.c2w),
                                          timestamp=f.timestamp, depth=None if f.depth is None else np.array(f.depth),
                                          defer=defer, frame_no=f.seq)
        except ValueError as e:  # the library refused this frame: count it, keep going
            self.bad_input(f"frame {f.seq}: {e}", "rejected_frames")
            self.last_seq = max(self.last_seq, f.seq)
            return []
        self.seq_of_fid.append(f.seq)
        self.last_seq = max(self.last_seq, f.seq)
        self._acked_ts = f.timestamp
        self.counters.inc("frames_processed")
        self.counters.inc("frames_unposed" if pose is None else "frames_posed")
        if self.book.is_keyframe(f.seq):
            self.counters.inc("keyframes_integrated")
        if stats is None:
            return []
        now = self.clock()  # the update kept us from reading poses: pending frames start waiting afresh
        for s in self._arrived:
            self._arrived[s] = now
        self.counters.set("last_window_s", round(time.perf_counter() - t0, 3))
        return self._after_update(stats)

    def _after_update(self, stats, points: bool = True) -> list[Output]:
        if stats.kind == "window":
            self.window_iters += stats.iterations
        elif stats.kind == "init":
            self.init_seq = self.last_seq
        self.windows += 1
        self.counters.set("windows", self.windows)
        self.counters.inc(f"updates_{stats.kind}")
        self.counters.set("last_loss", float(stats.loss) if np.isfinite(stats.loss) else -1.0)
        self._announce_keyframe()
        out: list[Output] = []
        snap = self.field_snapshot()
        if snap is not None:
            out.append(("field", snap))
        if self.opts.publish_mapper_poses:
            out += [("poses", p) for p in self.window_poses()]
        self._points_dirty = True
        if points and time.monotonic() - self._last_points >= self.opts.points_interval:
            pts = self.points_snapshot(self.opts.max_points)
            if pts is not None:
                out.append(("points", pts))
        if self.opts.checkpoint_every > 0 and self.windows % self.opts.checkpoint_every == 0:
            self.save_checkpoint()
        return out

    def _announce_keyframe(self) -> None:
        """Status counter ``last_keyframe``: the frame number (``seq``) of the newest keyframe. Keyframes
        are chosen only in an update; ``services.io view`` draws each one it is told of at its pose."""
        ids = self.mapper.keyframe_ids() if self.mapper is not None else []
        if ids and max(ids) < len(self.seq_of_fid):  # fid = index into seq_of_fid (frames in the order added)
            self.counters.set("last_keyframe", self.seq_of_fid[max(ids)])

    def tick(self) -> list[Output]:
        """Periodic work: frames whose pose timed out move on; a points snapshot when the map
        changed and the interval passed."""
        out = self._integrate() if self.frames else []
        if self._points_dirty and time.monotonic() - self._last_points >= self.opts.points_interval:
            pts = self.points_snapshot(self.opts.max_points)
            if pts is not None:
                out.append(("points", pts))
        return out

    def finish(self) -> list[Output]:
        """Integrate what can be, run the mapper's closing stage, write outputs; idempotent."""
        if self.finished:
            return []
        out: list[Output] = []
        self.paused = False
        self._stopped = True  # no frame waits for an anchor pose any more
        out += self._integrate()
        if self.frames:  # frames still without a pose: they cannot be mapped
            self.counters.inc("frames_without_pose", len(self.frames))
            self.last_seq = max(self.last_seq, max(self.frames))
            self.frames.clear()
        if self.mapper is not None:
            pending = self.cfg.iters_per_window if self.mapper.window_due() else 0  # finish runs that window
            owed = max(0.0, self.owed_iters() - pending)
            extra = int(min(self.opts.max_owed_iters, round(owed * self.cfg.owed_iters_factor)))
            self.counters.set("closing_extra_iters", extra)
            stats = self.mapper.finish(extra_iters=extra)
            if stats is not None:
                out += self._after_update(stats, points=False)
        self.finished = True
        if self.mapper is not None and self.mapper.field is not None:
            pts = self.points_snapshot(self.opts.max_points)
            if pts is not None:
                out.append(("points", pts))
        if self.out is not None:
            t0 = time.perf_counter()
            self.write_outputs(final=True)
            log.info("wrote the final map, mesh and trajectory in %.2f s", time.perf_counter() - t0)
        if self.checkpoint_path is not None and self.checkpoint_path.exists() and not self.opts.keep_checkpoint:
            self.checkpoint_path.unlink()
        return out

    @property
    def source_settled(self) -> bool:
        """Has the pose source sent everything it will? True once its status says done (or error), and for a
        source that never reported a status (GT, an external producer): nothing to wait for."""
        return self.source_state is None or self.source_state in ("done", "error")

    def reset(self) -> None:
        """Forget the map and pending inputs (frame numbers already consumed stay consumed)."""
        self.mapper = None
        self.camera_dict = None
        self.frames.clear()
        self.poses.clear()
        self.anchors.clear()
        self._arrived.clear()
        self.seq_of_fid = []
        self.latest_field = None
        self.latest_points = None
        self.latest_field_bytes = None
        self.finished = self._stopped = False
        self.counters.inc("resets")

    # ------------------------------------------------------------ outputs
    def field_snapshot(self, bump: bool = True) -> Optional[P.FieldSnapshot]:
        """The current field as a FieldSnapshot (a new version unless ``bump`` is False); kept for queries."""
        m = self.mapper
        if m is None or m.field is None:
            return None
        if bump:
            self.version += 1
        from fmapping.fileio import plain_tree

        arrays = {k: np.ascontiguousarray(v) for k, v in m.field.snapshot().items()}
        cfg = self.cfg
        config = {"field": plain_tree(dataclasses.asdict(cfg.field)), "near": cfg.near, "far": cfg.far,
                  "n_coarse": cfg.n_coarse, "n_fine": cfg.n_fine, "camera": self.camera_dict}
        last_fid = len(self.seq_of_fid) - 1
        poses = m.frame_poses() if last_fid >= 0 else {}
        snap = P.FieldSnapshot(version=self.version, kind=cfg.field.kind, config=config,
                               aabb=m.aabb.detach().cpu().numpy().astype(np.float64), arrays=arrays,
                               frame_seq=self.seq_of_fid[-1] if self.seq_of_fid else -1, timestamp=time.time(),
                               frame_c2w=orthonormalize(poses[last_fid]) if last_fid in poses else None)
        data = P.encode(snap)
        self.latest_field, self.latest_field_bytes = snap, data
        self.counters.set("field_version", self.version)
        self.counters.set("field_bytes", len(data))
        return snap

    def window_poses(self) -> list[P.Pose]:
        m = self.mapper
        poses = m.frame_poses()
        stamps = m.frame_timestamps()
        out = []
        for fid in m.window_ids():
            if 0 <= fid < len(self.seq_of_fid) and fid in poses:
                out.append(P.Pose(seq=self.seq_of_fid[fid], timestamp=float(stamps.get(fid, 0.0)),
                                  c2w=orthonormalize(poses[fid]), source="mapper"))
        return out

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """(timestamps, c2w (N, 4, 4), frame numbers) of every mapped frame, in order."""
        if self.mapper is None:
            return np.zeros(0), np.zeros((0, 4, 4)), []
        poses, stamps = self.mapper.frame_poses(), self.mapper.frame_timestamps()
        fids = sorted(poses)
        c2w = np.stack([poses[i] for i in fids]) if fids else np.zeros((0, 4, 4))
        return (np.array([stamps[i] for i in fids]), c2w,
                [self.seq_of_fid[i] for i in fids if i < len(self.seq_of_fid)])

    def points_snapshot(self, max_points: int) -> Optional[P.PointsSnapshot]:
        if self.mapper is None or self.mapper.field is None:
            return None
        t0 = time.perf_counter()
        pts, cols = map_points(self.mapper, max_points)
        self._last_points = time.monotonic()
        self._points_dirty = False
        self.counters.set("points", len(pts))
        self.counters.set("points_ms", round((time.perf_counter() - t0) * 1e3, 1))
        self.latest_points = P.PointsSnapshot(version=self.version, points=pts, colors=cols, frame_seq=self.last_seq)
        return self.latest_points

    def write_outputs(self, final: bool = True, quick: bool = False) -> dict:
        """OUT/map.ply (points), OUT/mesh.ply, OUT/traj.txt, OUT/stats.json. ``quick`` (on a signal):
        the cheap live-snapshot points and no mesh, to stop within seconds."""
        from fmapping.ply import write_ply
        from fmapping.trajectory import write_tum_trajectory

        out = self.out
        out.mkdir(parents=True, exist_ok=True)
        files = {}
        ts, c2w, seqs = self.trajectory()
        if len(ts):
            files["traj"] = str(write_tum_trajectory(out / "traj.txt", ts, c2w))
        if self.mapper is not None and self.mapper.field is not None:
            last = self.latest_points
            if quick and (last is not None and last.version == self.version or self.interrupted):
                # stopping on a signal: the newest live snapshot costs nothing (none yet: no map file)
                pts, cols = (last.points, last.colors) if last is not None else (None, None)
            else:
                pts, cols = map_points(self.mapper, self.opts.final_points, final=not quick, quick=quick,
                                       should_stop=None if quick else self.should_stop)
            if pts is not None:
                files["map"] = str(write_ply(out / "map.ply", pts, cols))
            if self.opts.write_mesh and not quick:
                v, f, c = map_mesh(self.mapper, self.opts.mesh_resolution, should_stop=self.should_stop)
                files["mesh"] = str(write_ply(out / "mesh.ply", v, c, faces=f))
        stats = {"final": final, "frames": len(seqs), "field_version": self.version, "files": files,
                 "counters": self.counters.snapshot(), "pose_source": self.opts.pose_source,
                 "resumed_from": self.resumed_from}
        if self.mapper is not None:
            stats["mapper"] = self.mapper.stats()
        write_json(out / "stats.json", stats)
        return files

    # ------------------------------------------------------------ checkpoints
    def save_checkpoint(self) -> Optional[Path]:
        """torch.save of the mapper state + the service's bookkeeping: temp file, fsync, rename."""
        if self.checkpoint_path is None or self.mapper is None:
            return None
        import torch

        t0 = time.perf_counter()
        path = self.checkpoint_path
        path.parent.mkdir(parents=True, exist_ok=True)
        state = {
            "version": CHECKPOINT_VERSION,
            "mapper": self.mapper.state_dict(),
            "service": {"seq_of_fid": list(self.seq_of_fid), "last_seq": int(self.last_seq),
                        "version": int(self.version), "windows": int(self.windows),
                        "camera": dict(self.camera_dict), "pose_source": self.opts.pose_source,
                        "init_seq": self.init_seq, "window_iters": int(self.window_iters)},
        }
        with atomic_open(path, fsync=True, fsync_folder=True) as fh:
            torch.save(state, fh)
        self.counters.inc("checkpoints")
        self.counters.set("checkpoint_ms", round((time.perf_counter() - t0) * 1e3, 1))
        return path

    def load_checkpoint(self, path=None) -> bool:
        """Resume from a checkpoint (weights_only load); False when there is none."""
        from fmapping.camera import PinholeCamera
        from fmapping.mapping import Mapper

        path = Path(path) if path else self.checkpoint_path
        if path is None or not path.is_file():
            return False
        state = read_checkpoint(path)
        svc = state["service"]
        if svc.get("pose_source") != self.opts.pose_source:
            log.warning("checkpoint %s was made with pose source %s, now %s", path, svc.get("pose_source"),
                        self.opts.pose_source)
        mapper = Mapper(self.cfg, PinholeCamera.from_dict(svc["camera"]), device=self.device,
                        should_stop=self.should_stop)
        mapper.load_state_dict(state["mapper"])
        self.mapper = mapper
        self.camera_dict = dict(svc["camera"])
        self.seq_of_fid = [int(s) for s in svc["seq_of_fid"]]
        self.last_seq = int(svc["last_seq"])
        self.version = int(svc["version"])
        self.windows = int(svc["windows"])
        self.init_seq = None if svc.get("init_seq") is None else int(svc["init_seq"])
        self.window_iters = int(svc.get("window_iters", 0))
        self.resumed_from = str(path)
        self.counters.set("resumed_at_seq", self.last_seq)
        self.counters.set("resumed_windows", self.windows)
        self.counters.set("windows", self.windows)
        self.counters.inc("resumes")
        if mapper.field is not None:
            self.field_snapshot(bump=False)
        return True


def load_mapper_config(path=None, overrides: Optional[dict] = None):
    """MapperConfig from YAML (``fmapping.config.load_config``)."""
    from fmapping.config import load_config
    from fmapping.mapping import MapperConfig

    return load_config(MapperConfig(), path, overrides)


def await_source_final(get: Callable[[float], Optional[tuple]], core: MapperCore, publish: Callable[[list], None],
                       timeout: float, clock: Callable[[], float] = time.monotonic, quiet: float = 0.5,
                       should_stop: Callable[[], bool] = lambda: False) -> bool:
    """At the stream's end, before the closing stage: take the inbox's items (``get(timeout)`` -> (channel,
    (key, message)) or None) until the pose source reports it is done, at most ``timeout`` seconds. The
    tracker answers the stop with its last poses: the frames it still held and the ones a bundle adjustment
    moved when it merged the one in flight (a loop closure's often). Closing before they came mapped the
    whole run on poses they would have moved (``fmapping up`` at 30 fps over 1,000 frames: the mapper's poses
    1.9 cm from the tracker's final ones, median). Its status can overtake the last of them (seen: 233 of
    745 came after it), so once it says done the items are taken until none has come for ``quiet``
    seconds, within the same ``timeout``. Frames still queued behind the stop are taken too. A second
    stop is dropped; other controls apply. ``should_stop()`` (a signal) ends the wait at once. Returns True
    when the source settled in time."""
    end = clock() + timeout
    while not core.source_settled and clock() < end and not should_stop():
        item = get(0.1)
        if item is not None:
            _take(core, publish, item)
    settled = core.source_settled
    # a source without a status, or one that never settled: only what is queued already
    wait = quiet if settled and core.source_state is not None else 0.0
    while not should_stop():
        item = get(max(0.0, min(wait, end - clock())))
        if item is None:
            return settled
        _take(core, publish, item)
    return settled


def _take(core: MapperCore, publish: Callable[[list], None], item: tuple) -> None:
    channel, (_, msg) = item
    if channel in ("end", "control") and msg.command == "stop":
        core.counters.inc("stops_while_ending")
        return
    publish(core.on_source_status(msg) if channel == "status" else core.apply(msg))


def read_checkpoint(path) -> dict:
    """The state a mapper checkpoint holds (``torch.load(weights_only=True)``); a ValueError naming the file
    when it is not one."""
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"{path}: not a readable mapper checkpoint: {e}") from None
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: not a mapper checkpoint of version {CHECKPOINT_VERSION}")
    return state
