"""``python -m services.tracker``: the tracking process (zenoh shell around :class:`services.tracker.core.TrackerCore`).

Subscribes to ``frames``, ``map/field``, ``poses/mapper``, ``control`` and (front end
``mono``) the anchor poses ``poses/<anchor>``; publishes ``poses/tracker`` and
``status/tracker``. On start it asks ``map/latest`` for the newest field snapshot (late
joiners and restarts continue from the current map).
"""
from __future__ import annotations

import argparse
import logging

from fmapping.runtime import limit_blas_threads, retain_freed_memory, single_malloc_arena
from services.core_support import MIB
from services.process import (FirstMessage, add_first_message_arg, add_stream_camera_arg, run_main, service_parser,
                              set_torch_threads, setup_logging, stream_camera)
from services.tracker.core import TrackerCore, TrackerServiceOptions, load_tracker_config
from services.transport import Service
from services.zenoh_session import add_common_args, query_latest


def build_parser() -> argparse.ArgumentParser:
    p = service_parser("services.tracker", __doc__)
    p.add_argument("--config", default=None,
                   help="YAML overrides of the tracker config (fmapping.tracking TrackerConfig)")
    p.add_argument("--use-depth", action="store_true", help="reference depth from the sensor when frames carry it")
    p.add_argument("--max-buffer", type=int, default=64, help="frames waiting for a map")
    p.add_argument("--skip-behind", type=int, default=1,
                   help="mono: skip (answer with quality 0) a frame when this many newer ones wait, never two in a "
                        "row, so that the poses keep pace with the camera (0 = never skip)")
    p.add_argument("--stream-idle", type=float, default=2.0,
                   help="mono: ... while frames keep coming: once none has arrived for this many seconds (the "
                        "stream ended or paused), every frame waiting is tracked")
    p.add_argument("--interpolate-skipped", default="on", choices=["on", "off"],
                   help="mono: a frame skipped to keep pace gets the pose between its tracked neighbours', published "
                        "with the next frame's (off: answered at once with quality 0, no pose)")
    p.add_argument("--ba-thread", default="on", choices=["on", "off"],
                   help="mono: keyframe bundle adjustment and loop search in worker threads, merged between frames, "
                        "and a keyframe's own work after its pose went out, so that a keyframe does not hold up "
                        "its pose (off: on the frame path, as fmapping slam)")
    p.add_argument("--frame-pose", default="pnp", choices=["pnp", "direct"],
                   help="mono: a frame's pose from its KLT-tracked landmarks (PnP), checked photometrically, the "
                        "direct alignment only for the frames that fail that (20-30 %% less time a frame); direct: "
                        "every frame aligned photometrically first, as fmapping slam")
    p.add_argument("--frontend", default="mono", choices=["mono", "map"],
                   help="mono: RGB-only front end from frame 0 (as fmapping slam); map: track against the "
                        "mapper's field (frames wait for the first map)")
    p.add_argument("--anchor", default="gt",
                   help="pose source fixing world frame and scale of the mono bootstrap ('' for none)")
    p.add_argument("--state", default=None,
                   help="mono: file where the current keyframe is kept; a tracker (re)started with one "
                        "re-localises against it and goes on in the same world frame and scale")
    p.add_argument("--query-timeout", type=float, default=2.0, help="seconds to wait for map/latest at start")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0 = auto: 1; its tensors are small)")
    add_first_message_arg(p, "frame")
    add_stream_camera_arg(p)
    return add_common_args(p)


# inbox bounds per channel, items and bytes (the stop queue "end" comes first, see services.transport):
# at most ~426 MiB queued; the field channel holds one snapshot of the largest size the protocol allows
CAPACITIES = {"end": 8, "control": 64, "field": 2, "poses": 8192, "frames": 64}
MAX_BYTES = {"end": 1 * MIB, "control": 1 * MIB, "field": 160 * MIB, "poses": 8 * MIB, "frames": 256 * MIB}


