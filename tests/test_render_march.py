"""The fused marches (numba) against PyTorch's, through a contracted space and through a box: the same samples, skips,
windows and threads."""

import pytest
import torch

from broken_numba import kernel_that_cannot_compile
from kernel_threads import split_over

from nerfmeta.fused import fused_kernels
from nerfmeta.render import estimators
from nerfmeta.render.contraction import InnerBox
from nerfmeta.render.estimators import (OccupancyGrid, contracted_march, contracted_march_fused, fused_march_available,
                                        march_fused, march_packed)

needs_numba = pytest.mark.skipif(not fused_march_available(), reason="numba is not installed (the fused kernels are optional)")

BOX = InnerBox((0.3, -0.2, 0.5), 1.5, shell=0.8)


def _rays(n: int, dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Rays from inside and outside the inner box (cameras stand in the shell), some starting past their exit:
    origins, directions, near, far (to infinity), jitter."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.tensor(BOX.centre) + torch.randn(n, 3, generator=g, dtype=torch.float64) * 2.5
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    directions[0] = torch.tensor([1.0, 0.0, 0.0])  # axis-aligned
    near = torch.rand(n, generator=g, dtype=torch.float64) * 0.5
    near[1] = 40.0  # far beyond the box: a short march in the shell
    jitter = torch.rand(n, generator=g, dtype=torch.float64)
    return origins.to(dtype), directions.to(dtype), near.to(dtype), torch.full((n,), 1e10, dtype=dtype), jitter.to(dtype)


def _grid(seed: int = 1) -> OccupancyGrid:
    g = torch.Generator().manual_seed(seed)
    marks = torch.rand(24, 20, 22, generator=g) < 0.6
    return OccupancyGrid(torch.tensor([[-BOX.extent] * 3, [BOX.extent] * 3]), marks, box=BOX)


def _box_grid(seed: int = 2) -> OccupancyGrid:
    g = torch.Generator().manual_seed(seed)
    return OccupancyGrid(torch.tensor([[-1.0, -0.8, -1.2], [1.1, 0.9, 1.0]]), torch.rand(17, 13, 19, generator=g) < 0.5)


def _box_rays(n: int, dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Rays from a shell of cameras around the box towards points in it, and a few that miss it."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1) * 3.0
    directions = torch.nn.functional.normalize(torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5 - origins / 3, dim=-1)
    directions[:3] = -directions[:3]  # away from the box: no samples
    jitter = torch.rand(n, generator=g, dtype=torch.float64)
    return origins.to(dtype), directions.to(dtype), torch.zeros(n, dtype=dtype), torch.full((n,), 8.0, dtype=dtype), jitter.to(dtype)


SPACES = {"contracted": (_grid, _rays, 0.03), "box": (_box_grid, _box_rays, 0.01)}
"""Each space's occupancy grid, rays and step."""


def _both(grid: OccupancyGrid, rays, skip: bool = True, step: float = 0.03) -> tuple[estimators.PackedSamples, ...]:
    """The grid's samples of ``rays`` (origins, directions, near, far, jitter) with the kernels and with PyTorch's ops."""
    o, d, near, far, jitter = rays
    out = [grid.sampling(o, d, near, far, step=step, jitter=jitter, skip_empty=skip)]
    with fused_kernels(False):
        out.append(grid.sampling(o, d, near, far, step=step, jitter=jitter, skip_empty=skip))
    return tuple(out)


@needs_numba
@pytest.mark.parametrize("space", SPACES)
@pytest.mark.parametrize("skip", [True, False])
def test_the_fused_march_keeps_pytorchs_samples_in_float64(space, skip):
    make_grid, make_rays, step = SPACES[space]
    grid, rays = make_grid(), make_rays(300, torch.float64)
    fast, slow = _both(grid, rays, skip, step)
    assert len(fast) > 3000 and torch.equal(fast.ray_idx, slow.ray_idx) and torch.equal(fast.far, slow.far)
    torch.testing.assert_close(fast.t, slow.t, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fast.delta, slow.delta, rtol=1e-7, atol=1e-12)
    if skip:  # the skip dropped samples, and only those whose nearest corner is unmarked
        everything = _both(grid, rays, False, step)[0]
        assert len(fast) < 0.8 * len(everything)
        assert bool(grid.lookup(fast, *rays[:2]).all())


@needs_numba
@pytest.mark.parametrize("seed", [0, 1])
def test_the_fused_march_in_float32_is_closer_to_float64_than_pytorchs_on_average(seed):
    """In float32 both paths round, the shell's far samples most (their world distance is a difference of near-equal
    numbers, from the same float32 marching interval): both within 0.5 % of the float64 march everywhere, the kernel,
    which works in float64 inside, closer on average (its median error about 2e-8 against PyTorch's 8e-8 for ``t``
    and 1e-6 for ``delta``)."""
    grid = _grid()
    rays32 = _rays(300, torch.float32, seed)
    fast, slow = _both(grid, rays32, skip=False)
    exact = _both(grid, tuple(r.double() for r in rays32), skip=False)[1]
    assert torch.equal(fast.ray_idx, exact.ray_idx) and torch.equal(slow.ray_idx, exact.ray_idx)
    for name in ("t", "delta"):
        ref = getattr(exact, name)
        err_fast = (getattr(fast, name).double() - ref).abs() / ref.abs().clamp(min=1e-6)
        err_slow = (getattr(slow, name).double() - ref).abs() / ref.abs().clamp(min=1e-6)
        assert err_fast.max() < 5e-3 and err_slow.max() < 5e-3, name
        assert err_fast.mean() < err_slow.mean() and err_fast.median() < err_slow.median(), name


@needs_numba
@pytest.mark.parametrize(("first", "limit"), [(0, 7), (5, 11), (200, None), (10**6, 4)])
def test_a_window_of_the_march_is_the_same_window(first, limit):
    o, d, near, _, jitter = _rays(50, torch.float64, seed=3)
    fast = contracted_march_fused(o, d, near, BOX, 0.03, jitter, first, limit)
    slow = contracted_march(o, d, near, BOX, 0.03, jitter, first, limit)
    assert torch.equal(fast.ray_idx, slow.ray_idx) and torch.equal(fast.far, slow.far)
    torch.testing.assert_close(fast.t, slow.t, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fast.delta, slow.delta, rtol=1e-7, atol=1e-12)


@needs_numba
@pytest.mark.parametrize("space", SPACES)
@pytest.mark.parametrize("threads", [2, 3])
def test_split_over_threads_the_march_is_the_one_thread_march_bit_for_bit(space, threads, monkeypatch):
    make_grid, make_rays, step = SPACES[space]
    grid, (o, d, near, far, jitter) = make_grid(), make_rays(200, torch.float32, seed=4)
    near[150:] = 1e12  # the last rays have no samples: a part may get none
    one = grid.sampling(o, d, near, far, step=step, jitter=jitter)
    calls = split_over(monkeypatch, threads, estimators, "MARCH_SPLIT_MIN_SAMPLES")
    split = grid.sampling(o, d, near, far, step=step, jitter=jitter)
    assert calls == [threads] and len(split) > 1000
    assert all(torch.equal(getattr(split, k), getattr(one, k)) for k in ("ray_idx", "t", "delta", "far"))


@needs_numba
def test_no_rays_and_rays_without_samples_march_to_nothing():
    o, d, near, _, jitter = _rays(4, torch.float32)
    empty = contracted_march_fused(o[:0], d[:0], near[:0], BOX, 0.03, jitter[:0])
    assert len(empty) == 0 and empty.far.shape == (0,)
    none = contracted_march_fused(o, d, near, BOX, 0.03, jitter, first=10**9)
    assert len(none) == 0 and none.far.shape == (4,)


@needs_numba
def test_a_numba_that_cannot_compile_means_pytorchs_march_with_a_warning(monkeypatch):
    from nerfmeta.render import _march_numba

    grid = _grid()
    o, d, near, far, jitter = _rays(40, torch.float32, seed=6)
    with fused_kernels(False):
        expected = grid.sampling(o, d, near, far, step=0.03, jitter=jitter)
    with kernel_that_cannot_compile(monkeypatch, _march_numba, "march"):
        with pytest.warns(UserWarning, match="numba could not compile the march kernel .*no LLVM target"):
            assert not fused_march_available()
        got = grid.sampling(o, d, near, far, step=0.03, jitter=jitter)
    assert fused_march_available()
    # PyTorch's march (the contraction's own kernel still at work in the skip: the same values to rounding)
    assert torch.equal(got.ray_idx, expected.ray_idx) and torch.equal(got.far, expected.far)
    torch.testing.assert_close(got.t, expected.t, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(got.delta, expected.delta, rtol=1e-6, atol=1e-6)


@needs_numba
def test_the_fused_march_through_a_box_in_float32_is_pytorchs_to_rounding():
    grid = _box_grid()
    rays32 = _box_rays(300, torch.float32, seed=1)
    fast, slow = _both(grid, rays32, False, 0.01)
    assert torch.equal(fast.ray_idx, slow.ray_idx)
    torch.testing.assert_close(fast.t, slow.t, rtol=2e-6, atol=2e-6)
    torch.testing.assert_close(fast.delta, slow.delta, rtol=2e-5, atol=2e-6)
    kept = _both(grid, rays32, True, 0.01)  # a sample on a corner's rounding boundary may go either way: a handful at most
    assert abs(len(kept[0]) - len(kept[1])) <= 3


@needs_numba
@pytest.mark.parametrize(("first", "limit"), [(0, 7), (5, 11), (150, None)])
def test_a_window_of_the_march_through_a_box_is_the_same_window(first, limit):
    o, d, near, far, jitter = _box_rays(50, torch.float64, seed=3)
    near, far = near + 1.0, far - 3.0
    fast = march_fused(o, d, near, far, 0.01, jitter, first, limit)
    ray_idx, t, delta = march_packed(near, far, 0.01, jitter, first, limit)
    assert torch.equal(fast.ray_idx, ray_idx)
    torch.testing.assert_close(fast.t, t, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(fast.delta, delta, rtol=1e-9, atol=1e-12)
