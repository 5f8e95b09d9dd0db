"""The fused trilinear lookups (numba) against PyTorch's gather path and float64 references."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from autograd_graph import count_nodes
from broken_numba import kernel_that_cannot_compile

from nerfmeta import fused
from nerfmeta.data.scene import RayBatch
from nerfmeta.fields import grid_kernels
from nerfmeta.fields.grid_kernels import fused_available, fused_lookups, trilinear_coords
from nerfmeta.fields.grid_ops import corners_from_coords, trilinear_gather
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig

needs_numba = pytest.mark.skipif(not fused_available(), reason="numba is not installed (the fused kernels are optional)")
SIZE = (4, 5, 6)


def _coords(n: int, generator: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    """(3, n) corner coordinates, a tenth of them outside the grid on some axis (clamped to the faces)."""
    top = torch.tensor([s - 1 for s in SIZE], dtype=dtype)[:, None]
    return (torch.rand(3, n, generator=generator, dtype=dtype) * 1.2 - 0.1) * top


def _reference(grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation written out per corner in float64 (independent of both paths)."""
    top = torch.tensor([s - 1 for s in grid.shape[1:]], dtype=torch.float64)[:, None]
    x = x.double().clamp(torch.zeros_like(top), top)
    i0 = torch.minimum(x.floor(), top - 1).long()
    f = x - i0
    out = torch.zeros(grid.shape[0], x.shape[1], dtype=torch.float64)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1]) * (f[2] if dz else 1 - f[2])
                out += w * grid.double()[:, i0[0] + dx, i0[1] + dy, i0[2] + dz]
    return out


@needs_numba
@pytest.mark.parametrize("channels", [1, 3, 12])
def test_fused_lookup_equals_the_float64_reference_and_the_gather_path(channels):
    g = torch.Generator().manual_seed(channels)
    grid = torch.randn(channels, *SIZE, generator=g, dtype=torch.float64)
    x = _coords(500, g)
    got = trilinear_coords(grid, x)
    torch.testing.assert_close(got, _reference(grid, x), rtol=0, atol=1e-12)
    with fused_lookups(False):
        torch.testing.assert_close(trilinear_coords(grid, x), got, rtol=0, atol=1e-12)
    # float32: the same values to float32's rounding
    got32 = trilinear_coords(grid.float(), x.float())
    assert got32.dtype == torch.float32
    torch.testing.assert_close(got32.double(), _reference(grid, x.float()), rtol=0, atol=1e-5)


@needs_numba
def test_fused_lookup_hits_corners_exactly_and_clamps_outside_points_to_the_faces():
    g = torch.Generator().manual_seed(5)
    grid = torch.randn(2, *SIZE, generator=g, dtype=torch.float64)
    corners = torch.stack(torch.meshgrid(*[torch.arange(s, dtype=torch.float64) for s in SIZE], indexing="ij")).reshape(3, -1)
    torch.testing.assert_close(trilinear_coords(grid, corners), grid.reshape(2, -1), rtol=0, atol=0)
    far = torch.tensor([[-5.0, 99.0], [-5.0, 99.0], [-5.0, 99.0]], dtype=torch.float64)
    torch.testing.assert_close(trilinear_coords(grid, far), torch.stack([grid[:, 0, 0, 0], grid[:, -1, -1, -1]], 1))


@needs_numba
def test_fused_lookup_never_reads_outside_the_grid_for_nan_or_infinite_coordinates():
    grid = torch.arange(2 * 2 * 2, dtype=torch.float32).reshape(1, 2, 2, 2).requires_grad_()
    x = torch.tensor([[float("nan"), float("inf"), -float("inf")]] * 3)
    out = trilinear_coords(grid, x)
    torch.testing.assert_close(out.detach(), torch.tensor([[0.0, 7.0, 0.0]]))  # NaN and -inf: corner 0; +inf: the last
    out.sum().backward()
    want = torch.zeros(8)
    want[0], want[7] = 2.0, 1.0
    torch.testing.assert_close(grid.grad.reshape(-1), want)


@needs_numba
def test_fused_gradients_pass_gradcheck_and_gradgradcheck_in_float64():
    g = torch.Generator().manual_seed(3)
    grid = torch.randn(3, *SIZE, generator=g, dtype=torch.float64, requires_grad=True)
    x = _coords(40, g)
    torch.autograd.gradcheck(lambda v: trilinear_coords(v, x), (grid,))
    torch.autograd.gradgradcheck(lambda v: trilinear_coords(v, x) ** 2, (grid,))  # MAML differentiates the backward


