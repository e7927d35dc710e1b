"""Plumbing shared by the services: zenoh configuration and sessions, bounded inboxes,
status counters and heartbeats, signal handling, and what the zenoh-free service cores share
(:class:`ServiceCore`: bad-input accounting, the stream camera check).

Only ``services/`` imports zenoh; the library (``fmapping``) never does, and neither do the
service cores (this module imports zenoh only when a session or config is made). Every service
follows the same shape: zenoh callbacks do no work beyond checking the payload where the
service asks for that (:meth:`Service.subscribe` with ``admit``: decoded and checked for
plausibility in the callback, so that a bad message is never queued and never displaces a real
one) and copying it into a bounded :class:`Inbox` (drop-oldest, or thinned; bounded in items
and in bytes); one worker loop (the main thread) calls the library and publishes
results. A message that fails to decode is counted (``decode_errors``) and logged (rate
limited); it never reaches the service's state. Stop commands (the end of the sequence among
them) have a queue of their own, ``end``, that neither data nor other commands can evict.

Network defaults are explicit and container friendly: peer mode, multicast scouting off,
loopback endpoints given on the command line (``--listen`` / ``--connect``), or a zenoh
JSON5 config file (``--zenoh-config``) for anything else (TLS, access control, routers).
"""
from __future__ import annotations

import argparse
import collections
import faulthandler
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Optional, Sequence

import numpy as np
from fmapping.cli import DefaultsHelp
from fmapping.config import read_yaml_mapping
from fmapping.fileio import write_json

from fmapping import protocol as P

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("fmapping.services")

MIB = 1024 * 1024
# Plausibility of what an authenticated peer sends (it may still be buggy or compromised):
MAX_SEQ_AHEAD = 10_000  # a frame / pose number this far beyond the newest frame seen is refused
# A map version is bumped once per mapper update and every update but the closing one integrates
# a new frame, so one mapper run has version <= frame_seq + 2; the slack covers resets and stops.
VERSION_SLACK = 64
DEFAULT_CHANNEL_BYTES = 64 * MIB  # an inbox channel's byte bound unless the service gives one
END_CAPACITY = 8  # the stop queue: any one stop ends the run, a few are plenty
EXIT_STALLED = 3  # exit code of a service that gave up waiting (the run cannot progress); 2 is bad input


# ---------------------------------------------------------------------------- configuration
def _split(values: Optional[Iterable[str]]) -> list[str]:
    out: list[str] = []
    for v in values or []:
        out += [x.strip() for x in str(v).split(",") if x.strip()]
    return out


def names(text: Optional[str]) -> list[str]:
    """Service names from a comma-separated option value ('' or None: none)."""
    return _split([text] if text else [])


class _ServiceHelp(argparse.RawDescriptionHelpFormatter, DefaultsHelp):
    """The module docstring as written, each flag's default after its help."""


def service_parser(prog: str, doc: Optional[str]) -> argparse.ArgumentParser:
    """The argument parser of ``python -m <prog>``, its module docstring as description."""
    return argparse.ArgumentParser(prog=f"python -m {prog}", description=doc, formatter_class=_ServiceHelp)


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask: a container's cpuset, ``taskset``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def set_torch_threads(n: int, auto: int) -> int:
    """``--threads``: torch intra-op threads, ``auto`` when ``n`` is 0 (at least 1). Returns the count.

    Not torch's default (one per core in every process): the services share the cores, and
    torch's OpenMP threads spin while they wait for each other. ``make demo`` on 2 cores, wall
    time: torch's default 69-82 s idle and 257 s beside two busy processes; one thread each
    95-97 s idle and 110 s beside them (2026-12-02)."""
    import torch

    k = n if n > 0 else max(1, int(auto))
    torch.set_num_threads(k)
    return k


LOG_LEVEL_HELP = "logging level: DEBUG, INFO, WARNING or ERROR (default: $FMAPPING_LOG, else INFO)"
FINAL_TIMEOUT_HELP = ("seconds to wait, after the end-of-sequence stop, for the --wait-done services to report "
                      "'done' (they write their final outputs then)")


