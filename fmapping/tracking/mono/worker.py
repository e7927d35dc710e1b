"""One job at a time in a worker thread, handed back between frames: the front end's way of taking work off
the frame path (the keyframe bundle adjustment, :mod:`~fmapping.tracking.mono.ba_thread`; the loop search,
:mod:`~fmapping.tracking.mono.loop_closing`). The job reads only what it was given (copies), so the only
synchronisation is the hand-over of one finished result."""
from __future__ import annotations

import threading
from typing import Any, Callable, Optional


class BackgroundJob:
    """:meth:`start` a call in a worker thread, :meth:`take` its result later (on the caller's thread)."""

    def __init__(self, name: str):
        self.name = name
        self._job: Optional[tuple] = None  # (tag, thread, box): box holds "result" or "error"
        self.submitted = 0
        self.waited = 0  # takes that had to wait for the worker (the frame path paid for them)

    @property
    def busy(self) -> bool:
        """Is a job in flight (finished or not, not yet taken)?"""
        return self._job is not None

    def ready(self) -> bool:
        """Is a job finished and waiting to be taken?"""
        return self._job is not None and not self._job[1].is_alive()

    def start(self, tag: Any, fn: Callable[[], Any]) -> None:
        """Run ``fn()`` in the worker; ``tag`` comes back with its result."""
        if self._job is not None:
            raise RuntimeError(f"{self.name}: a job is in flight: take it first")
        box: dict = {}

        def work() -> None:
            try:
                box["result"] = fn()
            except Exception as e:  # noqa: BLE001 - handed to the taker, raised there
                box["error"] = e

        t = threading.Thread(target=work, name=self.name, daemon=True)
        self._job = (tag, t, box)
        self.submitted += 1
        t.start()

    def take(self, wait: bool) -> Optional[tuple[Any, Any]]:
        """The finished (tag, result), or None when nothing is in flight or (``wait`` False) it is still
        running. With ``wait`` it blocks until the worker is done. A failed job raises here, in the taker's
        thread."""
        if self._job is None:
            return None
        tag, t, box = self._job
        if t.is_alive():
            if not wait:
                return None
            self.waited += 1
            t.join()
        self._job = None
        if "error" in box:
            raise box["error"]
        return tag, box["result"]
