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
    # weigh each track's pixel error by the shape of its corner (features.corner_covariance): points on edges and
    # stripes count only across the edge, where LK can measure them (bench/results/anisotropic_tracks/)
    anisotropic_tracks: bool = True
    # ... and the bootstrap's two-view pose, once the isotropic one would be accepted, is fitted again on the
    # whitened error from this many translation directions too (its cost on a nearly planar scene has local
    # minima; 0: from RANSAC's start only)
    init_two_view_starts: int = 8
    # ... and replaces the isotropic pose only when their translations differ by more than this: within it
    # either is as good (the rest of the front end weighs pixel errors alike), beyond it the isotropic one is
    # the aperture problem's
    init_whitened_min_change_deg: float = 15.0
    tri_min_parallax_deg: float = 1.0
    tri_max_reproj_px: float = 2.0
    min_ref_points: int = 40
    unit_depth: float = 2.0  # scale convention without an anchor: median scene depth of the bootstrap
    # keyframes in the bundle adjustment: 10 tracked as well as 7 or better on the synthetic rooms and on TUM fr1_rpy,
    # and 14 no better than 10 (bench/results/mono_tuning.md).
    window: int = 10
    # Up to this many older keyframes that saw the window's landmarks join the BA, fixed. Off by default:
    # they helped on four of five synthetic rooms but cost rotation accuracy on TUM fr1_rpy
    # (bench/results/mono_tuning.md).
    ba_fixed_observers: int = 0
    ba: bool = True
    ba_huber_px: float = 1.5
    ba_max_nfev: int = 15
    # ... and stops once an accepted step lowers the robust cost by less than this fraction of it (keyframe and
    # loop bundle adjustments). The window BA is within 0.1 % of its optimum after 3-4 evaluations; 1e-9 (the
    # old rule) ran ~14 of 15 for the last 0.03 %. With direct_step_tol below, on five synthetic rooms: BA time
    # 2.3x less, Sim3 ATE 0.47/1.48/0.59/0.80/0.69 -> 0.47/1.40/0.61/0.67/0.71 cm; TUM fr1_rpy 1.92 -> 1.19,
    # 7-Scenes dev 2.79 -> 2.93 cm. 1e-3 (3.1x less) lost the loop of tests/test_loop.py's 160x120 room
    # (bench/results/tracker_cpu/).
    ba_rel_tol: float = 1e-4
    ba_outlier_px: float = 4.0  # observations beyond this after BA are dropped
    # Weigh each keyframe observation's pixel error by its corner in that keyframe (KeyframeStore._whitening):
    # variance 1 + ba_anisotropic_noise / lambda along each eigenvector of the structure tensor (grey
    # levels per pixel, squared, summed over the LK window), at most ba_anisotropic_cap. On a stripe KLT cannot see
    # motion along it; after skipped frames tracks that slid along stripes bent window BAs by centimetres (2 of 64
    # skip patterns ended at 44 cm). Weighing by the eigenvalues' ratio alone (the bootstrap's corner_covariance)
    # also discounts well-measured textured corners and cost synthetic room 3 1.3 cm offline
    # (bench/results/anisotropic_ba_2026-12-07/)
    ba_anisotropic: bool = True
    ba_anisotropic_noise: float = 50.0
    ba_anisotropic_cap: float = 100.0
    # A track whose landmark reprojects farther than this (pixels at 320 px of width) from it in a new keyframe, at
    # the keyframe's pose, adds no observation there and starts again from there (as a BA outlier does), unless
    # more than kf_obs_max_share of the keyframe's tracks are that far (then the pose is what is off). On a
    # repeating pattern KLT can lock onto the next period and keep the track there, 30 px off; a few dozen such
    # observations bent a window BA by 15 cm. 0: every track adds its observation (before 2026-12-07).
    # Offline (fmapping slam) Sim3 ATE: default rooms 0-4 0.62/1.12/0.54/0.66/0.70 -> 0.59/1.11/0.60/0.60/0.62 cm;
    # TUM fr1_rpy, 6 copies, mean 2.24 -> 2.28 cm; 7-Scenes dev 2.81/3.16/2.95/3.21 -> 2.91/2.91/2.90/3.03 cm
    # (bench/results/motion_gaps_2026-12-07/)
    kf_obs_max_px: float = 8.0
    kf_obs_max_share: float = 0.3
    # After frames skipped to keep pace (the tracker service at a camera's rate), KLT starts each track where the
    # frame's predicted pose puts its landmark (MonoFrontend._klt_guess) instead of at its last pixel: the flow
    # is then two frames' or more, and on a repeating pattern beyond half a period KLT locks onto the next one.
    # Without skipped frames nothing changes (bench/results/motion_gaps_2026-12-07/)
    klt_gap_guess: bool = True
    # When the sequence ends, one bundle adjustment of all keyframes (MonoFrontend.final_ba; the first two fixed), at
    # most final_ba_max_nfev iterations: "after_loops" when a loop was closed, "always" or "never". Paired runs
    # (bench/results/final_ba_2026-12-06/, Sim3 ATE): 7-Scenes long walk (17-21 loops) 5.35 / 5.04 / 5.03 ->
    # 4.82 / 4.22 / 4.09 cm; TUM fr1_rpy (no loop) worse in 4 of 4 (1.89-2.21 -> 2.03-2.82); 7-Scenes dev (2-4 loops)
    # worse in 3 of 4 (median 2.92 -> 2.99); the synthetic rooms with loops unchanged, without (seeds 1, 3) better in
    # 5 of 6. 30 iterations gave the same.
    final_ba: str = "after_loops"
    final_ba_max_nfev: int = 10
    # Solve the keyframe BA in a worker thread while the next frames are tracked (fmapping.tracking.mono.ba_thread):
    # a keyframe then costs its frame ~5 ms instead of ~150 ms. The merge point depends on timing, so results
    # vary from run to run; off for the offline runs, on in the tracker service at a camera's rate.
    ba_thread: bool = False
    # ... and the loop search at a keyframe (verification, cross-check, pose graph: 20-60 ms at 320x240) in another
    # worker (fmapping.tracking.mono.loop_closing): its correction is merged at a later frame, when the BA worker
    # is idle; while the loop's BA is in that worker (0.6-0.7 s at 320x240), keyframes are added without waiting
    # for it and move with its newest keyframe when it is merged. Needs ba_thread.
    loop_thread: bool = False
    # ... and after a loop closure's BA the worker hands the C heap's free pages back (fmapping.runtime): the tracker
    # service retains freed memory for reuse, so the loop's ~26 MB of temporaries stayed resident. Not after the
    # window BAs: trimming after each of them looked slower (bench/tracker_realtime.py, 8 alternated runs: pose latency
    # p95 median 0.80 s against 0.42 s without, worse in 6 of the 8 pairs; bench/results/tracker_memory/)
    ba_release_memory: bool = True
    # ... and with it, while the worker solves a loop closure's bundle adjustment, a frame asking to become a
    # keyframe stays an ordinary one (tracked against the current keyframe) for up to this many tracked frames in
    # a row, instead of waiting for the worker on the frame path (MonoFrontend._defer_keyframe; 0: always wait) ...
    loop_ba_defer_frames: int = 15
    ba_defer_min_visible: float = 0.5  # ... while the frame still sees this fraction of the keyframe's reference
    # Add depth from ``extra_depth`` (the map) to new keyframes when given ... Off: the map's depth sits a
    # little off the landmarks, which cost accuracy even gated as below, and ungated it derailed tracking
    # (bench/results/mono_tuning.md).
    dense_extra: bool = False
    dense_max_gap: float = 0.05  # ... and when, at the landmarks' pixels, its median relative gap to the
    dense_min_rendered: float = 0.5  # landmarks' depth is below this, with depth at this fraction of them
    klt_from_keyframe: bool = True  # re-track from the keyframe image (chained positions as the guess): no KLT drift
    # ... without the forward-backward check: the re-tracked position is kept only within 2 px of the chained one,
    # which had that check. A quarter of the KLT time (bench/mono_variants.py, KLT ms a frame: five synthetic rooms
    # 10.7 -> 7.6, TUM fr1_rpy 36.4 -> 25.8, 7-Scenes dev 29.3 -> 26.6), Sim3 ATE 0.47/1.40/0.61/0.67/0.71 ->
    # 0.62/1.12/0.54/0.67/0.70 cm, TUM 3.39 -> 1.89, 7-Scenes 3.16 -> 2.81 cm (bench/results/realtime_tail/).
    klt_keyframe_fb: bool = False
    # Where a frame's pose comes from first: "direct" (photometric alignment against the keyframe's reference,
    # then pose_refine) | "pnp" (the KLT-tracked landmarks by PnP from the motion model's prediction, judged by
    # the reference's photometric residual at that pose; the direct alignment only when that fails). "pnp" takes
    # a non-keyframe 20-30 % less time (bench/mono_variants.py, same process: rooms 0 / 2 13.8 / 13.3 -> 9.7-11.1 ms,
    # 7-Scenes dev 29.9-32.2 -> 24.3-26.0 ms) at the same Sim3 ATE over perturbed copies (better in 9 of 18 runs:
    # 7-Scenes dev median 2.98 -> 2.94 cm, rooms 1 / 3 1.19 -> 1.07 / 0.80 -> 0.94, TUM fr1_rpy 2.09 -> 2.29), and
    # its frame poses sit a little further from the GT relative to their keyframe (median 1.90 -> 1.92 mm, room 1
    # 2.93 -> 3.05 mm): "direct" offline, "pnp" in the tracker service at a camera's rate (services.tracker
    # --frame-pose; bench/results/frame_pose_pnp_2026-12-06/)
    frame_pose: str = "direct"
    pnp_first_gate_px: float = 8.0  # "pnp": first fit on the landmarks within this of the prediction (at 320 px)
    pnp_first_min_share: float = 0.5  # ... and the pose kept when this share of them fits within pnp_inlier_px
    # per-frame pose after direct alignment: "pnp" (reprojection of tracked landmarks) | "none"
    pose_refine: str = "pnp"
    # With pose_refine "pnp" the direct alignment only seeds the PnP (and gates its inliers at pnp_inlier_px), so
    # it stops once a step is below this (m / rad) instead of TrackerConfig.align.step_tol (1e-6): the direct
    # alignment 15-20 % faster (~1.5 ms a frame at 320x240). Alone (after ba_rel_tol): synthetic rooms 0-3 the
    # same Sim3 ATE to 0.01 mm; room 4, TUM fr1_rpy, 7-Scenes dev 0.80 -> 0.82, 1.57 -> 1.33, 2.68 -> 2.89 cm.
    direct_step_tol: float = 1e-4
    reinit_after: int = 3  # consecutive lost frames after which the current frame becomes a keyframe
    #                        with a constant-depth plane at the last median depth (reported as "reinit")
    pnp_min_points: int = 30
    pnp_recovery: bool = True  # a frame the direct alignment loses gets its pose from the landmarks (PnP + RANSAC)
    pnp_inlier_px: float = 2.0
    # With an anchor, its baseline sets the scale again at the first tracked frame with an anchor pose from
    # frame first + late_anchor_frames - 1 on (15: frame 14, the end of the mapper's init window, where the
    # map front end takes its scale): everything is scaled about the first camera centre then. The
    # bootstrap's baseline is a few frames long, too short to fix the scale (TUM fr1_rpy:
    # bench/results/mono_tuning.md). Given up (scale kept) after twice as many frames without one.
    # 0: the bootstrap's scale stays.
    late_anchor_frames: int = 15
    late_anchor_factor_max: float = 10.0  # a refresh changing the scale by more (or less than 1/this) is refused
    loop: LoopConfig = field(default_factory=LoopConfig)  # loop closure at keyframes (fmapping.tracking.loop)
    # Rolling shutter: readout time from the first to the last row as a fraction of the frame interval
    # (0: global shutter). Tracked pixels are unrolled (fmapping.tracking.rolling_shutter) before PnP,
    # triangulation and bundle adjustment, with each frame's rotation since the previous one. Off by
    # default: on TUM fr1_rpy, whose images prefer 0.85 (bench/tracking.py images_optimum), it improved the
    # rotation but not the SE3 error, and on global-shutter frames it costs accuracy
    # (bench/results/mono_tuning.md).
    rolling_shutter: float = 0.0

    def validate(self) -> None:
        if self.final_ba not in ("after_loops", "always", "never"):
            raise ValueError(f"mono.final_ba must be 'after_loops', 'always' or 'never', got {self.final_ba!r}")
        if self.final_ba_max_nfev < 1:
            raise ValueError(f"mono.final_ba_max_nfev must be >= 1, got {self.final_ba_max_nfev}")
        if self.frame_pose not in ("direct", "pnp"):
            raise ValueError(f"mono.frame_pose must be 'direct' or 'pnp', got {self.frame_pose!r}")
        if self.frame_pose == "pnp" and self.rolling_shutter:
            raise ValueError("mono.frame_pose 'pnp' needs a global shutter (mono.rolling_shutter 0): the tracks are "
                             "unrolled with the rotation the direct alignment measures")
        if not (self.pnp_first_gate_px > 0 and 0.0 <= self.pnp_first_min_share <= 1.0):
            raise ValueError(f"mono.pnp_first_gate_px must be > 0 and mono.pnp_first_min_share in [0, 1], got "
                             f"{self.pnp_first_gate_px} and {self.pnp_first_min_share}")
        if not (self.ba_anisotropic_noise >= 0 and self.ba_anisotropic_cap >= 1):
            raise ValueError(f"mono.ba_anisotropic_noise must be >= 0 and mono.ba_anisotropic_cap >= 1, got "
                             f"{self.ba_anisotropic_noise}, {self.ba_anisotropic_cap}")
        if not self.kf_obs_max_px >= 0 or not 0.0 <= self.kf_obs_max_share <= 1.0:
            raise ValueError(f"mono.kf_obs_max_px must be >= 0 and mono.kf_obs_max_share in [0, 1], got "
                             f"{self.kf_obs_max_px}, {self.kf_obs_max_share}")
        if self.loop_thread and not self.ba_thread:
            raise ValueError("mono.loop_thread needs mono.ba_thread (the loop's bundle adjustment goes to its worker)")
        if self.loop_ba_defer_frames < 0 or not 0.0 <= self.ba_defer_min_visible <= 1.0:
            raise ValueError(f"mono.loop_ba_defer_frames must be >= 0 and mono.ba_defer_min_visible in [0, 1], got "
                             f"{self.loop_ba_defer_frames} and {self.ba_defer_min_visible}")
        if not (np.isfinite(self.rolling_shutter) and 0.0 <= self.rolling_shutter <= 1.0):
            raise ValueError(f"mono.rolling_shutter is the readout time as a fraction of the frame interval, "
                             f"0 (global shutter) to 1, got {self.rolling_shutter}")
        self.loop.validate()
