"""The mono tracker's saved keyframes (``TrackerServiceOptions.state_path``, ``--state``): written after
each keyframe, read by a restarted tracker to re-localise against them (:meth:`MonoFrontend.resume`).
"""
from __future__ import annotations

import logging
import threading
from typing import Optional

import numpy as np

from fmapping.fileio import atomic_open

log = logging.getLogger("fmapping.tracker")


RESUME_KEYS = {"index": 0, "gray": 2, "c2w": 2, "world": 2, "uv": 2, "prev_index": 0, "prev_c2w": 2}  # key: ndim
OPTIONAL_KEYS = {"lid": 1}  # the landmarks' ids (files of before them resume against one keyframe)


def save_resume_state(path, states: list) -> None:
    """``states`` (:meth:`MonoFrontend.keyframe_states`) as one .npz (``k<i>_<key>``), written
    atomically (temp file, fsync, rename)."""
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, fsync=True) as fh:
        np.savez(fh, **{f"k{i}_{k}": np.asarray(st[k]) for i, st in enumerate(states)
                        for k in (*RESUME_KEYS, *OPTIONAL_KEYS) if k in st})


class StateWriter:
    """Writes the newest states given to it (:func:`save_resume_state`) in a thread of its own: the atomic write
    with its fsync took ~25 ms a keyframe on the frame path beside the busy recorder and mapper. A state given
    while another is being written replaces any still waiting (only the newest matters). ``saved`` counts the
    files written, ``error`` is the last failure (None once one succeeds)."""

    def __init__(self, path):
        self.path = path
        self.saved = 0
        self.error: Optional[str] = None
        self._pending: Optional[list] = None
        self._busy = False
        self._closed = False
        self._cv = threading.Condition()
        self._thread: Optional[threading.Thread] = None

    def put(self, states: list) -> None:
        with self._cv:
            if self._closed:
                raise RuntimeError("StateWriter.put after close")
            self._pending = states
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="tracker-state", daemon=True)
                self._thread.start()
            self._cv.notify_all()

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending is not None or self._closed)
                if self._pending is None:
                    return
                states, self._pending, self._busy = self._pending, None, True
            try:
                save_resume_state(self.path, states)
                error = None
            except OSError as e:
                error = f"tracker state not saved: {e}"
            with self._cv:
                self._busy = False
                self.error = error
                self.saved += error is None
                self._cv.notify_all()

    def flush(self, timeout: float = 30.0) -> bool:
        """Wait until everything given so far is written (or failed); False on time-out."""
        with self._cv:
            return self._cv.wait_for(lambda: self._pending is None and not self._busy, timeout)

    def close(self, timeout: float = 30.0) -> bool:
        """Write what is waiting, then stop the thread. True when all was written in time."""
        done = self.flush(timeout)
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
        return done


def _resume_entry(z, i: int) -> dict:
    """Keyframe ``i`` of a loaded state file, checked (ValueError / KeyError when it is not one)."""
    st = {k: np.array(z[f"k{i}_{k}"]) for k in RESUME_KEYS}
    st.update({k: np.array(z[f"k{i}_{k}"]) for k in OPTIONAL_KEYS if f"k{i}_{k}" in z.files})
    bad = [k for k, nd in {**RESUME_KEYS, **OPTIONAL_KEYS}.items() if k in st and st[k].ndim != nd]
    n = len(st["world"])
    if bad or st["c2w"].shape != (4, 4) or st["world"].shape != (n, 3) or st["uv"].shape != (n, 2) \
            or ("lid" in st and (st["lid"].shape != (n,) or st["lid"].dtype.kind not in "iu")) \
            or not all(np.isfinite(st[k]).all() for k in ("c2w", "world", "uv", "prev_c2w")):
        raise ValueError(f"keyframe {i}: unexpected arrays {bad or 'shapes'}")
    st["index"], st["prev_index"] = int(st["index"]), int(st["prev_index"])
    return st


def load_resume_state(path) -> Optional[list]:
    """The keyframes :func:`save_resume_state` wrote (oldest first), or None when there is no such file
    or it is not one (logged)."""
    from pathlib import Path

    if not Path(path).is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            count = len({name.split("_", 1)[0] for name in z.files})
            states = [_resume_entry(z, i) for i in range(count)]
        if not states or len({st["gray"].shape for st in states}) != 1:
            raise ValueError("no keyframes, or images of different sizes")
    except (OSError, ValueError, KeyError, EOFError) as e:
        log.warning("ignoring the tracker state %s: %s", path, e)
        return None
    return states
