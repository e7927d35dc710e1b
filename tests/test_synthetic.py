"""Synthetic scene generator: exact depth and colour, GT files, trajectory limits, determinism."""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from fmapping import geometry as g
from fmapping import synthetic as S
from fmapping.ply import read_ply
from fmapping.trajectory import read_tum_trajectory

SEED, FRAMES, SIZE = 1, 20, (80, 60)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("synth")
    info = S.generate_scene(out, seed=SEED, frames=FRAMES, size=SIZE, max_cloud_points=120_000)
    return out, info


@pytest.fixture(scope="module")
def mesh(scene_dir):
    return read_ply(scene_dir[0] / "gt_mesh.ply")


# ------------------------------------------------------------------ independent geometry helpers
def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact distance of points p (N, 3) to triangles (a, b, c) (N, 3) each: plane distance when
    the projection falls inside, else the nearest of the three edges."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dist_plane = np.abs(((p - a) * n).sum(1))
    q = p - ((p - a) * n).sum(1, keepdims=True) * n
    inside = np.ones(len(p), bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(v - u, q - u) * n).sum(1) >= -1e-12

    def seg(u, v):
        t = np.clip(((p - u) * (v - u)).sum(1) / ((v - u) ** 2).sum(1), 0, 1)
        return np.linalg.norm(p - (u + t[:, None] * (v - u)), axis=1)

    return np.where(inside, dist_plane, np.minimum(np.minimum(seg(a, b), seg(b, c)), seg(c, a)))


def _mesh_distance(points: np.ndarray, verts: np.ndarray, faces: np.ndarray, k: int = 24) -> np.ndarray:
    """Distance of points to a triangle mesh: exact point-triangle test on the k triangles with the
    nearest centroids (triangles are ~5 cm, so the containing one is always among them)."""
    tri = verts[faces]
    tree = cKDTree(tri.mean(1))
    _, idx = tree.query(points, k=k)
    best = np.full(len(points), np.inf)
    for j in range(k):
        t = tri[idx[:, j]]
        best = np.minimum(best, _point_triangle_distance(points, t[:, 0], t[:, 1], t[:, 2]))
    return best


def _backproject(camera, c2w: np.ndarray, depth: np.ndarray, step: int = 1):
    v, u = np.mgrid[0:camera.height:step, 0:camera.width:step]
    z = depth[v, u].astype(np.float64)
    x = (u - camera.cx) / camera.fx * z
    y = (v - camera.cy) / camera.fy * z
    pc = np.stack([x, y, z], -1).reshape(-1, 3)
    return pc @ c2w[:3, :3].T + c2w[:3, 3], v.ravel(), u.ravel()


# --------------------------------------------------------------------------------------- tests
def test_camera_for_size():
    cam = S.camera_for_size(320, 240)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (256.0, 256.0, 159.5, 119.5, 320, 240)
    assert abs(np.degrees(2 * np.arctan(160 / 256)) - 64.0) < 0.1  # horizontal FOV
    with pytest.raises(ValueError, match="at least 8x8"):
        S.camera_for_size(4, 3)


@pytest.mark.parametrize("seed", range(8))
def test_scene_layout(seed):
    sc = S.make_scene(seed)
    dims = sc.room_max - sc.room_min
    assert 4.0 <= dims[0] <= 6.0 and 3.5 <= dims[1] <= 5.0 and 2.5 <= dims[2] <= 3.0
    assert 4 <= len(sc.boxes) <= 7
    assert {"table", "cabinet", "shelf", "small"} <= {b.kind for b in sc.boxes}
    assert len(sc.rects) == sc.n_surfaces == 6 + 6 * len(sc.boxes)
    for r in sc.rects:  # surface ids index the list; normals point into free space
        assert sc.rects[r.sid] is r
        probe = r.origin + 0.5 * r.e1 + 0.5 * r.e2 + 0.02 * r.normal
        inside_room = np.all(probe > sc.room_min) and np.all(probe < sc.room_max)
        in_box = any(np.all(np.abs(b.to_local(probe[None])[0]) < b.half) for b in sc.boxes)
        assert inside_room and not in_box or (not r.exposed), r.name
    for b in sc.boxes:  # furniture stands on the floor, inside the room
        assert abs(b.center[2] - b.half[2]) < 1e-12
        fp = b.footprint()
        assert np.all(fp > sc.room_min[:2]) and np.all(fp < sc.room_max[:2])