def add_common_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """zenoh and service options every service accepts."""
    g = p.add_argument_group("zenoh")
    g.add_argument("--mode", choices=["peer", "client"], default=None, help="zenoh mode (default peer)")
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="listen endpoint(s), e.g. tcp/127.0.0.1:7447 (repeat or comma-separate)")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint(s) to connect to, e.g. tcp/127.0.0.1:7447 or a router tcp/zenoh:7447")
    g.add_argument("--multicast", action="store_true", default=None,
                   help="enable multicast scouting (off by default: explicit endpoints work in containers and CI)")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="zenoh JSON5 config (native format, e.g. for TLS) or a YAML file with keys "
                        "mode, listen, connect, multicast, namespace, options {json5/key/path: value}; "
                        "command-line options override it")
    g.add_argument("--ns", "--namespace", dest="ns", default=None,
                   help="key-expression namespace: fmapping/<ns>/... (default $FMAPPING_NS or 'default')")
    g = p.add_argument_group("service")
    g.add_argument("--status-file", default=None, help="also write the status as JSON to this file (atomically)")
    g.add_argument("--status-interval", type=float, default=0.5, help="heartbeat period in seconds")
    g.add_argument("--exit-with-parent", action="store_true", help="stop when the parent process goes away")
    g.add_argument("--log-level", default=os.environ.get("FMAPPING_LOG", "INFO"), help=LOG_LEVEL_HELP)
    return p


def _insert(conf: zenoh.Config, key: str, value: Any) -> None:
    try:
        conf.insert_json5(key, json.dumps(value))
    except Exception as e:  # zenoh raises ZError with the offending key
        raise ValueError(f"zenoh config: cannot set {key} = {value!r}: {e}") from None


def zenoh_config(mode: Optional[str] = "peer", listen: Optional[list[str]] = None,
                 connect: Optional[list[str]] = None, multicast: Optional[bool] = False, options: Optional[dict] = None,
                 base: Optional[zenoh.Config] = None) -> zenoh.Config:
    """A zenoh config with explicit endpoints; ``options`` maps JSON5 key paths to values."""
    import zenoh

    conf = base if base is not None else zenoh.Config()
    # None keeps what ``base`` (a native JSON5 file) says
    if mode is not None:
        if mode not in ("peer", "client", "router"):
            raise ValueError(f"zenoh mode must be peer, client or router, got {mode!r}")
        _insert(conf, "mode", mode)
    if multicast is not None:
        _insert(conf, "scouting/multicast/enabled", bool(multicast))
    if listen is not None:
        _insert(conf, "listen/endpoints", list(listen))
    if connect is not None:
        _insert(conf, "connect/endpoints", list(connect))
    for k, v in (options or {}).items():
        _insert(conf, k, v)
    return conf


def resolve_network(args) -> dict:
    """Merge --zenoh-config (YAML) and command-line options into mode/listen/connect/multicast/ns/options."""
    net: dict[str, Any] = {"mode": "peer", "listen": None, "connect": None, "multicast": False,
                           "ns": os.environ.get("FMAPPING_NS", "default"), "options": {}, "native": None}
    path = getattr(args, "zenoh_config", None)
    if path:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"zenoh config not found: {path}")
        if path.suffix in (".json5", ".json"):
            # a native file keeps its own mode and scouting unless the command line says otherwise
            net.update(native=str(path), mode=None, multicast=None)
        else:
            data = read_yaml_mapping(path)
            unknown = set(data) - {"mode", "listen", "connect", "multicast", "namespace", "options"}
            if unknown:
                raise ValueError(f"{path}: unknown keys {sorted(unknown)} "
                                 "(valid: mode, listen, connect, multicast, namespace, options)")
            for k in ("mode", "multicast", "options"):
                if k in data:
                    net[k] = data[k]
            for k in ("listen", "connect"):
                if k in data:
                    net[k] = _split(data[k] if isinstance(data[k], list) else [data[k]])
            if "namespace" in data:
                net["ns"] = str(data["namespace"])
    if getattr(args, "mode", None):
        net["mode"] = args.mode
    if getattr(args, "listen", None):
        net["listen"] = _split(args.listen)
    if getattr(args, "connect", None):
        net["connect"] = _split(args.connect)
    if getattr(args, "multicast", None):
        net["multicast"] = True
    if getattr(args, "ns", None):
        net["ns"] = args.ns
    if net["mode"] == "peer" and net["listen"] is None and net["native"] is None:
        net["listen"] = ["tcp/127.0.0.1:0"]  # loopback only, any free port, announced by gossip
    if net["mode"] == "client":
        net["listen"] = net["listen"] or []
        # wait (up to 2 min) for the router instead of failing at once: containers start in any order
        net["options"].setdefault("connect/timeout_ms", 120000)
        net["options"].setdefault("connect/exit_on_failure", False)
    return net


