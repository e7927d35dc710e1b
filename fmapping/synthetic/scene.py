"""The procedural room: layout draws (room, furniture, camera loop), the wide-variety
:class:`Style`, the surface rectangles and the generator's camera (see :mod:`fmapping.synthetic`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from fmapping.camera import PinholeCamera
from fmapping.synthetic.texture import Texture, _make_texture, _style_texture

_PLACEMENT_CLEARANCE = 0.55  # xy distance furniture footprints keep from the camera loop
_WALL_GAP = 0.05  # furniture keeps this gap from the walls
_BOX_GAP = 0.15  # and this separation from each other

VARIETIES = ("default", "wide")

# full sizes (x, y, z) ranges in metres for each furniture kind
_KIND_SIZES = {
    "table": ((0.8, 1.4), (0.6, 0.9), (0.72, 0.78)),
    "cabinet": ((0.4, 1.0), (0.35, 0.6), (0.8, 1.2)),
    "shelf": ((0.6, 1.0), (0.3, 0.45), (1.6, 2.1)),
    "small": ((0.2, 0.45), (0.2, 0.45), (0.3, 0.55)),
    # thin structures (wide variety only): a pole and an upright board
    "pole": ((0.03, 0.07), (0.03, 0.07), (1.5, 2.3)),
    "panel": ((0.5, 1.1), (0.018, 0.03), (0.9, 1.9)),
}
_THIN_KINDS = ("pole", "panel")


@dataclass(frozen=True)
class _Ranges:
    """Uniform ranges of the layout draws."""

    room: tuple  # ((x lo, x hi), (y lo, y hi), (z lo, z hi)) full room sizes, m
    loop_radius: tuple  # loop radii as a fraction of the room sizes
    height: tuple  # loop height, m
    look_yaw: tuple  # yaw offset of the view from facing outwards, rad
    pitch: tuple  # mean view pitch, rad (negative = down)


_DEFAULT_RANGES = _Ranges(((4.0, 6.0), (3.5, 5.0), (2.5, 3.0)), (0.16, 0.2), (1.3, 1.6), (0.8, 1.25), (-0.45, -0.3))
# larger rooms; views turned inwards (yaw offset > pi/2) and more level views see across the room
_WIDE_RANGES = _Ranges(((4.0, 8.0), (3.5, 6.0), (2.5, 3.0)), (0.12, 0.22), (1.2, 1.7), (0.6, 2.6), (-0.45, -0.1))


@dataclass(frozen=True)
class Style:
    """What the seed draws for a ``"wide"`` scene on top of the layout (the default room has none).

    Texture lengths are multiplied by ``texture_scale`` and amplitudes by ``contrast``
    (both jittered per surface); each surface is near-uniform with ``low_texture_prob``
    or striped with ``stripe_prob``. Camera effects act on the written RGB only:
    ``written = gain * blur(clean) + offset + noise`` per channel, in 8-bit units, with
    ``log gain = exposure_amp * sin(2 pi i / exposure_period + p_0) + white_balance_amp *
    sin(2 pi i / (0.7 exposure_period) + p_{1+c})`` and ``offset = offset_amp_dn * sin(2 pi i /
    exposure_period + p_{4+c})`` at frame i and channel c (p = ``exposure_phase``); the blur
    is a line ``blur_exposure`` times the image motion to the neighbouring frame long;
    ``jpeg_quality`` 0 writes PNG.
    """

    texture_scale: float
    contrast: float
    low_texture_prob: float
    stripe_prob: float
    striped_floor: bool
    free_yaw_prob: float  # chance that a box gets a free yaw instead of 0 or 90 deg
    poles: int
    panels: int
    exposure_amp: float
    white_balance_amp: float
    offset_amp_dn: float
    exposure_period: float  # frames
    exposure_phase: tuple  # 7 phases (rad): exposure, white balance (3), offset (3)
    noise_sigma_dn: float
    blur_exposure: float  # fraction of the frame interval the shutter is open
    jpeg_quality: int


def draw_style(seed: int) -> Style:
    """The wide-variety :class:`Style` for ``seed`` (its own random stream: the layout draws are
    independent of it)."""
    rng = np.random.default_rng([int(seed), 7005])

    def maybe(p: float, lo: float, hi: float) -> float:
        on = rng.random() < p
        value = float(rng.uniform(lo, hi))  # drawn either way: later draws do not depend on `on`
        return value if on else 0.0

    return Style(
        texture_scale=float(np.exp(rng.uniform(np.log(0.7), np.log(4.0)))),
        contrast=float(np.exp(rng.uniform(np.log(0.2), np.log(1.2)))),
        low_texture_prob=maybe(0.6, 0.15, 0.5),
        stripe_prob=maybe(0.5, 0.05, 0.25),
        striped_floor=bool(rng.random() < 0.4),
        free_yaw_prob=float(rng.choice([0.0, 0.5, 0.9])),
        poles=int(rng.integers(0, 4)),
        panels=int(rng.integers(0, 3)),
        exposure_amp=maybe(0.75, 0.05, 0.25),
        white_balance_amp=maybe(0.6, 0.02, 0.08),
        offset_amp_dn=maybe(0.5, 2.0, 10.0),
        exposure_period=float(rng.uniform(60, 300)),
        exposure_phase=tuple(float(x) for x in rng.uniform(0, 2 * np.pi, 7)),
        noise_sigma_dn=maybe(0.7, 0.5, 3.0),
        blur_exposure=maybe(0.5, 0.15, 0.5),
        jpeg_quality=int(round(maybe(0.5, 60, 95))),
    )


@dataclass(frozen=True)
class Box:
    """A furniture box standing on the floor, rotated by ``yaw`` (rad) about +z."""

    kind: str
    center: np.ndarray  # (3,) world
    half: np.ndarray  # (3,) half sizes in the local frame
    yaw: float

    @property
    def rotation(self) -> np.ndarray:
        """Local-to-world rotation (3, 3)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_local(self, pts: np.ndarray) -> np.ndarray:
        return (np.asarray(pts, np.float64) - self.center) @ self.rotation

    def footprint(self) -> np.ndarray:
        """The four xy corners (4, 2) of the footprint, counter-clockwise."""
        hx, hy = self.half[:2]
        loc = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        return loc @ self.rotation[:2, :2].T + self.center[:2]

    def to_dict(self) -> dict:
        return {"kind": self.kind, "center": self.center.tolist(), "size": (2 * self.half).tolist(),
                "yaw_deg": math.degrees(self.yaw)}


