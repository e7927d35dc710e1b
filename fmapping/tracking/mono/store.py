"""The monocular front end's keyframe/landmark store: KLT tracks, keyframe poses and images,
landmarks and their observations, frames stored relative to their keyframe, and the windowed
bundle adjustment over them."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.geometry import inv_pose, scale_about
from fmapping.tracking.ba import BAResult, bundle_adjust, whitening
from fmapping.tracking.features import at_width, structure_tensor, to_u8, triangulate
from fmapping.tracking.mono.config import MonoConfig


class Tracks:
    """KLT tracks: current pixel (``uv``, in the image; ``geo``, unrolled for a rolling shutter, the
    one geometry uses), landmark id (-1: none), first keyframe and the (unrolled) pixel there, and the
    shape of each track's position error (``cov``, (N, 2, 2):
    :func:`~fmapping.tracking.features.corner_covariance` where it was detected; the identity when not given).
    :meth:`mark_keyframe` keeps the pixels at the current keyframe (``uv_kf``, which the front end re-tracks
    from, and ``geo_kf``, unrolled, where a track restarts when its landmark is dropped; ``kf``: which keyframe,
    -1 none)."""

    def __init__(self, uv: np.ndarray, kf: int, cov: Optional[np.ndarray] = None):
        n = len(uv)
        self.kf = -1
        self.uv_kf: Optional[np.ndarray] = None
        self.geo_kf: Optional[np.ndarray] = None
        self.uv = np.asarray(uv, np.float64).reshape(-1, 2).copy()
        self.geo = self.uv
        self.lid = np.full(n, -1, np.int64)
        self.first_kf = np.full(n, kf, np.int64)
        self.uv_first = self.uv.copy()
        self.tid = np.arange(n)
        self.cov = _covariances(cov, n)

    def keep(self, mask: np.ndarray) -> None:
        self.uv, self.geo, self.lid, self.first_kf, self.uv_first, self.tid, self.cov = (
            self.uv[mask], self.geo[mask], self.lid[mask], self.first_kf[mask], self.uv_first[mask], self.tid[mask],
            self.cov[mask])
        if self.uv_kf is not None:
            self.uv_kf, self.geo_kf = self.uv_kf[mask], self.geo_kf[mask]

    def mark_keyframe(self, index: int) -> None:
        """The tracks' pixels now are their pixels in keyframe ``index``."""
        self.kf = int(index)
        self.uv_kf = self.uv.astype(np.float32)
        self.geo_kf = np.array(self.geo, np.float64)

    def restart_pixels(self, kf: int) -> np.ndarray:
        """Each track's (unrolled) pixel in keyframe ``kf``: kept by :meth:`mark_keyframe` when that was ``kf``,
        else the current one (a keyframe whose pixels are not marked yet is the current frame)."""
        return self.geo_kf if self.geo_kf is not None and self.kf == kf else self.geo

    def add(self, uv: np.ndarray, kf: int, geo: Optional[np.ndarray] = None) -> None:
        """Tracks starting at keyframe ``kf`` (their error shape the identity: only the bootstrap's are shaped)."""
        n = len(uv)
        geo = uv if geo is None else geo
        self.uv = np.concatenate([self.uv, uv])
        self.geo = np.concatenate([self.geo, geo])
        self.lid = np.concatenate([self.lid, np.full(n, -1, np.int64)])
        self.first_kf = np.concatenate([self.first_kf, np.full(n, kf, np.int64)])
        self.uv_first = np.concatenate([self.uv_first, geo])
        start = int(self.tid.max()) + 1 if len(self.tid) else 0
        self.tid = np.concatenate([self.tid, np.arange(start, start + n)])
        self.cov = np.concatenate([self.cov, _covariances(None, n)])
        if self.uv_kf is not None:  # the same length as the rest (a keyframe marks all of them next)
            self.uv_kf = np.concatenate([self.uv_kf, np.asarray(uv, np.float32)])
            self.geo_kf = np.concatenate([self.geo_kf, geo])

    def __len__(self) -> int:
        return len(self.uv)


def _covariances(cov: Optional[np.ndarray], n: int) -> np.ndarray:
    """``cov`` as (n, 2, 2) float64, or n identities."""
    if cov is None:
        return np.tile(np.eye(2), (n, 1, 1))
    cov = np.asarray(cov, np.float64).reshape(-1, 2, 2)
    if len(cov) != n:
        raise ValueError(f"Tracks: {n} pixels but {len(cov)} covariances")
    return cov


