"""The mapper's frame images by frame id: the working set raw, the keyframes beyond it compressed.

A mapper keeps the images of its local window and pending frames (used by every update) and of every
keyframe (global keyframes of later windows, the closing refinement, the export). Keyframes accumulate
with the sequence, so they are kept compressed once they leave the local window and decoded when an update
asks for them; the most recently decoded ones stay in a small cache (global keyframes recur from window to
window). The codec is PNG (lossless: the images the mapper trains on do not change) or JPEG at a high
quality without chroma subsampling (a third of PNG's bytes on real 640x480 frames, themselves JPEGs).
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Iterator, Optional

import cv2
import numpy as np
import torch
from torch import Tensor


def encode_png(img: Tensor) -> bytes:
    """Lossless PNG bytes of a uint8 (H, W, 3) image (channel order kept as is)."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img.numpy()), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def encode_jpeg(img: Tensor, quality: int = 95) -> bytes:
    """JPEG bytes of a uint8 (H, W, 3) image at ``quality``, colour not subsampled (4:4:4; channel order kept
    as is: :func:`decode_image` gives it back in the same order)."""
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
              cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img.numpy()), params)
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def decode_image(data: bytes) -> Tensor:
    """The image :func:`encode_png` or :func:`encode_jpeg` packed."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("not a PNG or JPEG image")
    return torch.from_numpy(img)


class ImageStore:
    """Images by frame id (uint8 (H, W, 3) tensors): ``store[fid] = img`` keeps it raw; :meth:`compress`
    packs one (``codec`` "png" | "jpeg" at ``quality``); ``store[fid]`` returns it either way (decoded ones
    cached, at most ``cache``)."""

    def __init__(self, cache: int = 32, codec: str = "png", quality: int = 95):
        if codec not in ("png", "jpeg") or not 1 <= int(quality) <= 100:
            raise ValueError(f"ImageStore: codec must be png or jpeg and quality in 1..100, got {codec!r}, {quality}")
        self.codec, self.quality = codec, int(quality)
        self.cache_size = int(cache)
        self._raw: dict[int, Tensor] = {}
        self._png: dict[int, bytes] = {}
        self._cache: "OrderedDict[int, Tensor]" = OrderedDict()

    def __setitem__(self, fid: int, img: Tensor) -> None:
        self._png.pop(fid, None)
        self._cache.pop(fid, None)
        self._raw[fid] = img

    def __getitem__(self, fid: int) -> Tensor:
        img = self._raw.get(fid)
        if img is not None:
            return img
        img = self._cache.get(fid)
        if img is not None:
            self._cache.move_to_end(fid)
            return img
        img = decode_image(self._png[fid])  # KeyError for an unknown frame, as a dict
        self._cache[fid] = img
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return img

    def __contains__(self, fid) -> bool:
        return fid in self._raw or fid in self._png

    def __len__(self) -> int:
        return len(self._raw) + len(self._png)

    def __iter__(self) -> Iterator[int]:
        return iter(sorted([*self._raw, *self._png]))

    def keys(self) -> list[int]:
        return list(self)

    def pop(self, fid: int, default: Optional[Tensor] = None) -> Optional[Tensor]:
        if fid not in self:
            return default
        img = self[fid]
        self._raw.pop(fid, None)
        self._png.pop(fid, None)
        self._cache.pop(fid, None)
        return img

    def compress(self, fid: int) -> None:
        """Keep frame ``fid``'s image compressed from now on (no-op when it is already, or unknown)."""
        img = self._raw.pop(fid, None)
        if img is not None:
            self._png[fid] = encode_png(img) if self.codec == "png" else encode_jpeg(img, self.quality)

    def is_compressed(self, fid: int) -> bool:
        return fid in self._png

    def nbytes(self) -> int:
        """Bytes held: raw images plus compressed ones (the decode cache aside)."""
        return sum(t.numel() * t.element_size() for t in self._raw.values()) + sum(len(b) for b in self._png.values())

    def state_dict(self) -> dict:
        return {"raw": {int(i): t.clone() for i, t in self._raw.items()},
                "png": {int(i): torch.frombuffer(bytearray(b), dtype=torch.uint8) for i, b in self._png.items()}}

    def load_state_dict(self, d: dict) -> None:
        """Restore :meth:`state_dict`, or a plain ``{fid: image}`` map (checkpoints of before the store)."""
        self._cache.clear()
        if set(d) <= {"raw", "png"} and isinstance(d.get("raw", {}), dict) and "png" in d:
            self._raw = {int(i): t.clone() for i, t in d["raw"].items()}
            self._png = {int(i): bytes(t.numpy().tobytes()) for i, t in d["png"].items()}
        else:
            self._raw = {int(i): t.clone() for i, t in d.items()}
            self._png = {}
