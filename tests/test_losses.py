"""Losses against analytic cases: a textured plane z = 2 seen by two cameras."""

import math

import pytest
import torch

from fmapping.camera import PinholeCamera
from fmapping.geometry import make_pose
from fmapping.losses import (
    depth_l1_loss, distortion_loss, expected_depth_l1, gaussian_blur, patch_offsets,
    photometric_loss, project_patches,
    sample_consistency_cost, sample_frames, sample_views, view_angle_mask, warping_loss,
)

CAM = PinholeCamera(80.0, 80.0, 39.5, 29.5, 80, 60)
PLANE_Z = 2.0


def texture(x, y):
    """Smooth colour texture on the plane (world x, y in metres) -> (..., 3) in [0, 1]."""
    return torch.stack([
        0.5 + 0.4 * torch.sin(9.0 * x + 1.0),
        0.5 + 0.4 * torch.cos(7.0 * y - 0.5),
        0.5 + 0.3 * torch.sin(5.0 * x + 6.0 * y),
    ], -1)


def render_plane(c2w):
    """Analytic image of the plane for a camera with optical axis +z (no rotation about x/y)."""
    uv = CAM.pixel_grid(dtype=torch.float64)
    o, d = CAM.rays(c2w, uv)
    t = (PLANE_Z - o[:, 2]) / d[:, 2]
    p = o + d * t[:, None]
    return texture(p[:, 0], p[:, 1]).reshape(CAM.height, CAM.width, 3).float(), t.reshape(CAM.height, CAM.width)


def setup_two_views():
    eye = torch.eye(3, dtype=torch.float64)
    c2w = torch.stack([
        make_pose(eye, torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)),
        make_pose(eye, torch.tensor([0.3, 0.05, 0.0], dtype=torch.float64)),
    ])
    imgs = torch.stack([render_plane(c)[0] for c in c2w])
    return imgs, c2w.float()


def rays_for(c2w, uv):
    return CAM.rays(c2w, uv)


def test_photometric_l2_huber_values():
    pred = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    tgt = torch.tensor([[0.5, 0.5, 0.5], [1.0, 1.0, 0.95]])
    # l2: mean over rays of mean over channels: (0.25 + 0.0025/3)/2
    assert photometric_loss(pred, tgt).item() == pytest.approx((0.25 + 0.0025 / 3) / 2)
    # huber(delta=0.1): |e|=0.5 -> 0.1*(0.5-0.05)=0.045 ; |e|=0.05 -> 0.5*0.0025=0.00125
    assert photometric_loss(pred, tgt, "huber", delta=0.1).item() == pytest.approx((0.045 + 0.00125 / 3) / 2)
    w = torch.tensor([1.0, 0.0])
    assert photometric_loss(pred, tgt, weight=w).item() == pytest.approx(0.25)
    with pytest.raises(ValueError):
        photometric_loss(pred, tgt, "l3")


def test_depth_l1_ignores_invalid():
    pred = torch.tensor([1.0, 2.0, 3.0, 4.0])
    tgt = torch.tensor([1.5, 0.0, float("nan"), 3.0])
    assert depth_l1_loss(pred, tgt).item() == pytest.approx(0.75)


def test_expected_depth_l1_values_and_gradient():
    t = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    w = torch.tensor([[0.0, 1.0, 0.0], [0.5, 0.0, 0.25], [0.0, 0.0, 0.0]], requires_grad=True)
    acc = w.sum(-1)
    far = torch.tensor([4.0, 4.0, 4.0])
    z = torch.tensor([2.0, 2.0, 0.0])  # third ray has no valid depth
    loss = expected_depth_l1(w, t, acc, far, z)
    # ray 0: all mass at z -> 0; ray 1: 0.5*1 + 0.25*1 + 0.25*|4-2| = 1.25
    assert loss.item() == pytest.approx((0.0 + 1.25) / 2)
    loss.backward()
    # mass at the target depth is cheaper than unreached mass; mass far from it is dearer
    # d/dw_i = (|t_i - z| - |far - z|) / n_valid_rays
    torch.testing.assert_close(w.grad[1], torch.tensor([-0.5, -1.0, -0.5]))
    assert w.grad[0, 1] < w.grad[0, 0] and w.grad[2].abs().sum() == 0


