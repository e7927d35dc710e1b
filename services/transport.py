"""The zenoh shell of a service: :class:`Service` (session, publishers, subscriptions into a
bounded inbox, queryables, status heartbeat), the status of the other services (:class:`Peers`)
and the worker loop of a consumer that ends with the sequence (:func:`serve_until_end`).

Only ``services/`` imports zenoh; the library (``fmapping``) never does, and neither do the
service cores (:mod:`services.core_support`; this module imports zenoh only when a session is
made, :mod:`services.zenoh_session`). Every service follows the same shape: zenoh callbacks do
no work beyond checking the payload where the service asks for that (:meth:`Service.subscribe`
with ``admit``: decoded and checked for plausibility in the callback, so that a bad message is
never queued and never displaces a real one) and copying it into a bounded
:class:`~services.core_support.Inbox` (drop-oldest, or thinned; bounded in items and in bytes);
one worker loop (the main thread) calls the library and publishes results. A message that fails
to decode is counted (``decode_errors``) and logged (rate limited); it never reaches the
service's state. Stop commands (the end of the sequence among them) have a queue of their own,
``end``, that neither data nor other commands can evict.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence

from fmapping import protocol as P
from fmapping.fileio import write_json
from services.core_support import Counters, Inbox
from services.process import EXIT_STALLED, FirstMessage, RateLimitedLog, Shutdown
from services.zenoh_session import open_session, payload_bytes

if TYPE_CHECKING:
    import zenoh

END_CAPACITY = 8  # the stop queue: any one stop ends the run, a few are plenty
FINAL_TIMEOUT_HELP = ("seconds to wait, after the end-of-sequence stop, for the --wait-done services to report "
                      "'done' (they write their final outputs then)")


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
                 max_bytes: Optional[dict[str, int]] = None, rank: Optional[dict] = None):
        self.name = name
        self.args = args
        self.status = StatusBoard(name)
        self.counters = self.status.counters
        capacities = dict(capacities or {})
        if "control" in capacities and "end" not in capacities:
            # stop commands (the end of the sequence) first, in a queue nothing else can evict
            capacities = {"end": END_CAPACITY, **capacities}
        self.inbox = Inbox(capacities, self.counters, thin, max_bytes, rank)
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
        if getattr(self.args, "sched_idle", False):  # its start-up ran at the launcher's priority
            from services.process import enter_sched_idle

            self.log.info("under SCHED_IDLE from here on: %s", enter_sched_idle())

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