def open_session(args) -> tuple[zenoh.Session, P.Keys]:
    """Open the zenoh session described by the parsed arguments; returns (session, keys)."""
    import zenoh

    net = resolve_network(args)
    keys = P.Keys(net["ns"])
    base = zenoh.Config.from_file(net["native"]) if net["native"] else None
    conf = zenoh_config(net["mode"], net["listen"], net["connect"], net["multicast"], net["options"], base=base)
    log.debug("zenoh: mode=%s listen=%s connect=%s multicast=%s ns=%s",
              net["mode"], net["listen"], net["connect"], net["multicast"], net["ns"])
    return zenoh.open(conf), keys


def payload_bytes(sample) -> bytes:
    """The payload of a zenoh Sample (or Reply.ok) as bytes."""
    return sample.payload.to_bytes()


def query_latest(session: zenoh.Session, key: str, timeout: float = 5.0, retry: float = 0.05) -> Optional[bytes]:
    """Ask the queryable on ``key`` for its latest value; retry until ``timeout`` (a queryable
    declared by a peer that just connected takes a moment to propagate). None if nobody answers."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        for reply in session.get(key, timeout=max(0.05, min(left, 2.0))):
            if reply.ok is not None:
                return payload_bytes(reply.ok)
        time.sleep(min(retry, max(0.0, deadline - time.monotonic())))


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


# ---------------------------------------------------------------------------- queues and counters
class Counters:
    """Thread-safe named counters (ints or floats)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._c: dict[str, float] = {}

    def inc(self, name: str, n: float = 1) -> None:
        with self._lock:
            self._c[name] = self._c.get(name, 0) + n

    def set(self, name: str, value: float) -> None:
        # a Status carries numbers only: anything else would make every later status fail to encode
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise TypeError(f"counter {name!r} must be a number, got {type(value).__name__} {value!r}")
        with self._lock:
            self._c[name] = value

    def get(self, name: str, default: float = 0) -> float:
        with self._lock:
            return self._c.get(name, default)

    def snapshot(self) -> dict:
        with self._lock:
            return dict(self._c)


# ---------------------------------------------------------------------------- service cores (no zenoh)
def rigid_pose(m: np.ndarray) -> np.ndarray:
    """``m`` (4, 4) with its rotation block projected onto SO(3) (SVD) and last row [0, 0, 0, 1]:
    float poses out of an optimiser must pass the protocol's rotation check before publishing.
    :func:`fmapping.geometry.orthonormalize` (imported here, not above: it brings torch)."""
    from fmapping.geometry import orthonormalize

    return orthonormalize(m)


def usable_camera(cam: Any, undistorted: bool = False) -> dict:
    """The protocol normal form of camera dict ``cam`` (``Frame.camera``) when the library can use
    it (:class:`fmapping.camera.PinholeCamera` accepts it; no distortion coefficients when
    ``undistorted``), else ValueError naming what is wrong."""
    from fmapping.camera import PinholeCamera

    if undistorted and isinstance(cam, dict) and cam.get("dist"):
        raise ValueError(f"camera has distortion coefficients {cam['dist']}; this service needs undistorted frames "
                         "(the player undistorts)")
    try:
        out = P.check_camera(cam, "camera")
        PinholeCamera.from_dict(out)
    except (P.ProtocolError, TypeError, ValueError, KeyError) as e:
        raise ValueError(f"unusable camera {cam}: {e}") from None
    return out