def test_sample_views_matches_integer_pixels_and_patch():
    img = torch.rand(2, 5, 7, 3)
    uv = torch.tensor([[[3.0, 2.0], [0.0, 4.0]], [[6.0, 0.0], [1.0, 1.0]]])
    out = sample_views(img, uv)
    torch.testing.assert_close(out[0, 0], img[0, 2, 3])
    torch.testing.assert_close(out[1, 0], img[1, 0, 6])
    # halfway between two pixels is their mean
    mid = sample_views(img[:1], torch.tensor([[[2.5, 1.0]]]))[0, 0]
    torch.testing.assert_close(mid, (img[0, 1, 2] + img[0, 1, 3]) / 2)
    off = patch_offsets(1)
    assert off.shape == (9, 2) and off.abs().max() == 1
    got = sample_frames(img, torch.tensor([1, 0]), torch.tensor([[2.0, 3.0], [4.0, 1.0]])[:, None] + off)
    torch.testing.assert_close(got[0, 4], img[1, 3, 2])
    torch.testing.assert_close(got[1, 0], img[0, 0, 3])


def _center_rays(c2w, n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    # pixels of view 0 that are seen by view 1 (right part, away from the border)
    u = torch.randint(35, 74, (n,), generator=g).float()
    v = torch.randint(5, 50, (n,), generator=g).float()
    uv = torch.stack([u, v], -1)
    o, d = rays_for(c2w[0], uv)
    return uv, o, d


def test_warping_loss_zero_at_true_depth_and_positive_when_off():
    imgs, c2w = setup_two_views()
    uv, o, d = _center_rays(c2w)
    src = torch.zeros(len(uv), dtype=torch.long)
    true = torch.full((len(uv),), PLANE_Z)
    r0 = warping_loss(o, d, true, uv, src, imgs, c2w, CAM)
    assert r0.valid_rays.all()
    assert r0.loss.item() < 0.01  # only bilinear interpolation error of a smooth texture
    r1 = warping_loss(o, d, true * 1.15, uv, src, imgs, c2w, CAM)
    assert r1.loss.item() > 5 * r0.loss.item() and r1.loss.item() > 0.03
    r2 = warping_loss(o, d, true * 0.85, uv, src, imgs, c2w, CAM)
    assert r2.loss.item() > 5 * r0.loss.item()


def test_warping_loss_gradient_points_to_true_depth():
    imgs, c2w = setup_two_views()
    uv, o, d = _center_rays(c2w, n=300, seed=1)
    src = torch.zeros(len(uv), dtype=torch.long)
    for factor, sign in ((1.04, 1.0), (0.96, -1.0)):
        depth = torch.full((len(uv),), PLANE_Z * factor, requires_grad=True)
        res = warping_loss(o, d, depth, uv, src, imgs, c2w, CAM)
        res.loss.backward()
        g = depth.grad[res.valid_rays]
        # descent moves most depths toward the plane
        assert (torch.sign(g) == sign).float().mean() > 0.7
    # one gradient-descent step reduces the loss
    depth = torch.full((len(uv),), PLANE_Z * 1.04, requires_grad=True)
    res = warping_loss(o, d, depth, uv, src, imgs, c2w, CAM)
    res.loss.backward()
    with torch.no_grad():
        step = depth - 0.02 / depth.grad.abs().max() * depth.grad
    assert warping_loss(o, d, step, uv, src, imgs, c2w, CAM).loss < res.loss


def test_warping_loss_gradient_reaches_poses():
    imgs, c2w = setup_two_views()
    uv, _, _ = _center_rays(c2w)
    c2w = c2w.clone().requires_grad_(True)
    o, d = CAM.rays(c2w[0], uv)
    src = torch.zeros(len(uv), dtype=torch.long)
    res = warping_loss(o, d, torch.full((len(uv),), PLANE_Z * 1.05), uv, src, imgs, c2w, CAM)
    res.loss.backward()
    assert torch.isfinite(c2w.grad).all() and c2w.grad[1].abs().sum() > 0


def test_warping_loss_masks_out_of_view_and_self():
    imgs, c2w = setup_two_views()
    # left border pixels of view 0 project left of view 1's image (it sits 0.3 m to the right)
    uv = torch.tensor([[2.0, 30.0], [5.0, 10.0], [60.0, 30.0]])
    o, d = rays_for(c2w[0], uv)
    src = torch.zeros(3, dtype=torch.long)
    res = warping_loss(o, d, torch.full((3,), PLANE_Z), uv, src, imgs, c2w, CAM)
    assert res.mask[:, 0].sum() == 0  # a ray never compares with its own frame
    assert res.valid_rays.tolist() == [False, False, True]
    assert res.per_ray[0] == 0 and torch.isinf(res.errors[0, 1])
    # behind the camera: negative depth gives no valid view
    res = warping_loss(o, d, torch.full((3,), -1.0), uv, src, imgs, c2w, CAM)
    assert not res.valid_rays.any()
    # occlusion test: view 1 "sees" a surface at 1 m, so the point at 2 m is hidden
    vd = torch.full((2, CAM.height, CAM.width), 1.0)
    res = warping_loss(o, d, torch.full((3,), PLANE_Z), uv, src, imgs, c2w, CAM, view_depths=vd)
    assert not res.valid_rays.any()


def test_warping_loss_robust_keep_uses_best_views():
    imgs, c2w = setup_two_views()
    # a third view whose image is garbage (an occluder): keep=0.5 of 2 views uses the good one
    bad = torch.rand(1, CAM.height, CAM.width, 3, generator=torch.Generator().manual_seed(0))
    eye = torch.eye(3)
    c2w3 = torch.cat([c2w, make_pose(eye, torch.tensor([0.1, -0.05, 0.0]))[None]])
    imgs3 = torch.cat([imgs, bad])
    uv, o, d = _center_rays(c2w)
    src = torch.zeros(len(uv), dtype=torch.long)
    depth = torch.full((len(uv),), PLANE_Z)
    all_views = warping_loss(o, d, depth, uv, src, imgs3, c2w3, CAM, keep=1.0)
    best = warping_loss(o, d, depth, uv, src, imgs3, c2w3, CAM, keep=0.5)
    assert best.loss.item() < 0.01 < all_views.loss.item()


def test_view_angle_mask_against_the_angle_each_camera_sees_the_point_from():
    """A point at the origin on a ray along +z; cameras on a circle of 2 m around it in the x-z plane, placed
    so that the angle between their line of sight to the point and the ray is 0, 30, 44, 46, 90 and 180 deg."""
    angles = [0.0, 30.0, 44.0, 46.0, 90.0, 180.0]
    centres = torch.tensor([[-2 * math.sin(math.radians(a)), 0.0, -2 * math.cos(math.radians(a))] for a in angles])
    c2w = torch.eye(4).repeat(len(angles), 1, 1)
    c2w[:, :3, 3] = centres
    pts = torch.zeros(1, 3)
    got = view_angle_mask(pts, torch.tensor([[0.0, 0.0, 3.0]]), c2w, 45.0)
    assert got[:, 0].tolist() == [True, True, True, False, False, False]
    assert view_angle_mask(pts, torch.tensor([[0.0, 0.0, 1.0]]), c2w, 100.0)[:, 0].tolist() == [True] * 5 + [False]


def test_warping_loss_max_angle_leaves_out_a_view_from_far_around():
    """Two views of the plane as above and a third from 60 deg around the points whose image disagrees (an
    occluder seen from the side): with every view the loss at the true depth is large, with a 45-deg limit it
    is the two-view loss; the same for the per-sample cost."""
    imgs, c2w = setup_two_views()
    uv, o, d = _center_rays(c2w)
    src = torch.zeros(len(uv), dtype=torch.long)
    depth = torch.full((len(uv),), PLANE_Z)
    # a camera at 60 deg around the point (0, 0, 2), turned to look at it
    a = math.radians(60.0)
    centre = torch.tensor([2 * math.sin(a), 0.0, 2 - 2 * math.cos(a)])
    z = torch.tensor([0.0, 0.0, 2.0]) - centre
    z = z / z.norm()
    x = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), z)
    rot = torch.stack([x, torch.linalg.cross(z, x), z], 1)
    c2w3 = torch.cat([c2w, make_pose(rot, centre)[None]])
    bad = torch.rand(1, CAM.height, CAM.width, 3, generator=torch.Generator().manual_seed(0))
    imgs3 = torch.cat([imgs, bad])
    two = warping_loss(o, d, depth, uv, src, imgs, c2w, CAM, keep=1.0)
    every = warping_loss(o, d, depth, uv, src, imgs3, c2w3, CAM, keep=1.0)
    limited = warping_loss(o, d, depth, uv, src, imgs3, c2w3, CAM, keep=1.0, max_angle_deg=45.0)
    assert every.mask[:, 2].float().mean() > 0.5  # the side view does see most of the points
    assert not limited.mask[:, 2].any()
    assert two.loss.item() < 0.01 < every.loss.item()
    torch.testing.assert_close(limited.loss, two.loss)
    pts = (o + d * depth[:, None])[:, None]
    ref = sample_frames(imgs, src, uv[:, None] + patch_offsets(1))
    c_two, _ = sample_consistency_cost(pts, ref, src, imgs, c2w, CAM, keep=1.0)
    c_lim, n_lim = sample_consistency_cost(pts, ref, src, imgs3, c2w3, CAM, keep=1.0, ray_dirs=d, max_angle_deg=45.0)
    torch.testing.assert_close(c_lim, c_two)
    assert (n_lim == 1).all()


