"""``io view``: log everything on the bus to rerun.

Entities (timeline ``frame`` = frame number):
``world/camera`` (pose of the primary source) with ``world/camera/image`` (pinhole, RGB)
and ``world/camera/image/depth`` (only with ``--depth-every``: set it when the run uses depth;
in an RGB-only run the frames may still carry the dataset's depth, which would mislead);
``world/cams/<source>`` a frustum per pose source; ``world/traj/<source>`` trajectories
(tracked vs GT vs external); ``world/keyframes`` the keyframes (positions, and a frustum each)
as the services announce them in their status (counter ``last_keyframe``); ``world/map/points``
the map points (every ``PointsSnapshot``); ``world/map/aabb`` the field's bounding box;
``world/map/final`` and ``world/map/mesh`` the mapper's final map.ply / mesh.ply
(``--final-outputs``); ``status/<service>/...`` lag and queue counters as scalars.

Live: ``--serve`` (the default without ``--save``) hosts rerun's gRPC server (``--bind``,
``--grpc-port``) and web viewer (``--web-port``) and prints the address to open; ``--save
out.rrd`` writes a recording (open with ``rerun out.rrd``); both together do both (one
recording stream, two sinks). The view stops like ``record``: after the end-of-sequence stop
once ``--wait-done`` are done; when serving it then keeps serving until a signal
(``--exit-at-end``: it exits).
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
KEYFRAME_COLOR = (250, 200, 40)


def add_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--save", default=None, metavar="OUT.rrd", help="write the recording to this file (default: none)")
    p.add_argument("--serve", action="store_true",
                   help="serve the gRPC server and the web viewer (also with --save; the default without it)")
    p.add_argument("--bind", default="127.0.0.1",
                   help="address the gRPC server listens on (0.0.0.0 in a container; default: %(default)s)")
    p.add_argument("--grpc-port", type=int, default=9876, help="rerun gRPC port when serving (default: %(default)s)")
    p.add_argument("--web-port", type=int, default=9090, help="web viewer port when serving (default: %(default)s)")
    p.add_argument("--open-browser", action="store_true", help="open the web viewer in a browser")
    p.add_argument("--primary", default="auto", help="pose source that carries the camera image (auto: tracker > external > gt)")
    p.add_argument("--image-every", type=int, default=1, help="log every n-th RGB image (0 = none)")
    p.add_argument("--depth-every", type=int, default=0,
                   help="log every n-th depth image of the frames (default 0 = none: only runs that use depth "
                        "should show it)")
    p.add_argument("--final-outputs", default=None, metavar="DIR",
                   help="at the end also log DIR/map.ply and DIR/mesh.ply when the mapper wrote them (default: none)")
    p.add_argument("--jpeg-quality", type=int, default=85, help="compress logged RGB (0 = raw)")
    p.add_argument("--exit-at-end", action="store_true", help="when serving: exit at the end instead of serving on")
    p.add_argument("--wait-done", default="mapper")
    p.add_argument("--final-timeout", type=float, default=120.0)
    return add_common_args(p)


class Viewer:
    """Zenoh-free: turns decoded messages into rerun log calls on a RecordingStream."""

    PRIORITY = ("tracker", "external", "gt")

    def __init__(self, rec, primary: str = "auto", image_every: int = 1, depth_every: int = 0, jpeg_quality: int = 85):
        import rerun as rr

        self.rr, self.rec = rr, rec
        self.primary = primary
        self.image_every, self.depth_every, self.jpeg_quality = image_every, depth_every, jpeg_quality
        self.traj: dict[str, list[np.ndarray]] = {}
        self.poses: dict[str, dict[int, np.ndarray]] = {}  # newest c2w per source and frame (keyframes)
        self.keyframes: list[int] = []
        self._camera: Optional[dict] = None
        self._traj_logged: dict[str, float] = {}
        self.frames = 0
        rec.log("world", rr.ViewCoordinates.RDF, static=True)

    def logs_depth(self, f: P.Frame) -> bool:
        """Whether frame ``f``'s depth is logged: only with ``depth_every`` (the run uses depth),
        every ``depth_every``-th frame. The frames of an RGB-only run can carry the dataset's
        ground-truth depth; showing it would suggest the system used or estimated it."""
        return f.depth is not None and self.depth_every > 0 and self.frames % self.depth_every == 0

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
        if self.logs_depth(f):
            self.rec.log("world/camera/image/depth", rr.DepthImage(f.depth, meter=1.0))
        self.frames += 1

    def on_pose(self, p: P.Pose) -> None:
        rr = self.rr
        self.rec.set_time("frame", sequence=max(p.seq, 0))
        self.traj.setdefault(p.source, []).append(np.asarray(p.c2w[:3, 3], np.float32))
        self.poses.setdefault(p.source, {})[p.seq] = np.array(p.c2w)
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
        """The trajectory of ``source`` in frame order, the newest pose of each frame (a tracker
        re-sends the poses its bundle adjustment or a loop closure moved)."""
        poses = self.poses.get(source, {})
        if len(poses) > 1:
            pts = np.stack([c2w[:3, 3] for _, c2w in sorted(poses.items())]).astype(np.float32)
            color = SOURCE_COLORS.get(source, (200, 200, 200))
            self.rec.log(f"world/traj/{source}", self.rr.LineStrips3D([pts], radii=0.005, colors=[color]))

    def on_points(self, s: P.PointsSnapshot) -> None:
        self.rec.set_time("frame", sequence=max(s.frame_seq, 0))
        self.rec.log("world/map/points", self.rr.Points3D(s.points, colors=s.colors, radii=0.01))

    def on_field(self, s: P.FieldSnapshot) -> None:
        self.rec.set_time("frame", sequence=max(s.frame_seq, 0))
        lo, hi = np.asarray(s.aabb[0], np.float32), np.asarray(s.aabb[1], np.float32)
        self.rec.log("world/map/aabb", self.rr.Boxes3D(mins=[lo], sizes=[hi - lo], colors=[(180, 180, 180)]))

    def keyframe_pose(self, seq: int) -> Optional[np.ndarray]:
        """The newest pose of frame ``seq`` from the first source that has one (primary order)."""
        order = [self.primary] if self.primary != "auto" else []
        for src in order + list(self.PRIORITY) + sorted(self.poses):
            c2w = self.poses.get(src, {}).get(seq)
            if c2w is not None:
                return c2w
        return None

    def on_keyframe(self, seq: int) -> None:
        """A new keyframe ``seq`` (announced by a status counter ``last_keyframe``), drawn at its
        pose; one whose pose has not arrived yet is drawn when it is announced again."""
        if seq in self.keyframes or self.keyframe_pose(seq) is None:
            return
        self.keyframes.append(seq)
        self.log_keyframes([seq])

    def log_keyframes(self, seqs) -> None:
        """Frustums of keyframes ``seqs`` at their newest poses, and the positions of all keyframes."""
        rr = self.rr
        for seq in seqs:
            c2w = self.keyframe_pose(seq)
            self.rec.log(f"world/keyframes/kf{seq:06d}", rr.Transform3D(translation=c2w[:3, 3], mat3x3=c2w[:3, :3]),
                         static=True)
            if self._camera is not None:
                c = self._camera
                self.rec.log(f"world/keyframes/kf{seq:06d}/frustum",
                             rr.Pinhole(focal_length=[c["fx"], c["fy"]], principal_point=[c["cx"], c["cy"]],
                                        resolution=[c["width"], c["height"]], image_plane_distance=0.05,
                                        color=KEYFRAME_COLOR), static=True)
        if self.keyframes:
            centres = np.asarray([self.keyframe_pose(k)[:3, 3] for k in self.keyframes], np.float32)
            self.rec.log("world/keyframes", rr.Points3D(centres, radii=0.015, colors=[KEYFRAME_COLOR]))

    def on_status(self, st: P.Status) -> None:
        kf = st.counters.get("last_keyframe")
        if kf is not None and kf >= 0:
            self.on_keyframe(int(kf))
        self.rec.log(f"status/{st.service}/lag", self.rr.Scalars(float(st.lag)))
        for k in ("frames_processed", "windows", "dropped_frames", "decode_errors"):
            if k in st.counters:
                self.rec.log(f"status/{st.service}/{k}", self.rr.Scalars(float(st.counters[k])))

    def log_final_outputs(self, folder, since: float = 0.0) -> list[str]:
        """``folder``/map.ply as ``world/map/final`` and ``folder``/mesh.ply as ``world/map/mesh``, when
        written at or after ``since`` (a ``time.time()``: an earlier run's files are not this run's).
        Returns the entities logged."""
        from pathlib import Path

        from fmapping.ply import read_ply

        logged = []
        for name, entity in (("map.ply", "world/map/final"), ("mesh.ply", "world/map/mesh")):
            path = Path(folder) / name
            try:
                if path.stat().st_mtime < since - 2.0:  # 2 s: coarse file-system timestamps
                    continue
                ply = read_ply(path)
            except (OSError, ValueError):
                continue
            if ply.faces is not None and len(ply.faces):
                self.rec.log(entity, self.rr.Mesh3D(vertex_positions=ply.points, triangle_indices=ply.faces,
                                                    vertex_colors=ply.colors), static=True)
            else:
                self.rec.log(entity, self.rr.Points3D(ply.points, colors=ply.colors, radii=0.005), static=True)
            logged.append(entity)
        return logged

    def finish(self) -> None:
        for src in self.traj:
            self.log_trajectory(src)
        self.log_keyframes(self.keyframes)  # their final (bundle-adjusted, loop-closed) poses
        self.rec.flush(timeout_sec=10.0)


def serving(args) -> bool:
    """Whether the view serves a live viewer: ``--serve``, or no ``--save``."""
    return bool(args.serve or not args.save)


def viewer_url(web_port: int, grpc_url: str) -> str:
    return f"http://localhost:{web_port}/?url={grpc_url}"


def open_recording(args):
    """A RecordingStream with the sinks the options ask for: a file (``--save``), a gRPC server
    with rerun's web viewer (``--serve``, or no ``--save``), or both."""
    import rerun as rr

    rec = rr.RecordingStream("fmapping")
    sinks = []
    if serving(args):
        server = rr.GrpcServerSink(args.bind, args.grpc_port)
        sinks.append(server)
    if args.save:
        from pathlib import Path

        Path(args.save).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(args.save))
    rec.set_sinks(*sinks)
    if serving(args):
        # the URL a browser opens: the web viewer connects back to the gRPC server
        url = server.uri.replace("0.0.0.0", "localhost").replace("127.0.0.1", "localhost")
        rr.serve_web_viewer(web_port=args.web_port, open_browser=args.open_browser, connect_to=url)
        print(f"rerun viewer: {viewer_url(args.web_port, url)}  (or native: rerun --connect {url})", flush=True)
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
    started = time.time()
    view = Viewer(rec, args.primary, args.image_every, args.depth_every, args.jpeg_quality)
    peers = Peers()
    wait_done = names(args.wait_done)
    for key, ch in ((svc.keys.frames, "frames"), (svc.keys.poses(), "poses"), (svc.keys.points, "points"),
                    (svc.keys.field, "field"), (svc.keys.status(), "status"), (svc.keys.control, "control")):
        svc.subscribe(key, ch)
    svc.start()
    serve_until_end(svc, peers, lambda ch, key, data: handle_message(svc, view, peers, ch, key, data, wait_done),
                    wait_done, args.final_timeout)
    if args.final_outputs:
        view.log_final_outputs(args.final_outputs, since=started)
    view.finish()
    if serving(args) and not args.exit_at_end and not svc.shutdown.requested:
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
