"""Dataset readers behind one factory, :func:`open_dataset`.

Formats (``kind``): ``"tum"`` (TUM RGB-D, or any TUM-layout folder with ``calib.txt``),
``"synthetic"`` (``fmapping synth`` output, TUM layout + ``scene.json``), ``"replica"``
(NICE-SLAM layout), ``"7scenes"``, ``"nerf"`` (``transforms.json``), ``"euroc"`` (EuRoC
MAV ``mav0/``), ``"scannet"`` (ScanNet export), ``"rosbag"`` (rosbag2 folder, ``.mcap``,
``.db3``, ROS1 ``.bag``; needs the ``[ros]`` extra), ``"video"`` (``.mp4`` ``.avi``
``.mkv`` ``.mov``) and ``"images"`` (a plain folder of png / jpg). Readers are lazy:
construction reads the text files and the first image only; images are decoded in
``dataset[i]``. Frames follow the conventions of :mod:`fmapping.datasets.base` (RGB
uint8, depth float32 metres with 0 = invalid, c2w float64 in OpenCV axes).

Image folders, videos and bags without ``CameraInfo`` carry no intrinsics: they come from
``camera=`` (``--camera``) or a ``calib.txt`` / ``camera.yaml`` next to the images, and
without either the source is refused with an error that says so (never a guess).

``camera:N`` (a live webcam) is not a dataset: no length, no random access. It is opened
only with ``open_dataset(..., live=True)``, which ``python -m services.io play`` passes;
``fmapping map`` / ``slam`` / ``info`` get an error telling them to record it first.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Union

from fmapping.camera import PinholeCamera
from fmapping.datasets._io import WHITE, Background, ImageSequence
from fmapping.datasets.base import Dataset, DatasetError, Frame
from fmapping.datasets.euroc import is_euroc, load_euroc
from fmapping.datasets.images import IMAGE_EXTS, is_image_folder, load_images
from fmapping.datasets.live import LiveCamera, is_live_spec, open_live, refuse_live
from fmapping.datasets.nerf import TRANSFORMS_FILES, is_nerf, load_nerf
from fmapping.datasets.replica import is_replica, load_replica
from fmapping.datasets.rosbag import BAG_EXTS, is_rosbag, load_rosbag
from fmapping.datasets.scannet import is_scannet, load_scannet
from fmapping.datasets.sevenscenes import is_sevenscenes, load_sevenscenes
from fmapping.datasets.tum import is_tum, load_tum
from fmapping.datasets.video import VIDEO_EXTS, is_video, load_video

__all__ = ["Frame", "Dataset", "DatasetError", "ImageSequence", "LiveCamera", "open_dataset", "detect_kind",
           "KINDS"]

_LOADERS: dict[str, Callable] = {
    "tum": load_tum,
    "synthetic": load_tum,
    "replica": load_replica,
    "7scenes": load_sevenscenes,
    "nerf": load_nerf,
    "euroc": load_euroc,
    "scannet": load_scannet,
    "rosbag": load_rosbag,
    "video": load_video,
    "images": load_images,
}
KINDS = tuple(_LOADERS)
_ALIASES = {"sevenscenes": "7scenes", "7-scenes": "7scenes", "seven_scenes": "7scenes", "transforms": "nerf",
            "nerfstudio": "nerf", "synth": "synthetic", "bag": "rosbag", "ros": "rosbag", "mcap": "rosbag",
            "image": "images", "folder": "images"}
_FILE_KINDS = ("nerf", "video", "rosbag")  # formats whose path is a file, not the folder around it
_OPTIONS = {"fps": ("images", "video"), "topic": ("rosbag",)}
_LOOKED_FOR = (
    "rgb.txt (TUM RGB-D / calib.txt / fmapping synth), "
    "results/frameXXXXXX.jpg + traj.txt (Replica, NICE-SLAM layout), "
    "frame-XXXXXX.color.png or seq-XX/ folders (7-Scenes), "
    f"{' or '.join(TRANSFORMS_FILES)} (NeRF / nerfstudio), "
    "mav0/cam0/data.csv (EuRoC MAV), color/ + intrinsic/ or pose/ (ScanNet export), "
    "metadata.yaml + .mcap/.db3 (rosbag2), "
    f"{'/'.join(IMAGE_EXTS)} images (a plain image folder)"
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
        if is_video(path):
            return "video"
        if is_rosbag(path):
            return "rosbag"
        raise DatasetError(
            f"{path}: not a dataset file (give a folder, a transforms*.json, an rgb.txt, a video "
            f"({'/'.join(VIDEO_EXTS)}) or a ROS bag ({'/'.join(BAG_EXTS)}))"
        )
    if is_tum(path):
        return "synthetic" if _is_synthetic(path) else "tum"
    if is_replica(path):
        return "replica"
    if is_sevenscenes(path):
        return "7scenes"
    if is_nerf(path):
        return "nerf"
    if is_euroc(path):
        return "euroc"
    if is_scannet(path):
        return "scannet"
    if is_rosbag(path):
        return "rosbag"
    if is_image_folder(path):  # last: the folders of the formats above hold images too
        return "images"
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


def _source_options(kind: str, path, **given) -> dict:
    """The options given (not None), refused with a message when they do not apply to ``kind``."""
    opts = {name: value for name, value in given.items() if value is not None}
    for name in opts:
        if kind not in _OPTIONS[name]:
            raise DatasetError(f"{name}= applies to {' / '.join(_OPTIONS[name])} sources, not to {kind} ({path})")
    return opts


def open_dataset(
    path: Union[str, Path],
    camera: Union[str, PinholeCamera, None] = None,
    max_frames: Optional[int] = None,
    kind: str = "auto",
    background: Background = WHITE,
    *,
    fps: Optional[float] = None,
    topic: Optional[str] = None,
    live: bool = False,
) -> Union[Dataset, LiveCamera]:
    """Open a dataset folder, video or bag lazily (or, with ``live=True``, a ``camera:N`` device).

    Args:
        path: dataset folder (or a ``transforms*.json`` / ``rgb.txt`` inside one), a video
            file, a ROS bag (file or rosbag2 folder), a plain image folder, or ``camera:N``.
        camera: intrinsics override replacing the reader's, either a
            ``"fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]"`` string (the ``--camera`` option; the
            image size is read from the first image), the path of a ``calib.txt`` /
            ``camera.yaml``, or a :class:`PinholeCamera`. With distortion, frames are
            undistorted and ``dataset.camera`` has none.
        max_frames: keep only the first N frames.
        kind: ``"auto"`` or one of :data:`KINDS`.
        background: RGB colour (0-255) that RGBA images are composited over.
        fps: frame rate of an image folder (default 30) or of a video (default: the container's).
        topic: image topic of a ROS bag (default: see :mod:`fmapping.datasets.rosbag`).
        live: accept ``camera:N`` and return a :class:`LiveCamera` (no ``len``, read in order);
            only a streaming consumer (``services.io play``) can use it.

    Raises:
        DatasetError: missing folder, unknown format, malformed files (naming file and line),
        no intrinsics for a source that has none, a live camera without ``live=True``.
    """
    if is_live_spec(path):
        if not live:
            raise refuse_live(str(path))
        _source_options("a live camera", path, fps=fps, topic=topic)
        return open_live(str(path), camera=camera, max_frames=max_frames)
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
    opts = _source_options(k, path, fps=fps, topic=topic)
    root = path.parent if path.is_file() and k not in _FILE_KINDS else path
    return _LOADERS[k](root, camera=camera, max_frames=max_frames, background=bg, **opts)