@needs_numba
def test_fused_backward_equals_the_gather_paths_scatter():
    g = torch.Generator().manual_seed(4)
    grid = torch.randn(3, *SIZE, generator=g, dtype=torch.float32, requires_grad=True)
    x = _coords(3000, g, torch.float32)  # many points per corner: the scatter accumulates
    upstream = torch.randn(3, 3000, generator=g)
    (trilinear_coords(grid, x) * upstream).sum().backward()
    fused = grid.grad.clone()
    grid.grad = None
    (trilinear_gather(grid.view(3, -1), *corners_from_coords(x, SIZE)) * upstream).sum().backward()
    torch.testing.assert_close(fused, grid.grad, rtol=1e-5, atol=1e-4)


@needs_numba
@pytest.mark.parametrize("threads", [2, 3])
def test_lookups_split_over_threads_give_the_one_thread_values_and_gradients_bit_for_bit(threads, monkeypatch):
    g = torch.Generator().manual_seed(threads)
    grid = torch.randn(3, *SIZE, generator=g, dtype=torch.float32, requires_grad=True)
    x = _coords(5000, g, torch.float32)  # ~40 points a cell: every corner plane is written by many points
    upstream = torch.randn(3, 5000, generator=g)

    monkeypatch.setenv("GOMP_SPINCOUNT", "10000")
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)

    def lookup_and_grad(parts: int):
        monkeypatch.setattr(grid_kernels, "SPLIT_MIN_POINTS", 1000)
        monkeypatch.setattr(torch, "get_num_threads", lambda: parts)
        grid.grad = None
        out = trilinear_coords(grid, x)
        (out * upstream).sum().backward()
        return out.detach(), grid.grad.clone()

    calls = []
    real_split = fused.split
    monkeypatch.setattr(fused, "split", lambda kernel, args: (calls.append(len(args)), real_split(kernel, args)))
    one, split = lookup_and_grad(1), lookup_and_grad(threads)
    assert calls == [1, 1, threads, threads]  # the lookup and its scatter, each split
    assert torch.equal(one[0], split[0]) and torch.equal(one[1], split[1])
    torch.testing.assert_close(one[0].double(), _reference(grid.detach(), x), rtol=0, atol=1e-5)


@pytest.mark.parametrize(("spincount", "policy", "split"), [
    (None, None, False), ("300000", None, False), ("infinite", None, False), ("10000", None, True),
    ("0", None, True), (None, "PASSIVE", True), ("300000", "passive", True), (None, "active", False),
])
def test_lookups_split_only_while_openmp_workers_wait_briefly(spincount, policy, split, monkeypatch):
    for name, value in (("GOMP_SPINCOUNT", spincount), ("OMP_WAIT_POLICY", policy)):
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    assert fused.short_openmp_wait() is split
    assert grid_kernels._parts(10**6) == (2 if split else 1)
    assert grid_kernels._parts(grid_kernels.SPLIT_MIN_POINTS - 1) == 1


def _sorting(monkeypatch, shift: int = 1) -> None:
    """Every lookup of 1000 points or more visits its points by blocks of ``2**shift`` cells (as a grid larger than the cache would)."""
    monkeypatch.setattr(grid_kernels, "SPLIT_MIN_POINTS", 1000)
    monkeypatch.setattr(grid_kernels, "SORT_MIN_BYTES", 0)
    monkeypatch.setattr(grid_kernels, "SORT_BLOCK_SHIFT", shift)