class Observations:
    """The landmark observations ``(keyframe, landmark id, u, v)`` of a :class:`KeyframeStore`, in the order they
    were made, as arrays that grow in place. They accumulate over the sequence (25k at 1,000 frames): a Python
    list of tuples cost every keyframe a conversion of all of them and the loop detection a scan per candidate;
    here those are vectorised over the arrays. ``kf``, ``lid`` and ``uv`` are views of the rows (writing ``uv``
    writes the table); iterating yields the rows as tuples. Each row also has the 2x2 matrix that whitens its
    pixel error (``whiten``, :func:`~fmapping.tracking.ba.whitening`; the identity unless given)."""

    def __init__(self):
        self._kf = np.zeros(0, np.int64)
        self._lid = np.zeros(0, np.int64)
        self._uv = np.zeros((0, 2), np.float64)
        self._wh = np.zeros((0, 2, 2), np.float64)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def kf(self) -> np.ndarray:
        return self._kf[: self._n]

    @property
    def lid(self) -> np.ndarray:
        return self._lid[: self._n]

    @property
    def uv(self) -> np.ndarray:
        return self._uv[: self._n]

    @property
    def whiten(self) -> np.ndarray:
        return self._wh[: self._n]

    def __iter__(self):
        return iter([(int(k), int(i), float(u), float(v)) for k, i, (u, v) in zip(self.kf, self.lid, self.uv)])

    def extend(self, kf, lid, uv, whiten: Optional[np.ndarray] = None) -> None:
        """Append rows: keyframes ``kf`` (an int or one per row), landmarks ``lid`` (M,), pixels ``uv`` (M, 2),
        their pixel errors' whitening matrices ``whiten`` (M, 2, 2; default the identity)."""
        lid = np.asarray(lid, np.int64).reshape(-1)
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        m = len(lid)
        if len(uv) != m or (whiten is not None and len(whiten) != m):
            raise ValueError(f"Observations.extend: {m} landmarks but {len(uv)} pixels"
                             + ("" if whiten is None else f" and {len(whiten)} whitening matrices"))
        end = self._n + m
        if end > len(self._kf):  # amortised growth: the arrays at least double
            cap = max(end, 2 * len(self._kf), 256)
            self._kf = np.resize(self._kf, cap)
            self._lid = np.resize(self._lid, cap)
            self._uv = np.resize(self._uv, (cap, 2))
            self._wh = np.resize(self._wh, (cap, 2, 2))
        self._kf[self._n:end] = kf
        self._lid[self._n:end] = lid
        self._uv[self._n:end] = uv
        self._wh[self._n:end] = np.eye(2) if whiten is None else whiten
        self._n = end

    def append(self, kf: int, lid: int, u: float, v: float) -> None:
        self.extend(kf, [lid], [[u, v]])

    def rows(self) -> np.ndarray:
        """A copy of the table as (N, 4) float64: keyframe, landmark id, u, v."""
        return np.column_stack([self.kf, self.lid, self.uv]).astype(np.float64)

    def of_keyframe(self, kf: int) -> tuple[np.ndarray, np.ndarray]:
        """Landmark ids (M,) and pixels (M, 2) keyframe ``kf`` observed, in table order (copies)."""
        m = self.kf == kf
        return self.lid[m].copy(), self.uv[m].copy()

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the rows where ``mask`` (N,) is true, in their order."""
        mask = np.asarray(mask, bool)
        kf, lid, uv, wh = self.kf[mask], self.lid[mask], self.uv[mask], self.whiten[mask]
        self._kf, self._lid, self._uv, self._wh, self._n = kf.copy(), lid.copy(), uv.copy(), wh.copy(), len(kf)

    def drop(self, pairs) -> None:
        """Drop every row whose (keyframe, landmark id) is in ``pairs``."""
        pairs = np.asarray(list(pairs), np.int64).reshape(-1, 2)
        if len(pairs):
            self.keep(~np.isin(_pair_keys(self.kf, self.lid), _pair_keys(pairs[:, 0], pairs[:, 1])))

    def first_keyframes(self) -> dict:
        """{landmark id: the keyframe of its first remaining row}."""
        return dict(zip(*(a.tolist() for a in self.first_keyframe_arrays())))

    def first_keyframe_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`first_keyframes` as two arrays: landmark ids (ascending) and their keyframes."""
        lids, first = np.unique(self.lid, return_index=True)
        return lids, self.kf[first]


