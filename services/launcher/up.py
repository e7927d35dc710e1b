"""``fmapping up``: the run itself (:func:`run_up`): check the inputs, then start the router and the
services (at once in a secure run, in order in the open mesh; :mod:`services.launcher.commands` writes their
command lines), supervise them (:mod:`services.launcher.supervise`) and add the run's dataset and config to
OUT/stats.json.
See :mod:`services.launcher` for the whole story."""
from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Optional

import yaml

from fmapping.cli import source_options
from fmapping.config import read_yaml_mapping
from fmapping.up_config import (LauncherOptions, UpConfig, mapper_defaults, split_config, tracker_defaults,
                                up_config_dict)
from services.launcher.commands import (EXTERNAL_SOURCE, MONO_BOOTSTRAP_WINDOW, live_url, parser_of, play_sends_depth,
                                        play_source, play_wait_for, resend_to, service_command, tracker_state,
                                        view_argv, view_mode)
from services.launcher.resume import keep_logs, resume_args, save_run_args, start_over
from services.launcher.supervise import IDLE, Proc, linger, monitor, stop_all, wait_ready, write_summary
from services.process import command_line, live_stream_camera
from services.zenoh_session import free_port


def run_info(data, poses: str, mapper_cfg: Optional[Path], tracker_cfg: Optional[Path],
             opts: LauncherOptions, camera: Optional[str] = None, source: Optional[dict] = None) -> dict:
    """What the launcher adds to the mapper's OUT/stats.json, as ``fmapping map`` records them: the
    dataset (intrinsics, depth scale, as ``io play`` opens it) and the config every service runs with.
    A live camera (``camera:N``) is not opened here: play opens it, and a webcam may take one reader only;
    its intrinsics are the ``--camera`` given. ``source``: :func:`fmapping.cli.source_options` (fps, topic)."""
    from fmapping.config import load_config
    from fmapping.datasets import open_dataset
    from fmapping.datasets.live import is_live_spec

    resolved = UpConfig(mapper=load_config(mapper_defaults(), mapper_cfg),
                        tracker=load_config(tracker_defaults(), tracker_cfg), launcher=opts)
    if is_live_spec(data):
        dataset = {"root": data, "kind": "camera", "live": True, "frames": None, "camera_source": camera}
    else:
        dataset = open_dataset(data, camera=camera, **(source or {})).describe()
    return {"dataset": dataset, "poses": poses, "config": up_config_dict(resolved)}


def up_data(args, out: Path, opts: LauncherOptions):
    """The source ``fmapping up`` plays: ``--data`` (a path that must exist, or ``camera:N`` with
    ``--camera``), else the generated synthetic scene. A path is a Path, a live camera its string."""
    from fmapping.datasets.live import is_live_spec, live_index

    if args.data and is_live_spec(args.data):
        if live_index(args.data) is None:
            raise ValueError(f"--data {args.data}: a live camera is camera:N, N the device number (camera:0)")
        if not getattr(args, "camera", None):
            raise ValueError(f"--data {args.data}: a live camera has no intrinsics of its own: give "
                             "--camera fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] or --camera path/to/camera.yaml")
        return args.data
    data = Path(args.data) if args.data else make_scene(out, opts)
    if not data.exists():
        raise FileNotFoundError(f"dataset folder not found: {data}")
    return data


def add_run_info(out: Path, info: dict, since: float) -> bool:
    """Merge ``info`` into OUT/stats.json when the mapper wrote it in this run (modified at or after
    ``since``, a ``time.time()``; a file left by an earlier run in OUT is not touched). False when
    there is none."""
    from fmapping.fileio import write_json

    path = out / "stats.json"
    try:
        if path.stat().st_mtime < since - 2.0:  # 2 s: file systems with coarse timestamps
            return False
        stats = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    if not isinstance(stats, dict):
        return False
    stats.update(info)
    write_json(path, stats)
    return True


