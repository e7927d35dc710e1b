"""Helpers shared by the dataset readers: image decoding, camera resolution, text parsing.

Every reader builds an :class:`ImageSequence`: per-frame file paths plus the
camera of the files as stored (``raw_camera``, possibly with lens distortion).
Images are decoded only in ``__getitem__``:

* rgb: ``cv2`` BGR -> RGB ``uint8`` (H, W, 3); grayscale is replicated, 16-bit is
  reduced to 8 bits, RGBA is composited over ``background`` (default white);
* depth: single-channel PNG divided by ``depth_scale`` -> ``float32`` metres,
  ``depth_invalid`` raw values, non-finite and negative values -> 0 (invalid);
* both are undistorted with ``raw_camera.undistort_image`` when the camera has
  distortion (rgb bilinear, depth nearest), and ``Dataset.camera`` is then the
  undistorted camera.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.datasets.base import Dataset, DatasetError, Frame

log = logging.getLogger("fmapping.datasets")

CameraArg = Union[str, PinholeCamera, None]
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".bmp", ".tif", ".tiff")
Background = tuple[int, int, int]
WHITE: Background = (255, 255, 255)


# ----------------------------------------------------------------- images
def _imread(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise DatasetError(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise DatasetError(f"cannot decode image (unreadable or corrupt): {path}")
    return img


def to_rgb8(img: np.ndarray, path: Path, background: Background = WHITE) -> np.ndarray:
    """A decoded cv2 image (gray / BGR / BGRA, 8 or 16 bit) -> RGB uint8 (H, W, 3)."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise DatasetError(f"unsupported colour image type {img.dtype} (expected 8 or 16 bit): {path}")
    if img.ndim == 2:
        img = img[..., None]
    c = img.shape[2]
    if c == 1:
        return np.repeat(img, 3, axis=2)
    if c == 3:
        return np.ascontiguousarray(img[..., ::-1])
    if c == 4:
        rgb = img[..., 2::-1].astype(np.float32)
        a = img[..., 3:4].astype(np.float32) / 255.0
        bg = np.asarray(background, np.float32).reshape(1, 1, 3)
        return np.clip(np.rint(rgb * a + bg * (1.0 - a)), 0, 255).astype(np.uint8)
    raise DatasetError(f"unsupported number of channels {c} in colour image: {path}")


def read_rgb(path: Path, background: Background = WHITE) -> np.ndarray:
    return to_rgb8(_imread(path), path, background)


