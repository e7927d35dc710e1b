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


def field_from_snapshot(cfg: FieldConfig, arrays: dict, device=None) -> Field:
    """Rebuild a field from :meth:`Field.snapshot` arrays (``cfg`` must match the snapshot)."""
    return Field.from_snapshot(cfg, arrays, device=device)


__all__ = [
    "EMPTY_RAW", "Field", "FieldConfig", "as_aabb", "CPField", "VMField", "MLPField", "GridField",
    "FIELD_KINDS", "build_field", "field_from_snapshot",
]