class ServiceCore:
    """What the zenoh-free service cores share: counters (the shell passes its own), decoding
    each payload by the message type its channel carries (``CHANNELS``), and counting bad input.

    Bad input (a payload that fails to decode, a frame the stream cannot take) is counted as
    ``bad_input`` plus a specific counter, kept in ``last_error``, passed to ``on_bad_input``
    (a one-line description) and never changes the state. The stream's camera is fixed by
    the first usable frame (:meth:`frame_camera`)."""

    CHANNELS: dict[str, type] = {}

    def __init__(self, counters=None, on_bad_input: Optional[Callable[[str], None]] = None):
        self.counters = counters if counters is not None else Counters()
        self.on_bad_input = on_bad_input
        self.last_error = ""
        self.camera_dict: Optional[dict] = None
        self.newest_seq = -1  # the newest frame number the core took (the head of the stream)

    @property
    def ack(self) -> int:
        return -1

    def handle(self, channel: str, data: bytes, key: str = "") -> list:
        """:meth:`admit` and :meth:`apply` one payload from ``channel``."""
        msg = self.admit(channel, data, key)
        return [] if msg is None else self.apply(msg)

    def admit(self, channel: str, data: bytes, key: str = "") -> Optional[P.Message]:
        """The decoded message of ``data`` (the type ``channel`` carries) when it is plausible, else
        None (counted: ``decode_errors``, ``rejected_seq``). Thread safe: the shell calls it in the
        zenoh callback, before anything is queued, so a bad message never displaces a real one."""
        expect = self.CHANNELS.get(channel)
        if expect is None:
            raise ValueError(f"{type(self).__name__}.admit: unknown channel {channel!r}")
        try:
            msg = P.decode(data, expect)
        except P.ProtocolError as e:
            self.bad_input(f"{key or channel}: {e}", "decode_errors")
            return None
        why = seq_problem(msg, max(self.newest_seq, self.ack))
        if why:
            self.bad_input(f"{key or channel}: {why}", "rejected_seq")
            return None
        return msg

    def took_frame(self, seq: int) -> None:
        """The core accepted frame ``seq``: the head of the stream moves (see :func:`seq_problem`)."""
        self.newest_seq = max(self.newest_seq, int(seq))

    def apply(self, msg: P.Message) -> list:
        raise NotImplementedError

    def bad_input(self, why: str, counter: str) -> None:
        self.counters.inc(counter)
        self.counters.inc("bad_input")
        self.last_error = why
        if self.on_bad_input is not None:
            self.on_bad_input(why)

    def frame_camera(self, f: P.Frame, undistorted: bool = False) -> Optional[dict]:
        """The camera of frame ``f`` when the stream can take the frame, else None (counted as
        ``rejected_frames``): the stream's camera (``camera_dict``) when it is fixed, the
        :func:`usable_camera` of the first frame otherwise (the caller fixes it)."""
        try:
            if self.camera_dict is None:
                return usable_camera(f.camera, undistorted)
            if f.camera != self.camera_dict:
                raise ValueError(f"camera {f.camera} differs from the stream's {self.camera_dict}")
        except ValueError as e:
            self.bad_input(f"frame {f.seq}: {e}", "rejected_frames")
            return None
        return self.camera_dict


def seq_problem(msg: Any, head: int) -> str:
    """Why a Frame or Pose number is implausible ('' when it is not): negative, or more than
    :data:`MAX_SEQ_AHEAD` beyond ``head``, the newest frame seen (-1: none yet, then any number
    starts the stream). A frame far ahead would move the acknowledgement past every real frame."""
    if not isinstance(msg, (P.Frame, P.Pose)):
        return ""
    what = "frame" if isinstance(msg, P.Frame) else f"pose ({msg.source})"
    if msg.seq < 0:
        return f"{what} {msg.seq}: negative frame number"
    if head >= 0 and msg.seq > head + MAX_SEQ_AHEAD:
        return f"{what} {msg.seq}: more than {MAX_SEQ_AHEAD} beyond the newest frame {head}"
    return ""


def snapshot_problem(version: int, frame_seq: int, current: int, head: int) -> str:
    """Why a map snapshot (``version``, newest integrated ``frame_seq``) is implausible after
    version ``current`` with ``head`` the newest frame seen (-1: unknown); '' when it is not.
    Versions never go back, grow by one per mapper update (at most :data:`VERSION_SLACK` beyond
    the frames integrated), and the frame must not be far ahead of the stream: a forged version
    10**9 would otherwise shadow every real snapshot for good."""
    if version < current:
        return f"version {version} is older than version {current}"
    if version > max(frame_seq, 0) + VERSION_SLACK:
        return f"version {version} cannot follow from frame {frame_seq} (one version per mapper update)"
    if head >= 0 and frame_seq > head + MAX_SEQ_AHEAD:
        return f"frame {frame_seq} is more than {MAX_SEQ_AHEAD} beyond the newest frame {head}"
    return ""


