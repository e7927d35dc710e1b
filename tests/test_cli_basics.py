"""The command line's user-facing basics: packaging (matplotlib only for benches), ``--version``,
``config dump``, help text on every flag, one-line errors for a bad ``--out``."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fakes import fake_up

ROOT = Path(__file__).resolve().parents[1]


def test_library_and_services_import_without_matplotlib():
    # matplotlib is the [bench] extra: a plain `pip install fmapping` must import every module
    code = textwrap.dedent("""
        import importlib, pkgutil, sys
        sys.modules["matplotlib"] = None  # any `import matplotlib` now raises ImportError
        import fmapping, services
        names = []
        for pkg in (fmapping, services):
            for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
                if not m.name.endswith("__main__"):
                    importlib.import_module(m.name)
                    names.append(m.name)
        print(len(names))
    """)
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.split()[-1]) > 20


def test_fmapping_lists_every_sub_command_and_the_library_never_imports_services():
    # the console entry point (services.cli) adds the process sub-commands to the library's
    from fmapping.cli import build_parser as library_parser
    from services.cli import build_parser

    def commands(parser):
        import argparse

        return list(next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices)

    assert commands(build_parser()) == ["synth", "info", "map", "slam", "eval", "up", "demo", "config"]
    assert "up" not in commands(library_parser()) and "demo" not in commands(library_parser())
    r = subprocess.run([sys.executable, "-m", "services.cli", "--help"], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "{synth,info,map,slam,eval,up,demo,config}" in r.stdout
    # layering: fmapping/ never imports services (nor zenoh)
    for path in (ROOT / "fmapping").rglob("*.py"):
        text = path.read_text()
        assert "import services" not in text and "from services" not in text, path
        assert "import zenoh" not in text, path


# ------------------------------------------------------------------ --version
def test_version_from_metadata_or_package(capsys, monkeypatch):
    import importlib.metadata

    import fmapping
    from fmapping.cli import main, version

    with pytest.raises(SystemExit) as ei:
        main(["--version"])
    assert ei.value.code == 0
    assert capsys.readouterr().out.strip() == f"fmapping {importlib.metadata.version('fmapping')}"

    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)
    monkeypatch.setattr(fmapping, "__version__", "9.8.7")
    assert version() == "9.8.7"


# ------------------------------------------------------------------ config dump
def _dump(which, capsys) -> str:
    from fmapping.cli import main

    assert main(["config", "dump", which]) == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("which", ["map", "slam"])
def test_config_dump_loads_back_unchanged(which, tmp_path, capsys):
    from fmapping.cli import default_config
    from fmapping.config import load_config, to_dict

    text = _dump(which, capsys)
    path = tmp_path / f"{which}.yaml"
    path.write_text(text)
    default = default_config(which)
    loaded = load_config(default, path)
    assert loaded == default and to_dict(loaded) == to_dict(default)
    assert "init_rounds: [[0, 32], [3, 64], [4, 64], [5, 64]]" in text  # every key is there, nested ones too


def test_config_dump_up_loads_back_unchanged(tmp_path, capsys):
    from fmapping.config import load_config
    from fmapping.up_config import LauncherOptions, UpConfig, split_config
    from fmapping.mapping import MapperConfig
    from fmapping.tracking.direct_tracker import TrackerConfig

    path = tmp_path / "up.yaml"
    path.write_text(_dump("up", capsys))
    assert load_config(UpConfig(), path) == UpConfig()
    # and as `fmapping up --config` reads it: one file per service and the launcher options
    mapper_yaml, tracker_yaml, opts = split_config(str(path), tmp_path / "out")
    assert load_config(MapperConfig(), mapper_yaml) == MapperConfig()
    assert load_config(TrackerConfig(), tracker_yaml) == TrackerConfig()
    assert opts == LauncherOptions()


def test_config_dump_defaults_to_the_mapper(capsys):
    from fmapping.cli import main

    assert main(["config", "dump"]) == 0
    assert capsys.readouterr().out == _dump("map", capsys)


# ------------------------------------------------------------------ help text
def _subparsers(parser, path=()):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sp in action.choices.items():
                yield path + (name,), sp
                yield from _subparsers(sp, path + (name,))


def test_every_flag_has_help_with_its_default():
    import argparse

    from services.cli import build_parser

    seen = 0
    parsers = dict(_subparsers(build_parser()))
    for path, sp in parsers.items():
        for action in sp._actions:
            if not action.option_strings:
                continue
            seen += 1
            flag = " ".join(path) + " " + action.option_strings[-1]
            assert action.help and action.help.strip(), f"{flag} has no help text"
            if action.default not in (None, argparse.SUPPRESS) and not isinstance(action.default, bool):
                # a value default is in the help: appended by the formatter, or said in words
                assert "default" in sp._get_formatter()._get_help_string(action), flag
    assert seen > 40 and ("config", "dump") in parsers
    text = " ".join(parsers[("map",)].format_help().split())
    assert "torch device: auto (CUDA when present, else CPU), cpu, cuda (default: auto)" in text
    text = " ".join(parsers[("synth",)].format_help().split())
    assert "number of frames (default: 200)" in text and "(default: 320x240)" in text


def test_every_service_flag_has_help_with_its_default():
    import argparse

    from services import router
    from services.io import play, record, view
    from services.mapper.__main__ import build_parser as mapper_parser
    from services.process import service_parser
    from services.ros2.__main__ import build_parser as ros2_parser
    from services.tracker.__main__ import build_parser as tracker_parser

    parsers = {"io play": play.add_args(service_parser("services.io play", None)),
               "io view": view.add_args(service_parser("services.io view", None)),
               "io record": record.add_args(service_parser("services.io record", None)),
               "mapper": mapper_parser(), "tracker": tracker_parser(), "ros2": ros2_parser(),
               "router": router.build_parser()}
    seen = 0
    for name, p in parsers.items():
        for action in p._actions:
            if not action.option_strings or action.default is argparse.SUPPRESS:
                continue
            seen += 1
            flag = f"{name} {action.option_strings[-1]}"
            assert action.help and action.help.strip(), f"{flag} has no help text"
            if action.default is not None and not isinstance(action.default, bool):
                assert "default" in p._get_formatter()._get_help_string(action), flag
    assert seen > 120
    text = " ".join(parsers["io play"].format_help().split())
    assert "frames in flight beyond the slowest acknowledgement (default: 4)" in text


# ------------------------------------------------------------------ bad --out
@pytest.mark.parametrize("command", ["map", "slam"])
def test_bad_out_is_one_line_and_rc_2(command, tmp_path, capsys):
    from fmapping.cli import main

    data = tmp_path / "no-data-needed"  # --out is checked before the dataset is read
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [(afile, "exists and is not a folder"), (afile / "sub" / "out", f"{afile} is a file")]
    if Path("/sys").is_dir():  # not writable even for root
        cases.append((Path("/sys/fmapping-out-test"), "cannot create the folder"))
    if os.geteuid() != 0:
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        cases.append((locked, "cannot write in the folder"))
    for out, reason in cases:
        assert main([command, "--data", str(data), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--out {out}" in err and reason in err, err
        assert err.startswith(f"fmapping {command}: error: ")


def test_bad_out_without_traceback_from_the_shell(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    r = subprocess.run([sys.executable, "-m", "fmapping.cli", "slam", "--data", str(tmp_path), "--out",
                        str(afile / "run")], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == f"fmapping slam: error: --out {afile / 'run'}: {afile} is a file, not a folder"


def test_out_is_created_with_its_parents(tmp_path):
    from fmapping.cli import check_out

    out = check_out(tmp_path / "a" / "b")
    assert out.is_dir() and list(out.iterdir()) == []


# ------------------------------------------------------------------ fmapping up: stats.json
def test_up_stats_get_the_intrinsics_and_the_resolved_config(scene, tmp_path):
    import json
    import time

    from fmapping.datasets import open_dataset
    from fmapping.up_config import split_config
    from services.launcher.up import add_run_info, run_info

    out = tmp_path / "up"
    cfg = tmp_path / "up.yaml"
    cfg.write_text("mapper:\n  rays_per_iter: 512\n  bbox: [[-1, -1, -1], [1, 1, 1]]\n"
                   "tracker:\n  num_points: 900\nlauncher:\n  view: false\n  size: [64, 48]\n")
    mapper_yaml, tracker_yaml, opts = split_config(str(cfg), out)
    info = run_info(scene, "gt", mapper_yaml, tracker_yaml, opts)
    ds = open_dataset(scene)
    assert info["dataset"]["camera"] == ds.camera.to_dict() and info["dataset"]["depth_scale"] == ds.depth_scale
    c = info["config"]
    assert c["mapper"]["rays_per_iter"] == 512 and c["mapper"]["n_coarse"] == 32  # given, and defaults filled in
    assert c["mapper"]["bbox"] == ((-1, -1, -1), (1, 1, 1))
    assert c["tracker"]["num_points"] == 900 and c["launcher"]["view"] is False and "extra" not in c["launcher"]
    assert info["poses"] == "gt"

    # merged into the stats.json the mapper wrote in this run; its own keys stay
    started = time.time()
    stats = out / "stats.json"
    stats.write_text(json.dumps({"final": True, "frames": 14}))
    assert add_run_info(out, info, since=started)
    got = json.loads(stats.read_text())
    assert got["final"] is True and got["frames"] == 14
    assert got["dataset"]["camera"]["fx"] == ds.camera.fx and got["config"]["tracker"]["num_points"] == 900
    # the recorded config is a valid `up` config: it reruns with the same settings
    again = tmp_path / "again.yaml"
    again.write_text(__import__("yaml").safe_dump(got["config"]))
    m2, t2, o2 = split_config(str(again), tmp_path / "up2")
    assert run_info(scene, "gt", m2, t2, o2)["config"] == c

    # a stats.json left in OUT by an earlier run is not the mapper's of this run: untouched
    stats.write_text(json.dumps({"old": 1}))
    os.utime(stats, (started - 3600, started - 3600))
    assert not add_run_info(out, info, since=started) and json.loads(stats.read_text()) == {"old": 1}
    stats.unlink()
    assert not add_run_info(out, info, since=started)  # the mapper wrote none (failed early)


# ------------------------------------------------------------------ the sources on the command line
def _image_folder(folder: Path, n: int = 3) -> Path:
    import cv2
    import numpy as np

    folder.mkdir()
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((24, 32, 3), 60 * i, np.uint8))
    return folder


def test_data_help_lists_the_sources_and_fps_topic_reach_the_dataset(tmp_path, capsys):
    import argparse

    from fmapping.job import Job
    from fmapping.pipeline import open_job_dataset
    from services.cli import build_parser, main

    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    for cmd in ("info", "map", "slam", "up"):
        text = " ".join(subs[cmd].format_help().split())
        for source in ("image folder", "video", "EuRoC", "ScanNet", "rosbag2", "MCAP", "camera:N"):
            assert source in text, (cmd, source)
    for cmd in ("info", "map", "slam"):  # fps = timestamps of an image folder / video; topic = a bag's images
        for flag in ("--fps", "--data-fps"):
            a = parser.parse_args([cmd, "--data", "x", flag, "12.5", "--topic", "/cam/image_raw"]
                                  + (["--out", "o"] if cmd != "info" else []))
            assert a.data_fps == 12.5 and a.topic == "/cam/image_raw"
    # up: --fps is the playback rate, the timestamps' rate is --data-fps
    a = parser.parse_args(["up", "--fps", "5", "--data-fps", "12.5", "--topic", "/cam/image_raw"])
    assert (a.fps, a.data_fps, a.topic) == (5.0, 12.5, "/cam/image_raw")

    images = _image_folder(tmp_path / "imgs")
    job = Job.from_args(parser.parse_args(["map", "--data", str(images), "--camera", "30,30,16,12", "--fps", "10",
                                           "--out", str(tmp_path / "o")]), poses="gt")
    assert (job.data_fps, job.topic, job.camera) == (10.0, None, "30,30,16,12")
    ds = open_job_dataset(job)
    assert [round(t, 6) for t in ds.timestamps] == [0.0, 0.1, 0.2]
    capsys.readouterr()
    assert main(["info", "--data", str(images), "--camera", "30,30,16,12", "--fps", "10"]) == 0
    assert '"fps": 10.0' in capsys.readouterr().out
    assert main(["info", "--data", str(images), "--camera", "30,30,16,12", "--topic", "/x"]) == 2
    assert "topic= applies to rosbag sources" in capsys.readouterr().err


def test_up_takes_a_live_camera_with_its_intrinsics_and_passes_them_to_play(tmp_path, monkeypatch, capsys):
    """`fmapping up --data camera:N` needs --camera (one-line error otherwise) and hands both to io play;
    the launcher itself never opens the device (stats.json gets the --camera given)."""
    from fmapping.up_config import LauncherOptions
    from services.cli import main
    from services.launcher import up as launcher

    out = tmp_path / "up"
    assert main(["up", "--data", "camera:0", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "camera:0" in err and "--camera" in err and len(err.strip().splitlines()) == 1
    assert main(["up", "--data", "camera:front", "--camera", "500,500,320,240", "--out", str(out)]) == 2
    assert "camera:N" in capsys.readouterr().err

    started = fake_up(monkeypatch)  # records what would run; no process starts
    opened = []
    monkeypatch.setattr("fmapping.datasets.open_dataset", lambda *a, **k: opened.append(a) or None)
    assert main(["up", "--data", "camera:0", "--camera", "500,500,320,240", "--poses", "gt", "--view", "save",
                 "--insecure", "--out", str(out)]) == 0
    play = started["play"]
    assert play[play.index("--data") + 1] == "camera:0" and play[play.index("--camera") + 1] == "500,500,320,240"
    assert opened == []  # the device is play's alone
    info = launcher.run_info("camera:0", "gt", None, None, LauncherOptions(), "500,500,320,240")
    assert info["dataset"] == {"root": "camera:0", "kind": "camera", "live": True, "frames": None,
                               "camera_source": "500,500,320,240"}


def test_up_sends_the_datasets_depth_only_to_runs_that_may_use_it(scene, tmp_path, monkeypatch):
    """The synthetic scene has depth. An RGB-only run's player sends colour alone (``--no-depth``); a mapper
    with ``use_depth`` or an external pose producer (kiss-icp reads depth) gets the depth."""
    import yaml

    from services.cli import main

    assert (scene / "depth").is_dir()
    started = fake_up(monkeypatch)
    base = ["up", "--data", str(scene), "--view", "save", "--insecure"]

    def play_argv(*extra) -> list:
        started.clear()
        assert main(base + ["--out", str(tmp_path / f"up{len(list(tmp_path.iterdir()))}"), *extra]) == 0
        return started["play"]

    assert "--no-depth" in play_argv("--poses", "tracker")
    assert "--no-depth" in play_argv("--poses", "gt")
    cfg = tmp_path.parent / f"{tmp_path.name}_depth.yaml"
    cfg.write_text(yaml.safe_dump({"mapper": {"use_depth": True}}))
    assert "--no-depth" not in play_argv("--poses", "gt", "--config", str(cfg))
    assert "--no-depth" not in play_argv("--poses", "external")


def test_up_passes_camera_for_a_recorded_source_too(tmp_path, monkeypatch):
    from fmapping.up_config import LauncherOptions
    from services.launcher import up as launcher

    images = _image_folder(tmp_path / "imgs")
    info = launcher.run_info(images, "tracker", None, None, LauncherOptions(), "30,30,16,12")
    assert info["dataset"]["kind"] == "images" and info["dataset"]["camera"]["fx"] == 30.0
    with pytest.raises(Exception, match="no camera intrinsics"):
        launcher.run_info(images, "tracker", None, None, LauncherOptions())


def test_up_passes_the_mapper_inbox_bounds_of_its_config(scene, tmp_path, monkeypatch, capsys):
    """``launcher.mapper_inbox_frames`` / ``mapper_inbox_mb`` reach the mapper's command line, which its own
    parser reads back; unset, the mapper keeps its defaults; a bad value is a one-line error naming the key,
    before any process starts."""
    import yaml

    from services.cli import main
    from services.mapper.__main__ import build_parser
    from services.mapper.intake import FRAME_BYTES, FRAME_CAPACITY

    started = fake_up(monkeypatch)

    def mapper_args(launcher: dict):
        started.clear()
        cfg = tmp_path / f"up{len(list(tmp_path.iterdir()))}.yaml"
        cfg.write_text(yaml.safe_dump({"launcher": launcher}))
        rc = main(["up", "--data", str(scene), "--poses", "gt", "--view", "save", "--insecure", "--config", str(cfg),
                   "--out", str(tmp_path / cfg.stem)])
        return rc, (build_parser().parse_args(started["mapper"][3:]) if "mapper" in started else None)

    rc, a = mapper_args({"mapper_inbox_frames": 64, "mapper_inbox_mb": 24})
    assert rc == 0 and (a.inbox_frames, a.inbox_mb) == (64, 24.0)
    rc, a = mapper_args({})
    assert rc == 0 and (a.inbox_frames, a.inbox_mb) == (FRAME_CAPACITY, FRAME_BYTES / 2 ** 20)
    capsys.readouterr()
    for bad in ({"mapper_inbox_frames": 0}, {"mapper_inbox_frames": 2.5}, {"mapper_inbox_mb": -1},
                {"mapper_inbox_mb": float("inf")}):
        rc, a = mapper_args(bad)
        err = capsys.readouterr().err
        assert rc == 2 and a is None and started == {}, bad
        assert f"launcher.{next(iter(bad))}" in err and len(err.strip().splitlines()) == 1, err
