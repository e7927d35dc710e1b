"""The scene box the field lives in: from the view frusta, from depth maps, or from the
triangulated points and what each camera saw of them."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from fmapping.camera import PinholeCamera
from fmapping.sparse_points import TrackTriangulator, aabb_from_points, frusta_box


def aabb_from_poses(c2w: np.ndarray, camera: PinholeCamera, near: float, far: float, margin: float = 0.1) -> np.ndarray:
    """Bounding box (2, 3) of the view frusta (near..far) of the cameras ``c2w`` (N, 4, 4)."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    w, h = camera.width, camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]], np.float64)
    d = np.stack([(corners[:, 0] - camera.cx) / camera.fx, (corners[:, 1] - camera.cy) / camera.fy, np.ones(4)], -1)
    pts = np.concatenate([d * near, d * far])  # (8, 3) camera frame
    world = np.einsum("nij,kj->nki", c2w[:, :3, :3], pts) + c2w[:, None, :3, 3]
    allp = np.concatenate([world.reshape(-1, 3), c2w[:, :3, 3]])
    return np.stack([allp.min(0) - margin, allp.max(0) + margin])


def aabb_from_depth(c2w: np.ndarray, depths: list, camera: PinholeCamera, margin: float = 0.1,
                    stride: int = 8) -> Optional[np.ndarray]:
    """Bounding box (2, 3) of the back-projected valid depth of frames (robust 0.5/99.5 percentiles)."""
    pts = []
    uv = camera.pixel_grid(dtype=torch.float64).numpy().reshape(camera.height, camera.width, 2)[::stride, ::stride]
    for pose, dep in zip(c2w, depths):
        if dep is None:
            continue
        z = np.asarray(dep, np.float64)[::stride, ::stride]
        ok = np.isfinite(z) & (z > 0)
        if not ok.any():
            continue
        p = np.stack([(uv[..., 0][ok] - camera.cx) / camera.fx * z[ok],
                      (uv[..., 1][ok] - camera.cy) / camera.fy * z[ok], z[ok]], -1)
        pts.append(p @ pose[:3, :3].T + pose[:3, 3])
        pts.append(pose[None, :3, 3])
    if not pts:
        return None
    allp = np.concatenate(pts)
    return np.stack([np.percentile(allp, 0.5, 0) - margin, np.percentile(allp, 99.5, 0) + margin])


def points_box(sparse: TrackTriangulator, frame_poses: dict, camera: PinholeCamera,
               margin: float) -> Optional[np.ndarray]:
    """The box of the triangulated points and camera centres, widened to hold what each camera saw out
    to the median depth of its own points (:func:`fmapping.sparse_points.frusta_box`), plus the margin.
    ``frame_poses``: {frame id: float64 (4, 4) c2w tensor}; frames without a pose are left out."""
    ids = [i for i in sparse.frame_ids if i in frame_poses]
    if not ids:
        return None
    poses = np.stack([frame_poses[i].numpy() for i in ids])
    b = aabb_from_points(sparse.points, poses[:, :3, 3], margin=margin)
    seen = frusta_box(poses, np.array([sparse.depth_quantile(i) for i in ids]), camera)
    if b is None or seen is None:
        return b
    pad = np.maximum(margin, 0.05 * (seen[1] - seen[0]))
    return np.stack([np.minimum(b[0], seen[0] - pad), np.maximum(b[1], seen[1] + pad)])
