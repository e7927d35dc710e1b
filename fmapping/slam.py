"""The full SLAM loop behind ``fmapping slam``: track every frame, map with the tracked poses.

``run_slam(job)`` (:class:`fmapping.job.Job`) opens ``job.data`` and runs, frame by frame,

    pose source -> Mapper.add_frame -> (after each mapping window) refresh of the tracker's reference

and writes into ``job.out``: ``map.ply`` (coloured point cloud), ``mesh.ply``,
``traj.txt`` (TUM format, every frame), ``stats.json`` (per-frame tracking ms,
per-window mapping seconds, tracking-loss events, ATE against the GT when it exists).
``--no-export`` (``slam.export: false``) skips ``map.ply`` / ``mesh.ply`` (and the
reconstruction metrics); ``traj.txt`` and ``stats.json`` are still written.

Pose sources (``job.poses``):

* ``photometric`` (default): RGB only, front end :class:`~fmapping.tracking.mono.MonoFrontend`
  (``slam.frontend: mono``): KLT tracks and a two-view bootstrap give the first poses
  and sparse landmarks; every frame is then aligned photometrically
  (:class:`~fmapping.tracking.direct_tracker.DirectTracker`, the fast path) to the current
  keyframe, whose depth comes from the landmarks (with ``mono.dense_extra``, off by
  default, plus depth rendered from the map where mapped frames looked, at each keyframe
  where it agrees with the landmarks); keyframes are refined by a windowed bundle
  adjustment. The mapper receives the tracked poses (its init pose optimisation is
  off unless ``slam.mapper_refines_init``), and after each keyframe's bundle adjustment
  the poses it moved (``slam.mapper_follows_ba``, :meth:`Mapper.set_poses`).
  ``slam.frontend: map`` is the paper-style alternative: constant-depth bootstrap
  guesses refined by the mapper's init, then tracking against depth rendered from the
  map only (with init checks, retries and a constant-depth fallback). With ``--use-depth`` the sensor depth replaces the
  rendered depth for the references and supervises the mapper (RGB-D mode).
  ``slam.tracking: render_compare`` swaps the direct alignment of the map front end
  for render-and-compare through the field (slow; for comparison).
* ``kiss-icp``: kiss-icp odometry on back-projected depth (needs depth).
* ``gt`` / ``PATH.txt``: given poses (the loop is then the mapping job with tracking stats).

Scale and world frame (monocular RGB has no metric scale), in this order:

1. ground-truth poses in the dataset (``scale_anchor: auto|gt``): the world frame is
   the GT frame of frame 0 and the scale is the GT distance between frame 0 and the
   frame that completes the bootstrap (DIM-SLAM anchors its scale with the first GT
   poses in the same spirit), taken again between frames 0 and 14, the end of the
   init window (``mono.late_anchor_frames``): the front end is rescaled about frame 0
   then, and the mapper gets its first frames only after that, with the rescaled poses.
   With the map front end the same baseline is taken at the end of the init window
   and the remaining factor after the mapper's init is applied to everything written
   out (poses, map, mesh) as a similarity about frame 0. Evaluate with SE(3) (or none).
2. depth in the dataset (map front end, ``auto|depth``): the factor is the median
   ratio of sensor depth to rendered depth at the last init frame.
3. otherwise the median scene depth of the bootstrap is ``mono.unit_depth`` (mono)
   or the assumed ``init_depth`` plane (map); evaluate with Sim(3).

Init failure (map front end): after the init stage the first init frames are aligned
back to the last one with the rendered depth; if the inlier ratio is low or the map
renders too few pixels, init is retried with ``init_retry_frames`` more frames (up to
``init_retries`` times), then tracking falls back to constant-depth references until
the map renders depth (reported in ``notes``). A failed monocular bootstrap falls back
to the map front end. Tracking loss is reported per frame in ``tracking_loss_events``.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.cancel import Cancelled, StopFn
from fmapping.config import load_config, to_dict
from fmapping.geometry import scale_about
from fmapping.job import Job
from fmapping.map_outputs import MESH_RESOLUTION, write_map_outputs
from fmapping.mapping import Mapper, MapperConfig
from fmapping.pipeline import open_job_dataset, recon_stats, write_stats
from fmapping.session import PoseSession, SlamSession, session_config_from
from fmapping.tracking.direct_tracker import DirectTracker, TrackerConfig
from fmapping.tracking.mapview import MapView, MapViewConfig
from fmapping.tracking.mono import MonoConfig
from fmapping.tracking.render_compare import RenderCompareConfig
from fmapping.tracking.sources import KissIcpConfig

log = logging.getLogger("fmapping.slam")


@dataclass
class SlamConfig:
    mapper: MapperConfig = field(default_factory=MapperConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    map_view: MapViewConfig = field(default_factory=MapViewConfig)
    render_compare: RenderCompareConfig = field(default_factory=RenderCompareConfig)
    kiss_icp: KissIcpConfig = field(default_factory=KissIcpConfig)
    mono: MonoConfig = field(default_factory=MonoConfig)
    frontend: str = "mono"  # RGB-only front end: "mono" (two-view bootstrap + BA, sparse depth; map depth only with
    #                         mono.dense_extra) | "map" (mapper init from constant-depth guesses, rendered depth only)
    mapper_refines_init: bool = False  # let the mapper's init re-estimate the front end's init poses
    tracking: str = "direct"  # photometric tracking path: "direct" | "render_compare"
    init_depth: float = 2.0  # assumed depth of the constant-depth plane of the bootstrap (units if no anchor)
    scale_anchor: str = "auto"  # "auto" | "gt" | "depth" | "none"
    anchor_world_gt: bool = True  # put frame 0 at its GT pose when GT exists
    init_min_inlier_ratio: float = 0.6
    init_min_depth_fraction: float = 0.3  # fraction of reference pixels the map must render
    init_retries: int = 2
    init_retry_frames: int = 10
    refresh_every_window: bool = True  # re-render the reference depth after each mapping window
    feed_lost_frames: bool = False  # give the mapper frames whose tracking was lost (at the predicted pose)
    # After each keyframe bundle adjustment, give the mapper the poses of the frames it holds that the BA
    # moved by > 1 mm or 0.05 deg (mono front end). Synthetic rooms, 200 frames, completion ratio after Sim3,
    # seeds 1 / 2 / 3: 86.0 / 83.3 / 95.4 % without, 89.9 / 87.9 / 91.0 % handing on every pose at every
    # keyframe, 88.1 % (seed 2) / 96.0 % (seed 3) with the threshold.
    mapper_follows_ba: bool = True
    export: bool = True  # write map.ply / mesh.ply at the end (``--no-export`` turns it off)

    def validate(self) -> None:
        if self.frontend not in ("mono", "map"):
            raise ValueError(f"slam.frontend must be 'mono' or 'map', got {self.frontend!r}")
        if self.tracking not in ("direct", "render_compare"):
            raise ValueError(f"slam.tracking must be 'direct' or 'render_compare', got {self.tracking!r}")
        if self.scale_anchor not in ("auto", "gt", "depth", "none"):
            raise ValueError(f"slam.scale_anchor must be auto|gt|depth|none, got {self.scale_anchor!r}")
        if not self.init_depth > 0:
            raise ValueError(f"slam.init_depth must be > 0, got {self.init_depth}")
        self.mapper.validate()


def build_slam_config(job: Job) -> SlamConfig:
    """The config of a ``fmapping slam`` job: its YAML, then the job's depth, box, device, pose source."""
    cfg = load_config(SlamConfig(), job.config)
    m = cfg.mapper
    if job.use_depth:
        m = dataclasses.replace(m, use_depth=True)
    if job.bbox is not None:
        m = dataclasses.replace(m, bbox=tuple(tuple(map(float, r)) for r in job.bbox))
    dev = job.device
    if dev and dev != "auto":
        m = dataclasses.replace(m, device=dev)
    poses = job.poses
    if poses not in ("photometric",) or m.use_depth or (cfg.frontend == "mono" and not cfg.mapper_refines_init):
        # external poses are trusted; with sensor depth the bootstrap is RGB-D odometry, already metric
        m = dataclasses.replace(m, optimize_init_poses=False)
    cfg = dataclasses.replace(cfg, mapper=m)
    if not job.export:  # --no-export
        cfg = dataclasses.replace(cfg, export=False)
    cfg.validate()
    return cfg