def make_scene(out: Path, opts: LauncherOptions) -> Path:
    """Generate (or reuse) the synthetic scene OUT/scene."""
    scene = out / "scene"
    meta = scene / "scene.json"
    if meta.is_file():
        try:
            info = json.loads(meta.read_text())
            if (info.get("frames") == opts.frames and list(info.get("size", [])) == list(opts.size)
                    and info.get("seed") == opts.seed):
                print(f"fmapping up: reusing the synthetic scene in {scene}", flush=True)
                return scene
        except (OSError, ValueError):
            pass
    from fmapping.synthetic import generate_scene

    print(f"fmapping up: generating a synthetic scene ({opts.frames} frames, {opts.size[0]}x{opts.size[1]}, "
          f"seed {opts.seed}) in {scene}", flush=True)
    generate_scene(scene, seed=opts.seed, frames=opts.frames, size=tuple(opts.size))
    return scene


def mapper_inbox(opts: LauncherOptions) -> dict:
    """The mapper's inbox bounds of ``launcher.mapper_inbox_frames`` / ``mapper_inbox_mb`` as its options
    (unset: left to the service's defaults), checked before any process starts."""
    from services.mapper.intake import inbox_frames_ok, inbox_mib_ok

    frames, mb = opts.mapper_inbox_frames, opts.mapper_inbox_mb
    if frames is not None and not inbox_frames_ok(frames):
        raise ValueError(f"launcher.mapper_inbox_frames must be an integer >= 1, got {frames!r}")
    if mb is not None and not inbox_mib_ok(mb):
        raise ValueError(f"launcher.mapper_inbox_mb must be a number > 0 and finite (MiB), got {mb!r}")
    return {"inbox_frames": frames, "inbox_mb": None if mb is None else float(mb)}


def with_user_box(mapper_cfg: Optional[Path], bbox: Optional[list], out: Path) -> Optional[Path]:
    """Mapper YAML (written under OUT/config) = the user's mapper section + the ``--bbox`` they gave;
    unchanged without one. Otherwise the mapper bounds the scene itself, from the points it
    triangulates, and grows the box as the camera explores (nothing else of the dataset is read)."""
    if bbox is None:
        return mapper_cfg
    overrides = read_yaml_mapping(mapper_cfg) if mapper_cfg else {}
    path = out / "config" / "mapper.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump({**overrides, "bbox": [list(map(float, bbox[0])), list(map(float, bbox[1]))]},
                                   sort_keys=False))
    print(f"fmapping up: mapper box {bbox} (--bbox)", flush=True)
    return path


