"""The one frame record and the dataset interface every reader implements."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from fmapping.camera import PinholeCamera


class DatasetError(ValueError):
    """Bad or missing dataset input; the message names the file (and line) at fault."""


@dataclass
class Frame:
    index: int
    timestamp: float
    rgb: np.ndarray  # (H, W, 3) uint8, undistorted
    camera: PinholeCamera  # intrinsics of ``rgb`` (dist is None after undistortion)
    depth: Optional[np.ndarray] = None  # (H, W) float32 metres, 0 = invalid
    c2w: Optional[np.ndarray] = None  # (4, 4) float64 ground-truth camera-to-world, if known


@dataclass
class Dataset:
    """A lazily loaded sequence of frames.

    Readers fill the index (timestamps, file paths, GT poses) at construction and
    decode images only in :meth:`__getitem__`.
    """

    root: Path
    camera: PinholeCamera  # intrinsics of the frames as delivered (undistorted)
    timestamps: np.ndarray  # (N,) seconds
    gt_poses: list  # N entries: (4, 4) float64 c2w or None
    kind: str = "unknown"
    depth_scale: Optional[float] = None  # raw depth units per metre, None when no depth
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> Frame:  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    @property
    def has_depth(self) -> bool:
        return self.depth_scale is not None

    def describe(self) -> dict:
        """What a run writes into its outputs: the data, intrinsics and depth scale in use."""
        return {
            "root": str(self.root),
            "kind": self.kind,
            "frames": len(self),
            "camera": self.camera.to_dict(),
            "depth_scale": self.depth_scale,
            "gt_poses": int(sum(p is not None for p in self.gt_poses)),
            **self.meta,
        }
