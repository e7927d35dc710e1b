"""Export of point clouds and meshes from an analytic field with known geometry."""
from typing import Optional

import numpy as np
import pytest
import torch
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.export import (VoxelAccumulator, export_mesh, export_point_cloud, field_opacity_grid,
                             voxel_downsample)
from fmapping.field import EMPTY_RAW, FieldConfig
from fmapping.field.base import Field


@pytest.fixture(autouse=True)
def _one_thread():
    """Small workloads: one thread is faster and steadier on a shared CPU."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)

CAM = PinholeCamera(60.0, 60.0, 31.5, 23.5, 64, 48)
AABB = torch.tensor([[-3.0, -3.0, -0.5], [3.0, 3.0, 3.0]])


class SlabField(Field):
    """Opaque slabs |z - z0| < h (x, y inside given ranges), constant colour per slab; a cube floater optional."""

    def __init__(self, slabs, floater: Optional[tuple] = None):
        super().__init__(FieldConfig(), AABB)
        self.slabs = slabs  # list of (z0, h, (xmin, xmax), (ymin, ymax), rgb)
        self.floater = floater  # (centre (3,), half size, rgb)

    def _which(self, xyz: Tensor) -> Tensor:
        idx = torch.full(xyz.shape[:1], -1, dtype=torch.long)
        for k, (z0, h, xr, yr, _) in enumerate(self.slabs):
            inside = ((xyz[:, 2] - z0).abs() < h) & (xyz[:, 0] > xr[0]) & (xyz[:, 0] < xr[1]) \
                & (xyz[:, 1] > yr[0]) & (xyz[:, 1] < yr[1])
            idx[inside] = k
        if self.floater is not None:
            c, hs, _ = self.floater
            inside = ((xyz - torch.tensor(c, dtype=xyz.dtype)).abs() < hs).all(-1)
            idx[inside] = len(self.slabs)
        return idx

    def density_raw(self, xyz):
        return torch.where(self._which(xyz) >= 0, torch.full(xyz.shape[:1], 400.0),
                           torch.full(xyz.shape[:1], EMPTY_RAW))

    def color(self, xyz, viewdirs=None):
        cols = [s[4] for s in self.slabs] + ([self.floater[2]] if self.floater else []) + [(0.0, 0.0, 0.0)]
        table = torch.tensor(cols, dtype=torch.float32)
        return table[self._which(xyz)]

    def grid_parameters(self):
        return []

    def decoder_parameters(self):
        return []


def look_forward(x, y=0.0):
    p = np.eye(4)
    p[:3, 3] = [x, y, 0.0]
    return p


def test_voxel_downsample_averages_per_voxel():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [0.11, 0.0, 0.0], [0.5, 0.5, 0.5]])
    cols = np.array([[0, 0, 0], [100, 100, 100], [10, 20, 30], [1, 2, 3]], np.uint8)
    p, c = voxel_downsample(pts, cols, 0.05)
    assert len(p) == 3
    i = np.argmin(np.linalg.norm(p - [0.02, 0.01, 0.01], axis=1))
    np.testing.assert_allclose(p[i], [0.02, 0.01, 0.01])
    np.testing.assert_allclose(c[i], [50, 50, 50])
    p2, _ = voxel_downsample(pts, cols, 0.0)
    assert len(p2) == 4


def test_point_cloud_lies_on_the_surface_and_drops_floaters():
    wall = (2.0, 0.05, (-3, 3), (-3, 3), (0.9, 0.1, 0.1))
    # a floater in front of camera 0 only: outside the view of the cameras at x >= 0.4
    field = SlabField([wall], floater=((-0.45, 0.0, 0.6), 0.05, (0.1, 0.9, 0.1)))
    poses = [look_forward(-0.4), look_forward(0.4), look_forward(0.8)]
    kw = dict(stride=1, voxel=0.02, near=0.1, far=5.0, n_samples=48, n_importance=16)
    pts, cols = export_point_cloud(field, poses, CAM, min_consistent=1, **kw)
    assert len(pts) > 500
    assert np.abs(pts[:, 2] - 1.95).max() < 0.03  # the front face of the slab
    assert (cols[:, 0] > 200).all() and (cols[:, 1] < 50).all()
    raw, _ = export_point_cloud(field, poses, CAM, min_consistent=0, **kw)
    assert (raw[:, 2] < 1.0).sum() > 5  # without the multi-view test the floater is exported
    assert (pts[:, 2] < 1.0).sum() == 0  # with it, it is gone


def test_point_cloud_low_opacity_dropped():
    field = SlabField([(2.0, 0.02, (-3, 3), (-3, 3), (0.5, 0.5, 0.5))])
    field.density_raw = lambda xyz: torch.where(field._which(xyz) >= 0, torch.full(xyz.shape[:1], 10.0),
                                                torch.full(xyz.shape[:1], EMPTY_RAW))  # sigma ~0.7/m: faint
    pts, _ = export_point_cloud(field, [look_forward(0.0), look_forward(0.3)], CAM, stride=2, min_acc=0.5)
    assert len(pts) == 0


def test_opacity_grid_and_mesh_culled_to_views():
    seen = (2.0, 0.1, (-1.5, 1.5), (-1.5, 1.5), (0.2, 0.2, 0.8))
    hidden = (2.0, 0.1, (2.2, 2.9), (-1.0, 1.0), (0.8, 0.8, 0.2))  # right of every frustum at z = 2
    field = SlabField([seen, hidden])
    alpha, origin, spacing = field_opacity_grid(field, AABB, 61)
    assert alpha.shape == (61, 61, 61) and alpha.max() > 0.99 and alpha.min() < 1e-6
    np.testing.assert_allclose(origin, AABB[0].numpy())
    poses = [look_forward(-0.2), look_forward(0.2)]
    v, f, c = export_mesh(field, AABB, 61, poses, CAM, level=0.5, near=0.1, far=5.0)
    assert len(f) > 20 and f.max() < len(v)
    assert np.abs(np.abs(v[:, 2] - 2.0) - 0.1).max() < 0.1  # on the slab faces (cell 0.1 m)
    assert (v[:, 0] < 2.0).all()  # the hidden slab is culled
    assert (c[:, 2] > 150).all()
    # with a depth render the back face (behind the front face) is culled too
    def render(c2w, cam):
        d = np.full((cam.height, cam.width), 1.9)
        return {"depth": d, "acc": np.ones_like(d)}
    v2, f2, _ = export_mesh(field, AABB, 61, poses, CAM, level=0.5, near=0.1, far=5.0, render=render)
    assert len(f2) > 0 and v2[:, 2].max() < 2.05


class ViewSlabField(SlabField):
    """A slab whose colour depends only on the view direction: red = 0.5 + 0.5 x (its x component)."""

    def __init__(self, slabs):
        super().__init__(slabs)
        self.cfg = FieldConfig(view_dependent=True).validate()

    def color(self, xyz, viewdirs=None):
        if viewdirs is None:
            raise ValueError("view dependent: needs viewdirs")
        v = viewdirs.to(torch.float32)
        return torch.stack([0.5 + 0.5 * v[:, 0], torch.full_like(v[:, 0], 0.5), torch.full_like(v[:, 0], 0.5)], -1)


def test_mesh_of_a_view_dependent_field_is_coloured_as_seen_from_the_nearest_camera():
    field = ViewSlabField([(2.0, 0.1, (-1.5, 1.5), (-1.5, 1.5), None)])
    poses = [look_forward(-1.0), look_forward(1.0)]
    v, f, c = export_mesh(field, AABB, 61, poses, CAM, level=0.5, near=0.1, far=5.0)
    assert len(f) > 20
    centres = np.array([p[:3, 3] for p in poses])
    nearest = centres[np.argmin(np.linalg.norm(v[:, None] - centres[None], axis=2), 1)]
    d = (v - nearest) / np.linalg.norm(v - nearest, axis=1, keepdims=True)
    np.testing.assert_allclose(c[:, 0], np.round(255 * (0.5 + 0.5 * d[:, 0])), atol=1)
    assert c[:, 0].min() < 110 and c[:, 0].max() > 145  # both sides of each camera


def test_exports_stop_between_views_when_asked():
    """``should_stop`` is asked once before each view: the export stops after as many views as
    it allowed (counted by the renders made), and runs to the same result when it never fires."""
    from fmapping.cancel import Cancelled

    field = SlabField([(2.0, 0.1, (-3, 3), (-3, 3), (0.5, 0.5, 0.5))])
    poses = [look_forward(x) for x in (-0.4, 0.0, 0.4, 0.8)]
    renders = []

    def render(c2w, cam):
        renders.append(1)
        d = np.full((cam.height, cam.width), 1.9)
        return {"depth": d, "acc": np.ones_like(d)}

    asked = []
    with pytest.raises(Cancelled, match="mesh export"):
        export_mesh(field, AABB, 41, poses, CAM, render=render, should_stop=lambda: asked.append(1) or len(asked) > 2)
    assert len(renders) == 2
    v, f, _ = export_mesh(field, AABB, 41, poses, CAM, render=render, should_stop=lambda: False)
    v0, f0, _ = export_mesh(field, AABB, 41, poses, CAM, render=render)
    np.testing.assert_array_equal(f, f0)
    asked.clear()
    with pytest.raises(Cancelled, match="point cloud export"):
        export_point_cloud(field, poses, CAM, stride=4, should_stop=lambda: asked.append(1) or len(asked) > 3)
    assert len(asked) == 4
    p, _ = export_point_cloud(field, poses, CAM, stride=4, should_stop=lambda: False)
    p0, _ = export_point_cloud(field, poses, CAM, stride=4)
    np.testing.assert_array_equal(p, p0)


# ----------------------------------------------------------------- fast export path vs the reference renderers
def _structured_cp_field(resolution: int = 32):
    """A CP field with a dense wall at z ~ 2 and a small cube at (-0.45, 0, 0.6), random low-density noise elsewhere."""
    from fmapping.field import CPField

    cfg = FieldConfig(kind="cp", resolution=resolution, density_components=4, appearance_components=6,
                      app_features=8, hidden=16, seed=3)
    field = CPField(cfg, AABB)
    axes = [torch.linspace(float(AABB[0, a]), float(AABB[1, a]), resolution) for a in range(3)]
    with torch.no_grad():
        lines = field.density_lines  # (3, C, R, 1)
        lines[:, 0, :, 0] = 1.0
        lines[2, 0, :, 0] = 30.0 * torch.exp(-((axes[2] - 2.0) / 0.12) ** 2)  # the wall
        for a, c in enumerate((-0.45, 0.0, 0.6)):  # the cube: a product of three bumps
            lines[a, 1, :, 0] = 3.2 * torch.exp(-((axes[a] - c) / 0.15) ** 2)
    return field


def test_node_table_off_the_fields_own_nodes_is_the_field_at_each_node():
    """The node table at a resolution that is not the field's own (made slab by slab, in small chunks) against
    the field evaluated at an explicit meshgrid of the nodes."""
    from fmapping.export import _node_raw
    from fmapping.field import build_field

    field = build_field(FieldConfig(kind="cp", resolution=17, init_scale=1.0), AABB)
    box = np.asarray(AABB, np.float64) * 0.8
    r = 13
    axes = [np.linspace(box[0, a], box[1, a], r) for a in range(3)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pts = torch.as_tensor(np.stack([gx.ravel(), gy.ravel(), gz.ravel()], -1), dtype=torch.float32)
    ref = field.density_raw(pts).detach().numpy().reshape(r, r, r)
    for chunk in (1, 400, 10 ** 6):  # one slab per call (chunk < r * r), several, all
        np.testing.assert_allclose(_node_raw(field, box, r, chunk=chunk), ref, rtol=1e-5, atol=1e-6)


def test_node_density_equals_the_field_for_multilinear_fields():
    from fmapping.export import node_density
    from fmapping.field import build_field

    g = torch.Generator().manual_seed(0)
    o = torch.randn(300, 3, generator=g) * 0.5 + torch.tensor([0.0, 0.0, 1.0])
    d = torch.randn(300, 3, generator=g)
    t = torch.rand(300, 20, generator=g).sort(-1).values * 6.0  # many samples leave the box
    xyz = o[:, None] + t[..., None] * d[:, None]
    for kind, extra in (("cp", {}), ("vm", {}), ("grid", {"grid_resolution": 12})):
        field = build_field(FieldConfig(kind=kind, resolution=17, init_scale=1.0, **extra), AABB)
        nd = node_density(field)
        assert nd is not None, kind
        ref = field.density_raw(xyz.reshape(-1, 3)).view(300, 20).detach()
        torch.testing.assert_close(nd.raw_rays(o, d, t), ref, rtol=1e-4, atol=1e-4, msg=kind)
    assert node_density(build_field(FieldConfig(kind="mlp", mlp_layers=1, mlp_width=8), AABB)) is None
    assert node_density(SlabField([])) is None


@pytest.mark.parametrize("use_nodes", [True, False])
def test_render_view_matches_render_image(use_nodes):
    from fmapping.export import node_density, render_view
    from fmapping.render import render_image

    field = _structured_cp_field()
    nd = node_density(field) if use_nodes else None
    for pose in (look_forward(-0.4), look_forward(0.6, 0.3)):
        ref = render_image(field, CAM, pose, 0.1, 5.0, 32, n_importance=16)
        out = render_view(field, CAM, pose, 0.1, 5.0, 32, 16, node=nd)
        acc = ref["acc"].numpy()
        assert (acc > 0.9).mean() > 0.8  # the wall fills most of the view
        np.testing.assert_allclose(out["acc"], acc, atol=1e-4)
        hit = acc > 0.5
        np.testing.assert_allclose(out["depth"][hit], ref["depth_normalized"].numpy()[hit], atol=1e-3)
        np.testing.assert_allclose(out["rgb"], ref["rgb"].clamp(0, 1).numpy(), atol=1e-4)
        # colour from the 4 largest weights (renormalised), only on opaque rays
        top = render_view(field, CAM, pose, 0.1, 5.0, 32, 16, node=nd, color_samples=4, color_min_acc=0.9)
        opaque = acc >= 0.9
        assert np.abs(top["rgb"][opaque] - out["rgb"][opaque]).mean() < 2 / 255
        assert (top["rgb"][~opaque] == 0).all()


def test_fast_export_matches_the_reference_export():
    from scipy.spatial import cKDTree

    field = _structured_cp_field()
    poses = [look_forward(-0.4), look_forward(0.4), look_forward(0.8)]
    kw = dict(stride=1, voxel=0.02, near=0.1, far=5.0, n_samples=32, n_importance=16)
    p_ref, c_ref = export_point_cloud(field, poses, CAM, fast=False, **kw)
    p_new, c_new = export_point_cloud(field, poses, CAM, **kw)
    assert len(p_ref) > 500
    assert abs(len(p_new) - len(p_ref)) <= 0.002 * len(p_ref)
    d1, i1 = cKDTree(p_ref).query(p_new)
    d2, _ = cKDTree(p_new).query(p_ref)
    assert np.median(d1) < 1e-6 and max(np.quantile(d1, 0.99), np.quantile(d2, 0.99)) < 1e-3
    assert np.abs(c_new.astype(float) - c_ref[i1]).mean() < 2.0
    # the cube in front of camera 0 only is dropped by both (multi-view test)
    assert (p_ref[:, 2] < 1.0).sum() == 0 and (p_new[:, 2] < 1.0).sum() == 0


def test_fast_export_of_a_mapper_matches_its_renderer():
    from fmapping.mapping import Mapper, MapperConfig

    cfg = MapperConfig()
    cfg.field.resolution = 32
    cfg.field.density_components, cfg.field.appearance_components = 4, 6
    cfg.field.app_features, cfg.field.hidden = 8, 16
    m = Mapper(cfg, CAM, aabb=AABB.numpy())
    m._build()  # a field without training; its parameters are set below
    m.field.load_state_dict(_structured_cp_field().state_dict())
    poses = {i: look_forward(x) for i, x in enumerate((-0.4, 0.4, 0.8))}
    kw = dict(stride=2, voxel=0.02, near=cfg.near, far=cfg.far, n_samples=32, n_importance=16)
    p_ref, c_ref = export_point_cloud(m, poses, CAM, fast=False, **kw)
    p_new, c_new = export_point_cloud(m, poses, CAM, **kw)
    assert len(p_ref) > 100 and abs(len(p_new) - len(p_ref)) <= 0.01 * len(p_ref)
    from scipy.spatial import cKDTree
    d, i = cKDTree(p_ref).query(p_new)
    assert np.quantile(d, 0.99) < 1e-3
    assert np.abs(c_new.astype(float) - c_ref[i]).mean() < 2.0


def test_voxel_downsample_matches_a_slow_reference():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(5000, 3)) * [1.0, 0.5, 0.2] - [3.0, 0.0, 1.0]  # negative coordinates too
    cols = rng.integers(0, 256, (5000, 3)).astype(np.uint8)
    p, c = voxel_downsample(pts, cols, 0.1)
    keys = np.floor(pts / 0.1).astype(np.int64)
    uniq = sorted(set(map(tuple, keys)))  # lexicographic (x, y, z), as documented
    assert len(p) == len(uniq)
    for n in (0, len(uniq) // 2, len(uniq) - 1):
        m = (keys == uniq[n]).all(1)
        np.testing.assert_allclose(p[n], pts[m].mean(0), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(c[n], cols[m].mean(0), rtol=1e-12)


def test_voxel_accumulator_fed_in_parts_matches_all_points_at_once():
    """The export's grid, reduced every 700 points over 12 parts, against the slow per-voxel reference: the
    same voxels in the same order, their means, and the tag of each voxel's first point in the order added."""
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(6000, 3)) * [1.0, 0.5, 0.2] - [3.0, 0.0, 1.0]
    cols = rng.integers(0, 256, (6000, 3)).astype(np.float64)
    order = np.arange(6000)
    acc = VoxelAccumulator(0.1, reduce_at=700)
    for part in np.array_split(order, 12):
        acc.add(pts[part], values=cols[part], tags=order[part, None])
    p, c, counts, tags = acc.result()
    keys = np.floor(pts / 0.1).astype(np.int64)
    uniq = sorted(set(map(tuple, keys)))
    assert len(p) == len(uniq) and counts.sum() == 6000
    for n in range(0, len(uniq), max(1, len(uniq) // 50)):
        m = (keys == uniq[n]).all(1)
        np.testing.assert_allclose(p[n], pts[m].mean(0), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(c[n], cols[m].mean(0), rtol=1e-12)
        assert counts[n] == m.sum() and tags[n, 0] == np.flatnonzero(m)[0]
    p1, c1 = voxel_downsample(pts, cols, 0.1)
    np.testing.assert_allclose(p, p1, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(c, c1, rtol=1e-12)
    with pytest.raises(ValueError, match="voxel"):
        VoxelAccumulator(0.0)
