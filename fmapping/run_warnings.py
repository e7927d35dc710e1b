"""Plain warnings for a user when a run's trajectory, and so its map, is not to be trusted. They come from the
run's own counters, never from ground truth, so a user without it gets the same: ``fmapping slam``'s summary
(:func:`fmapping.slam.job.run_slam`) and ``fmapping up``'s tracker status (``services.launcher.supervise``)."""
from __future__ import annotations

from typing import Optional


def tracking_warnings(frames: int, posed: Optional[int] = None, lost: int = 0, relocalised: int = 0,
                      degraded: bool = False, source: str = "photometric", max_unposed: float = 0.05,
                      max_relocalised: float = 0.1) -> list[str]:
    """Warnings for a run over ``frames`` frames: more than ``max_unposed`` of them without a pose (``posed``, when
    known; ``source`` names where poses come from, "photometric" for the monocular front end), tracking ``lost``
    on some frames, more than ``max_relocalised`` of them ``relocalised``, or ``degraded`` at the end."""
    if int(frames) <= 0:
        return []  # stopped before its first frame: nothing ran to be trusted or not
    n = int(frames)
    out = []
    if posed is not None and n - int(posed) > max_unposed * n:
        why = (": the monocular start needs texture and camera translation (not only rotation) in its first frames"
               if source == "photometric" else f" from the pose source ({source})")
        out.append(f"{n - int(posed)} of {n} frames have no pose{why}")
    if lost:
        out.append(f"tracking was lost on {int(lost)} frame(s); {int(relocalised)} frame(s) were re-localised: the "
                   f"trajectory and the map may be wrong there (weak texture, fast motion or blur)")
    elif relocalised > max_relocalised * n:
        out.append(f"{int(relocalised)} of {n} frames were re-localised: tracking was fragile")
    if degraded:
        out.append("the run ended degraded: the map could not give depth to the tracker")
    return out
