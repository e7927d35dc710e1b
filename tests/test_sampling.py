"""Ray/AABB, stratified, inverse-CDF and sliding-window samplers."""
import numpy as np
import pytest
import torch

from fmapping.field import EMPTY_RAW, Field, FieldConfig
from fmapping.render import render_weights
from fmapping.sampling import (merge_samples, ray_aabb, sample_pdf, sliding_window_interval,
                               sliding_window_sample, sliding_window_scores, stratified)

BOX = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 5.0]])


def test_ray_aabb_hand_cases():
    o = torch.tensor([
        [0.0, 0.0, -2.0],   # in front of the box, looking +z: enters z=0 at t=2, leaves z=5 at t=7
        [0.0, 0.0, 1.0],    # inside the box: near clamped to near_min, leaves at t=4
        [5.0, 0.0, -2.0],   # x = 5 beside the box, looking +z: misses
        [0.0, 0.0, -2.0],   # looking away (-z): misses
        [0.0, 0.0, -1.0],   # oblique: d = (0.5, 0, 1), x leaves at t=2 (x=1), z enters at t=1
        [-3.0, 1.0, 2.0],   # along +x with zero y/z components: enters x=-1 at t=2, leaves x=1 at t=4
    ])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.5, 0.0, 1.0],
                      [1.0, 0.0, 0.0]])
    near, far, hit = ray_aabb(o, d, BOX, near_min=0.05)
    assert hit.tolist() == [True, True, False, False, True, True]
    torch.testing.assert_close(near, torch.tensor([2.0, 0.05, 0.05, 0.05, 1.0, 2.0]))
    torch.testing.assert_close(far, torch.tensor([7.0, 4.0, 0.05, 0.05, 2.0, 4.0]))
    # a box entirely behind near_min is a miss
    _, _, hit2 = ray_aabb(torch.tensor([[0.0, 0.0, 4.99]]), torch.tensor([[0.0, 0.0, 1.0]]), BOX, near_min=0.05)
    assert not hit2.any()


def test_stratified_bins():
    near = torch.tensor([0.5, 1.0, 2.0])
    far = torch.tensor([4.5, 1.5, 2.0])
    g = torch.Generator().manual_seed(0)
    t = stratified(near, far, 16, generator=g)
    assert t.shape == (3, 16)
    assert (t >= near[:, None]).all() and (t <= far[:, None]).all()
    assert (t.diff(dim=-1) >= 0).all()
    # exactly one sample in each of the 16 equal bins
    bins = ((t - near[:, None]) / (far - near).clamp_min(1e-12)[:, None] * 16).floor().clamp(0, 15)
    assert torch.equal(bins[:2], torch.arange(16.0).expand(2, 16))
    centres = stratified(near, far, 4, perturb=False)
    torch.testing.assert_close(centres[0], torch.tensor([1.0, 2.0, 3.0, 4.0]))
    t2 = stratified(near, far, 16, generator=torch.Generator().manual_seed(0))
    assert torch.equal(t, t2)


def test_sample_pdf_concentrates_on_the_weight():
    t = torch.linspace(0.5, 4.5, 64).expand(200, 64).contiguous()
    w = torch.full((200, 64), 0.05 / 63)
    w[:, 40] = 0.95
    new = sample_pdf(t, w, 128, generator=torch.Generator().manual_seed(1))
    assert new.shape == (200, 128)
    assert (new.diff(dim=-1) >= 0).all()
    assert (new >= 0.5).all() and (new <= 4.5).all()
    # bin of sample 40 spans the midpoints to its neighbours
    lo, hi = 0.5 * (t[0, 39] + t[0, 40]), 0.5 * (t[0, 40] + t[0, 41])
    frac_in = ((new >= lo) & (new <= hi)).float().mean()
    assert frac_in > 0.9
    a = sample_pdf(t, w, 32, deterministic=True)
    b = sample_pdf(t, w, 32, deterministic=True)
    assert torch.equal(a, b)
    # zero weights: uniform over [t_0, t_last]
    u = sample_pdf(t, torch.zeros_like(w), 8, deterministic=True)
    torch.testing.assert_close(u[0], 0.5 + 4.0 * (torch.arange(8.0) + 0.5) / 8, atol=1e-3, rtol=0)


def test_sample_pdf_is_detached_and_validates():
    t = torch.linspace(0, 1, 8).expand(2, 8).clone().requires_grad_(True)
    w = torch.rand(2, 8, requires_grad=True)
    assert not sample_pdf(t, w, 4).requires_grad
    with pytest.raises(ValueError):
        sample_pdf(t, w[:, :4], 4)
    # degenerate rays (near == far) stay finite
    flat = sample_pdf(torch.full((2, 8), 0.7), torch.zeros(2, 8), 5)
    torch.testing.assert_close(flat, torch.full((2, 5), 0.7))
    torch.testing.assert_close(merge_samples(torch.tensor([[3.0, 1.0]]), torch.tensor([[2.0]])),
                               torch.tensor([[1.0, 2.0, 3.0]]))