@dataclass(frozen=True)
class Rect:
    """A planar surface patch ``origin + a * e1 + b * e2`` (a, b in [0, 1]); ``e1 x e2`` is the
    outward normal (pointing into free space). Texture coordinates are metres along e1, e2."""

    sid: int
    name: str
    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    exposed: bool = True  # False for box faces resting on the floor

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.e1, self.e2)
        return n / np.linalg.norm(n)

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.e1, self.e2)))

    def uv(self, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Texture coordinates (metres along e1, e2) of points given as columns (3, M)."""
        a = self.e1 / np.linalg.norm(self.e1)
        b = self.e2 / np.linalg.norm(self.e2)
        q = [cols[k] - self.origin[k] for k in range(3)]
        return q[0] * a[0] + q[1] * a[1] + q[2] * a[2], q[0] * b[0] + q[1] * b[1] + q[2] * b[2]



@dataclass(frozen=True)
class LoopPath:
    """Closed camera loop ``c + r(theta) * (rx cos(s*theta), ry sin(s*theta))`` at height
    ``z0 + dz sin(2 theta + phase)``; ``r(theta) = 1 + wobble sin(3 theta + phase)``."""

    center: np.ndarray  # (2,)
    radii: np.ndarray  # (2,)
    height: float
    height_amp: float
    direction: int  # +1 counter-clockwise, -1 clockwise (seen from above)
    wobble: float
    phase: float

    def positions(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, np.float64)
        r = 1.0 + self.wobble * np.sin(3 * theta + self.phase)
        a = self.direction * theta
        x = self.center[0] + r * self.radii[0] * np.cos(a)
        y = self.center[1] + r * self.radii[1] * np.sin(a)
        z = self.height + self.height_amp * np.sin(2 * theta + self.phase)
        return np.stack([x, y, z], -1)


@dataclass
class Scene:
    seed: int
    room_min: np.ndarray  # (3,)
    room_max: np.ndarray  # (3,)
    boxes: list  # list[Box]
    texture: Texture
    path: LoopPath
    rects: list = field(default_factory=list)  # list[Rect], index == surface id
    style: Optional[Style] = None  # wide variety only
    surface_styles: list = field(default_factory=list)  # wide variety: per-surface draws (dicts)

    @property
    def n_surfaces(self) -> int:
        return 6 + 6 * len(self.boxes)

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.room_min.copy(), self.room_max.copy()

    def to_dict(self) -> dict:
        return {
            "room": {"min": self.room_min.tolist(), "max": self.room_max.tolist()},
            "boxes": [b.to_dict() for b in self.boxes],
        }


def camera_for_size(width: int, height: int) -> PinholeCamera:
    """The generator's pinhole camera: fx = fy = 0.8 W (about 64 deg horizontal FOV)."""
    if int(width) < 8 or int(height) < 8:
        raise ValueError(f"synthetic image size must be at least 8x8, got {width}x{height}")
    w, h = int(width), int(height)
    return PinholeCamera(0.8 * w, 0.8 * w, (w - 1) / 2.0, (h - 1) / 2.0, w, h)


def _room_rects(lo: np.ndarray, hi: np.ndarray) -> list:
    """Floor, ceiling and walls with normals pointing into the room."""
    X, Y, Z = hi - lo
    ex, ey, ez = np.array([X, 0, 0.0]), np.array([0, Y, 0.0]), np.array([0, 0, Z])
    x0, y0, z0 = lo
    return [
        Rect(0, "floor", lo.copy(), ex, ey),
        Rect(1, "ceiling", np.array([x0, y0, hi[2]]), ey, ex),
        Rect(2, "wall_xmin", lo.copy(), ey, ez),
        Rect(3, "wall_xmax", np.array([hi[0], y0, z0]), ez, ey),
        Rect(4, "wall_ymin", lo.copy(), ez, ex),
        Rect(5, "wall_ymax", np.array([x0, hi[1], z0]), ex, ez),
    ]


def _box_rects(box: Box, b: int) -> list:
    """Six faces of ``box`` (surface ids 6 + 6 b + f), outward normals."""
    rot, h = box.rotation, box.half
    out = []
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, 1):
            sgn = 1.0 if side else -1.0
            n = rot[:, axis] * sgn
            e1 = rot[:, a1] * 2 * h[a1]
            e2 = rot[:, a2] * 2 * h[a2]
            if np.dot(np.cross(e1, e2), n) < 0:
                e1, e2 = e2, e1
            origin = box.center + sgn * h[axis] * rot[:, axis] - 0.5 * e1 - 0.5 * e2
            f = 2 * axis + side
            out.append(Rect(6 + 6 * b + f, f"{box.kind}{b}_{'-+'[side]}{'xyz'[axis]}", origin, e1, e2,
                            exposed=(f != 4)))
    return out


