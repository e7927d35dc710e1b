"""Procedural textured indoor room with an exact RGB-D camera: the embedded default data.

Nothing is downloaded: a seed determines the whole scene (room, furniture, textures,
camera loop) and :func:`generate_scene` writes it in TUM layout with ground truth.

Conventions (on top of :mod:`fmapping.geometry`):

* World frame: metres, **z up**, floor at ``z = 0``, room centred on ``x = y = 0``.
* Surfaces are planar rectangles with integer *surface ids*: ``0`` floor, ``1``
  ceiling, ``2``/``3`` walls at x-min/x-max, ``4``/``5`` walls at y-min/y-max, and
  ``6 + 6 * b + f`` for face ``f`` of box ``b`` with ``f = 2 * axis + side``
  (axis of the box's local frame, side 0 = the ``-`` face, 1 = the ``+`` face).
  Boxes stand on the floor, so their bottom faces (``f = 4``) are never exposed.
* Colour is view-independent: a pure function of (surface id, 3-D point) given by
  :func:`surface_colour`, values in ``[0.05, 0.95]``. Rendered pixels are the
  average of ``supersample ** 2`` sub-pixel rays; depth is the camera-frame ``z``
  of the centre ray's hit (exact up to float rounding).
* Timestamps are ``i / 30`` s; depth PNGs hold ``round(depth * 5000)`` (0 invalid).

Varieties: ``"default"`` is the close-up, strongly textured room above (unchanged for
existing seeds). ``"wide"`` lets the seed also draw a :class:`Style`: texture scale and
contrast, near-uniform and striped surfaces, larger rooms and camera distances, thin
poles and panels, rotated furniture, and camera effects on the written colour frames
only (smooth per-frame gain and offset per channel, motion blur, sensor noise, JPEG).
Depth, poses, GT mesh and clouds stay exact; the drawn parameters go to
``scene.json["variety"]`` for reports (nothing in the pipeline reads them).
"""
from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from fmapping.camera import PinholeCamera

DEPTH_FACTOR = 5000.0
FPS = 30.0
MAX_STEP_M = 0.03  # translation limit between consecutive frames
MAX_STEP_DEG = 2.0  # rotation limit between consecutive frames
STEP_FILL = 0.97  # trajectories use at most this fraction of the limits
CLEARANCE_M = 0.5  # camera distance to walls, floor, ceiling and furniture
VISIBLE_TOL_M = 0.01  # |projected z - rendered depth| for a GT point to count as seen

_PLACEMENT_CLEARANCE = 0.55  # xy distance furniture footprints keep from the camera loop
_WALL_GAP = 0.05  # furniture keeps this gap from the walls
_BOX_GAP = 0.15  # and this separation from each other
_NOISE_TABLE = 256  # value-noise lattice period (cells)
_N_SINES = 6
_LIGHT = np.array([0.35, -0.5, 0.8]) / np.linalg.norm([0.35, -0.5, 0.8])

PATTERNS = ("checker", "planks", "blobs", "tiles")
# PATTERNS plus those only the wide variety assigns; appended, so that the default's indices keep their meaning
_ALL_PATTERNS = PATTERNS + ("stripes",)
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


# ---------------------------------------------------------------------------- scene
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


@dataclass
class Texture:
    """Per-surface texture parameters (index = surface id) and a shared value-noise table."""

    table: np.ndarray  # (P, P) float32 in [0, 1)
    base: np.ndarray  # (S, 3) base colour incl. Lambert shading
    sin_k: np.ndarray  # (S, K, 2) wave vectors, rad/m
    sin_phase: np.ndarray  # (S, K)
    sin_amp: np.ndarray  # (S, K, 3)
    noise_cell: np.ndarray  # (S, 2) cell sizes of two value-noise octaves, m
    noise_off: np.ndarray  # (S, 2, 2) integer lattice offsets
    noise_amp: np.ndarray  # (S, 2, 3)
    pattern: np.ndarray  # (S,) index into PATTERNS
    pattern_scale: np.ndarray  # (S,) m
    pattern_amp: np.ndarray  # (S, 3)
    pattern_off: np.ndarray  # (S, 2) integer lattice offsets


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


