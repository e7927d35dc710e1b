"""Rolling shutter: the rows of a frame are exposed one after another, top to bottom.

While the camera turns, each row sees the world from a slightly different orientation: a
yaw becomes a shear, a pitch a vertical stretch. Geometry that assumes a global shutter
(essential matrix, PnP, bundle adjustment) then explains the tracks with the wrong poses.
A consumer RGB-D camera at 30 Hz reads out for most of the frame interval; on the TUM
fr1_rpy clip (up to 115 deg/s) that is up to ~15 px between the top and the bottom row.

The model here is rotation only, at a constant angular velocity over one frame: with
``step`` the camera's rotation over one frame interval (a rotation vector in the camera
frame: ``R_prev^T R_cur`` of camera-to-world poses) and ``readout`` the time from the first
to the last row as a fraction of the frame interval, row ``v`` is exposed at
``tau = readout * (v - h / 2) / h`` frame intervals from the middle row, with orientation
``R exp(tau [step])``. :func:`unroll` moves each pixel to where the frame's middle-row
orientation (its pose) would have seen the same direction, so everything downstream can
keep its global-shutter geometry. Translation during a readout (millimetres) is ignored.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fmapping.camera import PinholeCamera


def unroll(camera: PinholeCamera, uv: np.ndarray, step: np.ndarray, readout: float) -> np.ndarray:
    """Pixels ``uv`` (N, 2) of a rolling-shutter frame as a global shutter at the frame's middle
    row would have seen them (see the module docstring). ``readout`` 0 returns ``uv`` itself."""
    uv = np.asarray(uv, np.float64)
    if readout == 0.0 or len(uv) == 0:
        return uv
    tau = readout * (uv[:, 1] - camera.height / 2.0) / camera.height
    rays = np.c_[(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))]
    rot = Rotation.from_rotvec(tau[:, None] * np.asarray(step, np.float64).reshape(1, 3)).as_matrix()
    return camera.world_to_pixels(np.eye(4), np.einsum("nij,nj->ni", rot, rays))[0]


def rotation_step(c2w_prev: np.ndarray, c2w_cur: np.ndarray) -> np.ndarray:
    """The rotation from one frame to the next as a rotation vector in the camera frame (3,)."""
    return Rotation.from_matrix(np.asarray(c2w_prev)[:3, :3].T @ np.asarray(c2w_cur)[:3, :3]).as_rotvec()


def rotation_steps(c2w: np.ndarray) -> np.ndarray:
    """Per frame of a trajectory (N, 4, 4) its rotation over one frame interval (N, 3): half the
    rotation from the previous to the next frame (one-sided at the ends)."""
    c2w = np.asarray(c2w, np.float64)
    n = len(c2w)
    out = np.zeros((n, 3))
    for i in range(n):
        a, b = max(0, i - 1), min(n - 1, i + 1)
        if b > a:
            out[i] = rotation_step(c2w[a], c2w[b]) / (b - a)
    return out


def unroll_tracks(camera: PinholeCamera, tracks, steps: np.ndarray, readout: float):
    """:class:`~fmapping.tracking.consistency.FrameTracks` with every observation unrolled with its
    frame's rotation step (``steps`` (N, 3), e.g. :func:`rotation_steps` of a trajectory)."""
    import dataclasses

    steps = np.asarray(steps, np.float64)
    uv = np.array(tracks.uv, np.float64)
    for f in np.unique(tracks.frame):
        m = tracks.frame == f
        uv[m] = unroll(camera, uv[m], steps[f], readout)
    return dataclasses.replace(tracks, uv=uv)