def main(argv=None, session=None, keys=None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, "tracker")
    threads = set_torch_threads(args.threads, auto=1)
    logging.getLogger("fmapping.tracker").info("torch threads: %d", threads)
    retain_freed_memory()  # the numpy bundle adjustment: reuse freed temporaries, and one BLAS thread next
    limit_blas_threads(1)  # to the other services on the same cores (fmapping.runtime)
    single_malloc_arena()  # before zenoh's threads: one heap, not one retained peak per thread
    cfg = load_tracker_config(args.config)
    opts = TrackerServiceOptions(max_buffer=args.max_buffer, use_depth=args.use_depth, frontend=args.frontend,
                                 anchor_source=args.anchor, state_path=args.state,
                                 skip_behind=args.skip_behind, stream_idle_s=args.stream_idle,
                                 interpolate_skipped=args.interpolate_skipped == "on",
                                 ba_thread=args.ba_thread == "on", frame_pose=args.frame_pose).validate()
    # frames thinned evenly when the inbox is full (a long gap loses the track; evenly spread gaps do not)
    with Service("tracker", args, capacities=CAPACITIES, max_bytes=MAX_BYTES, session=session, keys=keys,
                 thin=("frames",)) as svc:
        return serve(svc, cfg, opts, args)


def serve(svc: Service, cfg, opts: TrackerServiceOptions, args) -> int:
    core = TrackerCore(cfg, opts, counters=svc.counters, on_bad_input=svc.report_bad_input)
    core.backlog = lambda: svc.inbox.size("frames")
    core.stream_idle = lambda: svc.inbox.idle("frames")
    core.expected_camera = stream_camera(args, svc.log)
    keys = svc.keys
    # checked before queueing: a bad or implausible message never displaces a real one
    svc.subscribe_control()
    svc.subscribe(keys.field, "field", admit=lambda k, d: core.admit("field", d, k))
    svc.subscribe(keys.poses("mapper"), "poses", admit=lambda k, d: core.admit("poses", d, k))
    if opts.frontend == "mono" and opts.anchor_source:
        svc.subscribe(keys.poses(opts.anchor_source), "poses", admit=lambda k, d: core.admit("poses", d, k))
    svc.subscribe(keys.frames, "frames", admit=lambda k, d: core.admit("frames", d, k))
    svc.start()
    latest = query_latest(svc.session, keys.latest, timeout=args.query_timeout)
    if latest is not None:
        core.handle("field", latest, keys.latest)
        svc.log.info("synced to map version %d (frame %d) from %s", core.version, core.map_seq, keys.latest)
    try:
        return _loop(svc, core, args)
    finally:
        core.close()  # the saved keyframes written


def _loop(svc: Service, core, args) -> int:
    keys = svc.keys
    stop = False
    first = FirstMessage(args.first_message_timeout, f"frame on {keys.frames}")
    while not svc.shutdown.requested and not stop:
        item = svc.inbox.get(timeout=0.1)
        if item is None:
            if first.expired():
                return svc.give_up(first.message())
            continue
        channel, (key, msg) = item  # decoded and checked already (admit)
        if channel == "frames":
            first.see()
        try:
            if channel in ("end", "control") and msg.command == "stop":
                stop = True  # what the stop releases (held poses, a last bundle adjustment's) still goes out
            for _, pose in core.apply(msg):
                svc.publish(keys.poses("tracker"), pose)
            for _, pose in core.finish_frame():  # a new keyframe's work, after its pose went out
                svc.publish(keys.poses("tracker"), pose)
        except Exception as e:  # a library failure: report it, keep serving
            svc.counters.inc("errors")
            svc.status.error(f"{type(e).__name__}: {e}")
            svc.log.exception("tracker step failed")
        svc.report_core(core)
    return 0


if __name__ == "__main__":
    run_main(main, "services.tracker")