def _footprint_distance(box: Box, xy: np.ndarray) -> np.ndarray:
    """Distance in the xy plane from points (M, 2) to the box footprint (0 inside)."""
    rot2 = box.rotation[:2, :2]
    q = np.abs((xy - box.center[:2]) @ rot2) - box.half[:2]
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1)


def _separation(a: Box, b: Box) -> float:
    """Lower bound of the xy distance between two footprints (separating-axis gaps; <= 0 if overlapping)."""
    ca, cb = a.footprint(), b.footprint()
    best = -np.inf
    for box in (a, b):
        for axis in box.rotation[:2, :2].T:
            pa, pb = ca @ axis, cb @ axis
            best = max(best, pb.min() - pa.max(), pa.min() - pb.max())
    return float(best)


def _place_boxes(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, path: LoopPath,
                 extra_kinds: Sequence[str] = (), free_yaw_prob: float = 0.5) -> list:
    loop_xy = path.positions(np.linspace(0, 2 * np.pi, 1440, endpoint=False))[:, :2]
    kinds = ["table", "cabinet", "shelf", "small"]
    kinds += list(rng.choice(["table", "cabinet", "small", "cabinet"], int(rng.integers(0, 4))))
    kinds += list(extra_kinds)
    boxes: list = []
    for kind in kinds:
        size = np.array([rng.uniform(*r) for r in _KIND_SIZES[kind]])
        placed = None
        for _shrink in range(6):
            for _ in range(300):
                yaw = (float(rng.choice([0.0, np.pi / 2])) if rng.random() < 1.0 - free_yaw_prob
                       else float(rng.uniform(-np.pi / 4, np.pi / 4)))
                center = np.array([rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), size[2] / 2])
                cand = Box(kind, center, size / 2, yaw)
                fp = cand.footprint()
                if (fp < lo[:2] + _WALL_GAP).any() or (fp > hi[:2] - _WALL_GAP).any():
                    continue
                if _footprint_distance(cand, loop_xy).min() < _PLACEMENT_CLEARANCE:
                    continue
                if any(_separation(cand, other) < _BOX_GAP for other in boxes):
                    continue
                placed = cand
                break
            if placed is not None:
                break
            size[:2] *= 0.85
        if placed is not None:
            boxes.append(placed)
    if len(boxes) < 4:
        raise RuntimeError(f"synthetic scene: could place only {len(boxes)} furniture boxes (need 4)")
    return boxes


