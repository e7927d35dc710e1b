"""The config file of ``fmapping up`` and ``fmapping demo``: sections ``mapper:``, ``tracker:`` and
``launcher:`` (:class:`LauncherOptions`), their defaults (``fmapping config dump up``) and the split
into one file per service. The processes themselves are started by :mod:`services.launcher`."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

from fmapping.config import read_yaml_mapping

SECTIONS = ("mapper", "tracker", "launcher")


@dataclass
class LauncherOptions:
    timeout: Optional[float] = None  # seconds for the whole run (None = no limit)
    view: bool = True
    window: int = 4
    frames: int = 200
    size: tuple = (320, 240)
    seed: int = 0
    threads: int = 0
    tracker_frontend: str = "mono"  # --poses tracker: "mono" (RGB-only front end, as fmapping slam) | "map"
    start_timeout: float = 120.0
    grace: float = 15.0  # seconds between SIGINT and SIGKILL on shutdown
    # the mapper's frame inbox (services.mapper --inbox-frames / --inbox-mb): frames and MiB it holds at most while
    # it is behind the camera, non-keyframes evicted first; None: the service's default (512 frames, 384 MiB)
    mapper_inbox_frames: Optional[int] = None
    mapper_inbox_mb: Optional[float] = None
    extra: dict = field(default_factory=dict)


def mapper_defaults():
    from fmapping.mapping import MapperConfig

    return MapperConfig()


def tracker_defaults():
    from fmapping.tracking.direct_tracker import TrackerConfig

    return TrackerConfig()


@dataclass
class UpConfig:
    """Every key an ``fmapping up`` config may set, by section (``fmapping config dump up`` prints
    the defaults; :func:`split_config` reads such a file). The sections are built on first use so
    that importing the launcher does not import torch."""
    mapper: Any = field(default_factory=mapper_defaults)  # fmapping.mapping.MapperConfig
    tracker: Any = field(default_factory=tracker_defaults)  # fmapping.tracking.direct_tracker.TrackerConfig
    launcher: LauncherOptions = field(default_factory=LauncherOptions)


def up_config_dict(cfg: UpConfig) -> dict:
    """``cfg`` as the sections of an ``up`` config file (``launcher.extra`` is internal, not a key)."""
    from fmapping.config import to_dict

    d = to_dict(cfg)
    d["launcher"].pop("extra", None)
    return d


def split_config(path: Optional[str], out: Path) -> tuple[Optional[Path], Optional[Path], LauncherOptions]:
    """Split an ``up`` config into mapper / tracker YAML files under OUT/config and launcher options."""
    opts = LauncherOptions()
    if not path:
        return None, None, opts
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"config file not found: {p}")
    data = read_yaml_mapping(p)
    if not data or not set(data) <= set(SECTIONS):
        data = {"mapper": data}  # plain mapper overrides
    cdir = out / "config"
    cdir.mkdir(parents=True, exist_ok=True)
    files = {}
    for name in ("mapper", "tracker"):
        if data.get(name):
            if not isinstance(data[name], dict):
                raise ValueError(f"{p}: section {name!r} must be a mapping")
            files[name] = cdir / f"{name}.yaml"
            files[name].write_text(yaml.safe_dump(data[name], sort_keys=False))
    launch = data.get("launcher") or {}
    if not isinstance(launch, dict):
        raise ValueError(f"{p}: section 'launcher' must be a mapping")
    valid = {f for f in LauncherOptions.__dataclass_fields__ if f != "extra"}
    unknown = set(launch) - valid
    if unknown:
        raise ValueError(f"{p}: unknown launcher keys {sorted(unknown)} (valid: {', '.join(sorted(valid))})")
    for k, v in launch.items():
        setattr(opts, k, tuple(v) if k == "size" else v)
    return files.get("mapper"), files.get("tracker"), opts
