"""``fmapping up``: run the multi-process system on one machine.

Starts, as separate OS processes (``sys.executable -m services...``):

* ``services.mapper`` (first),
* ``services.io record`` (OUT/record/: traj_<source>.txt, points.ply),
* ``services.io view --save OUT/run.rrd`` (rerun recording; ``--view live`` also serves rerun's
  web viewer on ``--view-port`` / ``--grpc-port`` and prints its URL),
* ``services.tracker`` when ``--poses tracker``,
* ``services.io play`` last (it waits until the others report, then streams the data).

Networking is secure by default (:mod:`services.credentials`, docs/security.md): the launcher
makes per-run credentials (a random password per role, files 0600 in OUT/secrets, deleted at
the end) and starts a zenoh router (``services.router``) on a free loopback port that admits
only those users and lets each role publish, subscribe and ask only its own keys; every
service is a client of it, in a namespace of its own (``fmapping/up<pid>/...``). With
``--insecure`` (local debugging) it is the old open peer mesh instead: each process listens
on a free ``tcp/127.0.0.1:<port>`` and connects to every process started before it. Each process logs
to OUT/logs/<name>.log and writes its status to OUT/status/<name>.json, which the launcher
reads to show progress. At the end of the sequence play sends the end-of-sequence stop;
the mapper runs its closing stage and writes OUT/map.ply, OUT/mesh.ply, OUT/traj.txt and
OUT/stats.json; record and view finish after it. A mapper, tracker, recorder or viewer that
crashes while play streams is started again (at most 3 times, backoff 1, 2, 4 s; counted in
OUT/up.json ``restarts``); the mapper resumes from its checkpoint, the mono tracker re-localises
against its saved keyframes (OUT/tracker/state.npz), and play sends a restarted service the frames
it never handled (``io play --resend-to``). ``fmapping up --resume OUT`` continues a run whose
launcher was killed (its arguments are in OUT/run.json). Ctrl-C (or SIGTERM) stops
every process (SIGINT, then SIGKILL after a grace period); the mapper still writes its current map.

This module only starts processes and reads files: it does not import zenoh.
With ``--poses external`` a producer must publish ``Pose(source="external")`` (see
``examples/publish_poses.py``; the launcher prints the command); play waits for it.

``--config`` YAML: either mapper overrides at the top level (like ``fmapping map``), or
sections ``mapper:``, ``tracker:`` and ``launcher:`` (keys: ``timeout`` seconds,
``view`` true/false, ``window`` frames in flight, ``frames`` / ``size`` / ``seed`` of
the generated scene, ``threads`` per torch process, ``tracker_frontend`` mono|map).

With ``--poses tracker`` the tracker's default front end is ``mono`` (RGB only from the
first frame, world frame and scale from the first GT poses that play publishes, exactly
as ``fmapping slam``); the mapper takes its poses as given. ``tracker_frontend: map`` runs
the paper-style loop instead: the mapper initialises without poses (``--unposed-init yes``)
and the tracker follows its field.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

from fmapping.cli import source_options
from fmapping.config import read_yaml_mapping

SECTIONS = ("mapper", "tracker", "launcher")
# Frames play keeps in flight with the mono tracker: the mapper can take no frame before the
# tracker's bootstrap answers (it held 7-14 frames on the synthetic rooms); a smaller window
# stalls playback until the mapper's pose timeout. Both inboxes hold more (mapper 32, tracker 64).
MONO_BOOTSTRAP_WINDOW = 20
EXTERNAL_SOURCE = "external"  # pose source and status name of an external producer (poses/external, status/external)
# A service's status file is rewritten by its heartbeat thread every 0.5 s, even during a long update:
# one unchanged for this long belongs to a hung process, and the run is stopped with its name.
HEARTBEAT_TIMEOUT = 120.0
# Supervision: a service that dies while play still streams is started again, at most MAX_RESTARTS
# times each, after RESTART_BACKOFF * 2**k seconds (k = restarts so far). The mapper resumes from
# OUT/checkpoint.pt, the tracker re-syncs from map/latest. Play is not restarted (it would start the
# sequence over), nor is anything once play has finished (the end-of-sequence stop is gone then).
RESTARTABLE = ("mapper", "tracker", "record", "view")
MAX_RESTARTS = 3
RESTART_BACKOFF = 1.0
FINAL_CODES = (2, 3)  # bad input, gave up waiting (services.common.EXIT_STALLED): starting again changes nothing


@dataclass
class LauncherOptions:
    timeout: Optional[float] = None  # seconds for the whole run (None = no limit)
    view: bool = True
    window: int = 4
    frames: int = 200
    size: tuple = (320, 240)
    seed: int = 0
    threads: int = 0
    tracker_frontend: str = "mono"  # --poses tracker: "mono" (RGB-only front end, as fmapping slam) | "map"
    start_timeout: float = 120.0
    grace: float = 15.0  # seconds between SIGINT and SIGKILL on shutdown
    extra: dict = field(default_factory=dict)


def _mapper_defaults():
    from fmapping.mapping import MapperConfig

    return MapperConfig()


def _tracker_defaults():
    from fmapping.tracking.direct_tracker import TrackerConfig

    return TrackerConfig()


@dataclass
class UpConfig:
    """Every key an ``fmapping up`` config may set, by section (``fmapping config dump up`` prints
    the defaults; :func:`split_config` reads such a file). The sections are built on first use so
    that importing the launcher does not import torch."""
    mapper: Any = field(default_factory=_mapper_defaults)  # fmapping.mapping.MapperConfig
    tracker: Any = field(default_factory=_tracker_defaults)  # fmapping.tracking.direct_tracker.TrackerConfig
    launcher: LauncherOptions = field(default_factory=LauncherOptions)


def up_config_dict(cfg: UpConfig) -> dict:
    """``cfg`` as the sections of an ``up`` config file (``launcher.extra`` is internal, not a key)."""
    from fmapping.config import to_dict

    d = to_dict(cfg)
    d["launcher"].pop("extra", None)
    return d


def run_info(data, poses: str, mapper_cfg: Optional[Path], tracker_cfg: Optional[Path],
             opts: LauncherOptions, camera: Optional[str] = None, source: Optional[dict] = None) -> dict:
    """What the launcher adds to the mapper's OUT/stats.json, as ``fmapping map`` records them: the
    dataset (intrinsics, depth scale, as ``io play`` opens it) and the config every service runs with.
    A live camera (``camera:N``) is not opened here: play opens it, and a webcam may take one reader only;
    its intrinsics are the ``--camera`` given. ``source``: :func:`fmapping.cli.source_options` (fps, topic)."""
    from fmapping.config import load_config
    from fmapping.datasets import open_dataset
    from fmapping.datasets.live import is_live_spec

    resolved = UpConfig(mapper=load_config(_mapper_defaults(), mapper_cfg),
                        tracker=load_config(_tracker_defaults(), tracker_cfg), launcher=opts)
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
    data = Path(args.data) if args.data else _scene(out, opts)
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


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (small race window until someone binds it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def split_config(path: Optional[str], out: Path) -> tuple[Optional[Path], Optional[Path], LauncherOptions]:
    """Split an ``up`` config into mapper / tracker YAML files under OUT/config and launcher options."""
    opts = LauncherOptions()
    if not path:
        return None, None, opts
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"config file not found: {p}")
    data = read_yaml_mapping(p)
    if not data or not set(data) <= set(SECTIONS):
        data = {"mapper": data}  # plain mapper overrides
    cdir = out / "config"
    cdir.mkdir(parents=True, exist_ok=True)
    files = {}
    for name in ("mapper", "tracker"):
        if data.get(name):
            if not isinstance(data[name], dict):
                raise ValueError(f"{p}: section {name!r} must be a mapping")
            files[name] = cdir / f"{name}.yaml"
            files[name].write_text(yaml.safe_dump(data[name], sort_keys=False))
    launch = data.get("launcher") or {}
    if not isinstance(launch, dict):
        raise ValueError(f"{p}: section 'launcher' must be a mapping")
    valid = {f for f in LauncherOptions.__dataclass_fields__ if f != "extra"}
    unknown = set(launch) - valid
    if unknown:
        raise ValueError(f"{p}: unknown launcher keys {sorted(unknown)} (valid: {', '.join(sorted(valid))})")
    for k, v in launch.items():
        setattr(opts, k, tuple(v) if k == "size" else v)
    return files.get("mapper"), files.get("tracker"), opts


def _scene(out: Path, opts: LauncherOptions) -> Path:
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


def run_demo(args) -> int:
    """``fmapping demo``, the main job on the embedded default: a synthetic room in ``args.out/scene``, run
    the multi-process system on it (``fmapping up``, poses from the RGB-only tracker unless
    ``args.poses`` says ``gt``, playback paced by the consumers) and print the trajectory and
    reconstruction metrics (``args.out/demo.json``)."""
    from fmapping.fileio import json_default

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene_dir = _scene(out, LauncherOptions(frames=int(getattr(args, "frames", 200)),
                                            seed=int(getattr(args, "seed", 0))))
    poses = getattr(args, "poses", None) or "tracker"
    uargs = argparse.Namespace(data=str(scene_dir), poses=poses, out=str(out), fps=0.0,
                               config=getattr(args, "config", None))
    rc = run_up(uargs)
    if rc != 0:
        return rc
    report = demo_metrics(out, scene_dir)
    (out / "demo.json").write_text(json.dumps(report, indent=2, default=json_default))
    print(json.dumps(report, indent=2, default=json_default))
    t, r, r3 = report.get("trajectory", {}), report.get("recon", {}), report.get("recon_sim3", {})
    if "ate_sim3_cm" in t:
        print(f"trajectory ({poses} poses, {t['frames']} frames): ATE {t['ate_se3_cm']:.2f} cm (SE3), "
              f"{t['ate_sim3_cm']:.2f} cm (Sim3)")
    if "completion_ratio" in r:
        print(f"reconstruction vs visible GT: accuracy {r['accuracy_cm']:.2f} cm, completion {r['completion_cm']:.2f} cm, "
              f"completion ratio (5 cm) {r['completion_ratio']:.1f} %")
    if "completion_ratio" in r3:
        print(f"after the trajectory's Sim3: accuracy {r3['accuracy_cm']:.2f} cm, completion "
              f"{r3['completion_cm']:.2f} cm, completion ratio (5 cm) {r3['completion_ratio']:.1f} %")
    return 0


def demo_metrics(out: Path, scene_dir: Path) -> dict:
    """ATE of ``out/traj.txt`` against the scene's ground truth (SE3 and Sim3) and the map's scores
    (:func:`fmapping.pipeline.recon_stats`: unaligned and after the trajectory's Sim3)."""
    from fmapping.datasets import open_dataset
    from fmapping.metrics import align_trajectory, ate, match_trajectory_files
    from fmapping.pipeline import recon_stats

    report: dict = {"out": str(out)}
    sim3 = None
    if (out / "traj.txt").is_file():
        est, gt, _, _ = match_trajectory_files(out / "traj.txt", scene_dir / "groundtruth.txt")
        t = {a: ate(est, gt, a) for a in ("se3", "sim3")}
        sim3 = align_trajectory(est, gt, "sim3")[1]
        report["trajectory"] = {"frames": len(est), "ate_se3_cm": 100 * t["se3"]["rmse_m"],
                                "ate_sim3_cm": 100 * t["sim3"]["rmse_m"], "sim3_scale": float(sim3[0]),
                                "rot_fit_mean_deg": t["sim3"]["rot_fit_mean_deg"]}
    if (out / "map.ply").is_file():
        keys = ("accuracy_cm", "completion_cm", "completion_ratio")
        for name, r in recon_stats(open_dataset(scene_dir), out, sim3=sim3).items():
            report[name] = {k: r[k] for k in keys if k in r}
    return report


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


class Proc:
    """One child service process with its log file and status file."""

    def __init__(self, name: str, argv: list[str], out: Path, env: dict):
        self.name = name
        self.status_file = out / "status" / f"{name}.json"
        self.log_path = out / "logs" / f"{name}.log"
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self.status_file.parent.mkdir(parents=True, exist_ok=True)
        if self.status_file.exists():
            self.status_file.unlink()
        self.argv = argv + ["--status-file", str(self.status_file), "--exit-with-parent"]
        self.env = env
        self.restarts = 0
        self._log = open(self.log_path, "w")
        self.popen = subprocess.Popen(self.argv, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                      start_new_session=True)

    def restart(self) -> None:
        """Start the same command again after it died: the log goes on, the status starts over."""
        self._log.write(f"\n--- fmapping up: restart {self.restarts + 1} (exit code {self.rc}) ---\n")
        self._log.flush()
        if self.status_file.exists():
            self.status_file.unlink()
        self.popen = subprocess.Popen(self.argv, stdout=self._log, stderr=subprocess.STDOUT, env=self.env,
                                      start_new_session=True)
        self.restarts += 1

    @property
    def rc(self) -> Optional[int]:
        return self.popen.poll()

    def status(self) -> dict:
        try:
            return json.loads(self.status_file.read_text())
        except (OSError, ValueError):
            return {}

    def silent_for(self) -> float:
        """Seconds since the status file last changed (0 before it exists: start-up has its own timeout)."""
        try:
            return max(0.0, time.time() - self.status_file.stat().st_mtime)
        except OSError:
            return 0.0

    def signal(self, sig: int) -> None:
        if self.popen.poll() is None:
            try:
                self.popen.send_signal(sig)
            except ProcessLookupError:
                pass

    def close(self) -> None:
        self._log.close()

    def tail(self, n: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


def _wait_ready(procs: list[Proc], timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for p in procs:
            if p.rc is not None:
                raise RuntimeError(f"{p.name} exited with code {p.rc} during start-up:\n{p.tail()}")
        if all(p.status_file.exists() for p in procs):
            return
        time.sleep(0.1)
    missing = [p.name for p in procs if not p.status_file.exists()]
    raise RuntimeError(f"{', '.join(missing)} did not start within {timeout:.0f} s (see {procs[0].log_path.parent})")


def _progress(procs: dict[str, Proc], t0: float) -> str:
    play = procs["play"].status() if "play" in procs else {}
    pc = play.get("counters", {})
    total = int(pc.get("frames_total", 0) or 0)
    sent = int(pc.get("frames_sent", 0) or 0)
    parts = [f"{time.monotonic() - t0:6.1f}s", f"play {sent}/{total or '?'}"]
    m = procs["mapper"].status()
    if m:
        mc = m.get("counters", {})
        parts.append(f"mapper acked {m.get('frame_seq', -1) + 1} windows {int(mc.get('windows', 0))} "
                     f"v{int(mc.get('field_version', 0))} [{m.get('state', '?')}]")
    if "tracker" in procs:
        t = procs["tracker"].status()
        tc = t.get("counters", {})
        parts.append(f"tracker {int(tc.get('frames_tracked', 0))} tracked {int(tc.get('frames_lost', 0))} lost")
    errs = sum(int(p.status().get("counters", {}).get("decode_errors", 0)) for p in procs.values())
    if errs:
        parts.append(f"decode errors {errs}")
    return " | ".join(parts)


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


def run_up(args) -> int:
    """Run the system (see the module docstring); returns the exit code."""
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
    # optional: endpoints every service also connects to, e.g. a monitoring session (bench/system.py)
    extra_connect = [str(e) for e in (getattr(args, "connect_extra", None) or [])]
    # secure by default: per-run credentials, a router with access control (services.credentials);
    # a monitoring session joining the mesh (connect_extra) needs the old open mesh
    insecure = bool(getattr(args, "insecure", False)) or bool(extra_connect)
    creds = None  # services.credentials.RunCredentials of a secure run, made once the inputs are checked

    def net(role: str) -> list[str]:
        """Secure: the client config of ``role`` (its credentials, the run's router). --insecure: listen
        on a fresh loopback port and connect to every process started before (explicit mesh)."""
        if creds is not None:
            return ["--zenoh-config", str(creds.config(role)), "--ns", ns]
        ep = f"tcp/127.0.0.1:{free_port()}"
        peers = extra_connect + mesh
        argv = ["--listen", ep, "--ns", ns] + (["--connect", ",".join(peers)] if peers else [])
        mesh.append(ep)
        return argv
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PYTHONUNBUFFERED", "1")
    py = [sys.executable, "-m"]
    threads = ["--threads", str(opts.threads)] if opts.threads else []

    if opts.tracker_frontend not in ("mono", "map"):
        raise ValueError(f"launcher.tracker_frontend must be 'mono' or 'map', got {opts.tracker_frontend!r}")
    mono = poses == "tracker" and opts.tracker_frontend == "mono"
    live = isinstance(data, str)  # up_data: a live camera is its camera:N string, a dataset a Path
    mapper_cfg = with_user_box(mapper_cfg, getattr(args, "bbox", None), out)
    # errors in data or configs: before any process
    info = run_info(data, poses, mapper_cfg, tracker_cfg, opts, camera, source_options(args))
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
    mapper_argv = py + ["services.mapper", "--poses", poses, "--out", str(out)] + net("mapper") + threads
    # the services give up on their first message after a while (default 900 s); play waits up to an
    # hour for an external producer, so they wait longer then
    first_wait = ["--first-message-timeout", "4500"] if poses == "external" else []
    mapper_argv += first_wait
    if poses == "tracker" and not mono:
        mapper_argv += ["--unposed-init", "yes"]  # the map tracker tracks only once the mapper has a map
    if poses == "tracker" and not live:
        mapper_argv += ["--resent-frames"]  # play sends a restarted tracker what it missed (resend_argv)
    if mapper_cfg:
        mapper_argv += ["--config", str(mapper_cfg)]
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
            infra["router"] = Proc("router", py + ["services.router", "--zenoh-config", str(creds.router_config)],
                                   out, env)
            try:
                _wait_ready([infra["router"]], opts.start_timeout)
                break
            except RuntimeError:  # the free port was taken before the router bound it: another port
                if attempt == 2:
                    raise
                infra.pop("router").close()
                creds = make_run_credentials(out / "secrets", f"tcp/127.0.0.1:{free_port()}", ns)
        if creds is not None:
            print(f"fmapping up: secure run: router on {creds.endpoint}, per-run credentials in {creds.folder} "
                  "(mode 0600), access control by role (--insecure: the open loopback mesh)", flush=True)
        procs["mapper"] = Proc("mapper", mapper_argv, out, env)
        _wait_ready([procs["mapper"]], opts.start_timeout)
        procs["record"] = Proc("record", py + ["services.io", "record", "--out", str(out / "record"),
                                               "--source", record_src] + (["--append"] if resuming else [])
                               + net("record") + first_wait, out, env)
        later = [procs["record"]]
        view = view_mode(getattr(args, "view", None)) if opts.view else ""
        if view:
            uses_depth = bool(info["config"]["mapper"].get("use_depth"))
            procs["view"] = Proc("view", py + ["services.io", "view"] + view_argv(out, view, args, uses_depth)
                                 + net("view"), out, env)
            later.append(procs["view"])
        if poses == "tracker":
            targv = py + ["services.tracker", "--frontend", opts.tracker_frontend] + net("tracker") + threads
            if mono:  # a restarted tracker re-localises against its last keyframe (same world frame and scale)
                targv += ["--state", str(tracker_state(out))]
            if tracker_cfg:
                targv += ["--config", str(tracker_cfg)]
            procs["tracker"] = Proc("tracker", targv, out, env)
            later.append(procs["tracker"])
        _wait_ready(later, opts.start_timeout)
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
        play_argv = py + ["services.io", "play"] + play_source_argv(data, args) + [
            "--fps", str(getattr(args, "fps", None) or 0), "--window", str(window), "--ack-from", "mapper",
            "--wait-for", ",".join(wait_for), "--start-timeout", str(play_start_timeout)] \
            + resend_argv(poses, live) + (["--start-after", "mapper"] if resuming else []) + net("play")
        procs["play"] = Proc("play", play_argv, out, env)
        if view == "live":
            print(f"fmapping up: live viewer at {live_url(args)} (the recording also goes to {out / 'run.rrd'})",
                  flush=True)
        rc = _monitor(procs, t0, timeout, out, serving=("view",) if view == "live" else (), infra=infra,
                      errors=errors)
        if view == "live" and rc == 0:
            _linger(procs["view"], live_url(args))
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
        _stop_all(procs, opts.grace, first=("play", "tracker", "mapper", "record", "view"))
        add_run_info(out, info, since=started)  # the mapper has exited: its stats.json is final
        if errors:  # a failed run still says what it wrote and why it ended
            _write_summary(procs, t0, out, error=errors[0])
        _stop_all(infra, opts.grace, first=("router",))  # after the services: they talk through it to the end
        for p in (*procs.values(), *infra.values()):
            p.close()
        if creds is not None:
            creds.remove()  # per-run passwords: useless once the router is gone
        for sig, h in old_handlers.items():
            signal.signal(sig, h)


def tracker_state(out: Path) -> Path:
    """Where the mono tracker keeps its current keyframe for a restart (``services.tracker --state``)."""
    return out / "tracker" / "state.npz"


def resend_argv(poses: str, live: bool) -> list[str]:
    """``io play --resend-to``: the consumers that get the frames they never handled again after a
    restart (a resumed mapper from its checkpoint's frame on, a restarted tracker from its last
    acknowledgement on); a live camera cannot go back."""
    if live:
        return []
    return ["--resend-to", "mapper,tracker" if poses == "tracker" else "mapper"]


def play_source_argv(data, args) -> list[str]:
    """``io play``'s options of the source ``fmapping up`` plays: the data, ``--camera`` and the
    source options (:func:`fmapping.cli.add_source_args`) as given to ``up``."""
    argv, src = ["--data", str(data)], source_options(args)
    for flag, value in (("--camera", getattr(args, "camera", None)), ("--data-fps", src["fps"]),
                        ("--topic", src["topic"])):
        if value is not None:
            argv += [flag, str(value)]
    return argv


def play_wait_for(poses: str, view: bool = True) -> list[str]:
    """The services ``io play`` waits for before the first frame. With ``--poses external`` that
    includes the producer, which reports its status as its pose source (``status/external``, see
    ``examples/publish_poses.py``)."""
    names = ["mapper", "record"] + (["view"] if view else [])
    if poses == "tracker":
        names.append("tracker")
    elif poses == "external":
        names.append(EXTERNAL_SOURCE)
    return names


def threading_main() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def view_mode(requested: Optional[str]) -> str:
    """``--view``: live (serve rerun's web viewer and save OUT/run.rrd) or save (only the file);
    auto (the CLI's default) is live when someone can look: a display and a terminal. None (a
    caller without the option, e.g. ``fmapping demo``) is save."""
    if requested in ("live", "save"):
        return requested
    if requested is None:
        return "save"
    if requested != "auto":
        raise ValueError(f"--view must be auto, live or save, got {requested!r}")
    display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    return "live" if display and sys.stdout.isatty() else "save"


def view_argv(out: Path, mode: str, args, uses_depth: bool) -> list[str]:
    """The ``services.io view`` options of ``fmapping up``: always OUT/run.rrd, plus the live
    viewer on the fixed ports of --view-port / --grpc-port; depth images only when the mapper
    uses depth (an RGB-only run must not show the dataset's depth); the final map and mesh."""
    argv = ["--save", str(out / "run.rrd"), "--final-outputs", str(out)]
    if mode == "live":
        argv += ["--serve", "--web-port", str(getattr(args, "view_port", None) or 9090),
                 "--grpc-port", str(getattr(args, "grpc_port", None) or 9876)]
    if uses_depth:
        argv += ["--depth-every", "5"]
    return argv


def live_url(args) -> str:
    grpc = getattr(args, "grpc_port", None) or 9876
    return f"http://localhost:{getattr(args, 'view_port', None) or 9090}/?url=rerun+http://localhost:{grpc}/proxy"


def _linger(view: Proc, url: str) -> None:
    """After a live run: the viewer keeps serving until Ctrl-C when someone is at the terminal."""
    if view.rc is not None or not sys.stdin.isatty():
        return
    print(f"fmapping up: the viewer keeps serving at {url}; Ctrl-C to stop it", flush=True)
    try:
        while view.rc is None:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass


def _monitor(procs: dict[str, Proc], t0: float, timeout: Optional[float], out: Path, serving: tuple = (),
             infra: Optional[dict] = None, errors: Optional[list] = None) -> int:
    """Wait until every process has exited (those in ``serving``, a live viewer, may serve on); a process
    of ``infra`` (the router) must stay up meanwhile, and every running service must keep beating
    (:data:`HEARTBEAT_TIMEOUT`). A failure is printed and appended to ``errors``; returns 1 then."""
    errors = errors if errors is not None else []
    pending: dict[str, float] = {}  # service -> when to restart it

    def fail(msg: str) -> int:
        print(f"\nfmapping up: {msg}", file=sys.stderr, flush=True)
        errors.append(msg.split("\n", 1)[0])
        return 1

    tty = sys.stdout.isatty()
    last_print = 0.0
    while True:
        now = time.monotonic()
        if now - last_print >= (0.5 if tty else 5.0):
            line = _progress(procs, t0)
            print(("\r" + line + " " * 8) if tty else line, end="" if tty else "\n", flush=True)
            last_print = now
        _supervise(procs, pending, now)
        rcs = {n: p.rc for n, p in procs.items()}
        failed = {n: rc for n, rc in rcs.items() if rc not in (None, 0) and n not in pending}
        failed.update({n: p.rc for n, p in (infra or {}).items() if p.rc is not None})
        if failed:
            name, rc = next(iter(failed.items()))
            tail = {**procs, **(infra or {})}[name].tail()
            return fail(f"{name} exited with code {rc}; last log lines:\n{tail}")
        if all(rc == 0 for n, rc in rcs.items() if n not in serving):
            break
        if timeout is not None and now - t0 > timeout:
            return fail(f"timed out after {timeout:.0f} s")
        silent = [p.name for p in procs.values() if p.rc is None and p.silent_for() > HEARTBEAT_TIMEOUT]
        if silent:
            return fail(f"no heartbeat from {', '.join(silent)} for {HEARTBEAT_TIMEOUT:.0f} s (a hung process; "
                        f"see {out / 'logs'})")
        time.sleep(0.2)
    if tty:
        print()
    summary = _write_summary(procs, t0, out)
    print("fmapping up: done in %.1f s; outputs: %s" % (summary["seconds"], ", ".join(summary["outputs"].values())),
          flush=True)
    missing = [n for n in ("map.ply", "traj.txt") if n not in summary["outputs"]]
    if missing:
        print(f"fmapping up: missing outputs {missing} (see {out / 'logs'})", file=sys.stderr, flush=True)
        return 1
    return 0


def _supervise(procs: dict[str, Proc], pending: dict[str, float], now: float) -> None:
    """Schedule a restart (``pending``: service -> monotonic time) for every restartable service that
    died while play still runs and has restarts left; start those whose time has come."""
    play = procs.get("play")
    streaming = play is None or play.rc is None
    for name in RESTARTABLE:
        p = procs.get(name)
        if p is None or p.rc in (None, 0, *FINAL_CODES) or name in pending or not streaming \
                or p.restarts >= MAX_RESTARTS:
            continue
        delay = RESTART_BACKOFF * 2 ** p.restarts
        pending[name] = now + delay
        print(f"\nfmapping up: {name} exited with code {p.rc}; restarting it in {delay:.0f} s "
              f"({p.restarts + 1}/{MAX_RESTARTS})", file=sys.stderr, flush=True)
    for name, when in list(pending.items()):
        if now >= when:
            del pending[name]
            procs[name].restart()


def _write_summary(procs: dict[str, Proc], t0: float, out: Path, error: str = "") -> dict:
    """OUT/up.json: seconds, the outputs present, every service's last status, and ``error`` (why
    the run failed) when there is one."""
    summary: dict = {"seconds": round(time.monotonic() - t0, 1), "outputs": {}}
    if error:
        summary["error"] = error
    for name in ("map.ply", "mesh.ply", "traj.txt", "stats.json", "run.rrd", "record/traj.txt", "record/points.ply"):
        p = out / name
        if p.exists():
            summary["outputs"][name] = str(p)
    summary["status"] = {n: {"state": p.status().get("state"), "frame_seq": p.status().get("frame_seq"),
                             "counters": p.status().get("counters", {}), "rc": p.rc,
                             "last_error": p.status().get("last_error", "")} for n, p in procs.items()}
    summary["restarts"] = {n: p.restarts for n, p in procs.items() if p.restarts}
    (out / "up.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def _stop_all(procs: dict[str, Proc], grace: float, first: tuple) -> None:
    """SIGINT to every running process (in ``first`` order), SIGKILL what is left after ``grace`` s."""
    running = [procs[n] for n in first if n in procs and procs[n].rc is None]
    if not running:
        return
    for p in running:
        p.signal(signal.SIGINT)
    end = time.monotonic() + grace
    for p in running:
        try:
            p.popen.wait(timeout=max(0.1, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            print(f"fmapping up: {p.name} did not stop within {grace:.0f} s: killing it", file=sys.stderr, flush=True)
            p.popen.kill()
            p.popen.wait(timeout=5)
