"""``io view``: log everything on the bus to rerun.

Entities (timeline ``frame`` = frame number):
``world/camera`` (pose of the primary source) with ``world/camera/image`` (pinhole, RGB)
and ``world/camera/image/depth``; ``world/cams/<source>`` a frustum per pose source;
``world/traj/<source>`` trajectories (tracked vs GT vs external); ``world/map/points``
the map points; ``world/map/aabb`` the field's bounding box; ``status/<service>/...`` lag
and queue counters as scalars.

Live: ``--serve`` (default without ``--save``) starts rerun's gRPC server and web viewer
(``rr.serve_grpc`` + ``rr.serve_web_viewer``) and prints the address to open.
``--save out.rrd`` writes a recording instead (open with ``rerun out.rrd``). The view
stops like ``record``: after the end-of-sequence stop once ``--wait-done`` are done.
"""
from __future__ import annotations

import argparse
import time
from typing import Optional

import numpy as np

from fmapping import protocol as P
from services.common import (Peers, Service, add_common_args, names, serve_until_end, service_parser, setup_logging,
                             stop_kind)

SOURCE_COLORS = {"tracker": (230, 80, 40), "gt": (40, 200, 80), "external": (60, 120, 240)}


def add_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--save", default=None, metavar="OUT.rrd", help="write a rerun recording instead of serving")
    p.add_argument("--grpc-port", type=int, default=None, help="rerun gRPC port when serving (default rerun's 9876)")
    p.add_argument("--web-port", type=int, default=None, help="web viewer port when serving (default rerun's 9090)")
    p.add_argument("--open-browser", action="store_true")
    p.add_argument("--primary", default="auto", help="pose source that carries the camera image (auto: tracker > external > gt)")
    p.add_argument("--image-every", type=int, default=1, help="log every n-th RGB image (0 = none)")
    p.add_argument("--depth-every", type=int, default=5, help="log every n-th depth image (0 = none)")
    p.add_argument("--jpeg-quality", type=int, default=85, help="compress logged RGB (0 = raw)")
    p.add_argument("--exit-at-end", action="store_true", help="when serving: exit at the end instead of serving on")
    p.add_argument("--wait-done", default="mapper")
    p.add_argument("--final-timeout", type=float, default=120.0)
    return add_common_args(p)


class Viewer:
    """Zenoh-free: turns decoded messages into rerun log calls on a RecordingStream."""

    PRIORITY = ("tracker", "external", "gt")

    def __init__(self, rec, primary: str = "auto", image_every: int = 1, depth_every: int = 5, jpeg_quality: int = 85):
        import rerun as rr

        self.rr, self.rec = rr, rec
        self.primary = primary
        self.image_every, self.depth_every, self.jpeg_quality = image_every, depth_every, jpeg_quality
        self.traj: dict[str, list[np.ndarray]] = {}
        self._camera: Optional[dict] = None
        self._traj_logged: dict[str, float] = {}
        self.frames = 0
        rec.log("world", rr.ViewCoordinates.RDF, static=True)

    def _primary_for(self, source: str) -> bool:
        if self.primary != "auto":
            return source == self.primary
        seen = [s for s in self.PRIORITY if s in self.traj] + sorted(s for s in self.traj if s not in self.PRIORITY)
        return bool(seen) and seen[0] == source

    def on_frame(self, f: P.Frame) -> None:
        rr = self.rr
        self.rec.set_time("frame", sequence=f.seq)
        if f.camera != self._camera:
            c = f.camera
            self.rec.log("world/camera/image", rr.Pinhole(focal_length=[c["fx"], c["fy"]], principal_point=[c["cx"], c["cy"]],
                                                          resolution=[c["width"], c["height"]]), static=True)
            self._camera = f.camera
        if self.image_every and self.frames % self.image_every == 0:
            img = rr.Image(f.rgb)
            self.rec.log("world/camera/image", img.compress(jpeg_quality=self.jpeg_quality) if self.jpeg_quality else img)
        if f.depth is not None and self.depth_every and self.frames % self.depth_every == 0:
            self.rec.log("world/camera/image/depth", rr.DepthImage(f.depth, meter=1.0))
        self.frames += 1

    def on_pose(self, p: P.Pose) -> None:
        rr = self.rr
        self.rec.set_time("frame", sequence=max(p.seq, 0))
        self.traj.setdefault(p.source, []).append(np.asarray(p.c2w[:3, 3], np.float32))
        tf = rr.Transform3D(translation=p.c2w[:3, 3], mat3x3=p.c2w[:3, :3])
        if self._primary_for(p.source):
            self.rec.log("world/camera", tf)
        self.rec.log(f"world/cams/{p.source}", tf)
        if self._camera is not None and f"world/cams/{p.source}" not in self._traj_logged:
            c = self._camera
            self.rec.log(f"world/cams/{p.source}/frustum",
                         rr.Pinhole(focal_length=[c["fx"], c["fy"]], principal_point=[c["cx"], c["cy"]],
                                    resolution=[c["width"], c["height"]], image_plane_distance=0.1,
                                    color=SOURCE_COLORS.get(p.source, (200, 200, 200))), static=True)
            self._traj_logged[f"world/cams/{p.source}"] = 0.0
        now = time.monotonic()
        if now - self._traj_logged.get(p.source, 0.0) > 0.2:
            self.log_trajectory(p.source)
            self._traj_logged[p.source] = now

    def log_trajectory(self, source: str) -> None:
        pts = self.traj.get(source)
        if pts and len(pts) > 1:
            self.rec.log(f"world/traj/{source}", self.rr.LineStrips3D([np.stack(pts)], radii=0.005,
                                                                       colors=[SOURCE_COLORS.get(source, (200, 200, 200))]))

    def on_points(self, s: P.PointsSnapshot) -> None:
        self.rec.set_time("frame", sequence=max(s.frame_seq, 0))
        self.rec.log("world/map/points", self.rr.Points3D(s.points, colors=s.colors, radii=0.01))

    def on_field(self, s: P.FieldSnapshot) -> None:
        self.rec.set_time("frame", sequence=max(s.frame_seq, 0))
        lo, hi = np.asarray(s.aabb[0], np.float32), np.asarray(s.aabb[1], np.float32)
        self.rec.log("world/map/aabb", self.rr.Boxes3D(mins=[lo], sizes=[hi - lo], colors=[(180, 180, 180)]))

    def on_status(self, st: P.Status) -> None:
        self.rec.log(f"status/{st.service}/lag", self.rr.Scalars(float(st.lag)))
        for k in ("frames_processed", "windows", "dropped_frames", "decode_errors"):
            if k in st.counters:
                self.rec.log(f"status/{st.service}/{k}", self.rr.Scalars(float(st.counters[k])))

    def finish(self) -> None:
        for src in self.traj:
            self.log_trajectory(src)
        self.rec.flush(timeout_sec=10.0)