@needs_numba
def test_block_order_is_a_stable_sort_of_the_points_by_grid_block():
    g = torch.Generator().manual_seed(8)
    size = (9, 7, 12)
    x = torch.rand(3, 2000, generator=g) * torch.tensor([[s - 1.0] for s in size])
    x[:, :5] = torch.tensor([[8.0, 0.0, 3.9, -1.0, float("nan")], [6.0, 0.0, 2.0, 0.5, 1.0], [11.0, 0.0, 4.0, 0.5, 1.0]])
    order, ordered = grid_kernels._kernels().block_order(x.numpy(), *size, 2)
    # independently: lower corner (clamped to size - 2, NaN to 0), block = corner // 4, keys in x-y-z memory order
    top = torch.tensor([[s - 2] for s in size])
    corner = torch.minimum(torch.nan_to_num(x, nan=0.0).clamp(min=0).floor().long(), top)
    blocks = [int(t) // 4 + 1 for t in top[:, 0]]
    key = ((corner[0] // 4) * blocks[1] + corner[1] // 4) * blocks[2] + corner[2] // 4
    assert torch.equal(torch.from_numpy(order), torch.sort(key, stable=True).indices)
    torch.testing.assert_close(torch.from_numpy(ordered), x[:, order], rtol=0, atol=0, equal_nan=True)
    assert key[order].diff().min() >= 0 and len(set(order.tolist())) == 2000


@needs_numba
@pytest.mark.parametrize("threads", [1, 2])
def test_lookups_visiting_points_by_block_give_the_same_values_and_the_same_gradients_to_rounding(threads, monkeypatch):
    g = torch.Generator().manual_seed(9)
    size = (12, 10, 14)
    grid = torch.randn(3, *size, generator=g, requires_grad=True)
    x = (torch.rand(3, 6000, generator=g) * 1.2 - 0.1) * torch.tensor([[s - 1.0] for s in size])
    upstream = torch.randn(3, 6000, generator=g)
    monkeypatch.setenv("GOMP_SPINCOUNT", "10000")
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)

    def lookup_and_grad():
        grid.grad = None
        out = trilinear_coords(grid, x)
        (out * upstream).sum().backward()
        return out.detach(), grid.grad.clone()

    monkeypatch.setattr(grid_kernels, "SPLIT_MIN_POINTS", 1000)
    ray_order = lookup_and_grad()
    _sorting(monkeypatch)
    orders = []
    real = grid_kernels._ordered
    monkeypatch.setattr(grid_kernels, "_ordered", lambda *a: orders.append(real(*a)) or orders[-1])
    by_block = lookup_and_grad()
    assert len(orders) == 1 and len(orders[0][0]) == 6000  # sorted once; the backward's scatter reuses the order
    with torch.no_grad():  # a render: its chunks' rays are coherent already, so it keeps their order
        assert torch.equal(trilinear_coords(grid, x), ray_order[0]) and len(orders[-1][0]) == 0
    trilinear_coords(grid.detach(), x)
    assert len(orders) == 3 and len(orders[-1][0]) == 0
    assert torch.equal(by_block[0], ray_order[0])  # each point's arithmetic is unchanged
    assert not torch.equal(by_block[1], ray_order[1])  # the scatter's sums do run in another order
    torch.testing.assert_close(by_block[1], ray_order[1], rtol=1e-5, atol=1e-5)
    if threads == 2:  # split over threads, by block: still the one-thread result bit for bit
        monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
        assert all(torch.equal(a, b) for a, b in zip(lookup_and_grad(), by_block))


@needs_numba
def test_lookups_visiting_points_by_block_pass_gradcheck_and_gradgradcheck(monkeypatch):
    _sorting(monkeypatch, shift=0)
    monkeypatch.setattr(grid_kernels, "SPLIT_MIN_POINTS", 30)
    g = torch.Generator().manual_seed(10)
    grid = torch.randn(2, *SIZE, generator=g, dtype=torch.float64, requires_grad=True)
    x = _coords(40, g)
    torch.autograd.gradcheck(lambda v: trilinear_coords(v, x), (grid,))
    torch.autograd.gradgradcheck(lambda v: trilinear_coords(v, x) ** 2, (grid,))


def test_only_grids_larger_than_the_last_level_cache_are_visited_by_block(tmp_path, monkeypatch):
    for index, (level, size) in enumerate([(1, "32K"), (1, "32K"), (2, "512K"), (3, "16M")]):
        (tmp_path / f"index{index}").mkdir()
        (tmp_path / f"index{index}" / "level").write_text(f"{level}\n")
        (tmp_path / f"index{index}" / "size").write_text(f"{size}\n")
    assert grid_kernels.last_level_cache_bytes(tmp_path) == 16 << 20
    assert grid_kernels.last_level_cache_bytes(tmp_path / "missing") == 32 << 20
    monkeypatch.setattr(grid_kernels, "SORT_MIN_BYTES", 16 << 20)
    x = torch.zeros(3, grid_kernels.SPLIT_MIN_POINTS)
    assert len(grid_kernels._ordered((1, 256, 128, 128), 4, x)[0]) == 0  # exactly the cache's size: as given
    if fused_available():
        assert len(grid_kernels._ordered((1, 256, 128, 129), 4, x)[0]) == x.shape[1]
        assert len(grid_kernels._ordered((1, 256, 128, 129), 4, x[:, 1:])[0]) == 0  # too few points to pay


@pytest.mark.parametrize(("code", "before", "after"), [
    ("import nerfmeta", None, "10000"),  # as the CLI starts: nerfmeta before torch
    ("import nerfmeta", "250", "250"),  # the user's own value is kept
    ("import torch, nerfmeta", None, None),  # torch first: too late for libgomp, so left alone
])
def test_importing_nerfmeta_before_torch_shortens_the_openmp_spin(code, before, after):
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    if before is not None:
        env["GOMP_SPINCOUNT"] = before
    done = subprocess.run([sys.executable, "-c", code + "; import os; print(os.environ.get('GOMP_SPINCOUNT'))"],
                          capture_output=True, text=True, env=env, timeout=120, check=True)
    assert done.stdout.strip() == str(after)


def test_switched_off_or_not_float_the_lookup_falls_back_to_the_gather_path():
    g = torch.Generator().manual_seed(6)
    grid = torch.randn(2, *SIZE, generator=g, dtype=torch.float64, requires_grad=True)
    x = _coords(30, g)
    with fused_lookups(False):
        out = trilinear_coords(grid, x)
    assert "TrilinearGather" in type(out.grad_fn).__name__
    torch.testing.assert_close(out, _reference(grid.detach(), x), rtol=0, atol=1e-12)
    mixed = trilinear_coords(grid, x.float())  # dtypes differ: not the kernel's case
    assert "TrilinearGather" in type(mixed.grad_fn).__name__


BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _rays_into_the_box(n: int, seed: int) -> RayBatch:
    """``n`` rays from near (0, 0, -3) towards +z through :data:`BOX`, with random targets."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, -3.0])
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    return RayBatch(origins, directions, torch.full((n,), 1.0), torch.full((n,), 5.0), torch.rand(n, 3, generator=g))


@needs_numba
def test_a_voxel_grid_trains_to_the_same_step_with_either_lookup():
    """One forward and backward of a real VoxelGrid: the same loss and gradients from both paths."""
    config = VoxelGridConfig(num_voxels=12**3, coarse_num_voxels=8**3, coarse_iters=0, view_dependent=True)
    rays = _rays_into_the_box(64, 7)
    results = []
    for fused in (True, False):
        torch.manual_seed(0)
        model = VoxelGrid(config, BOX)
        with torch.no_grad():
            model.density.normal_(0, 1, generator=torch.Generator().manual_seed(8))
        model.begin_step(1, None)
        with fused_lookups(fused):
            torch.manual_seed(1)
            out = model(rays, background=torch.ones(3))
            assert count_nodes(out.rgb, "TrilinearCoords" if fused else "TrilinearGather") == 2  # density and features
            loss = ((out.rgb - rays.target) ** 2).mean()
            loss.backward()
        results.append((loss.detach(), {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}))
    (loss_a, grads_a), (loss_b, grads_b) = results
    torch.testing.assert_close(loss_a, loss_b)
    assert grads_a.keys() == grads_b.keys() and {"density", "features"} <= grads_a.keys()
    for k in grads_a:
        torch.testing.assert_close(grads_a[k], grads_b[k], rtol=1e-4, atol=1e-6)


def test_interp_points_equals_interp_gather_with_world_points_outside_the_box_clamped():
    from nerfmeta.fields.grid_kernels import interp_points
    from nerfmeta.fields.grid_ops import interp_gather

    g = torch.Generator().manual_seed(9)
    grid = torch.randn(4, *SIZE, generator=g, dtype=torch.float64)
    bounds = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 0.5, 3.0]], dtype=torch.float64)
    points = bounds[0] + torch.rand(200, 3, generator=g, dtype=torch.float64) * 1.4 * (bounds[1] - bounds[0]) \
        - 0.2 * (bounds[1] - bounds[0])
    got = interp_points(grid, points, bounds)
    assert got.shape == (200, 4)
    torch.testing.assert_close(got, interp_gather(grid, points, bounds), rtol=0, atol=1e-12)


@needs_numba
def test_a_numba_that_cannot_compile_means_the_pytorch_path_with_a_warning(monkeypatch):
    from nerfmeta.fields import _grid_numba

    with kernel_that_cannot_compile(monkeypatch, _grid_numba, "gather"):
        with pytest.warns(UserWarning, match="numba could not compile the grid lookups .*no LLVM target"):
            assert not fused_available()
        g = torch.Generator().manual_seed(10)
        grid = torch.randn(2, *SIZE, generator=g, dtype=torch.float64)
        x = _coords(20, g)
        torch.testing.assert_close(trilinear_coords(grid, x), _reference(grid, x), rtol=0, atol=1e-12)
    assert fused_available()


def test_a_fit_loads_the_kernels_before_its_clock_starts(tiny_scene, tmp_path, monkeypatch):
    """The once-per-process load is not in the first step's time of whichever fit runs first."""
    from nerfmeta.fields import voxel_grid
    from nerfmeta.fit import run as run_module
    from nerfmeta.fit.run import RunConfig, run_fit

    events = []
    monkeypatch.setattr(voxel_grid.VoxelGrid, "warm_up", classmethod(lambda cls: events.append("warm_up")))
    real_build = run_module.build_initial_model
    monkeypatch.setattr(run_module, "build_initial_model", lambda *a, **k: (events.append("build"), real_build(*a, **k))[1])
    model = {"num_voxels": 6**3, "coarse_num_voxels": 4**3, "coarse_iters": 1, "growth_steps": []}
    from nerfmeta.fit.loop import FitConfig

    run_fit(RunConfig(scene=str(tiny_scene), backbone="grid", init="scratch", model=model,
                      fit=FitConfig(iters=2, eval_every=0, checkpoint_every=0, final_ssim=False), renders=0), tmp_path / "run")
    assert events[:2] == ["warm_up", "build"]


@needs_numba
@pytest.mark.parametrize("view_dependent", [False, True])  # 3 feature channels (fused at test time) or 9 (grid_sample)
def test_test_time_renders_give_the_same_image_with_or_without_the_fused_kernels(view_dependent):
    config = VoxelGridConfig(num_voxels=12**3, coarse_num_voxels=8**3, coarse_iters=0, view_dependent=view_dependent)
    rays = _rays_into_the_box(128, 11)
    torch.manual_seed(0)
    model = VoxelGrid(config, BOX)
    with torch.no_grad():
        model.density.normal_(0, 1, generator=torch.Generator().manual_seed(12))
        model.features.normal_(0, 1, generator=torch.Generator().manual_seed(13))
    model.begin_step(1, None)
    model.eval()
    images = []
    for fused in (True, False):
        with fused_lookups(fused), torch.no_grad():
            images.append(model(rays, background=torch.ones(3)).rgb)
    assert images[0].std() > 0.02  # a real image, not a blank
    torch.testing.assert_close(images[0], images[1], rtol=0, atol=1e-3)  # grid_sample rounds its coordinates


@needs_numba
def test_large_gradient_buffers_are_recycled_only_once_no_tensor_holds_them(monkeypatch):
    """A scatter's gradient is reused (zeroed) only after every tensor made from it is gone, never while held."""
    monkeypatch.setattr(grid_kernels, "RECYCLE_MIN_BYTES", 1000)
    monkeypatch.setattr(grid_kernels, "_SPARES", type(grid_kernels._SPARES)())
    g = torch.Generator().manual_seed(21)
    grid = torch.randn(3, *SIZE, generator=g, dtype=torch.float64, requires_grad=True)  # 2880 bytes: recycled
    x = _coords(50, g)

    def grad_of(weights):
        (grad,) = torch.autograd.grad((trilinear_coords(grid, x) * weights).sum(), grid)
        return grad

    w1, w2 = torch.randn(3, 50, generator=g, dtype=torch.float64), torch.randn(3, 50, generator=g, dtype=torch.float64)
    first = grad_of(w1)
    expected_first = first.clone()
    second = grad_of(w2)  # the first is held: a new buffer
    assert first.data_ptr() != second.data_ptr()
    torch.testing.assert_close(first, expected_first, rtol=0, atol=0)
    view = first[0]  # a view holds the buffer as well
    address = first.data_ptr()
    del first
    third = grad_of(w2)
    third_address = third.data_ptr()
    assert third_address not in (address, second.data_ptr()) and view.data_ptr() == address
    del view, third
    fourth = grad_of(w1)  # the first and third buffers are free now: one is reused, zeroed first
    assert fourth.data_ptr() in (address, third_address)
    torch.testing.assert_close(fourth, expected_first, rtol=0, atol=0)
    small = torch.randn(1, 2, 2, 2, dtype=torch.float64, requires_grad=True)  # 64 bytes: a fresh buffer each time
    (a,) = torch.autograd.grad(trilinear_coords(small, torch.full((3, 1), 0.5, dtype=torch.float64)).sum(), small)
    assert len(grid_kernels._SPARES) == 1
    assert len(next(iter(grid_kernels._SPARES.values()))) == 2  # the third buffer, made while two were held, was not kept
