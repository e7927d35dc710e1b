"""Fields: interpolation against slow explicit references, finite-difference gradients,
out-of-box behaviour, snapshots and parameter counts."""
import math

import numpy as np
import pytest
import torch
from torch.func import functional_call

from fmapping.field import EMPTY_RAW, Field, FieldConfig, build_field, field_from_snapshot

AABB = np.array([[-1.0, -0.5, 0.0], [2.0, 1.5, 4.0]])


def _points(n, seed=0, margin=0.0):
    rng = np.random.default_rng(seed)
    lo, hi = AABB[0] + margin, AABB[1] - margin
    return lo + rng.random((n, 3)) * (hi - lo)


def _lerp_1d(line, x, lo, hi):
    """Explicit linear interpolation of ``line`` (R,) whose R nodes span [lo, hi]."""
    r = len(line)
    p = (x - lo) / (hi - lo) * (r - 1)
    i0 = min(int(np.floor(p)), r - 2)
    f = p - i0
    return line[i0] * (1 - f) + line[i0 + 1] * f


def _bilerp(img, x, y, lox, hix, loy, hiy):
    """img[h, w]: w indexes x, h indexes y."""
    h, w = img.shape
    px = (x - lox) / (hix - lox) * (w - 1)
    py = (y - loy) / (hiy - loy) * (h - 1)
    ix, iy = min(int(np.floor(px)), w - 2), min(int(np.floor(py)), h - 2)
    fx, fy = px - ix, py - iy
    return (img[iy, ix] * (1 - fx) * (1 - fy) + img[iy, ix + 1] * fx * (1 - fy)
            + img[iy + 1, ix] * (1 - fx) * fy + img[iy + 1, ix + 1] * fx * fy)


def _trilerp(vol, p, lo, hi):
    """vol[z, y, x]."""
    r = np.array(vol.shape[::-1]) - 1
    q = (p - lo) / (hi - lo) * r
    i = np.minimum(np.floor(q).astype(int), r - 1)
    f = q - i
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                wgt = (f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1]) * (f[2] if dz else 1 - f[2])
                out += wgt * vol[i[2] + dz, i[1] + dy, i[0] + dx]
    return out


def _mlp_np(dec, feat):
    w1, b1 = dec.fc1.weight.detach().double().numpy(), dec.fc1.bias.detach().double().numpy()
    w2, b2 = dec.fc2.weight.detach().double().numpy(), dec.fc2.bias.detach().double().numpy()
    h = np.maximum(w1 @ feat + b1, 0)
    return 1 / (1 + np.exp(-(w2 @ h + b2)))


