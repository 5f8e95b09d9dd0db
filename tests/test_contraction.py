"""The contracted space of unbounded scenes: exact small cases and properties of the map and of the march."""

import math

import pytest
import torch

from nerfmeta.fused import fused_kernels
from nerfmeta.render.contraction import (InnerBox, contract, from_march, fused_contraction, inner_box_from_cameras,
                                          inner_exit, to_march)
from nerfmeta.render.estimators import OccupancyGrid, contracted_march


def test_identity_inside_the_inner_box():
    p = torch.rand(1000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 2 - 1
    assert torch.equal(contract(p), p)


def test_exact_values_outside():
    p = torch.tensor([[2.0, 0.0, 0.0], [4.0, -4.0, 1.0], [0.0, 0.0, -1e12]], dtype=torch.float64)
    c = contract(p)
    assert torch.allclose(c[0], torch.tensor([1.5, 0.0, 0.0], dtype=torch.float64))  # (2 - 1/2) * (1, 0, 0)
    assert torch.allclose(c[1], torch.tensor([1.75, -1.75, 0.4375], dtype=torch.float64))  # (2 - 1/4) * p / 4
    assert torch.allclose(c[2], torch.tensor([0.0, 0.0, -2.0], dtype=torch.float64))
    half = contract(torch.tensor([[3.0, 0.0, 0.0]], dtype=torch.float64), shell=0.2)
    assert math.isclose(float(half[0, 0]), 1.2 - 0.2 / 3, rel_tol=1e-12)


def test_continuous_at_the_boundary():
    g = torch.Generator().manual_seed(1)
    dirs = torch.randn(500, 3, dtype=torch.float64, generator=g)
    on = dirs / dirs.abs().amax(-1, keepdim=True)  # |p|_inf == 1
    for eps in (1e-6, 1e-9):
        assert torch.allclose(contract(on * (1 + eps)), on, atol=3 * eps)
        assert torch.allclose(contract(on * (1 - eps)), on, atol=3 * eps)


@pytest.mark.parametrize("shell", [1.0, 0.25])
def test_bounded_and_monotone_along_rays_from_the_centre(shell):
    g = torch.Generator().manual_seed(2)
    dirs = torch.randn(200, 3, dtype=torch.float64, generator=g)
    t = torch.logspace(-3, 8, 400, dtype=torch.float64)
    pts = dirs[:, None, :] * t[None, :, None]
    norms = contract(pts.reshape(-1, 3), shell).abs().amax(-1).reshape(200, 400)
    assert float(norms.max()) <= 1 + shell
    assert bool((norms[:, 1:] > norms[:, :-1]).all())


def test_lines_stay_lines_of_positive_length_inside_the_cube():
    """Along any line, consecutive points stay apart after contraction (no folding) and inside the cube."""
    g = torch.Generator().manual_seed(3)
    o = torch.randn(100, 3, dtype=torch.float64, generator=g) * 3
    d = torch.randn(100, 3, dtype=torch.float64, generator=g)
    t = torch.linspace(0, 50, 300, dtype=torch.float64)
    c = contract((o[:, None] + d[:, None] * t[None, :, None]).reshape(-1, 3)).reshape(100, 300, 3)
    steps = torch.linalg.vector_norm(c[:, 1:] - c[:, :-1], dim=-1)
    assert bool((steps > 0).all()) and float(c.abs().max()) <= 2.0


def test_march_distance_round_trips_and_is_monotone():
    t1 = torch.tensor(2.0, dtype=torch.float64)
    t = torch.tensor([0.5, 2.0, 2.5, 10.0, 1e6], dtype=torch.float64)
    m = to_march(t, t1, 3.0)
    assert torch.equal(m[:2], t[:2])  # unchanged up to the inner exit
    assert bool((m[1:] > m[:-1]).all()) and float(m.max()) < 2.0 + 3.0
    assert torch.allclose(from_march(m, t1, 3.0), t, rtol=1e-9)
    # slope 1 at the exit: continuous marching
    assert math.isclose(float(to_march(t1 + 1e-6, t1, 3.0) - t1), 1e-6, rel_tol=1e-5)


def test_inner_box_from_cameras():
    centres = torch.tensor([[4.0, 0.0, 0.0], [-4.0, 0.0, 0.0], [0.0, 3.0, 1.0], [0.0, 0.0, 5.0]])
    box = inner_box_from_cameras(centres, torch.zeros(3), fraction=0.5)
    assert box.centre == (0.0, 0.0, 0.0) and box.radius == 2.0  # half the median distance, (4 + 4) / 2 / 2
    assert inner_box_from_cameras(centres, None).centre == tuple(centres.double().mean(0).tolist())


def test_contracted_march_exact_steps_and_lengths():
    box = InnerBox((0.0, 0.0, 0.0), 2.0, 1.0)
    o = torch.tensor([[0.5, 0.0, 0.0]], dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    near = torch.tensor([0.1], dtype=torch.float64)
    s = contracted_march(o, d, near, box, 0.05, torch.full((1,), 0.5, dtype=torch.float64))
    assert float(inner_exit(o, d, near, box)[0]) == 1.5
    inner = s.t < 1.5
    # inside: world step 0.05 * radius, contracted length 0.05
    assert torch.allclose(s.delta[inner], torch.full_like(s.delta[inner], 0.05))
    assert torch.allclose(s.t[1:4] - s.t[:3], torch.full((3,), 0.1, dtype=torch.float64))
    # the contracted length of the whole ray: from p = 0.3 to the cube's face at 2
    assert math.isclose(float(s.delta.sum()), 2.0 - 0.3, rel_tol=1e-5)
    # far field gets fewer samples per world unit: steps grow
    assert bool((s.t[1:] - s.t[:-1] >= 0.1 - 1e-9).all()) and float(s.t[-1] - s.t[-2]) > 50
    assert len(s) == round(1.7 / 0.05)


def test_occupancy_grid_looks_up_contracted_positions():
    box = InnerBox((0.0, 0.0, 0.0), 1.0, 1.0)
    marks = torch.zeros(9, 9, 9, dtype=torch.bool)
    marks[8, 4, 4] = True  # the far +x face of the contracted cube: the background
    grid = OccupancyGrid(torch.tensor([[-2.0] * 3, [2.0] * 3]), marks, box=box)
    o = torch.zeros(2, 3)
    d = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    s = grid.sampling(o, d, torch.zeros(2), torch.full((2,), 5.0), step=0.05, jitter=torch.full((2,), 0.5))
    assert len(s) > 0 and bool((s.ray_idx == 0).all())  # only the ray towards the mark keeps samples
    assert bool((box.contract(o[s.ray_idx] + s.t[:, None] * d[s.ray_idx])[:, 0] > 1.75).all())


@pytest.mark.skipif(not fused_contraction(torch.zeros(1, 3)), reason="numba is not installed (the fused kernels are optional)")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_fused_contraction_gives_pytorchs_values_and_layout(dtype):
    """The CPU kernel against :func:`contract` of the normalised points: near, far (1e12), on the box's faces, NaN and
    infinite coordinates; component-major out; a gradient still taken through PyTorch's ops."""
    g = torch.Generator().manual_seed(5)
    box = InnerBox((0.3, -0.2, 1.1), 1.7, shell=0.6)
    p = torch.cat([torch.randn(2000, 3, generator=g, dtype=torch.float64) * 4,
                   torch.tensor([[0.3 + 1.7, -0.2, 1.1], [1e12, 3.0, -2.0], [float("nan"), 5.0, 0.0],
                                 [0.0, float("inf"), 1.0], [-float("inf"), 0.0, 0.0]], dtype=torch.float64)]).to(dtype)
    points = p.t().contiguous().t()  # component-major, as sample points come
    fast = box.contract(points)
    with fused_kernels(False):
        slow = box.contract(points)
    assert fast.stride() == slow.stride() == (1, len(p))
    tol = {"rtol": 1e-12, "atol": 1e-12} if dtype == torch.float64 else {"rtol": 1e-6, "atol": 1e-6}
    torch.testing.assert_close(fast, slow, equal_nan=True, **tol)
    assert torch.isnan(fast[-3]).tolist() == torch.isnan(slow[-3]).tolist() == [True, False, False]
    rows = p.contiguous()  # row-major points (a grid's) take the kernel too
    torch.testing.assert_close(box.contract(rows), slow, equal_nan=True, **tol)
    leaf = points.detach().clone().requires_grad_()
    assert not fused_contraction(leaf) and box.contract(leaf).grad_fn is not None
    with torch.no_grad():
        assert fused_contraction(leaf)
