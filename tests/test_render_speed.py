"""The fast test-time path: marching windows, early termination in rounds, and the grid's evaluation renders
(the same samples and colours as the reference path, training untouched)."""

import dataclasses

import pytest
import torch

from nerfmeta.data.scene import RayBatch
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig
from nerfmeta.render.contraction import InnerBox
from nerfmeta.render.estimators import OccupancyGrid, march_packed
from nerfmeta.render.volume import packed_transmittance

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)


def _rays(n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1) * 3.0
    directions = torch.nn.functional.normalize(0.5 * torch.randn(n, 3, generator=g, dtype=dtype) - origins, dim=-1)
    return origins, directions, torch.full((n,), 1.0, dtype=dtype), torch.full((n,), 5.0, dtype=dtype)


def test_march_windows_tile_the_whole_march():
    near = torch.tensor([0.0, 1.0, 2.0, 0.3], dtype=torch.float64)
    far = torch.tensor([1.0, 1.0, 2.95, 0.31], dtype=torch.float64)
    jitter = torch.tensor([0.5, 0.1, 0.9, 0.3], dtype=torch.float64)
    whole = march_packed(near, far, 0.1, jitter)
    parts = [march_packed(near, far, 0.1, jitter, first, 3) for first in range(0, 12, 3)]
    ray_idx = torch.cat([p[0] for p in parts])
    order = torch.sort(ray_idx, stable=True).indices
    for k in range(3):
        assert torch.equal(torch.cat([p[k] for p in parts])[order], whole[k])


@pytest.mark.parametrize("box", [None, InnerBox((0.0, 0.0, 0.0), 1.0, 1.0)])
@pytest.mark.parametrize("skip", [False, True])
def test_rounds_keep_exactly_the_samples_of_one_pass(box, skip):
    marks = torch.rand(9, 9, 9, generator=torch.Generator().manual_seed(0)) > 0.3
    aabb = BOX if box is None else 2 * BOX
    grid = OccupancyGrid(aabb, marks, box=box)
    origins, directions, near, far = _rays(40)
    jitter = torch.rand(40, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ball = lambda p, s: 20.0 * (p.norm(dim=-1) < 0.6).to(p.dtype) + 0.05  # an opaque ball in a faint haze
    kw = dict(step=0.02, jitter=jitter, skip_empty=skip, sigma_fn=ball, early_stop_eps=1e-3)
    one = grid.sampling(origins, directions, near, far, **kw)
    rounds = grid.sampling(origins, directions, near, far, round_samples=7, **kw)
    for name in ("ray_idx", "t", "delta", "far"):
        assert torch.equal(getattr(rounds, name), getattr(one, name)), name
    everything = grid.sampling(origins, directions, near, far, step=0.02, jitter=jitter, skip_empty=skip)
    assert len(one) < len(everything)
    tau = ball(everything.points(origins, directions), everything) * everything.delta
    assert torch.equal(one.t, everything.t[packed_transmittance(tau, everything.ray_idx, 40) >= 1e-3])


def _trained_like_grid(config):
    """A grid with an opaque textured ball (what a fit leaves), MLP weights random."""
    model = VoxelGrid(config, BOX.float())
    with torch.no_grad():
        pts = torch.stack(torch.meshgrid(*[torch.linspace(-1, 1, s) for s in model.size], indexing="ij"), -1)
        model.density.copy_(torch.where(pts.norm(dim=-1) < 0.5, 6.0, -20.0)[None])
        model.features.normal_(generator=torch.Generator().manual_seed(3))
        for p in model.mlp.parameters():
            p.normal_(std=0.3, generator=torch.Generator().manual_seed(4))
    return model


def test_grid_evaluation_renders_match_the_reference_path_and_training_is_untouched():
    base = VoxelGridConfig(coarse_iters=0, num_voxels=32**3, growth_steps=(), mlp_width=16, feature_dim=4)
    fast = _trained_like_grid(dataclasses.replace(base, render_stop_eps=1e-4))
    slow = _trained_like_grid(base)  # the default: the one-pass path
    o, d, near, far = _rays(300, seed=2, dtype=torch.float32)
    rays = RayBatch(o, d, near, far)
    white = torch.ones(3)
    with torch.no_grad():
        a, b = fast(rays, background=white), slow(rays, background=white)
    assert a.samples_evaluated < 0.85 * b.samples_evaluated
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=2e-4)  # what lies behind T < 1e-4 is dropped
    # training renders never terminate early: the same samples and gradients
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    ta = fast(rays, background=white, train=True, generator=g1)
    tb = slow(rays, background=white, train=True, generator=g2)
    assert ta.samples_evaluated == tb.samples_evaluated and torch.equal(ta.rgb, tb.rgb)


