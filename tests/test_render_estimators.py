"""The occupancy-grid estimator: packed marching, empty-space skipping, early termination, updates."""

import math

import torch

from nerfmeta.render.estimators import OccupancyGrid, PackedSamples, early_termination_keep, grid_points, march_packed, split_sections, values_near
from nerfmeta.render.sampling import fixed_step_samples
from nerfmeta.render.volume import packed_transmittance

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_march_packed_equals_fixed_step_samples():
    near = torch.tensor([2.0, 2.5, 3.0, 1.0], dtype=torch.float64)
    far = torch.tensor([3.0, 2.5, 3.35, 1.1], dtype=torch.float64)  # a zero-length ray, partial last bins
    jitter = torch.tensor([0.5, 0.1, 0.9, 0.0], dtype=torch.float64)
    step = 0.1
    ray_idx, t, delta = march_packed(near, far, step, jitter)
    t_d, delta_d, valid = fixed_step_samples(near, far, step, 12, perturb=False)
    assert ray_idx.tolist() == valid.nonzero()[:, 0].tolist()
    t_ref = near[:, None] + step * torch.arange(12, dtype=torch.float64) + delta_d * jitter[:, None]
    torch.testing.assert_close(t, t_ref[valid])
    torch.testing.assert_close(delta, delta_d[valid])
    torch.testing.assert_close(torch.zeros(4, dtype=torch.float64).index_add(0, ray_idx, delta), far - near)


def _rays(n: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g, dtype=torch.float64)
    origins = 3.0 * origins / origins.norm(dim=-1, keepdim=True)
    aim = torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5
    directions = torch.nn.functional.normalize(aim - origins, dim=-1)
    return origins, directions, torch.full((n,), 0.5, dtype=torch.float64), torch.full((n,), 6.0, dtype=torch.float64)


def _occupancy(size=(9, 9, 9), seed=1) -> OccupancyGrid:
    binaries = torch.rand(size, generator=torch.Generator().manual_seed(seed)) < 0.3
    return OccupancyGrid(BOX, binaries)


