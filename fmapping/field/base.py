"""Neural field interface shared by the factorized fields and the baselines.

Conventions (stated once for all of :mod:`fmapping.field`):

* Points are world coordinates in metres, shape ``(N, 3)``. Every field owns an
  axis-aligned box ``aabb`` (a ``(2, 3)`` buffer: row 0 = min, row 1 = max).
  Inside the box, points are mapped to normalised coordinates ``u in [-1, 1]^3``
  (``-1`` = min corner, ``+1`` = max corner). Grid-based fields put their
  ``R`` nodes per axis exactly on ``[-1, 1]`` (``grid_sample`` with
  ``align_corners=True``), so a line factor of length ``R`` covers the box with
  ``R - 1`` intervals of size ``extent / (R - 1)``.
* ``density_raw`` is the *pre-activation* value: the renderer turns it into
  opacity with ``softplus(raw + density_shift)`` (density mode) or
  ``sigmoid(raw + density_shift)`` (occupancy mode), see :func:`fmapping.render.raw_to_alpha`.
  Points outside the box return :data:`EMPTY_RAW` (no NaN, no index error, no gradient).
* ``color`` returns RGB in ``[0, 1]`` (sigmoid output).
* The field computes in the dtype of its parameters (float32 by default; call
  ``.double()`` for float64, e.g. for gradcheck) and on the device of ``aabb``;
  inputs are cast to that dtype.
* Parameter groups: ``grid_parameters()`` (the spatial factors, lr 0.02 in the
  mapper) and ``decoder_parameters()`` (appearance basis + colour MLP, lr 0.001,
  frozen after the init stage). The two lists partition ``parameters()``.
  ``grid_param_groups()`` splits the grid parameters into ``(params, lr multiplier)``
  pairs; cp and mlp keep one group with multiplier 1, the dense grid raises the
  learning rate of its density (see :mod:`.grid`), VM that of its planes (see :mod:`.vm`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor, nn

#: Pre-activation returned for points outside the box. ``softplus(EMPTY_RAW - 10)``
#: underflows to 0 and ``sigmoid(EMPTY_RAW - 10)`` is < 1e-47: empty space.
EMPTY_RAW: float = -100.0


@dataclass
class FieldConfig:
    """Configuration for every field kind (unused keys are ignored by the other kinds)."""

    kind: str = "cp"               # cp | vm | mlp | grid
    resolution: int = 128          # nodes per axis of the factor lines / planes (cp, vm)
    density_components: int = 16   # CP density rank
    appearance_components: int = 24  # CP appearance rank
    app_features: int = 27         # width of the linear appearance basis fed to the MLP
    hidden: int = 48               # colour MLP hidden width (2 layers: in -> hidden -> 3)
    alpha_mode: str = "density"    # "density": alpha = 1-exp(-softplus(raw+shift)*delta);
    #                                "occupancy": alpha = sigmoid(raw+shift) (UNISURF)
    density_shift: float = -10.0   # start clear: softplus(0-10) ~ 4.5e-5
    init_scale: float = 0.1        # std of factor init
    # cp / vm: the share of light a ray crossing the box's mean side absorbs at the start (a uniform fog of density
    # -ln(1 - init_opacity) / side; in occupancy mode the opacity of one cell of that fog per sample). 0: clear, as
    # TensoRF starts (softplus(0 - 10) ~ 4.5e-5 /m). From clear, the density needs ~40 Adam steps at lr 0.02 to
    # appear at all (an init of 4 x 25 iterations left an empty map); from the fog the photometric, warping and
    # photo-consistency losses carve the surfaces from the first step (bench/init_speed.py)
    init_opacity: float = 0.95
    view_dependent: bool = False   # feed view directions (with PE) to the colour MLP
    view_pe_freqs: int = 2         # PE frequencies of the view direction when view_dependent
    mlp_layers: int = 4            # iMAP-like baseline: hidden layers
    mlp_width: int = 256           # iMAP-like baseline: hidden width (4 x 256: ~0.21 M params, as iMAP)
    pe_freqs: int = 6              # iMAP-like baseline: PE frequencies of the position
    grid_features: int = 8         # dense grid baseline: feature channels besides density
    grid_resolution: int = 64      # dense grid baseline: nodes per axis (R^3 memory, so lower than `resolution`)
    grid_init_density: float = 3e-3  # dense grid baseline: initial density (1/m) after the shift (5 m absorb 1.5 %)
    grid_density_lr_scale: float = 30.0  # dense grid baseline: lr multiplier of the density grid (see field/grid.py)
    vm_density_components: int = 4     # VM: density components per plane/line pair (x3 axes)
    vm_appearance_components: int = 8  # VM: appearance components per plane/line pair (x3 axes)
    vm_plane_lr_scale: float = 10.0    # VM: lr multiplier of the planes (1: one group, as TensoRF; see field/vm.py)
    seed: int = 0                  # parameter initialisation seed (a local generator, no global RNG)

    def validate(self) -> "FieldConfig":
        kinds = ("cp", "vm", "mlp", "grid")
        if self.kind not in kinds:
            raise ValueError(f"field.kind must be one of {kinds}, got {self.kind!r}")
        if self.alpha_mode not in ("density", "occupancy"):
            raise ValueError(f"field.alpha_mode must be 'density' or 'occupancy', got {self.alpha_mode!r}")
        for name in ("resolution", "grid_resolution"):
            if getattr(self, name) < 2:
                raise ValueError(f"field.{name} must be >= 2, got {getattr(self, name)}")
        for name in ("density_components", "appearance_components", "app_features", "hidden",
                     "mlp_layers", "mlp_width", "grid_features", "vm_density_components",
                     "vm_appearance_components"):
            if getattr(self, name) < 1:
                raise ValueError(f"field.{name} must be >= 1, got {getattr(self, name)}")
        if self.pe_freqs < 0 or self.view_pe_freqs < 0:
            raise ValueError("field.pe_freqs and field.view_pe_freqs must be >= 0")
        if not self.init_scale > 0:
            raise ValueError(f"field.init_scale must be > 0, got {self.init_scale}")
        if not 0 <= self.init_opacity < 1:
            raise ValueError(f"field.init_opacity must be in [0, 1), got {self.init_opacity}")
        if not self.grid_init_density > 0:
            raise ValueError(f"field.grid_init_density must be > 0, got {self.grid_init_density}")
        if not self.vm_plane_lr_scale > 0:
            raise ValueError(f"field.vm_plane_lr_scale must be > 0, got {self.vm_plane_lr_scale}")
        if not self.grid_density_lr_scale > 0:
            raise ValueError(f"field.grid_density_lr_scale must be > 0, got {self.grid_density_lr_scale}")
        return self


def as_aabb(aabb, device=None, dtype=torch.float32) -> Tensor:
    """Validate and convert an AABB given as (2, 3) array/tensor or (min, max) pair."""
    t = torch.as_tensor(np.asarray(aabb.detach().cpu() if isinstance(aabb, Tensor) else aabb, dtype=np.float64))
    if t.shape != (2, 3):
        raise ValueError(f"aabb must have shape (2, 3) [min; max], got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"aabb must be finite, got {t.tolist()}")
    if not (t[1] > t[0]).all():
        raise ValueError(f"aabb max must exceed min on every axis, got min={t[0].tolist()} max={t[1].tolist()}")
    if device is None and isinstance(aabb, Tensor):
        device = aabb.device
    return t.to(device=device, dtype=dtype)


def start_raw(cfg: FieldConfig, aabb: Tensor) -> float:
    """The pre-activation of a uniform start of ``cfg.init_opacity`` across the box's mean side (see
    :class:`FieldConfig`); ``-inf`` for a clear start (``init_opacity`` 0)."""
    if cfg.init_opacity <= 0:
        return float("-inf")
    side = float((aabb[1] - aabb[0]).double().mean())
    sigma = -math.log1p(-cfg.init_opacity) / side
    if cfg.alpha_mode == "occupancy":
        alpha = -math.expm1(-sigma * side / max(cfg.resolution - 1, 1))
        return math.log(alpha / (1.0 - alpha)) - cfg.density_shift
    return math.log(math.expm1(sigma)) - cfg.density_shift


def tv_1d(x: Tensor) -> Tensor:
    """Mean squared difference along the last axis."""
    return (x[..., 1:] - x[..., :-1]).pow(2).mean()


class Field(nn.Module):
    """Abstract neural field; see the module docstring for conventions."""

    aabb: Tensor

    def __init__(self, cfg: FieldConfig, aabb) -> None:
        super().__init__()
        self.cfg = cfg.validate()
        self.register_buffer("aabb", as_aabb(aabb))

    # ------------------------------------------------------------ helpers
    @property
    def device(self) -> torch.device:
        return self.aabb.device

    @property
    def dtype(self) -> torch.dtype:
        return self.aabb.dtype

    def normalize(self, xyz: Tensor) -> Tensor:
        """World (N, 3) -> normalised box coordinates in [-1, 1] (outside points exceed it)."""
        xyz = xyz.to(self.dtype)
        lo, hi = self.aabb[0], self.aabb[1]
        return (xyz - lo) * (2.0 / (hi - lo)) - 1.0

    def normalize_clamped(self, xyz: Tensor) -> tuple[Tensor, Tensor]:
        """``(u, u.clamp(-1, 1))``: true normalised coordinates (for the inside test) and the
        clamped ones used for lookups (finite even for huge or infinite inputs)."""
        u = self.normalize(xyz)
        return u, u.clamp(-1.0, 1.0)

    def contains(self, xyz: Tensor) -> Tensor:
        """(N,) bool: point inside the (closed) box."""
        u = self.normalize(xyz)
        return (u.abs() <= 1.0).all(-1)

    @staticmethod
    def _check_points(xyz: Tensor) -> None:
        if xyz.dim() != 2 or xyz.shape[-1] != 3:
            raise ValueError(f"expected points of shape (N, 3), got {tuple(xyz.shape)}")

    def _mask_outside(self, raw: Tensor, u: Tensor) -> Tensor:
        inside = (u.abs() <= 1.0).all(-1)
        return torch.where(inside, raw, torch.full_like(raw, EMPTY_RAW))

    # ------------------------------------------------------------ interface
    def forward(self, xyz: Tensor, viewdirs: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        """``(density_raw(xyz), color(xyz, viewdirs))`` (mostly for tests / functional_call)."""
        return self.density_raw(xyz), self.color(xyz, viewdirs)

    def density_raw(self, xyz: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def color(self, xyz: Tensor, viewdirs: Optional[Tensor] = None) -> Tensor:  # pragma: no cover
        raise NotImplementedError

    def grid_parameters(self) -> list[nn.Parameter]:  # pragma: no cover
        raise NotImplementedError

    def decoder_parameters(self) -> list[nn.Parameter]:  # pragma: no cover
        raise NotImplementedError

    def grid_param_groups(self) -> list[tuple[list[nn.Parameter], float]]:
        """``(parameters, lr multiplier)`` pairs that partition :meth:`grid_parameters`
        (default: one group, multiplier 1)."""
        return [(list(self.grid_parameters()), 1.0)]

    def regularizer(self, kind: str = "tv") -> Tensor:  # pragma: no cover
        raise NotImplementedError

    def refit_box(self, aabb) -> None:
        """Move the field onto a new box keeping its content (cp and vm; the other kinds raise NotImplementedError)."""
        raise NotImplementedError(f"a {self.cfg.kind!r} field cannot change its box")

    def flops_per_point(self) -> int:  # pragma: no cover
        raise NotImplementedError

    def num_parameters(self) -> int:
        return int(sum(p.numel() for p in self.parameters()))

    def describe(self) -> str:
        """One line: kind, parameter counts (total / grid / decoder) and FLOPs per point."""
        n_grid = sum(p.numel() for p in self.grid_parameters())
        n_dec = sum(p.numel() for p in self.decoder_parameters())
        return (f"{self.cfg.kind} field: {self.num_parameters() / 1e6:.4f} M parameters "
                f"(grid {n_grid}, decoder {n_dec}), {self.flops_per_point()} FLOPs/point, "
                f"aabb min {self.aabb[0].tolist()} max {self.aabb[1].tolist()}")

    def _check_reg_kind(self, kind: str) -> None:
        if kind not in ("tv", "l1"):
            raise ValueError(f"regularizer kind must be 'tv' or 'l1', got {kind!r}")

    def _zero(self) -> Tensor:
        return torch.zeros((), dtype=self.dtype, device=self.device)

    # ------------------------------------------------------------ transport
    def snapshot(self) -> dict[str, np.ndarray]:
        """All tensors (parameters and the ``aabb`` buffer) as float32 numpy arrays."""
        return {k: v.detach().to("cpu", torch.float32).numpy().copy() for k, v in self.state_dict().items()}

    @classmethod
    def from_snapshot(cls, cfg: FieldConfig, arrays: dict, device=None) -> "Field":
        """Rebuild a field of kind ``cfg.kind`` from :meth:`snapshot` arrays."""
        if "aabb" not in arrays:
            raise ValueError("field snapshot has no 'aabb' entry")
        if cls is Field:
            from . import build_field

            field = build_field(cfg, as_aabb(arrays["aabb"], device=device))
        else:
            field = cls(cfg, as_aabb(arrays["aabb"], device=device))
        field.load_arrays(arrays)
        return field

    def load_arrays(self, arrays: dict) -> None:
        """Copy snapshot arrays into this field, with clear errors on missing/extra/misshaped keys."""
        own = self.state_dict()
        missing = sorted(set(own) - set(arrays))
        extra = sorted(set(arrays) - set(own))
        if missing or extra:
            raise ValueError(
                f"field snapshot does not match a {self.cfg.kind!r} field: missing {missing}, unexpected {extra}"
            )
        new = {}
        for k, v in own.items():
            a = torch.as_tensor(np.asarray(arrays[k]))
            if tuple(a.shape) != tuple(v.shape):
                raise ValueError(
                    f"field snapshot entry {k!r} has shape {tuple(a.shape)}, expected {tuple(v.shape)} "
                    f"(check resolution / component counts in the field config)"
                )
            if not torch.isfinite(a).all():
                raise ValueError(f"field snapshot entry {k!r} contains non-finite values")
            new[k] = a.to(device=v.device, dtype=v.dtype)
        self.load_state_dict(new)


def randn_param(shape: Sequence[int], scale: float, device, generator: torch.Generator) -> nn.Parameter:
    """A float32 parameter with N(0, scale^2) entries on ``device`` (drawn on CPU for reproducibility)."""
    t = torch.randn(*shape, generator=generator) * scale
    return nn.Parameter(t.to(device))


def make_generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))