def read_depth(path: Path, scale: float, invalid: Optional[int] = None) -> np.ndarray:
    """Single-channel depth image -> float32 metres (raw / scale), 0 where invalid."""
    raw = _imread(path)
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.ndim != 2:
        raise DatasetError(f"depth image must have one channel, got shape {raw.shape}: {path}")
    depth = raw.astype(np.float32) / np.float32(scale)
    bad = ~np.isfinite(depth) | (depth < 0)
    if invalid is not None:
        bad |= raw == invalid
    depth[bad] = 0.0
    return depth


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image (decodes it once: used for the first frame only)."""
    img = _imread(path)
    return int(img.shape[1]), int(img.shape[0])


def resolve_image_path(path: Path) -> Path:
    """``path`` itself, or ``path`` + an image suffix when it was given without one (NeRF)."""
    if path.is_file() or path.suffix in IMAGE_SUFFIXES:
        return path
    for ext in IMAGE_SUFFIXES:
        cand = path.with_name(path.name + ext)
        if cand.is_file():
            return cand
    return path


# ----------------------------------------------------------------- camera
def resolve_camera(
    override: CameraArg, default: Optional[PinholeCamera], size: tuple[int, int], source: str
) -> tuple[PinholeCamera, str]:
    """The camera to use: ``override`` (``--camera`` string, calibration file or object) wins over ``default``.

    ``override`` may name a calibration file (``calib.txt`` / ``camera.yaml`` format, see
    :mod:`fmapping.datasets.calib`). Without either, the error says how to give intrinsics.

    Returns the camera (of the files as stored, possibly distorted) and a note of where
    the intrinsics came from.
    """
    w, h = size
    if override is None:
        if default is None:
            raise DatasetError(no_intrinsics_message(source))
        return default, source
    if isinstance(override, (str, Path)) and Path(override).is_file():
        # ``--camera path/to/camera.yaml``: the only way to give a file to a source that has no
        # folder of its own (a webcam) or whose folder the user cannot write to
        from fmapping.datasets.calib import read_camera_file

        return read_camera_file(Path(override), size), str(override)
    if isinstance(override, PinholeCamera):
        if (override.width, override.height) != (w, h):
            raise DatasetError(
                f"--camera is for {override.width}x{override.height} images but the images are {w}x{h}"
            )
        return override, "--camera"
    try:
        return PinholeCamera.from_string(str(override), w, h), "--camera"
    except ValueError as e:
        raise DatasetError(f"--camera {override!r}: {e}") from None


def no_intrinsics_message(what: str) -> str:
    """The error for a source without intrinsics: says every way to give them (never guessed)."""
    return (
        f"{what}: no camera intrinsics. Give them with --camera fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] "
        "(or --camera path/to/camera.yaml; in Python open_dataset(..., camera='fx,fy,cx,cy')), "
        "or put a calib.txt (one line 'fx fy cx cy [k1 k2 p1 p2 [k3]]') or a camera.yaml "
        "(fx, fy, cx, cy [, k1, k2, p1, p2, k3, fps] keys, or a ROS camera_info yaml) next to the images"
    )


def make_camera(vals: Sequence[float], size: tuple[int, int], where: str) -> PinholeCamera:
    """``fx fy cx cy [k1 k2 p1 p2 [k3]]`` -> camera; validation errors name ``where``."""
    if len(vals) not in (4, 8, 9):
        raise DatasetError(f"{where}: expected 'fx fy cx cy [k1 k2 p1 p2 [k3]]' (4, 8 or 9 numbers), got {len(vals)}")
    dist = tuple(float(v) for v in vals[4:]) if len(vals) > 4 and any(vals[4:]) else None
    try:
        return PinholeCamera(float(vals[0]), float(vals[1]), float(vals[2]), float(vals[3]), size[0], size[1], dist)
    except ValueError as e:
        raise DatasetError(f"{where}: invalid intrinsics: {e}") from None


def scaled_default(cam: PinholeCamera, size: tuple[int, int], name: str) -> tuple[PinholeCamera, Optional[str]]:
    """A nominal camera adapted to the actual image size (with a note), or unchanged."""
    if (cam.width, cam.height) == tuple(size):
        return cam, None
    note = (f"{name} intrinsics are for {cam.width}x{cam.height}; images are {size[0]}x{size[1]}: "
            "intrinsics rescaled (pass --camera to set them)")
    log.warning(note)
    return cam.resized(*size), note


# ------------------------------------------------------------------- text
_COMMENT = re.compile(r"^\s*(#|//|%)")


def text_lines(path: Path) -> list[tuple[int, str]]:
    """Non-empty, non-comment lines of a text file with their 1-based line numbers."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text file") from None
    except OSError as e:
        raise DatasetError(f"cannot read {path}: {e}") from None
    return [(i, s.strip()) for i, s in enumerate(text.splitlines(), 1) if s.strip() and not _COMMENT.match(s)]


def parse_floats(s: str, path: Path, lineno: int, expected: Optional[Sequence[int]] = None,
                 what: str = "") -> list[float]:
    parts = s.replace(",", " ").split()
    if expected is not None and len(parts) not in expected:
        want = " or ".join(str(n) for n in expected)
        raise DatasetError(f"{path}:{lineno}: expected {want} numbers{' (' + what + ')' if what else ''}, "
                           f"got {len(parts)}: {s!r}")
    try:
        return [float(p) for p in parts]
    except ValueError:
        raise DatasetError(f"{path}:{lineno}: non-numeric value in {s!r}") from None


def check_max_frames(max_frames: Optional[int]) -> Optional[int]:
    if max_frames is None:
        return None
    if int(max_frames) <= 0:
        raise DatasetError(f"max_frames must be a positive number of frames, got {max_frames}")
    return int(max_frames)


