"""PLY read/write: coloured point clouds and triangle meshes (binary little-endian or ASCII).

Files written here open in Open3D, MeshLab and CloudCompare: vertex properties
``x y z`` (float32) and optional ``red green blue`` (uchar); faces as
``list uchar int vertex_indices``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


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
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
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
    tmp.replace(path)
    return path


def read_ply(path) -> PlyData:
    """Read vertices (x, y, z, optional red/green/blue) and triangle faces."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file (first line is not 'ply')")
        fmt, elements = None, []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no end_header")
            tok = line.decode("ascii", "replace").split()
            if not tok or tok[0] in ("comment", "obj_info"):
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                elements.append([tok[1], int(tok[2]), []])
            elif tok[0] == "property":
                if tok[1] == "list":
                    elements[-1][2].append((tok[4], "list", _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
                else:
                    elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
            elif tok[0] == "end_header":
                break
        if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
            raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
        data = {}
        if fmt == "ascii":
            rest = f.read().decode("ascii").split()
            pos = 0
            for name, count, props in elements:
                rows = []
                for _ in range(count):
                    row = []
                    for p in props:
                        if p[1] == "list":
                            k = int(rest[pos]); pos += 1
                            row.append([float(x) for x in rest[pos:pos + k]]); pos += k
                        else:
                            row.append(float(rest[pos])); pos += 1
                    rows.append(row)
                data[name] = (props, rows)
        else:
            end = "<" if fmt == "binary_little_endian" else ">"
            for name, count, props in elements:
                if any(p[1] == "list" for p in props):
                    if len(props) != 1:
                        raise ValueError(f"{path}: mixed list/scalar properties in element {name!r} not supported")
                    _, _, ct, it = props[0]
                    rows = []
                    for _ in range(count):
                        k = int(np.frombuffer(f.read(np.dtype(ct).itemsize), end + ct)[0])
                        rows.append([np.frombuffer(f.read(k * np.dtype(it).itemsize), end + it).tolist()])
                    data[name] = (props, rows)
                else:
                    dt = np.dtype([(p[0], end + p[1]) for p in props])
                    buf = f.read(dt.itemsize * count)
                    if len(buf) != dt.itemsize * count:
                        raise ValueError(f"{path}: truncated PLY data in element {name!r}")
                    data[name] = (props, np.frombuffer(buf, dt))
    if "vertex" not in data:
        raise ValueError(f"{path}: PLY has no vertex element")
    props, v = data["vertex"]
    names = [p[0] for p in props]
    if isinstance(v, list):
        arr = np.asarray(v, dtype=np.float64)
        col = {n: arr[:, i] for i, n in enumerate(names)} if len(arr) else {n: np.zeros(0) for n in names}
    else:
        col = {n: v[n] for n in names}
    pts = np.stack([col["x"], col["y"], col["z"]], -1).astype(np.float64)
    colors = None
    if all(c in col for c in ("red", "green", "blue")):
        colors = np.stack([col["red"], col["green"], col["blue"]], -1).astype(np.uint8)
    faces = None
    if "face" in data:
        fprops, rows = data["face"]
        tri = [r[0] for r in rows if len(r[0]) == 3]
        faces = np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    return PlyData(pts, colors, faces)