# ----------------------------------------------------------------------------- helpers
def constant_depth(camera, depth: float) -> np.ndarray:
    return np.full((camera.height, camera.width), float(depth), np.float32)


def bootstrap_poses(rgbs: list, camera, c2w0: np.ndarray, tcfg: TrackerConfig, depth: float,
                    depths: Optional[list] = None) -> tuple[list, list]:
    """Initial guesses for the init window: direct alignment to a constant-depth plane (or sensor depth).

    Returns (poses, per-frame TrackResult dicts). New references (same constant depth)
    are taken when the tracker asks for a keyframe.
    """
    tr = DirectTracker(camera, tcfg)
    d0 = depths[0] if depths is not None and depths[0] is not None else constant_depth(camera, depth)
    tr.set_reference(rgbs[0], d0, c2w0, 0)
    tr.observe(c2w0)
    poses, info = [np.asarray(c2w0, np.float64)], [{}]
    for k in range(1, len(rgbs)):
        r = tr.track(rgbs[k])
        poses.append(r.c2w)
        info.append(r.to_dict())
        if r.need_keyframe and not r.lost:
            dk = depths[k] if depths is not None and depths[k] is not None else constant_depth(camera, depth)
            try:
                tr.set_reference(rgbs[k], dk, r.c2w, k)
            except ValueError:
                pass
    return poses, info


