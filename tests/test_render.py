"""Volume rendering against analytic cases (homogeneous medium, opaque slab), colour
subsetting against colouring everywhere, occupancy mode, backgrounds, full images."""
import math

import numpy as np
import pytest
import torch

from fmapping.camera import PinholeCamera
from fmapping.field import EMPTY_RAW, Field, FieldConfig, build_field
from fmapping.render import composite, raw_to_alpha, render_image, render_rays, render_weights, sample_deltas

BOX = [[-3.0, -3.0, -1.0], [3.0, 3.0, 6.0]]


class AnalyticField(Field):
    """Field with closed-form density / colour, for renderer tests."""

    def __init__(self, raw_fn, rgb_fn=None, **cfg):
        super().__init__(FieldConfig(kind="cp", **cfg), BOX)
        self.raw_fn = raw_fn
        self.rgb_fn = rgb_fn or (lambda x: torch.stack([torch.sigmoid(x[:, 0]), torch.sigmoid(x[:, 1]),
                                                        torch.full_like(x[:, 0], 0.25)], -1))
        self.color_calls = 0

    def density_raw(self, xyz):
        return self.raw_fn(xyz.to(self.dtype))

    def color(self, xyz, viewdirs=None):
        self.color_calls += xyz.shape[0]
        return self.rgb_fn(xyz.to(self.dtype))