def test_surface_colour_range_and_view_independence():
    sc = S.make_scene(0)
    rng = np.random.default_rng(0)
    for r in sc.rects:
        ab = rng.random((500, 2))
        pts = r.origin + ab[:, :1] * r.e1 + ab[:, 1:] * r.e2
        col = S.surface_colour(sc, pts, np.full(500, r.sid))
        assert col.shape == (500, 3)
        assert col.min() >= 0.05 and col.max() <= 0.95
        assert col.std(0).max() > 0.02  # textured, not flat
        # a pure function of the point: same answer in any order / batch
        perm = rng.permutation(500)
        np.testing.assert_array_equal(S.surface_colour(sc, pts[perm], np.full(500, r.sid)), col[perm])
    with pytest.raises(ValueError, match="surface ids"):
        S.surface_colour(sc, np.zeros((1, 3)), np.array([sc.n_surfaces]))


def test_depth_lies_on_gt_mesh(mesh):
    assert mesh.faces is not None and len(mesh.faces) > 10_000
    sc = S.make_scene(SEED)
    poses = S.make_trajectory(sc, FRAMES, SEED)
    cam = S.camera_for_size(*SIZE)
    pts = []
    for i in (0, 7, 13, 19):
        _, depth = S.render_view(sc, cam, poses[i], supersample=1)
        assert depth.min() > 0.4  # the camera keeps its distance from everything
        p, _, _ = _backproject(cam, poses[i], depth, step=2)
        pts.append(p)
    pts = np.concatenate(pts)
    dist = _mesh_distance(pts, mesh.points, mesh.faces)
    assert dist.max() < 1e-3, f"max distance of back-projected depth to the GT mesh {dist.max():.2e} m"
    # a 1 % depth error would be detected
    p_bad, _, _ = _backproject(cam, poses[0], 1.01 * S.render_view(sc, cam, poses[0], supersample=1)[1], step=4)
    assert np.median(_mesh_distance(p_bad, mesh.points, mesh.faces)) > 5e-3


def test_rendered_colour_is_surface_colour():
    sc = S.make_scene(2)
    poses = S.make_trajectory(sc, 10, 2)
    cam = S.camera_for_size(96, 72)
    for i in (0, 9):
        rgb, depth, ids = S.render_view(sc, cam, poses[i], supersample=1, return_ids=True)
        pts, v, u = _backproject(cam, poses[i], depth)
        sid = ids[v, u]
        # each back-projected point lies on the plane of the surface it was attributed to
        nrm = np.stack([sc.rects[s].normal for s in sid])
        org = np.stack([sc.rects[s].origin for s in sid])
        assert np.abs(((pts - org) * nrm).sum(1)).max() < 1e-5
        ref = S.surface_colour(sc, pts, sid) * 255
        assert np.abs(ref - rgb[v, u].astype(np.float64)).max() <= 2.0
        assert len(np.unique(sid)) >= 2


def test_supersampling_is_the_mean_of_shifted_renders():
    """2x2 supersampling (plane shortcut inside surfaces, casting at edges) equals four centre-ray
    renders with the principal point shifted by a quarter pixel."""
    sc = S.make_scene(3)
    pose = S.make_trajectory(sc, 30, 3)[17]
    cam = S.camera_for_size(64, 48)
    rgb, _ = S.render_view(sc, cam, pose, supersample=2)
    ref = np.zeros(rgb.shape)
    for dv in (-0.25, 0.25):
        for du in (-0.25, 0.25):
            ref += S.render_view(sc, replace(cam, cx=cam.cx - du, cy=cam.cy - dv), pose, supersample=1)[0]
    assert np.abs(ref / 4 - rgb).max() <= 1.0


def test_texture_has_gradients_everywhere():
    sc = S.make_scene(0)
    cam = S.camera_for_size(160, 120)
    for pose in S.make_trajectory(sc, 40, 0)[::13]:
        gray = cv2.cvtColor(S.render_view(sc, cam, pose)[0], cv2.COLOR_RGB2GRAY).astype(np.float64)
        gx = cv2.Sobel(gray, cv2.CV_64F, 1, 0, ksize=3) / 8
        gy = cv2.Sobel(gray, cv2.CV_64F, 0, 1, ksize=3) / 8
        assert (np.hypot(gx, gy) > 0.5).mean() > 0.9


