"""Bootstrap of the monocular front end: KLT tracks from the first frame until the two-view geometry
holds, the anchor's scale, photometric tracking of the frames between, a bundle adjustment of them."""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from fmapping.geometry import inv_pose, line_angle_deg, orthonormalize, pose_distance
from fmapping.tracking.ba import bundle_adjust
from fmapping.tracking.features import (
    at_width, corner_covariance, detect_corners, to_u8, triangulate, two_view_init, two_view_known_baseline,
)
from fmapping.tracking.mono.store import Tracks
from fmapping.tracking.rolling_shutter import rotation_step, unroll


def _parallax_deg(c2w_a: np.ndarray, c2w_b: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the rays from the two camera centres to each world point (N, 3)."""
    ra = world - c2w_a[:3, 3]
    rb = world - c2w_b[:3, 3]
    cos = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


class Bootstrap:
    """:meth:`bootstrap` (stage 1 of :mod:`fmapping.tracking.mono`). A mixin of
    :class:`~fmapping.tracking.mono.frontend.MonoFrontend`: it works on the front end's state (``store``,
    ``tracker``, ``cfg`` and the fields ``MonoFrontend.__init__`` sets) and helpers (``_klt``, ``_geo``,
    ``_set_reference``)."""

    def bootstrap(self, index: int, rgb: np.ndarray, c2w0: np.ndarray,
                  anchor_baseline: Optional[Callable[[int], Optional[float]]] = None,
                  anchor_position: Optional[Callable[[int], Optional[np.ndarray]]] = None) -> Optional[dict]:
        """Feed frames from the start. Returns {index: c2w} of all frames so far once initialised, else None.

        ``anchor_baseline(index)`` gives the metric distance between the camera
        centres of the first frame and frame ``index`` (from a pose source), or None.
        ``anchor_position(index)`` gives the camera centre (3,) of frame ``index`` in the
        world frame of ``c2w0`` (the "first two poses known" convention), or None; it
        takes precedence: the baseline *vector* is then known and only the rotation is
        fitted to the tracks (:func:`~fmapping.tracking.features.two_view_known_baseline`).
        The essential matrix cannot tell a small translation from a rotation when the
        motion is mostly rotation (centimetres of baseline at metres of depth): its
        translation direction, hence the triangulated depth and the scale, is then
        wrong even with the right baseline length.
        """
        gray = to_u8(rgb)
        c = self.cfg
        if not self._buf:
            self._first_index = index
            self._buf.append((index, rgb))
            corners = detect_corners(gray, c.klt)
            self.store.tracks = Tracks(corners, index,
                                       corner_covariance(gray, corners, c.klt) if c.anisotropic_tracks else None)
            self._last_gray, self._last_gray_frame = gray, index
            self._c2w0 = orthonormalize(np.asarray(c2w0, np.float64))
            self._hist = {index: (self.store.tracks.tid.copy(), self.store.tracks.uv.copy())}
            return None
        self._buf.append((index, rgb))
        self._klt(gray, index)
        self._hist[index] = (self.store.tracks.tid.copy(), self.store.tracks.uv.copy())
        if len(self._buf) > c.init_max_frames or len(self.store.tracks) < c.init_min_points:
            self.failed = True
            return None
        tr = self.store.tracks
        flow = np.median(np.linalg.norm(tr.uv - tr.uv_first, axis=1))
        if flow < at_width(c.init_min_flow_px, self.camera.width):
            return None
        need_px = c.init_min_parallax_px if len(tr) >= 2 * c.init_min_points else c.init_fallback_parallax_px
        pos = anchor_position(index) if anchor_position is not None else None
        if pos is not None:
            c_a = self._c2w0[:3, :3].T @ (np.asarray(pos, np.float64).reshape(3) - self._c2w0[:3, 3])
            if np.linalg.norm(c_a) < 1e-4:
                return None
            kb = two_view_known_baseline(self.camera, tr.uv_first, tr.uv, c_a, c.ransac_px)
            if kb is None:
                return None
            c2w_k = orthonormalize(self._c2w0 @ kb[0])
            world, valid = triangulate(self.camera, self._c2w0, c2w_k, tr.uv_first, tr.uv,
                                       c.tri_min_parallax_deg, c.tri_max_reproj_px)
            valid &= kb[1]
            median_par = float(np.median(_parallax_deg(self._c2w0, c2w_k, world[valid]))) if valid.any() else 0.0
            if valid.sum() < c.init_min_points or median_par < c.init_min_parallax_deg \
                    or np.radians(median_par) * self.camera.fx < need_px:
                return None
            s, how = float(np.linalg.norm(c_a)), "anchor_position"
        else:
            cov = tr.cov if c.anisotropic_tracks else None

            def usable(tv) -> bool:
                return (tv is not None and tv.valid.sum() >= c.init_min_points
                        and tv.median_parallax_deg >= c.init_min_parallax_deg
                        and np.radians(tv.median_parallax_deg) * self.camera.fx >= need_px)

            tv = two_view_init(self.camera, tr.uv_first, tr.uv, c.ransac_px, c.tri_min_parallax_deg)
            if not usable(tv):
                return None
            if cov is not None:
                # the isotropic pose is a start the bootstrap would take; on edges and stripes it can be tens of
                # degrees off. The whitened fit (searched from init_two_view_starts directions) replaces it
                # unless it is ambiguous or leaves too few points: the time to start stays the isotropic one's
                tw = two_view_init(self.camera, tr.uv_first, tr.uv, c.ransac_px, c.tri_min_parallax_deg, cov=cov,
                                   starts=c.init_two_view_starts)
                if (tw is not None and tw.valid.sum() >= c.init_min_points
                        and tw.median_parallax_deg >= c.init_min_parallax_deg
                        and line_angle_deg(tw.c2w_b[:3, 3], tv.c2w_b[:3, 3]) > c.init_whitened_min_change_deg):
                    tv = tw
            base = anchor_baseline(index) if anchor_baseline is not None else None
            if base is not None and base > 1e-4:
                s, how = float(base), "anchor"  # recoverPose's translation has unit norm
            else:
                s, how = float(c.unit_depth / np.median(tv.points[tv.valid, 2])), "unit_depth"
            c2w_k = tv.c2w_b.copy()
            c2w_k[:3, 3] *= s
            c2w_k = orthonormalize(self._c2w0 @ c2w_k)
            world = (tv.points * s) @ self._c2w0[:3, :3].T + self._c2w0[:3, 3]
            valid, median_par = tv.valid, tv.median_parallax_deg
        i0 = self._buf[0][0]
        # landmarks and their two observations
        sel = np.flatnonzero(valid)
        self.store.kf_pose = {i0: self._c2w0.copy(), index: c2w_k}
        for j in sel:
            lid = len(self.store.lm)
            self.store.lm.append(world[j])
            tr.lid[j] = lid
            self.store.obs.append(i0, lid, tr.uv_first[j, 0], tr.uv_first[j, 1])
            self.store.obs.append(index, lid, tr.uv[j, 0], tr.uv[j, 1])
        self.store.window = [i0, index]
        self.store.kf_rgb = {i0: self._buf[0][1], index: rgb}
        if c.loop.enabled:
            self._kf_images = {i0: to_u8(self._buf[0][1]), index: gray}
        # photometric tracking of frames 1..k against frame 0 with the landmarks' depth
        lids = tr.lid[tr.lid >= 0]
        pts_cam0 = self.store.cam_points(i0, lids, tr.uv_first[tr.lid >= 0])
        self.tracker.set_reference_points(self._buf[0][1], pts_cam0, self._c2w0, i0)
        self.tracker.at_frame(i0)
        self.tracker.observe(self._c2w0)
        poses = {i0: self._c2w0.copy()}
        for fi, frgb in self._buf[1:-1]:
            self.tracker.at_frame(fi)
            poses[fi] = self.tracker.track(frgb).c2w
        self.tracker.at_frame(index)
        r = self.tracker.track(rgb, c2w_guess=self.store.kf_pose[index])
        two_view_vs_photo = pose_distance(self.store.kf_pose[index], r.c2w)[1]
        poses[index] = self.store.kf_pose[index]
        if c.rolling_shutter:
            self._unroll_bootstrap(poses, i0, index)
        # multi-view bundle adjustment of the bootstrap (frame 0 fixed), then the anchor scale again
        rms = self._bootstrap_ba(poses, index, s if how == "anchor" else None, fix_last=how == "anchor_position")
        for fi in poses:
            self.store.rel[fi] = (i0, inv_pose(self._c2w0) @ poses[fi])
        self.store.rel[index] = (index, np.eye(4))
        poses[index] = self.store.kf_pose[index]
        self.tracker.reset_motion([poses[self._buf[-2][0]], poses[index]], [self._buf[-2][0], index])
        self.init_info = {"frame": int(index), "frames": len(self._buf), "points": int(len(sel)),
                          "median_parallax_deg": median_par, "scale": s, "scale_from": how,
                          "two_view_vs_photometric_deg": two_view_vs_photo, "ba_rms_px": rms}
        try:
            self._set_reference(index, rgb, gray)
        except ValueError as e:  # the bundle adjustment left too few landmarks to track against: not a start
            self.init_info["failed"] = str(e)
            self.failed = True
            return None
        self.initialized = True
        self._buf = []
        if how != "unit_depth" and anchor_baseline is not None and c.late_anchor_frames > 0:
            self._anchor = anchor_baseline
        return poses

    def _unroll_bootstrap(self, poses: dict, i0: int, index: int) -> None:
        """Once the bootstrap frames have poses: their tracked pixels (history, first pixels,
        observations) unrolled for the rolling shutter with each frame's rotation step."""
        ids = sorted(poses)  # each frame's step from the previous frame; the first frame takes the second's
        steps = {f: rotation_step(poses[ids[max(j - 1, 0)]], poses[ids[max(j, 1)]]) for j, f in enumerate(ids)}
        cam, r = self.camera, self.cfg.rolling_shutter
        self._hist = {f: (tids, unroll(cam, uvs, steps[f], r)) for f, (tids, uvs) in self._hist.items()}
        tr = self.store.tracks
        tr.uv_first = unroll(cam, tr.uv_first, steps[i0], r)
        self._step = steps[index]
        tr.geo = self._geo(tr.uv)
        obs = self.store.obs
        for f in (i0, index):
            m = obs.kf == f
            obs.uv[m] = unroll(cam, obs.uv[m], steps[f], r)

    def _bootstrap_ba(self, poses: dict, k_index: int, baseline: Optional[float],
                      fix_last: bool = False) -> Optional[float]:
        """BA over up to 6 bootstrap frames (frame 0 fixed, and frame ``k_index`` with ``fix_last``;
        the scale re-anchored to ``baseline`` when given); updates poses and landmarks."""
        c = self.cfg
        tr = self.store.tracks
        ids = [f for f, _ in self._buf]
        sel = sorted(set([ids[0], ids[-1]] + [ids[int(j)] for j in np.linspace(0, len(ids) - 1, min(6, len(ids)))]))
        tid_to_lid = {int(t): int(lid) for t, lid in zip(tr.tid, tr.lid) if lid >= 0}
        obs_kf, obs_pt, obs_uv = [], [], []
        lids = sorted(set(tid_to_lid.values()))
        lpos = {lid: i for i, lid in enumerate(lids)}
        for kpos, f in enumerate(sel):
            tids, uvs = self._hist[f]
            for t, uv in zip(tids, uvs):
                lid = tid_to_lid.get(int(t))
                if lid is not None:
                    obs_kf.append(kpos)
                    obs_pt.append(lpos[lid])
                    obs_uv.append(uv)
        if len(lids) < 10:
            return None
        fixed = [0, len(sel) - 1] if fix_last else [0]  # sel ends with k_index (the newest frame)
        res = bundle_adjust(self.camera, [poses[f] for f in sel], fixed, np.stack([self.store.lm[lid] for lid in lids]),
                            np.array(obs_kf), np.array(obs_pt), np.array(obs_uv), c.ba_huber_px, 30)
        new = dict(zip(sel, res.poses))
        pts = res.points
        c0 = self._c2w0[:3, 3]
        if baseline is not None:
            b = np.linalg.norm(new[k_index][:3, 3] - c0)
            f = baseline / b if b > 1e-9 else 1.0
            for key in new:
                new[key][:3, 3] = c0 + f * (new[key][:3, 3] - c0)
            pts = c0 + f * (pts - c0)
        # frames not in the BA keep their pose relative to the nearest earlier BA frame
        moved = {}
        for fi in poses:
            if fi in new:
                moved[fi] = new[fi]
            else:
                prev = max(x for x in sel if x <= fi)
                moved[fi] = orthonormalize(new[prev] @ inv_pose(poses[prev]) @ poses[fi])
        poses.update(moved)
        for lid, p in zip(lids, pts):
            self.store.lm[lid] = p
        self.store.kf_pose[k_index] = poses[k_index]
        bad = res.residual_px > c.ba_outlier_px
        return float(np.sqrt(np.mean(res.residual_px[~bad] ** 2))) if (~bad).any() else None
