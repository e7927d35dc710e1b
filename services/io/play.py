"""``io play``: publish a dataset as Frame messages (and GT poses on ``poses/gt``).

Pacing: with ``--fps F`` frames go out at F per second whatever the consumers do (they
drop the oldest when they fall behind). With ``--fps 0`` (default) playback is as fast
as the consumers keep up: at most ``--window`` frames are in flight beyond the newest
frame acknowledged (``Status.frame_seq``) by every service in ``--ack-from``, however long
they take while their heartbeat goes on; a consumer silent for ``--ack-timeout`` seconds
no longer holds playback back (``ack_timeouts``). A consumer that is alive but whose
acknowledgement has not moved for ``--stall-timeout`` seconds means the run can no longer
progress: play then logs which consumer it waited for and at which frame, sends the
end-of-sequence stop (so that the consumers write their outputs) and exits with code 3.

Before the first frame it waits (``--start-timeout``) until every service in
``--wait-for`` has published a status, so nobody misses the start. A consumer that joins
or restarts later (its status counter starts over) is not waited for on frames sent
before it appeared. At the end it waits
for the last acknowledgement, then publishes ``Control(stop, {reason: end, last_seq})``.
Control: pause / resume / stop / reset (restart from the first frame; frame numbers
keep increasing) / start (begin when launched with ``--paused``).

Restarts: a consumer named in ``--resend-to`` whose status counter starts over gets the frames
after what it has done sent again, with their frame numbers (a resumed mapper from its
checkpoint's frame, a restarted tracker from its last acknowledgement). ``--start-after mapper``
begins with the frame after the mapper's acknowledgement (``fmapping up --resume``).

``--data`` is any source fmapping reads, with the options of ``fmapping info`` / ``map`` / ``slam``
(``--camera``, ``--max-frames``, ``--topic``; their ``--fps``, the timestamps of an image folder or a
video, is ``--data-fps`` here). ``--data camera:N`` streams a live webcam
(:class:`fmapping.datasets.live.LiveCamera`, intrinsics from ``--camera``): frames are read as they
are sent, until the device stops or ``--max-frames``; it has no length, so no ``frames_total``, no
``--loop``, and ``reset`` just goes on.
"""
from __future__ import annotations

import argparse
import threading
import time
from typing import Optional

import numpy as np

from fmapping import protocol as P
from fmapping.cli import add_source_args, source_options
from services.process import EXIT_STALLED, service_parser
from services.transport import Peers, Service
from services.zenoh_session import add_common_args, names


def add_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--data", required=True, help="dataset folder, video, ROS bag or image folder (any source "
                   "fmapping reads), or camera:N for a live webcam (needs --camera)")
    p.add_argument("--camera", default=None, help="override intrinsics fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] "
                   "or a calib.txt / camera.yaml path")
    p.add_argument("--max-frames", type=int, default=None, help="play only the first N frames (default: all)")
    p.add_argument("--fps", type=float, default=0.0,
                   help="playback rate in frames per second (0 = as fast as consumers keep up; the frames' "
                        "timestamps of an image folder or video: --data-fps)")
    add_source_args(p, ("--data-fps",))
    p.add_argument("--window", type=int, default=4, help="frames in flight beyond the slowest acknowledgement")
    p.add_argument("--ack-from", default="mapper", help="comma-separated services whose acknowledgements pace playback")
    p.add_argument("--wait-for", default=None,
                   help="services that must be up before the first frame (default: --ack-from)")
    p.add_argument("--start-timeout", type=float, default=60.0,
                   help="seconds to wait for the services of --wait-for; then playback starts anyway")
    p.add_argument("--ack-timeout", type=float, default=15.0,
                   help="seconds without a status after which a consumer no longer paces playback")
    p.add_argument("--stall-timeout", type=float, default=600.0,
                   help="seconds a live consumer's acknowledgement may stay put while frames wait for it; then "
                        "playback ends with an error (exit code 3) (0 = wait forever)")
    p.add_argument("--resend-to", default="",
                   help="comma-separated consumers to which the frames they never handled are sent again (same "
                        "frame numbers) when they restart: from a restarted tracker's last acknowledgement, or a "
                        "mapper's resumed one (not for a live camera)")
    p.add_argument("--start-after", default=None, metavar="SERVICE",
                   help="begin with the frame after the one SERVICE acknowledges when playback starts (a mapper "
                        "resumed from its checkpoint: fmapping up --resume), with the frame numbers of a full run")
    p.add_argument("--loop", action="store_true", help="start over at the end (frame numbers keep increasing)")
    p.add_argument("--paused", action="store_true", help="wait for a 'start' or 'resume' control before playing")
    p.add_argument("--no-gt", action="store_true", help="do not publish ground-truth poses on poses/gt")
    p.add_argument("--no-depth", action="store_true", help="do not send depth even when the dataset has it")
    p.add_argument("--no-end-stop", action="store_true", help="do not send the end-of-sequence stop")
    return add_common_args(p)


