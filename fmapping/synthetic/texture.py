"""Surface textures: the per-surface parameters drawn for a room (value noise, waves, patterns)
and the colour of a point on a surface, a pure function of (surface id, point)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from fmapping.synthetic.scene import Scene, Style

_NOISE_TABLE = 256  # value-noise lattice period (cells)
_N_SINES = 6
_LIGHT = np.array([0.35, -0.5, 0.8]) / np.linalg.norm([0.35, -0.5, 0.8])

PATTERNS = ("checker", "planks", "blobs", "tiles")
# PATTERNS plus those only the wide variety assigns; appended, so that the default's indices keep their meaning
_ALL_PATTERNS = PATTERNS + ("stripes",)


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