@pytest.mark.parametrize("seed,frames", [(0, 20), (0, 200), (4, 400), (5, 120)])
def test_trajectory_step_limits_and_clearance(seed, frames):
    sc = S.make_scene(seed)
    c2w = S.make_trajectory(sc, frames, seed)
    assert c2w.shape == (frames, 4, 4)
    rot = torch.from_numpy(c2w[:, :3, :3])
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(frames, 3, 3))
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(frames, dtype=torch.float64))
    rel = rot[:-1].transpose(1, 2) @ rot[1:]
    deg = torch.rad2deg(g.rotation_angle(rel)).numpy()
    step = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)
    assert step.max() <= 0.03 and deg.max() <= 2.0
    assert step.min() > 0.005  # it moves (no stalls)
    # heights 1.2-1.7 m; camera looks down a little (OpenCV z axis = forward)
    assert np.all((c2w[:, 2, 3] > 1.2) & (c2w[:, 2, 3] < 1.7))
    assert np.all(c2w[:, 2, 2] < 0)
    # >= 0.5 m from every surface: GT surface points never come closer
    pts, _, _ = S.gt_cloud(sc, max_points=40_000)
    d, _ = cKDTree(pts).query(c2w[:, :3, 3])
    assert d.min() >= 0.5
    if frames >= 400:  # enough frames for the full loop: it closes within the step limits
        assert np.linalg.norm(c2w[0, :3, 3] - c2w[-1, :3, 3]) <= 0.03
        assert np.degrees(g.rotation_angle(torch.from_numpy(c2w[0, :3, :3].T @ c2w[-1, :3, :3])).item()) <= 2.0


def test_yaw_covers_the_room():
    c2w = S.make_trajectory(S.make_scene(0), 200, 0)
    yaw = np.unwrap(np.arctan2(c2w[:, 1, 2], c2w[:, 0, 2]))
    assert abs(yaw[-1] - yaw[0]) > np.radians(300)