def _make_texture(rng: np.random.Generator, rects: list) -> Texture:
    s = len(rects)
    table = rng.random((_NOISE_TABLE, _NOISE_TABLE)).astype(np.float32)
    # a distinct hue per surface: a random colour pushed away from grey
    base = rng.uniform(0.25, 0.75, (s, 3))
    base = 0.5 + 1.4 * (base - base.mean(1, keepdims=True)) + 0.6 * (base.mean(1, keepdims=True) - 0.5)
    shade = np.array([0.78 + 0.22 * max(0.0, float(np.dot(r.normal, _LIGHT))) for r in rects])
    base = base * shade[:, None] + 0.08 * (1 - shade[:, None])
    wavelength = np.exp(rng.uniform(np.log(0.03), np.log(0.3), (s, _N_SINES)))
    ang = rng.uniform(0, np.pi, (s, _N_SINES))
    sin_k = (2 * np.pi / wavelength)[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    # finer waves get weaker amplitude so that they do not alias at 320x240
    amp_scale = 0.05 * np.sqrt(wavelength / 0.3)
    sin_amp = amp_scale[..., None] * rng.uniform(-1, 1, (s, _N_SINES, 3))
    noise_cell = np.stack([rng.uniform(0.18, 0.35, s), rng.uniform(0.05, 0.1, s)], -1)
    noise_off = rng.integers(0, _NOISE_TABLE, (s, 2, 2))
    noise_amp = rng.uniform(-1, 1, (s, 2, 3)) * np.array([0.22, 0.12])[None, :, None]
    pattern = rng.integers(0, len(PATTERNS), s)
    pattern[0] = PATTERNS.index("planks")  # the floor is always a plank floor
    scale_ranges = {"checker": (0.06, 0.25), "planks": (0.1, 0.25), "blobs": (0.08, 0.3), "tiles": (0.15, 0.3)}
    pattern_scale = np.array([rng.uniform(*scale_ranges[PATTERNS[p]]) for p in pattern])
    pattern_amp = rng.uniform(-1, 1, (s, 3)) * 0.06 + rng.choice([-1, 1], (s, 1)) * 0.1
    pattern_off = rng.integers(0, _NOISE_TABLE, (s, 2))
    return Texture(table, base, sin_k, rng.uniform(0, 2 * np.pi, (s, _N_SINES)), sin_amp, noise_cell,
                   noise_off, noise_amp, pattern, pattern_scale, pattern_amp, pattern_off)


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


def _style_texture(tex: Texture, style: Style, rects: list, rng: np.random.Generator) -> tuple[Texture, list]:
    """``tex`` rescaled and re-weighted per surface as ``style`` asks; also the per-surface records."""
    s = len(rects)
    scale = style.texture_scale * np.exp(rng.uniform(-0.35, 0.35, s))
    contrast = style.contrast * np.exp(rng.uniform(-0.3, 0.3, s))
    striped = rng.random(s) < style.stripe_prob
    striped[0] = style.striped_floor
    low = (rng.random(s) < style.low_texture_prob) & ~striped
    low_level = rng.uniform(0.03, 0.08, s)
    # amplitude multipliers of the (sines, noise, pattern) fields
    mult = np.repeat(contrast[:, None], 3, 1)
    mult[low] = low_level[low, None]
    # stripes dominate: the other fields stay faint, so that the surface is close to 1-D
    mult[striped] = np.array([0.1, 0.15, 1.6])
    pattern = tex.pattern.copy()
    pattern[striped] = _ALL_PATTERNS.index("stripes")
    out = replace(tex, sin_k=tex.sin_k / scale[:, None, None], sin_amp=tex.sin_amp * mult[:, :1, None],
                  noise_cell=tex.noise_cell * scale[:, None], noise_amp=tex.noise_amp * mult[:, 1:2, None],
                  pattern=pattern, pattern_scale=tex.pattern_scale * scale,
                  pattern_amp=tex.pattern_amp * mult[:, 2:])
    records = [{"sid": r.sid, "name": r.name,
                "kind": "striped" if striped[r.sid] else "low_texture" if low[r.sid] else "textured",
                "pattern": _ALL_PATTERNS[int(pattern[r.sid])], "scale": float(scale[r.sid]),
                "amplitude": [float(x) for x in mult[r.sid]]} for r in rects]
    return out, records


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


# -------------------------------------------------------------------------- texture
def _value_noise(table: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth (quintic) value noise in [0, 1] on the integer lattice stored in ``table`` (P, P), P = 2^k."""
    p = table.shape[0]
    mask = p - 1
    shift = p.bit_length() - 1
    xf, yf = np.floor(x), np.floor(y)
    fx, fy = x - xf, y - yf
    xi = xf.astype(np.int32) & mask  # two's complement: also right for negative cells
    yi = yf.astype(np.int32) & mask
    xj, yj = (xi + 1) & mask, (yi + 1) & mask
    xi <<= shift
    xj <<= shift
    sx = fx * fx * fx * (fx * (fx * 6 - 15) + 10)
    sy = fy * fy * fy * (fy * (fy * 6 - 15) + 10)
    flat = table.ravel()
    a, b = flat[xi + yi], flat[xj + yi]
    c, d = flat[xi + yj], flat[xj + yj]
    ab = a + (b - a) * sx
    cd = c + (d - c) * sx
    return ab + (cd - ab) * sy


def _surface_texture(tex: Texture, s: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Colour (3, M) in [0.05, 0.95] of surface ``s`` at texture coordinates u, v (metres).

    Evaluated in float32 from float64 coordinates, channel by channel (no BLAS: its
    threads only contend on a shared CPU).
    """
    f32 = np.float32
    fields = []  # scalar fields, each (M,) in about [-1, 1], mixed into RGB below
    u32, v32 = u.astype(f32), v.astype(f32)
    for k in range(_N_SINES):
        kx, ky = tex.sin_k[s, k].astype(f32)
        fields.append(np.sin(u32 * kx + v32 * ky + f32(tex.sin_phase[s, k])))
    for o in range(2):
        inv_cell = f32(1.0 / tex.noise_cell[s, o])
        ox, oy = (f32(x) for x in tex.noise_off[s, o])
        fields.append(_value_noise(tex.table, u32 * inv_cell + ox, v32 * inv_cell + oy) - f32(0.5))
    kind = _ALL_PATTERNS[int(tex.pattern[s])]
    sc = tex.pattern_scale[s]
    us, vs = u32 * f32(1.0 / sc), v32 * f32(1.0 / sc)
    if kind == "checker":
        pat = np.tanh(f32(3.0) * np.sin(f32(np.pi) * us) * np.sin(f32(np.pi) * vs))
    elif kind == "planks":
        row = np.floor(vs)
        # staggered plank joints every 6 widths, random tint per plank, soft grooves between rows
        col = np.floor(us / f32(6) + f32(0.5) * (row % 2))
        idx = ((row.astype(np.int64) + tex.pattern_off[s, 0]) % _NOISE_TABLE) * _NOISE_TABLE
        idx += (col.astype(np.int64) + tex.pattern_off[s, 1]) % _NOISE_TABLE
        tint = f32(2) * tex.table.ravel()[idx] - f32(1)
        dv = np.abs(vs - np.round(vs)) * f32(sc / 0.008)  # distance to the joint in 8 mm units
        pat = f32(0.7) * tint - f32(0.9) * np.exp(-dv * dv)
    elif kind == "stripes":  # bars one pattern scale wide, varying along e1 or e2 only
        w = us if tex.pattern_off[s, 0] % 2 else vs
        pat = np.tanh(f32(4.0) * np.sin(f32(np.pi) * w))
    elif kind == "blobs":
        n = _value_noise(tex.table, us + f32(tex.pattern_off[s, 0]), vs + f32(tex.pattern_off[s, 1]))
        pat = np.tanh(f32(10.0) * (n - f32(0.5)))
    else:  # tiles with soft grout lines
        du = np.abs(us - np.round(us)) * f32(sc / 0.01)
        dv = np.abs(vs - np.round(vs)) * f32(sc / 0.01)
        pat = f32(1) - f32(2) * np.exp(-np.minimum(du, dv) ** 2)
    fields.append(pat)
    amps = np.concatenate([tex.sin_amp[s], tex.noise_amp[s], tex.pattern_amp[s][None]]).astype(f32)
    out = np.empty((3, len(u)), f32)
    for c in range(3):
        acc = np.full(len(u), f32(tex.base[s, c] - 0.5), f32)
        for fld, amp in zip(fields, amps[:, c]):
            acc += fld * amp
        # smooth squashing into [0.05, 0.95] (monotone, keeps gradients)
        out[c] = f32(0.5) + f32(0.45) * np.tanh(acc * f32(1 / 0.45))
    return out


def _colour_columns(scene: Scene, cols: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """:func:`surface_colour` for points given as columns (3, M); returns (3, M) float32."""
    order = np.argsort(ids.astype(np.int16), kind="stable")  # radix sort
    sorted_ids = ids[order]
    pts = cols[:, order]
    cuts = np.flatnonzero(np.diff(sorted_ids)) + 1
    out = np.empty((3, len(ids)), np.float32)
    for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(ids)]])):
        s = int(sorted_ids[a])
        u, v = scene.rects[s].uv(pts[:, a:b])
        out[:, order[a:b]] = _surface_texture(scene.texture, s, u, v)
    return out


