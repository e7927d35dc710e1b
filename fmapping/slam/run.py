"""One SLAM run over a dataset (:class:`SlamRun`): set-up, external pose sources, the mono front end
driven through :mod:`fmapping.session`, the closing stage and the output poses. The ``map`` front end is
the :class:`~fmapping.slam.map_frontend.MapFrontend` mixin. See :mod:`fmapping.slam`.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.cancel import Cancelled, StopFn
from fmapping.geometry import inv_pose, scale_about
from fmapping.mapping import Mapper
from fmapping.session import PoseSession, SlamSession, session_config_from
from fmapping.slam.config import SlamConfig
from fmapping.slam.map_frontend import MapFrontend
from fmapping.tracking.direct_tracker import DirectTracker
from fmapping.tracking.mapview import MapView


# ----------------------------------------------------------------------------- the loop
class SlamRun(MapFrontend):
    """State of one SLAM run over a dataset (see the :mod:`fmapping.slam` docstring)."""

    def __init__(self, ds, cfg: SlamConfig, poses: str = "photometric", out: Optional[Path] = None,
                 progress: bool = True, should_stop: StopFn = None):
        self.ds = ds
        self.should_stop = should_stop  # asked before every frame and mapper iteration (fmapping.cancel)
        self.stopped_at: Optional[int] = None  # the first frame not processed, when a stop request ended the run
        self.cfg = cfg
        self.camera = ds.camera
        self.poses_mode = poses
        self.out = out
        self.progress = progress
        self.has_gt = any(p is not None for p in ds.gt_poses)
        self.gt0 = ds.gt_poses[0] if self.has_gt and ds.gt_poses[0] is not None else None
        self.c2w0 = self.gt0 if (self.gt0 is not None and cfg.anchor_world_gt) else np.eye(4)
        self.use_depth = bool(cfg.mapper.use_depth and ds.has_depth)
        anchor = cfg.scale_anchor
        if anchor == "auto":
            anchor = "gt" if self.gt0 is not None else ("depth" if ds.has_depth else "none")
        if anchor == "gt" and self.gt0 is None:
            raise ValueError("slam.scale_anchor 'gt' needs ground-truth poses in the dataset")
        if anchor == "depth" and not ds.has_depth:
            raise ValueError("slam.scale_anchor 'depth' needs depth images in the dataset")
        if self.use_depth:
            anchor = "none"  # metric already
        self.anchor = anchor if poses == "photometric" else "none"
        self.scale = 1.0  # output = scale_about(internal, c2w0 centre, scale)
        self.track_ms: dict[int, float] = {}
        self.track_info: dict[int, dict] = {}
        self.loss_events: list[dict] = []
        self.pose_updates = 0  # mapper poses replaced by bundle-adjusted ones (mapper_follows_ba)
        self.window_stats: list[dict] = []
        self.est: dict[int, np.ndarray] = {}  # dataset index -> internal c2w
        self.fid_of: dict[int, int] = {}  # dataset index -> mapper frame id
        self.notes: list[str] = []
        self.mapper: Optional[Mapper] = None
        self.degraded = False  # True while the map cannot give depth: references use the constant-depth plane
        self.boot_scale = 1.0
        self.init_degraded = False
        self.frontend = None  # the session's MonoFrontend (mono front end)
        self.session: Optional[SlamSession] = None
        self.tracker: Optional[DirectTracker] = None
        self.view: Optional[MapView] = None
        self._rc = None

    # -------------------------------------------------------------- set-up
    def _new_mapper(self, init_frames: int) -> Mapper:
        """The mapper bounds the scene itself (``mapper.bbox`` when given, else its triangulated points)."""
        mcfg = dataclasses.replace(self.cfg.mapper, init_frames=init_frames)
        return Mapper(mcfg, self.camera, should_stop=self.should_stop)

    # -------------------------------------------------------------- external pose sources
    def _external_poses(self) -> list:
        ds = self.ds
        if self.poses_mode == "gt":
            if not self.has_gt:
                raise ValueError(f"--poses gt: dataset {ds.root} has no ground-truth poses")
            return list(ds.gt_poses)
        if self.poses_mode == "kiss-icp":
            if not ds.has_depth:
                raise ValueError(f"--poses kiss-icp needs depth images; dataset {ds.root} has none")
            from fmapping.tracking.sources import KissIcpOdometry

            odo = KissIcpOdometry(self.camera, self.cfg.kiss_icp, self.c2w0)
            out = []
            for i in self._iter(range(len(ds)), "kiss-icp"):
                f = ds[i]
                if f.depth is None:
                    raise ValueError(f"frame {i} of {ds.root} has no depth image")
                t0 = time.perf_counter()
                out.append(odo.register(f.depth))
                self.track_ms[i] = (time.perf_counter() - t0) * 1000
            return out
        from fmapping.tracking.sources import ensure_path, poses_from_file

        return poses_from_file(ensure_path(self.poses_mode), np.asarray(ds.timestamps))

    def _iter(self, it, desc: str):
        """The frame indices ``it`` (with a progress bar), up to the first one at which a stop was requested."""
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = it = tqdm(it, desc=desc, unit="frame")
        try:
            for i in it:
                if self.stop_requested:
                    self.stopped_at = int(i)
                    return
                yield i
        finally:
            if bar is not None:
                bar.close()

    @property
    def stop_requested(self) -> bool:
        return self.should_stop is not None and bool(self.should_stop())

    def run(self) -> None:
        """Track and map every frame (with the mapper's closing stage), or up to a stop request:
        then without the closing stage, and ``stopped_at`` says where it ended."""
        try:
            if self.poses_mode == "photometric":
                self.run_photometric()
            else:
                self.run_external()
        except Cancelled:  # inside a mapper update: its frame is the last one with a pose
            pass
        if self.stop_requested:
            if self.stopped_at is None:
                self.stopped_at = max(self.est, default=-1) + 1
            self.notes.append(f"stopped on request before frame {self.stopped_at}; no closing optimisation")
            return
        try:
            self.finish()
        except Cancelled:  # during the closing optimisation: every frame has its pose, the map is as far as it got
            self.stopped_at = len(self.ds)
            self.notes.append("stopped on request during the closing optimisation")

    def run_external(self) -> None:
        poses = self._external_poses()
        self.mapper = self._new_mapper(self.cfg.mapper.init_frames)
        for i in self._iter(range(len(self.ds)), "mapping"):
            if poses[i] is None:
                continue
            f = self.ds[i]
            self.est[i] = np.asarray(poses[i], np.float64)
            self._add_to_mapper(i, f.rgb, poses[i], f.timestamp, f.depth)

    # -------------------------------------------------------------- photometric
    def _add_to_mapper(self, i: int, rgb, c2w, ts, depth) -> Optional[dict]:
        fid = len(self.fid_of)
        st = self.mapper.add_frame(rgb, c2w, ts, depth if self.use_depth else None)
        self.fid_of[i] = fid
        if st is not None:
            d = st.to_dict()
            d["after_frame"] = i
            self.window_stats.append(d)
            return d
        return None

    # -------------------------------------------------------------- monocular front end
    def _anchor_pose(self, k: int) -> Optional[np.ndarray]:
        """Frame ``k``'s anchor pose (``scale_anchor`` "gt"): its GT pose in the run's world frame (frame 0
        at ``c2w0``), or None. A bootstrap that starts at frame ``k`` takes world frame and scale from it."""
        g = self.ds.gt_poses[k] if self.anchor == "gt" else None
        if g is None:
            return None
        return self.c2w0 @ inv_pose(self.gt0) @ np.asarray(g, np.float64)

    def run_mono(self) -> None:
        """The mono front end driven through a :class:`~fmapping.session.SlamSession`, which owns the policy
        (bootstrap buffer, late-anchor hold, bundle-adjusted poses to the mapper)."""
        cfg = self.cfg
        n = len(self.ds)
        # A failed bootstrap starts again at the next frame (the frames before get no pose). With a GT anchor
        # each start takes its world pose and baseline from its own first frame's anchor pose; without one
        # the world frame is c2w0 and the scale the bootstrap's unit depth.
        anchored = self.anchor == "gt"
        poses = PoseSession(self.camera, cfg.tracker, cfg.mono, session_config_from(cfg),
                            c2w0=None if anchored else self.c2w0)
        sess = SlamSession(poses, lambda: self._new_mapper(cfg.mapper.init_frames), feed_lost=cfg.feed_lost_frames,
                           use_depth=self.use_depth, on_window=self._on_window)
        self.frontend = poses.frontend
        self.session = sess
        boot = []
        i = 0
        t_boot = time.perf_counter()
        while i < n and not poses.initialized:
            f = self.ds[i]
            boot.append(f.index)
            a = self._anchor_pose(f.index) if anchored else None
            if a is not None:
                poses.add_anchor(f.index, a)
            self._apply(sess.push(f))
            i += 1
        if not poses.initialized:
            self.notes.append(f"monocular bootstrap failed on all {len(boot)} frames ({poses.bootstrap_failures} "
                              "starts); falling back to the map front end (constant-depth guesses)")
            self.frontend = self.session = None
            self.run_photometric_map()
            return
        fe = self.frontend = poses.frontend  # a restarted bootstrap made a new front end
        if poses.bootstrap_failures:
            self.notes.append(f"monocular bootstrap restarted {poses.bootstrap_failures} times: frames before "
                              f"{min(poses.bootstrapped)} have no pose")
        boot_ms = (time.perf_counter() - t_boot) * 1000 / max(1, len(boot) - 1)
        for k in boot:
            self.track_ms[k] = boot_ms if k else 0.0
        self.init_report = {"frontend": "mono", **fe.init_info, "bootstrap_ms_per_frame": boot_ms}
        if fe.init_info.get("scale_from") == "unit_depth":
            self.anchor = "none"
        for i in self._iter(range(i, n), "slam"):
            f = self.ds[i]
            a = self._anchor_pose(f.index) if anchored and poses.scale_pending else None
            if a is not None:  # the late anchor
                poses.add_anchor(f.index, a)
            # map depth for new keyframes; the front end uses it only where it agrees with the landmarks
            extra = self.view.depth_fn if self.view is not None else None
            ups = sess.push(f, extra_depth=extra)
            r = poses.last
            info = r.to_dict()
            self.track_ms[i] = info["ms"]
            self.track_info[i] = info
            self.est[i] = r.c2w
            if r.lost:
                self.loss_events.append({"frame": i, "reason": r.reason, "inlier_ratio": r.inlier_ratio,
                                         "reference": r.reference})
            self._apply(ups)
        self._apply(sess.finish())  # the sequence ended before the late anchor: the bootstrap's scale stays
        # BA-refined poses of every tracked frame
        for k, p in fe.poses().items():
            self.est[k] = p
        self.init_report["late_anchor"] = fe.late_anchor
        self.init_report["ba"] = {"runs": len(fe.ba_stats),
                                  "ms_median": float(np.median([b["ms"] for b in fe.ba_stats]))
                                  if fe.ba_stats else None,
                                  "rms_after_px_median": float(np.median([b["rms_after_px"] for b in fe.ba_stats]))
                                  if fe.ba_stats else None}

    def _apply(self, ups) -> None:
        """The session's pose updates into the run's estimates and counts."""
        sess = self.session
        self.mapper, self.fid_of, self.pose_updates = sess.mapper, sess.fid_of, sess.pose_updates
        for u in ups:  # a pose the mapper took (tracked, released after the late anchor, or refined by the BA)
            if u.index in self.fid_of:
                self.est[u.index] = u.c2w

    def _on_window(self, d: dict) -> None:
        self.mapper = self.session.mapper
        self.window_stats.append(d)
        self._after_window(d)

    def _after_window(self, win) -> None:
        if win is not None and self.mapper is not None and self.mapper.initialized:
            self.view = MapView.from_mapper(self.mapper, self.cfg.map_view)

    def run_photometric(self) -> None:
        if self.cfg.frontend == "mono" and not self.use_depth:
            self.run_mono()
        else:
            self.run_photometric_map()

    # -------------------------------------------------------------- finishing
    def finish(self) -> None:
        if self.mapper is None:
            return
        st = self.mapper.finish()
        if st is not None:
            self.window_stats.append(st.to_dict())
        # the mapper may have refined poses (init frames, or windows if it optimises poses)
        if self.init_degraded or (self.frontend is not None and not self.cfg.mapper_refines_init):
            return  # init poses: the mapper's refinement failed its check, or it did not refine
        refined = self.mapper.frame_poses()
        for i, fid in self.fid_of.items():
            if fid in refined:
                self.est[i] = refined[fid]

    def output_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(frame indices, c2w) of every frame from the first with a pose up to where the run ended (a later
        frame without one keeps the previous pose). Frames before the first pose (a monocular bootstrap
        that started again further on) are left out."""
        c = self.c2w0[:3, 3]
        n = len(self.ds) if self.stopped_at is None else self.stopped_at
        first = min((i for i in self.est if i < n), default=n)
        idx, out = [], []
        last = None
        for i in range(first, n):
            p = self.est.get(i, last)
            last = p
            idx.append(i)
            out.append(scale_about(p, c, self.scale))
        return np.asarray(idx, np.int64), (np.stack(out) if out else np.zeros((0, 4, 4)))