class Inbox:
    """Bounded channels between zenoh callbacks and the worker, drop-oldest per channel.

    Every channel is bounded in items (``capacities``) and in bytes (``max_bytes``, default
    :data:`DEFAULT_CHANNEL_BYTES`; an item's size is the ``nbytes`` given to :meth:`put`, by
    default the length of the bytes it holds). A new item evicts older ones of its channel
    until both bounds hold again; it is never evicted itself, so a channel holds at most its
    byte bound or a single item, whichever is larger. Channels never evict each other's items.

    ``get`` serves channels in the priority order given at construction (e.g. control
    before poses before frames). Drops are counted as ``dropped_<channel>``.

    A channel in ``thin`` drops differently when full: the item whose neighbours arrived
    closest together (:func:`thin_victim`), so that a backlog stays spread evenly over the
    time it covers. The mapper's frames use it: while a long update runs it then gets a
    subsampled stream rather than only the newest frames.
    """

    def __init__(self, capacities: dict[str, int], counters: Optional[Counters] = None, thin: Sequence[str] = (),
                 max_bytes: Optional[dict[str, int]] = None):
        self._q = {name: collections.deque() for name in capacities}
        self._cap = dict(capacities)
        self._max_bytes = {name: int((max_bytes or {}).get(name, DEFAULT_CHANNEL_BYTES)) for name in capacities}
        self._sizes = {name: collections.deque() for name in capacities}  # bytes of each queued item
        self._bytes = {name: 0 for name in capacities}
        self._thin = {name: collections.deque() for name in thin}  # arrival numbers of the thinned channels
        self._arrivals = 0
        self._cond = threading.Condition()
        self.counters = counters or Counters()

    def put(self, channel: str, item: Any, nbytes: Optional[int] = None) -> bool:
        """Append ``item`` (``nbytes`` long, default :func:`item_bytes`); returns False when older
        items had to be dropped."""
        size = item_bytes(item) if nbytes is None else int(nbytes)
        with self._cond:
            q, sizes = self._q[channel], self._sizes[channel]
            arr = self._thin.get(channel)
            if arr is not None:
                self._arrivals += 1
                arr.append(self._arrivals)
            q.append(item)
            sizes.append(size)
            self._bytes[channel] += size
            dropped = 0
            while len(q) > 1 and (len(q) > self._cap[channel] or self._bytes[channel] > self._max_bytes[channel]):
                # the victim is never the new item: thin_victim keeps the newest, drop-oldest takes index 0
                i = thin_victim(arr) if arr is not None else 0
                del q[i]
                if arr is not None:
                    del arr[i]
                self._bytes[channel] -= sizes[i]
                del sizes[i]
                dropped += 1
            self._cond.notify()
        self.counters.inc(f"received_{channel}")
        if dropped:
            self.counters.inc(f"dropped_{channel}", dropped)
        return not dropped

    def get(self, timeout: Optional[float] = None) -> Optional[tuple[str, Any]]:
        """(channel, item) of the highest-priority non-empty channel, or None after ``timeout``."""
        with self._cond:
            end = None if timeout is None else time.monotonic() + timeout
            while True:
                for name, q in self._q.items():
                    if q:
                        if name in self._thin:
                            self._thin[name].popleft()
                        self._bytes[name] -= self._sizes[name].popleft()
                        return name, q.popleft()
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cond.wait(left)

    def size(self, channel: Optional[str] = None) -> int:
        with self._cond:
            return len(self._q[channel]) if channel else sum(len(q) for q in self._q.values())

    def nbytes(self, channel: Optional[str] = None) -> int:
        """Bytes queued in ``channel`` (all channels when None)."""
        with self._cond:
            return self._bytes[channel] if channel else sum(self._bytes.values())

    def has(self, channel: str) -> bool:
        return channel in self._q

    def clear(self) -> None:
        with self._cond:
            for q in (*self._q.values(), *self._thin.values(), *self._sizes.values()):
                q.clear()
            for name in self._bytes:
                self._bytes[name] = 0


def item_bytes(item: Any) -> int:
    """The size an inbox charges for ``item``: the bytes-like objects it is or holds (a tuple's
    elements), 0 for anything else."""
    parts = item if isinstance(item, tuple) else (item,)
    return sum(len(x) for x in parts if isinstance(x, (bytes, bytearray, memoryview)))


def thin_victim(arrivals: Sequence[int]) -> int:
    """Index of the item to drop from a full thinned queue (arrival numbers, oldest first): the
    one whose removal leaves the smallest gap between its neighbours, the oldest of equals.
    The oldest and the newest item always stay."""
    a = list(arrivals)
    if len(a) < 3:
        return 0
    gaps = [a[i + 1] - a[i - 1] for i in range(1, len(a) - 1)]
    return 1 + gaps.index(min(gaps))


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


