"""TUM RGB-D layout: ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (+ optional ``calib.txt``).

* ``rgb.txt`` / ``depth.txt``: ``timestamp path`` per line, paths relative to the folder.
  Every rgb entry is a frame; its depth is the nearest depth entry within 0.02 s
  (None otherwise). Its pose is interpolated at the rgb timestamp between the two
  bracketing ground-truth rows (linear translation, slerp rotation) when they are at
  most 0.02 s apart; otherwise (a gap in the ground truth, or outside its time range)
  the nearest row within 0.02 s; otherwise None (see
  :func:`fmapping.trajectory.interpolate_poses`; the counts go into
  ``meta["groundtruth_association"]``). ``associations.txt`` is not needed and is ignored.
* ``groundtruth.txt``: ``timestamp tx ty tz qx qy qz qw`` camera-to-world (optional).
* Intrinsics: ``calib.txt`` when present (first line ``fx fy cx cy [k1 k2 p1 p2 [k3]]``,
  optional line ``depth_factor F``; a file holding just the named rig's own four numbers
  gets that rig's distortion, see :func:`complete_tum_distortion`), else the TUM table by sequence name
  (freiburg1/2/3 or fr1/2/3 in the folder name), else a :class:`DatasetError` asking for
  ``--camera`` or a ``calib.txt`` (a guessed camera would only show up as a bad map).
  Depth factor 5000 raw units per metre unless ``calib.txt`` says otherwise.
* Folders written by ``fmapping synth`` (``scene.json`` with ``"generator":
  "fmapping.synthetic"``) are read the same way with kind ``"synthetic"``; the paths of
  the GT geometry files and the scene description go into ``meta``.
"""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import (
    WHITE, Background, CameraArg, build_sequence, check_max_frames, image_size, log,
    make_camera, parse_floats, resolve_camera, scaled_default, text_lines,
)
from fmapping.datasets.base import DatasetError
from fmapping.trajectory import associate, interpolate_poses, read_tum_trajectory

MAX_DT = 0.02  # seconds: association tolerance rgb <-> depth and rgb <-> ground truth
TUM_DEPTH_FACTOR = 5000.0
SYNTHETIC_GENERATOR = "fmapping.synthetic"
SYNTHETIC_GT_FILES = ("gt_mesh", "gt_cloud", "gt_visible_cloud")

# TUM RGB-D benchmark, RGB camera calibration per recording rig (fx, fy, cx, cy, dist or None)
TUM_INTRINSICS: dict[str, tuple[tuple[float, float, float, float], Optional[tuple[float, ...]]]] = {
    "freiburg1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": ((535.4, 539.2, 320.1, 247.6), None),
}
_SEQ_RE = re.compile(r"(?:^|[^a-z0-9])(?:freiburg|fr)([123])(?:[^0-9]|$)", re.IGNORECASE)


def is_tum(root: Path) -> bool:
    return (root / "rgb.txt").is_file()


def sequence_rig(name: str) -> Optional[str]:
    """``'freiburg1'``.. from a TUM folder name (``rgbd_dataset_freiburg1_desk``, ``tum_fr1_rpy``)."""
    m = _SEQ_RE.search(name)
    return f"freiburg{m.group(1)}" if m else None


def read_file_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    """``timestamp relative/path`` lines -> (timestamps, absolute paths). Errors name file:line."""
    ts, paths = [], []
    for lineno, s in text_lines(path):
        parts = s.split()
        if len(parts) != 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename', got {len(parts)} fields: {s!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: timestamp is not a number: {parts[0]!r}") from None
        if not np.isfinite(t):
            raise DatasetError(f"{path}:{lineno}: timestamp is not finite: {parts[0]!r}")
        ts.append(t)
        paths.append(path.parent / parts[1])
    return np.asarray(ts, np.float64), paths


def read_calib(path: Path) -> tuple[list[float], int, Optional[float]]:
    """``calib.txt`` -> (``fx fy cx cy [k1 k2 p1 p2 [k3]]``, its line number, depth factor or None)."""
    lines = text_lines(path)
    if not lines:
        raise DatasetError(f"{path}: empty calibration file (expected 'fx fy cx cy [k1 k2 p1 p2 [k3]]')")
    cam_line, first = lines[0]
    vals = parse_floats(first, path, cam_line, (4, 8, 9), "fx fy cx cy [k1 k2 p1 p2 [k3]]")
    factor = None
    for lineno, s in lines[1:]:
        parts = s.replace("=", " ").replace(":", " ").split()
        if len(parts) == 2 and parts[0].lower() == "depth_factor":
            try:
                factor = float(parts[1])
            except ValueError:
                factor = float("nan")
            if not np.isfinite(factor) or factor <= 0:
                raise DatasetError(f"{path}:{lineno}: depth_factor must be a positive number, got {parts[1]!r}")
        else:
            raise DatasetError(f"{path}:{lineno}: unexpected line {s!r} "
                               "(only 'depth_factor F' may follow the intrinsics)")
    return vals, cam_line, factor


