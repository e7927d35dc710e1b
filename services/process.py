"""What every service process does around its core: its command line (``python -m services.<name>``),
logging, torch threads, the stop flag of SIGINT / SIGTERM, the first-message timeout, and the exit.

No zenoh here (:mod:`services.zenoh_session` opens sessions, :mod:`services.transport` runs them)."""
from __future__ import annotations

import argparse
import faulthandler
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional

from fmapping.cli import DefaultsHelp

EXIT_STALLED = 3  # exit code of a service that gave up waiting (the run cannot progress); 2 is bad input


class _ServiceHelp(argparse.RawDescriptionHelpFormatter, DefaultsHelp):
    """The module docstring as written, each flag's default after its help."""


def service_parser(prog: str, doc: Optional[str]) -> argparse.ArgumentParser:
    """The argument parser of ``python -m <prog>``, its module docstring as description."""
    return argparse.ArgumentParser(prog=f"python -m {prog}", description=doc, formatter_class=_ServiceHelp)


def command_line(parser: argparse.ArgumentParser, **values: Any) -> list[str]:
    """The arguments that ``parser`` reads back as ``values`` (option destination -> value, in the
    order given): each option's first long flag and ``str(value)``; an on/off flag alone when the
    value is true; None (and a false on/off flag) left out. A launcher names destinations and values
    only, so the flags of a service have one home, its parser, and a wrong name fails here, not in
    the child process."""
    actions = {a.dest: a for a in parser._actions if a.option_strings}
    argv: list[str] = []
    for dest, value in values.items():
        action = actions.get(dest)
        if action is None:
            raise ValueError(f"{parser.prog}: no option for {dest!r}")
        if value is None:
            continue
        flag = next((s for s in action.option_strings if s.startswith("--")), action.option_strings[0])
        if action.nargs == 0:  # store_true and the like
            if value:
                argv.append(flag)
            continue
        if action.choices is not None and str(value) not in [str(c) for c in action.choices]:
            raise ValueError(f"{parser.prog}: {flag} {value!r} is not one of {list(action.choices)}")
        argv += [flag, str(value)]
    return argv


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask: a container's cpuset, ``taskset``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def runs_idle() -> bool:
    """Whether this process runs under the SCHED_IDLE policy (``fmapping up`` starts the mapper and the viewer so:
    they get only the CPU time nothing else wants)."""
    try:
        return os.sched_getscheduler(0) == os.SCHED_IDLE
    except (AttributeError, OSError):  # not Linux
        return False


def enter_sched_idle() -> bool:
    """Put every thread of this process under the SCHED_IDLE policy (threads started later inherit it from their
    creator). Returns whether this thread now runs so (False where the policy does not exist: not Linux).

    A service asks for it once started (``--sched-idle``, :meth:`services.transport.Service.start`), not from the
    launcher before it runs: under SCHED_IDLE from its first instruction, a mapper on a machine whose cores were
    busy with other work got almost no CPU for its imports and did not start within the launcher's 120 s."""
    if not hasattr(os, "SCHED_IDLE"):
        return False
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        tids = [0]
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        except OSError:  # a thread that has just ended
            pass
    return runs_idle()


def set_torch_threads(n: int, auto: int) -> int:
    """``--threads``: torch intra-op threads, ``auto`` when ``n`` is 0 (at least 1). Returns the count.

    Not torch's default (one per core in every process): the services share the cores, and
    torch's OpenMP threads spin while they wait for each other (README, "Torch threads", has the
    wall times of ``make demo`` both ways)."""
    import torch

    k = n if n > 0 else max(1, int(auto))
    torch.set_num_threads(k)
    return k


LOG_LEVEL_HELP = "logging level: DEBUG, INFO, WARNING or ERROR (default: $FMAPPING_LOG, else INFO)"