def run_up(args) -> int:
    """Run the system (see :mod:`services.launcher`); returns the exit code."""
    if isinstance(getattr(args, "resume", None), str):  # fmapping up --resume OUT
        args = resume_args(args.resume)
    resuming = getattr(args, "resume", None) is True
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mapper_cfg, tracker_cfg, opts = split_config(getattr(args, "config", None), out)
    poses = args.poses
    if poses not in ("tracker", "gt", "external"):
        raise ValueError(f"--poses must be tracker, gt or external, got {poses!r}")
    data = up_data(args, out, opts)
    camera = getattr(args, "camera", None)
    timeout = getattr(args, "timeout", None) or opts.timeout
    ns = getattr(args, "ns", None) or f"up{os.getpid()}"
    mesh: list[str] = []  # endpoints of the processes started so far
    # optional: endpoints every service also connects to, e.g. a monitoring session in the open mesh; a secure
    # run's observer is args.observe(monitor config path, ns) instead, called once the router is up
    extra_connect = [str(e) for e in (getattr(args, "connect_extra", None) or [])]
    # secure by default: per-run credentials, a router with access control (services.credentials);
    # a monitoring session joining the mesh (connect_extra) needs the old open mesh
    insecure = bool(getattr(args, "insecure", False)) or bool(extra_connect)
    creds = None  # services.credentials.RunCredentials of a secure run, made once the inputs are checked

    def net(role: str) -> dict:
        """The network options of ``role``. Secure: its client config (its credentials, the run's router).
        --insecure: listen on a fresh loopback port and connect to every process started before (explicit mesh)."""
        idle = {"sched_idle": role in IDLE}  # once started, it runs on the CPU time nothing else wants
        if creds is not None:
            return {"zenoh_config": str(creds.config(role)), "ns": ns, **idle}
        ep = f"tcp/127.0.0.1:{free_port()}"
        peers = extra_connect + mesh
        mesh.append(ep)
        return {"listen": ep, "ns": ns, "connect": ",".join(peers) if peers else None, **idle}
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PYTHONUNBUFFERED", "1")
    threads = opts.threads or None  # 0: each service's own default

    if opts.tracker_frontend not in ("mono", "map"):
        raise ValueError(f"launcher.tracker_frontend must be 'mono' or 'map', got {opts.tracker_frontend!r}")
    inbox = mapper_inbox(opts)
    mono = poses == "tracker" and opts.tracker_frontend == "mono"
    live = isinstance(data, str)  # up_data: a live camera is its camera:N string, a dataset a Path
    # paced playback (a dataset at --fps 0): the player waits for the mapper, so nobody is behind the camera:
    # the tracker tracks every frame and the mapper maps every frame (no keeping pace, no catching up)
    paced = not live and not (getattr(args, "fps", None) or 0)
    mapper_cfg = with_user_box(mapper_cfg, getattr(args, "bbox", None), out)
    # errors in data or configs: before any process
    info = run_info(data, poses, mapper_cfg, tracker_cfg, opts, camera, source_options(args))
    # the camera play's frames carry (the data's, as play opens it): the mapper and the tracker refuse a first frame
    # with another one, so that a peer gone wrong cannot fix the stream's camera before play's first frame (a live
    # camera: the intrinsics of its --camera string, the size being the device's)
    stream_camera = live_stream_camera(camera) if live else json.dumps(info["dataset"]["camera"])
    started = time.time()
    if resuming:
        print(f"fmapping up: resuming the run in {out}: the mapper from its checkpoint, play from the first frame "
              f"it had not mapped (the earlier part's logs: {keep_logs(out)})", flush=True)
    else:
        start_over(out)
        save_run_args(args, out)
    if not insecure:
        from services.credentials import make_run_credentials

        creds = make_run_credentials(out / "secrets", f"tcp/127.0.0.1:{free_port()}", ns)
    # the services give up on their first message after a while (default 900 s); play waits up to an
    # hour for an external producer, so they wait longer then
    first_wait = "4500" if poses == "external" else None
    mapper_argv = service_command(
        "services.mapper", poses=poses, out=str(out), **net("mapper"), threads=threads,
        first_message_timeout=first_wait, stream_camera=stream_camera,
        # the map tracker tracks only once the mapper has a map
        unposed_init="yes" if poses == "tracker" and not mono else None,
        resent_frames=poses == "tracker" and not live,  # play sends a restarted tracker what it missed (resend_to)
        behind_frames=0 if paced else None,
        **inbox,
        config=str(mapper_cfg) if mapper_cfg else None)
    record_src = poses
    procs: dict[str, Proc] = {}
    errors: list[str] = []  # why the run failed (the first reason), for OUT/up.json
    infra: dict[str, Proc] = {}  # the router of a secure run: started first, stopped last
    t0 = time.monotonic()
    old_handlers = {}

    def on_signal(signum, frame):
        raise KeyboardInterrupt

    if threading_main():  # explicit: SIGINT may be ignored when started in the background
        for sig in (signal.SIGINT, signal.SIGTERM):
            old_handlers[sig] = signal.signal(sig, on_signal)
    try:
        for attempt in range(3 if creds is not None else 0):
            router_argv = service_command("services.router", zenoh_config=str(creds.router_config))
            infra["router"] = Proc("router", router_argv, out, env)
            try:
                wait_ready([infra["router"]], opts.start_timeout)
                break
            except RuntimeError:  # the free port was taken before the router bound it: another port
                if attempt == 2:
                    raise
                infra.pop("router").close()
                creds = make_run_credentials(out / "secrets", f"tcp/127.0.0.1:{free_port()}", ns)
        if creds is not None:
            print(f"fmapping up: secure run: router on {creds.endpoint}, per-run credentials in {creds.folder} "
                  "(mode 0600), access control by role (--insecure: the open loopback mesh)", flush=True)
            observe = getattr(args, "observe", None)
            if observe is not None:  # an observer in this process (bench/system.py): before any service starts
                observe(creds.config("monitor"), ns)
        procs["mapper"] = Proc("mapper", mapper_argv, out, env)
        if creds is None:  # the open mesh: the services started later connect to the mapper's listening port
            wait_ready([procs["mapper"]], opts.start_timeout)
        # a secure run: every service connects to the router alone, so they all start at once, play too (start-up
        # is mostly imports, which then overlap on the cores); play sends its first frame once each has a status
        record_argv = service_command("services.io record", out=str(out / "record"), source=record_src,
                                      append=resuming, **net("record"), first_message_timeout=first_wait)
        procs["record"] = Proc("record", record_argv, out, env)
        later = [procs["mapper"], procs["record"]]
        view = view_mode(getattr(args, "view", None)) if opts.view else ""
        if view:
            uses_depth = bool(info["config"]["mapper"].get("use_depth"))
            procs["view"] = Proc("view", service_command("services.io view") + view_argv(out, view, args, uses_depth)
                                 + command_line(parser_of("services.io view"), **net("view")), out, env)
            later.append(procs["view"])
        if poses == "tracker":
            targv = service_command(
                "services.tracker", frontend=opts.tracker_frontend, **net("tracker"), threads=threads,
                stream_camera=stream_camera,
                # a restarted tracker re-localises against its last keyframe (same world frame and scale)
                state=str(tracker_state(out)) if mono else None, skip_behind=0 if paced else None,
                # paced: the poses of fmapping slam, run for run
                ba_thread="off" if paced else None, frame_pose="direct" if paced else None,
                config=str(tracker_cfg) if tracker_cfg else None)
            procs["tracker"] = Proc("tracker", targv, out, env)
            later.append(procs["tracker"])
        if creds is None:  # the open mesh: play connects to each of them
            wait_ready(later, opts.start_timeout)
        wait_for = play_wait_for(poses, opts.view)
        play_start_timeout = opts.start_timeout
        if poses == "external":
            play_start_timeout = 3600.0
            print("fmapping up: waiting for an external pose producer, e.g.\n"
                  f"  {sys.executable} examples/publish_poses.py --traj TRAJ.txt --source {EXTERNAL_SOURCE} "
                  + (f"--zenoh-config {creds.config('external')} --ns {ns}" if creds is not None else
                     f"--connect {mesh[0]} --ns {ns}"),
                  flush=True)
        window = max(opts.window, MONO_BOOTSTRAP_WINDOW) if mono else opts.window
        play_argv = service_command(
            "services.io play", **play_source(data, args), fps=getattr(args, "fps", None) or 0, window=window,
            ack_from="mapper", wait_for=",".join(wait_for), start_timeout=play_start_timeout,
            resend_to=resend_to(poses, live), start_after="mapper" if resuming else None,
            no_depth=not play_sends_depth(poses, info["config"]["mapper"].get("use_depth")), **net("play"))
        procs["play"] = Proc("play", play_argv, out, env)  # it sends nothing before each of --wait-for has a status
        if creds is not None:
            wait_ready(later, opts.start_timeout)
        if view == "live":
            print(f"fmapping up: live viewer at {live_url(args)} (the recording also goes to {out / 'run.rrd'})",
                  flush=True)
        rc = monitor(procs, t0, timeout, out, serving=("view",) if view == "live" else (), infra=infra,
                     errors=errors)
        if view == "live" and rc == 0:
            linger(procs["view"], live_url(args))
        return rc
    except KeyboardInterrupt:
        print("\nfmapping up: interrupted, stopping the services ...", file=sys.stderr, flush=True)
        errors.append("interrupted")
        return 130
    except RuntimeError as e:  # a service did not start: one message naming it, no traceback
        print(f"fmapping up: {e}", file=sys.stderr, flush=True)
        errors.append(str(e))
        return 1
    finally:
        stop_all(procs, opts.grace, first=("play", "tracker", "mapper", "record", "view"))
        add_run_info(out, info, since=started)  # the mapper has exited: its stats.json is final
        if errors:  # a failed run still says what it wrote and why it ended
            write_summary(procs, t0, out, error=errors[0])
        stop_all(infra, opts.grace, first=("router",))  # after the services: they talk through it to the end
        for p in (*procs.values(), *infra.values()):
            p.close()
        if creds is not None:
            creds.remove()  # per-run passwords: useless once the router is gone
        for sig, h in old_handlers.items():
            signal.signal(sig, h)


def threading_main() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()
