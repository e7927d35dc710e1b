"""PLY read/write: coloured point clouds and triangle meshes (binary little-endian or ASCII).

Files written here open in Open3D, MeshLab and CloudCompare: vertex properties
``x y z`` (float32) and optional ``red green blue`` (uchar); faces as
``list uchar int vertex_indices``. Reading goes through ``plyfile`` and takes what other
tools write too: any byte order, extra vertex / face properties (ignored), quads and
polygons (fan-triangulated).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import plyfile

from fmapping.fileio import atomic_open


@dataclass
class PlyData:
    points: np.ndarray  # (N, 3) float
    colors: Optional[np.ndarray] = None  # (N, 3) uint8
    faces: Optional[np.ndarray] = None  # (F, 3) int


def write_ply(path, points, colors=None, faces=None, binary: bool = True) -> Path:
    path = Path(path)
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(pts)
    cols = None
    if colors is not None:
        cols = np.asarray(colors)
        if cols.dtype != np.uint8:
            cols = np.clip(np.round(cols * 255 if cols.max(initial=0) <= 1.0 else cols), 0, 255).astype(np.uint8)
        cols = cols.reshape(-1, 3)
        if len(cols) != n:
            raise ValueError(f"write_ply: {len(cols)} colours for {n} points")
    tris = None if faces is None else np.asarray(faces, dtype=np.int32).reshape(-1, 3)
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment written by fmapping",
              f"element vertex {n}", "property float x", "property float y", "property float z"]
    if cols is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    if tris is not None:
        header += [f"element face {len(tris)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            vdt = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
            if cols is not None:
                vdt += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
            v = np.empty(n, dtype=vdt)
            v["x"], v["y"], v["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
            if cols is not None:
                v["red"], v["green"], v["blue"] = cols[:, 0], cols[:, 1], cols[:, 2]
            f.write(v.tobytes())
            if tris is not None:
                fa = np.empty(len(tris), dtype=[("n", "u1"), ("i", "<i4", (3,))])
                fa["n"] = 3
                fa["i"] = tris
                f.write(fa.tobytes())
        else:
            for i in range(n):
                row = f"{pts[i, 0]:.6f} {pts[i, 1]:.6f} {pts[i, 2]:.6f}"
                if cols is not None:
                    row += f" {cols[i, 0]} {cols[i, 1]} {cols[i, 2]}"
                f.write((row + "\n").encode())
            if tris is not None:
                for t in tris:
                    f.write(f"3 {t[0]} {t[1]} {t[2]}\n".encode())
    return path


def read_ply(path) -> PlyData:
    """Read vertices (x, y, z, optional red/green/blue) and faces as triangles.

    Polygons with k > 3 corners become k - 2 triangles fanned from their first corner, in file
    order; faces with fewer than 3 corners are dropped. Other properties are ignored.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file (first line is not 'ply')")
    try:
        ply = _read_plyfile(path)
    except plyfile.PlyParseError as e:
        raise ValueError(f"{path}: {e}") from None
    if "vertex" not in ply:
        raise ValueError(f"{path}: PLY has no vertex element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise ValueError(f"{path}: vertex element lacks {', '.join(missing)}")
    pts = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64)
    colors = None
    if all(c in names for c in ("red", "green", "blue")):
        colors = np.stack([v["red"], v["green"], v["blue"]], -1)
        if colors.dtype.kind == "f" and colors.size and colors.max() <= 1.0:
            colors = np.round(colors * 255)  # float colours in [0, 1] (some exporters)
        colors = np.clip(colors, 0, 255).astype(np.uint8)
    faces = None
    if "face" in ply:
        fe = ply["face"]
        key = next((k for k in _FACE_LISTS if k in fe.data.dtype.names), None)
        if key is None:
            raise ValueError(f"{path}: face element has no vertex_indices / vertex_index list")
        faces = _triangles(fe.data[key])
        if len(faces) and (faces.min() < 0 or faces.max() >= len(pts)):
            raise ValueError(f"{path}: face vertex index out of range 0..{len(pts) - 1}")
    return PlyData(pts, colors, faces)


# names other tools give the face's corner list (Open3D / MeshLab write vertex_indices, some vertex_index)
_FACE_LISTS = ("vertex_indices", "vertex_index")


def _read_plyfile(path: Path) -> "plyfile.PlyData":
    """plyfile reads a binary list property one row at a time in Python (seconds per million
    faces) unless told the list length, in which case it maps the whole element at once. Try
    all-triangle faces (what the writer above and most meshers produce), then all-quad faces; a
    file with mixed polygons fails both and is read row by row. A wrong guess shows as a length
    mismatch or as too few bytes for the element; the row-by-row read reports a truly short file."""
    for k in (3, 4):
        try:
            return _loaded(plyfile.PlyData.read(str(path), known_list_len={"face": dict.fromkeys(_FACE_LISTS, k)}))
        except plyfile.PlyElementParseError as e:
            if e.message not in ("unexpected list length", "early end-of-file"):
                raise
    return _loaded(plyfile.PlyData.read(str(path), mmap=False))


def _loaded(ply: "plyfile.PlyData") -> "plyfile.PlyData":
    # copy memory-mapped elements into memory: the file may be replaced or deleted after reading
    for el in ply.elements:
        if isinstance(el.data, np.memmap):
            el.data = np.array(el.data)
    return ply


def _triangles(lists: np.ndarray) -> np.ndarray:
    """(F, 3) int64 triangles from a face list column: a (F, k) array (fixed length k) or an
    object array of per-face index arrays; polygons fan out from their first corner."""
    if lists.dtype != object:
        rows = np.asarray(lists, np.int64).reshape(len(lists), -1)
        return _fan(rows) if rows.shape[1] >= 3 else np.zeros((0, 3), np.int64)
    n = np.fromiter((len(r) for r in lists), np.int64, len(lists))
    ntri = np.maximum(n - 2, 0)
    first = np.concatenate([[0], np.cumsum(ntri)[:-1]]) if len(n) else n  # first triangle of each face
    out = np.empty((int(ntri.sum()), 3), np.int64)
    for k in np.unique(n[n >= 3]):  # one vectorised fan per polygon size, scattered back in file order
        sel = np.flatnonzero(n == k)
        tris = _fan(np.stack(lists[sel]).astype(np.int64))  # (len(sel) * (k - 2), 3), grouped per face
        out[(first[sel, None] + np.arange(k - 2)).reshape(-1)] = tris
    return out


def _fan(rows: np.ndarray) -> np.ndarray:
    """(F, k) polygons -> (F * (k - 2), 3) triangles (c0, ci, ci+1), the k - 2 of each face together."""
    k = rows.shape[1]
    tris = np.stack([np.repeat(rows[:, :1], k - 2, 1), rows[:, 1:-1], rows[:, 2:]], -1)
    return tris.reshape(-1, 3)
