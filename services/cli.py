"""The ``fmapping`` console entry point: the library's sub-commands (:mod:`fmapping.cli`) plus ``up``
and ``demo``, which start the service processes (:mod:`services.launcher`).

    fmapping up    [--data DIR|VIDEO|BAG|camera:N] [--camera CAM] [--data-fps F] [--topic T] [--poses tracker|gt]
                   [--out OUT] [--view auto|live|save]
    fmapping demo  [--out OUT] [--poses tracker|gt]

``python -m services.cli ...`` is the same command from a source tree.
"""
from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence

from fmapping import cli as library
from fmapping.cli import BBOX_HELP, CAMERA_HELP, DATA_HELP, add_source_args, parse_bbox


def add_process_commands(sub) -> None:
    """The sub-commands ``up`` and ``demo`` (added to :func:`fmapping.cli.build_parser`)."""
    p = sub.add_parser("up", help="run the multi-process system (io, tracker, mapper over zenoh)")
    p.add_argument("--data", default=None,
                   help=DATA_HELP + ", or camera:N for the live webcam N (needs --camera) (default: a generated "
                        "synthetic scene)")
    p.add_argument("--camera", default=None, help=CAMERA_HELP)
    p.add_argument("--poses", default="tracker", choices=["tracker", "gt", "external"],
                   help="pose source of the mapper: the RGB-only tracker, the dataset's GT, or an external "
                        "producer")
    p.add_argument("--out", default="out/up", help="output folder: map.ply, mesh.ply, traj.txt, stats.json, logs/")
    p.add_argument("--fps", type=float, default=0.0,
                   help="playback rate in frames per second (0 = as fast as consumers keep up; the frames' "
                        "timestamps of an image folder or video: --data-fps)")
    add_source_args(p, ("--data-fps",))
    p.add_argument("--config", default=None, help="YAML with mapper / tracker / launcher sections "
                                                  "(all keys: fmapping config dump up; default: none)")
    p.add_argument("--bbox", type=parse_bbox, default=None, help=BBOX_HELP)
    p.add_argument("--view", default="auto", choices=["auto", "live", "save"],
                   help="live: serve rerun's web viewer (URL printed) and still save OUT/run.rrd; save: only "
                        "OUT/run.rrd; auto: live when there is a display and a terminal, else save (default: auto)")
    p.add_argument("--view-port", type=int, default=9090, help="web viewer port of --view live (default: 9090)")
    p.add_argument("--grpc-port", type=int, default=9876, help="rerun gRPC port of --view live (default: 9876)")
    p.add_argument("--resume", default=None, metavar="OUT",
                   help="continue the run of fmapping up in OUT that was killed: the same arguments, the mapper "
                        "from its checkpoint, play from the first frame it had not mapped, the tracker "
                        "re-localised against its last keyframe, record adding to its files")
    p.add_argument("--insecure", action="store_true",
                   help="local debugging only: no per-run credentials and no access control, the services form "
                        "an open zenoh peer mesh on loopback that any local process can join (default: secure, "
                        "see docs/security.md)")

    p = sub.add_parser("demo", help="the multi-process system on the embedded synthetic default, with metrics")
    p.add_argument("--out", default="out/demo", help="output folder (the scene goes to OUT/scene)")
    p.add_argument("--frames", type=int, default=200, help="frames of the generated scene")
    p.add_argument("--seed", type=int, default=0, help="random seed of the generated scene")
    p.add_argument("--poses", default="tracker", choices=["tracker", "gt"],
                   help="tracker: RGB-only tracking (default); gt: map with the ground-truth poses")
    p.add_argument("--config", default=None, help="fmapping up config (mapper / tracker / launcher sections)")


def build_parser() -> argparse.ArgumentParser:
    return library.build_parser(more=(add_process_commands,))


def cmd_up(a) -> int:
    from services.launcher.up import run_up

    return run_up(a)


def cmd_demo(a) -> int:
    from services.launcher.demo import run_demo

    return run_demo(a)


COMMANDS = {**library.COMMANDS, "up": cmd_up, "demo": cmd_demo}


def main(argv: Optional[Sequence[str]] = None) -> int:
    return library.main(argv, build_parser(), COMMANDS)


if __name__ == "__main__":
    sys.exit(main())
