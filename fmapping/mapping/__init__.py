"""The incremental neural-field mapper: :class:`Mapper` and its settings :class:`MapperConfig`
(modules: config, scene_box, window_schedule, optimisation, batch_render, state_io, mapper)."""
from fmapping.mapping.config import MapperConfig
from fmapping.mapping.mapper import Mapper
from fmapping.mapping.scene_box import aabb_from_depth, aabb_from_poses
from fmapping.mapping.window_schedule import WindowStats

__all__ = ["Mapper", "MapperConfig", "WindowStats", "aabb_from_depth", "aabb_from_poses"]
