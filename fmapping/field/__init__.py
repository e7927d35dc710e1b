"""Neural fields: CP (default) and VM factorizations; iMAP-like MLP and dense-grid baselines.

``build_field(cfg, aabb)`` dispatches on ``cfg.kind``; ``field_from_snapshot(cfg, arrays)``
rebuilds a field from :meth:`Field.snapshot` arrays. Conventions: :mod:`fmapping.field.base`.
"""
from __future__ import annotations

from .base import EMPTY_RAW, Field, FieldConfig, as_aabb
from .cp import CPField
from .grid import GridField
from .mlp import MLPField
from .vm import VMField

FIELD_KINDS: dict[str, type[Field]] = {"cp": CPField, "vm": VMField, "mlp": MLPField, "grid": GridField}


def build_field(cfg: FieldConfig, aabb) -> Field:
    """A new field of kind ``cfg.kind`` over ``aabb`` ((2, 3) min/max; its device is used)."""
    cfg.validate()
    return FIELD_KINDS[cfg.kind](cfg, aabb)


def min_field_elements(cfg: FieldConfig) -> int:
    """A lower bound on the number of parameters of the field ``cfg`` describes (the dominant
    tensors of each kind), computed without building it: a snapshot's arrays are checked
    against it before a forged config can make a reader allocate gigabytes."""
    kind = cfg.kind
    if kind == "cp":
        return 3 * (cfg.density_components + cfg.appearance_components) * cfg.resolution \
            + cfg.app_features * cfg.hidden
    if kind == "vm":
        return 3 * (cfg.vm_density_components + cfg.vm_appearance_components) * cfg.resolution * cfg.resolution \
            + cfg.app_features * cfg.hidden
    if kind == "grid":
        return (1 + cfg.grid_features) * cfg.grid_resolution ** 3 + cfg.grid_features * cfg.hidden
    if kind == "mlp":
        d_in = 3 * (1 + 2 * cfg.pe_freqs)
        return d_in * cfg.mlp_width + max(0, cfg.mlp_layers - 1) * cfg.mlp_width ** 2
    raise ValueError(f"unknown field kind {kind!r}")


def field_from_snapshot(cfg: FieldConfig, arrays: dict, device=None) -> Field:
    """Rebuild a field from :meth:`Field.snapshot` arrays (``cfg`` must match the snapshot)."""
    return Field.from_snapshot(cfg, arrays, device=device)


__all__ = [
    "EMPTY_RAW", "Field", "FieldConfig", "as_aabb", "CPField", "VMField", "MLPField", "GridField",
    "FIELD_KINDS", "build_field", "field_from_snapshot", "min_field_elements",
]
