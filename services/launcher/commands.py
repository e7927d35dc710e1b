"""The command lines ``fmapping up`` starts the services with. Each is written by the service's own
argument parser (:func:`parser_of`, :func:`services.process.command_line`): the launcher names option
destinations and values, never flags, so a service's command line has one home, its ``build_parser``."""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Callable, Optional

from fmapping.cli import source_options
from services.process import command_line

# Frames play keeps in flight with the mono tracker: the mapper can take no frame before the
# tracker's bootstrap answers (it held 7-14 frames on the synthetic rooms); a smaller window
# stalls playback until the mapper's pose timeout. Both inboxes hold more (mapper 32, tracker 64).
MONO_BOOTSTRAP_WINDOW = 20
EXTERNAL_SOURCE = "external"  # pose source and status name of an external producer (poses/external, status/external)


def _parser_builders() -> dict[str, Callable]:
    from services import router
    from services.io import play, record, view
    from services.mapper.__main__ import build_parser as mapper_parser
    from services.tracker.__main__ import build_parser as tracker_parser

    return {"services.router": router.build_parser, "services.mapper": mapper_parser,
            "services.tracker": tracker_parser, "services.io play": play.build_parser,
            "services.io record": record.build_parser, "services.io view": view.build_parser}


def parser_of(service: str):
    """The argument parser of ``python -m <service>`` (``services.mapper``, ``services.io play``, ...)."""
    builders = _parser_builders()
    if service not in builders:
        raise ValueError(f"no service {service!r} (one of {', '.join(builders)})")
    return builders[service]()


def service_command(service: str, **values: Any) -> list[str]:
    """``python -m <service>`` with the options ``values`` (destination -> value, in this order; None
    left out), written by the service's own parser (:func:`services.process.command_line`)."""
    return [sys.executable, "-m", *service.split()] + command_line(parser_of(service), **values)


def tracker_state(out: Path) -> Path:
    """Where the mono tracker keeps its current keyframe for a restart (``services.tracker --state``)."""
    return out / "tracker" / "state.npz"


def resend_to(poses: str, live: bool) -> Optional[str]:
    """``io play --resend-to``: the consumers that get the frames they never handled again after a
    restart (a resumed mapper from its checkpoint's frame on, a restarted tracker from its last
    acknowledgement on); a live camera cannot go back (None)."""
    if live:
        return None
    return "mapper,tracker" if poses == "tracker" else "mapper"


def play_source(data, args) -> dict:
    """``io play``'s options of the source ``fmapping up`` plays: the data, ``--camera`` and the
    source options (:func:`fmapping.cli.add_source_args`) as given to ``up`` (None: not given)."""
    src = source_options(args)
    return {"data": str(data), "camera": getattr(args, "camera", None), "data_fps": src["fps"], "topic": src["topic"]}


def play_sends_depth(poses: str, mapper_uses_depth: bool) -> bool:
    """Does ``io play`` send the dataset's depth with the frames? Only when a service of the run may use it:
    the mapper with ``use_depth``, or an external pose producer (a geometric one, e.g. kiss-icp, reads the
    frames' depth). An RGB-only run gets colour alone: no ground-truth depth travels where nothing may use it,
    and a frame is 230 KB at 320x240 instead of 537 KB for every subscriber to copy and decode (the
    tracker's inbox holds up to 64 of them when it falls behind)."""
    return bool(mapper_uses_depth) or poses == "external"


def play_wait_for(poses: str, view: bool = True) -> list[str]:
    """The services ``io play`` waits for before the first frame. With ``--poses external`` that
    includes the producer, which reports its status as its pose source (``status/external``, see
    ``examples/publish_poses.py``)."""
    names = ["mapper", "record"] + (["view"] if view else [])
    if poses == "tracker":
        names.append("tracker")
    elif poses == "external":
        names.append(EXTERNAL_SOURCE)
    return names


def view_mode(requested: Optional[str]) -> str:
    """``--view``: live (serve rerun's web viewer and save OUT/run.rrd) or save (only the file);
    auto (the CLI's default) is live when someone can look: a display and a terminal. None (a
    caller without the option, e.g. ``fmapping demo``) is save."""
    if requested in ("live", "save"):
        return requested
    if requested is None:
        return "save"
    if requested != "auto":
        raise ValueError(f"--view must be auto, live or save, got {requested!r}")
    display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    return "live" if display and sys.stdout.isatty() else "save"


def view_argv(out: Path, mode: str, args, uses_depth: bool) -> list[str]:
    """The ``services.io view`` options of ``fmapping up``: always OUT/run.rrd, plus the live
    viewer on the fixed ports of --view-port / --grpc-port; depth images only when the mapper
    uses depth (an RGB-only run must not show the dataset's depth); the final map and mesh."""
    live = mode == "live"
    return command_line(parser_of("services.io view"), save=str(out / "run.rrd"), final_outputs=str(out), serve=live,
                        web_port=(getattr(args, "view_port", None) or 9090) if live else None,
                        grpc_port=(getattr(args, "grpc_port", None) or 9876) if live else None,
                        depth_every=5 if uses_depth else None)


def live_url(args) -> str:
    grpc = getattr(args, "grpc_port", None) or 9876
    return f"http://localhost:{getattr(args, 'view_port', None) or 9090}/?url=rerun+http://localhost:{grpc}/proxy"