def open_recording(args):
    """A RecordingStream that saves to ``--save`` or serves gRPC + the web viewer."""
    import rerun as rr

    rec = rr.RecordingStream("fmapping")
    if args.save:
        from pathlib import Path

        Path(args.save).parent.mkdir(parents=True, exist_ok=True)
        rec.save(args.save)
    else:
        kw = {} if args.grpc_port is None else {"grpc_port": args.grpc_port}
        url = rec.serve_grpc(**kw)
        wkw = {} if args.web_port is None else {"web_port": args.web_port}
        rr.serve_web_viewer(connect_to=url, open_browser=args.open_browser, **wkw)
        port = args.web_port or 9090
        print(f"rerun viewer: http://localhost:{port}/?url={url}  (or native: rerun --connect {url})", flush=True)
    return rec


def handle_message(svc: Service, view: Viewer, peers: Peers, channel: str, key: str, data: bytes,
                   wait_done=()) -> Optional[str]:
    """Decode one payload of ``channel`` and log it; a bad one is counted (``decode_errors``,
    ``bad_input``) and logs nothing. Returns 'end' or 'stop' when the view should finish."""
    decoders = {"frames": (P.Frame, view.on_frame), "poses": (P.Pose, view.on_pose),
                "points": (P.PointsSnapshot, view.on_points), "field": (P.FieldSnapshot, view.on_field)}
    if channel in decoders:
        cls, fn = decoders[channel]
        msg = svc.decode(data, cls, key)
        if msg is not None:
            try:
                fn(msg)
                svc.counters.inc(f"logged_{channel}")
                if channel == "frames":
                    svc.status.update(frame_seq=msg.seq)
            except Exception as e:  # a rerun failure must not kill the service
                svc.counters.inc("log_errors")
                svc.status.error(f"rerun: {e}")
                svc.log.exception("rerun logging failed")
    elif channel == "status":
        msg = svc.decode(data, P.Status, key)
        if msg is not None:
            peers.update(msg)
            if msg.service != svc.name:
                view.on_status(msg)
    elif channel == "control":
        msg = svc.control(data, key)
        if msg is not None:
            return stop_kind(msg, wait_done)
    return None


def run(svc: Service, args, rec) -> int:
    view = Viewer(rec, args.primary, args.image_every, args.depth_every, args.jpeg_quality)
    peers = Peers()
    wait_done = names(args.wait_done)
    for key, ch in ((svc.keys.frames, "frames"), (svc.keys.poses(), "poses"), (svc.keys.points, "points"),
                    (svc.keys.field, "field"), (svc.keys.status(), "status"), (svc.keys.control, "control")):
        svc.subscribe(key, ch)
    svc.start()
    serve_until_end(svc, peers, lambda ch, key, data: handle_message(svc, view, peers, ch, key, data, wait_done),
                    wait_done, args.final_timeout)
    view.finish()
    if not args.save and not args.exit_at_end and not svc.shutdown.requested:
        svc.log.info("sequence ended; still serving the viewer (Ctrl-C to quit)")
        while not svc.shutdown.wait(0.5):
            pass
    return 0


def main(argv=None, session=None, keys=None) -> int:
    args = add_args(service_parser("services.io view", __doc__)).parse_args(argv)
    setup_logging(args.log_level, "view")
    rec = open_recording(args)
    svc = Service("view", args, capacities={"control": 64, "status": 256, "poses": 10_000, "field": 2,
                                            "points": 2, "frames": 8},
                  session=session, keys=keys)
    try:
        return run(svc, args, rec)
    finally:
        svc.close("done")
        rec.flush(timeout_sec=10.0)
        rec.disconnect()
