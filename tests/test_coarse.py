"""Coarse-to-fine steps on factor lines (fmapping.mapping.coarse): the interpolation matrix against the field's own
line lookup, the folded steps against the explicit reparameterisation, and a mapper that uses them."""
import numpy as np
import torch

from fmapping.field.cp import sample_lines
from fmapping.mapping.coarse import CoarseLines, interp_matrix


def test_interp_matrix_is_the_lines_linear_interpolation_at_the_fine_nodes():
    g = torch.Generator().manual_seed(0)
    for r, rc in ((128, 16), (128, 32), (17, 5), (9, 9)):
        coarse = torch.randn(3, 4, rc, 1, generator=g, dtype=torch.float64)
        u = torch.linspace(-1.0, 1.0, r, dtype=torch.float64)[:, None].expand(r, 3).contiguous()
        ref = sample_lines(coarse, u)  # (3, 4, r): grid_sample of the coarse lines at the fine nodes
        got = coarse[..., 0] @ interp_matrix(r, rc, torch.float64).t()
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-10)
        m = interp_matrix(r, rc, torch.float64)
        torch.testing.assert_close(m.sum(1), torch.ones(r, dtype=torch.float64))  # a partition of unity


def _loss(lines, u, target):
    s = sample_lines(lines, u)  # (3, C, N)
    return ((s.prod(0).sum(0) - target) ** 2).mean()


def test_folded_coarse_steps_follow_adam_on_the_reparameterised_lines():
    """Adam on (fine, coarse) with lines = fine + U coarse, coarse kept as a parameter, against CoarseLines'
    steps (coarse gradient from the lines' gradient, folded into the lines and zeroed after each step)."""
    g = torch.Generator().manual_seed(1)
    r, rc, c, n = 24, 6, 3, 400
    start = 0.5 + 0.1 * torch.randn(3, c, r, 1, generator=g, dtype=torch.float64)
    u = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1
    target = torch.sin(3 * u[:, 0]) * torch.cos(2 * u[:, 1]) + 0.3 * u[:, 2]
    m = interp_matrix(r, rc, torch.float64)

    fine_a = start.clone().requires_grad_(True)
    coarse_a = torch.zeros(3, c, rc, 1, dtype=torch.float64, requires_grad=True)
    opt_a = torch.optim.Adam([fine_a, coarse_a], lr=0.02, betas=(0.9, 0.99))
    fine_b = start.clone().requires_grad_(True)
    cl = CoarseLines([fine_b], rc)
    opt_b = torch.optim.Adam([fine_b, *cl.params()], lr=0.02, betas=(0.9, 0.99))
    first = float(_loss(start, u, target))
    for _ in range(30):
        opt_a.zero_grad()
        _loss(fine_a + (coarse_a[..., 0] @ m.t()).unsqueeze(-1), u, target).backward()
        opt_a.step()
        opt_b.zero_grad()
        _loss(fine_b, u, target).backward()
        cl.set_grads()
        opt_b.step()
        cl.fold()
    lines_a = (fine_a + (coarse_a[..., 0] @ m.t()).unsqueeze(-1)).detach()
    torch.testing.assert_close(fine_b.detach(), lines_a, rtol=1e-9, atol=1e-9)
    assert float(cl.params()[0].detach().abs().max()) == 0.0
    assert float(_loss(lines_a, u, target)) < 0.5 * first


def test_a_mapper_with_coarse_steps_maps_and_keeps_plain_lines(tmp_path):
    """Init and one window with coarse steps: the field stays a plain CP field (same parameter count) and renders
    the init views' depth about as well as without them (synthetic room, GT poses, depth for evaluation only)."""
    from fmapping.config import merge
    from fmapping.datasets import open_dataset
    from fmapping.mapping import Mapper, MapperConfig
    from fmapping.synthetic import generate_scene

    generate_scene(tmp_path / "room", seed=0, frames=20, size=(80, 60), max_cloud_points=2000)
    ds = open_dataset(tmp_path / "room")
    over = {"init_iters_per_round": 6, "iters_per_window": 4, "init_rays_per_iter": 256, "rays_per_iter": 256}
    errs, params = {}, {}
    for nodes in (0, 16):
        m = Mapper(merge(MapperConfig(), {**over, "coarse_nodes": nodes}), ds.camera)
        for i in range(len(ds)):
            f = ds[i]
            m.add_frame(f.rgb, f.c2w, f.timestamp)
        assert m.initialized and len(m.stats()["windows"]) >= 2  # the init and at least one window update
        if nodes:  # the coarse steps were taken and folded: the companions are back at zero, the field is plain
            assert all(float(c.detach().abs().max()) == 0.0 for c in m._coarse.params())
            assert len(m._coarse.params()) == 2 and m._opt.state[m._coarse.params()[0]]["step"] > 0
        params[nodes] = m.field.num_parameters()
        rel = []
        for i in (0, 7, 14):
            f = ds[i]
            d = m.render(f.c2w)["depth_normalized"]
            ok = f.depth > 0
            rel.append(float(np.median(np.abs(d[ok] - f.depth[ok]) / f.depth[ok])))
        errs[nodes] = float(np.median(rel))
    assert params[16] == params[0]
    print(errs)
    assert errs[16] < 0.15 and errs[16] < 1.5 * errs[0], errs


def test_coarse_settings_out_of_range_are_refused_by_name():
    import pytest

    from fmapping.config import merge
    from fmapping.mapping import MapperConfig

    for bad, match in (({"coarse_nodes": 1}, "coarse_nodes"), ({"coarse_nodes": 129}, "coarse_nodes"),
                       ({"coarse_nodes": 16, "coarse_lr_scale": 0.0}, "coarse_lr_scale")):
        with pytest.raises(ValueError, match=match):
            merge(MapperConfig(), bad).validate()
    merge(MapperConfig(), {"coarse_nodes": 128}).validate()


def test_a_state_saved_with_coarse_steps_resumes_with_them_and_names_the_mismatch_without(tmp_path):
    """A mapper state saved with coarse steps loads into a mapper with the same setting (the coarse Adam moments
    with it) and is refused, by name, by one without them."""
    import pytest

    from fmapping.config import merge
    from fmapping.datasets import open_dataset
    from fmapping.mapping import Mapper, MapperConfig
    from fmapping.synthetic import generate_scene

    generate_scene(tmp_path / "room", seed=1, frames=16, size=(64, 48), max_cloud_points=1000)
    ds = open_dataset(tmp_path / "room")
    over = {"init_iters_per_round": 2, "init_rays_per_iter": 64}
    m = Mapper(merge(MapperConfig(), {**over, "coarse_nodes": 8}), ds.camera)
    for i in range(len(ds)):
        f = ds[i]
        m.add_frame(f.rgb, f.c2w, f.timestamp)
    state = m.state_dict()
    same = Mapper(merge(MapperConfig(), {**over, "coarse_nodes": 8}), ds.camera)
    same.load_state_dict(state)
    moments = [same._opt.state[c]["exp_avg"] for c in same._coarse.params()]
    torch.testing.assert_close(moments, [m._opt.state[c]["exp_avg"] for c in m._coarse.params()])
    with pytest.raises(ValueError, match="coarse_nodes"):
        Mapper(merge(MapperConfig(), over), ds.camera).load_state_dict(state)
