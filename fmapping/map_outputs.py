"""What a run writes as its map, in one place: ``write_map_outputs`` (the files of ``fmapping map`` and
``fmapping slam``) and ``map_points`` / ``map_mesh`` (the mapper service's live snapshots and final files).
The extraction itself is :mod:`fmapping.export`."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping import protocol as P

MESH_RESOLUTION = 160  # marching-cubes grid nodes per axis (level 0.5 of the per-cell opacity)


def write_map_outputs(mapper, poses: dict, camera, out: Path, *, near: float, far: float,
                      cloud_samples: Optional[tuple[int, int]] = None, mesh_samples: tuple[int, int] = (48, 16),
                      mesh_resolution: int = MESH_RESOLUTION, center: Optional[np.ndarray] = None,
                      scale: float = 1.0) -> dict:
    """Export the map seen from ``poses`` (dict frame id -> c2w) into ``out/map.ply`` (coloured
    point cloud, :func:`fmapping.export.export_point_cloud`, rendered with ``cloud_samples``
    = (coarse, fine) samples per ray, the exporter's defaults when None) and ``out/mesh.ply``
    (:func:`fmapping.export.export_mesh` on a ``mesh_resolution``^3 grid, culled with depth rendered
    with ``mesh_samples``).
    With ``center`` both are written through the similarity ``x -> center + scale (x - center)``
    (the SLAM output frame). Returns ``{"points", "mesh_vertices", "mesh_faces", "seconds"}``."""
    from fmapping.export import export_mesh, export_point_cloud
    from fmapping.ply import write_ply

    t0 = time.perf_counter()
    kw = {} if cloud_samples is None else {"n_samples": cloud_samples[0], "n_importance": cloud_samples[1]}
    pts, cols = export_point_cloud(mapper, poses, camera, near=near, far=far, **kw)

    def render_fn(c2w, cam):
        r = mapper.render(c2w, cam, samples=mesh_samples)
        return {"depth": r["depth_normalized"], "acc": r["acc"]}

    verts, faces, vcols = export_mesh(mapper.field, mapper.aabb, mesh_resolution, poses, camera,
                                      render=render_fn, near=near, far=far)
    if center is not None:
        c = np.asarray(center, np.float64)
        if len(pts):
            pts = c + scale * (np.asarray(pts) - c)
        if len(verts):
            verts = c + scale * (np.asarray(verts) - c)
    write_ply(out / "map.ply", pts, cols)
    write_ply(out / "mesh.ply", verts, vcols, faces)
    return {"points": int(len(pts)), "mesh_vertices": int(len(verts)), "mesh_faces": int(len(faces)),
            "seconds": time.perf_counter() - t0}


def map_points(mapper, max_points: int, final: bool = False, quick: bool = False,
               seed: int = 0, should_stop=None) -> tuple[np.ndarray, np.ndarray]:
    """Coloured points of the map (:func:`fmapping.export.export_point_cloud`), at most ``max_points``.

    Live snapshots render up to 6 of the mapper's views (:meth:`~fmapping.mapping.Mapper.view_ids`:
    keyframes and the local window) at <= 64 px width (cheap; ``quick``: 4 at 48 px, for stopping on
    a signal); ``final`` renders every view at full resolution (stride 2) with the input images for
    colour. Returns float32 (N, 3), uint8 (N, 3)."""
    from fmapping.export import export_point_cloud

    cfg = mapper.cfg
    poses = mapper.frame_poses()
    ids = mapper.view_ids() or sorted(poses)
    cam = mapper.camera
    images = None
    check_views = 8
    if final:
        stride, voxel = 2, 0.02
        try:
            images = {i: mapper.keyframe_image(i) for i in ids}
        except KeyError:
            images = None
    else:
        views, width = (4, 48.0) if quick else (6, 64.0)
        if len(ids) > views:
            ids = [ids[int(round(i))] for i in np.linspace(0, len(ids) - 1, views)]
        scale = min(1.0, width / cam.width)
        cam = cam.scaled(scale) if scale < 1.0 else cam
        stride, voxel, check_views = 1, 0.03, views - 1
    pts, cols = export_point_cloud(mapper, {i: poses[i] for i in ids}, cam, images=images, stride=stride,
                                   voxel=voxel, near=cfg.near, far=cfg.far, n_samples=cfg.n_coarse,
                                   n_importance=cfg.n_fine, check_views=max(1, check_views),
                                   should_stop=should_stop)
    return _bounded(np.asarray(pts, np.float32).reshape(-1, 3), np.asarray(cols).reshape(-1, 3), max_points, seed)


def map_mesh(mapper, resolution: int = 96, should_stop=None):
    """(vertices, faces, colours) by marching cubes (:func:`fmapping.export.export_mesh`), culled to
    what the mapper's views (keyframes and the local window) saw."""
    from fmapping.export import export_mesh

    cfg = mapper.cfg
    poses = mapper.frame_poses()
    ids = mapper.view_ids() or sorted(poses)

    def render(c2w, cam):
        r = mapper.render(c2w, cam, samples=(cfg.n_coarse, cfg.n_fine))
        acc = r["acc"]
        return {"rgb": r["rgb"], "acc": acc, "depth": np.where(acc > 1e-6, r["depth"] / np.maximum(acc, 1e-6), 0.0)}

    v, f, c = export_mesh(mapper.field, mapper.aabb, resolution, {i: poses[i] for i in ids}, mapper.camera,
                          render=render, near=cfg.near, far=cfg.far, should_stop=should_stop)
    return np.asarray(v), np.asarray(f), np.asarray(c)


def _bounded(pts: np.ndarray, cols: np.ndarray, max_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    cols = np.asarray(cols)
    if cols.dtype != np.uint8:
        cols = np.clip(np.round(cols * 255 if cols.max(initial=0) <= 1.0 else cols), 0, 255).astype(np.uint8)
    ok = np.isfinite(pts).all(1)
    pts, cols = pts[ok], cols[ok]
    limit = min(int(max_points), P.MAX_POINTS)
    if len(pts) > limit:
        idx = np.sort(np.random.default_rng(seed).choice(len(pts), limit, replace=False))
        pts, cols = pts[idx], cols[idx]
    return np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(cols.reshape(-1, 3), np.uint8)