def surface_colour(scene: Scene, points: np.ndarray, surface_ids: np.ndarray) -> np.ndarray:
    """RGB in [0.05, 0.95] (float32, (M, 3)) of world ``points`` (M, 3) on surfaces ``surface_ids`` (M,)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    ids = np.asarray(surface_ids).reshape(-1).astype(np.int64)
    if len(ids) != len(points):
        raise ValueError(f"surface_colour: {len(points)} points but {len(ids)} surface ids")
    if len(ids) and (ids.min() < 0 or ids.max() >= scene.n_surfaces):
        raise ValueError(f"surface_colour: surface ids must be in [0, {scene.n_surfaces}), "
                         f"got range [{ids.min()}, {ids.max()}]")
    return _colour_columns(scene, np.ascontiguousarray(points.T), ids).T


# ------------------------------------------------------------------------ rendering
def _cast(scene: Scene, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cast_rays` on component arrays ``d`` (3, M) (row layout keeps numpy fast)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        # room: the ray leaves through the nearest of the three planes it heads for
        tx, ty, tz = (np.where(d[k] > 0, scene.room_max[k] - o[k], scene.room_min[k] - o[k]) * inv[k]
                      for k in range(3))
        t = np.minimum(np.minimum(tx, ty), tz)
        sid = np.where(t == tx, np.where(d[0] > 0, 3, 2),
                       np.where(t == ty, np.where(d[1] > 0, 5, 4), np.where(d[2] > 0, 1, 0)))
        for b, box in enumerate(scene.boxes):
            rot = box.rotation  # a yaw: the local z axis is the world z axis
            ol = (o - box.center) @ rot
            dls = (rot[0, 0] * d[0] + rot[1, 0] * d[1], rot[0, 1] * d[0] + rot[1, 1] * d[1], d[2])
            near, far = None, None
            lows = []
            for k in range(3):
                ik = 1.0 / dls[k]
                ta = (-box.half[k] - ol[k]) * ik
                tb = (box.half[k] - ol[k]) * ik
                lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
                lows.append(lo)
                near = lo if near is None else np.maximum(near, lo)
                far = hi if far is None else np.minimum(far, hi)
            hit = np.flatnonzero((near <= far) & (near > 0) & (near < t))
            if not len(hit):
                continue
            tn = near[hit]
            ax = np.where(tn == lows[0][hit], 0, np.where(tn == lows[1][hit], 1, 2))
            dl_ax = np.where(ax == 0, dls[0][hit], np.where(ax == 1, dls[1][hit], dls[2][hit]))
            t[hit] = tn
            sid[hit] = 6 + 6 * b + 2 * ax + (dl_ax < 0)
    return t, sid


def cast_rays(scene: Scene, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays ``origin + t * dirs`` (M, 3) (origin inside the room, outside all boxes).

    Returns ``t`` (M,) in units of ``dirs`` and the surface id (M,) of the hit.
    """
    o = np.asarray(origin, np.float64).reshape(3)
    d = np.ascontiguousarray(np.asarray(dirs, np.float64).reshape(-1, 3).T)
    return _cast(scene, o, d)