def test_losses_read_a_subset_of_views_in_place_as_they_read_it_copied():
    """The mapper hands the warping and consistency losses its whole window and the indices of the views to
    compare (``views``) instead of a copy of those images: the same losses, gradients and costs as the copy."""
    eye = torch.eye(3, dtype=torch.float64)
    centres = ([0.0, 0.0, 0.0], [0.3, 0.05, 0.0], [-0.2, 0.1, 0.05], [0.1, -0.15, -0.1])
    poses = torch.stack([make_pose(eye, torch.tensor(c, dtype=torch.float64)) for c in centres])
    stack = torch.stack([render_plane(c)[0] for c in poses])
    views = torch.tensor([3, 0, 1])  # the subset, in the mapper's random order; rays come from view 0 (index 1)
    c2w = poses[views].float().requires_grad_(True)
    c2w_copy = poses[views].float().requires_grad_(True)
    uv, o, d = _center_rays(poses.float(), n=200, seed=2)  # rays of pose 0
    src = torch.ones(len(uv), dtype=torch.long)
    depth = torch.full((len(uv),), PLANE_Z * 1.05, requires_grad=True)
    depth_copy = depth.detach().clone().requires_grad_(True)
    for ref in (None, sample_frames(stack, torch.zeros(len(uv), dtype=torch.long), uv[:, None] + patch_offsets(1))):
        a = warping_loss(o, d, depth, uv, src, stack, c2w, CAM, views=views, ref_colors=ref)
        b = warping_loss(o, d, depth_copy, uv, src, stack[views], c2w_copy, CAM, ref_colors=ref)
        assert a.valid_rays.float().mean() > 0.9
        torch.testing.assert_close(a.loss, b.loss)
        torch.testing.assert_close(a.errors, b.errors)
        a.loss.backward()
        b.loss.backward()
        torch.testing.assert_close(depth.grad, depth_copy.grad)
        torch.testing.assert_close(c2w.grad, c2w_copy.grad)
        assert depth.grad.abs().sum() > 0 and c2w.grad.abs().sum() > 0
    t = torch.linspace(1.0, 3.0, 21)
    pts = o[:, None] + d[:, None] * t[None, :, None]
    ref = sample_frames(stack, torch.zeros(len(uv), dtype=torch.long), uv[:, None] + patch_offsets(1))
    cost, nval = sample_consistency_cost(pts, ref, src, stack, c2w.detach(), CAM, views=views)
    cost_copy, nval_copy = sample_consistency_cost(pts, ref, src, stack[views], c2w.detach(), CAM)
    torch.testing.assert_close(cost, cost_copy)
    torch.testing.assert_close(nval, nval_copy)
    assert (nval[:, 10] == 2).float().mean() > 0.5  # both other views compared for most rays


