"""The keyframe bundle adjustment off the frame path (``MonoConfig.ba_thread``), as ORB-SLAM's local
mapping thread: at a keyframe the front end copies the window's problem out of its store
(:meth:`~fmapping.tracking.mono.store.KeyframeStore.ba_problem`) and solves it in a worker thread
while the next frames are tracked against the keyframe as it was. The solution is merged between
frames: as soon as it is ready, and at the latest before anything that changes the store (the next
keyframe, a rescale, a re-initialisation) or reads refined poses. One problem is in flight at a time.

Solving touches nothing shared (numpy / LAPACK release the GIL for most of it), so the only
synchronisation is the hand-over of one finished result. A problem submitted with ``release_memory``
(a loop closure's, ``MonoConfig.ba_release_memory``) has the worker hand the C heap's free pages back
after solving it (:func:`fmapping.runtime.release_free_memory`): the tracker service keeps freed memory
for reuse, and a loop's problem would otherwise leave its peak (tens of MB) resident for the rest of
the run. The small window problems keep their memory for the next one.
"""
from __future__ import annotations

import threading
from typing import Optional

from fmapping.camera import PinholeCamera
from fmapping.runtime import release_free_memory
from fmapping.tracking.ba import BAResult
from fmapping.tracking.mono.store import BAProblem, solve_ba_problem


class BackgroundBA:
    """One bundle adjustment at a time in a worker thread: :meth:`submit`, then :meth:`take` it."""

    def __init__(self, camera: PinholeCamera):
        self.camera = camera
        self._job: Optional[tuple] = None  # (problem, thread, box): box holds "result" or "error"
        self.submitted = 0
        self.waited = 0  # takes that had to wait for the worker (the frame path paid for them)

    @property
    def busy(self) -> bool:
        """Is a problem in flight (solved or not, not yet taken)?"""
        return self._job is not None

    def ready(self) -> bool:
        return self._job is not None and not self._job[1].is_alive()

    def submit(self, prob: BAProblem, release_memory: bool = False) -> None:
        if self._job is not None:
            raise RuntimeError("BackgroundBA.submit while a bundle adjustment is in flight: take it first")
        box: dict = {}

        def work() -> None:
            try:
                box["result"] = solve_ba_problem(self.camera, prob)
            except Exception as e:  # noqa: BLE001 - handed to the taker, raised there
                box["error"] = e
            if release_memory:
                release_free_memory()

        t = threading.Thread(target=work, name="fmapping-ba", daemon=True)
        self._job = (prob, t, box)
        self.submitted += 1
        t.start()

    def take(self, wait: bool) -> Optional[tuple[BAProblem, BAResult]]:
        """The finished (problem, result), or None when nothing is in flight or (``wait`` False) it is
        still being solved. With ``wait`` it blocks until the worker is done. A failed solve raises
        here, in the taker's thread."""
        if self._job is None:
            return None
        prob, t, box = self._job
        if t.is_alive():
            if not wait:
                return None
            self.waited += 1
            t.join()
        self._job = None
        if "error" in box:
            raise box["error"]
        return prob, box["result"]
