"""``python -m services.mapper``: the mapping process (zenoh shell around :class:`services.mapper.core.MapperCore`).

Subscribes to ``frames``, ``poses/<source>`` and ``control``; publishes ``map/field`` after
every mapper update, ``map/points`` at a bounded rate, ``poses/mapper`` (refined window
poses) and ``status/mapper``; answers ``map/latest`` with the newest FieldSnapshot.
Resumes from ``--checkpoint`` (default OUT/checkpoint.pt) when present.

On the end-of-sequence stop it runs the mapper's closing stage, writes OUT/map.ply,
OUT/mesh.ply, OUT/traj.txt, OUT/stats.json, publishes the final snapshots and exits.
On SIGINT / SIGTERM it skips the closing optimisation and writes the same files from the
current map (and a checkpoint) before exiting.
"""
from __future__ import annotations

import argparse
import logging
import time

from fmapping import protocol as P
from fmapping.cancel import Cancelled
from fmapping.runtime import preload_optimiser
from services.core_support import MIB
from services.mapper.core import (
    POSE_SOURCES, MapperCore, MapperServiceOptions, await_source_final, load_mapper_config,
)
from services.mapper.intake import FRAME_BYTES, FRAME_CAPACITY, book_for, frame_rank, inbox_frames_ok, inbox_mib_ok
from services.process import (FirstMessage, add_first_message_arg, add_stream_camera_arg, available_cpus, run_main,
                              runs_idle, service_parser, set_torch_threads, setup_logging, stream_camera)
from services.transport import Service
from services.zenoh_session import add_common_args


def build_parser() -> argparse.ArgumentParser:
    p = service_parser("services.mapper", __doc__)
    p.add_argument("--poses", default="gt", choices=POSE_SOURCES, help="pose source: key poses/<source>")
    p.add_argument("--config", default=None, help="YAML overrides of the mapper config (fmapping.mapping.MapperConfig)")
    p.add_argument("--field", default=None, choices=["cp", "vm", "mlp", "grid"],
                   help="field type (default: the config's field.kind, cp)")
    p.add_argument("--out", default=None,
                   help="output folder for map.ply, mesh.ply, traj.txt, stats.json, checkpoint.pt")
    p.add_argument("--checkpoint", default=None, help="checkpoint file (default OUT/checkpoint.pt)")
    p.add_argument("--checkpoint-every", type=int, default=1, help="windows between checkpoints (0 = never)")
    p.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--keep-checkpoint", action="store_true", help="keep the checkpoint after a completed run")
    p.add_argument("--points-interval", type=float, default=2.0, help="min seconds between map point snapshots")
    p.add_argument("--max-points", type=int, default=100_000, help="points per snapshot")
    p.add_argument("--unposed-init", choices=["auto", "yes", "no"], default="auto",
                   help="accept frames without a pose before the map exists; the mapper then optimises its init "
                        "poses (auto: no; yes for the tracker's map front end, which tracks only once a map exists)")
    p.add_argument("--pose-timeout", type=float, default=30.0,
                   help="seconds a frame waits for its pose before it is skipped (0 = forever)")
    p.add_argument("--anchor", default=None,
                   help="pose source fixing the first --anchor-frames frames (scale) of an unposed init "
                        "(default: gt with --unposed-init yes, none otherwise; '' for none)")
    p.add_argument("--anchor-frames", type=int, default=2, help="frames of an unposed init that --anchor fixes")
    p.add_argument("--no-mesh", action="store_true", help="skip mesh.ply at the end (map.ply is still written)")
    p.add_argument("--mesh-resolution", type=int, default=96, help="marching-cubes grid per axis")
    p.add_argument("--resent-frames", action="store_true",
                   help="the player sends a restarted pose source the frames it never handled again (io play "
                        "--resend-to): frames waiting for a pose wait for its answers (else skipped at once)")
    p.add_argument("--keyframes", default="auto", choices=["auto", "source", "motion"],
                   help="which frames are keyframes (kept when the mapper falls behind): source = the pose "
                        "source's flag, motion = every --keyframe-every frames or 5 cm / 5 deg of camera motion; "
                        "auto = source for the tracker, motion for gt / external poses")
    p.add_argument("--keyframe-every", type=int, default=5, help="motion keyframes: at least every this many frames")
    p.add_argument("--behind-frames", type=int, default=10,
                   help="frames waiting beyond which the mapper maps keyframes only and windows take more frames "
                        "(0 = never: paced playback)")
    p.add_argument("--stream-idle", type=float, default=2.0,
                   help="... while frames keep coming: once none has arrived for this many seconds (the stream "
                        "ended or paused), every posed frame waiting is mapped")
    p.add_argument("--source-final-timeout", type=float, default=10.0,
                   help="at the stop, wait at most this long for the pose source's last poses (a tracker's final "
                        "bundle adjustment) before the closing refinement (a source without a status: no wait)")
    p.add_argument("--inbox-frames", type=int, default=FRAME_CAPACITY,
                   help=f"frames the inbox holds at most (default {FRAME_CAPACITY}); when full, non-keyframes go first")
    p.add_argument("--inbox-mb", type=float, default=FRAME_BYTES / MIB,
                   help=f"MiB of frames the inbox holds at most (default {FRAME_BYTES // MIB})")
    p.add_argument("--device", default=None, help="torch device (default: the config's, 'auto')")
    p.add_argument("--threads", type=int, default=0,
                   help="torch threads (0 = auto: half the CPUs this process may use, at least 1; under the "
                        "SCHED_IDLE policy, as fmapping up starts it, all of them for the closing stage)")
    p.add_argument("--linger", action="store_true", help="after the end, keep answering map/latest until SIGTERM")
    add_first_message_arg(p, "frame")
    add_stream_camera_arg(p)
    return add_common_args(p)