def exit_process(code: Optional[int]) -> None:
    """End a service process now with ``code`` once its outputs are written: flush the logs and
    standard streams, then ``os._exit``. The interpreter's normal teardown of torch alone takes
    1.5 s here (several seconds when a whole system stops at once on a busy machine), which would
    break the promise that SIGTERM / SIGINT end a service within 5 s."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(0 if code is None else int(code))


def run_main(main: Callable[[], Optional[int]], prog: str) -> None:
    """``python -m <prog>``: run ``main()``; a missing file or bad value is a one-line error
    (exit code 2); then :func:`exit_process`. ``kill -USR1 <pid>`` prints every thread's stack
    to stderr (a service that hangs shows where)."""
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        code = main()
    except (FileNotFoundError, ValueError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        code = 2
    exit_process(code)  # outputs are written: skip the slow interpreter teardown


def setup_logging(level: str = "INFO", name: str = "") -> None:
    logging.basicConfig(level=getattr(logging, str(level).upper(), logging.INFO),
                        format=f"%(asctime)s {name or '%(name)s'} %(levelname)s %(message)s", datefmt="%H:%M:%S")


class Shutdown:
    """A stop flag set by SIGINT / SIGTERM (and optionally by the parent process going away).

    The handler only sets the flag. Long library calls poll :attr:`requested` (the mapper
    between iterations) rather than being broken off by an exception raised at an arbitrary
    point, which can leave a lock held (a logging handler's, a counter's) and hang the exit."""

    def __init__(self, install: bool = True, watch_parent: bool = False):
        self.event = threading.Event()
        self.reason = ""
        self._parent = os.getppid() if watch_parent else None
        if install and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, self._handler)

    def _handler(self, signum, _frame) -> None:
        self.set(signal.Signals(signum).name)

    def set(self, reason: str = "requested") -> None:
        if not self.event.is_set():
            self.reason = reason
        self.event.set()

    @property
    def requested(self) -> bool:
        if self._parent is not None and os.getppid() != self._parent:
            self.set("parent exited")
        return self.event.is_set()

    def wait(self, timeout: float) -> bool:
        return self.event.wait(timeout) or self.requested


FIRST_MESSAGE_TIMEOUT = 900.0  # default of --first-message-timeout (fmapping up passes its own)


def add_first_message_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--first-message-timeout", type=float, default=FIRST_MESSAGE_TIMEOUT,
                   help=f"seconds to wait for the first {what}; then the service writes what it has and exits "
                        f"with code {EXIT_STALLED}, naming what it waited for (0 = wait forever)")


def camera_json(text: str) -> dict:
    """``--stream-camera``'s value: a JSON object (a Frame's camera dict), an argparse error otherwise."""
    try:
        cam = json.loads(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"not JSON: {e}") from None
    if not isinstance(cam, dict) or not {"fx", "fy", "cx", "cy"} <= set(cam):
        raise argparse.ArgumentTypeError("a JSON object with fx, fy, cx, cy (and width, height: a frame's camera)")
    return cam


def live_stream_camera(camera: Optional[str]) -> Optional[str]:
    """``--stream-camera`` for a live camera (``camera:N``), as JSON: the intrinsics of its ``--camera
    fx,fy,cx,cy[,dist]`` string as play's frames carry them (undistorted: ``dist`` None), without the size, which
    only the device knows once open (:func:`services.core_support.camera_matches` checks the keys given). None for
    a calibration file or no camera: the first frame then fixes the stream's camera."""
    from fmapping.camera import PinholeCamera

    if not camera or Path(camera).exists():
        return None
    try:
        cam = PinholeCamera.from_string(camera, 1 << 20, 1 << 20).undistorted().to_dict()  # any size: not compared
    except ValueError:
        return None
    return json.dumps({k: cam[k] for k in ("fx", "fy", "cx", "cy", "dist")})


def add_stream_camera_arg(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--stream-camera", type=camera_json, default=None,
                   help="the camera the run's frames carry (JSON, as in a frame message): a first frame with "
                        "another camera is refused instead of fixing the stream's (fmapping up passes its data's)")
    g.add_argument("--stream-camera-of", default=None, metavar="DATA",
                   help="the same, the camera of the dataset DATA as io play opens it without --camera (docker "
                        "compose: /data); a dataset that cannot be opened here leaves the check off, with a warning")


def stream_camera(args, log: logging.Logger) -> Optional[dict]:
    """The camera ``--stream-camera`` / ``--stream-camera-of`` give (None: neither, or a dataset that cannot be
    opened, logged)."""
    if getattr(args, "stream_camera", None) is not None:
        return args.stream_camera
    data = getattr(args, "stream_camera_of", None)
    if not data:
        return None
    from fmapping.datasets import open_dataset

    try:
        return dict(open_dataset(data).describe()["camera"])
    except Exception as e:  # any dataset error: the check is an extra, the frames' own checks still apply
        log.warning("--stream-camera-of %s: cannot open it (%s); the first frame fixes the stream's camera", data, e)
        return None


class FirstMessage:
    """A service waiting for its first data message: :meth:`expired` once ``timeout`` seconds
    (0: never) have passed since start without :meth:`see`. A run whose producer never came
    then ends with an error that names what was awaited instead of hanging."""

    def __init__(self, timeout: float, what: str):
        self.timeout, self.what = float(timeout or 0), what
        self.t0 = time.monotonic()
        self.seen = False

    def see(self) -> None:
        self.seen = True

    def expired(self) -> bool:
        return not self.seen and self.timeout > 0 and time.monotonic() - self.t0 > self.timeout

    def message(self) -> str:
        return f"no {self.what} within {self.timeout:g} s of start (is the player running?)"


class RateLimitedLog:
    """Log the first ``first`` events, then every ``every``-th (fuzzed inputs must not flood logs)."""

    def __init__(self, logger: logging.Logger, first: int = 10, every: int = 1000):
        self.logger, self.first, self.every, self.n = logger, first, every, 0

    def __call__(self, msg: str, *args) -> None:
        self.n += 1
        if self.n <= self.first or self.n % self.every == 0:
            self.logger.warning(msg + (f" [{self.n} so far]" if self.n > self.first else ""), *args)

