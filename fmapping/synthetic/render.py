"""Ray casting the scene into exact colour (supersampled) and z-depth images."""
from __future__ import annotations

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.synthetic.scene import Scene
from fmapping.synthetic.texture import _colour_columns, _surface_texture


def _cast(scene: Scene, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cast_rays` on component arrays ``d`` (3, M) (row layout keeps numpy fast)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        # room: the ray leaves through the nearest of the three planes it heads for
        tx, ty, tz = (np.where(d[k] > 0, scene.room_max[k] - o[k], scene.room_min[k] - o[k]) * inv[k]
                      for k in range(3))
        t = np.minimum(np.minimum(tx, ty), tz)
        sid = np.where(t == tx, np.where(d[0] > 0, 3, 2),
                       np.where(t == ty, np.where(d[1] > 0, 5, 4), np.where(d[2] > 0, 1, 0)))
        for b, box in enumerate(scene.boxes):
            rot = box.rotation  # a yaw: the local z axis is the world z axis
            ol = (o - box.center) @ rot
            dls = (rot[0, 0] * d[0] + rot[1, 0] * d[1], rot[0, 1] * d[0] + rot[1, 1] * d[1], d[2])
            near, far = None, None
            lows = []
            for k in range(3):
                ik = 1.0 / dls[k]
                ta = (-box.half[k] - ol[k]) * ik
                tb = (box.half[k] - ol[k]) * ik
                lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
                lows.append(lo)
                near = lo if near is None else np.maximum(near, lo)
                far = hi if far is None else np.minimum(far, hi)
            hit = np.flatnonzero((near <= far) & (near > 0) & (near < t))
            if not len(hit):
                continue
            tn = near[hit]
            ax = np.where(tn == lows[0][hit], 0, np.where(tn == lows[1][hit], 1, 2))
            dl_ax = np.where(ax == 0, dls[0][hit], np.where(ax == 1, dls[1][hit], dls[2][hit]))
            t[hit] = tn
            sid[hit] = 6 + 6 * b + 2 * ax + (dl_ax < 0)
    return t, sid


def cast_rays(scene: Scene, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays ``origin + t * dirs`` (M, 3) (origin inside the room, outside all boxes).

    Returns ``t`` (M,) in units of ``dirs`` and the surface id (M,) of the hit.
    """
    o = np.asarray(origin, np.float64).reshape(3)
    d = np.ascontiguousarray(np.asarray(dirs, np.float64).reshape(-1, 3).T)
    return _cast(scene, o, d)


def _camera_dirs(camera: PinholeCamera, c2w: np.ndarray, du: float = 0.0, dv: float = 0.0) -> np.ndarray:
    """World directions (3, H*W) of pixel centres shifted by (du, dv), z-normalised in the camera."""
    x = (np.arange(camera.width) + du - camera.cx) / camera.fx
    y = (np.arange(camera.height) + dv - camera.cy) / camera.fy
    xs = np.broadcast_to(x[None, :], (camera.height, camera.width)).ravel()
    ys = np.broadcast_to(y[:, None], (camera.height, camera.width)).ravel()
    r = c2w[:3, :3]
    return r[:, :1] * xs + r[:, 1:2] * ys + r[:, 2:3]


def _interior_pixels(sid: np.ndarray) -> np.ndarray:
    """(H, W) mask of pixels whose 8 neighbours see the same surface (False on the image border)."""
    h, w = sid.shape
    pad = np.pad(sid, 1, mode="constant", constant_values=-1)
    same = np.ones((h, w), bool)
    for dy in range(3):
        for dx in range(3):
            same &= pad[dy:dy + h, dx:dx + w] == sid
    return same


def _segments(ids: np.ndarray):
    """Yield (id, positions) for each distinct value of a small non-negative int array."""
    order = np.argsort(ids.astype(np.int16), kind="stable")  # radix sort
    sorted_ids = ids[order]
    cuts = np.flatnonzero(np.diff(sorted_ids)) + 1
    for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(ids)]])):
        yield int(sorted_ids[a]), order[a:b]


def _plane_colours(scene: Scene, camera: PinholeCamera, c2w: np.ndarray, s: int, pix: np.ndarray,
                   offsets: np.ndarray) -> np.ndarray:
    """Mean colour (3, K) over sub-pixel ``offsets`` (J, 2) of pixels ``pix`` (K,) known to see surface ``s``.

    The texture coordinates on a plane are ratios of affine functions of the pixel
    coordinates (a homography), so no 3-D points are formed.
    """
    rect = scene.rects[s]
    r, o = c2w[:3, :3], c2w[:3, 3]
    a = rect.e1 / np.linalg.norm(rect.e1)
    b = rect.e2 / np.linalg.norm(rect.e2)
    nrm = rect.normal
    ra, rb, rn = r.T @ a, r.T @ b, r.T @ nrm  # the surface axes in camera coordinates
    num = float(nrm @ (rect.origin - o))  # ray parameter t = num / (n . d)
    u0, v0 = float(a @ (o - rect.origin)), float(b @ (o - rect.origin))
    px = (pix % camera.width).astype(np.float64)
    py = (pix // camera.width).astype(np.float64)
    x = ((px[None, :] + offsets[:, :1]) - camera.cx) / camera.fx
    y = ((py[None, :] + offsets[:, 1:]) - camera.cy) / camera.fy
    t = num / (rn[0] * x + rn[1] * y + rn[2])
    u = u0 + t * (ra[0] * x + ra[1] * y + ra[2])
    v = v0 + t * (rb[0] * x + rb[1] * y + rb[2])
    col = _surface_texture(scene.texture, s, u.ravel(), v.ravel())
    return col.reshape(3, len(offsets), len(pix)).mean(1)


def render_view(scene: Scene, camera: PinholeCamera, c2w, supersample: int = 2, return_ids: bool = False):
    """Exact RGB (H, W, 3) uint8 and z-depth (H, W) float32 metres of ``scene`` seen from ``c2w``.

    Colour averages ``supersample x supersample`` sub-pixel rays (1 = the centre ray only);
    depth and (with ``return_ids``) the surface id map (H, W) come from the centre ray.
    Sub-pixel rays of pixels whose 8 neighbours all see one surface are intersected with
    that surface's plane directly (exact: every feature is far wider than a pixel); the
    others are cast against the whole scene.
    """
    if camera.dist is not None:
        raise ValueError("render_view renders an ideal pinhole camera; camera.dist must be None")
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    c2w = np.asarray(c2w, np.float64).reshape(4, 4)
    o = c2w[:3, 3]
    h, w = camera.height, camera.width
    d = _camera_dirs(camera, c2w)
    t, sid = _cast(scene, o, d)
    depth = t.reshape(h, w).astype(np.float32)
    n = int(supersample)
    if n == 1:
        col = _colour_columns(scene, o[:, None] + t * d, sid)
    else:
        interior = _interior_pixels(sid.reshape(h, w)).ravel()
        inner, edge = np.flatnonzero(interior), np.flatnonzero(~interior)
        offs1 = (np.arange(n) + 0.5) / n - 0.5
        offsets = np.stack(np.meshgrid(offs1, offs1, indexing="xy"), -1).reshape(-1, 2)  # rows (du, dv)
        col = np.empty((3, h * w), np.float32)
        for s, pos in _segments(sid[inner]):
            pix = inner[pos]
            col[:, pix] = _plane_colours(scene, camera, c2w, s, pix, offsets)
        if len(edge):
            pts, ids = [], []
            for du, dv in offsets:
                ds = _camera_dirs(camera, c2w, du, dv)[:, edge]
                ts, ss = _cast(scene, o, ds)
                pts.append(o[:, None] + ts * ds)
                ids.append(ss)
            ce = _colour_columns(scene, np.concatenate(pts, 1), np.concatenate(ids))
            col[:, edge] = ce.reshape(3, len(offsets), len(edge)).mean(1)
    rgb = np.round(np.clip(col.T, 0, 1) * 255).astype(np.uint8).reshape(h, w, 3)
    if return_ids:
        return rgb, depth, sid.reshape(h, w)
    return rgb, depth

