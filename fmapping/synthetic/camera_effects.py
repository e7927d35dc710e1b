"""Camera effects of the wide variety on the written colour frames: exposure and white-balance
drift, motion blur, sensor noise."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.synthetic.scene import Style


def exposure_curve(style: Style, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame gain (N, 3) and offset (N, 3, 8-bit units) of the written colour (see :class:`Style`),
    rounded as recorded in scene.json so that the record reproduces the images."""
    i = np.arange(int(frames), dtype=np.float64)[:, None]
    ph = np.asarray(style.exposure_phase, np.float64)
    w = 2 * np.pi / style.exposure_period
    log_gain = style.exposure_amp * np.sin(w * i + ph[0]) + style.white_balance_amp * np.sin(w / 0.7 * i + ph[1:4])
    offset = style.offset_amp_dn * np.sin(w * i + ph[4:7])
    return np.round(np.exp(log_gain), 5), np.round(offset, 3) + 0.0  # + 0.0: no -0.0 in the record


def image_motion(camera: PinholeCamera, c2w: np.ndarray, c2w_other: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Mean displacement (2,) in pixels of the points seen at ``c2w`` (z-depth ``depth``) when they
    are seen from ``c2w_other`` instead (on a coarse pixel grid)."""
    h, w = depth.shape
    step = max(1, min(h, w) // 8)
    v, u = np.mgrid[step // 2:h:step, step // 2:w:step]
    z = depth[v, u].astype(np.float64).ravel()
    u, v = u.ravel().astype(np.float64), v.ravel().astype(np.float64)
    pc = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)
    world = pc @ c2w[:3, :3].T + c2w[:3, 3]
    q = (world - c2w_other[:3, 3]) @ c2w_other[:3, :3]
    ok = (z > 0) & (q[:, 2] > 1e-3)
    if not ok.any():
        return np.zeros(2)
    du = q[ok, 0] / q[ok, 2] * camera.fx + camera.cx - u[ok]
    dv = q[ok, 1] / q[ok, 2] * camera.fy + camera.cy - v[ok]
    return np.array([du.mean(), dv.mean()])


def _line_kernel(vec: np.ndarray) -> Optional[np.ndarray]:
    """Normalised kernel of a line segment ``vec`` (dx, dy) pixels long centred on the middle pixel
    (centred: the blurred image does not move against the GT pose); None below half a pixel."""
    length = float(np.hypot(vec[0], vec[1]))
    if length < 0.5:
        return None
    r = int(math.ceil(length / 2)) + 1
    k = np.zeros((2 * r + 1, 2 * r + 1))
    for t in np.linspace(-0.5, 0.5, int(math.ceil(4 * length)) + 1):
        x, y = r + t * vec[0], r + t * vec[1]
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        k[y0:y0 + 2, x0:x0 + 2] += np.array([[(1 - fx) * (1 - fy), fx * (1 - fy)], [(1 - fx) * fy, fx * fy]])
    return k / k.sum()


def apply_camera_effects(rgb: np.ndarray, gain: np.ndarray, offset: np.ndarray, blur: np.ndarray,
                         noise_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``clip(round(gain * blur(rgb) + offset + noise))`` per channel, uint8 (H, W, 3) in and out.

    ``blur`` is the motion-blur segment (dx, dy) in pixels, ``noise_sigma`` the standard
    deviation of the Gaussian sensor noise in 8-bit units.
    """
    import cv2

    img = rgb.astype(np.float32)
    kernel = _line_kernel(np.asarray(blur, np.float64))
    if kernel is not None:  # symmetric kernel: correlation = convolution
        img = cv2.filter2D(img, -1, kernel.astype(np.float32), borderType=cv2.BORDER_REFLECT)
    img = img * np.asarray(gain, np.float32) + np.asarray(offset, np.float32)
    if noise_sigma > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)

