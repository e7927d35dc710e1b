"""Loop closure in the monocular front end: at a keyframe, an old keyframe the camera has come back to
is verified on its landmarks and image; the keyframes since move by a pose graph, then a bundle adjustment.

The search (:func:`search_loop`: verification, cross-check, pose graph) reads a :class:`LoopQuery`, a copy
of what it needs taken out of the store at the keyframe. Offline it runs at once; with
``MonoConfig.loop_thread`` (the tracker service) it runs in a worker thread while the next frames are
tracked, and its correction is merged at a later frame (:meth:`LoopClosing._merge_loop`), as ORB-SLAM's
loop-closing thread does."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import inv_pose, orthonormalize, pose_distance
from fmapping.tracking.features import KltConfig
from fmapping.tracking.loop import LoopConfig, LoopMatch, cross_check, locate_in_keyframe, loop_candidates
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


@dataclass
class LoopQuery:
    """What the loop search at keyframe ``index`` reads, copied out of the front end's store."""
    index: int
    gray: np.ndarray  # keyframe ``index``'s image
    scale: float  # the median scene depth (the unit of the loop's distances)
    poses: dict  # keyframe -> c2w, every keyframe from the oldest candidate to ``index``
    candidates: list  # (old keyframe, its image, landmark ids, their pixels (N, 2), their world points (N, 3))
    own: Optional[tuple]  # keyframe ``index``'s (pixels, world points), for the cross-check; None: too few
    epoch: int = 0  # the front end's geometry epoch (a rescale or re-initialisation voids the search)


@dataclass
class LoopFound:
    """A verified loop: keyframe ``index`` located in the map of keyframe ``old`` (``match``, on
    ``old``'s landmarks ``old_lids``), and the pose graph's poses of the keyframes from ``old`` to ``index``."""
    old: int
    index: int
    match: LoopMatch
    old_lids: np.ndarray
    record: dict
    before: dict  # keyframe -> c2w the pose graph started from
    after: dict  # keyframe -> c2w the pose graph moved it to


@dataclass
class LoopSearch:
    """What :func:`search_loop` found: the loops it refused (records) and the one to correct, if any."""
    refused: list
    found: Optional[LoopFound] = None


def search_loop(camera: PinholeCamera, q: LoopQuery, klt: KltConfig, lc: LoopConfig) -> LoopSearch:
    """Try the candidates of ``q`` nearest first (:func:`~fmapping.tracking.loop.locate_in_keyframe`); the
    first that verifies and disagrees with the chain, confirmed the other way round
    (:func:`~fmapping.tracking.loop.cross_check`), gets a pose graph over the keyframes from it to ``q.index``:
    the chain's relative poses plus the loop edge. One that agrees with the chain ends the search. Reads
    only ``q``: safe in a worker thread."""
    out = LoopSearch([])
    cur = q.poses[q.index]
    for k, old_gray, lids, uv, world in q.candidates:
        m = locate_in_keyframe(camera, old_gray, uv, world, q.poses[k], q.gray, cur, klt, lc)
        if m is None:
            continue
        dt, dr = pose_distance(cur, m.c2w)
        rec = {"frame": int(q.index), "keyframe": int(k), "points": m.points, "inliers": m.inliers,
               "moved_m": dt, "moved_deg": dr}
        if dt > lc.max_correction * q.scale:
            rec["why"] = f"correction {dt:.3g} > {lc.max_correction} x median depth {q.scale:.3g}"
            out.refused.append(rec)
            continue
        if dt < lc.min_correction_m * q.scale and dr < lc.min_correction_deg:
            return out  # the chain already agrees with the old keyframe
        if np.isfinite(lc.max_cross_deg):
            cross = None if q.own is None else cross_check(camera, old_gray, q.poses[k], m, q.gray, q.own[0],
                                                           q.own[1], cur, klt, lc)
            if cross is not None:
                rec["cross_deg"], rec["cross_dist"] = cross[0], cross[1] / q.scale
            if cross is None or cross[0] > lc.max_cross_deg or cross[1] > lc.max_cross_dist * q.scale:
                rec["why"] = (f"measured the other way round: {cross and round(cross[0], 3)} deg, "
                              f"{cross and round(cross[1] / q.scale, 4)} x median depth apart")
                out.refused.append(rec)
                continue
        kfs = sorted(j for j in q.poses if k <= j <= q.index)
        before = [q.poses[j] for j in kfs]
        edges = [(a, a + 1, inv_pose(before[a]) @ before[a + 1]) for a in range(len(kfs) - 1)]
        edges.append((0, len(kfs) - 1, inv_pose(before[0]) @ m.c2w))
        after, stats = optimize_pose_graph(before, edges, [0], unit=q.scale)
        rec.update(cost_before=stats["cost_before"], cost_after=stats["cost_after"])
        out.found = LoopFound(k, q.index, m, lids, rec, dict(zip(kfs, before)), dict(zip(kfs, after)))
        return out
    return out


