"""The learned start's fused feature kernel (nerfmeta.priors._features_numba) against PyTorch's features."""

from __future__ import annotations

import pytest
import torch

import nerfmeta.priors.occupancy as occupancy
from broken_numba import kernel_that_cannot_compile
from kernel_threads import split_over
from nerfmeta.fused import fused_kernels
from nerfmeta.priors.occupancy import GridViews, fused_inputs_available, occupancy_inputs
from nerfmeta.render.cameras import look_at
from test_carve import grid_model
from test_occupancy_start import constant_net, sphere_scene

needs_numba = pytest.mark.skipif(not fused_inputs_available(), reason="numba is not installed (the fused kernels are optional)")

SIZE = (9, 10, 11)


def random_views(dtype: torch.dtype, seed: int = 0, n_views: int = 7) -> GridViews:
    """Cameras 2 units from the origin looking at it, random masks and colours on 13 x 17 images, and grid points
    filling [-3, 3]^3: some behind a camera, some outside its image, some on its edges."""
    g = torch.Generator().manual_seed(seed)
    eyes = torch.nn.functional.normalize(torch.randn(n_views, 3, generator=g), dim=-1) * 2.0
    poses = look_at(eyes, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    intrinsics = torch.tensor([12.0, 14.0, 8.5, 6.5]).repeat(n_views, 1)
    masks = torch.rand(n_views, 13, 17, generator=g) > 0.4
    images = torch.rand(n_views, 13, 17, 3, generator=g)
    axes = [torch.linspace(-3, 3, s) for s in SIZE]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return GridViews(points.to(dtype), masks, images.to(dtype), poses.to(dtype), intrinsics.to(dtype))


@needs_numba
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_fused_inputs_are_pytorchs_in_float64(seed):
    views = random_views(torch.float64, seed)
    with fused_kernels(False):
        expected, expected_allowed = occupancy_inputs(views, SIZE)
    got, allowed = occupancy_inputs(views, SIZE)
    assert got.shape == expected.shape == (occupancy.N_FEATURES, *SIZE) and got.dtype == torch.float32
    assert torch.equal(allowed, expected_allowed) and 0 < int(allowed.sum()) < allowed.numel()
    seen = expected[0].reshape(-1)
    assert 0 < int((seen == 0).sum()) and 0 < int(((seen > 0) & (seen < 1)).sum())  # the cases the points were made for
    torch.testing.assert_close(got, expected.float(), rtol=0, atol=1e-6)  # the spread: a sum of squares, not two passes


@needs_numba
def test_the_fused_inputs_of_a_float32_scene_start_the_same_voxels():
    scene, model = sphere_scene(), grid_model()
    views = occupancy.grid_views(model, scene)
    with fused_kernels(False):
        expected, expected_allowed = occupancy_inputs(views, model.size)
        before = occupancy.learned_grid_start(model, scene, torch.ones(3), constant_net(-1.0), threshold=0.2)
    got, allowed = occupancy_inputs(views, model.size)
    after = occupancy.learned_grid_start(model, scene, torch.ones(3), constant_net(-1.0), threshold=0.2)
    assert torch.equal(allowed, expected_allowed) and before.figures == after.figures
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-5)


@needs_numba
@pytest.mark.parametrize("threads", [2, 3])
def test_split_over_threads_the_inputs_are_the_one_thread_inputs_bit_for_bit(threads, monkeypatch):
    views = random_views(torch.float32, seed=4)
    one = occupancy_inputs(views, SIZE)
    calls = split_over(monkeypatch, threads, occupancy, "FUSED_SPLIT_MIN_POINTS")
    split = occupancy_inputs(views, SIZE)
    assert calls == [threads]
    assert torch.equal(split[0], one[0]) and torch.equal(split[1], one[1])


@needs_numba
def test_a_numba_that_cannot_compile_means_pytorchs_inputs_with_a_warning(monkeypatch):
    from nerfmeta.priors import _features_numba

    views = random_views(torch.float64, seed=5)
    with fused_kernels(False):
        expected = occupancy_inputs(views, SIZE)
    with kernel_that_cannot_compile(monkeypatch, _features_numba, "point_inputs"):
        with pytest.warns(UserWarning, match="numba could not compile the learned start's feature kernel .*no LLVM target"):
            assert not fused_inputs_available()
        got = occupancy_inputs(views, SIZE)
    assert fused_inputs_available()
    assert torch.equal(got[0], expected[0].float()) and torch.equal(got[1], expected[1])


def test_the_projection_rows_give_the_pixel_times_the_depth():
    views = random_views(torch.float64, seed=6)
    m = occupancy.projection_matrices(views.poses, views.intrinsics)
    homogeneous = torch.cat([views.points, torch.ones(len(views.points), 1, dtype=torch.float64)], 1)
    xyd = torch.einsum("vij,nj->vni", m, homogeneous)
    from nerfmeta.priors.carve import project

    xy, front = project(views.points, views.poses, views.intrinsics)
    assert torch.equal(front, xyd[..., 2] > 1e-6)
    torch.testing.assert_close(xyd[..., :2][front] / xyd[..., 2:][front], xy[front], rtol=1e-10, atol=1e-9)
