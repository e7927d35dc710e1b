"""Going on after a restart: the newest keyframes saved from one front end, a new one located among
their landmarks, in the same world frame and scale."""
from __future__ import annotations

from typing import Optional

import numpy as np

from fmapping.geometry import orthonormalize
from fmapping.tracking.features import to_u8
from fmapping.tracking.loop import locate_in_keyframe
from fmapping.tracking.mono.store import Observations, Tracks


class Restart:
    """:meth:`keyframe_states` and :meth:`resume`. A mixin of :class:`~fmapping.tracking.mono.frontend.MonoFrontend`:
    it works on the front end's state (``store``, ``tracker``, ``cfg`` and the fields ``MonoFrontend.__init__``
    sets) and its ``_set_reference``."""

    def keyframe_states(self, n: int = 5) -> list:
        """What a restarted front end needs to go on in this world frame and scale (:meth:`resume`): for
        the newest ``n`` keyframes of the bundle-adjustment window (oldest first), the frame number, grey
        image and pose, and the landmarks it observed (ids, world points and their pixels there). Empty
        before the bootstrap and while the scale is pending."""
        if not self.initialized or self.scale_pending:
            return []
        kfs = self.store.window[-n:]
        seen_by: dict = {}  # keyframe -> {landmark: pixel}
        for k in kfs:
            lids, uv = self.store.obs.of_keyframe(k)
            seen_by[k] = {int(i): (float(u), float(v)) for i, (u, v) in zip(lids, uv)}
        out = []
        for k in kfs:
            seen = seen_by[k]
            if k not in self.store.kf_pose or k not in self.store.kf_rgb or len(seen) < self.cfg.min_ref_points:
                continue
            lids = np.array(sorted(seen), np.int64)
            prev = max((j for j in self.store.kf_pose if j < k), default=k)  # for a motion guess (resume)
            out.append({"index": int(k), "gray": to_u8(self.store.kf_rgb[k]), "c2w": self.store.kf_pose[k].copy(),
                        "world": np.stack([self.store.lm[i] for i in lids]).astype(np.float64),
                        "uv": np.array([seen[i] for i in lids], np.float64), "lid": lids,
                        "prev_index": int(prev), "prev_c2w": self.store.kf_pose[prev].copy()})
        return out

    def resume(self, index: int, rgb: np.ndarray, states: list) -> Optional[np.ndarray]:
        """Start from saved keyframes (``states`` of :meth:`keyframe_states`) instead of a bootstrap:
        frame ``index`` is located among the landmarks of the keyframe nearest to it in frame number
        (KLT from the keyframe's image, rotated into the view, then PnP:
        :func:`~fmapping.tracking.loop.locate_in_keyframe`), the next nearest when that fails. When
        it is found, it becomes the first keyframe, at the located pose, holding the located
        landmarks, and tracking goes on from it in the saved world frame and scale: returns its
        pose. None when the images do not agree (the front end is unchanged). The pose is searched
        from guesses along the keyframes' motion, continued at constant velocity up to frame
        ``index`` (the frames between went by unseen); the guess locating most landmarks wins."""
        for state in sorted(states, key=lambda st: (abs(index - int(st["index"])), -int(st["index"]))):
            c2w = self._resume_from(index, rgb, state, states)
            if c2w is not None:
                return c2w
        return None

    def _resume_from(self, index: int, rgb: np.ndarray, state: dict, states: list) -> Optional[np.ndarray]:
        """:meth:`resume` against one saved keyframe."""
        gray = to_u8(rgb)
        c2w_kf = np.asarray(state["c2w"], np.float64)
        best = None
        for guess in resume_guesses(state, index):
            m = locate_in_keyframe(self.camera, np.asarray(state["gray"], np.uint8),
                                   np.asarray(state["uv"], np.float64), np.asarray(state["world"], np.float64),
                                   c2w_kf, gray, guess, self.cfg.klt, self.cfg.loop)
            if m is not None and (best is None or m.inliers > best.inliers):
                best = m
        m = best
        if m is None or len(m.index) < self.cfg.min_ref_points:
            return None
        c2w = orthonormalize(m.c2w)
        kept, lm, obs, ids = restored_keyframes(states, state, index)
        if not kept:  # the saved keyframe alone, its landmarks numbered afresh
            lm, obs = list(np.asarray(state["world"], np.float64)), Observations()
            ids = np.arange(len(lm), dtype=np.int64)
        lids = ids[m.index]
        self._first_index = self._kf_index = index
        self._c2w0 = c2w.copy()
        self.store.kf_pose = {**{int(st["index"]): np.asarray(st["c2w"], np.float64).copy() for st in kept},
                              index: c2w.copy()}
        self.store.kf_rgb = {**{int(st["index"]): np.asarray(st["gray"], np.uint8) for st in kept}, index: rgb}
        self.store.window = ([int(st["index"]) for st in kept] + [index])[-self.cfg.window:]
        self.store.lm = lm
        obs.extend(index, lids, m.uv)
        self.store.obs = obs
        tr = Tracks(m.uv, index)
        tr.lid = lids.astype(np.int64)
        self.store.tracks = tr
        self.store.rel = {k: (k, np.eye(4)) for k in self.store.kf_pose}
        self._last_gray, self._last_gray_frame = gray, index
        self.tracker.reset_motion([c2w], [index])
        try:
            self._set_reference(index, rgb, gray)
        except ValueError:
            return None  # too few points with depth to track against (still uninitialised)
        if self.cfg.loop.enabled:
            self._kf_images = {**{int(st["index"]): np.asarray(st["gray"], np.uint8) for st in kept}, index: gray}
        self.initialized, self.failed, self._buf = True, False, []
        self.init_info = {"frame": int(index), "resumed_from": int(state["index"]), "points": int(len(lids)),
                          "keyframes_restored": len(kept), "scale_from": "resumed"}
        return c2w