# ---------------------------------------------------------------- dataset
@dataclass
class ImageSequence(Dataset):
    """A dataset of per-frame image files (the one implementation behind every reader)."""

    rgb_paths: list = field(default_factory=list)  # N Paths
    depth_paths: list = field(default_factory=list)  # N Paths or None
    raw_camera: Optional[PinholeCamera] = None  # camera of the stored files (may be distorted)
    depth_invalid: Optional[int] = None  # raw depth value meaning "no reading" besides 0
    background: Background = WHITE  # RGBA images are composited over this colour

    def __post_init__(self) -> None:
        n = len(self.timestamps)
        if not (len(self.rgb_paths) == len(self.gt_poses) == n) or (self.depth_paths and len(self.depth_paths) != n):
            raise ValueError("ImageSequence: per-frame lists differ in length")  # programming error
        if not self.depth_paths:
            self.depth_paths = [None] * n
        if self.raw_camera is None:
            self.raw_camera = self.camera

    def truncate(self, max_frames: Optional[int]) -> "ImageSequence":
        if max_frames is not None and max_frames < len(self):
            self.timestamps = self.timestamps[:max_frames]
            self.gt_poses = self.gt_poses[:max_frames]
            self.rgb_paths = self.rgb_paths[:max_frames]
            self.depth_paths = self.depth_paths[:max_frames]
        return self

    def _check_size(self, img: np.ndarray, path: Path) -> None:
        cam = self.raw_camera
        if img.shape[:2] != (cam.height, cam.width):
            raise DatasetError(
                f"image size {img.shape[1]}x{img.shape[0]} differs from the first image's "
                f"{cam.width}x{cam.height}: {path}"
            )

    def _read_depth(self, path: Path) -> np.ndarray:
        """Depth in metres on the colour image's pixel grid (readers with a separate depth camera override it)."""
        return read_depth(path, self.depth_scale, self.depth_invalid)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an int, got {type(i).__name__}")
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        i = int(i)
        rgb_path = resolve_image_path(Path(self.rgb_paths[i]))
        rgb = read_rgb(rgb_path, self.background)
        self._check_size(rgb, rgb_path)
        depth = None
        dp = self.depth_paths[i]
        if dp is not None and self.depth_scale is not None:
            depth = self._read_depth(Path(dp))
            self._check_size(depth, Path(dp))
        cam = self.raw_camera
        if cam.dist is not None:
            rgb = cam.undistort_image(rgb)
            if depth is not None:
                depth = cam.undistort_image(depth)
        pose = self.gt_poses[i]
        return Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            rgb=rgb,
            camera=self.camera,
            depth=depth,
            c2w=None if pose is None else np.array(pose, dtype=np.float64),
        )


def build_sequence(
    *,
    root: Path,
    kind: str,
    raw_camera: PinholeCamera,
    timestamps: Sequence[float],
    rgb_paths: Sequence[Path],
    depth_paths: Optional[Sequence[Optional[Path]]],
    gt_poses: Sequence[Optional[np.ndarray]],
    depth_scale: Optional[float],
    meta: dict,
    max_frames: Optional[int],
    depth_invalid: Optional[int] = None,
    background: Background = WHITE,
    cls: type = ImageSequence,
    extra: Optional[dict] = None,
) -> ImageSequence:
    """Assemble an :class:`ImageSequence` (or subclass ``cls`` with the fields ``extra``) and add the
    common ``meta`` entries."""
    meta = dict(meta)
    meta["undistorted"] = raw_camera.dist is not None
    if raw_camera.dist is not None:
        meta["distortion"] = list(raw_camera.dist)
    ds = cls(
        root=Path(root),
        camera=raw_camera.undistorted(),
        timestamps=np.asarray(timestamps, np.float64),
        gt_poses=list(gt_poses),
        kind=kind,
        depth_scale=depth_scale,
        meta=meta,
        rgb_paths=[Path(p) for p in rgb_paths],
        depth_paths=list(depth_paths) if depth_paths is not None else [],
        raw_camera=raw_camera,
        depth_invalid=depth_invalid,
        background=tuple(int(c) for c in background),
        **(extra or {}),
    )
    ds.truncate(max_frames)
    if ds.depth_scale is not None:
        ds.meta["frames_with_depth"] = int(sum(p is not None for p in ds.depth_paths))
        if ds.meta["frames_with_depth"] == 0:
            ds.depth_scale = None
    return ds
