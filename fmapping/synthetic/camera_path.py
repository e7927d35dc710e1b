"""The camera path: smooth poses along the scene's loop within the step and clearance limits."""
from __future__ import annotations

import math

import numpy as np

from fmapping.synthetic.scene import _DEFAULT_RANGES, _WIDE_RANGES, LoopPath, Scene

MAX_STEP_M = 0.03  # translation limit between consecutive frames
MAX_STEP_DEG = 2.0  # rotation limit between consecutive frames
STEP_FILL = 0.97  # trajectories use at most this fraction of the limits
CLEARANCE_M = 0.5  # camera distance to walls, floor, ceiling and furniture


def _look_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations (..., 3, 3): OpenCV axes, forward at (yaw, pitch) in the z-up world."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    fwd = np.stack([cp * cy, cp * sy, sp], -1)
    right0 = np.stack([sy, -cy, np.zeros_like(cy)], -1)
    down0 = np.cross(fwd, right0)
    cr, sr = np.cos(roll)[..., None], np.sin(roll)[..., None]
    right = cr * right0 + sr * down0
    down = -sr * right0 + cr * down0
    return np.stack([right, down, fwd], -1)


def _angle_between(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad) between rotation stacks, accurate for small angles."""
    fro = np.linalg.norm((ra - rb).reshape(*ra.shape[:-2], 9), axis=-1)
    return 2.0 * np.arcsin(np.clip(fro / (2.0 * math.sqrt(2.0)), 0.0, 1.0))


def trajectory_steps(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) between consecutive poses (N-1,) each."""
    c2w = np.asarray(c2w, np.float64)
    trans = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)
    rot = np.degrees(_angle_between(c2w[:-1, :3, :3], c2w[1:, :3, :3]))
    return trans, rot


def _loop_poses(path: LoopPath, theta: np.ndarray, look: dict) -> np.ndarray:
    a = path.direction * theta
    yaw = a + path.direction * (look["yaw_offset"] + look["yaw_amp"] * np.sin(2 * theta + look["yaw_phase"]))
    pitch = look["pitch"] + look["pitch_amp"] * np.sin(3 * theta + look["pitch_phase"])
    roll = look["roll_amp"] * np.sin(theta + look["roll_phase"])
    out = np.zeros(theta.shape + (4, 4))
    out[..., :3, :3] = _look_rotation(yaw, pitch, roll)
    out[..., :3, 3] = path.positions(theta)
    out[..., 3, 3] = 1.0
    return out


def camera_clearance(scene: Scene, positions: np.ndarray) -> np.ndarray:
    """Distance (M,) of points to the nearest room plane or furniture box."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    d = np.minimum((p - scene.room_min).min(1), (scene.room_max - p).min(1))
    for box in scene.boxes:
        q = np.abs(box.to_local(p)) - box.half
        outside = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
        d = np.minimum(d, outside)
    return d


def make_trajectory(scene: Scene, frames: int, seed: int = 0) -> np.ndarray:
    """Smooth camera-to-world poses (N, 4, 4) along the scene's loop.

    ``seed`` sets the start point on the loop and the look-direction modulation; the
    loop itself belongs to the scene (furniture keeps clear of it). Frames are spaced
    by equal *effort* ``max(dt / 0.95*3cm, dR / 0.95*2deg)``: when N frames suffice the
    loop is closed and traversed once, otherwise the first ``N - 1`` effort units are used.
    Raises AssertionError if a step or the camera clearance breaks the limits.
    """
    frames = int(frames)
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rng = np.random.default_rng([int(seed), 7002])
    ranges = _DEFAULT_RANGES if scene.style is None else _WIDE_RANGES
    look = {
        "yaw_offset": float(rng.uniform(*ranges.look_yaw)),  # 0 = facing outwards, pi/2 = along the loop
        "yaw_amp": float(rng.uniform(0.05, 0.12)),
        "yaw_phase": float(rng.uniform(0, 2 * np.pi)),
        "pitch": float(rng.uniform(*ranges.pitch)),
        "pitch_amp": 0.06,
        "pitch_phase": float(rng.uniform(0, 2 * np.pi)),
        "roll_amp": 0.03,
        "roll_phase": float(rng.uniform(0, 2 * np.pi)),
    }
    theta0 = float(rng.uniform(0, 2 * np.pi))
    m = 20000
    grid = theta0 + np.linspace(0.0, 2 * np.pi, m + 1)
    dense = _loop_poses(scene.path, grid, look)
    dt, dr = trajectory_steps(dense)
    effort = np.maximum(dt / (STEP_FILL * MAX_STEP_M), dr / (STEP_FILL * MAX_STEP_DEG))
    cum = np.concatenate([[0.0], np.cumsum(effort)])
    total = cum[-1]
    targets = np.arange(frames) * (total / frames if frames >= total else 1.0)
    theta = np.interp(targets, cum, grid)
    c2w = _loop_poses(scene.path, theta, look)
    if frames > 1:
        st, sr = trajectory_steps(c2w)
        if st.max() > MAX_STEP_M or sr.max() > MAX_STEP_DEG:
            raise AssertionError(f"trajectory step {st.max():.4f} m / {sr.max():.3f} deg exceeds "
                                 f"{MAX_STEP_M} m / {MAX_STEP_DEG} deg")
    clear = camera_clearance(scene, c2w[:, :3, 3])
    if clear.min() < CLEARANCE_M:
        raise AssertionError(f"camera comes {clear.min():.3f} m close to a surface (< {CLEARANCE_M} m)")
    return c2w

