"""The command line's user-facing basics: packaging (matplotlib only for benches), ``--version``,
``config dump``, help text on every flag, one-line errors for a bad ``--out``."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

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
    from fmapping.launcher import LauncherOptions, UpConfig, split_config
    from fmapping.mapper import MapperConfig
    from fmapping.tracking.frontend import TrackerConfig

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

    from fmapping.cli import build_parser

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
    from fmapping.launcher import add_run_info, run_info, split_config

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
