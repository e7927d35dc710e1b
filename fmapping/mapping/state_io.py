"""Saving and restoring a mapper exactly (:class:`MapperStateIO`, mixed into
:class:`fmapping.mapping.Mapper`); tensors and plain python only, for ``weights_only`` loading."""
from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.fileio import plain_tree
from fmapping.mapping.window_schedule import WindowStats

STATE_VERSION = 1


class MapperStateIO:
    """:meth:`state_dict` / :meth:`load_state_dict` of :class:`fmapping.mapping.Mapper` (a mixin)."""

    def state_dict(self) -> dict:
        """Everything needed to resume exactly (tensors and plain python only)."""
        return {
            "version": STATE_VERSION,
            "config": plain_tree(dataclasses.asdict(self.cfg)),
            "camera": self.camera.to_dict(),
            "aabb": None if self.aabb is None else self.aabb.detach().cpu().clone(),
            "aabb_given": None if self._aabb_given is None else self._aabb_given.clone(),
            "field": None if self.field is None else {k: v.detach().cpu().clone()
                                                      for k, v in self.field.state_dict().items()},
            "optimizer": None if self._opt is None else pack_optimizer_state(_cpu_tree(self._opt.state_dict())),
            "pose_corr": None if self._pose_corr is None else self._pose_corr.detach().cpu().clone(),
            "images": self._images.state_dict(),
            "depths": {int(i): dp.clone() for i, dp in self._depths.items()},
            "poses": pack_by_frame({int(i): p.clone() for i, p in self._poses.items()}),
            "timestamps": {int(i): float(t) for i, t in self._timestamps.items()},
            "frame_numbers": {int(i): int(n) for i, n in self._frame_no.items()},
            "guessed": sorted(self._guessed),
            "next_id": self._next_id,
            "init_ids": list(self._init_ids),
            "pending": list(self._pending),
            "local": list(self._local),
            "keyframes": list(self._keyframes),
            "window": list(self._window),
            "initialized": self.initialized,
            "finished": self._finished,
            "iterations": self._iterations,
            "stats": [s.to_dict() for s in self._stats],
            "rng": self._gen.get_state().clone(),
            "exposure": pack_by_frame({int(i): p.detach().cpu().clone() for i, p in self._exposure.items()}),
            "pose_delta": pack_by_frame({int(i): p.detach().cpu().clone() for i, p in self._pose_delta.items()}),
            "sparse": None if self._sparse is None else self._sparse.state_dict(),
            "box_refits": self._box_refits,
            "box_provisional": self._box_provisional,
        }

    def load_state_dict(self, d: dict) -> None:
        """Restore a :meth:`state_dict` (the camera must match; the config of this mapper is kept)."""
        if not isinstance(d, dict) or d.get("version") != STATE_VERSION:
            raise ValueError(f"Mapper.load_state_dict: not a mapper state of version {STATE_VERSION}")
        cam = PinholeCamera.from_dict(d["camera"])
        if cam != self.camera:
            raise ValueError(f"Mapper.load_state_dict: camera differs ({cam} vs {self.camera})")
        self._aabb_given = None if d["aabb_given"] is None else d["aabb_given"].clone()
        self._images.load_state_dict(d["images"])
        self._depths = {int(i): dp.clone() for i, dp in d["depths"].items()}
        self._poses = {int(i): p.clone().to(torch.float64) for i, p in unpack_by_frame(d["poses"]).items()}
        self._timestamps = {int(i): float(t) for i, t in d["timestamps"].items()}
        self._frame_no = {int(i): int(n) for i, n in d.get("frame_numbers", {}).items()}
        self._guessed = set(d["guessed"])
        self._next_id = int(d["next_id"])
        self._init_ids = list(d["init_ids"])
        self._pending = list(d["pending"])
        self._local = list(d["local"])
        self._keyframes = list(d["keyframes"])
        self._window = list(d["window"])
        self.initialized = bool(d["initialized"])
        self._finished = bool(d["finished"])
        self._iterations = int(d["iterations"])
        self._stats = [WindowStats(**s) for s in d["stats"]]
        self._gen.set_state(d["rng"].clone())
        self._box_refits = int(d.get("box_refits", 0))
        self._box_provisional = bool(d.get("box_provisional", False))
        if self._sparse is not None and d.get("sparse") is not None:
            self._sparse.load_state_dict(d["sparse"])
        self._exposure = self._frame_params(unpack_by_frame(d.get("exposure", {})))
        self._pose_delta = self._frame_params(unpack_by_frame(d.get("pose_delta", {})))
        self.field, self._opt, self._pose_corr, self.aabb = None, None, None, None
        if d["field"] is not None:
            self._aabb_given, given = d["aabb"].clone(), self._aabb_given
            self._build()
            self._aabb_given = given
            self.field.load_state_dict(d["field"])
            if self._pose_corr is not None and d["pose_corr"] is not None:
                with torch.no_grad():
                    self._pose_corr.copy_(d["pose_corr"].to(self.device))
            if self.initialized:
                if self.cfg.freeze_decoder_after_init:
                    self._freeze_decoder()
                elif self._pose_corr is not None:
                    self._pose_corr.requires_grad_(False)
            try:
                self._opt.load_state_dict(unpack_optimizer_state(d["optimizer"]))
            except ValueError as e:  # torch: "loaded state dict has a different number of parameter groups"
                raise ValueError(f"Mapper.load_state_dict: the saved optimiser state does not fit this mapper's config "
                                 f"({e}): was it saved with other optimiser settings (coarse_nodes, refine_poses, "
                                 f"exposure)?") from None

    def _frame_params(self, saved: dict) -> dict:
        """Per-frame parameters (exposures, pose corrections) of a state, in frame order (frame 0 fixed)."""
        return {int(i): torch.nn.Parameter(e.clone().to(self.device), requires_grad=int(i) > 0)
                for i, e in sorted(saved.items())}