# ---------------------------------------------------------------------------- service shell
class StatusBoard:
    """The status of one service, built from its counters; thread safe."""

    def __init__(self, service: str, counters: Optional[Counters] = None):
        self.service = service
        self.counters = counters or Counters()
        self._lock = threading.Lock()
        self._seq = 0
        self.state = "starting"
        self.frame_seq = -1
        self.lag = 0.0
        self.last_error = ""
        self.started = time.time()

    def error(self, text: str) -> None:
        with self._lock:
            self.last_error = str(text)[: P.MAX_STRING]

    def update(self, state: Optional[str] = None, frame_seq: Optional[int] = None, lag: Optional[float] = None) -> None:
        with self._lock:
            if state is not None:
                self.state = state
            if frame_seq is not None:
                self.frame_seq = max(self.frame_seq, int(frame_seq))
            if lag is not None:
                self.lag = float(lag)

    def message(self) -> P.Status:
        with self._lock:
            self._seq += 1
            counters = {k: v for k, v in self.counters.snapshot().items()}
            counters["uptime"] = round(time.time() - self.started, 3)
            return P.Status(service=self.service, seq=self._seq, time=time.time(), state=self.state,
                            frame_seq=self.frame_seq, lag=self.lag, counters=counters, last_error=self.last_error)


def status_to_dict(st: P.Status) -> dict:
    return {"service": st.service, "seq": st.seq, "time": st.time, "state": st.state, "frame_seq": st.frame_seq,
            "lag": st.lag, "counters": st.counters, "last_error": st.last_error, "pid": os.getpid()}