def test_written_folder_layout(scene_dir):
    out, info = scene_dir
    names = sorted(p.name for p in (out / "rgb").iterdir())
    assert len(names) == FRAMES and names[1] == "0.033333.png"
    ts_expected = [f"{i / 30:.6f}" for i in range(FRAMES)]
    for txt, sub in (("rgb.txt", "rgb"), ("depth.txt", "depth")):
        lines = [ln for ln in (out / txt).read_text().splitlines() if not ln.startswith("#")]
        assert [ln.split() for ln in lines] == [[t, f"{sub}/{t}.png"] for t in ts_expected]
    gt_lines = [ln for ln in (out / "groundtruth.txt").read_text().splitlines() if not ln.startswith("#")]
    assert [ln.split()[0] for ln in gt_lines] == ts_expected
    calib = (out / "calib.txt").read_text().splitlines()
    assert [float(x) for x in calib[0].split()] == [64.0, 64.0, 39.5, 29.5]
    assert calib[1].split() == ["depth_factor", "5000"]
    meta = json.loads((out / "scene.json").read_text())
    assert meta["generator"] == "fmapping.synthetic" and meta["seed"] == SEED and meta["frames"] == FRAMES
    assert meta["size"] == list(SIZE) and meta["max_step_m"] <= 0.03 and meta["max_step_deg"] <= 2.0
    assert meta["bbox"] == meta["room"] and len(meta["boxes"]) >= 4
    depth = cv2.imread(str(out / "depth" / names[3]), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == SIZE[::-1] and depth.min() > 0
    assert set(info) >= {"paths", "timing", "frames", "camera", "bbox"}
    assert info["frames"] == FRAMES and Path(info["paths"]["gt_mesh"]).is_file()


def test_dataset_factory_reads_the_folder(scene_dir):
    datasets = pytest.importorskip("fmapping.datasets")
    out, _ = scene_dir
    ds = datasets.open_dataset(out)
    assert ds.kind == "synthetic" and len(ds) == FRAMES
    cam = S.camera_for_size(*SIZE)
    assert ds.camera == cam and ds.depth_scale == 5000.0
    sc = S.make_scene(SEED)
    poses = S.make_trajectory(sc, FRAMES, SEED)
    _, gt = read_tum_trajectory(out / "groundtruth.txt")
    np.testing.assert_allclose(gt, poses, atol=1e-8)
    for i in (0, 11, FRAMES - 1):
        fr = ds[i]
        assert abs(fr.timestamp - i / 30) < 1e-6
        rgb, depth = S.render_view(sc, cam, poses[i])
        np.testing.assert_array_equal(fr.rgb, rgb)
        assert np.abs(fr.depth - depth).max() <= 0.5 / 5000 + 1e-6
        np.testing.assert_allclose(fr.c2w, poses[i], atol=1e-8)


def test_gt_clouds(scene_dir):
    out, info = scene_dir
    full = read_ply(out / "gt_cloud.ply")
    vis = read_ply(out / "gt_visible_cloud.ply")
    assert 0 < len(vis.points) < len(full.points) == info["gt_cloud_points"]
    # visible points are rows of the full cloud (same float32 coordinates and colours)
    def key(p, c):
        return {tuple(r) for r in np.concatenate([p.astype(np.float32).view(np.uint32), c], 1).tolist()}

    assert key(vis.points, vis.colors) <= key(full.points, full.colors)
    sc = S.make_scene(SEED)
    # uniform by area: the ceiling and the x-min wall get point counts proportional to their areas
    lo, hi = sc.room_min, sc.room_max
    dens = len(full.points) / sum(r.area for r in sc.rects if r.exposed)
    on_ceiling = np.abs(full.points[:, 2] - hi[2]) < 1e-5
    on_wall = np.abs(full.points[:, 0] - lo[0]) < 1e-5
    assert abs(on_ceiling.sum() / (dens * sc.rects[1].area) - 1) < 0.03
    assert abs(on_wall.sum() / (dens * sc.rects[2].area) - 1) < 0.03
    # no floor point under furniture
    floor = full.points[np.abs(full.points[:, 2]) < 1e-6]
    for b in sc.boxes:
        q = np.abs(b.to_local(floor)[:, :2]) - b.half[:2]
        assert not np.any((q < -1e-4).all(1))
    # colours are the texture, and visible points are seen by some frame
    cam = S.camera_for_size(*SIZE)
    poses = S.make_trajectory(sc, FRAMES, SEED)
    seen = np.zeros(len(vis.points), bool)
    for pose in poses:
        seen |= S.visible_mask(cam, pose, S.render_view(sc, cam, pose, supersample=1)[1], vis.points)
    assert seen.all()
    ceiling_vis = vis.points[np.abs(vis.points[:, 2] - hi[2]) < 1e-5]
    if len(ceiling_vis):
        ref = S.surface_colour(sc, ceiling_vis, np.ones(len(ceiling_vis), int))
        col = vis.colors[np.abs(vis.points[:, 2] - hi[2]) < 1e-5].astype(np.float64)
        assert np.abs(ref * 255 - col).max() <= 1.0


def test_mesh_vertex_colours_are_the_texture(mesh):
    sc = S.make_scene(SEED)
    floor = np.abs(mesh.points[:, 2]) < 1e-6
    # walls and box sides also have vertices at z = 0: skip the room border and footprints (closed)
    floor &= (np.abs(mesh.points[:, :2] - sc.room_min[:2]).min(1) > 1e-5)
    floor &= (np.abs(mesh.points[:, :2] - sc.room_max[:2]).min(1) > 1e-5)
    for b in sc.boxes:
        floor &= ~(np.abs(b.to_local(mesh.points)[:, :2]) <= b.half[:2] + 1e-5).all(1)
    assert floor.sum() > 1000
    ref = S.surface_colour(sc, mesh.points[floor], np.zeros(floor.sum(), int)) * 255
    assert np.abs(ref - mesh.colors[floor]).max() <= 1.0
    tri = mesh.points[mesh.faces]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
    assert np.sort(edges, 1)[:, :2].max() <= 0.05 + 1e-6  # 5 cm grid cells split along a diagonal
    assert edges.max() <= 0.05 * np.sqrt(2) + 1e-6


def test_determinism(tmp_path):
    a = S.generate_scene(tmp_path / "a", seed=7, frames=3, size=(40, 30), max_cloud_points=20_000)
    b = S.generate_scene(tmp_path / "b", seed=7, frames=3, size=(40, 30), max_cloud_points=20_000)
    c = S.generate_scene(tmp_path / "c", seed=8, frames=3, size=(40, 30), max_cloud_points=20_000)
    for name in ("rgb/0.033333.png", "depth/0.066667.png", "groundtruth.txt", "gt_cloud.ply", "gt_mesh.ply"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert (tmp_path / "a" / "rgb/0.033333.png").read_bytes() != (tmp_path / "c" / "rgb/0.033333.png").read_bytes()
    assert a["bbox"] == b["bbox"] != c["bbox"]


def test_rerun_replaces_frames_and_bad_input(tmp_path):
    S.generate_scene(tmp_path, seed=0, frames=4, size=(16, 12), max_cloud_points=5_000)
    S.generate_scene(tmp_path, seed=0, frames=2, size=(16, 12), max_cloud_points=5_000)
    assert len(list((tmp_path / "rgb").iterdir())) == 2
    with pytest.raises(ValueError, match="frames"):
        S.make_trajectory(S.make_scene(0), 0, 0)
    with pytest.raises(ValueError, match="8x8"):
        S.generate_scene(tmp_path / "x", frames=2, size=(4, 4))
    with pytest.raises(ValueError, match="dist"):
        S.render_view(S.make_scene(0), replace(S.camera_for_size(16, 12), dist=(0.1, 0, 0, 0)), np.eye(4))


def test_cli_synth(tmp_path, capsys):
    from fmapping.cli import main

    assert main(["synth", "--out", str(tmp_path), "--seed", "2", "--frames", "3", "--size", "24x16"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 3 and info["camera"]["width"] == 24 and "total_s" in info["timing"]
    assert (tmp_path / "gt_visible_cloud.ply").is_file()


# ------------------------------------------------------------------------------ wide variety
WIDE_SEED, WIDE_FRAMES, WIDE_SIZE = 2, 12, (160, 120)  # seed 2: JPEG frames, poles seen in frame 9


@pytest.fixture(scope="module")
def wide_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth_wide")
    S.generate_scene(out, seed=WIDE_SEED, frames=WIDE_FRAMES, size=WIDE_SIZE, max_cloud_points=60_000,
                     variety="wide")
    return out


def test_default_variety_is_unchanged(tmp_path):
    """The default room must stay bit-identical: the hash below was computed with the generator
    as it was before the wide variety existed (commit 1e570e1), not with the current code.
    (It also depends on OpenCV's PNG encoder; a new encoder version would change it.)"""
    import hashlib

    S.generate_scene(tmp_path, seed=0, frames=4, size=(40, 30), max_cloud_points=20_000)
    h = hashlib.sha256()
    for p in sorted(q for q in tmp_path.rglob("*") if q.is_file()):
        h.update(p.relative_to(tmp_path).as_posix().encode() + b"\n" + p.read_bytes())
    assert h.hexdigest() == "345cdbc4bc6950c71d0de020f09eb3829cfed50228b4a4304faa85aa5cd57bdb"
    assert "variety" not in json.loads((tmp_path / "scene.json").read_text())
    with pytest.raises(ValueError, match="variety"):
        S.make_scene(0, "narrow")


def test_wide_seeds_draw_different_styles_and_every_feature(tmp_path):
    metas = []
    for seed in range(5):
        out = tmp_path / str(seed)
        S.generate_scene(out, seed=seed, frames=2, size=(40, 30), max_cloud_points=5_000, variety="wide")
        metas.append(json.loads((out / "scene.json").read_text()))
    styles = [m["variety"]["style"] for m in metas]
    assert all(styles[i] != styles[j] for i in range(5) for j in range(i))
    assert len({round(s["texture_scale"], 6) for s in styles}) == 5
    for m in metas:  # each recorded feature is backed by the recorded parameters / files
        v, f = m["variety"], m["variety"]["features"]
        kinds = {s["kind"] for s in v["surfaces"]}
        assert f["striped"] == ("striped" in kinds) and f["low_texture"] == ("low_texture" in kinds)
        off_grid = [b for b in m["boxes"] if abs(math.remainder(b["yaw_deg"], 90.0)) > 1.0]
        assert f["rotated_box"] == bool(off_grid)
        thin = [b for b in m["boxes"] if min(b["size"][:2]) < 0.08]
        assert f["thin_structure"] == bool(thin) and all(b["kind"] in ("pole", "panel") for b in thin)
        ext = {p.suffix for p in (tmp_path / str(m["seed"]) / "rgb").iterdir()}
        assert f["jpeg"] == (v["style"]["jpeg_quality"] > 0) == (ext == {".jpg"})
        assert len(v["per_frame"]["gain"]) == len(v["per_frame"]["offset_dn"]) == 2
        dims = np.array(m["room"]["max"]) - np.array(m["room"]["min"])
        assert np.all(dims >= [4.0, 3.5, 2.5]) and np.all(dims <= [8.0, 6.0, 3.0])
    for feature in ("striped", "low_texture", "rotated_box", "thin_structure", "jpeg"):
        assert any(m["variety"]["features"][feature] for m in metas), feature
    # low-frequency and low-contrast textures and larger rooms than the default's occur
    assert max(s["texture_scale"] for s in styles) > 2.0 and min(s["contrast"] for s in styles) < 0.4
    assert any(m["room"]["max"][0] - m["room"]["min"][0] > 6.0 for m in metas)


@pytest.mark.parametrize("seed", range(5))
def test_wide_trajectory_stays_clear(seed):
    sc = S.make_scene(seed, "wide")
    c2w = S.make_trajectory(sc, 300, seed)
    pos = c2w[:, :3, 3]
    assert np.all(pos > sc.room_min) and np.all(pos < sc.room_max)
    pts, _, _ = S.gt_cloud(sc, max_points=40_000)
    assert cKDTree(pts).query(pos)[0].min() >= 0.5
    step, deg = S.trajectory_steps(c2w)
    assert step.max() <= 0.03 and deg.max() <= 2.0
    cam = S.camera_for_size(40, 30)
    for pose in c2w[::100]:  # every pixel sees a surface at a plausible distance
        depth = S.render_view(sc, cam, pose, supersample=1)[1]
        assert depth.min() > 0.4 and depth.max() < 11.0


def test_wide_depth_lies_on_gt_mesh(wide_dir):
    mesh = read_ply(wide_dir / "gt_mesh.ply")
    _, gt = read_tum_trajectory(wide_dir / "groundtruth.txt")
    names = sorted((wide_dir / "depth").iterdir())
    cam = S.camera_for_size(*WIDE_SIZE)
    sc = S.make_scene(WIDE_SEED, "wide")
    thin_ids = [6 + 6 * b + f for b, box in enumerate(sc.boxes) if box.kind in ("pole", "panel") for f in range(6)]
    pts, on_thin = [], 0
    for i in (0, 5, 9, 11):
        depth = cv2.imread(str(names[i]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 5000.0
        assert depth.min() > 0.4
        p, v, u = _backproject(cam, gt[i], depth, step=2)
        pts.append(p)
        on_thin += np.isin(S.render_view(sc, cam, gt[i], supersample=1, return_ids=True)[2][v, u], thin_ids).sum()
    dist = _mesh_distance(np.concatenate(pts), mesh.points, mesh.faces)
    assert dist.max() < 1e-3, f"max distance of back-projected depth to the GT mesh {dist.max():.2e} m"
    assert on_thin > 0  # a thin pole is among the checked pixels


def _smoothed_errors(written: np.ndarray, clean: np.ndarray, gain, offset) -> tuple[float, float]:
    """Median |written - clean| and |written - (gain * clean + offset)| after a 9x9 Gaussian (which
    removes most noise, JPEG and blur differences), over unsaturated pixels, in 8-bit units."""
    gw = cv2.GaussianBlur(written.astype(np.float64), (9, 9), 0)
    gc = cv2.GaussianBlur(clean.astype(np.float64), (9, 9), 0)
    ok = (written > 3).all(-1) & (written < 252).all(-1)
    model = gc * np.asarray(gain) + np.asarray(offset)
    return float(np.median(np.abs(gw - gc)[ok])), float(np.median(np.abs(gw - model)[ok]))


def test_wide_exposure_gain_and_offset_are_applied(tmp_path, wide_dir):
    # seed 1: per-channel gains and offsets, noise, blur, PNG; the fixture: JPEG
    S.generate_scene(tmp_path, seed=1, frames=3, size=(80, 60), max_cloud_points=5_000, variety="wide")
    for out, seed, size, frames in ((tmp_path, 1, (80, 60), (0, 2)), (wide_dir, WIDE_SEED, WIDE_SIZE, (0, 11))):
        meta = json.loads((out / "scene.json").read_text())
        rec = meta["variety"]["per_frame"]
        sc = S.make_scene(seed, "wide")
        poses = S.make_trajectory(sc, meta["frames"], seed)
        files = sorted((out / "rgb").iterdir())
        cam = S.camera_for_size(*size)
        for i in frames:
            gain, offset = np.array(rec["gain"][i]), np.array(rec["offset_dn"][i])
            assert np.abs(gain - 1).max() > 0.05  # these frames have a visible exposure change
            written = cv2.imread(str(files[i]))[..., ::-1]
            clean = S.render_view(sc, cam, poses[i])[0]
            raw, undone = _smoothed_errors(written, clean, gain, offset)
            assert undone < 1.5 and raw > 3 * undone, (out, i, raw, undone)
    # smooth: consecutive frames change the gain only a little, but the gain does change
    g = np.array(S.exposure_curve(S.draw_style(1), 300)[0])
    assert np.abs(np.diff(np.log(g), axis=0)).max() < 0.03 and np.ptp(np.log(g), axis=0).min() > 0.1
    assert np.ptp(g[:, 0] - g[:, 2]) > 0.02  # white balance: the channels differ


def test_apply_camera_effects():
    rng = np.random.default_rng(0)
    img = rng.integers(20, 200, (60, 80, 3)).astype(np.uint8)
    gain, offset = np.array([1.1, 0.9, 1.0]), np.array([3.0, -2.0, 0.0])
    plain = S.apply_camera_effects(img, gain, offset, np.zeros(2), 0.0, rng)
    ref = img.astype(np.float32) * gain.astype(np.float32) + offset.astype(np.float32)  # float32 arithmetic
    np.testing.assert_array_equal(plain, np.clip(np.round(ref), 0, 255).astype(np.uint8))
    flat = np.full((60, 80, 3), 100, np.uint8)
    noisy = S.apply_camera_effects(flat, np.ones(3), np.zeros(3), np.zeros(2), 2.0, rng).astype(np.float64)
    assert abs(noisy.std() - 2.0) < 0.1 and abs(noisy.mean() - 100) < 0.1
    # horizontal blur of vertical bars: columns mix, rows stay identical
    bars = np.zeros((60, 80, 3), np.uint8)
    bars[:, ::8] = 200
    blurred = S.apply_camera_effects(bars, np.ones(3), np.zeros(3), np.array([6.0, 0.0]), 0.0, rng).astype(np.float64)
    assert blurred[:, 4:-4].max() < 100 and abs(blurred.mean() - bars.mean()) < 1.0
    assert np.all(blurred == blurred[:1])


def test_dataset_reads_a_wide_scene(wide_dir):
    datasets = pytest.importorskip("fmapping.datasets")
    ds = datasets.open_dataset(wide_dir)
    assert ds.kind == "synthetic" and len(ds) == WIDE_FRAMES and ds.camera == S.camera_for_size(*WIDE_SIZE)
    assert {p.suffix for p in (wide_dir / "rgb").iterdir()} == {".jpg"}
    sc = S.make_scene(WIDE_SEED, "wide")
    poses = S.make_trajectory(sc, WIDE_FRAMES, WIDE_SEED)
    for i in (0, WIDE_FRAMES - 1):
        fr = ds[i]
        assert fr.rgb.shape == (WIDE_SIZE[1], WIDE_SIZE[0], 3)
        np.testing.assert_allclose(fr.c2w, poses[i], atol=1e-8)
        depth = S.render_view(sc, ds.camera, poses[i], supersample=1)[1]
        assert np.abs(fr.depth - depth).max() <= 0.5 / 5000 + 1e-6


def test_cli_synth_variety(tmp_path, capsys):
    from fmapping.cli import main

    assert main(["synth", "--out", str(tmp_path), "--seed", "3", "--frames", "2", "--size", "24x16",
                 "--variety", "wide"]) == 0
    assert json.loads(capsys.readouterr().out)["variety"] == "wide"
    assert json.loads((tmp_path / "scene.json").read_text())["variety"]["name"] == "wide"
    with pytest.raises(SystemExit):
        main(["synth", "--out", str(tmp_path), "--variety", "narrow"])


def test_wide_is_deterministic(tmp_path):
    for name in ("a", "b"):  # seed 0 has noise, blur and JPEG frames
        S.generate_scene(tmp_path / name, seed=0, frames=3, size=(40, 30), max_cloud_points=5_000, variety="wide")
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert any(p.suffix == ".jpg" for p in files)
    for p in files:
        assert (tmp_path / "a" / p).read_bytes() == (tmp_path / "b" / p).read_bytes(), p