# torch.save costs tens of microseconds per tensor, whatever its size, and the mapper holds a few tiny ones per
# frame (pose, exposure, the exposures' Adam moments): packed into one stacked tensor per kind, a 400-frame
# state's checkpoint took 68-84 ms instead of 255-270 (bench/results/checkpoint_time/). Only tensors of at most
# PACK_NUMEL elements are packed: large ones stay as they are, with no copy (packing every tensor grew the
# mapper's RSS).
PACK_NUMEL = 64


def pack_by_frame(d: dict) -> dict:
    """``{frame id: tensor}`` whose tensors share one shape and dtype (and have at most :data:`PACK_NUMEL`
    elements) as ``{"packed_ids": ids, "packed_values": stacked}``; any other map as it is."""
    if not d:
        return d
    ts = list(d.values())
    t0 = ts[0]
    if t0.numel() > PACK_NUMEL or any(t.shape != t0.shape or t.dtype != t0.dtype for t in ts):
        return d
    return {"packed_ids": torch.tensor(list(d), dtype=torch.int64), "packed_values": torch.stack(ts)}


def unpack_by_frame(d: dict) -> dict:
    """The ``{frame id: tensor}`` map :func:`pack_by_frame` packed (a map it left as it is, unchanged)."""
    if set(d) != {"packed_ids", "packed_values"}:
        return d
    return {int(i): v.clone() for i, v in zip(d["packed_ids"].tolist(), d["packed_values"])}


def pack_optimizer_state(sd: dict) -> dict:
    """An optimizer ``state_dict`` with the per-parameter states made only of small tensors (at most
    :data:`PACK_NUMEL` elements each) stacked by their keys, shapes and dtypes into ``sd["packed"]``; the
    other states stay in ``sd["state"]``. :func:`unpack_optimizer_state` gives the ``state_dict`` back."""
    groups: dict = {}
    rest = {}
    for idx, st in sd["state"].items():
        if st and all(isinstance(v, Tensor) and v.numel() <= PACK_NUMEL for v in st.values()):
            sig = tuple((k, tuple(v.shape), v.dtype) for k, v in sorted(st.items()))
            groups.setdefault(sig, []).append(idx)
        else:
            rest[idx] = st
    packed = [{"ids": torch.tensor(ids, dtype=torch.int64),
               "values": {k: torch.stack([sd["state"][i][k] for i in ids]) for k, _, _ in sig}}
              for sig, ids in groups.items()]
    return {**sd, "state": rest, "packed": packed}


def unpack_optimizer_state(sd: dict) -> dict:
    """The ``state_dict`` :func:`pack_optimizer_state` packed (one without ``packed``, unchanged)."""
    if "packed" not in sd:
        return sd
    state = dict(sd["state"])
    for g in sd["packed"]:
        for j, idx in enumerate(g["ids"].tolist()):
            state[idx] = {k: v[j].clone() for k, v in g["values"].items()}
    out = {k: v for k, v in sd.items() if k != "packed"}
    out["state"] = dict(sorted(state.items()))
    return out


def _cpu_tree(x):
    if isinstance(x, Tensor):
        return x.detach().cpu().clone()
    if isinstance(x, dict):
        return {k: _cpu_tree(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_cpu_tree(v) for v in x]
    return x