def test_skipped_samples_are_exactly_those_in_empty_cells():
    grid = _occupancy()
    origins, directions, near, far = _rays(40)
    jitter = torch.rand(40, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    everything = grid.sampling(origins, directions, near, far, step=0.05, jitter=jitter, skip_empty=False)
    kept = grid.sampling(origins, directions, near, far, step=0.05, jitter=jitter)
    # the marks of every marched sample, by the nearest corner of its world position
    points = everything.points(origins, directions)
    ijk = ((points - BOX[0].double()) / 2.0 * 8).round().long().clamp(0, 8)
    marks = grid.binaries[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    assert 0 < int(marks.sum()) < len(everything)
    assert torch.equal(kept.t, everything.t[marks]) and torch.equal(kept.ray_idx, everything.ray_idx[marks])
    assert torch.equal(kept.delta, everything.delta[marks])
    assert bool((kept.ray_idx[1:] >= kept.ray_idx[:-1]).all())  # still packed


def test_marching_stays_in_the_box_and_covers_each_ray_inside_it():
    grid = OccupancyGrid(BOX)  # no grid: nothing skipped
    origins, directions, near, far = _rays(30, seed=4)
    s = grid.sampling(origins, directions, near, far, step=0.1, jitter=torch.full((30,), 0.5, dtype=torch.float64))
    assert bool((s.points(origins, directions).abs() <= 1 + 1e-9).all())
    covered = torch.zeros(30, dtype=torch.float64).index_add(0, s.ray_idx, s.delta)
    from nerfmeta.render.rays import clip_to_aabb
    n_in, f_in, _ = clip_to_aabb(origins, directions, near, far, BOX.double())
    torch.testing.assert_close(covered, f_in - n_in)
    torch.testing.assert_close(s.far, f_in)


def test_early_termination_drops_only_samples_behind_low_transmittance():
    # one ray of 6 samples: T in front of each = exp(-cumulative tau before it)
    tau = torch.tensor([0.1, 2.0, 3.0, 0.5, 0.1, 0.1], dtype=torch.float64)
    ray_idx = torch.zeros(6, dtype=torch.long)
    trans = [math.exp(-c) for c in (0.0, 0.1, 2.1, 5.1, 5.6, 5.7)]
    torch.testing.assert_close(packed_transmittance(tau, ray_idx, 1), torch.tensor(trans, dtype=torch.float64))
    eps = 1e-2
    keep = early_termination_keep(tau, ray_idx, 1, eps)
    assert keep.tolist() == [t >= eps for t in trans] == [True, True, True, False, False, False]


def test_early_termination_in_sampling_with_a_density_callback():
    grid = OccupancyGrid(BOX)
    origins, directions, near, far = _rays(25, seed=5)
    jitter = torch.full((25,), 0.5, dtype=torch.float64)
    ball = lambda p, s: 50.0 * (p.norm(dim=-1) < 0.5).to(p.dtype)  # an opaque ball
    everything = grid.sampling(origins, directions, near, far, step=0.02, jitter=jitter)
    eps = 1e-3
    kept = grid.sampling(origins, directions, near, far, step=0.02, jitter=jitter, sigma_fn=ball, early_stop_eps=eps)
    tau = ball(everything.points(origins, directions), everything) * everything.delta
    trans = packed_transmittance(tau, everything.ray_idx, 25)
    assert torch.equal(kept.t, everything.t[trans >= eps])
    assert len(kept) < len(everything)


def test_prune_only_unmarks_and_refresh_follows_the_field():
    grid = OccupancyGrid(BOX, torch.ones(5, 5, 5, dtype=torch.bool))
    inside = lambda p: (p.norm(dim=-1) < 0.6).to(p.dtype)  # alpha 1 inside a ball, 0 outside
    grid.prune(inside, threshold=0.5, dilation=0)
    corners = grid_points(BOX, (5, 5, 5))
    assert torch.equal(grid.binaries, corners.norm(dim=-1) < 0.6)
    grid.prune(lambda p: torch.ones(len(p)), threshold=0.5, dilation=0)  # pruning never adds marks
    assert torch.equal(grid.binaries, corners.norm(dim=-1) < 0.6)
    grid.prune(lambda p: torch.zeros(len(p)), threshold=0.5, dilation=0)  # nothing left: refused
    assert int(grid.binaries.sum()) == int((corners.norm(dim=-1) < 0.6).sum())
    grid.refresh(lambda p: torch.ones(len(p)), (3, 4, 5), threshold=0.5, dilation=0)  # refresh adds marks
    assert grid.binaries.shape == (3, 4, 5) and bool(grid.binaries.all())


def test_values_near_evaluates_only_below_the_limit():
    points = torch.arange(6.0).reshape(6, 1).expand(6, 3)
    seen = []

    def fn(p):
        seen.append(p[:, 0].tolist())
        return p[:, 0] * 10.0

    values, n = values_near(fn, points, None, 1.0, chunk=4)  # nothing known: every point, in chunks
    assert values.tolist() == [0.0, 10.0, 20.0, 30.0, 40.0, 50.0] and n == 6 and seen == [[0, 1, 2, 3], [4, 5]]
    seen.clear()
    known = torch.tensor([0.5, 9.0, 1.5, 0.0, 3.0, 2.0])
    values, n = values_near(fn, points, known, 2.0)
    assert seen == [[0.0, 2.0, 3.0]] and n == 3
    assert values.tolist() == [0.0, 9.0, 20.0, 30.0, 3.0, 2.0] and known.tolist()[2] == 1.5  # known is not written
    values, n = values_near(fn, points, known, -1.0)
    assert n == 0 and torch.equal(values, known)


def test_packed_samples_select_keeps_order_and_far():
    s = PackedSamples(torch.tensor([0, 0, 1, 2]), torch.tensor([1.0, 2.0, 1.5, 0.3]), torch.full((4,), 0.1), torch.ones(3))
    sub = s.select(torch.tensor([1, 3]))
    assert sub.ray_idx.tolist() == [0, 2] and torch.equal(sub.t, s.t[[1, 3]]) and sub.far is s.far


def test_split_sections_refines_marked_sections_in_place():
    s = PackedSamples(torch.tensor([0, 0, 1, 1, 1]), torch.tensor([1.0, 2.0, 0.5, 1.5, 2.5]), torch.ones(5), torch.full((2,), 3.0))
    r = split_sections(s, torch.tensor([False, True, False, True, False]), 4)
    assert r.ray_idx.tolist() == [0] * 5 + [1] * 6 and r.far is s.far
    assert r.t.tolist() == [1.0, 1.625, 1.875, 2.125, 2.375, 0.5, 1.125, 1.375, 1.625, 1.875, 2.5]
    assert r.delta.tolist() == [1.0] + [0.25] * 4 + [1.0] + [0.25] * 4 + [1.0]
    assert split_sections(s, torch.ones(5, dtype=torch.bool), 1) is s


def test_split_sections_keeps_each_rays_length_and_order():
    near = torch.tensor([0.0, 0.3, 1.0], dtype=torch.float64)
    far = torch.tensor([1.0, 2.05, 1.0], dtype=torch.float64)
    s = PackedSamples(*march_packed(near, far, 0.1, torch.full((3,), 0.5, dtype=torch.float64)), far)
    split = torch.arange(len(s)) % 3 == 0
    r = split_sections(s, split, 5)
    assert len(r) == len(s) + 4 * int(split.sum())
    torch.testing.assert_close(torch.zeros(3, dtype=torch.float64).index_add(0, r.ray_idx, r.delta), far - near)
    same_ray = r.ray_idx[1:] == r.ray_idx[:-1]
    assert bool((r.t[1:][same_ray] > r.t[:-1][same_ray]).all())