def test_cp_matches_explicit_reference():
    cfg = FieldConfig(kind="cp", resolution=7, density_components=3, appearance_components=4, app_features=5,
                      hidden=6)
    f = build_field(cfg, AABB)
    pts = _points(20, seed=1)
    dl = f.density_lines.detach().double().numpy()[..., 0]  # (3, C, R)
    al = f.app_lines.detach().double().numpy()[..., 0]
    basis = f.basis.weight.detach().double().numpy()
    ref_raw, ref_rgb = [], []
    for p in pts:
        raw = 0.0
        for r in range(cfg.density_components):
            prod = 1.0
            for a in range(3):
                prod *= _lerp_1d(dl[a, r], p[a], AABB[0, a], AABB[1, a])
            raw += prod
        feat = np.array([np.prod([_lerp_1d(al[a, r], p[a], AABB[0, a], AABB[1, a]) for a in range(3)])
                         for r in range(cfg.appearance_components)])
        ref_raw.append(raw)
        ref_rgb.append(_mlp_np(f.decoder, basis @ feat))
    x = torch.tensor(pts, dtype=torch.float32)
    torch.testing.assert_close(f.density_raw(x).double(), torch.tensor(ref_raw), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(f.color(x).double(), torch.tensor(np.array(ref_rgb)), atol=1e-6, rtol=1e-5)


def test_vm_matches_explicit_reference():
    cfg = FieldConfig(kind="vm", resolution=6, vm_density_components=2, vm_appearance_components=2,
                      app_features=4, hidden=5)
    f = build_field(cfg, AABB)
    pts = _points(15, seed=2)
    dp = f.density_planes.detach().double().numpy()
    dl = f.density_lines.detach().double().numpy()[..., 0]
    ap = f.app_planes.detach().double().numpy()
    al = f.app_lines.detach().double().numpy()[..., 0]
    basis = f.basis.weight.detach().double().numpy()
    pairs, vecs = ((0, 1), (0, 2), (1, 2)), (2, 1, 0)
    ref_raw, ref_rgb = [], []
    for p in pts:
        def comp(planes, lines, a, r):
            i, j = pairs[a]
            k = vecs[a]
            pv = _bilerp(planes[a, r], p[i], p[j], AABB[0, i], AABB[1, i], AABB[0, j], AABB[1, j])
            return pv * _lerp_1d(lines[a, r], p[k], AABB[0, k], AABB[1, k])
        ref_raw.append(sum(comp(dp, dl, a, r) for a in range(3) for r in range(2)))
        feat = np.array([comp(ap, al, a, r) for a in range(3) for r in range(2)])
        ref_rgb.append(_mlp_np(f.decoder, basis @ feat))
    x = torch.tensor(pts, dtype=torch.float32)
    torch.testing.assert_close(f.density_raw(x).double(), torch.tensor(ref_raw), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(f.color(x).double(), torch.tensor(np.array(ref_rgb)), atol=1e-6, rtol=1e-5)


def test_grid_matches_explicit_reference():
    cfg = FieldConfig(kind="grid", grid_resolution=5, grid_features=3, hidden=4)
    f = build_field(cfg, AABB)
    with torch.no_grad():
        f.density_grid.normal_()
    pts = _points(15, seed=3)
    dens = f.density_grid.detach().double().numpy()[0, 0]
    feats = f.feature_grid.detach().double().numpy()[0]
    ref_raw = [_trilerp(dens, p, AABB[0], AABB[1]) for p in pts]
    ref_rgb = [_mlp_np(f.decoder, np.array([_trilerp(feats[c], p, AABB[0], AABB[1]) for c in range(3)])) for p in pts]
    x = torch.tensor(pts, dtype=torch.float32)
    torch.testing.assert_close(f.density_raw(x).double(), torch.tensor(ref_raw), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(f.color(x).double(), torch.tensor(np.array(ref_rgb)), atol=1e-6, rtol=1e-5)


def test_line_nodes_sit_on_box_faces():
    """Node 0 at aabb min, node R-1 at aabb max: a point on a corner reads the corner nodes exactly."""
    cfg = FieldConfig(kind="cp", resolution=5, density_components=1)
    f = build_field(cfg, AABB)
    lines = f.density_lines.detach()[:, 0, :, 0]
    x = torch.tensor(AABB, dtype=torch.float32)
    expect = torch.stack([lines[:, 0].prod(), lines[:, -1].prod()])
    torch.testing.assert_close(f.density_raw(x), expect)


TINY = {
    "cp": dict(resolution=8, density_components=2, appearance_components=3, app_features=4, hidden=5),
    "vm": dict(resolution=8, vm_density_components=1, vm_appearance_components=2, app_features=3, hidden=4),
    "grid": dict(grid_resolution=6, grid_features=2, hidden=4),
    "mlp": dict(mlp_layers=2, mlp_width=8, pe_freqs=2),
}


@pytest.mark.parametrize("kind", ["cp", "vm", "grid", "mlp"])
def test_gradcheck_wrt_parameters_and_points(kind):
    f = build_field(FieldConfig(kind=kind, view_dependent=(kind == "cp"), **TINY[kind]), AABB).double()
    if kind == "grid":
        with torch.no_grad():
            f.density_grid.normal_()
    names = [n for n, _ in f.named_parameters()]
    params = tuple(p.detach().clone().requires_grad_(True) for _, p in f.named_parameters())
    x = torch.tensor(_points(5, seed=4, margin=0.05), dtype=torch.float64)
    vd = torch.randn(5, 3, dtype=torch.float64) if kind == "cp" else None

    def by_params(*ps):
        return functional_call(f, dict(zip(names, ps)), (x, vd))

    assert torch.autograd.gradcheck(by_params, params, eps=1e-6, atol=1e-6, fast_mode=True)
    xr = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: f(p, vd), (xr,), eps=1e-6, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("kind", ["cp", "vm", "grid", "mlp"])
def test_outside_points_are_empty_and_finite(kind):
    f = build_field(FieldConfig(kind=kind, **TINY[kind]), AABB)
    x = torch.tensor([[-5.0, 0.0, 1.0], [0.0, 0.0, 4.5], [1e30, -1e30, 2.0], [float("inf"), 0.0, 1.0],
                      [0.5, 0.5, 2.0]], requires_grad=True)
    raw = f.density_raw(x)
    assert torch.all(raw[:4] == EMPTY_RAW)
    assert raw[4] != EMPTY_RAW
    rgb = f.color(x)
    assert torch.isfinite(rgb).all() and (rgb >= 0).all() and (rgb <= 1).all()
    (raw.sum() + rgb.sum()).backward()
    for p in f.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()
    assert torch.isfinite(x.grad[:3]).all()


@pytest.mark.parametrize("kind", ["cp", "vm", "grid", "mlp"])
def test_initial_field_is_clear(kind):
    cfg = FieldConfig(kind=kind, init_opacity=0.0)
    f = build_field(cfg, AABB)
    x = torch.tensor(_points(4096, seed=5), dtype=torch.float32)
    with torch.no_grad():
        sigma = torch.nn.functional.softplus(f.density_raw(x) + cfg.density_shift)
    # optical thickness of 5 m of the initial field is below 2 %
    assert float(sigma.max()) * 5.0 < 0.02


@pytest.mark.parametrize("kind", ["cp", "vm"])
@pytest.mark.parametrize("opacity", [0.5, 0.95])
def test_foggy_start_absorbs_the_asked_share_across_the_box(kind, opacity):
    # cp / vm start as a uniform fog: a ray crossing the box's mean side absorbs init_opacity of its light. The
    # optical depth of the mean side is integrated from the field's own density at random points (the factor noise
    # makes the fog uneven, so the share is checked on the mean density)
    box = torch.tensor([[-1.0, -2.0, 0.0], [3.0, 1.0, 2.5]])
    cfg = FieldConfig(kind=kind, init_opacity=opacity)
    f = build_field(cfg, box)
    x = box[0] + (box[1] - box[0]) * torch.rand(20000, 3, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        sigma = torch.nn.functional.softplus(f.density_raw(x) + cfg.density_shift)
    side = float((box[1] - box[0]).mean())
    absorbed = 1.0 - math.exp(-float(sigma.mean()) * side)
    assert abs(absorbed - opacity) < 0.05 * opacity
    # occupancy mode: each sample at the opacity of one cell of that fog, so a ray of resolution - 1 samples across
    # the mean side absorbs the same share
    occ = FieldConfig(kind=kind, init_opacity=opacity, alpha_mode="occupancy")
    with torch.no_grad():
        alpha = torch.sigmoid(build_field(occ, box).density_raw(x) + occ.density_shift)
    through = float(torch.exp(torch.log1p(-alpha).mean() * (occ.resolution - 1)))
    assert abs((1.0 - through) - opacity) < 0.05 * opacity


def test_cp_parameter_count_matches_paper_budget():
    f = build_field(FieldConfig(kind="cp"), AABB)
    grid = (16 + 24) * 3 * 128
    assert sum(p.numel() for p in f.grid_parameters()) == grid
    assert f.num_parameters() == grid + 24 * 27 + (27 * 48 + 48) + (48 * 3 + 3)
    assert 0.01e6 <= f.num_parameters() <= 0.02e6


@pytest.mark.parametrize("kind", ["cp", "vm", "grid", "mlp"])
def test_parameter_groups_partition_parameters(kind):
    f = build_field(FieldConfig(kind=kind, **TINY[kind]), AABB)
    groups = [id(p) for p in f.grid_parameters()] + [id(p) for p in f.decoder_parameters()]
    assert sorted(groups) == sorted(id(p) for p in f.parameters())
    assert f.flops_per_point() > 0


@pytest.mark.parametrize("kind", ["cp", "vm", "grid", "mlp"])
def test_snapshot_roundtrip(kind):
    cfg = FieldConfig(kind=kind, **TINY[kind])
    f = build_field(cfg, AABB)
    with torch.no_grad():
        for p in f.parameters():
            p.add_(0.05 * torch.randn_like(p))
    arrays = f.snapshot()
    assert all(a.dtype == np.float32 for a in arrays.values())
    np.testing.assert_allclose(arrays["aabb"], AABB)
    g = field_from_snapshot(cfg, arrays)
    assert type(g) is type(f)
    x = torch.tensor(_points(50, seed=6), dtype=torch.float32)
    torch.testing.assert_close(g.density_raw(x), f.density_raw(x))
    torch.testing.assert_close(g.color(x), f.color(x))


def test_snapshot_mismatch_is_a_clear_error():
    arrays = build_field(FieldConfig(kind="cp", resolution=16), AABB).snapshot()
    with pytest.raises(ValueError, match="density_lines.*shape"):
        Field.from_snapshot(FieldConfig(kind="cp", resolution=32), arrays)
    with pytest.raises(ValueError, match="missing"):
        Field.from_snapshot(FieldConfig(kind="vm", resolution=16), arrays)


def test_view_dependence():
    f = build_field(FieldConfig(kind="cp", resolution=8, view_dependent=True), AABB)
    x = torch.tensor(_points(10, seed=7), dtype=torch.float32)
    with pytest.raises(ValueError, match="viewdirs"):
        f.color(x)
    a = f.color(x, torch.tensor([[0.0, 0.0, 1.0]]).expand(10, 3))
    b = f.color(x, torch.tensor([[1.0, 0.0, 0.0]]).expand(10, 3))
    assert (a - b).abs().max() > 1e-4
    # direction length does not matter
    torch.testing.assert_close(f.color(x, torch.tensor([[0.0, 0.0, 3.0]]).expand(10, 3)), a)


@pytest.mark.parametrize("kind", ["cp", "vm", "grid"])
def test_regularizers(kind):
    f = build_field(FieldConfig(kind=kind, **TINY[kind]), AABB)
    tv = f.regularizer("tv")
    assert tv > 0
    tv.backward()
    assert all(p.grad is not None for p in f.grid_parameters())
    with torch.no_grad():
        for p in f.grid_parameters():
            p.fill_(0.3)
    assert f.regularizer("tv").detach().item() == pytest.approx(0.0, abs=1e-12)
    assert f.regularizer("l1").detach().item() == pytest.approx(0.3 * (2 if kind == "vm" else 1), rel=1e-6)
    with pytest.raises(ValueError, match="regularizer kind"):
        f.regularizer("l2")


def test_bad_config_and_aabb():
    with pytest.raises(ValueError, match="kind"):
        build_field(FieldConfig(kind="hash"), AABB)
    with pytest.raises(ValueError, match="max must exceed min"):
        build_field(FieldConfig(), np.array([[0, 0, 0], [1, -1, 1.0]]))
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        build_field(FieldConfig(), np.zeros(6))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        build_field(FieldConfig(resolution=4), AABB).density_raw(torch.zeros(4, 2))


@pytest.mark.parametrize("kind", ["cp", "vm", "grid", "mlp"])
def test_grid_param_groups_partition_grid_parameters(kind):
    f = build_field(FieldConfig(kind=kind, **TINY[kind]), AABB)
    groups = f.grid_param_groups()
    ids = [id(p) for ps, _ in groups for p in ps]
    assert sorted(ids) == sorted(id(p) for p in f.grid_parameters())
    assert len(ids) == len(set(ids))
    scales = {id(p): s for ps, s in groups for p in ps}
    if kind == "grid":
        assert scales[id(f.density_grid)] == FieldConfig().grid_density_lr_scale
        assert scales[id(f.feature_grid)] == 1.0
    elif kind == "vm":
        assert scales[id(f.density_planes)] == scales[id(f.app_planes)] == FieldConfig().vm_plane_lr_scale
        assert scales[id(f.density_lines)] == scales[id(f.app_lines)] == 1.0
    else:  # cp and the MLP keep the mapper's grid lr unchanged, in one group
        assert all(s == 1.0 for s in scales.values()) and len(groups) == 1


def test_vm_plane_lr_scale_splits_planes_from_lines():
    f = build_field(FieldConfig(kind="vm", vm_plane_lr_scale=5.0, **TINY["vm"]), AABB)
    scales = {id(p): s for ps, s in f.grid_param_groups() for p in ps}
    assert scales == {id(f.density_planes): 5.0, id(f.app_planes): 5.0, id(f.density_lines): 1.0,
                      id(f.app_lines): 1.0}
    one = build_field(FieldConfig(kind="vm", vm_plane_lr_scale=1.0, **TINY["vm"]), AABB).grid_param_groups()
    assert len(one) == 1 and one[0][1] == 1.0 and len(one[0][0]) == 4  # TensoRF's single group
    with pytest.raises(ValueError, match="vm_plane_lr_scale"):
        FieldConfig(kind="vm", vm_plane_lr_scale=0.0).validate()
    with pytest.raises(ValueError, match="grid_density_lr_scale"):
        FieldConfig(kind="grid", grid_density_lr_scale=-1.0).validate()


def test_grid_initial_density_matches_config():
    cfg = FieldConfig(kind="grid", grid_resolution=8, grid_features=2, hidden=4, grid_init_density=0.002)
    f = build_field(cfg, AABB)
    with torch.no_grad():
        sigma = torch.nn.functional.softplus(f.density_raw(torch.tensor(_points(2000, seed=3), dtype=torch.float32))
                                             + cfg.density_shift)
    # log-normal spread from the 0.01-std init noise: mean within 1 %
    assert float(sigma.mean()) == pytest.approx(0.002, rel=0.01)


def _fit_slab_opacity(cfg: FieldConfig, steps: int) -> tuple[float, float]:
    """Fit the accumulated opacity of 128 rays along +z through a 2 x 2 x 4 m box (24 samples
    each) to 1 where x < 0 (a slab) and 0 elsewhere, with the mapper's Adam (lr 0.02 x the
    field's group multipliers, betas 0.9 / 0.99). Returns (final MSE, mean opacity of the empty rays)."""
    from fmapping.render import raw_to_alpha

    aabb = np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 4.0]])
    f = build_field(cfg, aabb)
    n, s = 128, 24
    xy = torch.rand(n, 2, generator=torch.Generator().manual_seed(1)) * 1.8 - 0.9
    t = torch.linspace(0.05, 3.95, s)
    delta = torch.full((n, s), float(t[1] - t[0]))
    pts = torch.cat([xy[:, None, :].expand(n, s, 2), t[None, :, None].expand(n, s, 1)], -1).reshape(-1, 3)
    target = (xy[:, 0] < 0).float()
    opt = torch.optim.Adam([{"params": ps, "lr": 0.02 * sc} for ps, sc in f.grid_param_groups()], betas=(0.9, 0.99))
    for _ in range(steps):
        alpha = raw_to_alpha(f.density_raw(pts).view(n, s), delta, "density", cfg.density_shift)
        acc = 1 - torch.prod(1 - alpha, -1)
        loss = (acc - target).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(loss.detach()), float(acc.detach()[target == 0].mean())


@pytest.mark.usefixtures("one_thread")
def test_grid_learns_opacity_as_fast_as_cp():
    """The dense grid must turn opaque within the few hundred iterations the mapper gives it.
    With the factor fields' start (raw ~ 0 under the -10 shift) and lr it stays empty: a voxel's
    raw value grows by ~lr per step, a CP product of three factors cubically."""
    grid_cfg = dict(kind="grid", grid_resolution=16, grid_features=2, hidden=4)
    cp_loss, _ = _fit_slab_opacity(FieldConfig(kind="cp", resolution=16), 60)
    grid_loss, grid_empty = _fit_slab_opacity(FieldConfig(**grid_cfg), 60)
    old_loss, _ = _fit_slab_opacity(FieldConfig(**grid_cfg, grid_density_lr_scale=1.0,
                                                grid_init_density=float(np.log1p(np.exp(-10.0)))), 60)
    assert cp_loss < 0.05  # the factorized field fits the slab in 60 steps ...
    assert grid_loss <= max(cp_loss, 0.01)  # ... and so does the grid
    assert grid_empty < 0.05  # without filling the empty half
    assert old_loss > 0.4  # the old start: acc ~ 0 everywhere (MSE ~ the slab's share, ~0.47)


@pytest.mark.parametrize("kind", ["cp", "vm"])
@pytest.mark.parametrize("grow", [True, False])
def test_refit_box_keeps_what_the_field_holds(kind, grow):
    """Moving a field onto a new box (grown as the camera explores, or cut down to the points) keeps its
    density and appearance at every world point both boxes hold. Bilinear resampling is exact for factors
    that are linear in position, so the factors are set to random linear functions first; points of the new
    box outside the old one are empty (a zero factor in every term)."""
    f = build_field(FieldConfig(kind=kind, **TINY[kind]), AABB).double()
    rng = np.random.default_rng(7)
    lo, hi = AABB
    with torch.no_grad():
        for name, p in f.named_parameters():
            if not name.endswith(("lines", "planes")):
                continue
            r = p.shape[2]
            t = torch.linspace(-1.0, 1.0, r, dtype=p.dtype)
            a = torch.tensor(rng.normal(size=p.shape[:2] + (3,)), dtype=p.dtype)  # per term: c + gx t_x + gy t_y
            if name.endswith("lines"):
                p.copy_((a[..., 0:1] + a[..., 1:2] * t)[..., None])
            else:
                ty, tx = torch.meshgrid(t, t, indexing="ij")
                p.copy_(a[..., 0, None, None] + a[..., 1, None, None] * tx + a[..., 2, None, None] * ty)
    new = np.stack([lo - [0.7, 0.3, 1.1], hi + [0.4, 0.9, 0.2]]) if grow else \
        np.stack([lo + [0.5, 0.2, 0.9], hi - [0.6, 0.4, 1.3]])
    inner = np.stack([np.maximum(lo, new[0]), np.minimum(hi, new[1])])
    # points at least one new cell inside both boxes (the resampled node next to the old boundary is zero)
    cell = (new[1] - new[0]) / (f.cfg.resolution - 1)
    x = torch.tensor(inner[0] + cell + rng.random((200, 3)) * (inner[1] - inner[0] - 2 * cell))
    before = (f.density_raw(x), f.color(x))
    f.refit_box(new)
    np.testing.assert_allclose(f.aabb.numpy(), new)
    torch.testing.assert_close(f.density_raw(x), before[0], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(f.color(x), before[1], rtol=1e-9, atol=1e-9)
    if grow:  # beyond the old box by more than a cell: zero raw density (empty after the shift)
        out = torch.tensor(np.stack([new[0] + 0.3 * cell, new[1] - 0.3 * cell]))
        assert torch.all(f.density_raw(out) == 0.0)