def _camera_dirs(camera: PinholeCamera, c2w: np.ndarray, du: float = 0.0, dv: float = 0.0) -> np.ndarray:
    """World directions (3, H*W) of pixel centres shifted by (du, dv), z-normalised in the camera."""
    x = (np.arange(camera.width) + du - camera.cx) / camera.fx
    y = (np.arange(camera.height) + dv - camera.cy) / camera.fy
    xs = np.broadcast_to(x[None, :], (camera.height, camera.width)).ravel()
    ys = np.broadcast_to(y[:, None], (camera.height, camera.width)).ravel()
    r = c2w[:3, :3]
    return r[:, :1] * xs + r[:, 1:2] * ys + r[:, 2:3]


def _interior_pixels(sid: np.ndarray) -> np.ndarray:
    """(H, W) mask of pixels whose 8 neighbours see the same surface (False on the image border)."""
    h, w = sid.shape
    pad = np.pad(sid, 1, mode="constant", constant_values=-1)
    same = np.ones((h, w), bool)
    for dy in range(3):
        for dx in range(3):
            same &= pad[dy:dy + h, dx:dx + w] == sid
    return same


def _segments(ids: np.ndarray):
    """Yield (id, positions) for each distinct value of a small non-negative int array."""
    order = np.argsort(ids.astype(np.int16), kind="stable")  # radix sort
    sorted_ids = ids[order]
    cuts = np.flatnonzero(np.diff(sorted_ids)) + 1
    for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(ids)]])):
        yield int(sorted_ids[a]), order[a:b]