def _pair_keys(kf: np.ndarray, lid: np.ndarray) -> np.ndarray:
    """One int64 per (keyframe, landmark id) pair (both below 2**31)."""
    return (np.asarray(kf, np.int64) << 32) | np.asarray(lid, np.int64)


class KeyframeStore:
    """What the bundle adjustment works on: keyframe poses (``kf_pose``, refined) and the window's
    images, landmark world points (``lm``) and their observations ``(keyframe, landmark id, u, v)``
    (``obs``; pixels unrolled for a rolling shutter), every tracked frame's pose relative to its
    keyframe (``rel``), the BA window and the KLT tracks that feed it. Poses are camera-to-world."""

    def __init__(self, camera: PinholeCamera, cfg: MonoConfig):
        self.camera = camera
        self.cfg = cfg
        self.tracks: Optional[Tracks] = None
        self.kf_pose: dict = {}  # keyframe index -> c2w (refined)
        self.kf_rgb: dict = {}  # window keyframes' images
        self.window: list = []  # keyframe indices in the BA window
        self.lm: list = []  # landmark world points
        self.obs = Observations()  # (kf index, landmark id, u, v)
        self.rel: dict = {}  # frame index -> (keyframe index, inv(c2w_kf) @ c2w)
        self.ba_stats: list = []  # per bundle adjustment: keyframes, points, rms before / after, ms
        self.stray_restarts = 0  # tracks restarted at a keyframe, their landmark far from them (kf_obs_max_px)

    def add_keyframe(self, index: int, rgb: np.ndarray, c2w: np.ndarray, gray: Optional[np.ndarray] = None) -> None:
        """Frame ``index`` becomes a keyframe at ``c2w``: tracks with a landmark add an observation,
        the others are triangulated between their first keyframe and this one; it joins the BA
        window (the oldest keyframe leaves it, with its image). With ``ba_anisotropic`` the observations made
        here are whitened by the shape of their corner in this image (``gray``, made from ``rgb`` when not given)."""
        c = self.cfg
        tr = self.tracks
        self.kf_pose[index] = np.asarray(c2w, np.float64).copy()
        self.kf_rgb[index] = rgb
        self._restart_stray_tracks(index)
        wh = self._whitening(rgb, gray)
        # observations of known landmarks
        has = tr.lid >= 0
        self.obs.extend(index, tr.lid[has], tr.geo[has], None if wh is None else wh[has])
        # triangulate the others between their first keyframe and this one
        for kf in np.unique(tr.first_kf[~has]):
            if kf not in self.kf_pose or kf == index:
                continue
            m = np.flatnonzero((~has) & (tr.first_kf == kf))
            pts, ok = triangulate(self.camera, self.kf_pose[kf], c2w, tr.uv_first[m], tr.geo[m],
                                  c.tri_min_parallax_deg, c.tri_max_reproj_px)
            sel = m[ok]
            lids = np.arange(len(self.lm), len(self.lm) + len(sel))
            self.lm.extend(pts[ok])
            tr.lid[sel] = lids
            # two rows per new landmark, in turn: its first keyframe's observation, then this one's
            rows_kf = np.empty(2 * len(sel), np.int64)
            rows_kf[0::2], rows_kf[1::2] = int(kf), index
            rows_uv = np.empty((2 * len(sel), 2))
            rows_uv[0::2], rows_uv[1::2] = tr.uv_first[sel], tr.geo[sel]
            rows_wh = None
            if wh is not None:  # a track's first pixel is where its corner was found: the identity there
                rows_wh = np.tile(np.eye(2), (2 * len(sel), 1, 1))
                rows_wh[1::2] = wh[sel]
            self.obs.extend(rows_kf, np.repeat(lids, 2), rows_uv, rows_wh)
        self.window.append(index)
        if len(self.window) > c.window:
            old = self.window.pop(0)
            self.kf_rgb.pop(old, None)

    def _whitening(self, rgb: np.ndarray, gray: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        """The whitening matrices (N, 2, 2) of the tracks' pixel errors in keyframe image ``rgb`` (``gray``, its grey
        image, when the caller has it); None when ``ba_anisotropic`` is off. Each direction's variance is
        ``1 + ba_anisotropic_noise / lambda`` for the structure tensor's eigenvalue ``lambda`` along it
        (:func:`~fmapping.tracking.features.structure_tensor`), at most ``ba_anisotropic_cap``: LK's error from
        image noise is ``sigma^2 G^-1``, the 1 is the floor every track has. A textured corner stays at the
        identity, a stripe is discounted along itself."""
        c, tr = self.cfg, self.tracks
        if not c.ba_anisotropic or not len(tr):
            return None
        w, vec = np.linalg.eigh(structure_tensor(to_u8(rgb) if gray is None else gray, tr.uv, c.klt))
        var = np.clip(1.0 + c.ba_anisotropic_noise / np.maximum(w, 1e-12), 1.0, c.ba_anisotropic_cap)
        return whitening(np.einsum("nij,nj,nkj->nik", vec, var, vec))

    def _restart_stray_tracks(self, index: int) -> None:
        """Tracks whose landmark reprojects more than ``kf_obs_max_px`` from them at keyframe ``index``'s pose
        start again from this keyframe (no observation of their landmark here; counted in ``stray_restarts``),
        unless more than ``kf_obs_max_share`` of the tracks with a landmark are that far."""
        c, tr = self.cfg, self.tracks
        has = np.flatnonzero(tr.lid >= 0)
        if c.kf_obs_max_px <= 0 or not len(has):
            return
        off = self.reprojection_px(index, tr.lid[has], tr.geo[has])
        bad = has[off > at_width(c.kf_obs_max_px, self.camera.width)]
        if len(bad) and len(bad) <= c.kf_obs_max_share * len(has):
            tr.lid[bad], tr.first_kf[bad], tr.uv_first[bad] = -1, index, tr.geo[bad]
            self.stray_restarts += len(bad)

    def reprojection_px(self, kf: int, lids: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Pixel distance (N,) between landmarks ``lids`` projected at keyframe ``kf``'s pose and pixels ``uv``
        (inf behind the camera)."""
        proj, z = self.camera.world_to_pixels(self.kf_pose[kf], np.stack([self.lm[i] for i in lids]))
        return np.where(z > 1e-3, np.linalg.norm(proj - uv, axis=1), np.inf)

    def cam_points(self, kf: int, lids: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Camera-frame points at observed pixels ``uv`` with the depth of landmarks ``lids`` in keyframe ``kf``."""
        if len(lids) == 0:
            return np.zeros((0, 3))
        w2c = inv_pose(self.kf_pose[kf])
        x = np.stack([self.lm[i] for i in lids]) @ w2c[:3, :3].T + w2c[:3, 3]
        z = x[:, 2]
        ok = z > 1e-3
        uv, z = uv[ok], z[ok]
        cam = self.camera
        return np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], -1)

    def tracked_landmarks(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """World points and current pixels of the tracks with a landmark (None below ``pnp_min_points``)."""
        tr = self.tracks
        has = tr.lid >= 0
        if has.sum() < self.cfg.pnp_min_points:
            return None
        return np.stack([self.lm[i] for i in tr.lid[has]]), tr.geo[has]

    def first_keyframes(self) -> dict:
        """{landmark id: the keyframe of its first remaining observation}: whose pose it moves with."""
        return self.obs.first_keyframes()

    def move_landmarks(self, corr: dict) -> None:
        """Move each landmark with the keyframe it moves with (:meth:`first_keyframes`): ``corr`` is
        {keyframe: 4x4 correction, new pose @ inv(old pose)}; landmarks of other keyframes stay."""
        lids, first = self.obs.first_keyframe_arrays()
        for k, c in corr.items():
            self._map_landmarks(lids[first == k], lambda x: x @ c[:3, :3].T + c[:3, 3])

    def _map_landmarks(self, sel: np.ndarray, fn) -> None:
        """Landmarks ``sel`` (ids) replaced by ``fn`` of them stacked (M, 3) -> (M, 3)."""
        if len(sel):
            for i, q in zip(sel.tolist(), fn(np.stack([self.lm[i] for i in sel]))):
                self.lm[i] = q

    def depths_seen(self, kf: int, lids: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
        """Landmark ids and their depths in keyframe ``kf``'s camera: of the landmarks it observes, or of ``lids``."""
        lids = np.asarray(self.obs.of_keyframe(kf)[0] if lids is None else lids, np.int64)
        if not len(lids):
            return lids, np.zeros(0)
        c2w = self.kf_pose[kf]
        return lids, (np.stack([self.lm[i] for i in lids.tolist()]) - c2w[:3, 3]) @ c2w[:3, 2]

    def spread_about(self, kfs: list, about: int) -> float:
        """Mean distance of the centres of keyframes ``kfs`` from keyframe ``about``'s."""
        c0 = self.kf_pose[about][:3, 3]
        return float(np.mean([np.linalg.norm(self.kf_pose[k][:3, 3] - c0) for k in kfs]))

    def scale_part(self, c0: np.ndarray, s: float, kfs: Optional[set] = None) -> None:
        """Scale by ``s`` about ``c0`` what belongs to keyframes ``kfs`` (default: everything): their
        poses, the landmarks first seen by them, the frames stored relative to them (translations)
        (the tracker's references are the front end's: :meth:`MonoFrontend._scale_part`)."""
        for k in list(self.kf_pose):
            if kfs is None or k in kfs:
                self.kf_pose[k] = scale_about(self.kf_pose[k], c0, s)
        if kfs is None:
            sel = np.arange(len(self.lm))
        else:
            lids, first = self.obs.first_keyframe_arrays()
            sel = lids[np.isin(first, np.fromiter(kfs, np.int64, len(kfs)))]
        self._map_landmarks(sel, lambda x: c0 + s * (x - c0))
        for i, (k, rel) in self.rel.items():
            if kfs is None or k in kfs:
                rel = rel.copy()
                rel[:3, 3] *= s
                self.rel[i] = (k, rel)

    def run_ba(self, fixed_all_but_points: bool = False, window: Optional[list] = None,
               max_nfev: Optional[int] = None) -> None:
        """Bundle adjustment of the keyframes ``window`` (default: the BA window; the first two fixed)
        and the landmarks they observe, at most ``max_nfev`` iterations (default ``ba_max_nfev``):
        :meth:`ba_problem`, :func:`solve_ba_problem`, :meth:`apply_ba` in one go."""
        prob = self.ba_problem(fixed_all_but_points, window, max_nfev)
        if prob is not None:
            self.apply_ba(prob, solve_ba_problem(self.camera, prob))

    def ba_problem(self, fixed_all_but_points: bool = False, window: Optional[list] = None,
                   max_nfev: Optional[int] = None) -> Optional["BAProblem"]:
        """The bundle adjustment :meth:`run_ba` would solve, copied out of the store (a
        :class:`BAProblem`, safe to solve in another thread while tracking goes on), or None when
        there is too little to adjust."""
        c = self.cfg
        win = list(self.window if window is None else window)
        if not len(self.obs):
            return None
        obs, wh = self.obs.rows(), self.obs.whiten
        kf_of = obs[:, 0].astype(np.int64)
        inwin = np.isin(kf_of, win)
        extra: list = []
        keep = inwin
        if c.ba_fixed_observers > 0 and inwin.any():
            # older keyframes that saw the window's landmarks join, fixed: their observations tie the
            # window to the past (without them scale and rotation drift from window to window)
            seen = np.isin(obs[:, 1].astype(np.int64), np.unique(obs[inwin, 1].astype(np.int64)))
            older = np.unique(kf_of[seen & ~inwin])
            extra = [int(k) for k in older[::-1][: c.ba_fixed_observers] if int(k) in self.kf_pose]
            keep = inwin | (seen & np.isin(kf_of, extra))
        obs, wh = obs[keep], wh[keep]
        if len(obs) == 0:
            return None
        lids, inv = np.unique(obs[:, 1].astype(np.int64), return_inverse=True)
        counts = np.bincount(inv)
        keep = counts[inv] >= 2
        obs, inv, wh = obs[keep], inv[keep], wh[keep]
        lids, inv = np.unique(obs[:, 1].astype(np.int64), return_inverse=True)
        if len(lids) < 10:
            return None
        order = np.array(win + extra, np.int64)  # each observation's keyframe -> its place in the problem
        srt = np.argsort(order)
        pose_of = srt[np.searchsorted(order[srt], obs[:, 0].astype(np.int64))]
        fixed = list(range(len(win))) if fixed_all_but_points else list(range(min(2, len(win))))
        fixed += list(range(len(win), len(win) + len(extra)))
        return BAProblem(win, extra, [self.kf_pose[k].copy() for k in win + extra], fixed, lids,
                         np.stack([self.lm[i] for i in lids]), pose_of,
                         inv, obs, c.ba_huber_px, c.ba_max_nfev if max_nfev is None else max_nfev, c.ba_rel_tol,
                         wh if c.ba_anisotropic else None)

    def apply_ba(self, prob: "BAProblem", res: BAResult) -> set:
        """Take the solution ``res`` of ``prob``: keyframe poses and landmarks, outlying observations
        dropped (their tracks are triangulated again later from the window's newest keyframe on).
        Returns the dropped observations as {(keyframe, landmark id)}."""
        c = self.cfg
        win, obs = prob.window, prob.obs
        for k, p in zip(win, res.poses[: len(win)]):
            self.kf_pose[k] = p
        for i, p in zip(prob.lids, res.points):
            self.lm[int(i)] = p
        # drop outlying observations (in the window)
        bad = res.residual_px > c.ba_outlier_px
        badset: set = set()
        if bad.any():
            badset = {(int(a), int(b)) for a, b in obs[bad][:, :2]}
            self.obs.drop(badset)
            bad_l = {b for _, b in badset}
            tr = self.tracks
            # merged frames after the keyframe (MonoConfig.ba_thread): restart at the keyframe's pixel, not the
            # current frame's, else the next triangulation pairs the keyframe's pose with another frame's pixel
            # (keyframes added while a loop's problem was solved: at the tracks' own keyframe, the newest)
            at = max(win[-1], tr.kf)
            restart = tr.restart_pixels(at)
            for j in np.flatnonzero(np.isin(tr.lid, list(bad_l))):
                tr.lid[j] = -1  # re-triangulate later from this keyframe on
                tr.first_kf[j] = at
                tr.uv_first[j] = restart[j]
        self.ba_stats.append({"keyframes": len(win), "fixed_observers": len(prob.extra), "points": int(len(prob.lids)),
                              "obs": int(len(obs)),
                              "rms_before_px": float(np.sqrt(2 * res.cost_before / max(1, len(obs)))),
                              "rms_after_px": float(np.sqrt(2 * res.cost_after / max(1, len(obs)))),
                              "outliers": int(bad.sum()), "ms": res.ms, "nfev": res.nfev})
        return badset


@dataclass
class BAProblem:
    """A windowed bundle adjustment copied out of a :class:`KeyframeStore`: the ``window`` keyframes
    (free but for ``fixed``) and the older ``extra`` ones (fixed), their poses, the landmarks ``lids``
    at ``points``, and per observation its pose position, point position and the store's row
    ``(keyframe, landmark id, u, v)`` (``obs``)."""
    window: list
    extra: list
    poses: list
    fixed: list
    lids: np.ndarray
    points: np.ndarray
    obs_pose: np.ndarray
    obs_point: np.ndarray
    obs: np.ndarray
    huber_px: float
    max_nfev: int
    rel_tol: float = 1e-9  # stop once a step lowers the cost by less than this fraction (MonoConfig.ba_rel_tol)
    whiten: Optional[np.ndarray] = None  # (O, 2, 2) per observation (MonoConfig.ba_anisotropic), None: isotropic


def solve_ba_problem(camera: PinholeCamera, prob: BAProblem) -> BAResult:
    """Solve ``prob`` (:func:`~fmapping.tracking.ba.bundle_adjust`); touches nothing shared, so it may
    run in another thread. ``res.ms`` is its wall time."""
    t0 = time.perf_counter()
    res = bundle_adjust(camera, prob.poses, prob.fixed, prob.points, prob.obs_pose, prob.obs_point,
                        prob.obs[:, 2:4], prob.huber_px, prob.max_nfev, prob.rel_tol, prob.whiten)
    res.ms = (time.perf_counter() - t0) * 1000
    return res
