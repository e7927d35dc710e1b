"""Ground-truth geometry of a scene: the surface mesh, the area-uniform point cloud and which
points a frame sees."""
from __future__ import annotations

import math

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.synthetic.scene import Scene
from fmapping.synthetic.texture import surface_colour

VISIBLE_TOL_M = 0.01  # |projected z - rendered depth| for a GT point to count as seen


def _inside_footprints(scene: Scene, pts: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(pts), bool)
    for box in scene.boxes:
        q = np.abs(box.to_local(pts)[:, :2]) - box.half[:2]
        inside |= (q < 0).all(1)
    return inside


def gt_mesh(scene: Scene, spacing: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of every exposed surface: vertices (V, 3), faces (F, 3), vertex colours (V, 3) float.

    Each rectangle is a regular grid of about ``spacing`` metres; faces wind counter-clockwise
    around the outward normal. The floor is kept whole (under furniture too).
    """
    verts, faces, cols = [], [], []
    nv = 0
    for r in scene.rects:
        if not r.exposed:
            continue
        na = max(1, int(math.ceil(np.linalg.norm(r.e1) / spacing)))
        nb = max(1, int(math.ceil(np.linalg.norm(r.e2) / spacing)))
        a, b = np.meshgrid(np.linspace(0, 1, na + 1), np.linspace(0, 1, nb + 1), indexing="ij")
        p = r.origin + a.reshape(-1, 1) * r.e1 + b.reshape(-1, 1) * r.e2
        idx = np.arange((na + 1) * (nb + 1)).reshape(na + 1, nb + 1) + nv
        i00, i10, i11, i01 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        tri = np.concatenate([np.stack([i00, i10, i11], -1).reshape(-1, 3),
                              np.stack([i00, i11, i01], -1).reshape(-1, 3)])
        verts.append(p)
        faces.append(tri)
        cols.append(surface_colour(scene, p, np.full(len(p), r.sid)))
        nv += len(p)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(cols)


def gt_cloud(scene: Scene, density: float = 1e4, max_points: int = 500_000, seed: int = 0):
    """Points sampled uniformly by area on every exposed surface (floor under furniture excluded).

    ``density`` is points per m^2 (1e4 = 1 / cm^2), reduced to respect ``max_points``.
    Returns points (M, 3), surface ids (M,) and colours (M, 3) float.
    """
    rng = np.random.default_rng([int(seed), 7003])
    rects = [r for r in scene.rects if r.exposed]
    area = np.array([r.area for r in rects])
    dens = min(float(density), max_points / area.sum())
    pts, ids = [], []
    for r, ar in zip(rects, area):
        k = int(math.floor(ar * dens))
        ab = rng.random((k, 2))
        p = r.origin + ab[:, :1] * r.e1 + ab[:, 1:] * r.e2
        if r.sid == 0:
            p = p[~_inside_footprints(scene, p)]
        pts.append(p)
        ids.append(np.full(len(p), r.sid, np.int64))
    pts, ids = np.concatenate(pts), np.concatenate(ids)
    return pts, ids, surface_colour(scene, pts, ids)


def _visible_columns(camera: PinholeCamera, c2w: np.ndarray, depth: np.ndarray, cols: np.ndarray,
                     tol: float) -> np.ndarray:
    r, t = c2w[:3, :3].tolist(), c2w[:3, 3].tolist()  # python floats keep float32 columns float32
    q = [cols[k] - t[k] for k in range(3)]
    x, y, z = (q[0] * r[0][j] + q[1] * r[1][j] + q[2] * r[2][j] for j in range(3))
    ok = z > 1e-3
    zs = np.where(ok, z, 1)
    u = np.round(x / zs * camera.fx + camera.cx)
    v = np.round(y / zs * camera.fy + camera.cy)
    ok &= (u >= 0) & (u <= camera.width - 1) & (v >= 0) & (v <= camera.height - 1)
    idx = np.where(ok, v * camera.width + u, 0).astype(np.int64)
    dz = depth.ravel()[idx]
    return ok & (dz > 0) & (np.abs(z - dz) < tol)


def visible_mask(camera: PinholeCamera, c2w: np.ndarray, depth: np.ndarray, pts: np.ndarray,
                 tol: float = VISIBLE_TOL_M) -> np.ndarray:
    """Which world points (M, 3) a frame sees: inside the image and within ``tol`` of its depth
    map at the nearest pixel."""
    cols = np.ascontiguousarray(np.asarray(pts, np.float64).reshape(-1, 3).T)
    return _visible_columns(camera, np.asarray(c2w, np.float64), np.asarray(depth), cols, tol)