def write_json_atomic(path, data: dict) -> None:
    """A status file: ``data`` as sorted JSON (anything else as ``str``), written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, data, sort_keys=True, default=str)


class Service:
    """A zenoh session plus what every service needs: keys, publishers, an inbox fed by
    subscriptions, a status heartbeat (published and optionally written to a file) and
    signal handling. The worker loop stays in the concrete service; ``with Service(...) as svc``
    closes it (state ``done``). ``install_signals`` defaults to "when it opens its own session"
    (a service given a session runs inside a host, e.g. a test, that keeps its signals)."""

    def __init__(self, name: str, args, capacities: Optional[dict[str, int]] = None,
                 session: Optional[zenoh.Session] = None, keys: Optional[P.Keys] = None,
                 install_signals: Optional[bool] = None, thin: Sequence[str] = (),
                 max_bytes: Optional[dict[str, int]] = None):
        self.name = name
        self.args = args
        self.status = StatusBoard(name)
        self.counters = self.status.counters
        capacities = dict(capacities or {})
        if "control" in capacities and "end" not in capacities:
            # stop commands (the end of the sequence) first, in a queue nothing else can evict
            capacities = {"end": END_CAPACITY, **capacities}
        self.inbox = Inbox(capacities, self.counters, thin, max_bytes)
        if install_signals is None:
            install_signals = session is None
        self.shutdown = Shutdown(install=install_signals, watch_parent=bool(getattr(args, "exit_with_parent", False)))
        self.log = logging.getLogger(f"fmapping.{name}")
        self.bad_input = RateLimitedLog(self.log)
        self._own_session = session is None
        if session is None:
            session, keys = open_session(args)
        self.session = session
        self.keys = keys or P.Keys(getattr(args, "ns", None) or "default")
        self._pubs: dict[str, Any] = {}
        self._decls: list[Any] = []
        self._hb_stop = threading.Event()
        self._hb: Optional[threading.Thread] = None
        self._closed = False

    def __enter__(self) -> "Service":
        return self

    def __exit__(self, *exc) -> None:
        self.close("done")

    # -- publishing
    def publisher(self, key: str, block: bool = True):
        if key not in self._pubs:
            import zenoh

            cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
            self._pubs[key] = self.session.declare_publisher(key, congestion_control=cc)
        return self._pubs[key]

    def publish(self, key: str, msg: P.Message, block: bool = True) -> int:
        data = P.encode(msg)
        self.publisher(key, block).put(data)
        self.counters.inc("published")
        return len(data)

    def publish_status(self) -> P.Status:
        st = self.status.message()
        try:
            self.publisher(self.keys.status(self.name)).put(P.encode(st))
        except Exception as e:  # a closed session during shutdown
            self.log.debug("status publish failed: %s", e)
        path = getattr(self.args, "status_file", None)
        if path:
            try:
                write_json_atomic(path, status_to_dict(st))
            except OSError as e:
                self.log.warning("cannot write status file %s: %s", path, e)
        return st

    # -- subscribing
    def subscribe(self, key: str, channel, admit: Optional[Callable[[str, bytes], Any]] = None) -> None:
        """Payloads on ``key`` go to inbox channel ``channel`` as (key, bytes); with ``admit``, as
        (key, admit(key, bytes)) and only when that is not None: the check runs in the callback,
        before queueing (``admit`` counts what it refuses). ``channel`` may be a function of the
        admitted item naming the channel. The inbox charges the payload's size either way."""
        inbox = self.inbox

        def on_sample(sample) -> None:
            k, data = str(sample.key_expr), payload_bytes(sample)
            if admit is None:
                inbox.put(channel, (k, data), nbytes=len(data))
                return
            try:
                item = admit(k, data)
            except Exception as e:  # never let a check's exception reach zenoh
                self.counters.inc("callback_errors")
                self.log.exception("check of a message on %s failed: %s", k, e)
                return
            if item is not None:
                inbox.put(channel(item) if callable(channel) else channel, (k, item), nbytes=len(data))

        self._decls.append(self.session.declare_subscriber(key, on_sample))

    def subscribe_control(self) -> None:
        """Control messages, decoded and addressed-checked in the callback, as (key, Control): stop
        commands (the end-of-sequence marker among them) to channel ``end``, the rest to
        ``control``. Neither data nor a flood of other commands can evict a stop."""
        end = "end" if self.inbox.has("end") else "control"
        self.subscribe(self.keys.control, lambda ctl: end if ctl.command == "stop" else "control",
                       admit=lambda key, data: self.control(data, key))

    def subscribe_callback(self, key: str, fn: Callable[[str, bytes], None]) -> None:
        def on_sample(sample) -> None:
            try:
                fn(str(sample.key_expr), payload_bytes(sample))
            except Exception as e:  # never let a callback exception reach zenoh
                self.counters.inc("callback_errors")
                self.log.exception("callback on %s failed: %s", key, e)

        self._decls.append(self.session.declare_subscriber(key, on_sample))

    def queryable(self, key: str, answer: Callable[[], Optional[bytes]]) -> None:
        """Answer queries on ``key`` with ``answer()`` (no reply when it returns None)."""

        def on_query(query) -> None:
            try:
                data = answer()
                if data is not None:
                    query.reply(key, data)
                    self.counters.inc("queries_answered")
            except Exception as e:
                self.counters.inc("callback_errors")
                self.log.exception("query on %s failed: %s", key, e)

        self._decls.append(self.session.declare_queryable(key, on_query))

    def decode(self, data: bytes, expect: Optional[type] = None, where: str = "") -> Optional[P.Message]:
        """Decode or count-and-log: returns None for a bad message (``decode_errors``)."""
        try:
            return P.decode(data, expect)
        except P.ProtocolError as e:
            self.counters.inc("decode_errors")
            self.counters.inc("bad_input")
            self.status.error(f"{where}: {e}" if where else str(e))
            self.bad_input("bad message on %s: %s", where or "?", e)
            return None

    def addressed(self, ctl: P.Control) -> bool:
        """Whether a Control message is for this service (no target or target == name)."""
        target = ctl.args.get("target")
        return target in (None, "", "all", self.name) or (isinstance(target, list) and self.name in target)

    def control(self, data: bytes, where: str = "") -> Optional[P.Control]:
        """The Control message in ``data`` when it decodes and is for this service, else None."""
        ctl = self.decode(data, P.Control, where)
        return ctl if ctl is not None and self.addressed(ctl) else None

    def give_up(self, why: str) -> int:
        """The run cannot progress: log ``why``, report it (state error, ``stalls``); returns the exit code."""
        self.counters.inc("stalls")
        self.status.update(state="error")
        self.status.error(why)
        self.log.error("giving up: %s", why)
        return EXIT_STALLED

    def report_bad_input(self, text: str) -> None:
        """A service core's ``on_bad_input``: the status's last error and a rate-limited warning."""
        self.status.error(text)
        self.bad_input("%s", text)

    def report_core(self, core, state: Optional[str] = None, lag: Optional[float] = None) -> None:
        """Status from a :class:`ServiceCore`: its acknowledgement (``ack``) and new ``last_error``."""
        self.status.update(state=state, frame_seq=core.ack, lag=lag)
        if core.last_error and core.last_error != self.status.last_error:
            self.status.error(core.last_error)

    # -- heartbeat and lifetime
    def start(self, state: str = "running") -> None:
        """Announce ``state`` now and start the heartbeat."""
        self.status.update(state=state)
        self.publish_status()
        self.start_heartbeat()

    def start_heartbeat(self) -> None:
        interval = float(getattr(self.args, "status_interval", 0.5) or 0.5)

        def beat() -> None:
            while not self._hb_stop.wait(interval):
                self.shutdown.requested  # noqa: B018 - polls the parent watchdog
                self.publish_status()

        self._hb = threading.Thread(target=beat, name=f"{self.name}-heartbeat", daemon=True)
        self._hb.start()

    def close(self, state: str = "done") -> None:
        if self._closed:
            return
        self._closed = True
        self._hb_stop.set()
        if self._hb is not None:
            self._hb.join(timeout=2.0)
        self.status.update(state=state)
        self.publish_status()
        for d in self._decls + list(self._pubs.values()):
            try:
                d.undeclare()
            except Exception:
                pass
        if self._own_session:
            self.session.close()


