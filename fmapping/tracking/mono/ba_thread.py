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

from fmapping.camera import PinholeCamera
from fmapping.runtime import release_free_memory
from fmapping.tracking.mono.store import BAProblem, solve_ba_problem
from fmapping.tracking.mono.worker import BackgroundJob


class BackgroundBA(BackgroundJob):
    """One bundle adjustment at a time in a worker thread: :meth:`submit`, then :meth:`take` (problem, result)."""

    def __init__(self, camera: PinholeCamera):
        super().__init__("fmapping-ba")
        self.camera = camera

    def submit(self, prob: BAProblem, release_memory: bool = False) -> None:
        if self.busy:
            raise RuntimeError("BackgroundBA.submit while a bundle adjustment is in flight: take it first")

        def work():
            try:
                return solve_ba_problem(self.camera, prob)
            finally:
                if release_memory:
                    release_free_memory()

        self.start(prob, work)