def _plane_colours(scene: Scene, camera: PinholeCamera, c2w: np.ndarray, s: int, pix: np.ndarray,
                   offsets: np.ndarray) -> np.ndarray:
    """Mean colour (3, K) over sub-pixel ``offsets`` (J, 2) of pixels ``pix`` (K,) known to see surface ``s``.

    The texture coordinates on a plane are ratios of affine functions of the pixel
    coordinates (a homography), so no 3-D points are formed.
    """
    rect = scene.rects[s]
    r, o = c2w[:3, :3], c2w[:3, 3]
    a = rect.e1 / np.linalg.norm(rect.e1)
    b = rect.e2 / np.linalg.norm(rect.e2)
    nrm = rect.normal
    ra, rb, rn = r.T @ a, r.T @ b, r.T @ nrm  # the surface axes in camera coordinates
    num = float(nrm @ (rect.origin - o))  # ray parameter t = num / (n . d)
    u0, v0 = float(a @ (o - rect.origin)), float(b @ (o - rect.origin))
    px = (pix % camera.width).astype(np.float64)
    py = (pix // camera.width).astype(np.float64)
    x = ((px[None, :] + offsets[:, :1]) - camera.cx) / camera.fx
    y = ((py[None, :] + offsets[:, 1:]) - camera.cy) / camera.fy
    t = num / (rn[0] * x + rn[1] * y + rn[2])
    u = u0 + t * (ra[0] * x + ra[1] * y + ra[2])
    v = v0 + t * (rb[0] * x + rb[1] * y + rb[2])
    col = _surface_texture(scene.texture, s, u.ravel(), v.ravel())
    return col.reshape(3, len(offsets), len(pix)).mean(1)


def render_view(scene: Scene, camera: PinholeCamera, c2w, supersample: int = 2, return_ids: bool = False):
    """Exact RGB (H, W, 3) uint8 and z-depth (H, W) float32 metres of ``scene`` seen from ``c2w``.

    Colour averages ``supersample x supersample`` sub-pixel rays (1 = the centre ray only);
    depth and (with ``return_ids``) the surface id map (H, W) come from the centre ray.
    Sub-pixel rays of pixels whose 8 neighbours all see one surface are intersected with
    that surface's plane directly (exact: every feature is far wider than a pixel); the
    others are cast against the whole scene.
    """
    if camera.dist is not None:
        raise ValueError("render_view renders an ideal pinhole camera; camera.dist must be None")
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    c2w = np.asarray(c2w, np.float64).reshape(4, 4)
    o = c2w[:3, 3]
    h, w = camera.height, camera.width
    d = _camera_dirs(camera, c2w)
    t, sid = _cast(scene, o, d)
    depth = t.reshape(h, w).astype(np.float32)
    n = int(supersample)
    if n == 1:
        col = _colour_columns(scene, o[:, None] + t * d, sid)
    else:
        interior = _interior_pixels(sid.reshape(h, w)).ravel()
        inner, edge = np.flatnonzero(interior), np.flatnonzero(~interior)
        offs1 = (np.arange(n) + 0.5) / n - 0.5
        offsets = np.stack(np.meshgrid(offs1, offs1, indexing="xy"), -1).reshape(-1, 2)  # rows (du, dv)
        col = np.empty((3, h * w), np.float32)
        for s, pos in _segments(sid[inner]):
            pix = inner[pos]
            col[:, pix] = _plane_colours(scene, camera, c2w, s, pix, offsets)
        if len(edge):
            pts, ids = [], []
            for du, dv in offsets:
                ds = _camera_dirs(camera, c2w, du, dv)[:, edge]
                ts, ss = _cast(scene, o, ds)
                pts.append(o[:, None] + ts * ds)
                ids.append(ss)
            ce = _colour_columns(scene, np.concatenate(pts, 1), np.concatenate(ids))
            col[:, edge] = ce.reshape(3, len(offsets), len(edge)).mean(1)
    rgb = np.round(np.clip(col.T, 0, 1) * 255).astype(np.uint8).reshape(h, w, 3)
    if return_ids:
        return rgb, depth, sid.reshape(h, w)
    return rgb, depth


# ----------------------------------------------------------------------- trajectory
def _look_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations (..., 3, 3): OpenCV axes, forward at (yaw, pitch) in the z-up world."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    fwd = np.stack([cp * cy, cp * sy, sp], -1)
    right0 = np.stack([sy, -cy, np.zeros_like(cy)], -1)
    down0 = np.cross(fwd, right0)
    cr, sr = np.cos(roll)[..., None], np.sin(roll)[..., None]
    right = cr * right0 + sr * down0
    down = -sr * right0 + cr * down0
    return np.stack([right, down, fwd], -1)


def _angle_between(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad) between rotation stacks, accurate for small angles."""
    fro = np.linalg.norm((ra - rb).reshape(*ra.shape[:-2], 9), axis=-1)
    return 2.0 * np.arcsin(np.clip(fro / (2.0 * math.sqrt(2.0)), 0.0, 1.0))


def trajectory_steps(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) between consecutive poses (N-1,) each."""
    c2w = np.asarray(c2w, np.float64)
    trans = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)
    rot = np.degrees(_angle_between(c2w[:-1, :3, :3], c2w[1:, :3, :3]))
    return trans, rot


