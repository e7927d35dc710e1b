"""Map export: a coloured point cloud and a coloured triangle mesh from a neural field.

Conventions are those of :mod:`fmapping.geometry` / :mod:`fmapping.camera` (metres,
camera-to-world poses, z-normalised rays whose parameter is the camera depth).

* :func:`export_point_cloud` renders depth, opacity and colour at the given poses
  (keyframes), keeps pixels whose accumulated opacity is high and whose depth is
  confirmed by the renders of other views (multi-view depth consistency), optionally
  checks photo-consistency against the input images, back-projects them and
  voxel-downsamples the result. Floaters (low opacity, or seen from one view only)
  are dropped.
* :func:`export_mesh` runs marching cubes (``skimage.measure.marching_cubes``) on
  the per-cell opacity of the field sampled on a regular grid, and keeps the
  triangles whose vertices some camera saw (in its frustum and not behind the
  rendered surface).
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.render import raw_to_alpha, render_image

RenderFn = Callable[[np.ndarray, PinholeCamera], dict]


def _render_fn(source, near: float, far: float, n_samples: int, n_importance: int) -> RenderFn:
    """A function ``(c2w, camera) -> dict(rgb, depth (normalised), acc)`` numpy, for a Mapper or a Field."""
    if hasattr(source, "render") and hasattr(source, "field"):  # Mapper
        def fn(c2w, cam):
            out = source.render(c2w, cam, samples=(n_samples, n_importance))
            return {"rgb": out["rgb"], "depth": out["depth_normalized"], "acc": out["acc"]}
        return fn

    def fn(c2w, cam):
        out = render_image(source, cam, c2w, near, far, n_samples, n_importance=n_importance)
        return {"rgb": out["rgb"].clamp(0, 1).cpu().numpy(), "depth": out["depth_normalized"].cpu().numpy(),
                "acc": out["acc"].cpu().numpy()}
    return fn


def voxel_downsample(points: np.ndarray, colors: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Average points and colours per cubic voxel of side ``voxel`` (<= 0: unchanged)."""
    if voxel <= 0 or len(points) == 0:
        return points, colors
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    out_p = np.zeros((len(counts), 3))
    out_c = np.zeros((len(counts), 3))
    np.add.at(out_p, inv, points)
    np.add.at(out_c, inv, colors.astype(np.float64))
    return out_p / counts[:, None], out_c / counts[:, None]


