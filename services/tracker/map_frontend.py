"""The tracker service's ``map`` front end, a mixin of :class:`~services.tracker.core.TrackerCore`: field snapshots
in, direct alignment against references with depth rendered from the mapper's field (protocol: the core's docstring).
"""
from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Optional

import numpy as np

from fmapping import protocol as P
from services.core_support import snapshot_problem, usable_camera

if TYPE_CHECKING:
    from services.tracker.core import Output


class MapFrontend:
    """Field snapshots and the ``map`` front end of :class:`~services.tracker.core.TrackerCore`, a mixin:
    it uses the core's state (``field``, ``tracker``, ``waiting``, ``recent``, ``mapper_poses``,
    ``own_poses`` ...) and its ``_emit``, ``_count``, ``_keep_own`` and ``_drop_oldest``."""

    # ------------------------------------------------------------ field snapshots
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
    # ------------------------------------------------------------ tracking (map front end)
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
                self.tracker.move_motion(corr)
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

    def _advance_map(self) -> list[Output]:
        """The map front end's part of :meth:`TrackerCore._advance`: answer the waiting frames it can."""
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

    def _answer(self, f: P.Frame, res) -> list[Output]:
        """Count a tracking result of the map front end and publish its pose (``quality = 0`` when lost)."""
        quality = self._count(f, res)
        if quality <= 0:
            return self._emit(f.seq, f.timestamp, res.c2w, 0.0)
        self._keep_own(f.seq, res.c2w, f.timestamp, quality, res.need_keyframe)
        return self._emit(f.seq, f.timestamp, res.c2w, quality, res.need_keyframe)
