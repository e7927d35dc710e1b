import cv2
import numpy as np
import pytest
import torch

from fmapping import geometry as g
from fmapping.camera import PinholeCamera, sample_image

CAM = PinholeCamera(fx=250.0, fy=240.0, cx=159.5, cy=119.5, width=320, height=240)


def test_unproject_project_roundtrip():
    uv = torch.rand(100, 2, dtype=torch.float64) * torch.tensor([320.0, 240.0], dtype=torch.float64)
    depth = torch.rand(100, dtype=torch.float64) * 5 + 0.1
    pts = CAM.unproject(uv, depth)
    torch.testing.assert_close(pts[:, 2], depth)
    uv2, z = CAM.project(pts)
    torch.testing.assert_close(uv2, uv)
    torch.testing.assert_close(z, depth)


def test_rays_in_world_match_transformed_points():
    c2w = g.se3_exp(torch.tensor([0.3, -0.2, 1.0, 0.1, 0.5, -0.3], dtype=torch.float64))
    uv = CAM.pixel_grid(dtype=torch.float64)[::97]
    depth = torch.linspace(0.5, 4.0, len(uv), dtype=torch.float64)
    o, d = CAM.rays(c2w, uv)
    world = o + d * depth[:, None]  # t is camera depth because directions are z-normalised
    expected = g.transform_points(c2w, CAM.unproject(uv, depth))
    torch.testing.assert_close(world, expected)
    # the same with one pose per ray
    o2, d2 = CAM.rays(c2w.expand(len(uv), 4, 4), uv)
    torch.testing.assert_close(o2 + d2 * depth[:, None], expected)


def test_projection_matches_opencv():
    pts = np.random.default_rng(0).uniform([-1, -1, 1], [1, 1, 4], (50, 3))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), CAM.K, None)
    uv, _ = CAM.project(torch.from_numpy(pts))
    np.testing.assert_allclose(uv.numpy(), ref[:, 0], atol=1e-9)


def test_resized_keeps_rays_of_pixel_corners():
    half = CAM.scaled(0.5)
    assert (half.width, half.height) == (160, 120)
    # the top-left corner of the image (-0.5, -0.5) maps to the same ray at both resolutions
    a = CAM.unproject(torch.tensor([[-0.5, -0.5], [319.5, 239.5]], dtype=torch.float64))
    b = half.unproject(torch.tensor([[-0.5, -0.5], [159.5, 119.5]], dtype=torch.float64))
    torch.testing.assert_close(a, b)


def test_undistort_inverts_opencv_distortion():
    cam = PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
    # a point seen through the distorted lens lands, after undistortion, on its pinhole projection
    img = np.zeros((480, 640), np.float32)
    p = np.array([[0.2, -0.1, 1.0]])
    dist_px, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, np.asarray(cam.dist))
    u, v = np.round(dist_px[0, 0]).astype(int)
    img[v - 2:v + 3, u - 2:u + 3] = 1.0
    und = cam.undistort_image(img, interpolation=cv2.INTER_LINEAR)
    ys, xs = np.nonzero(und > 0.5)
    pin, _ = cam.undistorted().project(torch.from_numpy(p))
    assert abs(xs.mean() - pin[0, 0].item()) < 1.5 and abs(ys.mean() - pin[0, 1].item()) < 1.5
    assert cam.undistorted().dist is None


def test_sample_image_at_pixel_centres_is_exact():
    img = torch.rand(24, 32, 3, dtype=torch.float64)
    vs, us = torch.meshgrid(torch.arange(24), torch.arange(32), indexing="ij")
    uv = torch.stack([us.reshape(-1), vs.reshape(-1)], -1).double()
    torch.testing.assert_close(sample_image(img, uv), img.reshape(-1, 3))
    # half-way between two pixels is their mean
    mid = sample_image(img, torch.tensor([[3.5, 7.0]], dtype=torch.float64))
    torch.testing.assert_close(mid[0], (img[7, 3] + img[7, 4]) / 2)


@pytest.mark.parametrize("text,match", [
    ("1,2,3", "4, 8 or 9"),
    ("a,b,c,d", "numbers"),
    ("-5,500,160,120", "positive"),
    ("500,500,5000,120", "principal point"),
    ("nan,500,160,120", "finite"),
])
def test_bad_intrinsics_are_named(text, match):
    with pytest.raises(ValueError, match=match):
        PinholeCamera.from_string(text, 320, 240)


def test_from_string_with_distortion_and_dict_roundtrip():
    cam = PinholeCamera.from_string("517.3,516.5,318.6,255.3,0.26,-0.95,-0.005,0.003,1.16", 640, 480)
    assert cam.dist == (0.26, -0.95, -0.005, 0.003, 1.16)
    assert PinholeCamera.from_dict(cam.to_dict()) == cam
