"""Pose sources other than the photometric tracker: ground truth, a TUM file, kiss-icp on depth.

All return camera-to-world 4x4 float64 poses in the conventions of
:mod:`fmapping.geometry`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.trajectory import associate, read_tum_trajectory


def poses_from_file(path, timestamps: np.ndarray, max_dt: float = 0.02) -> list:
    """Poses of a TUM trajectory file matched to ``timestamps`` (nearest within ``max_dt``).

    Raises ``ValueError`` naming the file when a frame has no pose.
    """
    ts, c2w = read_tum_trajectory(path)
    idx = associate(np.asarray(timestamps, np.float64), ts, max_dt)
    missing = np.flatnonzero(idx < 0)
    if len(missing):
        raise ValueError(f"{path}: no pose within {max_dt} s of {len(missing)} frame(s), "
                         f"first at t={timestamps[missing[0]]:.6f}")
    return [c2w[i] for i in idx]


def depth_to_points(depth: np.ndarray, camera: PinholeCamera, stride: int = 2, min_depth: float = 0.1,
                    max_depth: float = 8.0) -> np.ndarray:
    """Back-project every ``stride``-th pixel of a metric depth image to camera-frame points (N, 3) float64."""
    d = np.asarray(depth, np.float64)
    if d.shape != (camera.height, camera.width):
        raise ValueError(f"depth is {d.shape[1]}x{d.shape[0]} but the camera is {camera.width}x{camera.height}")
    v, u = np.mgrid[0:camera.height:stride, 0:camera.width:stride]
    z = d[v, u]
    ok = np.isfinite(z) & (z > min_depth) & (z < max_depth)
    z, u, v = z[ok], u[ok], v[ok]
    return np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)


@dataclass
class KissIcpConfig:
    voxel_size: float = 0.03  # metres; kiss-icp's map / downsampling voxel (indoor depth: 0.02-0.05)
    max_range: float = 6.0
    min_range: float = 0.1
    stride: int = 2  # pixel stride of the back-projected depth
    max_points_per_voxel: int = 20
    initial_threshold: float = 0.3  # metres; kiss-icp's default 2.0 is tuned for LiDAR
    min_motion_th: float = 0.01  # metres; kiss-icp's default 0.1 is tuned for cars
    threads: int = 1  # kiss-icp registration threads (0 = all cores; oversubscribes a shared 2-core box)


class KissIcpOdometry:
    """kiss-icp (through its Python API) on back-projected depth images.

    Poses are camera-to-world with the first frame at ``c2w_first`` (identity by
    default): kiss-icp reports each scan's pose in the first scan's frame, and the
    scans are camera-frame points, so that pose is the camera motion itself.
    """

    def __init__(self, camera: PinholeCamera, cfg: Optional[KissIcpConfig] = None,
                 c2w_first: Optional[np.ndarray] = None):
        try:
            from kiss_icp.config import KISSConfig
            from kiss_icp.kiss_icp import KissICP
        except ImportError as e:  # pragma: no cover - kiss-icp is a dependency
            raise RuntimeError(f"--poses kiss-icp needs the kiss-icp package: {e}") from e
        self.camera = camera
        self.cfg = cfg or KissIcpConfig()
        kc = KISSConfig()
        kc.data.max_range = self.cfg.max_range
        kc.data.min_range = self.cfg.min_range
        kc.data.deskew = False  # a depth image is one instant; no per-point times
        kc.mapping.voxel_size = self.cfg.voxel_size
        kc.mapping.max_points_per_voxel = self.cfg.max_points_per_voxel
        kc.registration.max_num_threads = self.cfg.threads
        kc.adaptive_threshold.initial_threshold = self.cfg.initial_threshold
        kc.adaptive_threshold.min_motion_th = self.cfg.min_motion_th
        self._kiss = KissICP(kc)
        self.c2w_first = np.eye(4) if c2w_first is None else np.asarray(c2w_first, np.float64)

    def register(self, depth: np.ndarray) -> np.ndarray:
        """Register the next depth image; returns its camera-to-world pose."""
        pts = depth_to_points(depth, self.camera, self.cfg.stride, self.cfg.min_range, self.cfg.max_range)
        if len(pts) < 100:
            raise ValueError(f"kiss-icp: only {len(pts)} valid depth points in the frame")
        self._kiss.register_frame(pts, np.zeros(len(pts)))
        return self.c2w_first @ np.asarray(self._kiss.last_pose, np.float64)


def default_kiss_config_for(camera: PinholeCamera, depth_example: Optional[np.ndarray] = None) -> KissIcpConfig:
    """A voxel size matched to the scene extent (1-2 % of the median depth, clipped to 2-5 cm)."""
    cfg = KissIcpConfig()
    if depth_example is not None:
        d = np.asarray(depth_example)
        d = d[np.isfinite(d) & (d > 0)]
        if len(d):
            cfg.voxel_size = float(np.clip(0.015 * np.median(d), 0.02, 0.05))
    return cfg


def ensure_path(p) -> Path:
    path = Path(p)
    if not path.is_file():
        raise FileNotFoundError(f"pose file not found: {path}")
    return path
