"""``io view``: log everything on the bus to rerun.

Entities (timeline ``frame`` = frame number):
``world/camera`` (pose of the primary source) with ``world/camera/image`` (pinhole, RGB)
and ``world/camera/image/depth`` (only with ``--depth-every``: set it when the run uses depth;
in an RGB-only run the frames may still carry the dataset's depth, which would mislead);
``world/cams/<source>`` a frustum per pose source; ``world/traj/<source>`` trajectories
(tracked vs GT vs external); ``world/keyframes`` the keyframes (positions, and a frustum each)
as the services announce them in their status (counter ``last_keyframe``); ``world/map/points``
the map points (every ``PointsSnapshot``); ``world/map/aabb`` the field's bounding box;
``world/camera/rendered/rgb`` and ``.../depth`` colour and depth rendered from the field at the
newest pose of the primary source, at reduced resolution (``--render-width``), at most every
``--render-every`` seconds; ``world/map/mesh_live`` a coarse mesh of the field (``--mesh-resolution``)
every ``--mesh-every`` seconds and at the end; ``world/map/final`` and ``world/map/mesh`` the
mapper's final map.ply / mesh.ply (``--final-outputs``; the live mesh is then cleared at the end);
``status/<service>/...`` lag and queue counters as scalars.

Rendering and meshing run on a background thread of this process (the newest field snapshot wins,
older pending ones are dropped) so that the view keeps consuming the bus; the rate limits bound
the CPU they take from the run.

Live: ``--serve`` (the default without ``--save``) hosts rerun's gRPC server (``--bind``,
``--grpc-port``) and web viewer (``--web-port``) and prints the address to open; ``--save
out.rrd`` writes a recording (open with ``rerun out.rrd``); both together do both (one
recording stream, two sinks). The view stops like ``record``: after the end-of-sequence stop
once ``--wait-done`` are done; when serving it then keeps serving until a signal
(``--exit-at-end``: it exits).
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import threading
import time
from typing import Callable, Optional

import numpy as np

from fmapping import protocol as P
from services.process import service_parser, setup_logging
from services.transport import FINAL_TIMEOUT_HELP, Peers, Service, serve_until_end, stop_kind
from services.zenoh_session import add_common_args, names

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
    p.add_argument("--primary", default="auto",
                   help="pose source that carries the camera image (auto: tracker > external > gt)")
    p.add_argument("--image-every", type=int, default=1, help="log every n-th RGB image (0 = none)")
    p.add_argument("--depth-every", type=int, default=0,
                   help="log every n-th depth image of the frames (default 0 = none: only runs that use depth "
                        "should show it)")
    p.add_argument("--render-every", type=float, default=2.0,
                   help="render colour and depth from the field at most every this many seconds (0 = never; "
                        "default: %(default)s)")
    p.add_argument("--render-width", type=int, default=160,
                   help="width of the rendered images in pixels (the height keeps the aspect; default: %(default)s)")
    p.add_argument("--mesh-every", type=float, default=10.0,
                   help="extract a coarse mesh from the field every this many seconds (0 = only at the end, "
                        "< 0 = never; default: %(default)s)")
    p.add_argument("--mesh-resolution", type=int, default=64,
                   help="marching-cubes grid of the live mesh per axis (default: %(default)s)")
    p.add_argument("--final-outputs", default=None, metavar="DIR",
                   help="at the end also log DIR/map.ply and DIR/mesh.ply when the mapper wrote them (default: none)")
    p.add_argument("--jpeg-quality", type=int, default=85, help="compress logged RGB (0 = raw)")
    p.add_argument("--exit-at-end", action="store_true", help="when serving: exit at the end instead of serving on")
    p.add_argument("--wait-done", default="mapper",
                   help="services whose 'done' status ends the logging at the end of a sequence")
    p.add_argument("--final-timeout", type=float, default=120.0, help=FINAL_TIMEOUT_HELP)
    return add_common_args(p)


# ---------------------------------------------------------------- rendering and meshing the field
# (zenoh- and rerun-free: plain arrays in, plain arrays out)

#: Caps on the snapshot's sample counts for the preview: the mapper may render with many more
#: samples than a 160-pixel preview needs, and the view must stay cheap (a 160 x 120 render of a
#: default CP field takes ~0.9 s of one busy core with these, 1.3 s with 48 + 16).
PREVIEW_SAMPLES = (32, 8)
#: The previews take at most this share of one core: the next render (mesh) is due no sooner
#: than its last one took divided by this, however short ``--render-every`` (``--mesh-every``):
#: on a loaded machine the previews thin out instead of slowing the run.
PREVIEW_DUTY = 0.2
#: At most this many poses cull the live mesh (each one projects every vertex once).
MESH_MAX_POSES = 100
#: Rays per chunk of a preview render: render_image's default (32,768) takes a whole 160 x 120 preview
#: (40 samples a ray) in one chunk, ~350 MB of temporaries. The view's resident size shows each preview's peak
#: (bench/results/view_memory/): on a mapped field 1,024 rays peak at +58-61 MB, 256 at +16-17 MB, the same image
#: in the same time (0.4-0.6 s, one thread).
PREVIEW_CHUNK = 256
#: Field evaluations per chunk of the live mesh (the grid's opacities and the vertices' colours): the default
#: (262,144) takes a 64^3 grid at once, ~100 MB of temporaries; the mesh of a mapped field peaks at +28-35 MB with
#: 32,768 (and its vertices coloured 65,536 at a time), at +15-17 MB with 8,192; the same mesh, no slower.
MESH_GRID_CHUNK = 8192


@dataclasses.dataclass
class RenderSettings:
    near: float = 0.1
    far: float = 6.0
    n_coarse: int = 32
    n_fine: int = 16


def field_of_snapshot(s: P.FieldSnapshot):
    """``(field, RenderSettings)`` rebuilt from a ``FieldSnapshot`` on the CPU, or ValueError /
    TypeError naming what does not fit. The size the config implies is checked against the
    arrays carried before building: a forged config must not make the view allocate gigabytes."""
    from fmapping.field import FieldConfig, field_from_snapshot, min_field_elements

    fdict = s.config.get("field") if isinstance(s.config, dict) else None
    if not isinstance(fdict, dict):
        raise ValueError(f"config.field must be a map, got {type(fdict).__name__}")
    fcfg = dataclasses.replace(FieldConfig(), **fdict).validate()  # unknown keys: TypeError
    need, have = min_field_elements(fcfg), sum(int(np.asarray(a).size) for a in s.arrays.values())
    if need > have:
        raise ValueError(f"config.field needs at least {need} parameters, the snapshot carries {have}")
    rs = RenderSettings()
    for k, lo, hi, cap in (("near", 0.0, 1e4, None), ("far", 0.0, 1e4, None),
                           ("n_coarse", 2, 1024, PREVIEW_SAMPLES[0]), ("n_fine", 0, 1024, PREVIEW_SAMPLES[1])):
        v = s.config.get(k, getattr(rs, k))
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
            raise ValueError(f"config.{k} must be a number in [{lo}, {hi}], got {v!r}")
        setattr(rs, k, float(v) if cap is None else min(int(v), cap))
    if not rs.near < rs.far:
        raise ValueError(f"config: need near < far, got {rs.near} and {rs.far}")
    field = field_from_snapshot(fcfg, {k: np.array(v) for k, v in s.arrays.items()}, device="cpu")
    return field, rs


def preview_camera(camera: dict, width: int):
    """The frame camera (undistorted: the player undistorts the frames) resized to ``width``
    pixels, keeping the aspect; never enlarged."""
    from fmapping.camera import PinholeCamera

    cam = PinholeCamera.from_dict(camera).undistorted()
    w = max(1, min(int(width), cam.width))
    return cam.resized(w, max(1, round(cam.height * w / cam.width)))


def render_view(field, rs: RenderSettings, camera, c2w) -> tuple[np.ndarray, np.ndarray]:
    """Colour (H, W, 3) uint8 and depth (H, W) float32 metres rendered from ``field`` at ``c2w``
    with ``camera``. The depth is the expected surface depth (``depth / acc``) where the ray is
    mostly opaque and 0 elsewhere (no depth in rerun), so empty space does not show as near."""
    import torch

    from fmapping.render import render_image

    r = render_image(field, camera, np.asarray(c2w, np.float64), rs.near, rs.far, rs.n_coarse,
                     background=0.0, n_importance=rs.n_fine, chunk=PREVIEW_CHUNK)
    rgb = (r["rgb"].clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
    acc = r["acc"].cpu().numpy()
    depth = np.where(acc > 0.5, r["depth_normalized"].cpu().numpy(), 0.0).astype(np.float32)
    return rgb, depth


def mesh_poses(poses: dict, every: int = 5, max_poses: int = MESH_MAX_POSES) -> list[np.ndarray]:
    """Every ``every``-th pose of ``poses`` (frame -> c2w) in frame order and the newest, at most
    about ``max_poses`` of them (the step grows on long runs): enough views to cull the mesh to
    what the run saw at a bounded cost."""
    seqs = sorted(poses)
    if not seqs:
        return []
    step = max(int(every), math.ceil(len(seqs) / max_poses))
    keep = seqs[::step]
    if keep[-1] != seqs[-1]:
        keep.append(seqs[-1])
    return [np.asarray(poses[k], np.float64) for k in keep]


def field_mesh(field, rs: RenderSettings, camera, poses: list, resolution: int = 64):
    """(vertices, faces, colours) of a coarse marching-cubes mesh of ``field`` culled to the
    frustums of ``poses`` (no occlusion test: that renders once per pose, too dear for a preview)."""
    from fmapping.export import export_mesh

    return export_mesh(field, field.aabb, int(resolution), poses, camera, near=rs.near, far=rs.far,
                       grid_chunk=MESH_GRID_CHUNK)


def warm_previews(width: int = 8, mesh_resolution: int = 8) -> None:
    """One render ``width`` pixels wide (4:3) and one mesh of a small CP field, logged nowhere. The
    previews' one-time costs (torch's first kernels on this thread, scipy's and scikit-image's imports
    for the mesh: ~45 MB) are then taken when the view starts, not as a step in the middle of the run
    at the first field snapshot (``bench/results/view_memory/``)."""
    import torch

    from fmapping.camera import PinholeCamera
    from fmapping.field import FieldConfig, build_field

    field = build_field(dataclasses.replace(FieldConfig(), resolution=8), torch.tensor([[-1.0] * 3, [1.0] * 3]))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():  # a field with a surface to mesh whatever the initialisation
        for p in field.parameters():
            p.add_(0.5 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
    w = max(4, int(width))
    cam = PinholeCamera(fx=float(w), fy=float(w), cx=(w - 1) / 2, cy=(w * 3 // 4 - 1) / 2, width=w, height=w * 3 // 4)
    c2w = np.eye(4)
    c2w[2, 3] = -2.0  # outside the box, looking into it (+z)
    rs = RenderSettings(n_coarse=PREVIEW_SAMPLES[0], n_fine=PREVIEW_SAMPLES[1])
    with torch.no_grad():
        render_view(field, rs, cam, c2w)
    field_mesh(field, rs, cam, [c2w], resolution=max(2, int(mesh_resolution)))


#: The job that warms the previews up (:func:`warm_previews`) on the preview thread, and how long the
#: service waits for it at the start (seconds; it goes on after that, the first preview then pays).
WARM_UP = "warm-up"
WARM_UP_TIMEOUT = 60.0


@dataclasses.dataclass
class FieldJob:
    """What to do with one field snapshot, captured on the view's thread (the worker must not
    read the Viewer's dicts while they change): render at ``render_c2w`` for frame ``render_seq``
    and / or mesh with ``mesh_poses``."""

    snapshot: P.FieldSnapshot
    camera: dict
    render_seq: Optional[int] = None
    render_c2w: Optional[np.ndarray] = None
    mesh_poses: Optional[list] = None


class LatestWorker:
    """One daemon thread that runs ``fn(job)`` for the newest submitted job: a job submitted while
    another is pending replaces it (a newer field snapshot makes the older one moot). Errors go
    to ``on_error`` and never stop the thread."""

    def __init__(self, fn: Callable, on_error: Callable[[BaseException], None]):
        self.fn, self.on_error = fn, on_error
        self._cond = threading.Condition()
        self._pending = None
        self._busy = False
        self._closed = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._loop, name="view-field", daemon=True)
        self._thread.start()

    def submit(self, job) -> None:
        with self._cond:
            if self._pending is not None:
                self.dropped += 1
            self._pending = job
            self._cond.notify_all()

    def _loop(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closed:
                    self._cond.wait()
                if self._pending is None:
                    return
                job, self._pending, self._busy = self._pending, None, True
            try:
                self.fn(job)
            except Exception as e:  # a bad snapshot must not end the previews
                self.on_error(e)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def wait_idle(self, timeout: float) -> bool:
        """Wait until nothing runs or is pending; False after ``timeout`` seconds."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._pending is not None or self._busy:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def close(self, timeout: float = 30.0) -> None:
        """Finish what is pending (up to ``timeout`` seconds), then stop the thread."""
        self.wait_idle(timeout)
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout=1.0)


