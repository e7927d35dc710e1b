"""The mapper's intake: which frames wait for the mapper and which go when it falls behind.

Frames come at the camera's rate whether the mapper is ready or not; one mapper update (the init
stage, a window) takes longer than many frames. Keyframes are what the map is made of, so:

* the pose source flags its keyframes (``Pose.keyframe``; the mono tracker by parallax and overlap).
  For a source that does not (``gt``, ``external``) the mapper flags them itself by camera motion
  (:func:`moved_enough`: every ``every``-th frame, or ``min_move_m`` / ``min_turn_deg`` since the
  last keyframe);
* the frames channel of the mapper's inbox is bounded by :data:`FRAME_CAPACITY` frames and
  :data:`FRAME_BYTES` bytes (the documented ceiling: 512 frames, 384 MiB; 640x480 RGB frames are
  0.9 MB, so about 415 of them). When full it evicts, thinned evenly over time, first frames known
  not to be keyframes, then frames whose pose has not come yet, and keyframes only when it holds
  nothing else (``dropped_frames_rank2``);
* a mapper more than ``behind_frames`` frames behind skips the frames known not to be keyframes
  (``frames_thinned``) and lets its next window take up to a whole local window of new frames
  (:meth:`fmapping.mapping.Mapper.add_frame` ``defer``), so that it catches up.

:class:`KeyframeBook` holds the flags; it is filled from the zenoh callbacks (the inbox asks it at
eviction time) and read by the worker, hence its lock.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Optional

import numpy as np

from fmapping import protocol as P
from fmapping.geometry import pose_distance
from services.core_support import MIB

FRAME_CAPACITY = 512
FRAME_BYTES = 384 * MIB


def inbox_frames_ok(frames) -> bool:
    """A frames-inbox bound in frames: an integer of at least 1."""
    return isinstance(frames, int) and not isinstance(frames, bool) and frames >= 1


def inbox_mib_ok(mib) -> bool:
    """A frames-inbox bound in MiB: a number above 0, finite."""
    return isinstance(mib, (int, float)) and not isinstance(mib, bool) and 0 < mib < float("inf")
NOT_KEYFRAME, UNKNOWN, KEYFRAME = 0, 1, 2  # eviction ranks: lowest goes first


def moved_enough(c2w: np.ndarray, last_kf: Optional[np.ndarray], frames_since: int, every: int, min_move_m: float,
                 min_turn_deg: float) -> bool:
    """The mapper's own keyframe rule for a pose source that flags none: the first frame, every ``every``-th
    frame since the last keyframe, or a camera that moved ``min_move_m`` / turned ``min_turn_deg`` since it."""
    if last_kf is None or frames_since >= every:
        return True
    dt, dr = pose_distance(last_kf, c2w)
    return dt >= min_move_m or dr >= min_turn_deg


class KeyframeBook:
    """Keyframe flags by frame number (bounded: the newest ``max_entries``). ``source_flags``: the pose
    source marks its keyframes (trust ``Pose.keyframe``); else :func:`moved_enough` decides."""

    def __init__(self, source_flags: bool, every: int = 5, min_move_m: float = 0.05, min_turn_deg: float = 5.0,
                 max_entries: int = 8192):
        self.source_flags = source_flags
        self.every, self.min_move_m, self.min_turn_deg = int(every), float(min_move_m), float(min_turn_deg)
        self.max_entries = int(max_entries)
        self._flags: "OrderedDict[int, bool]" = OrderedDict()
        self._last_kf: Optional[tuple[int, np.ndarray]] = None
        self._lock = threading.Lock()

    def note(self, p: P.Pose) -> bool:
        """Record the keyframe flag of pose ``p`` (the first pose of a frame decides; an unusable pose
        marks no keyframe); returns it."""
        with self._lock:
            if p.seq in self._flags:
                return self._flags[p.seq]
            usable = p.quality is None or p.quality > 0
            if not usable:
                flag = False
            elif self.source_flags:
                flag = bool(p.keyframe)
            else:
                last = self._last_kf
                since = p.seq - last[0] if last is not None else 0
                flag = moved_enough(np.asarray(p.c2w), None if last is None or since < 0 else last[1],
                                    max(since, 0), self.every, self.min_move_m, self.min_turn_deg)
            if flag and (self._last_kf is None or p.seq > self._last_kf[0]):
                self._last_kf = (p.seq, np.array(p.c2w))
            self._flags[p.seq] = flag
            if len(self._flags) > self.max_entries:
                for s in sorted(self._flags)[: len(self._flags) - self.max_entries]:
                    del self._flags[s]
            return flag

    def rank(self, seq: int) -> int:
        """Eviction rank of frame ``seq``: :data:`NOT_KEYFRAME`, :data:`UNKNOWN` (no pose yet) or :data:`KEYFRAME`."""
        with self._lock:
            flag = self._flags.get(seq)
        return UNKNOWN if flag is None else (KEYFRAME if flag else NOT_KEYFRAME)

    def is_keyframe(self, seq: int) -> bool:
        return self.rank(seq) == KEYFRAME

    def forget_before(self, seq: int) -> None:
        """Drop the flags of frames before ``seq`` (consumed)."""
        with self._lock:
            for s in [s for s in self._flags if s < seq]:
                del self._flags[s]


def book_for(opts) -> KeyframeBook:
    """The keyframe book of validated :class:`services.mapper.core.MapperServiceOptions`."""
    return KeyframeBook(opts.keyframes == "source", opts.keyframe_every, opts.keyframe_move_m, opts.keyframe_turn_deg,
                        max_entries=opts.max_poses)


def frame_rank(book: KeyframeBook):
    """The inbox rank function of the mapper's frames channel (items are ``(key, Frame)``)."""
    def rank(item: Any) -> int:
        msg = item[1] if isinstance(item, tuple) else item
        return book.rank(int(getattr(msg, "seq", -1)))
    return rank
