"""The ``fmapping`` command line of the library. Each sub-command is a thin call into the library;
``up`` and ``demo``, which start the service processes, are added by :mod:`services.cli`, the
``fmapping`` console entry point (``python -m fmapping.cli`` has the library's sub-commands only).

    fmapping synth --out DIR [--seed S] [--frames N] [--size WxH]
    fmapping info  --data DIR [--camera fx,fy,cx,cy]
    fmapping map   --data DIR --poses gt|PATH.txt --out OUT [--config cfg.yaml] [--field cp|vm|mlp|grid] [--use-depth]
    fmapping slam  --data DIR --out OUT [--poses photometric|kiss-icp|gt|PATH.txt] [--config cfg.yaml] [--field ...]
                   [--no-export]
    fmapping eval recon --pred P.ply --gt G.ply
    fmapping eval traj  --est E.txt --gt G.txt [--align sim3|se3|none]
    fmapping up    [--data DIR|VIDEO|BAG|camera:N] [--camera CAM] [--data-fps F] [--topic T] [--poses tracker|gt]
                   [--out OUT] [--view auto|live|save]
    fmapping demo  [--out OUT] [--poses tracker|gt]
    fmapping config dump [map|slam|up]
    fmapping --version
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Callable, Optional, Sequence

from fmapping.runtime import preload_optimiser, retain_freed_memory


DATA_HELP = ("a dataset folder (TUM, Replica, 7-Scenes, NeRF transforms.json, fmapping synth), a plain image "
             "folder (sorted by name), a video file, EuRoC MAV (mav0 layout), a ScanNet export, a rosbag2 / "
             "MCAP / ROS1 bag (needs the [ros] extra)")
CAMERA_HELP = ("intrinsics fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] or a calib.txt / camera.yaml path (default: the data's "
               "own, e.g. a calib.txt beside the images; a source without any is refused, never guessed)")


def _add_data_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True,
                   help=DATA_HELP + "; camera:N (a live webcam) only with fmapping up / io play")
    p.add_argument("--camera", default=None, help=CAMERA_HELP)
    p.add_argument("--max-frames", type=int, default=None, help="use only the first N frames (default: all)")
    add_source_args(p)


def add_source_args(p: argparse.ArgumentParser, fps_flags: Sequence[str] = ("--fps", "--data-fps")) -> None:
    """The options of how a source is read, shared by every command that opens one (``info``, ``map``,
    ``slam``, ``up``, ``python -m services.io play``); :func:`source_options` hands them to
    :func:`fmapping.datasets.open_dataset`. ``up`` and ``io play`` take the frame rate as ``--data-fps``
    only: their ``--fps`` is the playback rate."""
    p.add_argument(*fps_flags, dest="data_fps", type=float, default=None,
                   help="frame rate for the timestamps of an image folder (default 30, or the fps of its "
                        "camera.yaml) or a video (default: the file's own)")
    p.add_argument("--topic", default=None,
                   help="image topic of a ROS bag (default: the Image / CompressedImage topic with the most "
                        "messages, depth topics aside)")


def source_options(args) -> dict:
    """The keyword arguments of :func:`fmapping.datasets.open_dataset` that :func:`add_source_args` defines."""
    return {"fps": getattr(args, "data_fps", None), "topic": getattr(args, "topic", None)}


def parse_bbox(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or not all(lo < hi for lo, hi in zip(v[:3], v[3:])):
        raise argparse.ArgumentTypeError(f"--bbox must be xmin,ymin,zmin,xmax,ymax,zmax with min < max, got {text!r}")
    return tuple(v[:3]), tuple(v[3:])


BBOX_HELP = ("scene box xmin,ymin,zmin,xmax,ymax,zmax in metres (world frame of the poses); default: "
             "the mapper bounds the scene from points it triangulates, and grows the box as they spread")
FIELD_HELP = ("field kind (default: the config's field.kind, cp, the paper's 0.02 M parameters); vm (0.6 M) mapped "
              "real scenes better in bench/results/vm_and_box_2026-12-05/")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH, e.g. 320x240, got {text!r}") from None


def build_parser(more: Sequence[Callable[[argparse._SubParsersAction], None]] = ()
                 ) -> argparse.ArgumentParser:
    """The parser of the library's sub-commands; each function of ``more`` adds its own sub-commands
    (after ``eval``, before ``config``): :mod:`services.cli` adds ``up`` and ``demo``, which start processes."""
    ap = argparse.ArgumentParser(prog="fmapping", description="Factorized neural field mapping for dense RGB SLAM.")
    ap.add_argument("--version", action=_Version, help="print the version and exit")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("synth", help="generate a synthetic indoor scene in TUM layout with GT mesh and clouds")
    p.add_argument("--out", required=True, help="folder to write the scene to")
    p.add_argument("--seed", type=int, default=0, help="random seed of the room layout and the camera path")
    p.add_argument("--frames", type=int, default=200, help="number of frames")
    p.add_argument("--size", type=_size, default=(320, 240), help="image size WxH (default: 320x240)")
    p.add_argument("--variety", default="default", choices=["default", "wide"],
                   help="default: the standard close-up, strongly textured room; wide: the seed also draws "
                        "texture scale/contrast, low-texture and striped surfaces, larger rooms, thin structures, "
                        "and exposure/noise/blur/JPEG on the colour frames (default: %(default)s)")

    p = sub.add_parser("info", help="describe a dataset: format, frames, intrinsics, depth scale, GT")
    _add_data_args(p)

    p = sub.add_parser("map", help="build a map from images with given poses")
    _add_data_args(p)
    p.add_argument("--poses", default="gt", help="'gt' or a TUM trajectory file")
    p.add_argument("--out", required=True, help="output folder: map.ply, mesh.ply, traj.txt, stats.json")
    p.add_argument("--config", default=None,
                   help="YAML overrides of the mapper config (all keys: fmapping config dump map; default: none)")
    p.add_argument("--field", default=None, choices=["cp", "vm", "mlp", "grid"], help=FIELD_HELP)
    p.add_argument("--use-depth", action="store_true", help="supervise with depth when the dataset has it")
    p.add_argument("--device", default="auto", help="torch device: auto (CUDA when present, else CPU), cpu, cuda")
    p.add_argument("--bbox", type=parse_bbox, default=None, help=BBOX_HELP)

    p = sub.add_parser("slam", help="track and map from RGB (full SLAM loop)")
    _add_data_args(p)
    p.add_argument("--out", required=True, help="output folder: traj.txt, map.ply, mesh.ply, stats.json")
    p.add_argument("--poses", default="photometric", help="photometric | kiss-icp | gt | PATH.txt")
    p.add_argument("--config", default=None,
                   help="YAML overrides of the SLAM config (all keys: fmapping config dump slam; default: none)")
    p.add_argument("--field", default=None, choices=["cp", "vm", "mlp", "grid"], help=FIELD_HELP)
    p.add_argument("--use-depth", action="store_true", help="use depth when the dataset has it")
    p.add_argument("--device", default="auto", help="torch device: auto (CUDA when present, else CPU), cpu, cuda")
    p.add_argument("--bbox", type=parse_bbox, default=None, help=BBOX_HELP)
    p.add_argument("--no-export", dest="export", action="store_false",
                   help="skip map.ply / mesh.ply at the end (traj.txt and stats.json are still written)")

    p = sub.add_parser("eval", help="evaluate reconstructions and trajectories")
    esub = p.add_subparsers(dest="what", required=True)
    e = esub.add_parser("recon", help="accuracy / completion / completion ratio (NICE-SLAM protocol)")
    e.add_argument("--pred", required=True, help="reconstruction: PLY point cloud or mesh")
    e.add_argument("--gt", required=True, help="ground truth: PLY point cloud or mesh")
    e.add_argument("--samples", type=int, default=200_000, help="points sampled from each mesh")
    e.add_argument("--threshold", type=float, default=0.05, help="completion-ratio distance in metres")
    e.add_argument("--seed", type=int, default=0, help="random seed of the mesh sampling")
    e = esub.add_parser("traj", help="ATE RMSE after Umeyama alignment, orientation error after an "
                                     "orientation-only fit, and RPE")
    e.add_argument("--est", required=True, help="estimated trajectory (TUM format)")
    e.add_argument("--gt", required=True, help="ground-truth trajectory (TUM format)")
    e.add_argument("--align", default="sim3", choices=["sim3", "se3", "none"], help="alignment before the ATE")
    e.add_argument("--max-dt", type=float, default=0.02, help="seconds: timestamps further apart do not match")
    e.add_argument("--delta", type=int, default=1, help="RPE frame step")

    for add in more:  # sub-commands defined elsewhere (services.cli: up, demo)
        add(sub)

    p = sub.add_parser("config", help="show the configs that --config files override")
    csub = p.add_subparsers(dest="action", required=True)
    c = csub.add_parser("dump", help="print the full default config as YAML (a starting point for --config)")
    c.add_argument("which", nargs="?", default="map", choices=CONFIGS,
                   help="map: the mapper (fmapping map); slam: fmapping slam; up: the mapper / tracker / launcher "
                        "sections of fmapping up and demo")

    _show_defaults(ap)
    return ap


class DefaultsHelp(argparse.ArgumentDefaultsHelpFormatter):
    """Appends '(default: X)' to a flag's help, except where there is nothing to say (None, an
    on/off flag) or the text already says it in words. Also the services' (``services.process.service_parser``)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default is None or isinstance(action.default, bool) or "default" in text:
            return text
        return super()._get_help_string(action)