# inbox bounds per channel, items and bytes (the stop queue "end" comes first, see services.transport):
# at most ~394 MiB queued, whatever arrives; the frames' ceiling and eviction order: services.mapper.intake
CAPACITIES = {"end": 8, "control": 64, "status": 16, "poses": 8192, "frames": FRAME_CAPACITY}
MAX_BYTES = {"end": 1 * MIB, "control": 1 * MIB, "status": 1 * MIB, "poses": 8 * MIB, "frames": FRAME_BYTES}


def main(argv=None, session=None, keys=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not (inbox_frames_ok(args.inbox_frames) and inbox_mib_ok(args.inbox_mb)):
        parser.error(f"--inbox-frames must be >= 1 and --inbox-mb > 0 and finite (got {args.inbox_frames}, "
                     f"{args.inbox_mb})")
    setup_logging(args.log_level, "mapper")
    threads = set_torch_threads(args.threads, auto=available_cpus() // 2)
    log = logging.getLogger("fmapping.mapper")
    log.info("torch threads: %d", threads)
    # before the service has a status (play waits for it): the first optimiser's imports, not in the init
    log.info("torch optimiser preloaded in %.2f s", preload_optimiser())
    overrides = {"field": {"kind": args.field}} if args.field else None
    cfg = load_mapper_config(args.config, overrides)
    if args.device:
        cfg.device = args.device
    opts = MapperServiceOptions(
        pose_source=args.poses, out=args.out, checkpoint=args.checkpoint, checkpoint_every=args.checkpoint_every,
        resume=not args.no_resume, keep_checkpoint=args.keep_checkpoint,
        unposed_init=None if args.unposed_init == "auto" else args.unposed_init == "yes",
        points_interval=args.points_interval, max_points=args.max_points, write_mesh=not args.no_mesh,
        mesh_resolution=args.mesh_resolution,
        anchor_source=args.anchor, anchor_frames=args.anchor_frames, pose_timeout=args.pose_timeout,
        resent_frames=args.resent_frames, keyframes=args.keyframes, keyframe_every=args.keyframe_every,
        behind_frames=args.behind_frames, stream_idle_s=args.stream_idle,
    ).validate()
    # frames: when full, known non-keyframes go first, then frames without a pose yet, thinned evenly
    book = book_for(opts)
    capacities = dict(CAPACITIES, frames=args.inbox_frames)
    max_bytes = dict(MAX_BYTES, frames=int(args.inbox_mb * MIB))
    with Service("mapper", args, capacities=capacities, max_bytes=max_bytes, session=session,
                 keys=keys, thin=("frames",), rank={"frames": frame_rank(book)}) as svc:
        return serve(svc, cfg, opts, args, book)


def serve(svc: Service, cfg, opts: MapperServiceOptions, args, book=None) -> int:
    # a stop request (signal, parent gone) cancels a long update between two iterations
    core = MapperCore(cfg, opts, counters=svc.counters, on_bad_input=svc.report_bad_input,
                      should_stop=lambda: svc.shutdown.requested, book=book)
    core.backlog = lambda: svc.inbox.size("frames")
    core.stream_idle = lambda: svc.inbox.idle("frames")
    core.expected_camera = stream_camera(args, svc.log)
    # under SCHED_IDLE (fmapping up) the mapper runs on what the camera's path leaves. While the stream runs that is
    # about one core here: a second torch thread, starved by the tracker, held the first at every parallel loop
    # (1,000 frames at 30 fps: init 32.7 s). Once the stream has ended the cores are free and the closing stage takes
    # them all (200 frames at 30 fps, 4 alternated pairs with 2 threads throughout: the run ended 98-112 -> 82-92 s
    # after playback; bench/results/sched_idle_2026-12-07/)
    closing_threads = available_cpus() if getattr(args, "threads", 1) == 0 and runs_idle() else 0
    if opts.resume and core.load_checkpoint():
        svc.log.info("resumed from %s at frame %d (field version %d)", core.resumed_from, core.ack, core.version)
    keys = svc.keys
    # checked before queueing: a bad or implausible message never displaces a real one
    svc.subscribe_control()
    svc.subscribe(keys.poses(opts.pose_source), "poses", admit=lambda k, d: core.admit_pose(d, k))
    if opts.anchor_source:
        svc.subscribe(keys.poses(opts.anchor_source), "poses", admit=lambda k, d: core.admit("poses", d, k))
    svc.subscribe(keys.frames, "frames", admit=lambda k, d: core.admit("frames", d, k))
    if opts.pose_source != "gt":  # a restarted tracker / producer: skip the frames it will never answer
        svc.subscribe(keys.status(opts.pose_source), "status", admit=lambda k, d: svc.decode(d, P.Status, k))
    svc.queryable(keys.latest, lambda: core.latest_field_bytes)
    channels = {"field": keys.field, "points": keys.points}

    def publish(outputs) -> None:
        for channel, msg in outputs:
            key = keys.poses("mapper") if channel == "poses" else channels[channel]
            svc.publish(key, msg)

    def report(state=None) -> None:
        svc.report_core(core, state, lag=core.lag)
        svc.counters.set("queued_frames", svc.inbox.size("frames"))

    # torch.optim imports torch._dynamo on first use (0.9 s here, seconds on a busy machine):
    # pay for it now rather than inside the first update, where a stop request would wait for it
    import torch._dynamo  # noqa: F401

    report("running")
    svc.start()
    if core.latest_field is not None:
        publish([("field", core.latest_field)])
    interrupted = False
    code = 0
    first = FirstMessage(args.first_message_timeout, f"frame on {keys.frames}")
    if core.ack >= 0:
        first.see()  # resumed: frames came before
    while not svc.shutdown.requested and not core.finished:
        item = svc.inbox.get(timeout=0.1)
        if item is None and first.expired():
            code = svc.give_up(first.message())  # the outputs are still written below
            break
        try:
            if item is not None:
                channel, (key, msg) = item  # decoded and checked already (admit)
                if channel == "frames":
                    first.see()
                if channel in ("end", "control") and msg.command == "stop":
                    report("finishing")
                    svc.publish_status()
                    # the stream's end or a stop to all: the source stops too and sends its last poses first
                    to_all = msg.args.get("target") in (None, "", "all")
                    if to_all and not await_source_final(svc.inbox.get, core, publish, args.source_final_timeout,
                                                         should_stop=lambda: svc.shutdown.requested) \
                            and not svc.shutdown.requested:
                        svc.log.warning("the pose source (%s) did not report done within %.0f s of the stop: "
                                        "closing with the poses at hand", opts.pose_source, args.source_final_timeout)
                    if closing_threads and not svc.shutdown.requested:
                        svc.log.info("closing stage: torch threads %d", set_torch_threads(closing_threads, 1))
                publish(core.on_source_status(msg) if channel == "status" else core.apply(msg))
            publish(core.tick())
        except Cancelled:
            interrupted = core.interrupted = True
            break
        except Exception as e:  # a library failure: report it, keep serving
            svc.counters.inc("errors")
            svc.status.error(f"{type(e).__name__}: {e}")
            svc.log.exception("mapper step failed")
        report("paused" if core.paused else None)
    if not core.finished or interrupted:  # SIGINT / SIGTERM: no closing optimisation, but keep the work
        report("finishing")
        try:
            if interrupted:  # aborted inside an update: the last checkpoint is the consistent state
                svc.log.info("%s during an update: writing the current map (checkpoint kept from the last window)",
                             svc.shutdown.reason)
            else:
                svc.log.info("%s: writing the current map and a checkpoint", svc.shutdown.reason or "stopping")
                core.save_checkpoint()
            if core.out is not None:
                t0 = time.perf_counter()
                core.write_outputs(final=False, quick=True)
                svc.log.info("wrote the current map in %.2f s", time.perf_counter() - t0)
        except Exception as e:
            svc.status.error(f"{type(e).__name__}: {e}")
            svc.log.exception("writing outputs failed")
    report()
    svc.log.info("done: %d frames mapped, field version %d, %s", len(core.seq_of_fid), core.version,
                 f"outputs in {core.out}" if core.out else "no --out")
    if args.linger and core.finished:
        while not svc.shutdown.wait(0.5):
            pass
    return code


if __name__ == "__main__":
    run_main(main, "services.mapper")