def _rays(n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    o = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 0.4
    o[:, 2] = 0.0
    d = torch.cat([(torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 0.8, torch.ones(n, 1, dtype=dtype)], -1)
    return o, d


def test_homogeneous_medium_matches_closed_form():
    sigma, near, far, s = 0.7, 0.5, 4.0, 64
    raw = math.log(math.expm1(sigma))  # softplus(raw) == sigma with shift 0
    field = AnalyticField(lambda x: torch.full_like(x[:, 0], raw), density_shift=0.0).double()
    o, d = _rays(8)
    step = (far - near) / s
    t = (near + step * torch.arange(s, dtype=torch.float64)).expand(8, s)  # bin starts
    out = render_rays(field, o, d, t, background=0.0)
    dn = d.norm(dim=-1)
    length = (far - near) * dn
    torch.testing.assert_close(out.acc, 1 - torch.exp(-sigma * length))
    # discrete closed form: w_i = q^i (1 - q), q = exp(-sigma * step * |d|)
    q = torch.exp(-sigma * step * dn)
    geo = q * (1 - s * q ** (s - 1) + (s - 1) * q ** s) / (1 - q) ** 2  # sum_i i q^i
    depth = (1 - q ** s) * near + step * (1 - q) * geo
    torch.testing.assert_close(out.depth, depth)
    # continuous closed form (within one sample spacing)
    k = sigma * dn
    lz = far - near
    cont = near * (1 - torch.exp(-k * lz)) + (1 - torch.exp(-k * lz)) / k - lz * torch.exp(-k * lz)
    assert (out.depth - cont).abs().max() < step
    # colour is the weighted mean of the sample colours
    xyz = o[:, None] + t[..., None] * d[:, None]
    c = field.rgb_fn(xyz.reshape(-1, 3)).view(8, s, 3)
    torch.testing.assert_close(out.rgb, (out.weights[..., None] * c).sum(1), atol=1e-4, rtol=0)


def test_last_delta_is_mean_spacing():
    t = torch.tensor([[1.0, 1.5, 2.5, 3.0]])
    torch.testing.assert_close(sample_deltas(t, torch.tensor([2.0])), torch.tensor([[1.0, 2.0, 1.0, 4.0 / 3.0]]))


def _slab_raw(z0, thick, value):
    def fn(x):
        inside = (x[:, 2] >= z0) & (x[:, 2] <= z0 + thick)
        return torch.where(inside, torch.full_like(x[:, 2], value), torch.full_like(x[:, 2], EMPTY_RAW))
    return fn


def test_opaque_slab_depth_and_weights():
    z0, near, far, s = 2.3, 0.5, 4.5, 200
    field = AnalyticField(_slab_raw(z0, 0.3, 1010.0))  # sigma = 1000 / m after the -10 shift
    o, d = _rays(16, dtype=torch.float32)
    o[:, :2] = 0.0
    step = (far - near) / s
    t = (near + step * (torch.arange(s) + 0.5)).expand(16, s)
    out = render_rays(field, o, d, t)
    assert (out.acc > 0.999).all()
    assert (out.depth - z0).abs().max() < step  # t is the camera depth
    first_inside = (t >= z0).float().argmax(-1)
    assert torch.equal(out.weights.argmax(-1), first_inside)
    assert (out.weights.max(-1).values > 0.99).all()


def _cp_slab_field(z0=2.0, dtype=torch.float64):
    """A real CP field whose density is an opaque slab z in [z0, z0 + 0.25] (component 0)."""
    cfg = FieldConfig(kind="cp", resolution=64, density_components=4, appearance_components=6, app_features=7,
                      hidden=8)
    f = build_field(cfg, BOX).to(dtype)
    zs = torch.linspace(BOX[0][2], BOX[1][2], 64, dtype=dtype)
    with torch.no_grad():
        f.density_lines.zero_()
        f.density_lines[0, 0] = 4.0
        f.density_lines[1, 0] = 4.0
        f.density_lines[2, 0, :, 0] = torch.where((zs >= z0) & (zs <= z0 + 0.25), 6.0, 0.0)  # raw 96 inside
        f.app_lines.mul_(10.0)
    return f


def test_colour_only_where_weights_matter_matches_everywhere():
    f = _cp_slab_field()
    o, d = _rays(32)
    o.requires_grad_(True)
    t = (0.5 + (4.0 / 96) * (torch.arange(96, dtype=torch.float64) + 0.5)).expand(32, 96)

    def run(threshold):
        f.zero_grad()
        if o.grad is not None:
            o.grad = None
        out = render_rays(f, o, d, t, background=0.3, color_weight_threshold=threshold)
        loss = (out.rgb - torch.tensor([0.2, 0.5, 0.7], dtype=torch.float64)).pow(2).sum() + out.depth.sum()
        loss.backward()
        grads = {n: p.grad.clone() for n, p in f.named_parameters()}
        grads["origins"] = o.grad.clone()
        return out, grads

    full, g_full = run(None)
    sub, g_sub = run(1e-4)
    w = full.weights.detach()
    mask = w > 1e-4 * w.amax(-1, keepdim=True)
    assert mask.float().mean() < 0.2  # the subset is really a subset
    # the only difference is the skipped sum of w * c (colours in [0, 1]): bounded by the skipped weight
    skipped = (w * (~mask)).sum(-1, keepdim=True)
    assert ((sub.rgb - full.rgb).abs() <= skipped + 1e-12).all()
    torch.testing.assert_close(sub.rgb, full.rgb, atol=2e-4, rtol=0)
    torch.testing.assert_close(sub.depth, full.depth)
    # gradients: the skipped samples (empty space, sigma = softplus(-10) per metre) carry ~1e-4 of
    # each ray's weight, so the two gradients agree to ~1e-4 of their scale (asserted with 1e-3)
    for name, g in g_full.items():
        scale = g.abs().max().clamp_min(1e-12)
        torch.testing.assert_close(g_sub[name], g, atol=1e-3 * float(scale), rtol=0, msg=name)


def test_the_optimiser_batch_render_of_a_view_dependent_field_matches_the_reference():
    """``render_batch`` (coarse pass, importance samples, colour only where the weight matters) against
    ``render_rays`` on the same samples, for a field whose colour depends on the view direction: the
    same colours, so the batch render feeds each ray's unit direction (it used to raise)."""
    from fmapping.mapping import MapperConfig
    from fmapping.mapping.batch_render import render_batch

    cfg = FieldConfig(kind="cp", resolution=64, density_components=4, appearance_components=6, app_features=7,
                      hidden=8, view_dependent=True)
    f = build_field(cfg, BOX).to(torch.float64)
    src = _cp_slab_field()
    with torch.no_grad():
        f.density_lines.copy_(src.density_lines)
        f.app_lines.mul_(10.0)
    o, d = _rays(64)
    mcfg = MapperConfig()
    out, _ = render_batch(f, torch.tensor(BOX, dtype=torch.float64), mcfg, o, d, "pdf", 32, 16, grad=False)
    ref = render_rays(f, o, d, out.t, background=0.0, color_weight_threshold=mcfg.color_threshold)
    torch.testing.assert_close(out.rgb, ref.rgb)
    unit = d / d.norm(dim=-1, keepdim=True)
    backwards = render_rays(f, o, d, out.t, background=0.0, color_weight_threshold=mcfg.color_threshold,
                            viewdirs=-unit)
    assert (backwards.rgb - ref.rgb).abs().max() > 1e-3  # the direction really changes the colour


def test_clear_field_colours_every_sample():
    """Relative threshold: an untrained field has no dominant sample, so nothing is skipped."""
    f = build_field(FieldConfig(kind="cp", resolution=16), BOX)
    o, d = _rays(8, dtype=torch.float32)
    t = torch.linspace(0.5, 4.0, 32).expand(8, 32)
    a = render_rays(f, o, d, t, color_weight_threshold=1e-4)
    b = render_rays(f, o, d, t, color_weight_threshold=None)
    torch.testing.assert_close(a.rgb, b.rgb)
    calls = AnalyticField(lambda x: torch.zeros_like(x[:, 0]))
    render_rays(calls, o, d, t)
    assert calls.color_calls == 8 * 32


def test_render_gradients_wrt_rays_finite_differences():
    cfg = FieldConfig(kind="cp", resolution=8, density_components=2, appearance_components=3, app_features=3,
                      hidden=4, init_scale=1.5, density_shift=0.0)
    f = build_field(cfg, BOX).double()
    o, d = _rays(4)
    t = torch.linspace(0.63, 3.97, 12, dtype=torch.float64).expand(4, 12)

    def fn(o_, d_):
        out = render_rays(f, o_, d_, t, color_weight_threshold=1e-4, background=0.5)
        return out.rgb, out.depth

    assert torch.autograd.gradcheck(fn, (o.requires_grad_(True), d.requires_grad_(True)), eps=1e-6, atol=1e-6)


def test_occupancy_alpha_is_independent_of_spacing():
    raw = torch.tensor([[-2.0, 0.0, 1.5, 3.0]])
    a1 = raw_to_alpha(raw, torch.full_like(raw, 0.01), "occupancy", 0.0)
    a2 = raw_to_alpha(raw, torch.full_like(raw, 5.0), "occupancy", 0.0)
    torch.testing.assert_close(a1, torch.sigmoid(raw))
    torch.testing.assert_close(a2, a1)
    torch.testing.assert_close(raw_to_alpha(raw, raw * 0 + 1, "occupancy", -10.0), torch.sigmoid(raw - 10))
    # rendering: constant occupancy a gives w_i = a (1 - a)^i whatever the sample spacing
    field = AnalyticField(lambda x: torch.full_like(x[:, 0], 0.4), alpha_mode="occupancy", density_shift=0.0)
    o, d = _rays(3, dtype=torch.float32)
    t = torch.tensor([0.5, 0.6, 1.5, 1.55, 3.0]).expand(3, 5)
    a = torch.sigmoid(torch.tensor(0.4))
    expect = a * (1 - a) ** torch.arange(5.0)
    torch.testing.assert_close(render_rays(field, o, d, t).weights, expect.expand(3, 5))
    with pytest.raises(ValueError, match="alpha mode"):
        raw_to_alpha(raw, raw, "sdf", 0.0)


@pytest.mark.parametrize("bg", [0.0, 0.7, [0.1, 0.2, 0.3], "per-ray", None])
def test_background(bg):
    o, d = _rays(5, dtype=torch.float32)
    t = torch.linspace(0.5, 3.0, 16).expand(5, 16)
    empty = AnalyticField(lambda x: torch.full_like(x[:, 0], EMPTY_RAW))
    if bg == "per-ray":
        bg = torch.rand(5, 3)
    out = render_rays(empty, o, d, t, background=bg)
    expect = torch.zeros(5, 3) if bg is None else torch.as_tensor(bg, dtype=torch.float32).expand(5, 3)
    torch.testing.assert_close(out.rgb, expect)
    assert (out.acc == 0).all() and (out.depth_normalized == 0).all()


def test_composite_checks_shapes():
    with pytest.raises(ValueError, match="same shape"):
        composite(torch.zeros(2, 3), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="rgb must have shape"):
        composite(torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2, 3))


def test_render_weights_matches_render_rays():
    f = _cp_slab_field(dtype=torch.float32)
    o, d = _rays(6, dtype=torch.float32)
    t = torch.linspace(0.5, 4.5, 40).expand(6, 40)
    a, b = render_weights(f, o, d, t), render_rays(f, o, d, t)
    assert a.rgb is None
    torch.testing.assert_close(a.weights, b.weights)
    torch.testing.assert_close(a.depth, b.depth)


def test_render_image_of_slab():
    z0 = 2.0
    f = _cp_slab_field(z0, dtype=torch.float32)
    cam = PinholeCamera(12.0, 12.0, 7.5, 5.5, 16, 12)
    c2w = np.eye(4)
    c2w[:3, 3] = [0.1, -0.2, 0.0]
    img = render_image(f, cam, c2w, near=0.3, far=5.0, n_samples=64, chunk=50)
    assert img["rgb"].shape == (12, 16, 3) and img["depth"].shape == (12, 16)
    assert (img["acc"] > 0.99).all()
    step = (6.0 - 0.3) / 64  # rays are clipped to the box, whose far face is at z = 6
    assert (img["depth_normalized"] - z0).abs().max() < 2 * step
    fine = render_image(f, cam, c2w, near=0.3, far=5.0, n_samples=32, n_importance=32)
    assert (fine["depth_normalized"] - z0).abs().max() < 2 * step
    # rgb equals the colour of the slab surface rendered ray by ray
    uv = cam.pixel_grid(dtype=torch.float64)
    o, d = cam.rays(torch.as_tensor(c2w), uv)
    pts = (o + d * img["depth_normalized"].reshape(-1, 1).double()).float()
    torch.testing.assert_close(img["rgb"].reshape(-1, 3), f.color(pts).detach(), atol=0.05, rtol=0)


def test_render_image_rays_missing_the_box_are_empty_and_finite():
    f = _cp_slab_field(dtype=torch.float32)
    cam = PinholeCamera(12.0, 12.0, 3.5, 2.5, 8, 6)
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, -2.0]
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking along -z, away from the box
    img = render_image(f, cam, c2w, near=0.1, far=5.0, n_samples=16, n_importance=8)
    for v in img.values():
        assert torch.isfinite(v).all()
    assert (img["acc"] == 0).all() and (img["rgb"] == 0).all()
