"""``fmapping up --resume OUT``: the arguments of a run kept in OUT/run.json, checked and read back,
and what a new or a resumed run does with what an earlier one left in OUT."""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from services.launcher.commands import tracker_state

RUN_FILE = "run.json"  # OUT/run.json: the arguments of a run, for fmapping up --resume OUT


def save_run_args(args, out: Path) -> None:
    """OUT/run.json: the arguments of this run (its config file copied to OUT/config/up.yaml), so that
    ``fmapping up --resume OUT`` can continue it."""
    keep = {k: v for k, v in vars(args).items() if k not in ("command", "resume")
            and isinstance(v, (str, int, float, bool, list, tuple, type(None)))}
    if keep.get("config"):
        copy = out / "config" / "up.yaml"
        copy.parent.mkdir(parents=True, exist_ok=True)
        if Path(keep["config"]).resolve() != copy.resolve():
            copy.write_text(Path(keep["config"]).read_text())
        keep["config"] = str(copy)
    (out / RUN_FILE).write_text(json.dumps(keep, indent=1))


def resume_args(folder) -> argparse.Namespace:
    """The arguments of the run in ``folder`` to continue it (``fmapping up --resume OUT``), or
    ValueError with one line saying why there is nothing to resume."""
    out = Path(folder)
    try:
        saved = json.loads((out / RUN_FILE).read_text())
    except OSError:
        raise ValueError(f"--resume {out}: no run of fmapping up to resume there (no {RUN_FILE})") from None
    except ValueError:
        raise ValueError(f"--resume {out}: {out / RUN_FILE} is not readable JSON") from None
    if not isinstance(saved, dict):
        raise ValueError(f"--resume {out}: {out / RUN_FILE} does not hold the arguments of a run")
    if not (out / "checkpoint.pt").is_file():
        try:
            done = "error" not in json.loads((out / "up.json").read_text())
        except (OSError, ValueError):
            done = False
        raise ValueError(f"--resume {out}: " + ("the run there completed, nothing to resume" if done else
                         "no checkpoint.pt (the mapper never finished a window): start the run again without --resume"))
    if isinstance(saved.get("data"), str) and saved["data"].startswith("camera:"):
        raise ValueError(f"--resume {out}: the run played a live camera ({saved['data']}), which cannot go back")
    return argparse.Namespace(**{**saved, "out": str(out), "resume": True})


def keep_logs(out: Path) -> Path:
    """OUT/logs of the earlier part of a resumed run moved to OUT/logs.<n> (the first free n)."""
    n = 1
    while (out / f"logs.{n}").exists():
        n += 1
    if (out / "logs").is_dir():
        os.replace(out / "logs", out / f"logs.{n}")
    return out / f"logs.{n}"


def start_over(out: Path) -> None:
    """A new run in OUT: what an earlier, unfinished run left to resume from is not this run's."""
    if (out / "checkpoint.pt").exists():
        (out / "checkpoint.pt").unlink()
        print(f"fmapping up: starting over: removed the checkpoint of an earlier unfinished run in {out} "
              f"(fmapping up --resume {out} continues such a run)", flush=True)
    tracker_state(out).unlink(missing_ok=True)
