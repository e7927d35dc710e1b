"""Loop closure in the monocular front end: at a keyframe, an old keyframe the camera has come back to
is verified on its landmarks and image; the keyframes since move by a pose graph, then a bundle adjustment."""
from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

from fmapping.geometry import inv_pose, orthonormalize, pose_distance
from fmapping.tracking.loop import LoopMatch, cross_check, locate_in_keyframe, loop_candidates
from fmapping.tracking.mono.store import BAProblem, solve_ba_problem
from fmapping.tracking.posegraph import optimize_pose_graph


class PendingLoopBA(NamedTuple):
    """A loop's bundle adjustment in the worker (``ba_thread``): what :meth:`LoopClosing._after_loop_ba`
    needs once it is merged."""
    prob: BAProblem
    keyframes: list
    old: int
    graph_size: float
    record: dict


class LoopClosing:
    """Stage 4 of :mod:`fmapping.tracking.mono`. A mixin of :class:`~fmapping.tracking.mono.frontend.MonoFrontend`:
    it works on the front end's state (``store``, ``tracker``, ``cfg``, the keyframe images ``_kf_images``) and
    its ``_scale_part``."""

    def _close_loop(self, index: int, gray: np.ndarray) -> None:
        """Look for an old keyframe the camera has come back to (:mod:`fmapping.tracking.loop`); when
        one verifies and disagrees with the chain, correct the keyframes since then (:meth:`_correct_loop`)."""
        lc = self.cfg.loop
        ref = self.tracker.reference
        scale = ref.median_depth if ref is not None and np.isfinite(ref.median_depth) else self.cfg.unit_depth
        for k in loop_candidates(self.store.kf_pose, index, scale, lc):
            if k not in self._kf_images:
                continue
            lids, uv = self.store.obs.of_keyframe(k)
            if len(lids) < lc.min_points:
                continue
            m = locate_in_keyframe(self.camera, self._kf_images[k], uv, np.stack([self.store.lm[i] for i in lids]),
                                   self.store.kf_pose[k], gray, self.store.kf_pose[index], self.cfg.klt, lc)
            if m is None:
                continue
            dt, dr = pose_distance(self.store.kf_pose[index], m.c2w)
            rec = {"frame": int(index), "keyframe": int(k), "points": m.points, "inliers": m.inliers,
                   "moved_m": dt, "moved_deg": dr}
            if dt > lc.max_correction * scale:
                rec["why"] = f"correction {dt:.3g} > {lc.max_correction} x median depth {scale:.3g}"
                self.loops_refused.append(rec)
                continue
            if dt < lc.min_correction_m * scale and dr < lc.min_correction_deg:
                return  # the chain already agrees with the old keyframe
            if np.isfinite(lc.max_cross_deg):
                cross = self._cross_check(k, index, m, gray)
                if cross is not None:
                    rec["cross_deg"], rec["cross_dist"] = cross[0], cross[1] / scale
                if cross is None or cross[0] > lc.max_cross_deg or cross[1] > lc.max_cross_dist * scale:
                    rec["why"] = (f"measured the other way round: {cross and round(cross[0], 3)} deg, "
                                  f"{cross and round(cross[1] / scale, 4)} x median depth apart")
                    self.loops_refused.append(rec)
                    continue
            self._correct_loop(k, index, m, lids, scale, rec)
            self.loops.append(rec)
            return

    def _cross_check(self, old: int, index: int, m: LoopMatch, gray: np.ndarray) -> Optional[tuple]:
        """The loop ``m`` (keyframe ``index`` in the map of keyframe ``old``) measured the other way
        round, from keyframe ``index``'s own landmarks (:func:`~fmapping.tracking.loop.cross_check`)."""
        lids, uv = self.store.obs.of_keyframe(index)
        if len(lids) < self.cfg.loop.min_points:
            return None
        return cross_check(self.camera, self._kf_images[old], self.store.kf_pose[old], m, gray, uv,
                           np.stack([self.store.lm[i] for i in lids]), self.store.kf_pose[index], self.cfg.klt,
                           self.cfg.loop)

    def _correct_loop(self, old: int, index: int, m: LoopMatch, old_lids: np.ndarray, scale: float, out: dict) -> None:
        """Pose graph over the keyframes from ``old`` (fixed) to ``index``: the chain's relative poses
        plus the loop edge ``old`` -> ``index`` (``m``, a :class:`~fmapping.tracking.loop.LoopMatch` on
        the landmarks ``old_lids`` of keyframe ``old``). Landmarks move with their first keyframe;
        then (``loop.loop_ba``, loops up to ``loop_ba_max_keyframes``) the loop's inliers become
        observations of keyframe ``index``, the loop's keyframes are bundle-adjusted (the first two
        fixed) and scaled back to the pose graph's size (``loop_ba_keep_scale``). With ``ba_thread``
        that bundle adjustment is solved in the worker, off the frame path (a second or more for
        tens of keyframes), and taken like a keyframe's (:meth:`_merge_ba`, then :meth:`_after_loop_ba`).
        The tracker's references move with their keyframes; non-keyframes are stored relative to their keyframe.
        What it did goes into the loop's record ``out`` (the BA's figures once it is merged)."""
        lc = self.cfg.loop
        kfs = sorted(k for k in self.store.kf_pose if k >= old)
        before = [self.store.kf_pose[k].copy() for k in kfs]
        edges = [(a, a + 1, inv_pose(before[a]) @ before[a + 1]) for a in range(len(kfs) - 1)]
        edges.append((0, len(kfs) - 1, inv_pose(before[0]) @ m.c2w))
        after, stats = optimize_pose_graph(before, edges, [0], unit=scale)
        corr = {}
        for k, b, a in zip(kfs, before, after):
            self.store.kf_pose[k] = orthonormalize(a)
            corr[k] = self.store.kf_pose[k] @ inv_pose(b)
        self.store.move_landmarks(corr)
        out.update(keyframes=len(kfs), cost_before=stats["cost_before"], cost_after=stats["cost_after"])
        out["ba"] = lc.loop_ba and len(kfs) <= lc.loop_ba_max_keyframes
        if out["ba"]:
            have = self.store.obs.of_keyframe(index)[0]
            new = ~np.isin(old_lids[m.index], have)
            self.store.obs.extend(index, old_lids[m.index][new], np.asarray(m.uv, np.float64).reshape(-1, 2)[new])
            graph_size = self.store.spread_about(kfs, old)
            prob = self.store.ba_problem(window=kfs, max_nfev=lc.loop_ba_max_nfev)
            if self._bg is not None and prob is not None:  # ba_thread: solved off the frame path
                self._bg.submit(prob, release_memory=self.cfg.ba_release_memory)
                self._loop_ba = PendingLoopBA(prob, kfs, old, graph_size, out)
                out["ba_in_worker"] = True
            elif prob is not None:
                self.store.apply_ba(prob, solve_ba_problem(self.camera, prob))
        self.tracker.move_references({k: self.store.kf_pose[k] @ inv_pose(b) for k, b in zip(kfs, before)})
        if out["ba"] and self._loop_ba is None:
            self._after_loop_ba(kfs, old, graph_size, out)
        self._moved_all = True

    def _after_loop_ba(self, kfs: list, old: int, graph_size: float, out: dict) -> None:
        """The loop's bundle adjustment is in the store: its scale against the pose graph's
        (``ba_scale``), its rms, and (``loop_ba_keep_scale``) the keyframes scaled back to the graph's size."""
        out["ba_scale"] = graph_size / max(self.store.spread_about(kfs, old), 1e-12)
        out["ba_rms_px"] = self.store.ba_stats[-1]["rms_after_px"] if self.store.ba_stats else None
        if self.cfg.loop.loop_ba_keep_scale:
            self._scale_keyframes(kfs, old, out["ba_scale"])

    def _scale_keyframes(self, kfs: list, about: int, s: float) -> None:
        """Scale what belongs to keyframes ``kfs`` by ``s`` about keyframe ``about``'s centre (:meth:`_scale_part`)."""
        self._scale_part(self.store.kf_pose[about][:3, 3].copy(), s, set(kfs))
