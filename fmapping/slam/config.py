"""The config of ``fmapping slam`` (``slam:`` in its YAML) and how a :class:`~fmapping.job.Job` sets it."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from fmapping.config import load_config
from fmapping.job import Job
from fmapping.mapping import MapperConfig
from fmapping.tracking.direct_tracker import TrackerConfig
from fmapping.tracking.mapview import MapViewConfig
from fmapping.tracking.mono import MonoConfig
from fmapping.tracking.render_compare import RenderCompareConfig
from fmapping.tracking.sources import KissIcpConfig


@dataclass
class SlamConfig:
    mapper: MapperConfig = field(default_factory=MapperConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    map_view: MapViewConfig = field(default_factory=MapViewConfig)
    render_compare: RenderCompareConfig = field(default_factory=RenderCompareConfig)
    kiss_icp: KissIcpConfig = field(default_factory=KissIcpConfig)
    mono: MonoConfig = field(default_factory=MonoConfig)
    frontend: str = "mono"  # RGB-only front end: "mono" (two-view bootstrap + BA, sparse depth; map depth only with
    #                         mono.dense_extra) | "map" (mapper init from constant-depth guesses, rendered depth only)
    mapper_refines_init: bool = False  # let the mapper's init re-estimate the front end's init poses
    tracking: str = "direct"  # photometric tracking path: "direct" | "render_compare"
    init_depth: float = 2.0  # assumed depth of the constant-depth plane of the bootstrap (units if no anchor)
    scale_anchor: str = "auto"  # "auto" | "gt" | "depth" | "none"
    anchor_world_gt: bool = True  # put frame 0 at its GT pose when GT exists
    init_min_inlier_ratio: float = 0.6
    init_min_depth_fraction: float = 0.3  # fraction of reference pixels the map must render
    init_retries: int = 2
    init_retry_frames: int = 10
    refresh_every_window: bool = True  # re-render the reference depth after each mapping window
    feed_lost_frames: bool = False  # give the mapper frames whose tracking was lost (at the predicted pose)
    # After each keyframe bundle adjustment, give the mapper the poses of the frames it holds that the BA
    # moved by > 1 mm or 0.05 deg (mono front end). Synthetic rooms, 200 frames, completion ratio after Sim3,
    # seeds 1 / 2 / 3: 86.0 / 83.3 / 95.4 % without, 89.9 / 87.9 / 91.0 % handing on every pose at every
    # keyframe, 88.1 % (seed 2) / 96.0 % (seed 3) with the threshold.
    mapper_follows_ba: bool = True
    export: bool = True  # write map.ply / mesh.ply at the end (``--no-export`` turns it off)

    def validate(self) -> None:
        if self.frontend not in ("mono", "map"):
            raise ValueError(f"slam.frontend must be 'mono' or 'map', got {self.frontend!r}")
        if self.tracking not in ("direct", "render_compare"):
            raise ValueError(f"slam.tracking must be 'direct' or 'render_compare', got {self.tracking!r}")
        if self.scale_anchor not in ("auto", "gt", "depth", "none"):
            raise ValueError(f"slam.scale_anchor must be auto|gt|depth|none, got {self.scale_anchor!r}")
        if not self.init_depth > 0:
            raise ValueError(f"slam.init_depth must be > 0, got {self.init_depth}")
        self.mapper.validate()


def build_slam_config(job: Job) -> SlamConfig:
    """The config of a ``fmapping slam`` job: its YAML, then the job's depth, box, device, pose source."""
    cfg = load_config(SlamConfig(), job.config)
    m = job.mapper_config(cfg.mapper)
    poses = job.poses
    if poses not in ("photometric",) or m.use_depth or (cfg.frontend == "mono" and not cfg.mapper_refines_init):
        # external poses are trusted; with sensor depth the bootstrap is RGB-D odometry, already metric
        m = dataclasses.replace(m, optimize_init_poses=False)
    cfg = dataclasses.replace(cfg, mapper=m)
    if not job.export:  # --no-export
        cfg = dataclasses.replace(cfg, export=False)
    cfg.validate()
    return cfg
