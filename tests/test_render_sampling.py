"""Samplers: coverage of the ray interval and inverse-CDF behaviour."""

import torch

from nerfmeta.render.sampling import (
    fixed_step_samples,
    importance_samples,
    intervals_from_points,
    stratified_samples,
)


def test_stratified_midpoints_and_bin_widths():
    near, far = torch.tensor([2.0, 1.0]), torch.tensor([6.0, 1.0])
    t, delta, edges = stratified_samples(near, far, 4, perturb=False)
    assert t[0].tolist() == [2.5, 3.5, 4.5, 5.5]
    assert delta[0].tolist() == [1.0] * 4
    assert delta[1].tolist() == [0.0] * 4  # zero-length interval
    g = torch.Generator().manual_seed(0)
    t, delta, edges = stratified_samples(near, far, 4, generator=g)
    assert ((t >= edges[:, :-1]) & (t <= edges[:, 1:])).all()


def test_fixed_step_covers_exactly_near_to_far():
    near, far = torch.tensor([0.0, 1.0, 3.0]), torch.tensor([1.0, 1.25, 3.0])
    t, delta, valid = fixed_step_samples(near, far, 0.1, 12, perturb=False)
    torch.testing.assert_close(delta.sum(-1), far - near, atol=1e-5, rtol=0)
    assert valid.sum(-1).tolist() == [10, 3, 0]
    assert (t[valid] < far.repeat_interleave(valid.sum(-1))).all()


def test_importance_samples_follow_the_weights():
    edges = torch.linspace(0, 1, 11).expand(2, 11).contiguous()
    weights = torch.zeros(2, 10)
    weights[0, 3] = 1.0  # all mass in [0.3, 0.4]
    weights[1] = 1.0  # uniform
    s = importance_samples(edges, weights, 8, perturb=False, eps=0.0)
    assert ((s[0] >= 0.3) & (s[0] <= 0.4)).all()
    torch.testing.assert_close(s[1], (torch.arange(8) + 0.5) / 8)
    g = torch.Generator().manual_seed(0)
    s = importance_samples(edges, torch.zeros(2, 10), 64, generator=g)  # zero weights: uniform
    assert (s >= 0).all() and (s <= 1).all() and (s.diff(dim=-1) >= 0).all()


def test_intervals_from_points_partition_the_ray():
    t = torch.tensor([[2.5, 3.0, 5.0]])
    d = intervals_from_points(t, torch.tensor([2.0]), torch.tensor([6.0]))
    assert d[0].tolist() == [0.75, 1.25, 2.0]