def test_cpu_render_chunks_and_threads_change_nothing_but_the_speed(monkeypatch):
    """``render_rays`` on a CPU: the colours and sample count of one big chunk, whatever the chunk size and
    the number of worker threads; torch's thread count restored; the caller's grad mode reaches the workers."""
    import nerfmeta.fit.evaluate as evaluate

    model = _trained_like_grid(VoxelGridConfig(coarse_iters=0, num_voxels=32**3, growth_steps=(), mlp_width=16, feature_dim=4))
    model.eval()
    o, d, near, far = _rays(301, seed=6, dtype=torch.float32)
    rays, white = RayBatch(o, d, near, far), torch.ones(3)
    with torch.no_grad():
        whole = model(rays, background=white)
        monkeypatch.setattr(evaluate, "CPU_CHUNK_RAYS", 37)  # 9 chunks, the last one short
        threads = torch.get_num_threads()
        for workers in (1, 3):
            rgb, samples = evaluate.render_rays(model, rays, white, workers=workers)
            assert samples == whole.samples_evaluated
            torch.testing.assert_close(rgb, whole.rgb, rtol=0, atol=1e-6)
            assert torch.get_num_threads() == threads
    rgb, _ = evaluate.render_rays(model, rays, white, workers=2)
    assert rgb.requires_grad  # rendered with gradients where the caller asked for them


def test_channels_last_copies_live_only_while_kept():
    """Inside ``kept`` a copy is made once and reused (nested blocks share it); after the block, or outside
    one, every call copies the grid as it is now: no copy outlives a change of its grid. A deep copy
    of the owner starts empty."""
    import copy

    from nerfmeta.fields.grid_ops import ChannelsLastCopies

    grid = torch.nn.Parameter(torch.arange(2 * 3 * 4 * 5, dtype=torch.float32).reshape(2, 3, 4, 5))
    copies = ChannelsLastCopies()
    loose = copies.get("g", grid)
    assert torch.equal(loose, grid.detach()) and loose.stride(0) == 1  # channels innermost
    assert copies.get("g", grid) is not loose
    with copies.kept():
        first = copies.get("g", grid)
        with copies.kept():
            assert copies.get("g", grid) is first
        assert copies.get("g", grid) is first and copy.deepcopy(copies)._copies == {}
    with torch.no_grad():
        grid.data = grid.data + 1.0  # a change no version counter sees
    with copies.kept():
        assert torch.equal(copies.get("g", grid), grid.detach())


def test_colour_mlp_in_pieces_equals_one_pass(monkeypatch):
    """Without gradient the colour MLP runs its rows in pieces (cache-sized), in place; the logits are those of one
    pass with gradient, and its inputs (features as the grid hands them over: a strided view) are left untouched."""
    import nerfmeta.fields.voxel_grid as voxel_grid

    torch.manual_seed(0)
    mlp = voxel_grid.ColorMLP(feature_dim=4, view_dim=9, width=16, depth=3)
    for p in mlp.parameters():
        torch.nn.init.normal_(p, std=0.5)
    grid_values, view = torch.randn(7, 1001), torch.randn(40, 9)  # (C, N), as the grid's lookups return them
    features = grid_values[3:].t()  # (N, 4), not contiguous
    ray_idx = torch.sort(torch.randint(0, 40, (1001,))).values
    whole = mlp(features, view, ray_idx)  # grad enabled: one pass
    before = grid_values.clone(), view.clone()
    monkeypatch.setattr(voxel_grid, "MLP_PIECE_ROWS", 97)
    with torch.no_grad():
        pieces = mlp(features, view, ray_idx)
    torch.testing.assert_close(pieces, whole.detach(), rtol=0, atol=1e-6)
    assert torch.equal(grid_values, before[0]) and torch.equal(view, before[1])