class LoopClosing:
    """Stage 4 of :mod:`fmapping.tracking.mono`. A mixin of :class:`~fmapping.tracking.mono.frontend.MonoFrontend`:
    it works on the front end's state (``store``, ``tracker``, ``cfg``, the keyframe images ``_kf_images``, the
    loop worker ``_loop_worker``) and its ``_scale_part``."""

    def _close_loop(self, index: int, gray: np.ndarray) -> None:
        """Look for an old keyframe the camera has come back to (:func:`search_loop`) and correct the
        keyframes since then (:meth:`_apply_loop`): at once, or (``loop_thread``) in the worker, one
        search at a time (a keyframe whose search would wait for one in flight is not searched from), and none
        while a loop's bundle adjustment is in flight (its merge rescales the loop: the search would be stale)."""
        w = self._loop_worker
        if (w is not None and w.busy) or self._loop_ba is not None:
            self._loop_passed_over = index  # searched from at the end of the stream if no later one is
            return
        self._loop_passed_over = None
        q = self._loop_query(index, gray)
        if q is None:
            return
        if w is None:
            self._apply_loop(search_loop(self.camera, q, self.cfg.klt, self.cfg.loop))
        else:
            w.start(q, lambda: search_loop(self.camera, q, self.cfg.klt, self.cfg.loop))

    def _loop_query(self, index: int, gray: np.ndarray) -> Optional[LoopQuery]:
        """The search's input at keyframe ``index`` (copies), or None without a candidate."""
        lc = self.cfg.loop
        ref = self.tracker.reference
        scale = ref.median_depth if ref is not None and np.isfinite(ref.median_depth) else self.cfg.unit_depth
        lm = self.store.lm
        cands = []
        for k in loop_candidates(self.store.kf_pose, index, scale, lc):
            if k not in self._kf_images:
                continue
            lids, uv = self.store.obs.of_keyframe(k)
            if len(lids) < lc.min_points:
                continue
            cands.append((k, self._kf_images[k], np.array(lids), np.array(uv), np.stack([lm[i] for i in lids])))
        if not cands:
            return None
        own = None
        lids, uv = self.store.obs.of_keyframe(index)
        if np.isfinite(lc.max_cross_deg) and len(lids) >= lc.min_points:
            own = (np.array(uv), np.stack([lm[i] for i in lids]))
        first = min(c[0] for c in cands)
        poses = {k: p.copy() for k, p in self.store.kf_pose.items() if k >= first}
        return LoopQuery(index, gray, scale, poses, cands, own, self._loop_epoch)

    def _flush_loop(self) -> bool:
        """The end of the stream (``loop_thread``): the search in flight merged, then one from the last keyframe
        if it was passed over (:meth:`_close_loop`), each followed by the bundle adjustment its correction
        starts. True when poses moved."""
        merged = False
        for _ in range(2):
            k = self._loop_passed_over
            if not self._loop_worker.busy and k is not None and k in self._kf_images and self._loop_ba is None:
                self._close_loop(k, self._kf_images[k])
            if self._loop_worker.busy:
                merged = self._merge_loop(wait=True) or merged
                merged = self._merge_ba(wait=True) or merged
        return merged

    def _merge_loop(self, wait: bool = False) -> bool:
        """Merge the loop worker's search when it is done (``wait``: block until it is) and the bundle
        adjustment worker is idle (the correction changes the store, and the loop's BA goes to that worker):
        :meth:`_apply_loop`, then the motion model moves with the current keyframe. A search begun before a
        rescale or re-initialisation is dropped. True when keyframes moved."""
        w = self._loop_worker
        if w is None or not w.busy or (self._bg is not None and self._bg.busy) or not (wait or w.ready()):
            return False
        q, res = w.take(wait=True)
        if q.epoch != self._loop_epoch:
            return False
        k = self._kf_index
        was = self.store.kf_pose[k].copy() if k in self.store.kf_pose else None
        if not self._apply_loop(res):
            return False
        if was is not None:
            self.tracker.move_motion(self.store.kf_pose[k] @ inv_pose(was))
        self.ba_merges += 1  # the session hands the moved poses on
        return True

    def _apply_loop(self, res: LoopSearch) -> bool:
        """Correct the keyframes of the loop ``res.found`` (records of refused ones kept): each keyframe from
        the old one on moves as the pose graph moved it, keyframes newer than the search (``loop_thread``) as
        its last; landmarks move with their first keyframe; then (``loop.loop_ba``, loops up to
        ``loop_ba_max_keyframes``) the loop's inliers become observations of the loop's keyframe, the loop's
        keyframes are bundle-adjusted (the first two fixed) and scaled back to the pose graph's size
        (``loop_ba_keep_scale``). With ``ba_thread`` that bundle adjustment is solved in the worker, off the
        frame path (a second or more for tens of keyframes), and taken like a keyframe's (:meth:`_merge_ba`,
        then :meth:`_after_loop_ba`). The tracker's references move with their keyframes; non-keyframes are
        stored relative to their keyframe. What it did goes into the loop's record (the BA's figures once it
        is merged). True when keyframes moved."""
        self.loops_refused.extend(res.refused)
        f = res.found
        if f is None or f.old not in self.store.kf_pose or f.index not in self.store.kf_pose:
            return False
        lc, index, out = self.cfg.loop, f.index, f.record
        kfs = sorted(k for k in self.store.kf_pose if k >= f.old)
        before = [self.store.kf_pose[k].copy() for k in kfs]
        tail = f.after[index] @ inv_pose(f.before[index])  # keyframes newer than the search move as its last
        for k, b in zip(kfs, before):
            if k in f.before and np.array_equal(b, f.before[k]):
                a = f.after[k]
            else:  # moved since the search (a bundle adjustment merged meanwhile), or newer
                a = (f.after[k] @ inv_pose(f.before[k]) if k in f.before else tail) @ b
            self.store.kf_pose[k] = orthonormalize(a)
        corr = {k: self.store.kf_pose[k] @ inv_pose(b) for k, b in zip(kfs, before)}
        self.store.move_landmarks(corr)
        out["keyframes"] = len(kfs)
        out["ba"] = lc.loop_ba and len(kfs) <= lc.loop_ba_max_keyframes
        if out["ba"]:
            m = f.match
            have = self.store.obs.of_keyframe(index)[0]
            new = ~np.isin(f.old_lids[m.index], have)
            self.store.obs.extend(index, f.old_lids[m.index][new], np.asarray(m.uv, np.float64).reshape(-1, 2)[new])
            graph_size = self.store.spread_about(kfs, f.old)
            prob = self.store.ba_problem(window=kfs, max_nfev=lc.loop_ba_max_nfev)
            if self._bg is not None and prob is not None:  # ba_thread: solved off the frame path
                self._bg.submit(prob, release_memory=self.cfg.ba_release_memory)
                self._loop_ba = PendingLoopBA(prob, kfs, f.old, graph_size, out)
                out["ba_in_worker"] = True
            elif prob is not None:
                self.store.apply_ba(prob, solve_ba_problem(self.camera, prob))
        self.tracker.move_references({k: self.store.kf_pose[k] @ inv_pose(b) for k, b in zip(kfs, before)})
        if out["ba"] and self._loop_ba is None:
            self._after_loop_ba(kfs, f.old, graph_size, out)
        self._moved_all = True
        self.loops.append(out)
        return True

    def _after_loop_ba(self, kfs: list, old: int, graph_size: float, out: dict, newer: tuple = ()) -> None:
        """The loop's bundle adjustment is in the store: its scale against the pose graph's
        (``ba_scale``, over the loop's keyframes ``kfs``), its rms, and (``loop_ba_keep_scale``) the keyframes
        scaled back to the graph's size, with those added since (``newer``)."""
        out["ba_scale"] = graph_size / max(self.store.spread_about(kfs, old), 1e-12)
        out["ba_rms_px"] = self.store.ba_stats[-1]["rms_after_px"] if self.store.ba_stats else None
        if self.cfg.loop.loop_ba_keep_scale:
            self._scale_keyframes(list(kfs) + list(newer), old, out["ba_scale"])

    def _scale_keyframes(self, kfs: list, about: int, s: float) -> None:
        """Scale what belongs to keyframes ``kfs`` by ``s`` about keyframe ``about``'s centre (:meth:`_scale_part`)."""
        self._scale_part(self.store.kf_pose[about][:3, 3].copy(), s, set(kfs))