class Peers:
    """The latest Status of every other service, with waiting helpers (flow control, start-up)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._latest: dict[str, tuple[P.Status, float]] = {}

    def update(self, st: P.Status) -> None:
        with self._cond:
            old = self._latest.get(st.service)
            # keep the newest (status seq restarts when a service restarts: newer time wins)
            if old is None or st.seq > old[0].seq or st.time > old[0].time:
                self._latest[st.service] = (st, time.monotonic())
            self._cond.notify_all()

    def get(self, service: str) -> Optional[P.Status]:
        with self._cond:
            e = self._latest.get(service)
            return e[0] if e else None

    def age(self, service: str) -> float:
        with self._cond:
            e = self._latest.get(service)
            return float("inf") if e is None else time.monotonic() - e[1]

    def services(self) -> list[str]:
        with self._cond:
            return sorted(self._latest)

    def wait(self, predicate: Callable[["Peers"], bool], timeout: float,
             stop: Optional[threading.Event] = None) -> bool:
        """Block until ``predicate(self)`` holds (re-checked on every status), the timeout or ``stop``."""
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                if predicate(self):
                    return True
                left = end - time.monotonic()
                if left <= 0 or (stop is not None and stop.is_set()):
                    return False
                self._cond.wait(min(left, 0.1))

    def acked(self, service: str) -> int:
        st = self.get(service)
        return -1 if st is None else st.frame_seq

    def notify(self) -> None:
        with self._cond:
            self._cond.notify_all()


# ---------------------------------------------------------------------------- consumers of a sequence
def stop_kind(ctl: P.Control, wait_done: Sequence[str]) -> Optional[str]:
    """For a consumer that ends with the sequence: 'end' for the end-of-sequence stop when it
    waits for ``wait_done`` services, 'stop' for any other stop, None for other commands."""
    if ctl.command != "stop":
        return None
    return "end" if ctl.args.get("reason") == "end" and wait_done else "stop"


def serve_until_end(svc: Service, peers: Peers, handle: Callable[[str, str, bytes], Optional[str]],
                    wait_done: Sequence[str], final_timeout: float, first: Optional[FirstMessage] = None,
                    data_channels: Sequence[str] = ()) -> int:
    """The worker loop of a consumer that ends with the sequence (``io record``, ``io view``).

    Every inbox item goes to ``handle(channel, key, data)`` until it returns 'stop' or a signal
    comes; once it returns 'end' (:func:`stop_kind`) the loop ends when every service in
    ``wait_done`` reports state done (or error) in ``peers``, or after ``final_timeout`` seconds.
    What is still queued then (e.g. the final points published just before 'done') is handled too.
    With ``first``, nothing on ``data_channels`` before it expires ends the loop too: returns
    :data:`EXIT_STALLED` then (:meth:`Service.give_up`), else 0."""
    end_deadline: Optional[float] = None
    code = 0
    while not svc.shutdown.requested:
        item = svc.inbox.get(timeout=0.1)
        if item is None and first is not None and first.expired():
            code = svc.give_up(first.message())
            break
        if item is not None:
            channel, (key, data) = item
            if first is not None and channel in data_channels:
                first.see()
            what = handle(channel, key, data)
            if what == "stop":
                break
            if what == "end" and end_deadline is None:
                end_deadline = time.monotonic() + final_timeout
                svc.status.update(state="finishing")
        if end_deadline is not None:
            done = all(peers.get(n) is not None and peers.get(n).state in ("done", "error") for n in wait_done)
            if done or time.monotonic() > end_deadline:
                if not done:
                    svc.log.warning("%s not done after %.0f s: ending with what I have", wait_done, final_timeout)
                break
    while (item := svc.inbox.get(timeout=0)) is not None:
        channel, (key, data) = item
        handle(channel, key, data)
    return code
