"""Atomic file writes, JSON encoding, and dataclass trees as plain python (lists, dicts).

A reader of ``path`` sees either the old file or the whole new one, never a torn write: the
bytes go to a temp file ``.<name>.<pid>.tmp`` in the same folder, which is then renamed onto
``path`` (``os.replace``). With ``fsync`` the bytes are on disk before the rename; with
``fsync_folder`` the rename itself is made durable too. A writer that fails leaves the temp
file behind and ``path`` untouched.
"""
from __future__ import annotations

import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterator, Optional

import numpy as np


def temp_path(path) -> Path:
    """The temp file an atomic write of ``path`` goes through (same folder, hidden, per process)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def sync_folder(folder) -> None:
    """Make a rename in ``folder`` durable; file systems that cannot open a folder are skipped."""
    try:
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


def _open_new(tmp: Path, mode: Optional[int]) -> BinaryIO:
    if mode is None:
        return open(tmp, "wb")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)  # O_CREAT's mode does not apply to a file that already existed
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "wb")


@contextmanager
def atomic_open(path, *, fsync: bool = False, fsync_folder: bool = False,
                mode: Optional[int] = None) -> Iterator[BinaryIO]:
    """A binary file to stream into (``torch.save``, ``np.savez``, ...) that replaces ``path`` when
    the block ends without an exception. ``mode`` (e.g. ``0o600``): the file's permissions from
    its creation on; None: the usual ``open`` ones."""
    path = Path(path)
    tmp = temp_path(path)
    with _open_new(tmp, mode) as fh:
        yield fh
        if fsync:
            fh.flush()
            os.fsync(fh.fileno())
    os.replace(tmp, path)
    if fsync_folder:
        sync_folder(path.parent)


def atomic_write_bytes(path, data: bytes, **kw) -> Path:
    """Write ``data`` to ``path`` atomically (keywords: :func:`atomic_open`); returns ``path``."""
    with atomic_open(path, **kw) as fh:
        fh.write(data)
    return Path(path)


def atomic_write_text(path, text: str, **kw) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (keywords: :func:`atomic_open`); returns ``path``."""
    return atomic_write_bytes(path, text.encode(), **kw)


def json_default(o):
    """``json.dumps`` fallback: numpy scalars and arrays, paths, anything else as ``str``."""
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)


def write_json(path, obj: Any, *, indent: int = 1, sort_keys: bool = False,
               default: Callable[[Any], Any] = json_default, **kw) -> Path:
    """``obj`` as JSON in ``path``, atomically (keywords: :func:`atomic_open`); returns ``path``."""
    return atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=sort_keys, default=default), **kw)


def plain_tree(x):
    """Dataclass-asdict output -> plain python (tuples to lists) for weights_only loading."""
    if isinstance(x, dict):
        return {k: plain_tree(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain_tree(v) for v in x]
    return x
