"""Writing a scene to disk: TUM-layout frames and lists, ground truth, calibration, scene.json
and the gt mesh / clouds (:func:`generate_scene`)."""
from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Sequence

import numpy as np

from fmapping.synthetic.camera_effects import apply_camera_effects, exposure_curve, image_motion
from fmapping.synthetic.camera_path import camera_clearance, make_trajectory, trajectory_steps
from fmapping.synthetic.ground_truth import VISIBLE_TOL_M, _visible_columns, gt_cloud, gt_mesh
from fmapping.synthetic.render import render_view
from fmapping.synthetic.scene import _THIN_KINDS, Scene, _check_variety, camera_for_size, make_scene

DEPTH_FACTOR = 5000.0
FPS = 30.0


def _variety_record(scene: Scene, gains: np.ndarray, offsets: np.ndarray, blur: np.ndarray, rgb_ext: str) -> dict:
    """What a wide scene drew, for benchmark reports (scene.json["variety"])."""
    st = scene.style
    exposed = [rec for rec, r in zip(scene.surface_styles, scene.rects) if r.exposed]
    kinds = {rec["kind"] for rec in exposed}
    # yaw off the 0 / 90 deg grid by more than a degree
    rotated = [b for b in scene.boxes if abs(math.remainder(b.yaw, np.pi / 2)) > math.radians(1.0)]
    features = {
        "striped": "striped" in kinds,
        "low_texture": "low_texture" in kinds,
        "rotated_box": bool(rotated),
        "thin_structure": any(b.kind in _THIN_KINDS for b in scene.boxes),
        "jpeg": st.jpeg_quality > 0,
        "exposure_change": max(st.exposure_amp, st.white_balance_amp, st.offset_amp_dn) > 0,
        "noise": st.noise_sigma_dn > 0,
        "motion_blur": st.blur_exposure > 0,
    }
    return {
        "name": "wide",
        "features": features,
        "style": asdict(st),
        "rgb_format": rgb_ext,
        "room_size": (scene.room_max - scene.room_min).tolist(),
        "rotated_boxes": len(rotated),
        "thin_structures": sum(b.kind in _THIN_KINDS for b in scene.boxes),
        "surfaces": scene.surface_styles,
        "per_frame": {"gain": gains.tolist(), "offset_dn": offsets.tolist(), "blur_px": blur.tolist()},
    }


# ----------------------------------------------------------------------------- files
def _write_jpeg(path: Path, img: np.ndarray, quality: int) -> None:
    import cv2

    if not cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)]):
        raise OSError(f"could not write {path}")