RESEND_MAX = 1024  # frames play remembers for --resend-to (more than any window in flight)


class Stalled(RuntimeError):
    """The consumers are alive but their acknowledgement no longer moves (the message says who, where)."""


class Player:
    """The playback loop; ``dataset`` is any :class:`fmapping.datasets.base.Dataset`."""

    def __init__(self, svc: Service, dataset, args):
        self.svc, self.ds, self.args = svc, dataset, args
        self.peers = Peers()
        self.ack_from = names(args.ack_from)
        self.wait_for = names(args.wait_for) if args.wait_for is not None else list(self.ack_from)
        self.paused = threading.Event()
        if args.paused:
            self.paused.set()
        self.reset_requested = threading.Event()
        self.stop_requested = threading.Event()
        self.seq = -1  # last published frame number
        self.floor: dict[str, int] = {}  # per consumer: newest frame sent before it (re)joined
        self.resend_to = names(getattr(args, "resend_to", "") or "")
        self.rewind: Optional[int] = None  # first frame number to send again (a consumer of --resend-to restarted)
        self.sent: dict[int, tuple[int, int]] = {}  # recent frame number -> (dataset index, loop): what to resend
        svc.subscribe_callback(svc.keys.status(), self._on_status)
        svc.subscribe_callback(svc.keys.control, self._on_control)

    # -- callbacks (zenoh threads): small messages, decoded right here
    def _on_status(self, key: str, data: bytes) -> None:
        st = self.svc.decode(data, P.Status, key)
        if st is not None and st.service != self.svc.name:
            old = self.peers.get(st.service)
            if old is None or st.seq < old.seq:
                # first seen, or restarted: frames sent before cannot be acknowledged by it
                self.floor[st.service] = self.seq
                if old is not None:
                    self.svc.counters.inc(f"restarts_{st.service}")
                    if st.service in self.resend_to:
                        self._request_rewind(st, old)
            self.peers.update(st)

    def _on_control(self, key: str, data: bytes) -> None:
        ctl = self.svc.decode(data, P.Control, key)
        if ctl is None or not self.svc.addressed(ctl):
            return
        self.svc.counters.inc(f"control_{ctl.command}")
        if ctl.command == "pause":
            self.paused.set()
        elif ctl.command in ("resume", "start"):
            self.paused.clear()
        elif ctl.command == "stop" and ctl.args.get("reason") != "end":
            self.stop_requested.set()
        elif ctl.command == "reset":
            self.reset_requested.set()
        self.peers.notify()

    def _request_rewind(self, new: P.Status, old: P.Status) -> None:
        """A consumer of ``--resend-to`` restarted: the frames after what it has done (a resumed
        acknowledgement, else the one it had before) go out again, so that it sees them and, e.g.,
        a restarted tracker re-localises next to its last keyframe instead of frames later."""
        start = (new.frame_seq if new.frame_seq >= 0 else old.frame_seq) + 1
        if 0 <= start <= self.seq:
            self.rewind = start if self.rewind is None else min(self.rewind, start)
            self.floor[new.service] = start - 1  # it acknowledges them again
            self.peers.notify()

    def _resend(self) -> None:
        """Send frames ``rewind`` .. ``seq`` again, with their frame numbers (and GT poses)."""
        start, self.rewind = self.rewind, None
        seqs = [s for s in range(start, self.seq + 1) if s in self.sent]
        for s in seqs:
            i, loop = self.sent[s]
            self._publish(self.ds[i], s, loop)
        self.svc.counters.inc("frames_resent", len(seqs))
        self.svc.log.info("a consumer restarted: sent frames %d-%d again", start, self.seq)

    def _publish(self, f, seq: int, loop: int) -> None:
        svc, a = self.svc, self.args
        stamp = float(f.timestamp) + loop * self.period
        msg = P.frame_from_dataset(f, seq=seq, with_depth=not a.no_depth)
        msg.timestamp = stamp
        if f.c2w is not None and not a.no_gt:
            svc.publish(svc.keys.poses("gt"), P.Pose(seq=seq, timestamp=stamp,
                                                     c2w=np.asarray(f.c2w, np.float64), source="gt"))
            svc.counters.inc("gt_poses")
        nbytes = svc.publish(svc.keys.frames, msg)
        svc.counters.inc("bytes_sent", nbytes)

    # -- helpers
    def _halt(self) -> bool:
        return self.svc.shutdown.requested or self.stop_requested.is_set()

    def _live(self, name: str) -> bool:
        return self.peers.age(name) < self.args.ack_timeout

    def _min_ack(self) -> Optional[int]:
        acks = [max(self.peers.acked(n), self.floor.get(n, -1)) for n in self.ack_from if self._live(n)]
        return min(acks) if acks else None

    def wait_for_peers(self) -> bool:
        if not self.wait_for:
            return True
        self.svc.log.info("waiting for %s", ", ".join(self.wait_for))
        ok = self.peers.wait(lambda p: all(p.get(n) is not None for n in self.wait_for) or self._halt(),
                             self.args.start_timeout, self.svc.shutdown.event)
        if not ok or self._halt():
            missing = [n for n in self.wait_for if self.peers.get(n) is None]
            if missing:
                self.svc.log.warning("no status from %s after %.0f s: playing anyway", missing, self.args.start_timeout)
                self.svc.counters.inc("start_timeouts")
        return not self._halt()

    def _flow_control(self) -> None:
        """Block until fewer than ``window`` frames are in flight (or the consumers went silent)."""
        if not self.ack_from:
            return
        window = max(1, int(self.args.window))

        def ready(p: Peers) -> bool:
            m = self._min_ack()
            return m is None or self.seq - m < window or self._halt() or self.paused.is_set() \
                or self.reset_requested.is_set() or self.rewind is not None

        # a consumer whose status is older than --ack-timeout drops out of _min_ack; one alive whose
        # acknowledgement does not move for --stall-timeout ends the run (Stalled)
        before = [n for n in self.ack_from if self._live(n)]
        self._wait_acks(ready)
        gone = [n for n in before if not self._live(n)]
        if gone:
            self.svc.counters.inc("ack_timeouts")
            self.svc.log.warning("no status from %s for %.0f s: no longer waiting for it", gone, self.args.ack_timeout)

    def _wait_acks(self, ready) -> None:
        """Block until ``ready(peers)``; raise :class:`Stalled` when the slowest live consumer's
        acknowledgement has not moved for ``--stall-timeout`` seconds (a long mapping window moves
        it eventually; a consumer that lost frames or hangs never does)."""
        last, since = self._min_ack(), time.monotonic()
        limit = float(getattr(self.args, "stall_timeout", 0) or 0)
        while not self.peers.wait(ready, 1.0, self.svc.shutdown.event):
            if self._halt():
                return
            m = self._min_ack()
            if m != last:
                last, since = m, time.monotonic()
            elif limit > 0 and time.monotonic() - since > limit:
                slow = [n for n in self.ack_from
                        if self._live(n) and max(self.peers.acked(n), self.floor.get(n, -1)) == m]
                raise Stalled(f"no acknowledgement from {', '.join(slow) or '?'} beyond frame {m} for {limit:.0f} s "
                              f"(frames sent up to {self.seq})")

    def _wait_unpaused(self) -> None:
        if self.paused.is_set():
            self.svc.status.update(state="paused")
            while self.paused.is_set() and not self._halt():
                self.peers.wait(lambda p: not self.paused.is_set() or self._halt(), 0.5, self.svc.shutdown.event)
            self.svc.status.update(state="running")

    # -- main loop
    def run(self) -> int:
        svc, ds, a = self.svc, self.ds, self.args
        live = getattr(ds, "live", False)  # a LiveCamera: no length, frames come until ds[i] raises IndexError
        n = None if live else len(ds)
        if n == 0:
            raise ValueError(f"{a.data}: dataset has no frames")
        svc.status.update(state="waiting")
        if n is not None:
            svc.counters.set("frames_total", n)
        if not self.wait_for_peers():
            return 0
        svc.status.update(state="running")
        try:
            return self._play(n, live)
        except Stalled as e:
            svc.counters.inc("stalls")
            svc.status.update(state="error")
            svc.status.error(f"stalled: {e}")
            svc.log.error("the run cannot progress: %s; sending the end-of-sequence stop and giving up", e)
            if not a.no_end_stop:  # the consumers still finish and write what they have
                svc.publish(svc.keys.control, P.Control("stop", {"reason": "end", "last_seq": int(self.seq)}))
            return EXIT_STALLED

    def _play(self, n: Optional[int], live: bool) -> int:
        svc, ds, a = self.svc, self.ds, self.args
        self.period = 0.0
        if live:
            self.resend_to = []  # a live camera cannot go back
        else:
            ts = np.asarray(ds.timestamps, np.float64)
            self.period = float(ts[-1] - ts[0]) + (float(np.median(np.diff(ts))) if n > 1 else 1.0)
        loop, i = self._start_index(n)
        t_start = time.monotonic()
        sent_at_start = 0
        while not self._halt():
            self._wait_unpaused()
            if self._halt():
                break
            if self.rewind is not None:  # a restarted consumer (also at a fixed --fps)
                self._resend()
                continue
            if self.reset_requested.is_set():
                self.reset_requested.clear()
                i, loop = 0, 0
                svc.counters.inc("resets")
                continue
            if n is not None and i >= n:
                if not a.loop:
                    break
                i, loop = 0, loop + 1
            if a.fps and a.fps > 0:
                due = t_start + (self.seq + 1 - sent_at_start) / a.fps
                delay = due - time.monotonic()
                if delay > 0 and self.svc.shutdown.wait(delay):
                    break
                if delay < -1.0:  # fell far behind (slow disk): do not burst to catch up
                    t_start, sent_at_start = time.monotonic(), self.seq + 1
            else:
                self._flow_control()
                if self.rewind is not None:
                    self._resend()
                    continue
                if self._halt() or self.paused.is_set() or self.reset_requested.is_set():
                    continue
            t0 = time.perf_counter()
            try:
                f = ds[i]
            except IndexError:
                if not live:
                    raise
                break  # the camera stopped (or --max-frames reached): end of sequence as for a dataset
            seq = self.seq + 1
            self._publish(f, seq, loop)
            self.seq = seq
            if self.resend_to:
                self.sent[seq] = (i, loop)
                self.sent.pop(seq - RESEND_MAX, None)
            svc.counters.inc("frames_sent")
            svc.counters.set("frame_index", i)
            svc.counters.set("load_ms", round((time.perf_counter() - t0) * 1e3, 2))
            m = self._min_ack()
            svc.status.update(frame_seq=seq, lag=float(seq - m) if m is not None else 0.0)
            i += 1
        return self._finish()

    def _start_index(self, n: Optional[int]) -> tuple[int, int]:
        """(loop, dataset index) of the first frame: 0, 0, or with ``--start-after S`` the frame after S's
        acknowledgement (whose number it keeps: ``seq`` goes on from there)."""
        name = getattr(self.args, "start_after", None)
        ack = self.peers.acked(name) if name else -1
        if ack < 0 or n is None:
            return 0, 0
        self.seq = ack
        self.svc.counters.set("started_after", ack)
        self.svc.log.info("%s has frames up to %d: starting with frame %d", name, ack, ack + 1)
        loop, i = divmod(ack + 1, n)
        return (0, n) if loop and not self.args.loop else (loop, i)  # all played: straight to the end

    def _finish(self) -> int:
        svc, a = self.svc, self.args
        if self.svc.shutdown.requested or self.stop_requested.is_set():
            svc.log.info("stopped after %d frames", self.seq + 1)
            return 0
        if self.ack_from and self.seq >= 0:
            svc.status.update(state="finishing")
            done = lambda p: self._min_ack() is None or self._min_ack() >= self.seq or self._halt()  # noqa: E731
            while True:  # a consumer restarting now still gets the frames it never handled
                self._wait_acks(lambda p: done(p) or self.rewind is not None)
                if self.rewind is None or self._halt():
                    break
                self._resend()
        if not a.no_end_stop:
            svc.publish(svc.keys.control, P.Control("stop", {"reason": "end", "last_seq": int(self.seq)}))
        svc.log.info("end of sequence: %d frames sent", self.seq + 1)
        return 0


def open_source(args):
    """The source of ``--data`` as play reads it (``--camera``, ``--max-frames``, ``--data-fps``,
    ``--topic``); live=True: ``camera:N`` streams a webcam (a LiveCamera, read in order, no length)."""
    from fmapping.datasets import open_dataset

    return open_dataset(args.data, camera=args.camera, max_frames=args.max_frames, live=True,
                        **source_options(args))


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m services.io play``."""
    return add_args(service_parser("services.io play", __doc__))


def main(argv=None, session=None, keys=None, dataset=None) -> int:
    from services.process import setup_logging

    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, "play")
    if dataset is None:
        dataset = open_source(args)
    if getattr(dataset, "live", False) and args.loop:
        raise SystemExit(f"--loop: {args.data} is a live camera, it cannot start over")
    with Service("play", args, session=session, keys=keys) as svc:
        svc.start_heartbeat()
        return Player(svc, dataset, args).run()