def tum_camera(root: Path, size: tuple[int, int]) -> tuple[PinholeCamera, str, Optional[str]]:
    """Intrinsics from the TUM table by folder name (rescaled from 640x480 if needed) -> (camera, source, note);
    :class:`DatasetError` when the name is not a TUM sequence's."""
    rig = sequence_rig(root.resolve().name)
    if rig is None:
        # only a real TUM recording has published intrinsics; any other camera given fr1's would
        # track and map with a wrong focal length and no error at all
        raise DatasetError(
            f"{root}: TUM-layout folder without calib.txt, and its name is not a TUM RGB-D sequence "
            "(freiburg1/2/3 or fr1/fr2/fr3), so its camera intrinsics are unknown. Give them with "
            "--camera fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] (in Python open_dataset(..., camera='fx,fy,cx,cy')), "
            f"or write {root / 'calib.txt'} with the first line 'fx fy cx cy [k1 k2 p1 p2 [k3]]'")
    k, dist = TUM_INTRINSICS[rig]
    source = f"TUM {rig} calibration (by folder name)"
    nominal = PinholeCamera(*k, width=640, height=480, dist=dist)
    cam, note = scaled_default(nominal, size, f"TUM {rig}")
    return cam, source, note


def complete_tum_distortion(root: Path, vals: list[float], size: tuple[int, int]) -> tuple[list[float], Optional[str]]:
    """Add the TUM table's lens distortion to a ``calib.txt`` that gives only a rig's own ``fx fy cx cy``.

    TUM RGB-D images are stored distorted. A ``calib.txt`` with exactly the four numbers of
    the rig named in the folder (``fr1`` / ``freiburg1`` ...) at 640x480 describes those raw
    images, so the rig's distortion applies (freiburg1: about 2.6 % radial at the middle of
    the image edge; leaving it out costs several degrees of rotation when tracking). Any
    other file is taken as written.
    """
    rig = sequence_rig(root.resolve().name)
    if rig is None or len(vals) != 4 or tuple(size) != (640, 480):
        return vals, None
    k, dist = TUM_INTRINSICS[rig]
    if dist is None or not np.allclose(vals, k, atol=0.05):
        return vals, None
    return [*vals, *dist], (f"calib.txt gives the TUM {rig} intrinsics without distortion; "
                            f"using the {rig} distortion {list(dist)} of the TUM table")


def read_scene_json(path: Path) -> Optional[dict]:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}:{e.lineno}: invalid JSON: {e.msg}") from None


def load_tum(
    root, camera: CameraArg = None, max_frames: Optional[int] = None, background: Background = WHITE
):
    """Read a TUM-layout folder (TUM RGB-D, custom ``calib.txt``, ``fmapping synth``)."""
    root = Path(root)
    max_frames = check_max_frames(max_frames)
    rgb_txt = root / "rgb.txt"
    if not rgb_txt.is_file():
        raise DatasetError(f"not a TUM-layout folder, rgb.txt not found: {rgb_txt}")
    rgb_ts, rgb_paths = read_file_list(rgb_txt)
    if len(rgb_ts) == 0:
        raise DatasetError(f"{rgb_txt}: empty sequence, no frames listed")
    size = image_size(rgb_paths[0])
    meta: dict = {}

    # --- intrinsics and depth factor (an explicit ``camera`` makes the file's intrinsics irrelevant)
    depth_factor = TUM_DEPTH_FACTOR
    calib = root / "calib.txt"
    default, source = None, "--camera"
    if calib.is_file():
        vals, cam_line, factor = read_calib(calib)
        depth_factor = factor or depth_factor
        if camera is None:
            vals, note = complete_tum_distortion(root, vals, size)
            default, source = make_camera(vals, size, f"{calib}:{cam_line}"), str(calib)
            if note:
                meta["camera_note"] = note
    elif camera is None:
        default, source, note = tum_camera(root, size)
        if note:
            meta["camera_note"] = note
    cam, source = resolve_camera(camera, default, size, source)
    meta["camera_source"] = source

    # --- depth association
    depth_paths: list = [None] * len(rgb_ts)
    depth_txt = root / "depth.txt"
    has_depth = False
    if depth_txt.is_file():
        d_ts, d_paths = read_file_list(depth_txt)
        if len(d_ts):
            has_depth = True
            idx = associate(rgb_ts, d_ts, MAX_DT)
            depth_paths = [d_paths[j] if j >= 0 else None for j in idx]

    # --- ground truth association
    gt: list = [None] * len(rgb_ts)
    gt_txt = root / "groundtruth.txt"
    if gt_txt.is_file() and not text_lines(gt_txt):
        log.warning("%s: no poses in the file; frames have no ground truth", gt_txt)
    elif gt_txt.is_file():
        try:
            g_ts, g_c2w = read_tum_trajectory(gt_txt)
        except ValueError as e:
            raise DatasetError(str(e)) from None
        c2w, how = interpolate_poses(rgb_ts, g_ts, g_c2w, MAX_DT)
        gt = [c2w[i].copy() if h != "none" else None for i, h in enumerate(how)]
        meta["groundtruth"] = str(gt_txt)
        meta["groundtruth_association"] = {k: int((how == k).sum()) for k in ("interpolated", "nearest", "none")}

    # --- fmapping synth output
    kind = "tum"
    scene = read_scene_json(root / "scene.json")
    if isinstance(scene, dict) and scene.get("generator") == SYNTHETIC_GENERATOR:
        kind = "synthetic"
        meta["scene"] = scene
        for key in SYNTHETIC_GT_FILES:
            p = root / f"{key}.ply"
            if p.is_file():
                meta[key] = str(p)

    return build_sequence(
        root=root, kind=kind, raw_camera=cam, timestamps=rgb_ts, rgb_paths=rgb_paths,
        depth_paths=depth_paths, gt_poses=gt, depth_scale=depth_factor if has_depth else None,
        meta=meta, max_frames=max_frames, background=background,
    )