def test_sample_consistency_cost_minimum_at_surface():
    imgs, c2w = setup_two_views()
    uv, o, d = _center_rays(c2w, n=100)
    src = torch.zeros(len(uv), dtype=torch.long)
    t = torch.linspace(1.0, 3.0, 41)
    pts = o[:, None] + d[:, None] * t[None, :, None]
    ref = sample_frames(imgs, src, uv[:, None] + patch_offsets(1))
    cost, nvalid = sample_consistency_cost(pts, ref, src, imgs, c2w, CAM)
    assert cost.shape == (100, 41)
    best_t = t[cost.argmin(-1)]
    assert ((best_t - PLANE_Z).abs() <= 0.1).float().mean() > 0.9
    assert (nvalid[:, 20] == 1).all()
    # with one other view the robust mean (keep < 1, sorted path) equals the plain mean (keep = 1)
    cost1, _ = sample_consistency_cost(pts, ref, src, imgs, c2w, CAM, keep=1.0)
    torch.testing.assert_close(cost1, cost)


def test_project_patches_pixels_depths_masks_and_patches_on_the_plane():
    """Points on the plane z = 2 and one behind both cameras; view 1 sits at (0.3, 0.05, 0), so a
    point (x, y, 2) lands at u = 39.5 + 40 (x - 0.3), v = 29.5 + 40 (y - 0.05) there."""
    imgs, c2w = setup_two_views()
    pts = torch.tensor([[0.1, -0.05, 2.0], [0.0, 0.0, -1.0], [1.2875, 0.0, 2.0]])
    src = torch.tensor([0, 1, 0])
    uv, z, mask, patches = project_patches(pts, src, imgs, c2w, CAM, radius=1, dilation=1.0)
    torch.testing.assert_close(uv[:, 0], torch.tensor([[43.5, 27.5], [31.5, 25.5]]))
    torch.testing.assert_close(uv[1, 2], torch.tensor([79.0, 27.5]))
    torch.testing.assert_close(z, torch.tensor([[2.0, -1.0, 2.0], [2.0, -1.0, 2.0]]))
    # own frame, behind the camera, and a patch reaching past the image border are masked
    assert mask.tolist() == [[False, False, False], [True, False, False]]
    assert project_patches(pts, src, imgs, c2w, CAM, radius=0)[2].tolist() == [[False, False, False],
                                                                                [True, False, True]]
    # the 3x3 patch of the first point in view 1 is the plane's texture one pixel (2/80 m) apart
    off = patch_offsets(1, 1.0, dtype=torch.float64) * (PLANE_Z / CAM.fx)
    want = texture(0.1 + off[:, 0], -0.05 + off[:, 1]).float()
    assert patches.shape == (2, 3, 9, 3)
    torch.testing.assert_close(patches[1, 0], want, atol=5e-3, rtol=0)


