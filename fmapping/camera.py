"""Pinhole camera: intrinsics, optional OpenCV distortion, pixel <-> ray.

Conventions are those of :mod:`fmapping.geometry` (OpenCV camera axes,
camera-to-world poses, metres). Pixel ``(u, v)`` has its centre at integer
coordinates: the top-left pixel centre is ``(0, 0)``.

Rays are generated with *z-normalised* camera directions (``d_cam = ((u-cx)/fx,
(v-cy)/fy, 1)``), so the ray parameter ``t`` of a point equals its depth along
the optical axis. Renderers multiply sample spacings by ``|d|`` to get metres.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np
import torch
from torch import Tensor


@dataclass(frozen=True)
class PinholeCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    # OpenCV distortion (k1, k2, p1, p2[, k3]); None when images are already undistorted.
    dist: Optional[tuple[float, ...]] = None

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError(f"camera intrinsics must be finite, got fx,fy,cx,cy={vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (-0.5 * self.width <= self.cx <= 1.5 * self.width
                and -0.5 * self.height <= self.cy <= 1.5 * self.height):
            raise ValueError(
                f"principal point ({self.cx}, {self.cy}) is far outside the {self.width}x{self.height} image: "
                "are the intrinsics in the order fx,fy,cx,cy and for this resolution?"
            )
        if self.dist is not None and len(self.dist) not in (4, 5, 8):
            raise ValueError(f"distortion must have 4, 5 or 8 coefficients, got {len(self.dist)}")

    # ------------------------------------------------------------------ basics
    @classmethod
    def from_string(cls, text: str, width: int, height: int) -> "PinholeCamera":
        """Parse ``"fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]"`` (the ``--camera`` option)."""
        try:
            vals = [float(x) for x in text.replace(" ", ",").split(",") if x]
        except ValueError as e:
            raise ValueError(f"--camera expects numbers 'fx,fy,cx,cy[,k1,k2,p1,p2,k3]', got {text!r}") from e
        if len(vals) not in (4, 8, 9):
            raise ValueError(f"--camera expects 4, 8 or 9 numbers (fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]), got {len(vals)}")
        dist = tuple(vals[4:]) if len(vals) > 4 and any(vals[4:]) else None
        return cls(vals[0], vals[1], vals[2], vals[3], int(width), int(height), dist)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def to_dict(self) -> dict:
        return {
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "width": self.width, "height": self.height,
            "dist": list(self.dist) if self.dist is not None else None,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "PinholeCamera":
        dist = d.get("dist")
        return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                   int(d["width"]), int(d["height"]), tuple(dist) if dist else None)

    def scaled(self, s: float) -> "PinholeCamera":
        """Camera for an image resized by factor ``s`` (pixel-centre convention kept)."""
        return self.resized(int(round(self.width * s)), int(round(self.height * s)))

    def resized(self, width: int, height: int) -> "PinholeCamera":
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
            width=int(width), height=int(height),
        )

    # ------------------------------------------------------------ distortion
    def undistort_image(self, img: np.ndarray, interpolation: Optional[int] = None) -> np.ndarray:
        """Remove lens distortion (same K kept); identity when ``dist`` is None."""
        if self.dist is None:
            return img
        import cv2

        if interpolation is None:
            interpolation = cv2.INTER_NEAREST if img.dtype != np.uint8 else cv2.INTER_LINEAR
        map1, map2 = cv2.initUndistortRectifyMap(
            self.K, np.asarray(self.dist, np.float64), None, self.K, (self.width, self.height), cv2.CV_32FC1
        )
        return cv2.remap(img, map1, map2, interpolation)

    def undistorted(self) -> "PinholeCamera":
        return replace(self, dist=None)

    # ------------------------------------------------------------ projection
    def pixel_grid(self, device=None, dtype=torch.float32) -> Tensor:
        """All pixel centres as (H*W, 2) (u, v), row-major."""
        v, u = torch.meshgrid(
            torch.arange(self.height, device=device, dtype=dtype),
            torch.arange(self.width, device=device, dtype=dtype),
            indexing="ij",
        )
        return torch.stack([u.reshape(-1), v.reshape(-1)], -1)

    def unproject(self, uv: Tensor, depth: Optional[Tensor] = None) -> Tensor:
        """Pixels (..., 2) -> camera-frame points (..., 3) at ``depth`` (z), or z=1 directions."""
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        d = torch.stack([x, y, torch.ones_like(x)], -1)
        return d if depth is None else d * depth[..., None]

    def project(self, pts_cam: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-frame points (..., 3) -> pixels (..., 2) and depth z (...)."""
        z = pts_cam[..., 2]
        zs = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
        u = self.fx * pts_cam[..., 0] / zs + self.cx
        v = self.fy * pts_cam[..., 1] / zs + self.cy
        return torch.stack([u, v], -1), z

    def world_to_pixels(self, c2w: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (M, 3) -> pixels (M, 2) and camera z (M,) in the view ``c2w`` (numpy)."""
        r, t = c2w[:3, :3], c2w[:3, 3]
        pc = (pts - t) @ r
        z = pc[:, 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        return np.stack([self.fx * pc[:, 0] / zs + self.cx, self.fy * pc[:, 1] / zs + self.cy], -1), z

    def in_image(self, uv: Tensor, margin: float = 0.0) -> Tensor:
        return (
            (uv[..., 0] >= -0.5 + margin) & (uv[..., 0] <= self.width - 0.5 - margin)
            & (uv[..., 1] >= -0.5 + margin) & (uv[..., 1] <= self.height - 0.5 - margin)
        )

    def rays(self, c2w: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
        """World rays for pixels ``uv`` (N, 2) of a camera at ``c2w`` (4, 4) or (N, 4, 4).

        Returns origins (N, 3) and z-normalised world directions (N, 3): a point at
        ray parameter ``t`` has camera depth ``t``.
        """
        d_cam = self.unproject(uv.to(c2w.dtype))
        rot = c2w[..., :3, :3]
        if c2w.dim() == 2:
            d_world = d_cam @ rot.T
            o = c2w[:3, 3].expand_as(d_world)
        else:
            d_world = (rot @ d_cam[..., None])[..., 0]
            o = c2w[..., :3, 3]
        return o, d_world


def sample_image(img: Tensor, uv: Tensor, mode: str = "bilinear") -> Tensor:
    """Sample an image (H, W, C) at float pixels (N, 2) with border clamping -> (N, C)."""
    h, w = img.shape[:2]
    grid = torch.stack([(uv[:, 0] + 0.5) / w * 2 - 1, (uv[:, 1] + 0.5) / h * 2 - 1], -1)
    out = torch.nn.functional.grid_sample(
        img.permute(2, 0, 1)[None].to(uv.dtype), grid[None, None], mode=mode,
        padding_mode="border", align_corners=False,
    )
    return out[0, :, 0].T