def _loop_poses(path: LoopPath, theta: np.ndarray, look: dict) -> np.ndarray:
    a = path.direction * theta
    yaw = a + path.direction * (look["yaw_offset"] + look["yaw_amp"] * np.sin(2 * theta + look["yaw_phase"]))
    pitch = look["pitch"] + look["pitch_amp"] * np.sin(3 * theta + look["pitch_phase"])
    roll = look["roll_amp"] * np.sin(theta + look["roll_phase"])
    out = np.zeros(theta.shape + (4, 4))
    out[..., :3, :3] = _look_rotation(yaw, pitch, roll)
    out[..., :3, 3] = path.positions(theta)
    out[..., 3, 3] = 1.0
    return out


def camera_clearance(scene: Scene, positions: np.ndarray) -> np.ndarray:
    """Distance (M,) of points to the nearest room plane or furniture box."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    d = np.minimum((p - scene.room_min).min(1), (scene.room_max - p).min(1))
    for box in scene.boxes:
        q = np.abs(box.to_local(p)) - box.half
        outside = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
        d = np.minimum(d, outside)
    return d


def make_trajectory(scene: Scene, frames: int, seed: int = 0) -> np.ndarray:
    """Smooth camera-to-world poses (N, 4, 4) along the scene's loop.

    ``seed`` sets the start point on the loop and the look-direction modulation; the
    loop itself belongs to the scene (furniture keeps clear of it). Frames are spaced
    by equal *effort* ``max(dt / 0.95*3cm, dR / 0.95*2deg)``: when N frames suffice the
    loop is closed and traversed once, otherwise the first ``N - 1`` effort units are used.
    Raises AssertionError if a step or the camera clearance breaks the limits.
    """
    frames = int(frames)
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rng = np.random.default_rng([int(seed), 7002])
    ranges = _DEFAULT_RANGES if scene.style is None else _WIDE_RANGES
    look = {
        "yaw_offset": float(rng.uniform(*ranges.look_yaw)),  # 0 = facing outwards, pi/2 = along the loop
        "yaw_amp": float(rng.uniform(0.05, 0.12)),
        "yaw_phase": float(rng.uniform(0, 2 * np.pi)),
        "pitch": float(rng.uniform(*ranges.pitch)),
        "pitch_amp": 0.06,
        "pitch_phase": float(rng.uniform(0, 2 * np.pi)),
        "roll_amp": 0.03,
        "roll_phase": float(rng.uniform(0, 2 * np.pi)),
    }
    theta0 = float(rng.uniform(0, 2 * np.pi))
    m = 20000
    grid = theta0 + np.linspace(0.0, 2 * np.pi, m + 1)
    dense = _loop_poses(scene.path, grid, look)
    dt, dr = trajectory_steps(dense)
    effort = np.maximum(dt / (STEP_FILL * MAX_STEP_M), dr / (STEP_FILL * MAX_STEP_DEG))
    cum = np.concatenate([[0.0], np.cumsum(effort)])
    total = cum[-1]
    targets = np.arange(frames) * (total / frames if frames >= total else 1.0)
    theta = np.interp(targets, cum, grid)
    c2w = _loop_poses(scene.path, theta, look)
    if frames > 1:
        st, sr = trajectory_steps(c2w)
        if st.max() > MAX_STEP_M or sr.max() > MAX_STEP_DEG:
            raise AssertionError(f"trajectory step {st.max():.4f} m / {sr.max():.3f} deg exceeds "
                                 f"{MAX_STEP_M} m / {MAX_STEP_DEG} deg")
    clear = camera_clearance(scene, c2w[:, :3, 3])
    if clear.min() < CLEARANCE_M:
        raise AssertionError(f"camera comes {clear.min():.3f} m close to a surface (< {CLEARANCE_M} m)")
    return c2w


# ---------------------------------------------------------------- ground truth geometry
def _inside_footprints(scene: Scene, pts: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(pts), bool)
    for box in scene.boxes:
        q = np.abs(box.to_local(pts)[:, :2]) - box.half[:2]
        inside |= (q < 0).all(1)
    return inside


def gt_mesh(scene: Scene, spacing: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of every exposed surface: vertices (V, 3), faces (F, 3), vertex colours (V, 3) float.

    Each rectangle is a regular grid of about ``spacing`` metres; faces wind counter-clockwise
    around the outward normal. The floor is kept whole (under furniture too).
    """
    verts, faces, cols = [], [], []
    nv = 0
    for r in scene.rects:
        if not r.exposed:
            continue
        na = max(1, int(math.ceil(np.linalg.norm(r.e1) / spacing)))
        nb = max(1, int(math.ceil(np.linalg.norm(r.e2) / spacing)))
        a, b = np.meshgrid(np.linspace(0, 1, na + 1), np.linspace(0, 1, nb + 1), indexing="ij")
        p = r.origin + a.reshape(-1, 1) * r.e1 + b.reshape(-1, 1) * r.e2
        idx = np.arange((na + 1) * (nb + 1)).reshape(na + 1, nb + 1) + nv
        i00, i10, i11, i01 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        tri = np.concatenate([np.stack([i00, i10, i11], -1).reshape(-1, 3),
                              np.stack([i00, i11, i01], -1).reshape(-1, 3)])
        verts.append(p)
        faces.append(tri)
        cols.append(surface_colour(scene, p, np.full(len(p), r.sid)))
        nv += len(p)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(cols)


