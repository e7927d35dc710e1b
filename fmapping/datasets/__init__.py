"""Dataset readers behind one factory, :func:`open_dataset`.

Formats (``kind``): ``"tum"`` (TUM RGB-D, or any TUM-layout folder with ``calib.txt``),
``"synthetic"`` (``fmapping synth`` output, TUM layout + ``scene.json``), ``"replica"``
(NICE-SLAM layout), ``"7scenes"`` and ``"nerf"`` (``transforms.json``). Readers are
lazy: construction reads the text files and the first image only; images are decoded
in ``dataset[i]``. Frames follow the conventions of :mod:`fmapping.datasets.base`
(RGB uint8, depth float32 metres with 0 = invalid, c2w float64 in OpenCV axes).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Union

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import WHITE, Background, ImageSequence
from fmapping.datasets.base import Dataset, DatasetError, Frame
from fmapping.datasets.nerf import TRANSFORMS_FILES, is_nerf, load_nerf
from fmapping.datasets.replica import is_replica, load_replica
from fmapping.datasets.sevenscenes import is_sevenscenes, load_sevenscenes
from fmapping.datasets.tum import is_tum, load_tum

__all__ = ["Frame", "Dataset", "DatasetError", "ImageSequence", "open_dataset", "detect_kind", "KINDS"]

_LOADERS: dict[str, Callable] = {
    "tum": load_tum,
    "synthetic": load_tum,
    "replica": load_replica,
    "7scenes": load_sevenscenes,
    "nerf": load_nerf,
}
KINDS = tuple(_LOADERS)
_ALIASES = {"sevenscenes": "7scenes", "7-scenes": "7scenes", "seven_scenes": "7scenes", "transforms": "nerf",
            "nerfstudio": "nerf", "synth": "synthetic"}
_LOOKED_FOR = (
    "rgb.txt (TUM RGB-D / calib.txt / fmapping synth), "
    "results/frameXXXXXX.jpg + traj.txt (Replica, NICE-SLAM layout), "
    "frame-XXXXXX.color.png or seq-XX/ folders (7-Scenes), "
    f"{' or '.join(TRANSFORMS_FILES)} (NeRF / nerfstudio)"
)


def detect_kind(path: Union[str, Path]) -> str:
    """The format of a dataset folder (or of a ``transforms*.json`` / ``rgb.txt`` file)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"dataset folder not found: {path}")
    if path.is_file():
        if path.suffix == ".json":
            return "nerf"
        if path.name == "rgb.txt":
            return "tum"
        raise DatasetError(f"{path}: not a dataset file (give a folder, a transforms*.json or an rgb.txt)")
    if is_tum(path):
        return "synthetic" if _is_synthetic(path) else "tum"
    if is_replica(path):
        return "replica"
    if is_sevenscenes(path):
        return "7scenes"
    if is_nerf(path):
        return "nerf"
    entries = sorted(p.name + ("/" if p.is_dir() else "") for p in path.iterdir())
    shown = ", ".join(entries[:12]) + (f", ... ({len(entries)} entries)" if len(entries) > 12 else "")
    raise DatasetError(
        f"{path}: no recognisable dataset format. Looked for {_LOOKED_FOR}. "
        f"The folder contains: {shown or 'nothing'}"
    )


def _is_synthetic(root: Path) -> bool:
    from fmapping.datasets.tum import SYNTHETIC_GENERATOR, read_scene_json

    try:
        scene = read_scene_json(root / "scene.json")
    except DatasetError:
        return False
    return isinstance(scene, dict) and scene.get("generator") == SYNTHETIC_GENERATOR


def open_dataset(
    path: Union[str, Path],
    camera: Union[str, PinholeCamera, None] = None,
    max_frames: Optional[int] = None,
    kind: str = "auto",
    background: Background = WHITE,
) -> Dataset:
    """Open a dataset folder lazily.

    Args:
        path: dataset folder (or a ``transforms*.json`` / ``rgb.txt`` inside one).
        camera: intrinsics override replacing the reader's, either a
            ``"fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]"`` string (the ``--camera`` option; the
            image size is read from the first image) or a :class:`PinholeCamera`.
            With distortion, frames are undistorted and ``dataset.camera`` has none.
        max_frames: keep only the first N frames.
        kind: ``"auto"`` or one of :data:`KINDS`.
        background: RGB colour (0-255) that RGBA images are composited over.

    Raises:
        DatasetError: missing folder, unknown format, malformed files (naming file and line).
    """
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"dataset folder not found: {path}")
    bg = tuple(background)
    if len(bg) != 3 or not all(isinstance(c, (int, float)) and 0 <= c <= 255 for c in bg):
        raise DatasetError(f"background must be an RGB triple in 0..255, got {background!r}")
    k = _ALIASES.get(kind.lower(), kind.lower())
    if k == "auto":
        k = detect_kind(path)
    if k not in _LOADERS:
        raise DatasetError(f"unknown dataset kind {kind!r}; expected 'auto' or one of {', '.join(KINDS)}")
    root = path.parent if path.is_file() and k != "nerf" else path
    return _LOADERS[k](root, camera=camera, max_frames=max_frames, background=bg)