def _slow_scores(t, w, window, beta):
    t, w = t.numpy().astype(np.float64), w.numpy().astype(np.float64)
    n, s = t.shape
    out = np.zeros((n, s))
    left = (window - 1) // 2
    for r in range(n):
        gaps = [t[r, i + 1] - t[r, i] if i + 1 < s else t[r, s - 1] - t[r, s - 2] for i in range(s)]
        score = [beta * np.exp(-gaps[i]) + (1 - beta) * w[r, i] for i in range(s)]
        for i in range(s):
            acc = 0.0
            for j in range(window):
                k = min(max(i - left + j, 0), s - 1)  # edge-replicate padding
                acc += score[k] / window
            out[r, i] = acc
    return torch.tensor(out)


@pytest.mark.parametrize("window", [1, 3, 4, 5])
def test_sliding_window_scores_match_loop_reference(window):
    g = torch.Generator().manual_seed(window)
    t = torch.sort(torch.rand(5, 17, generator=g, dtype=torch.float64) * 4, -1).values
    w = torch.rand(5, 17, generator=g, dtype=torch.float64)
    w = w / w.sum(-1, keepdim=True)
    torch.testing.assert_close(sliding_window_scores(t, w, window, beta=0.3), _slow_scores(t, w, window, 0.3))


class _Slabs(Field):
    """Opaque slabs (sigma = 1000 / m) between the given z ranges."""

    def __init__(self, slabs, value=1010.0):
        super().__init__(FieldConfig(), [[-5.0, -5.0, -1.0], [5.0, 5.0, 10.0]])
        self.slabs, self.value = slabs, value

    def density_raw(self, xyz):
        raw = torch.full_like(xyz[:, 0], EMPTY_RAW)
        for z0, z1 in self.slabs:
            raw = torch.where((xyz[:, 2] >= z0) & (xyz[:, 2] <= z1), torch.full_like(raw, self.value), raw)
        return raw


def _rays(n):
    o = torch.zeros(n, 3)
    d = torch.cat([(torch.rand(n, 2, generator=torch.Generator().manual_seed(3)) - 0.5) * 0.5, torch.ones(n, 1)], -1)
    return o, d


def test_sliding_window_concentrates_on_an_opaque_slab():
    z0 = 2.37
    field = _Slabs([(z0, z0 + 0.5)])
    o, d = _rays(256)
    g = torch.Generator().manual_seed(0)
    t = stratified(torch.full((256,), 0.5), torch.full((256,), 4.5), 32, generator=g)  # spacing 12.5 cm
    w = render_weights(field, o, d, t).weights
    new = sliding_window_sample(t, w, 64, window=3, generator=g)
    assert new.shape == (256, 64) and (new.diff(dim=-1) >= 0).all()
    near_slab = ((new > z0 - 0.15) & (new < z0 + 0.15)).float().mean()
    assert near_slab > 0.8
    # the interval brackets the surface on every ray
    tn, tf = sliding_window_interval(t, w, 3)
    assert ((tn <= z0) & (tf >= z0)).all()
    # iterate as in the init stage (union with the previous samples, windows 3, 4, 5): tighter
    for window in (4, 5):
        t = merge_samples(t, new)
        w = render_weights(field, o, d, t).weights
        new = sliding_window_sample(t, w, 64, window=window, generator=g)
    assert ((new > z0 - 0.05) & (new < z0 + 0.05)).float().mean() > 0.9


def test_sliding_window_picks_the_surface_with_most_mass():
    """A thin first surface with a high single-sample peak vs. a second surface with more
    mass spread over three samples: the smoothed score selects the second one."""
    s = 40
    t = torch.linspace(1.0, 5.0, s).expand(2, s).contiguous()  # uniform: exp(-delta) is constant
    w = torch.zeros(2, s)
    w[:, 10] = 0.35
    w[:, 25:28] = 0.2
    tn, tf = sliding_window_interval(t, w, 3)
    assert (tn >= t[0, 24] - 1e-6).all() and (tf <= t[0, 28] + 1e-6).all()
    new = sliding_window_sample(t, w, 50, window=3, frac_pdf=0.4, generator=torch.Generator().manual_seed(0))
    in_second = ((new >= t[0, 24]) & (new <= t[0, 28])).float().mean()
    assert in_second > 0.6  # all 60 % window samples + the pdf share of the second surface
    # argmax of the raw weights would have chosen the first surface
    assert int(w[0].argmax()) == 10


def test_sliding_window_on_empty_rays_covers_the_whole_range():
    t = torch.linspace(0.5, 4.5, 32).expand(3, 32).contiguous()
    tn, tf = sliding_window_interval(t, torch.zeros(3, 32), 4)
    torch.testing.assert_close(tn, torch.full((3,), 0.5))
    torch.testing.assert_close(tf, torch.full((3,), 4.5))
    new = sliding_window_sample(t, torch.zeros(3, 32), 20, window=4, frac_pdf=0.4)
    assert (new >= 0.5).all() and (new <= 4.5).all()
    with pytest.raises(ValueError, match="window"):
        sliding_window_scores(t, torch.zeros(3, 32), 0)