def _ate_block(est: np.ndarray, gt: list) -> Optional[dict]:
    from fmapping.metrics import ate

    ok = [i for i, g in enumerate(gt) if g is not None]
    if len(ok) < 3:
        return None
    e = np.stack([est[i] for i in ok])
    g = np.stack([gt[i] for i in ok])
    res = {}
    for a in ("se3", "sim3", "none"):
        try:
            r = ate(e, g, a)
            res[a] = {k: r[k] for k in ("rmse_m", "mean_m", "max_m", "rot_err_mean_deg", "rot_fit_mean_deg",
                                        "rot_fit_rmse_deg", "scale")}
        except ValueError as err:
            res[a] = {"error": str(err)}
    return res


def _sim3_to_gt(est: np.ndarray, gt: list) -> Optional[tuple]:
    """(s, R, t) aligning the estimated camera positions to the GT ones (as the Sim3 ATE does)."""
    from fmapping.metrics import align_trajectory

    ok = [i for i, g in enumerate(gt) if g is not None]
    if len(ok) < 3:
        return None
    try:
        return align_trajectory(np.stack([est[i] for i in ok]), np.stack([gt[i] for i in ok]), "sim3")[1]
    except (ValueError, np.linalg.LinAlgError):
        return None


# ----------------------------------------------------------------------------- the loop
class SlamRun:
    """State of one SLAM run over a dataset (see the module docstring)."""

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

    def _ref_depth(self, i: int, c2w: np.ndarray, sensor_depth):
        if self.use_depth and sensor_depth is not None:
            return sensor_depth
        if self.degraded:
            return constant_depth(self.camera, self.cfg.init_depth * self.boot_scale)
        return self.view.depth_fn(c2w)

    def _try_leave_degraded(self, i: int) -> None:
        """After a mapping window in degraded mode: switch to map depth once the map renders it."""
        ref = self.tracker.reference
        rgb = self._ref_rgb.get(ref.frame_index)
        if rgb is None:
            return
        try:
            probe = DirectTracker(self.camera, self.cfg.tracker)
            r = probe.set_reference(rgb, self.view.depth_fn(ref.c2w), ref.c2w, ref.frame_index)
        except ValueError:
            return
        if len(r.points) >= self.cfg.init_min_depth_fraction * self.cfg.tracker.num_points:
            self.degraded = False
            self.notes.append(f"frame {i}: the map renders depth; tracking switches from the constant-depth "
                              "fallback to map depth")
            self.tracker.set_reference(rgb, self.view.depth_fn(ref.c2w), ref.c2w, ref.frame_index)

    def _init_stage(self, n_total: int) -> int:
        """Bootstrap + mapper init, with retries. Returns the number of frames consumed."""
        cfg = self.cfg
        n_init = min(cfg.mapper.init_frames, n_total)
        attempt = 0
        while True:
            frames = [self.ds[i] for i in range(n_init)]
            rgbs = [f.rgb for f in frames]
            sensor = [f.depth for f in frames] if self.use_depth else None
            t0 = time.perf_counter()
            guesses, info = bootstrap_poses(rgbs, self.camera, self.c2w0, cfg.tracker, cfg.init_depth, sensor)
            boot_ms = (time.perf_counter() - t0) * 1000 / max(1, n_init - 1)
            pre_scale = 1.0
            if self.anchor == "gt" and n_init > 1:
                g = self.ds.gt_poses
                b_gt = np.linalg.norm(g[n_init - 1][:3, 3] - g[0][:3, 3]) if g[n_init - 1] is not None else 0.0
                b_est = np.linalg.norm(guesses[-1][:3, 3] - guesses[0][:3, 3])
                if b_gt > 1e-4 and b_est > 1e-6:
                    pre_scale = float(b_gt / b_est)
                    guesses = [scale_about(p, self.c2w0[:3, 3], pre_scale) for p in guesses]
            self.mapper = self._new_mapper(n_init)
            self.fid_of = {}
            self.window_stats = [w for w in self.window_stats if w.get("kind") != "init"]
            for i, f in enumerate(frames):
                self.track_ms[i] = boot_ms if i else 0.0
                self._add_to_mapper(i, f.rgb, guesses[i] if i else self.c2w0, f.timestamp, f.depth)
            if not self.mapper.initialized:
                self.mapper.finish()
            refined = self.mapper.frame_poses()
            for i in range(n_init):
                self.est[i] = refined[self.fid_of[i]]
            self.view = MapView.from_mapper(self.mapper, cfg.map_view)
            self.boot_scale = pre_scale
            ok, why = self._check_init(frames)
            self.init_report = {"frames": n_init, "attempt": attempt, "ok": ok, "why": why,
                                "bootstrap_scale": pre_scale, "bootstrap_ms_per_frame": boot_ms,
                                "bootstrap_lost": int(sum(bool(x.get("lost")) for x in info))}
            if ok or attempt >= cfg.init_retries or n_init + cfg.init_retry_frames > n_total:
                if not ok:
                    # never continue from a map that renders garbage: keep the bootstrap poses and
                    # track against constant-depth references until the map renders depth
                    self.degraded = True
                    for i in range(n_init):
                        self.est[i] = guesses[i]
                    self.notes.append(f"init failed after {attempt} retries ({why}); bootstrap poses kept, "
                                      "constant-depth tracking until the map renders depth")
                    self.init_report["degraded"] = True
                    self.init_degraded = True
                break
            attempt += 1
            n_init = min(n_total, n_init + cfg.init_retry_frames)
            log.warning("init failed (%s); retrying with %d frames", why, n_init)
        # tracker on the refined map
        self.tracker = DirectTracker(self.camera, cfg.tracker)
        last = n_init - 1
        self.tracker.set_reference(frames[last].rgb, self._ref_depth(last, self.est[last], frames[last].depth),
                                   self.est[last], last)
        self.tracker.reset_motion([self.est[max(0, last - 1)], self.est[last]])
        self._ref_rgb = {last: frames[last].rgb}
        self._scale_after_init(frames)
        return n_init

    def _check_init(self, frames) -> tuple[bool, str]:
        """Align the first init frame to the last one through the rendered depth."""
        if self.use_depth:
            return True, ""
        last = len(frames) - 1
        tr = DirectTracker(self.camera, self.cfg.tracker)
        try:
            ref = tr.set_reference(frames[last].rgb, self.view.depth_fn(self.est[last]), self.est[last], last)
        except ValueError as e:
            return False, f"map renders no depth at the last init frame ({e})"
        n_sel = self.cfg.tracker.num_points
        frac = len(ref.points) / max(1, n_sel)
        if frac < self.cfg.init_min_depth_fraction:
            return False, f"map renders depth at only {frac:.0%} of the reference pixels"
        worst = 1.0
        for k in (0, last // 2):
            r = tr.track(frames[k].rgb, c2w_guess=self.est[k])
            worst = min(worst, r.inlier_ratio if not r.lost else 0.0)
        if worst < self.cfg.init_min_inlier_ratio:
            return False, f"init frames re-align with inlier ratio {worst:.2f}"
        return True, ""

    def _scale_after_init(self, frames) -> None:
        n = len(frames)
        if self.anchor == "gt":
            g = self.ds.gt_poses
            b_gt = np.linalg.norm(g[n - 1][:3, 3] - g[0][:3, 3]) if g[n - 1] is not None else 0.0
            b_est = np.linalg.norm(self.est[n - 1][:3, 3] - self.est[0][:3, 3])
            if b_gt > 1e-4 and b_est > 1e-6:
                self.scale = float(b_gt / b_est)
        elif self.anchor == "depth":
            f = frames[-1]
            if f.depth is not None:
                uv = np.stack(np.meshgrid(np.arange(0, self.camera.width, 8), np.arange(0, self.camera.height, 8)),
                              -1).reshape(-1, 2).astype(np.float64)
                rd = self.view.depth_at(self.est[n - 1], uv)
                sd = f.depth[uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(np.float64)
                ok = np.isfinite(rd) & (rd > 0) & (sd > 0)
                if ok.sum() > 20:
                    self.scale = float(np.median(sd[ok] / rd[ok]))
        self.init_report["output_scale"] = self.scale

    def _render_compare(self):
        if self._rc is None:
            from fmapping.tracking.render_compare import RenderCompareTracker

            self._rc = RenderCompareTracker(self.view, self.cfg.render_compare)
        return self._rc

    # -------------------------------------------------------------- monocular front end
    def _anchor_fn(self):
        if self.anchor != "gt":
            return None
        g = self.ds.gt_poses

        def base(k: int):
            return None if g[k] is None else float(np.linalg.norm(g[k][:3, 3] - g[0][:3, 3]))
        return base

    def run_mono(self) -> None:
        """The mono front end driven through a :class:`~fmapping.session.SlamSession`, which owns the policy
        (bootstrap buffer, late-anchor hold, bundle-adjusted poses to the mapper)."""
        cfg = self.cfg
        n = len(self.ds)
        poses = PoseSession(self.camera, cfg.tracker, cfg.mono, session_config_from(cfg), c2w0=self.c2w0,
                            baseline=self._anchor_fn())
        sess = SlamSession(poses, lambda: self._new_mapper(cfg.mapper.init_frames), feed_lost=cfg.feed_lost_frames,
                           use_depth=self.use_depth, on_window=self._on_window)
        fe = self.frontend = poses.frontend
        self.session = sess
        boot = []
        i = 0
        t_boot = time.perf_counter()
        while i < n and not poses.initialized:
            f = self.ds[i]
            boot.append(f.index)
            self._apply(sess.push(f))
            i += 1
            if poses.failed:
                break
        if not poses.initialized:
            self.notes.append(f"monocular bootstrap failed after {len(boot)} frames; falling back to the "
                              "map front end (constant-depth guesses)")
            self.frontend = self.session = None
            self.run_photometric_map()
            return
        boot_ms = (time.perf_counter() - t_boot) * 1000 / max(1, len(boot) - 1)
        for k in boot:
            self.track_ms[k] = boot_ms if k else 0.0
        self.init_report = {"frontend": "mono", **fe.init_info, "bootstrap_ms_per_frame": boot_ms}
        if fe.init_info.get("scale_from") == "unit_depth":
            self.anchor = "none"
        for i in self._iter(range(i, n), "slam"):
            f = self.ds[i]
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

    def run_photometric_map(self) -> None:
        cfg = self.cfg
        n = len(self.ds)
        start = self._init_stage(n)
        for i in self._iter(range(start, n), "slam"):
            f = self.ds[i]
            if cfg.tracking == "render_compare":
                pred = self.tracker.predict()
                res = self._render_compare().track(f.rgb, pred)
                c2w, lost = res.c2w, False
                self.tracker.observe(c2w)
                info = {"ms": res.ms, "loss": res.loss, "lost": False}
                need_kf = False
            else:
                r = self.tracker.track(f.rgb)
                c2w, lost, need_kf = r.c2w, r.lost, r.need_keyframe
                info = r.to_dict()
            self.track_ms[i] = info["ms"]
            self.track_info[i] = info
            self.est[i] = c2w
            if lost:
                self.loss_events.append({"frame": i, "reason": info.get("reason", ""),
                                         "inlier_ratio": info.get("inlier_ratio"), "reference": info.get("reference")})
            win = None
            if not lost or cfg.feed_lost_frames:
                win = self._add_to_mapper(i, f.rgb, c2w, f.timestamp, f.depth)
            if cfg.tracking != "direct":
                continue
            if need_kf and not lost:
                try:
                    self.tracker.set_reference(f.rgb, self._ref_depth(i, c2w, f.depth), c2w, i)
                    self._ref_rgb = {i: f.rgb}
                except ValueError as e:
                    self.notes.append(f"frame {i}: no new reference ({e})")
            elif win is not None and self.degraded:
                self._try_leave_degraded(i)
            elif win is not None and cfg.refresh_every_window and not self.use_depth:
                ref = self.tracker.reference
                rgb = self._ref_rgb.get(ref.frame_index)
                if rgb is not None:
                    try:
                        self.tracker.set_reference(rgb, self._ref_depth(ref.frame_index, ref.c2w, None), ref.c2w,
                                                   ref.frame_index)
                    except ValueError as e:
                        self.notes.append(f"frame {i}: reference refresh failed ({e})")

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

    def output_poses(self) -> np.ndarray:
        """Every frame's pose up to where the run ended (a frame without one keeps the previous pose)."""
        c = self.c2w0[:3, 3]
        n = len(self.ds) if self.stopped_at is None else self.stopped_at
        out = []
        last = None
        for i in range(n):
            p = self.est.get(i, last)
            if p is None:
                p = self.c2w0
            last = p
            out.append(scale_about(p, c, self.scale))
        return np.stack(out)


def _export(run: SlamRun, out: Path) -> dict:
    """map.ply and mesh.ply from the keyframe and window views, in the output frame (scaled
    about frame 0 by the anchor)."""
    m = run.mapper
    cfg = run.cfg.mapper
    poses = m.frame_poses()
    kf = sorted(set(m.keyframe_ids()) | set(m.window_ids()))
    kf_poses = {k: poses[k] for k in kf if k in poses}
    return write_map_outputs(m, kf_poses, run.camera, out, near=cfg.near, far=cfg.far,
                             mesh_samples=(48, 16), mesh_resolution=MESH_RESOLUTION,
                             center=run.c2w0[:3, 3], scale=run.scale)


def run_slam(job: Job, should_stop: StopFn = None) -> dict:
    """Run the SLAM loop (see the module docstring); returns the stats dict with a ``summary``.
    ``should_stop()`` True ends it early: the frames so far are written, without the closing
    optimisation (``summary["stopped_at"]``: the first frame not processed)."""
    import torch

    from fmapping.trajectory import write_tum_trajectory

    t_start = time.perf_counter()
    ds = open_job_dataset(job)
    cfg = build_slam_config(job)
    poses_mode = job.poses or "photometric"
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    run = SlamRun(ds, cfg, poses_mode, out, progress=not job.quiet, should_stop=should_stop)
    run.run()
    t_loop = time.perf_counter() - t_start
    est = run.output_poses()
    write_tum_trajectory(out / "traj.txt", np.asarray(ds.timestamps, np.float64)[:len(est)], est)
    mapped = run.mapper is not None and (run.stopped_at is None or run.mapper.initialized)
    if run.stopped_at is not None:
        log.warning("stopped before frame %d of %d: wrote %s%s", run.stopped_at, len(ds), out / "traj.txt",
                    "; exporting the map so far" if cfg.export and mapped else "")
    export = _export(run, out) if cfg.export and mapped else None

    ms = np.array([run.track_ms[i] for i in sorted(run.track_ms)], np.float64)
    track_ms_after_init = np.array([run.track_info[i]["ms"] for i in sorted(run.track_info)], np.float64)
    wins = [w for w in run.window_stats if w.get("kind") == "window"]
    mstats = run.mapper.stats() if run.mapper is not None else {}
    stats = {
        "config": to_dict(cfg),
        "dataset": ds.describe(),
        "poses": poses_mode,
        "scale_anchor": run.anchor,
        "output_scale": run.scale,
        "init": getattr(run, "init_report", None),
        "frames": len(ds),
        "frames_mapped": len(run.fid_of),
        "tracking_ms": {str(i): run.track_ms[i] for i in sorted(run.track_ms)},
        "tracking": {str(i): run.track_info[i] for i in sorted(run.track_info)},
        "tracking_loss_events": run.loss_events,
        "loop_closures": run.frontend.loops if run.frontend is not None else [],
        "loops_refused": run.frontend.loops_refused if run.frontend is not None else [],
        "mapper_pose_updates": run.pose_updates,
        "windows": run.window_stats,
        "mapper": mstats,
        "export": export,
        "notes": run.notes,
        "map_depth_checks": run.frontend.dense_checks if run.frontend is not None else [],
        "seconds": {"loop": t_loop, "total": time.perf_counter() - t_start},
        "torch_threads": torch.get_num_threads(),
    }
    gt = list(ds.gt_poses)[:len(est)]  # the frames the run got to
    ate_res = _ate_block(est, gt) if run.has_gt else None
    stats["ate"] = ate_res
    if export is not None and export["points"] > 0:
        stats.update(recon_stats(ds, out, sim3=_sim3_to_gt(est, gt)))
    summary = {
        "out": str(out),
        "poses": poses_mode,
        "frames": len(ds),
        "frames_mapped": len(run.fid_of),
        "stopped_at": run.stopped_at,
        "tracking_loss_events": len(run.loss_events),
        "loop_closures": len(run.frontend.loops) if run.frontend is not None else 0,
        "relocalised_frames": sum(bool(v.get("relocalised")) for v in run.track_info.values()),
        "tracking_ms_median": float(np.median(track_ms_after_init)) if len(track_ms_after_init) else
        (float(np.median(ms)) if len(ms) else None),
        "tracking_ms_min": float(np.min(track_ms_after_init)) if len(track_ms_after_init) else None,
        "window_seconds_median": float(np.median([w["seconds"] for w in wins])) if wins else None,
        "init_seconds": mstats.get("init_seconds"),
        "total_seconds": stats["seconds"]["total"],
        "scale_anchor": run.anchor,
        "output_scale": run.scale,
        "init_ok": bool(getattr(run, "init_report", {}).get("ok", True)),
        "init_frames": getattr(run, "init_report", {}).get("frames"),
        "degraded_at_end": run.degraded,
    }
    if ate_res:
        for a in ("se3", "sim3", "none"):
            if "rmse_m" in ate_res.get(a, {}):
                summary[f"ate_{a}_rmse_m"] = ate_res[a]["rmse_m"]
                summary[f"ate_{a}_rot_deg"] = ate_res[a]["rot_err_mean_deg"]
                # orientation-only fit: the same for every position alignment, well posed on straight runs
                summary.setdefault("ate_rot_fit_deg", ate_res[a]["rot_fit_mean_deg"])
    return write_stats(out, stats, summary)