def _show_defaults(parser: argparse.ArgumentParser) -> None:
    # set on every sub-parser after they are built: flags added later by any command get it too
    parser.formatter_class = DefaultsHelp
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sp in action.choices.values():
                _show_defaults(sp)


class _Version(argparse.Action):
    """``--version``, looked up only when asked for (the package metadata scan costs ~0.1 s)."""

    def __init__(self, option_strings, dest, help=None):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        sys.stdout.write(f"{parser.prog} {version()}\n")
        parser.exit()


def version() -> str:
    """The installed distribution's version; the package's own when run from an uninstalled tree."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("fmapping")
    except PackageNotFoundError:
        from fmapping import __version__

        return __version__


CONFIGS = ("map", "slam", "up")


def default_config(which: str):
    """The default config ``fmapping <which> --config FILE`` starts from: a dataclass, or for ``up``
    the dict of its sections."""
    if which == "map":
        from fmapping.mapping import MapperConfig

        return MapperConfig()
    if which == "slam":
        from fmapping.slam import SlamConfig

        return SlamConfig()
    if which == "up":
        from fmapping.up_config import UpConfig, up_config_dict

        return up_config_dict(UpConfig())
    raise ValueError(f"no config {which!r} (one of {', '.join(CONFIGS)})")


def cmd_config(a) -> int:
    from fmapping.config import to_yaml

    sys.stdout.write(f"# fmapping {a.which} config, every key at its default (fmapping {version()}).\n"
                     f"# Keep the keys to change and pass the file with: fmapping {a.which} --config FILE\n")
    sys.stdout.write(to_yaml(default_config(a.which)))
    return 0


def check_out(path) -> Path:
    """Create the output folder (with its parents) and make sure files can be written in it, so that
    a bad --out ends the command at once with one line naming it, not later inside a run."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    parent = next((p for p in out.parents if p.exists()), None)
    if parent is not None and not parent.is_dir():
        raise ValueError(f"--out {out}: {parent} is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"--out {out}: cannot create the folder: {e.strerror or e}") from None
    probe = out / f".fmapping-write-test-{os.getpid()}"
    try:  # a real write: permission bits say nothing for root or a read-only mount
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"--out {out}: cannot write in the folder: {e.strerror or e}") from None
    return out