def restored_keyframes(states: list, located: dict, index: int) -> tuple:
    """The saved keyframes a front end resumed at frame ``index`` (located against keyframe ``located``, one of
    ``states``) goes on with: ``(kept, landmarks, observations, ids)``, the states older than ``index`` (oldest
    first), the world points of their landmarks (each once), their observations (the identity whitening: the
    corners' shapes are not saved) and the new id of each of ``located``'s landmarks. ``([], [], None, None)`` when
    ``located`` is not among them, or a state holds no landmark ids (a file of before they were saved)."""
    kept = sorted((st for st in states if int(st["index"]) < index), key=lambda st: int(st["index"]))
    if not any(st is located for st in kept) or any("lid" not in st for st in kept):
        return [], [], None, None
    new_id: dict = {}
    lm: list = []
    obs = Observations()
    for st in kept:
        ids = np.empty(len(st["lid"]), np.int64)
        for j, (lid, w) in enumerate(zip(np.asarray(st["lid"]).tolist(), np.asarray(st["world"], np.float64))):
            if lid not in new_id:
                new_id[lid] = len(lm)
                lm.append(w.copy())
            ids[j] = new_id[lid]
        obs.extend(int(st["index"]), ids, np.asarray(st["uv"], np.float64))
        if st is located:
            located_ids = ids
    return kept, lm, obs, located_ids


def resume_guesses(state: dict, index: int, n: int = 8) -> list:
    """Pose guesses for frame ``index`` after a saved keyframe ``state`` (one of :meth:`MonoFrontend.keyframe_states`):
    the keyframe's pose moved on at the velocity between its previous keyframe and it, by 0 to
    1.5 times the frames in between, backwards for a frame before the keyframe (``n`` + 1 guesses;
    the keyframe's pose alone without a previous keyframe)."""
    import cv2

    c2w, k = np.asarray(state["c2w"], np.float64), int(state["index"])
    prev, kp = np.asarray(state.get("prev_c2w", c2w), np.float64), int(state.get("prev_index", k))
    if kp >= k or index == k:
        return [c2w]
    rvec = cv2.Rodrigues(prev[:3, :3].T @ c2w[:3, :3])[0].ravel() / (k - kp)  # per frame, in the camera frame
    vel = (c2w[:3, 3] - prev[:3, 3]) / (k - kp)  # per frame, in the world
    out = []
    for d in np.linspace(0.0, 1.5 * (index - k), n + 1):
        g = np.eye(4)
        g[:3, :3] = c2w[:3, :3] @ cv2.Rodrigues(rvec * d)[0]
        g[:3, 3] = c2w[:3, 3] + vel * d
        out.append(g)
    return out