def _distortion_reference(w, t, tn, tf):
    """The double sum written out: sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 delta_i per ray."""
    vals = []
    for r in range(w.shape[0]):
        s = [(float(x) - float(tn[r])) / (float(tf[r]) - float(tn[r])) for x in t[r]]
        n = len(s)
        inter = sum(float(w[r, i]) * float(w[r, j]) * abs(s[i] - s[j]) for i in range(n) for j in range(n))
        delta = [s[i + 1] - s[i] for i in range(n - 1)] + [1.0 - s[-1]]
        intra = sum(float(w[r, i]) ** 2 * delta[i] for i in range(n)) / 3
        vals.append(inter + intra)
    return sum(vals) / len(vals)


def test_distortion_loss_matches_the_double_sum_and_its_gradient():
    g = torch.Generator().manual_seed(0)
    tn = torch.rand(5, generator=g, dtype=torch.float64) * 0.5 + 0.1
    tf = tn + 2 + torch.rand(5, generator=g, dtype=torch.float64)
    t = tn[:, None] + torch.sort(torch.rand(5, 12, generator=g, dtype=torch.float64), -1)[0] * (tf - tn)[:, None]
    w = torch.rand(5, 12, generator=g, dtype=torch.float64)
    w = (w / w.sum(-1, keepdim=True) * 0.9).requires_grad_(True)
    val = distortion_loss(w, t, tn, tf)
    torch.testing.assert_close(val.item(), _distortion_reference(w.detach(), t, tn, tf), rtol=1e-10, atol=1e-12)
    assert torch.autograd.gradcheck(lambda x: distortion_loss(x, t, tn, tf), (w,))


