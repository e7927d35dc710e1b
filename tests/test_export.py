"""Export of point clouds and meshes from an analytic field with known geometry."""
from typing import Optional

import numpy as np
import pytest
import torch
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.export import export_mesh, export_point_cloud, field_opacity_grid, voxel_downsample
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
        return torch.where(self._which(xyz) >= 0, torch.full(xyz.shape[:1], 400.0), torch.full(xyz.shape[:1], EMPTY_RAW))

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