class Viewer:
    """Zenoh-free: turns decoded messages into rerun log calls on a RecordingStream."""

    PRIORITY = ("tracker", "external", "gt")

    def __init__(self, rec, primary: str = "auto", image_every: int = 1, depth_every: int = 0, jpeg_quality: int = 85,
                 render_every: float = 2.0, render_width: int = 160, mesh_every: float = 10.0,
                 mesh_resolution: int = 64,
                 background: bool = False, clock: Callable[[], float] = time.monotonic,
                 on_error: Optional[Callable[[BaseException], None]] = None, torch_threads: int = 0):
        """``render_every`` / ``mesh_every``: seconds (of ``clock``) between renders / live meshes of
        the field (render 0: never; mesh 0: only at the end, < 0: never). ``background``: do that
        work on a thread (the service) instead of inside ``on_field`` (tests). ``on_error`` gets
        what a render or mesh raised (default: logged). ``torch_threads`` > 0: torch's thread count
        for the previews (process-wide: the service sets 1, the view must not compete with the run
        for cores; tests leave it)."""
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
        self.render_every, self.render_width = float(render_every), int(render_width)
        self.mesh_every, self.mesh_resolution = float(mesh_every), int(mesh_resolution)
        self.clock = clock
        self.on_error = on_error or (lambda e: logging.getLogger("view").warning("field preview failed: %s", e))
        self.field: Optional[P.FieldSnapshot] = None  # the newest snapshot
        self._field_camera: Optional[dict] = None  # the snapshot's camera when no frame came yet
        self._last_render = self._last_mesh = -math.inf
        self.renders = self.meshes = 0  # field previews logged (tests, counters)
        self.render_seconds = self.mesh_seconds = 0.0  # what the last render / mesh took (PREVIEW_DUTY)
        self.torch_threads = int(torch_threads)
        self.worker = LatestWorker(self.run_field_job, self.on_error) if background else None
        rec.log("world", rr.ViewCoordinates.RDF, static=True)

    def logs_depth(self, f: P.Frame) -> bool:
        """Whether frame ``f``'s depth is logged: only with ``depth_every`` (the run uses depth),
        every ``depth_every``-th frame. The frames of an RGB-only run can carry the dataset's
        ground-truth depth; showing it would suggest the system used or estimated it."""
        return f.depth is not None and self.depth_every > 0 and self.frames % self.depth_every == 0

    def _primary_for(self, source: str) -> bool:
        return source == self.primary if self.primary != "auto" else source == self.primary_source()

    def on_frame(self, f: P.Frame) -> None:
        rr = self.rr
        self.rec.set_time("frame", sequence=f.seq)
        if f.camera != self._camera:
            c = f.camera
            pinhole = rr.Pinhole(focal_length=[c["fx"], c["fy"]], principal_point=[c["cx"], c["cy"]],
                                 resolution=[c["width"], c["height"]])
            self.rec.log("world/camera/image", pinhole, static=True)
            self._camera = f.camera
        if self.image_every and self.frames % self.image_every == 0:
            img = rr.Image(f.rgb)
            self.rec.log("world/camera/image",
                         img.compress(jpeg_quality=self.jpeg_quality) if self.jpeg_quality else img)
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
        self.field = s
        cam = s.config.get("camera") if isinstance(s.config, dict) else None
        if isinstance(cam, dict):
            self._field_camera = cam
        job = self.field_job(s, self.clock())
        if job is not None:
            self.submit(job)
            if self.worker is None:  # the job set the rendered frame's time on this thread
                self.rec.set_time("frame", sequence=max(s.frame_seq, 0))

    def primary_source(self) -> Optional[str]:
        """The pose source the view draws as the run's trajectory (``world/camera``)."""
        if self.primary != "auto":
            return self.primary if self.primary in self.poses else None
        seen = [s for s in self.PRIORITY if s in self.poses] + sorted(s for s in self.poses if s not in self.PRIORITY)
        return seen[0] if seen else None

    def field_job(self, s: P.FieldSnapshot, now: float, final: bool = False) -> Optional[FieldJob]:
        """The render and / or mesh due for snapshot ``s`` at time ``now`` (the rate limits), or None.
        The render is of the newest frame with a pose of the primary source (else the snapshot's
        own newest frame and pose); ``final``: the end-of-run mesh, whatever the time."""
        camera = self._camera or self._field_camera
        if camera is None:
            return None
        job = FieldJob(snapshot=s, camera=camera)
        render_gap = max(self.render_every, self.render_seconds / PREVIEW_DUTY)
        if not final and self.render_every > 0 and now - self._last_render >= render_gap:
            src = self.primary_source()
            if src is not None:
                job.render_seq = max(self.poses[src])
                job.render_c2w = self.poses[src][job.render_seq]
            elif s.frame_c2w is not None:
                job.render_seq, job.render_c2w = max(s.frame_seq, 0), np.asarray(s.frame_c2w)
            if job.render_c2w is not None:
                self._last_render = now
        mesh_gap = max(self.mesh_every, self.mesh_seconds / PREVIEW_DUTY)
        mesh_due = self.mesh_every > 0 and now - self._last_mesh >= mesh_gap
        if (mesh_due and not final) or (final and self.mesh_every >= 0):
            src = self.primary_source()
            poses = self.poses.get(src, {}) if src is not None else {}
            if not poses and s.frame_c2w is not None:
                poses = {max(s.frame_seq, 0): np.asarray(s.frame_c2w)}
            if poses:
                job.mesh_poses = mesh_poses(poses)
                self._last_mesh = now
        return job if job.render_c2w is not None or job.mesh_poses is not None else None

    def submit(self, job: FieldJob) -> None:
        if self.worker is not None:
            self.worker.submit(job)
            return
        try:
            self.run_field_job(job)
        except Exception as e:  # a bad snapshot must not stop the view
            self.on_error(e)

    def warm_up(self) -> None:
        """Take the previews' one-time costs now, on the thread that will render (:func:`warm_previews`);
        a field snapshot submitted before it starts replaces it (that preview pays them instead)."""
        self.submit(WARM_UP)

    def run_field_job(self, job: FieldJob) -> None:
        """Rebuild the field of ``job`` and log what it asks for: the rendered colour and depth at
        the frame's time under ``world/camera/rendered`` (next to the input image), the live mesh
        at the snapshot's time. Sets the time on the calling thread (rerun's time is per thread).
        The freed temporaries go back to the kernel afterwards (glibc keeps them in the thread's arena)."""
        from fmapping.runtime import release_free_memory

        try:
            self._run_field_job(job)
        finally:
            release_free_memory()

    def _run_field_job(self, job: FieldJob) -> None:
        rr = self.rr
        if self.torch_threads > 0:
            import torch

            torch.set_num_threads(self.torch_threads)
            self.torch_threads = 0
        if job is WARM_UP:
            warm_previews(self.render_width, self.mesh_resolution)
            return
        field, rs = field_of_snapshot(job.snapshot)
        if job.render_c2w is not None:
            t0 = time.perf_counter()
            cam = preview_camera(job.camera, self.render_width)
            rgb, depth = render_view(field, rs, cam, job.render_c2w)
            self.render_seconds = time.perf_counter() - t0
            self.rec.set_time("frame", sequence=job.render_seq)
            self.rec.log("world/camera/rendered",
                         rr.Pinhole(focal_length=[cam.fx, cam.fy], principal_point=[cam.cx, cam.cy],
                                    resolution=[cam.width, cam.height], image_plane_distance=0.2))
            self.rec.log("world/camera/rendered/rgb", rr.Image(rgb))
            self.rec.log("world/camera/rendered/depth", rr.DepthImage(depth, meter=1.0))
            self.renders += 1
        if job.mesh_poses is not None:
            from fmapping.camera import PinholeCamera

            t0 = time.perf_counter()
            cam = PinholeCamera.from_dict(job.camera).undistorted()
            v, f, c = field_mesh(field, rs, cam, job.mesh_poses, self.mesh_resolution)
            self.mesh_seconds = time.perf_counter() - t0
            self.rec.set_time("frame", sequence=max(job.snapshot.frame_seq, 0))
            if len(f):
                self.rec.log("world/map/mesh_live", rr.Mesh3D(vertex_positions=np.asarray(v, np.float32),
                                                               triangle_indices=np.asarray(f, np.uint32),
                                                               vertex_colors=c))
            else:
                self.rec.log("world/map/mesh_live", rr.Clear(recursive=False))
            self.meshes += 1

    def finish_field(self, final_mesh_logged: bool = False, timeout: float = 60.0, interrupted: bool = False) -> None:
        """At the end: let the pending preview finish, then log the live mesh of the newest field
        (unless ``--mesh-every`` < 0), or clear it when the mapper's final mesh.ply was logged
        (``world/map/mesh``: two meshes on top of each other would hide the final one). ``interrupted``
        (a stop signal): no waiting for a preview and no end mesh, a service must stop promptly."""
        if self.worker is not None:
            self.worker.close(0.0 if interrupted else timeout)
            self.worker = None
        s = self.field
        if s is None or interrupted:
            return
        if final_mesh_logged:
            self.rec.set_time("frame", sequence=max(s.frame_seq, 0))
            self.rec.log("world/map/mesh_live", self.rr.Clear(recursive=False))
            return
        job = self.field_job(s, self.clock(), final=True)
        if job is not None:
            self.submit(job)

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

    def finish(self, final_mesh_logged: bool = False, interrupted: bool = False) -> None:
        self.finish_field(final_mesh_logged, interrupted=interrupted)
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

    def preview_failed(e: BaseException) -> None:
        svc.counters.inc("preview_errors")
        svc.status.error(f"field preview: {e}")
        svc.log.warning("field preview failed: %s", e)

    view = Viewer(rec, args.primary, args.image_every, args.depth_every, args.jpeg_quality,
                  render_every=args.render_every, render_width=args.render_width, mesh_every=args.mesh_every,
                  mesh_resolution=args.mesh_resolution, background=True, on_error=preview_failed, torch_threads=1)
    if args.render_every > 0 or args.mesh_every >= 0:
        # torch (~190 MB) and the previews' first-run costs at the start, not as a step mid-run; waited for
        # before subscribing so that the imports do not hold the bus's callbacks back
        view.warm_up()
        view.worker.wait_idle(WARM_UP_TIMEOUT)
    peers = Peers()
    wait_done = names(args.wait_done)
    for key, ch in ((svc.keys.frames, "frames"), (svc.keys.poses(), "poses"), (svc.keys.points, "points"),
                    (svc.keys.field, "field"), (svc.keys.status(), "status"), (svc.keys.control, "control")):
        svc.subscribe(key, ch)
    svc.start()
    serve_until_end(svc, peers, lambda ch, key, data: handle_message(svc, view, peers, ch, key, data, wait_done),
                    wait_done, args.final_timeout)
    final = view.log_final_outputs(args.final_outputs, since=started) if args.final_outputs else []
    view.finish(final_mesh_logged="world/map/mesh" in final, interrupted=svc.shutdown.requested)
    if serving(args) and not args.exit_at_end and not svc.shutdown.requested:
        svc.log.info("sequence ended; still serving the viewer (Ctrl-C to quit)")
        while not svc.shutdown.wait(0.5):
            pass
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m services.io view``."""
    return add_args(service_parser("services.io view", __doc__))


def main(argv=None, session=None, keys=None) -> int:
    args = build_parser().parse_args(argv)
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