def test_distortion_loss_prefers_one_peak_to_a_spread():
    """The same opacity on one sample scores lower than spread over the ray (a fog / a sheet along it)."""
    t = torch.linspace(0.2, 4.0, 32, dtype=torch.float64)[None]
    tn, tf = torch.tensor([0.1], dtype=torch.float64), torch.tensor([4.1], dtype=torch.float64)
    peak = torch.zeros(1, 32, dtype=torch.float64)
    peak[0, 10] = 0.95
    spread = torch.full((1, 32), 0.95 / 32, dtype=torch.float64)
    two = torch.zeros(1, 32, dtype=torch.float64)
    two[0, 5], two[0, 25] = 0.475, 0.475
    lp, ls, l2 = (distortion_loss(w, t, tn, tf).item() for w in (peak, spread, two))
    assert lp < ls and lp < l2
    # two separated peaks: 2 * 0.475^2 * |s_5 - s_25| (+ the small intra terms)
    s = (t[0] - 0.1) / 4.0
    assert l2 > 2 * 0.475 ** 2 * float(s[25] - s[5])


def test_gaussian_blur_matches_the_explicit_weighted_sum():
    """The separable blur equals the 2-D sum of Gaussian-weighted neighbours (borders replicated), keeps a
    constant image, and sigma 0 is the identity."""
    import math

    gen = torch.Generator().manual_seed(0)
    imgs = torch.rand(2, 9, 11, 3, generator=gen, dtype=torch.float64)
    sigma = 1.3
    r = math.ceil(3 * sigma)
    ref = torch.zeros_like(imgs)
    norm = 0.0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            w = math.exp(-0.5 * (dx * dx + dy * dy) / sigma ** 2)
            ys = torch.arange(9).add(dy).clamp(0, 8)
            xs = torch.arange(11).add(dx).clamp(0, 10)
            ref += w * imgs[:, ys][:, :, xs]
            norm += w
    torch.testing.assert_close(gaussian_blur(imgs, sigma), ref / norm)
    flat = torch.full((1, 5, 6, 3), 0.4, dtype=torch.float64)
    torch.testing.assert_close(gaussian_blur(flat, 2.0), flat)
    assert gaussian_blur(imgs, 0.0) is imgs

