"""Coarse-to-fine steps on factor lines (an optimiser detail; the field keeps its own parameters).

A line ``l`` (R nodes over [-1, 1]) is optimised as ``l + U c``, where ``c`` holds ``Rc`` coarse nodes and
``U`` (R, Rc) interpolates them linearly onto the line's nodes. The loss's gradient with respect to ``c`` is
``g U``; after each Adam step ``U c`` is folded into the line and ``c`` is set back to zero (its Adam moments
stay), which leaves the optimisation exactly that of the reparameterised line while every other reader of the
field (export, snapshots, box refits) sees plain lines.
"""
from __future__ import annotations

import torch
from torch import Tensor


def interp_matrix(r: int, rc: int, dtype=torch.float32, device=None) -> Tensor:
    """(r, rc): row i holds the linear-interpolation weights of the coarse nodes at fine node i (both grids span
    [-1, 1] end to end, align_corners)."""
    x = torch.linspace(0.0, rc - 1.0, r, dtype=torch.float64)
    i0 = x.floor().clamp(max=rc - 2).long()
    w = x - i0
    u = torch.zeros(r, rc, dtype=torch.float64)
    u[torch.arange(r), i0] = 1.0 - w
    u[torch.arange(r), i0 + 1] += w
    return u.to(dtype=dtype, device=device)


def is_line(p: Tensor) -> bool:
    """A (3, C, R, 1) factor-line parameter."""
    return p.dim() == 4 and p.shape[0] == 3 and p.shape[-1] == 1 and p.shape[2] > 2


class CoarseLines:
    """The coarse companions of a field's line parameters."""

    def __init__(self, lines: list[Tensor], nodes: int) -> None:
        self.pairs = []
        for p in lines:
            u = interp_matrix(p.shape[2], nodes, p.dtype, p.device)
            c = torch.zeros(p.shape[0], p.shape[1], nodes, 1, dtype=p.dtype, device=p.device, requires_grad=True)
            self.pairs.append((p, c, u))

    def params(self) -> list[Tensor]:
        return [c for _, c, _ in self.pairs]

    def set_grads(self) -> None:
        """The coarse gradients from the lines' (call after ``backward``)."""
        for p, c, u in self.pairs:
            c.grad = None if p.grad is None else (p.grad[..., 0] @ u).unsqueeze(-1)

    @torch.no_grad()
    def fold(self) -> None:
        """Fold the coarse steps into the lines and zero them (call after the optimiser's step)."""
        for p, c, u in self.pairs:
            p.add_((c[..., 0] @ u.t()).unsqueeze(-1))
            c.zero_()
