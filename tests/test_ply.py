"""PLY reading (through plyfile): our own files, and what other tools write (quads, polygons,
extra properties, big-endian, ascii)."""
from __future__ import annotations

import numpy as np
import pytest

from fmapping.ply import read_ply, write_ply

PTS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1]], np.float64)


def _write_foreign(path, fmt: str, vertex_props: list[tuple[str, str]], vertex_rows: list[tuple],
                   face_props: list[tuple[str, str]], faces: list[tuple[list[int], tuple]]) -> None:
    """A PLY file as another exporter might write it: vertex / face properties in the given order
    (``("list", name)`` is the uchar-count int-index corner list), any format."""
    types = {"float": "f4", "double": "f8", "uchar": "u1", "int": "i4", "short": "i2"}
    head = ["ply", f"format {fmt} 1.0", "comment foreign exporter", f"element vertex {len(vertex_rows)}"]
    head += [f"property {t} {n}" for t, n in vertex_props]
    head.append(f"element face {len(faces)}")
    head += ["property list uchar int vertex_indices" if t == "list" else f"property {t} {n}" for t, n in face_props]
    head.append("end_header")
    if fmt == "ascii":
        body = [" ".join(map(str, r)) for r in vertex_rows]
        for corners, extra in faces:
            it = iter(extra)
            body.append(" ".join(f"{len(corners)} " + " ".join(map(str, corners)) if t == "list" else str(next(it))
                                 for t, _ in face_props))
        data = ("\n".join(body) + "\n").encode()
    else:
        end = "<" if fmt == "binary_little_endian" else ">"
        chunks = []
        for r in vertex_rows:
            chunks += [np.array(v, end + types[t]).tobytes() for (t, _), v in zip(vertex_props, r)]
        for corners, extra in faces:
            it = iter(extra)
            for t, _ in face_props:
                if t == "list":
                    chunks.append(np.uint8(len(corners)).tobytes() + np.asarray(corners, end + "i4").tobytes())
                else:
                    chunks.append(np.array(next(it), end + types[t]).tobytes())
        data = b"".join(chunks)
    path.write_bytes(("\n".join(head) + "\n").encode() + data)


@pytest.mark.parametrize("binary", [True, False])
def test_own_files_round_trip(tmp_path, binary):
    rng = np.random.default_rng(0)
    pts, cols = rng.random((50, 3)), rng.integers(0, 256, (50, 3)).astype(np.uint8)
    faces = rng.integers(0, 50, (40, 3))
    d = read_ply(write_ply(tmp_path / "m.ply", pts, cols, faces, binary=binary))
    np.testing.assert_allclose(d.points, pts.astype(np.float32), atol=1e-6)
    np.testing.assert_array_equal(d.colors, cols)
    np.testing.assert_array_equal(d.faces, faces)
    cloud = read_ply(write_ply(tmp_path / "c.ply", pts, binary=binary))
    assert cloud.faces is None and cloud.colors is None and cloud.points.shape == (50, 3)


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_quads_read_as_two_triangles_each(tmp_path, fmt):
    quads = [[0, 1, 2, 3], [4, 5, 6, 3]]
    _write_foreign(tmp_path / "q.ply", fmt, [("float", "x"), ("float", "y"), ("float", "z")],
                   [tuple(p) for p in PTS], [("list", "vertex_indices")], [(q, ()) for q in quads])
    d = read_ply(tmp_path / "q.ply")
    np.testing.assert_array_equal(d.faces, [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 3]])
    np.testing.assert_array_equal(d.points, PTS)


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_mixed_polygons_fan_in_file_order(tmp_path, fmt):
    # a triangle, a pentagon, a degenerate 2-corner face (dropped), a quad
    polys = [[6, 5, 4], [0, 1, 2, 3, 4], [1, 2], [3, 4, 5, 6]]
    _write_foreign(tmp_path / "p.ply", fmt, [("float", "x"), ("float", "y"), ("float", "z")],
                   [tuple(p) for p in PTS], [("list", "vertex_indices")], [(p, ()) for p in polys])
    d = read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(d.faces, [[6, 5, 4], [0, 1, 2], [0, 2, 3], [0, 3, 4], [3, 4, 5], [3, 5, 6]])


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_extra_vertex_and_face_properties_are_ignored(tmp_path, fmt):
    vprops = [("double", "x"), ("float", "nx"), ("double", "y"), ("double", "z"), ("uchar", "red"),
              ("uchar", "green"), ("uchar", "blue"), ("uchar", "alpha"), ("float", "quality")]
    rows = [(p[0], 0.5, p[1], p[2], 10 * i, 20 + i, 200, 255, 0.25) for i, p in enumerate(PTS)]
    # MeshLab-style faces: a flags int before the list and a colour after it
    fprops = [("int", "flags"), ("list", "vertex_indices"), ("uchar", "red"), ("float", "quality")]
    faces = [([0, 1, 2], (7, 9, 1.5)), ([2, 3, 0], (8, 9, 2.5)), ([4, 5, 6, 3], (0, 1, 0.0))]
    _write_foreign(tmp_path / "x.ply", fmt, vprops, rows, fprops, faces)
    d = read_ply(tmp_path / "x.ply")
    np.testing.assert_array_equal(d.points, PTS)
    np.testing.assert_array_equal(d.colors, [[10 * i, 20 + i, 200] for i in range(len(PTS))])
    np.testing.assert_array_equal(d.faces, [[0, 1, 2], [2, 3, 0], [4, 5, 6], [4, 6, 3]])


def test_bad_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "not.ply").write_text("hello\n")
    with pytest.raises(ValueError, match="not a PLY file"):
        read_ply(tmp_path / "not.ply")
    good = write_ply(tmp_path / "t.ply", PTS, faces=[[0, 1, 2], [2, 3, 4]])
    (tmp_path / "short.ply").write_bytes(good.read_bytes()[:-5])  # the last face cut short
    with pytest.raises(ValueError, match="short.ply"):
        read_ply(tmp_path / "short.ply")
    write_ply(tmp_path / "oob.ply", PTS, faces=[[0, 1, 7]])
    with pytest.raises(ValueError, match="out of range"):
        read_ply(tmp_path / "oob.ply")


def test_a_million_faces_read_back_exactly(tmp_path):
    # the mapper writes meshes of this size (read speed is measured in bench/, not asserted here)
    rng = np.random.default_rng(1)
    faces = rng.integers(0, 200_000, (1_000_000, 3))
    path = write_ply(tmp_path / "big.ply", rng.random((200_000, 3)), faces=faces)
    d = read_ply(path)
    np.testing.assert_array_equal(d.faces, faces)
