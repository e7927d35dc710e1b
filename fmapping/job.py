"""What a ``fmapping map`` / ``fmapping slam`` run is asked to do, as one typed object: the command line
turns its arguments into a :class:`Job` (:meth:`Job.from_args`) and the library never sees argparse."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional


@dataclass(frozen=True)
class Job:
    data: str  # dataset folder, image folder, video, bag (fmapping.datasets.open_dataset)
    out: str  # output folder
    poses: str = "gt"  # map: gt | PATH.txt; slam: photometric | kiss-icp | gt | PATH.txt
    config: Optional[str] = None  # YAML overrides of the map / slam config
    camera: Optional[str] = None  # intrinsics fx,fy,cx,cy[,dist] or a calib file (default: the data's own)
    max_frames: Optional[int] = None
    data_fps: Optional[float] = None  # frame rate for the timestamps of an image folder / video
    topic: Optional[str] = None  # image topic of a ROS bag
    field: Optional[str] = None  # map / slam: field kind cp | vm | mlp | grid (default: the config's)
    use_depth: bool = False  # supervise with sensor depth (RGB-D mode) when the data has it
    bbox: Optional[tuple] = None  # ((xmin, ymin, zmin), (xmax, ymax, zmax)): the user's scene box
    device: Optional[str] = None  # cpu | cuda | auto (None: the config's)
    export: bool = True  # slam: write map.ply / mesh.ply
    quiet: bool = False  # no progress bars

    @classmethod
    def from_args(cls, args, **defaults) -> "Job":
        """The fields ``args`` (an argparse namespace) has; ``defaults`` for those it lacks."""
        kw = dict(defaults)
        for f in dataclasses.fields(cls):
            v = getattr(args, f.name, None)
            if v is not None:
                kw[f.name] = v
        if kw.get("bbox") is not None:
            kw["bbox"] = tuple(tuple(map(float, r)) for r in kw["bbox"])
        return cls(**kw)

    def mapper_config(self, cfg):
        """``cfg`` (a :class:`~fmapping.mapping.MapperConfig`) with what the job says of the mapper: the field
        kind, sensor depth, the user's box, the device (``auto``: the config's)."""
        if self.field:
            cfg = dataclasses.replace(cfg, field=dataclasses.replace(cfg.field, kind=self.field))
        if self.use_depth:
            cfg = dataclasses.replace(cfg, use_depth=True)
        if self.bbox is not None:
            cfg = dataclasses.replace(cfg, bbox=tuple(tuple(map(float, r)) for r in self.bbox))
        if self.device and self.device != "auto":
            cfg = dataclasses.replace(cfg, device=self.device)
        return cfg

    def source_options(self) -> dict:
        """The keyword arguments of :func:`fmapping.datasets.open_dataset` beyond camera and frame count."""
        return {"fps": self.data_fps, "topic": self.topic}
