"""Settings of the monocular front end (:class:`MonoConfig`); the package docstring of
:mod:`fmapping.tracking.mono` says what each stage does."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fmapping.tracking.features import KltConfig
from fmapping.tracking.loop import LoopConfig


@dataclass
class MonoConfig:
    klt: KltConfig = field(default_factory=KltConfig)
    init_min_parallax_deg: float = 1.0  # median parallax of the triangulated tracks to accept the bootstrap ...
    init_min_parallax_px: float = 20.0  # ... and that parallax times the focal length (pixel noise matters);
    init_fallback_parallax_px: float = 10.0  # accepted instead once fewer than 2 x init_min_points tracks survive
    init_min_points: int = 60
    init_max_frames: int = 60  # give up the bootstrap after this many frames
    init_min_flow_px: float = 6.0  # median track length (scaled to a 320-px-wide image) before trying
    ransac_px: float = 1.0
    tri_min_parallax_deg: float = 1.0
    tri_max_reproj_px: float = 2.0
    min_ref_points: int = 40
    unit_depth: float = 2.0  # scale convention without an anchor: median scene depth of the bootstrap
    # keyframes in the bundle adjustment. Synthetic rooms (200 frames), Sim3 ATE seeds 0-4: 7 -> 0.91 / 1.61 /
    # 2.00 / 0.80 / 1.99 cm, 10 -> 0.91 / 1.49 / 1.95 / 0.80 / 1.91 cm (14: the same as 10); TUM fr1_rpy
    # SE3 3.45 -> 3.33 cm, rotation from the first GT pose 1.69 -> 1.60 deg.
    window: int = 10
    # Up to this many older keyframes that saw the window's landmarks join the BA, fixed. Measured with 10:
    # synthetic rooms (200 frames), Sim3 ATE seeds 0-4: 0.91 / 1.61 / 2.00 / 0.80 / 1.99 cm (0) -> 0.90 / 1.78 /
    # 1.91 / 0.55 / 1.88 cm; but TUM fr1_rpy (60 frames): rotation from the first GT pose 1.69 -> 2.42 deg,
    # SE3 3.45 -> 3.50 cm (3 gave the same). Off by default.
    ba_fixed_observers: int = 0
    ba: bool = True
    ba_huber_px: float = 1.5
    ba_max_nfev: int = 15
    ba_outlier_px: float = 4.0  # observations beyond this after BA are dropped
    # Add depth from ``extra_depth`` (the map) to new keyframes when given ... Off: on the synthetic
    # room (seed 0, 200 frames, with the 21 px KLT window of then) the map's depth sat ~2 % off the
    # landmarks and Sim3 ATE went 1.46 cm (off) -> 2.39 cm (on, gated as below); ungated it derailed
    # tracking (24 cm).
    dense_extra: bool = False
    dense_max_gap: float = 0.05  # ... and when, at the landmarks' pixels, its median relative gap to the
    dense_min_rendered: float = 0.5  # landmarks' depth is below this, with depth at this fraction of them
    klt_from_keyframe: bool = True  # re-track from the keyframe image (chained positions as the guess): no KLT drift
    pose_refine: str = "pnp"  # per-frame pose after direct alignment: "pnp" (reprojection of tracked landmarks) | "none"
    reinit_after: int = 3  # consecutive lost frames after which the current frame becomes a keyframe
    #                        with a constant-depth plane at the last median depth (reported as "reinit")
    pnp_min_points: int = 30
    pnp_recovery: bool = True  # a frame the direct alignment loses gets its pose from the landmarks (PnP + RANSAC)
    pnp_inlier_px: float = 2.0
    # With an anchor, its baseline sets the scale again at the first tracked frame with an anchor pose from
    # frame first + late_anchor_frames - 1 on (15: frame 14, the end of the mapper's init window, where the
    # map front end takes its scale): everything is scaled about the first camera centre then. The
    # bootstrap's baseline is a few frames long (TUM fr1_rpy: 1.3 cm at frame 4), too short to fix the
    # scale: by frame 14 the GT has moved 3.0x as far as the estimate. Given up (scale kept) after twice
    # as many frames without one. 0: the bootstrap's scale stays.
    late_anchor_frames: int = 15
    late_anchor_factor_max: float = 10.0  # a refresh changing the scale by more (or less than 1/this) is refused
    loop: LoopConfig = field(default_factory=LoopConfig)  # loop closure at keyframes (fmapping.tracking.loop)
    # Rolling shutter: readout time from the first to the last row as a fraction of the frame interval
    # (0: global shutter). Tracked pixels are unrolled (fmapping.tracking.rolling_shutter) before PnP,
    # triangulation and bundle adjustment, with each frame's rotation since the previous one. TUM fr1_rpy
    # (60 frames): its images prefer 0.85 (bench/tracking.py images_optimum: the optimum's cost 23 % below
    # the global shutter's); the front end with 0.85, median of 6 runs, best-fit rotation 1.70 -> 1.39 deg
    # but SE3 2.98 -> 3.22 cm. On global-shutter frames it costs accuracy (synthetic, 30 frames: Sim3
    # 0.23 cm at 0, 0.62 cm at 1.0). Off by default.
    rolling_shutter: float = 0.0

    def validate(self) -> None:
        if not (np.isfinite(self.rolling_shutter) and 0.0 <= self.rolling_shutter <= 1.0):
            raise ValueError(f"mono.rolling_shutter is the readout time as a fraction of the frame interval, "
                             f"0 (global shutter) to 1, got {self.rolling_shutter}")
        self.loop.validate()
