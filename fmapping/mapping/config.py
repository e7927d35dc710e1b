"""The mapper's settings (:class:`MapperConfig`, YAML-overridable) and their checks."""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from typing import Optional

from fmapping.field import FieldConfig
from fmapping.sparse_points import SparsePointsConfig


@dataclass
class MapperConfig:
    """Mapper settings (YAML-overridable through :func:`fmapping.config.load_config`).

    Defaults follow the paper where it is specific (15 init frames, rounds 32 / 64 / 64 / 64
    with sliding windows 3 / 4 / 5, window of 20 frames, 20 iterations every 5 frames, Adam
    lr 0.02 / 0.001, decoder frozen after init) and were measured on synthetic rooms where it
    is not (GT poses, RGB only, 200 frames at 320x240, bench/mapping.py): 1024 rays x (32
    coarse + 16 importance) samples, warping weight 2 over 8 random window views with the
    mean over the valid views (``warp_keep`` 1; keeping only the best half favours the
    small-baseline views, which barely see depth errors - on the 15 init frames both gave the
    same depth error), per-sample photo-consistency weight 4. In the init rounds
    the "samples per ray" are the coarse stratified samples plus ``samples - n_coarse``
    sliding-window samples.
    """

    field: FieldConfig = dc_field(default_factory=FieldConfig)
    # --- init stage
    init_frames: int = 15
    init_rounds: tuple = ((0, 32), (3, 64), (4, 64), (5, 64))  # (sliding window size (0 = stratified), samples per ray)
    # 4 x 20 iterations, the grid's lr going geometrically from init_lr_grid to lr_grid, from a foggy start
    # (field.init_opacity): with 512 rays 4.0-5.8 s on 2 cores against 21-29 s for the 4 x 75 x 1024 rays at lr 0.02
    # from a clear start before 2026-12-04, with a lower depth error after it on 3 of 4 synthetic rooms
    # (bench/init_speed.py). The final maps (GT poses) are about 1 point of completion ratio lower; the old init: 75,
    # 1024, 0.02 and field.init_opacity 0 (bench/results/init_fog/). 192 rays per iteration instead of 512
    # (bench/results/init_rays_2026-12-07/): the init's CPU 5.2-6.4 -> 2.8-3.7 s on 1 thread, its depth error within
    # the spread of the mapper's seeds, final maps with GT poses as good (7-Scenes dev 3 seeds 51.5 -> 53.5 %). In
    # `fmapping up` at 30 fps the init then ends before a 200-frame stream does and the mapper thins non-keyframes
    # to catch up; with owed_iters_factor 2 that no longer costs the final map (bench/results/closing_owed_2026-12-07/)
    init_iters_per_round: int = 20
    init_rays_per_iter: int = 192
    init_lr_grid: float = 0.05
    optimize_init_poses: bool = True  # frame 0 fixed; se(3) corrections for the others
    freeze_decoder_after_init: bool = True
    # --- on-the-fly stage
    window_size: int = 20
    new_frames_per_window: int = 5
    iters_per_window: int = 20
    n_global_keyframes: int = 10
    keyframe_every: int = 5
    # --- rays and samples
    rays_per_iter: int = 1024
    n_coarse: int = 32  # stratified samples (evaluated without gradient, density only)
    n_fine: int = 16  # importance / sliding-window samples added to them
    sampler: str = "pdf"  # on-the-fly fine samples: "pdf" | "sliding_window" | "stratified"
    sw_window: int = 5
    color_threshold: float = 0.01  # colour evaluated only where weight > this x the ray's max weight
    active_threshold: float = 1e-3  # coarse samples re-evaluated with gradient only above this x max opacity (0: all)
    # --- optimiser
    lr_grid: float = 0.02
    lr_decoder: float = 0.001
    lr_pose: float = 0.001
    # coarse-to-fine steps on the factor lines: each line also moves through a coarse copy of this many nodes per axis
    # (linearly interpolated onto its own nodes; 0: off), so the low frequencies settle first (fmapping.mapping.coarse).
    # fmapping map --poses gt, RGB only, completion ratio, off -> 16 (bench/results/coarse_lines_2026-12-07/):
    # wide synthetic seeds 0-4 67.9/67.3/77.0/63.8/64.0 -> 73.6/77.1/72.9/78.8/78.9 % (accuracy mean 10.8 -> 7.5 cm),
    # default rooms 96.1/95.3 -> 97.9/96.9 %, TUM fr1_rpy 17.4 -> 17.7 dB, but 7-Scenes dev 52.3/53.3/48.8 ->
    # 43.1/51.6/46.7 % (mapper seeds 0-2) and lego 21.9 -> 21.6 dB: off by default, the real kitchen is worse with it
    coarse_nodes: int = 0
    coarse_lr_scale: float = 1.0
    coarse_lines: str = "both"  # which factor lines get coarse steps: "both" | "density" | "appearance"
    # after the init, every update (window, closing) also refines the poses of its frames (frame 0 fixed): se(3)
    # corrections on the camera side, folded into the poses after each update. For external poses with per-frame
    # noise (tests: 0.93 -> 0.38 deg). Off by default: it does not fix a trajectory's slow drift. 7-Scenes dev,
    # fmapping map, completion ratio / accuracy: GT poses 51.4 % / 12.5 cm -> 53.4 % / 13.6 cm; the poses of a
    # fmapping slam run (their orientation drifts +-2 deg from the GT's over the clip) 13.1 % -> 12.9 % (lr 0.002:
    # 11.9 %), their orientation error unchanged (1.27 -> 1.26 deg)
    refine_poses: bool = False
    lr_pose_refine: float = 0.0005
    # --- losses
    photo_loss: str = "l2"
    huber_delta: float = 0.1
    warp_weight: float = 2.0
    warp_radius: int = 1
    warp_dilations: tuple = (1.0,)
    warp_keep: float = 1.0
    warp_views: int = 8  # target views per iteration (random subset of the window; 0 = all)
    # depth for warping: "expected" (sum w t / acc) | "far" (unreached mass at the ray's far bound)
    warp_depth: str = "expected"
    pc_weight: float = 4.0  # per-sample photo-consistency loss sum_i w_i (cost_i - mean cost) (plane-sweep cost volume)
    pc_rays: int = 512  # rays (of rays_per_iter) that get the per-sample cost
    pc_views: int = 4  # other window views the per-sample cost is computed in
    pc_radius: int = 0  # patch radius of the per-sample cost
    # share of a sample's views (lowest costs) its photo-consistency cost averages (1: all). 0.5 with the 45-deg limit
    # below: 7-Scenes dev 50.1 % / 11.90 cm against 51.9 % / 11.33 cm with 1 (bench/results/probes_2026-12-05c/)
    pc_keep: float = 1.0
    # the warping and photo-consistency losses compare a ray's point only with the views that see it within this
    # angle of the ray (0: every view), as multi-view stereo picks its views: from far around, the point is often
    # hidden or shows another side. fmapping map, GT poses, RGB only (bench/results/probes_2026-12-05c/): NeRF lego
    # novel-view PSNR 20.25 dB with every view, 21.64 / 21.75 / 21.91 / 21.11 dB at 20 / 30 / 45 / 60 deg (mapper seed
    # 1: 20.48 -> 22.01 dB at 45); 7-Scenes
    # dev 50.4 % (5 cm) with every view, 51.5 / 51.9 / 48.3 % at 30 / 45 / 60 deg (no trend: a change this small
    # moves the map by a few points either way); default rooms s0, s1 96.5 / 95.3 -> 96.6 / 95.8 %; wide rooms s0-4
    # mean 68.8 -> 68.3 % (45 deg)
    consistency_max_angle: float = 45.0
    # Gaussian sigma (px) of the images the warping and photo-consistency losses compare (0: the raw images): noise,
    # JPEG and each frame's own motion blur disagree between views at the finest scale. fmapping map --poses gt,
    # RGB only, wide synthetic seeds 0-4, completion ratio: 0 -> 1.0 px 69.2/66.0/72.5/63.9/63.7 ->
    # 75.8/74.2/80.0/69.1/64.8 % (0.6 px: 72.9/72.5/73.6/68.7/58.0); the default room 98.1 -> 96.8 % (0.6 px: 97.6);
    # 7-Scenes dev 50.1 -> 51.4 %, accuracy 13.7 -> 12.5 cm
    consistency_blur: float = 1.0
    tv_weight: float = 0.0
    l1_weight: float = 0.0
    distortion_weight: float = 0.0  # mip-NeRF 360 distortion loss on the colour rays (compact termination, no fog)
    use_depth: bool = False
    depth_weight: float = 0.5
    # --- sparse points: KLT tracks triangulated with the given poses (fmapping.sparse_points)
    sparse: SparsePointsConfig = dc_field(default_factory=SparsePointsConfig)
    # weight of the sparse depth term (0: off), which pulls rays onto the triangulated points. Off by default:
    # even weighted by their expected error the points hurt where tracks drift (wide synthetic seeds 0-4,
    # GT poses: completion ratio 56.8/55.1/65.2/59.9/54.7 % with the term at 1.0, 67.3/60.4/74.8/64.7/61.8 %
    # without; the default room 97.5 % either way; 7-Scenes dev 52.8 vs 52.2 %)
    sparse_depth_weight: float = 0.0
    sparse_rays: int = 256  # rays per iteration through triangulated points
    sparse_cap: float = 0.5  # relative depth error at which a point's pull has halved (losses.sparse_depth_loss)
    sparse_fill_weight: float = 0.0  # weight (x the points') of depth filled in between a frame's points (0: off)
    # --- per-frame affine colour (auto exposure / white balance): rendered = (1 + a) * colour + b per channel
    exposure: bool = True
    lr_exposure: float = 0.001
    exposure_reg: float = 0.01  # pull of (a, b) towards 0 (no change)
    # where a frame's (a, b) start when it enters its first window update (fmapping.mapping.exposure): "fit" (the
    # previous frame's, gains re-fitted to its colours) | "none" (no change, as before 2026-12-04)
    exposure_start: str = "fit"
    # --- scene bounds
    near: float = 0.1
    far: float = 6.0
    bbox: Optional[tuple] = None  # ((xmin, ymin, zmin), (xmax, ymax, zmax)); given: fixed, no growth
    bbox_margin: float = 0.1
    bounds: str = "points"  # box without `bbox`: "points" (triangulated, grows with them) | "frusta" (near..far)
    bounds_grow: float = 0.05  # re-fit the box when the points leave it by more than this share of its extent
    # --- kept keyframe images beyond the local window (fmapping.mapping.image_store): "jpeg" (quality 95, 4:4:4) |
    # "png" (lossless). JPEG takes 22 % of PNG's bytes on 7-Scenes frames (31 % on synthetic ones) at 48 dB (43 dB);
    # fmapping map, GT poses, completion ratio / accuracy: 7-Scenes dev 51.4 % / 12.5 cm (png) against 50.8 % /
    # 13.3 cm (jpeg), wide synthetic seed 0 75.8 % / 9.6 cm against 75.2 % / 9.2 cm
    keyframe_codec: str = "jpeg"
    keyframe_jpeg_quality: int = 95
    # --- closing refinement
    final_global_iters: int = 300
    # a caller that fell behind the stream (services.mapper) owes the window iterations it skipped; the closing
    # runs this many global iterations per owed one. A global iteration spreads its rays over every keyframe,
    # a window iteration over the 20 frames around the new ones: offline, GT poses, 200 frames of a synthetic
    # room with 42 non-keyframes thinned, 1x the owed iterations 93.1 %, 2x 96.0 %, 3x 96.4 %, every frame
    # kept and 0 owed 95.5 % (bench/results/init_rays_2026-12-07, thin.log)
    owed_iters_factor: float = 2.0
    seed: int = 0
    device: str = "auto"

    def validate(self) -> None:
        if not 0 <= self.owed_iters_factor <= 100:
            raise ValueError(f"MapperConfig.owed_iters_factor must be in 0..100, got {self.owed_iters_factor}")
        if self.init_frames < 1:
            raise ValueError(f"MapperConfig.init_frames must be >= 1, got {self.init_frames}")
        if self.window_size < 2 or not 0 <= self.n_global_keyframes < self.window_size:
            raise ValueError(f"MapperConfig: need window_size >= 2 and 0 <= n_global_keyframes < window_size, "
                             f"got {self.window_size}, {self.n_global_keyframes}")
        if self.new_frames_per_window < 1 or self.new_frames_per_window > self.window_size - self.n_global_keyframes:
            raise ValueError("MapperConfig.new_frames_per_window must be in 1..window_size - n_global_keyframes")
        if self.sampler not in ("pdf", "sliding_window", "stratified"):
            raise ValueError(f"MapperConfig.sampler must be pdf, sliding_window or stratified, got {self.sampler!r}")
        if self.bounds not in ("points", "frusta"):
            raise ValueError(f"MapperConfig.bounds must be 'points' or 'frusta', got {self.bounds!r}")
        if self.sparse_cap <= 0:
            raise ValueError(f"MapperConfig.sparse_cap must be > 0, got {self.sparse_cap}")
        if min(self.sparse_depth_weight, self.sparse_rays, self.sparse_fill_weight, self.lr_exposure, self.exposure_reg,
               self.distortion_weight, self.lr_pose_refine) < 0:
            raise ValueError("MapperConfig: sparse_depth_weight, sparse_rays, sparse_fill_weight, lr_exposure, "
                             "exposure_reg, distortion_weight and lr_pose_refine must be >= 0")
        self.sparse.validate()
        if self.keyframe_codec not in ("png", "jpeg") or not 1 <= self.keyframe_jpeg_quality <= 100:
            raise ValueError(f"MapperConfig: keyframe_codec must be png or jpeg and keyframe_jpeg_quality in 1..100, "
                             f"got {self.keyframe_codec!r}, {self.keyframe_jpeg_quality}")
        if self.exposure_start not in ("fit", "none"):
            raise ValueError(f"MapperConfig.exposure_start must be fit or none, got {self.exposure_start!r}")
        if not 0 < self.pc_keep <= 1 or not 0 <= self.consistency_max_angle <= 180:
            raise ValueError(f"MapperConfig: pc_keep must be in (0, 1] and consistency_max_angle in [0, 180] degrees, "
                             f"got {self.pc_keep}, {self.consistency_max_angle}")
        if not self.consistency_blur >= 0:
            raise ValueError(f"MapperConfig.consistency_blur must be >= 0, got {self.consistency_blur}")
        if self.warp_depth not in ("far", "expected"):
            raise ValueError(f"MapperConfig.warp_depth must be 'far' or 'expected', got {self.warp_depth!r}")
        if self.coarse_nodes != 0 and not 2 <= self.coarse_nodes <= self.field.resolution:
            raise ValueError(f"MapperConfig.coarse_nodes must be 0 (off) or 2..field.resolution "
                             f"({self.field.resolution}), got {self.coarse_nodes}")
        if self.coarse_lines not in ("both", "density", "appearance"):
            raise ValueError(f"MapperConfig.coarse_lines must be 'both', 'density' or 'appearance', got "
                             f"{self.coarse_lines!r}")
        if not self.coarse_lr_scale > 0:
            raise ValueError(f"MapperConfig.coarse_lr_scale must be > 0, got {self.coarse_lr_scale}")
        if not 0 < self.near < self.far:
            raise ValueError(f"MapperConfig: need 0 < near < far, got near={self.near}, far={self.far}")
        if self.rays_per_iter < 1 or self.init_rays_per_iter < 1 or self.n_coarse < 2:
            raise ValueError("MapperConfig: rays_per_iter and init_rays_per_iter must be >= 1 and n_coarse >= 2")
        if not self.init_lr_grid > 0 or self.init_iters_per_round < 1:
            raise ValueError(f"MapperConfig: need init_lr_grid > 0 and init_iters_per_round >= 1, got "
                             f"{self.init_lr_grid}, {self.init_iters_per_round}")
        for r in self.init_rounds:
            if len(r) != 2 or r[0] < 0 or r[1] < 2:
                raise ValueError(f"MapperConfig.init_rounds entries are (window >= 0, samples >= 2), got {r!r}")
