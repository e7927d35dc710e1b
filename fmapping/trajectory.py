"""TUM-format trajectory files (``timestamp tx ty tz qx qy qz qw``), timestamp association and
pose interpolation at arbitrary timestamps.

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


def interpolate_poses(query, ref_ts, ref_c2w, max_dt: float = 0.02,
                      nearest_fallback: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query`` timestamps from a sampled trajectory ``(ref_ts, ref_c2w)``.

    For each query time ``q`` with bracketing samples ``t_a <= q <= t_b``:

    * ``"interpolated"`` when ``t_b - t_a <= max_dt`` (a query equal to a sample has
      ``t_a = t_b = q`` and gets that sample exactly): translation linear in time,
      rotation on the geodesic (slerp) ``R_a exp(w log(R_a^T R_b))``, ``w = (q - t_a) / (t_b - t_a)``;
    * otherwise (a gap in the reference, or ``q`` outside its time range; no
      extrapolation) ``"nearest"``: the nearest sample when it is within ``max_dt``
      (TUM ``associate.py`` behaviour, for references sampled about as sparsely as the
      queries) and ``nearest_fallback`` is on;
    * otherwise ``"none"``.

    Returns ``(c2w (N, 4, 4) float64, NaN where "none"; how (N,) str array)``.
    """
    from fmapping.geometry import so3_exp, so3_log

    q = np.asarray(query, np.float64).reshape(-1)
    ts = np.asarray(ref_ts, np.float64).reshape(-1)
    poses = np.asarray(ref_c2w, np.float64)
    if poses.shape != (len(ts), 4, 4):
        raise ValueError(f"interpolate_poses: {len(ts)} timestamps but poses of shape {poses.shape} "
                         f"(expected ({len(ts)}, 4, 4))")
    if max_dt < 0:
        raise ValueError(f"interpolate_poses: max_dt must be >= 0 seconds, got {max_dt}")
    out = np.full((len(q), 4, 4), np.nan)
    how = np.full(len(q), "none", dtype=object)
    if len(ts) == 0 or len(q) == 0:
        return out, how.astype(str)
    order = np.argsort(ts, kind="stable")
    ts, poses = ts[order], poses[order]
    n = len(ts)
    hi = np.searchsorted(ts, q, side="left")  # first sample at or after q
    exact = (hi < n) & (ts[np.minimum(hi, n - 1)] == q)
    lo = np.where(exact, hi, hi - 1)
    inside = (lo >= 0) & (hi < n)
    lo_c, hi_c = np.clip(lo, 0, n - 1), np.clip(hi, 0, n - 1)
    gap = ts[hi_c] - ts[lo_c]
    interp = inside & (gap <= max_dt)
    if interp.any():
        a, b = poses[lo_c[interp]], poses[hi_c[interp]]
        g = gap[interp]
        w = np.where(g > 0, (q[interp] - ts[lo_c[interp]]) / np.where(g > 0, g, 1.0), 0.0)
        rel = np.swapaxes(a[:, :3, :3], -1, -2) @ b[:, :3, :3]
        step = so3_exp(torch.from_numpy(w)[:, None] * so3_log(torch.from_numpy(rel))).numpy()
        res = np.zeros_like(a)
        res[:, :3, :3] = a[:, :3, :3] @ step
        res[:, :3, 3] = a[:, :3, 3] + w[:, None] * (b[:, :3, 3] - a[:, :3, 3])
        res[:, 3, 3] = 1.0
        out[interp] = res
        how[interp] = "interpolated"
    if nearest_fallback and (~interp).any():
        j = associate(q[~interp], ts, max_dt)
        rows = np.flatnonzero(~interp)
        ok = j >= 0
        out[rows[ok]] = poses[j[ok]]
        how[rows[ok]] = "nearest"
    return out, how.astype(str)