def _project(c2w: np.ndarray, cam: PinholeCamera, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (M, 3) -> pixel (M, 2) and camera z (M,) in view ``c2w``."""
    r, t = c2w[:3, :3], c2w[:3, 3]
    pc = (pts - t) @ r
    z = pc[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    uv = np.stack([cam.fx * pc[:, 0] / zs + cam.cx, cam.fy * pc[:, 1] / zs + cam.cy], -1)
    return uv, z


def _lookup_nearest(img: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-pixel values of ``img`` (H, W[, C]) at ``uv`` and the in-image mask."""
    h, w = img.shape[:2]
    ui = np.round(uv[:, 0]).astype(np.int64)
    vi = np.round(uv[:, 1]).astype(np.int64)
    ok = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    vals = img[np.clip(vi, 0, h - 1), np.clip(ui, 0, w - 1)]
    return vals, ok


def export_point_cloud(
    source,
    poses: Union[dict, Sequence[np.ndarray]],
    camera: PinholeCamera,
    images: Optional[dict] = None,
    stride: int = 2,
    voxel: float = 0.02,
    min_acc: float = 0.9,
    depth_tol: float = 0.03,
    min_consistent: int = 1,
    check_views: int = 8,
    photo_tol: Optional[float] = None,
    near: float = 0.1,
    far: float = 10.0,
    n_samples: int = 64,
    n_importance: int = 32,
    max_depth: Optional[float] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Coloured point cloud of the map seen from ``poses``.

    ``source``: a :class:`fmapping.mapper.Mapper` (its renderer is used) or a field.
    ``poses``: dict id -> c2w or a list of c2w; ``images``: optional dict/list of the
    input RGB (uint8) at those poses, same keys/order, used for the point colour and
    the photo-consistency test. Per view, pixels on a grid of step ``stride`` are kept
    when ``acc >= min_acc`` and, among the ``check_views`` nearest other views (by
    camera distance) that see the point in front of their rendered surface, at least
    ``min_consistent`` rendered a depth within ``depth_tol`` (relative) of the point's
    depth (and, with ``photo_tol``, an image colour within ``photo_tol``). The result is
    voxel-downsampled (``voxel`` m). Returns points (M, 3) float64 and colours (M, 3) uint8.
    """
    keys = list(poses.keys()) if isinstance(poses, dict) else list(range(len(poses)))
    plist = [np.asarray(poses[k], np.float64) for k in keys]
    if images is not None:
        ilist = [np.asarray(images[k]) for k in keys]
    if not plist:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    stride = max(1, int(stride))
    cam_lo = camera.resized(max(1, camera.width // stride), max(1, camera.height // stride))
    render = _render_fn(source, near, far, n_samples, n_importance)
    renders = [render(p, cam_lo) for p in plist]
    centres = np.stack([p[:3, 3] for p in plist])
    uv = cam_lo.pixel_grid(dtype=torch.float64).numpy()
    dirs = np.stack([(uv[:, 0] - cam_lo.cx) / cam_lo.fx, (uv[:, 1] - cam_lo.cy) / cam_lo.fy, np.ones(len(uv))], -1)
    all_p, all_c = [], []
    for i, (pose, rd) in enumerate(zip(plist, renders)):
        acc = rd["acc"].reshape(-1)
        dep = rd["depth"].reshape(-1)
        keep = (acc >= min_acc) & (dep > near)
        if max_depth is not None:
            keep &= dep <= max_depth
        if not keep.any():
            continue
        pts = (dirs[keep] * dep[keep, None]) @ pose[:3, :3].T + pose[:3, 3]
        if images is not None:
            uv_full = np.stack([(uv[keep, 0] + 0.5) * stride - 0.5, (uv[keep, 1] + 0.5) * stride - 0.5], -1)
            col, _ = _lookup_nearest(ilist[i], uv_full)
            col = col.astype(np.float64)
        else:
            col = rd["rgb"].reshape(-1, 3)[keep] * 255.0
        if min_consistent > 0 and len(plist) > 1:
            dist = np.linalg.norm(centres - centres[i], axis=1)
            dist[i] = np.inf
            others = np.argsort(dist)[:check_views]
            good = np.zeros(len(pts), np.int64)
            for j in others:
                if not np.isfinite(dist[j]):
                    continue
                uvj, zj = _project(plist[j], cam_lo, pts)
                dj, okj = _lookup_nearest(renders[j]["depth"], uvj)
                aj, _ = _lookup_nearest(renders[j]["acc"], uvj)
                okj &= (zj > near) & (aj >= min_acc)
                cons = okj & (np.abs(dj - zj) <= depth_tol * zj)
                if photo_tol is not None and images is not None:
                    uvj_full = (uvj + 0.5) * stride - 0.5
                    cj, _ = _lookup_nearest(ilist[j], uvj_full)
                    cons &= np.abs(cj.astype(np.float64) - col).mean(-1) <= photo_tol * 255
                good += cons
            ok = good >= min_consistent
            pts, col = pts[ok], col[ok]
        all_p.append(pts)
        all_c.append(col)
    if not all_p:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    p, c = voxel_downsample(np.concatenate(all_p), np.concatenate(all_c), voxel)
    return p, np.clip(np.round(c), 0, 255).astype(np.uint8)


@torch.no_grad()
def field_opacity_grid(field, aabb, resolution: int, chunk: int = 262144) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Opacity of a cell-sized step at every node of a ``resolution``^3 grid over ``aabb``.

    Density fields: ``alpha = 1 - exp(-sigma * cell)`` with ``cell`` the mean node
    spacing; occupancy fields: the occupancy itself. Returns (alpha (R, R, R) indexed
    [x, y, z], origin (3,), spacing (3,)).
    """
    box = np.asarray(aabb.detach().cpu() if isinstance(aabb, Tensor) else aabb, np.float64).reshape(2, 3)
    r = int(resolution)
    axes = [np.linspace(box[0, a], box[1, a], r) for a in range(3)]
    spacing = (box[1] - box[0]) / (r - 1)
    cell = float(spacing.mean())
    alpha = np.empty(r ** 3, np.float32)
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([gx.reshape(-1), gy.reshape(-1), gz.reshape(-1)], -1)
    dev, dtype = field.device, field.dtype
    for s in range(0, len(pts), chunk):
        x = torch.as_tensor(pts[s:s + chunk], dtype=dtype, device=dev)
        raw = field.density_raw(x)
        a = raw_to_alpha(raw, torch.full_like(raw, cell), field.cfg.alpha_mode, field.cfg.density_shift)
        alpha[s:s + chunk] = a.cpu().numpy()
    return alpha.reshape(r, r, r), box[0], spacing


def export_mesh(
    field,
    aabb,
    resolution: int,
    poses: Union[dict, Sequence[np.ndarray]],
    camera: PinholeCamera,
    level: float = 0.5,
    render: Optional[RenderFn] = None,
    near: float = 0.1,
    far: float = 10.0,
    visibility_tol: float = 0.05,
    stride: int = 4,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching-cubes mesh of the field, culled to what the cameras at ``poses`` saw.

    The iso-surface is taken at ``level`` of the per-cell opacity (:func:`field_opacity_grid`).
    A vertex is *seen* when some pose has it in its frustum between ``near`` and ``far``
    and, when ``render`` (``(c2w, camera) -> dict(depth, acc)``) is given, not more than
    ``visibility_tol`` (relative) behind the rendered depth at its pixel (renders at
    1/``stride`` resolution). Faces with any unseen vertex are dropped. Returns
    vertices (V, 3) float64, faces (F, 3) int64 and vertex colours (V, 3) uint8 (the
    field's colour at the vertex).
    """
    from skimage.measure import marching_cubes

    alpha, origin, spacing = field_opacity_grid(field, aabb, resolution)
    if not (alpha.min() < level < alpha.max()):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)
    verts, faces, _, _ = marching_cubes(alpha, level=level, spacing=tuple(spacing))
    verts = verts + origin
    plist = [np.asarray(p, np.float64) for p in (poses.values() if isinstance(poses, dict) else poses)]
    seen = np.zeros(len(verts), bool)
    cam_lo = camera.resized(max(1, camera.width // stride), max(1, camera.height // stride))
    for pose in plist:
        todo = np.flatnonzero(~seen)
        if len(todo) == 0:
            break
        uv, z = _project(pose, camera, verts[todo])
        ok = (z > near) & (z < far) & camera.in_image(torch.from_numpy(uv)).numpy()
        if render is not None and ok.any():
            rd = render(pose, cam_lo)
            uv_lo = (uv + 0.5) / stride - 0.5
            d, _ = _lookup_nearest(rd["depth"], uv_lo)
            a, _ = _lookup_nearest(rd["acc"], uv_lo)
            ok &= (a < 0.5) | (z <= d * (1 + visibility_tol) + 0.02)
        seen[todo[ok]] = True
    keep_f = seen[faces].all(1)
    faces = faces[keep_f]
    used = np.unique(faces)
    remap = -np.ones(len(verts), np.int64)
    remap[used] = np.arange(len(used))
    verts = verts[used]
    faces = remap[faces]
    cols = np.zeros((len(verts), 3), np.uint8)
    if len(verts):
        with torch.no_grad():
            out = []
            for s in range(0, len(verts), 65536):
                x = torch.as_tensor(verts[s:s + 65536], dtype=field.dtype, device=field.device)
                out.append(field.color(x).cpu().numpy())
        cols = np.clip(np.round(np.concatenate(out) * 255), 0, 255).astype(np.uint8)
    return verts, faces.astype(np.int64), cols