def _write_png(path: Path, img: np.ndarray) -> None:
    import cv2

    data = img[..., ::-1] if img.ndim == 3 else img
    if not cv2.imwrite(str(path), np.ascontiguousarray(data), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OSError(f"could not write {path}")


def _ts_name(ts: float) -> str:
    return f"{ts:.6f}"


def _clean_previous(out: Path) -> None:
    """Remove frame folders of an earlier run of this generator (never anything else)."""
    meta = out / "scene.json"
    if not meta.is_file():
        return
    try:
        old = json.loads(meta.read_text())
    except (OSError, ValueError):
        return
    if old.get("generator") == "fmapping.synthetic":
        for sub in ("rgb", "depth"):
            if (out / sub).is_dir():
                shutil.rmtree(out / sub)


def generate_scene(out, seed: int = 0, frames: int = 200, size: Sequence[int] = (320, 240),
                   supersample: int = 2, max_cloud_points: int = 500_000, mesh_spacing: float = 0.05,
                   variety: str = "default") -> dict:
    """Render ``frames`` RGB-D frames of the scene for ``seed`` into ``out`` (TUM layout) with GT.

    Writes rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt, calib.txt, scene.json,
    gt_mesh.ply, gt_cloud.ply and gt_visible_cloud.ply; returns a summary dict
    (paths, timing, frames, camera, bbox). ``variety="wide"`` draws a :class:`Style` too:
    the colour frames get its camera effects (and are JPEG files when it says so), and
    scene.json records it under ``"variety"``.
    """
    from fmapping.ply import write_ply
    from fmapping.trajectory import write_tum_trajectory

    t_start, cpu_start = time.perf_counter(), time.process_time()
    if len(size) != 2:
        raise ValueError(f"size must be (W, H), got {size!r}")
    camera = camera_for_size(*size)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"synth output {out} exists and is not a directory")
    _clean_previous(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)

    scene = make_scene(seed, _check_variety(variety))
    style = scene.style
    c2w = make_trajectory(scene, frames, seed)
    step_t, step_r = trajectory_steps(c2w) if len(c2w) > 1 else (np.zeros(1), np.zeros(1))
    ts = np.arange(len(c2w)) / FPS
    names = [_ts_name(t) for t in ts]
    rgb_ext = "jpg" if style is not None and style.jpeg_quality > 0 else "png"
    if style is not None:
        gains, offsets = exposure_curve(style, len(c2w))
        blur = np.zeros((len(c2w), 2))

    t0 = time.perf_counter()
    cloud, cloud_ids, cloud_col = gt_cloud(scene, max_points=max_cloud_points, seed=seed)
    t_cloud = time.perf_counter() - t0

    seen = np.zeros(len(cloud), bool)
    cloud_cols = np.ascontiguousarray(cloud.T, dtype=np.float32)  # as stored in the PLY
    t_render = t_vis = t_io = 0.0
    max_depth = 0.0
    for i, pose in enumerate(c2w):
        t0 = time.perf_counter()
        rgb, depth = render_view(scene, camera, pose, supersample=supersample)
        t1 = time.perf_counter()
        todo = np.flatnonzero(~seen)
        seen[todo[_visible_columns(camera, pose, depth, cloud_cols[:, todo], VISIBLE_TOL_M)]] = True
        t2 = time.perf_counter()
        raw = np.round(depth.astype(np.float64) * DEPTH_FACTOR)
        if raw.max() > 65535:
            raise AssertionError(f"depth {depth.max():.2f} m does not fit 16-bit PNG at factor {DEPTH_FACTOR}")
        max_depth = max(max_depth, float(depth.max()))
        if style is not None:
            other = c2w[i - 1] if i > 0 else c2w[min(1, len(c2w) - 1)]
            blur[i] = np.round(style.blur_exposure * image_motion(camera, pose, other, depth), 3)
            rgb = apply_camera_effects(rgb, gains[i], offsets[i], blur[i], style.noise_sigma_dn,
                                       np.random.default_rng([int(seed), 7007, i]))
        if rgb_ext == "jpg":
            _write_jpeg(out / "rgb" / f"{names[i]}.jpg", rgb, style.jpeg_quality)
        else:
            _write_png(out / "rgb" / f"{names[i]}.png", rgb)
        _write_png(out / "depth" / f"{names[i]}.png", raw.astype(np.uint16))
        t_render += t1 - t0
        t_vis += t2 - t1
        t_io += time.perf_counter() - t2

    header = f"# fmapping.synthetic seed {seed}, {len(ts)} frames {camera.width}x{camera.height}\n"
    if style is not None:
        header = header[:-1] + ", variety wide\n"
    (out / "rgb.txt").write_text("# color images\n" + header + "# timestamp filename\n"
                                 + "".join(f"{n} rgb/{n}.{rgb_ext}\n" for n in names))
    (out / "depth.txt").write_text(f"# depth maps (uint16, {DEPTH_FACTOR:g} per metre, 0 = invalid)\n" + header
                                   + "# timestamp filename\n" + "".join(f"{n} depth/{n}.png\n" for n in names))
    write_tum_trajectory(out / "groundtruth.txt", ts, c2w)
    (out / "calib.txt").write_text(f"{camera.fx:.6f} {camera.fy:.6f} {camera.cx:.6f} {camera.cy:.6f}\n"
                                   f"depth_factor {DEPTH_FACTOR:g}\n")

    t0 = time.perf_counter()
    verts, faces, vcol = gt_mesh(scene, spacing=mesh_spacing)
    write_ply(out / "gt_mesh.ply", verts, (np.round(vcol * 255)).astype(np.uint8), faces)
    cloud_u8 = np.round(cloud_col * 255).astype(np.uint8)
    write_ply(out / "gt_cloud.ply", cloud, cloud_u8)
    write_ply(out / "gt_visible_cloud.ply", cloud[seen], cloud_u8[seen])
    t_gt = time.perf_counter() - t0

    lo, hi = scene.bbox()
    meta = {
        "generator": "fmapping.synthetic",
        "seed": int(seed),
        "frames": int(len(ts)),
        "size": [camera.width, camera.height],
        "camera": camera.to_dict(),
        "depth_factor": DEPTH_FACTOR,
        "fps": FPS,
        **scene.to_dict(),
        "bbox": {"min": lo.tolist(), "max": hi.tolist()},
        "max_step_m": float(step_t.max()),
        "max_step_deg": float(step_r.max()),
        "min_clearance_m": float(camera_clearance(scene, c2w[:, :3, 3]).min()),
        "max_depth_m": max_depth,
        "gt_cloud_points": int(len(cloud)),
        "gt_visible_points": int(seen.sum()),
        "supersample": int(supersample),
    }
    if style is not None:
        meta["variety"] = _variety_record(scene, gains, offsets, blur, rgb_ext)
    (out / "scene.json").write_text(json.dumps(meta, indent=2))
    total = time.perf_counter() - t_start
    paths = {k: str(out / v) for k, v in {
        "root": "", "rgb": "rgb.txt", "depth": "depth.txt", "groundtruth": "groundtruth.txt",
        "calib": "calib.txt", "scene": "scene.json", "gt_mesh": "gt_mesh.ply", "gt_cloud": "gt_cloud.ply",
        "gt_visible_cloud": "gt_visible_cloud.ply"}.items()}
    return {
        "paths": paths,
        "frames": int(len(ts)),
        "seed": int(seed),
        "variety": variety,
        "camera": camera.to_dict(),
        "bbox": meta["bbox"],
        "boxes": len(scene.boxes),
        "max_step_m": meta["max_step_m"],
        "max_step_deg": meta["max_step_deg"],
        "gt_cloud_points": meta["gt_cloud_points"],
        "gt_visible_points": meta["gt_visible_points"],
        "timing": {
            "total_s": round(total, 3),
            "total_cpu_s": round(time.process_time() - cpu_start, 3),
            "render_s": round(t_render, 3),
            "render_ms_per_frame": round(1000 * t_render / max(1, len(ts)), 2),
            "visibility_s": round(t_vis, 3),
            "png_s": round(t_io, 3),
            "gt_cloud_s": round(t_cloud, 3),
            "gt_files_s": round(t_gt, 3),
        },
    }
