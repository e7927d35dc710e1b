"""The paper-style ``map`` front end of :class:`~fmapping.slam.run.SlamRun` (``slam.frontend: map``): init stage
with checks and retries, tracking against rendered map depth, the constant-depth (degraded) fallback, render-compare.
"""
from __future__ import annotations

import logging
import time
from typing import Optional

import numpy as np

from fmapping.geometry import scale_about
from fmapping.tracking.direct_tracker import DirectTracker, TrackerConfig
from fmapping.tracking.mapview import MapView

log = logging.getLogger("fmapping.slam")


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


class MapFrontend:
    """The map front end of :class:`~fmapping.slam.run.SlamRun`, a mixin: it shares the run's state
    (``ds``, ``cfg``, ``camera``, ``mapper``, ``tracker``, ``view``, ``est``, ``degraded`` ...) and uses
    its ``_iter``, ``_new_mapper`` and ``_add_to_mapper``."""

    # -------------------------------------------------------------- photometric (map front end)
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
