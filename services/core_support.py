"""What the zenoh-free service cores share: the :class:`ServiceCore` base (decoding by channel,
bad-input accounting, the stream camera check), the plausibility checks of frame numbers and map
versions, thread-safe :class:`Counters`, and the bounded :class:`Inbox` between zenoh callbacks
and a service's worker loop. Nothing here imports zenoh.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable, Optional, Sequence

import numpy as np

from fmapping import protocol as P

MIB = 1024 * 1024
# Plausibility of what an authenticated peer sends (it may still be buggy or compromised):
MAX_SEQ_AHEAD = 10_000  # a frame / pose number this far beyond the newest frame seen is refused
# A map version is bumped once per mapper update and every update but the closing one integrates
# a new frame, so one mapper run has version <= frame_seq + 2; the slack covers resets and stops.
VERSION_SLACK = 64
DEFAULT_CHANNEL_BYTES = 64 * MIB  # an inbox channel's byte bound unless the service gives one


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
        # the camera the run's frames carry, when the launcher knows it (its data): a first frame with another one
        # is refused instead of fixing the stream's camera (an authorised peer gone wrong could otherwise take the
        # stream with one small frame before the data's first)
        self.expected_camera: Optional[dict] = None
        self.newest_seq = -1  # the newest frame number the core took (the head of the stream)
        # seconds since a frame last arrived (the shell: its frames inbox, Inbox.idle). A core behind the
        # camera drops work to keep pace only while frames keep coming; once the stream has ended or
        # paused there is no camera to keep up with (default: always streaming)
        self.stream_idle: Callable[[], float] = lambda: 0.0

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
        :func:`usable_camera` of the first frame otherwise (the caller fixes it), which must be
        ``expected_camera`` when that is set."""
        try:
            if self.camera_dict is None:
                if self.expected_camera is not None and not camera_matches(f.camera, self.expected_camera):
                    raise ValueError(f"camera {f.camera} is not the run's camera {self.expected_camera}")
                return usable_camera(f.camera, undistorted)
            if f.camera != self.camera_dict:
                raise ValueError(f"camera {f.camera} differs from the stream's {self.camera_dict}")
        except ValueError as e:
            self.bad_input(f"frame {f.seq}: {e}", "rejected_frames")
            return None
        return self.camera_dict


def camera_matches(camera: Any, expected: dict) -> bool:
    """Whether a frame's camera dict has every key of ``expected`` with its value (a live run's expected camera
    has no size: the device tells it)."""
    return isinstance(camera, dict) and all(k in camera and camera[k] == v for k, v in expected.items())


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

    A thinned channel may also have a ``rank`` (item -> int, asked at eviction time): the victim
    is then thinned out of the items of the lowest rank only, the new item included (the mapper's
    frames: known non-keyframes first, then frames whose pose has not come, keyframes last; see
    :mod:`services.mapper.intake`). Evictions of items of rank >= 2 are also counted as
    ``dropped_<channel>_rank2``.
    """

    def __init__(self, capacities: dict[str, int], counters: Optional[Counters] = None, thin: Sequence[str] = (),
                 max_bytes: Optional[dict[str, int]] = None, rank: Optional[dict[str, Callable[[Any], int]]] = None):
        self._q = {name: collections.deque() for name in capacities}
        self._cap = dict(capacities)
        self._max_bytes = {name: int((max_bytes or {}).get(name, DEFAULT_CHANNEL_BYTES)) for name in capacities}
        self._sizes = {name: collections.deque() for name in capacities}  # bytes of each queued item
        self._bytes = {name: 0 for name in capacities}
        self._thin = {name: collections.deque() for name in thin}  # arrival numbers of the thinned channels
        self._arrivals = 0
        self._rank = dict(rank or {})
        for name in self._rank:
            if name not in self._thin:
                raise ValueError(f"Inbox: ranked channel {name!r} must also be thinned")
        self._cond = threading.Condition()
        self.counters = counters or Counters()
        self._last_put: dict[str, float] = {}  # channel -> time.monotonic() of its newest item

    def idle(self, channel: str) -> float:
        """Seconds since the newest item of ``channel`` arrived (inf before the first)."""
        with self._cond:
            t = self._last_put.get(channel)
        return float("inf") if t is None else time.monotonic() - t

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
            self._last_put[channel] = time.monotonic()
            dropped = ranked_out = 0
            rank = self._rank.get(channel)
            while len(q) > 1 and (len(q) > self._cap[channel] or self._bytes[channel] > self._max_bytes[channel]):
                if rank is not None:  # thinned among the lowest rank (the new item may go)
                    i, r = ranked_victim(arr, [rank(x) for x in q])
                    ranked_out += r >= 2
                else:  # never the new item: thin_victim keeps the newest, drop-oldest takes index 0
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
        if ranked_out:
            self.counters.inc(f"dropped_{channel}_rank2", ranked_out)
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


def ranked_victim(arrivals: Sequence[int], ranks: Sequence[int]) -> tuple[int, int]:
    """(index, rank) of the item to drop from a full ranked queue: :func:`thin_victim` among the items of
    the lowest rank (their arrival numbers), so that what stays of that rank is spread evenly."""
    low = min(ranks)
    idx = [i for i, r in enumerate(ranks) if r == low]
    return idx[thin_victim([arrivals[i] for i in idx])], low


def thin_victim(arrivals: Sequence[int]) -> int:
    """Index of the item to drop from a full thinned queue (arrival numbers, oldest first): the
    one whose removal leaves the smallest gap between its neighbours, the oldest of equals.
    The oldest and the newest item always stay."""
    a = list(arrivals)
    if len(a) < 3:
        return 0
    gaps = [a[i + 1] - a[i - 1] for i in range(1, len(a) - 1)]
    return 1 + gaps.index(min(gaps))