def _print_json(d: dict) -> None:
    print(json.dumps(d, indent=2, sort_keys=True, default=str))


def cmd_synth(a) -> int:
    from fmapping.synthetic import generate_scene

    info = generate_scene(a.out, seed=a.seed, frames=a.frames, size=a.size, variety=a.variety)
    _print_json(info)
    return 0


def cmd_info(a) -> int:
    from fmapping.datasets import open_dataset

    ds = open_dataset(a.data, camera=a.camera, max_frames=a.max_frames, **source_options(a))
    _print_json(ds.describe())
    return 0


def cmd_map(a) -> int:
    from fmapping.job import Job
    from fmapping.pipeline import run_map

    with stop_on_signal("fmapping map") as stop:
        stats = run_map(Job.from_args(a, poses="gt"), should_stop=stop.is_set)
    summary = stats.get("summary", {})
    _print_json(summary)
    return 130 if summary.get("stopped_at") is not None else 0


def cmd_slam(a) -> int:
    from fmapping.datasets import is_live_spec
    from fmapping.job import Job
    from fmapping.slam import run_slam

    if is_live_spec(a.data):  # the first optimiser's imports now, not in the mapper's init while the camera runs
        preload_optimiser()
    with stop_on_signal("fmapping slam") as stop:
        stats = run_slam(Job.from_args(a, poses="photometric"), should_stop=stop.is_set)
    summary = stats.get("summary", {})
    _print_json(summary)
    return 130 if summary.get("stopped_at") is not None else 0


@contextlib.contextmanager
def stop_on_signal(prog: str):
    """Within: the first SIGINT / SIGTERM sets the yielded event (a long job ends at its next
    frame and writes what it has); a second SIGINT raises KeyboardInterrupt as usual."""
    stop = threading.Event()

    def handler(signum, _frame):
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        print(f"\n{prog}: {signal.Signals(signum).name}: stopping; writing what is done so far "
              "(Ctrl-C again to abort)", file=sys.stderr)

    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def cmd_eval(a) -> int:
    from fmapping import metrics

    if a.what == "recon":
        res = metrics.eval_recon_files(a.pred, a.gt, samples=a.samples, threshold=a.threshold, seed=a.seed)
    else:
        res = metrics.eval_traj_files(a.est, a.gt, align=a.align, max_dt=a.max_dt, delta=a.delta)
    _print_json(res)
    return 0


COMMANDS = {
    "synth": cmd_synth, "info": cmd_info, "map": cmd_map, "slam": cmd_slam,
    "eval": cmd_eval, "config": cmd_config,
}


def main(argv: Optional[Sequence[str]] = None, parser: Optional[argparse.ArgumentParser] = None,
         commands: Optional[dict] = None) -> int:
    """Run the sub-command of ``argv``; ``parser`` / ``commands`` (default: the library's own) let
    :mod:`services.cli` add its sub-commands."""
    args = (parser or build_parser()).parse_args(argv)
    retain_freed_memory()
    try:
        if getattr(args, "out", None) and not getattr(args, "resume", None):  # --resume OUT: that folder's run
            check_out(args.out)
        return (commands or COMMANDS)[args.command](args) or 0
    except (FileNotFoundError, ValueError) as e:  # bad input: one clear line, no traceback
        print(f"fmapping {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into e.g. `head`
        return 0
    except OSError as e:
        if e.filename is None:  # not about a path the user gave: a real failure, keep the traceback
            raise
        print(f"fmapping {args.command}: error: {e.filename}: {e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fmapping {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
