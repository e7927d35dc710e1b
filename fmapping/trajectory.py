"""TUM-format trajectory files (``timestamp tx ty tz qx qy qz qw``) and timestamp association.

These files are what the evo tools, ORB-SLAM and kiss-icp exchange; poses are
camera-to-world (see :mod:`fmapping.geometry`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from fmapping.geometry import make_pose, matrix_to_quat, quat_to_matrix


def poses_to_tum_rows(timestamps, c2w) -> np.ndarray:
    c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float64).reshape(-1, 4, 4)
    q = matrix_to_quat(c2w[:, :3, :3]).numpy()
    t = c2w[:, :3, 3].numpy()
    return np.concatenate([np.asarray(timestamps, np.float64)[:, None], t, q], 1)


def tum_rows_to_poses(rows: np.ndarray) -> np.ndarray:
    rows = torch.as_tensor(np.asarray(rows, np.float64))
    return make_pose(quat_to_matrix(rows[:, 4:8]), rows[:, 1:4]).numpy()


def write_tum_trajectory(path, timestamps, c2w) -> Path:
    path = Path(path)
    rows = poses_to_tum_rows(timestamps, c2w)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for r in rows:
            f.write(f"{r[0]:.6f} " + " ".join(f"{x:.9f}" for x in r[1:]) + "\n")
    return path


def read_tum_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> (timestamps (N,), c2w (N, 4, 4)). Errors name file and line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise ValueError(f"{path}:{lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise ValueError(f"{path}:{lineno}: non-numeric value in {s!r}") from None
        if not np.all(np.isfinite(vals)):
            raise ValueError(f"{path}:{lineno}: NaN or Inf in pose")
        if np.linalg.norm(vals[4:8]) < 1e-6:
            raise ValueError(f"{path}:{lineno}: zero quaternion")
        rows.append(vals)
    if not rows:
        raise ValueError(f"{path}: no poses in trajectory file")
    arr = np.asarray(rows)
    return arr[:, 0], tum_rows_to_poses(arr)


def associate(query: np.ndarray, reference: np.ndarray, max_dt: float = 0.02) -> np.ndarray:
    """For each query timestamp the index of the nearest reference timestamp, or -1 beyond ``max_dt``."""
    query = np.asarray(query, np.float64)
    reference = np.asarray(reference, np.float64)
    if len(reference) == 0:
        return np.full(len(query), -1, dtype=np.int64)
    order = np.argsort(reference)
    ref = reference[order]
    j = np.clip(np.searchsorted(ref, query), 1, len(ref) - 1) if len(ref) > 1 else np.zeros(len(query), int)
    if len(ref) > 1:
        left_better = np.abs(query - ref[j - 1]) <= np.abs(query - ref[j])
        j = np.where(left_better, j - 1, j)
    idx = order[j]
    return np.where(np.abs(reference[idx] - query) <= max_dt, idx, -1).astype(np.int64)