def gt_cloud(scene: Scene, density: float = 1e4, max_points: int = 500_000, seed: int = 0):
    """Points sampled uniformly by area on every exposed surface (floor under furniture excluded).

    ``density`` is points per m^2 (1e4 = 1 / cm^2), reduced to respect ``max_points``.
    Returns points (M, 3), surface ids (M,) and colours (M, 3) float.
    """
    rng = np.random.default_rng([int(seed), 7003])
    rects = [r for r in scene.rects if r.exposed]
    area = np.array([r.area for r in rects])
    dens = min(float(density), max_points / area.sum())
    pts, ids = [], []
    for r, ar in zip(rects, area):
        k = int(math.floor(ar * dens))
        ab = rng.random((k, 2))
        p = r.origin + ab[:, :1] * r.e1 + ab[:, 1:] * r.e2
        if r.sid == 0:
            p = p[~_inside_footprints(scene, p)]
        pts.append(p)
        ids.append(np.full(len(p), r.sid, np.int64))
    pts, ids = np.concatenate(pts), np.concatenate(ids)
    return pts, ids, surface_colour(scene, pts, ids)


def _visible_columns(camera: PinholeCamera, c2w: np.ndarray, depth: np.ndarray, cols: np.ndarray,
                     tol: float) -> np.ndarray:
    r, t = c2w[:3, :3].tolist(), c2w[:3, 3].tolist()  # python floats keep float32 columns float32
    q = [cols[k] - t[k] for k in range(3)]
    x, y, z = (q[0] * r[0][j] + q[1] * r[1][j] + q[2] * r[2][j] for j in range(3))
    ok = z > 1e-3
    zs = np.where(ok, z, 1)
    u = np.round(x / zs * camera.fx + camera.cx)
    v = np.round(y / zs * camera.fy + camera.cy)
    ok &= (u >= 0) & (u <= camera.width - 1) & (v >= 0) & (v <= camera.height - 1)
    idx = np.where(ok, v * camera.width + u, 0).astype(np.int64)
    dz = depth.ravel()[idx]
    return ok & (dz > 0) & (np.abs(z - dz) < tol)


def visible_mask(camera: PinholeCamera, c2w: np.ndarray, depth: np.ndarray, pts: np.ndarray,
                 tol: float = VISIBLE_TOL_M) -> np.ndarray:
    """Which world points (M, 3) a frame sees: inside the image and within ``tol`` of its depth
    map at the nearest pixel."""
    cols = np.ascontiguousarray(np.asarray(pts, np.float64).reshape(-1, 3).T)
    return _visible_columns(camera, np.asarray(c2w, np.float64), np.asarray(depth), cols, tol)


# --------------------------------------------------------------------- camera effects
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