def _check_variety(variety: str) -> str:
    if variety not in VARIETIES:
        raise ValueError(f"variety must be one of {VARIETIES}, got {variety!r}")
    return variety


def make_scene(seed: int = 0, variety: str = "default") -> Scene:
    """The procedural room for ``seed``: sizes, furniture, textures and camera loop.

    ``variety="wide"`` also draws a :class:`Style` (see the module docstring).
    """
    style = draw_style(seed) if _check_variety(variety) == "wide" else None
    ranges = _DEFAULT_RANGES if style is None else _WIDE_RANGES
    rng = np.random.default_rng([int(seed), 7001])
    dims = np.array([rng.uniform(*r) for r in ranges.room])
    lo = np.array([-dims[0] / 2, -dims[1] / 2, 0.0])
    hi = np.array([dims[0] / 2, dims[1] / 2, dims[2]])
    path = LoopPath(
        center=rng.uniform(-0.1, 0.1, 2),
        radii=np.array([rng.uniform(*ranges.loop_radius) * dims[0], rng.uniform(*ranges.loop_radius) * dims[1]]),
        height=float(rng.uniform(*ranges.height)),
        height_amp=0.08,
        direction=int(rng.choice([-1, 1])),
        wobble=float(rng.uniform(0.0, 0.08)),
        phase=float(rng.uniform(0, 2 * np.pi)),
    )
    if style is None:
        boxes = _place_boxes(rng, lo, hi, path)
    else:
        thin = ["pole"] * style.poles + ["panel"] * style.panels
        boxes = _place_boxes(rng, lo, hi, path, thin, style.free_yaw_prob)
    rects = _room_rects(lo, hi)
    for b, box in enumerate(boxes):
        rects += _box_rects(box, b)
    texture = _make_texture(rng, rects)
    if style is None:
        return Scene(int(seed), lo, hi, boxes, texture, path, rects)
    texture, records = _style_texture(texture, style, rects, np.random.default_rng([int(seed), 7006]))
    return Scene(int(seed), lo, hi, boxes, texture, path, rects, style, records)
