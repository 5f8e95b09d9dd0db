"""Scene bounds from camera frusta (nerfmeta.data.bounds)."""

from __future__ import annotations

import math

import pytest
import torch

from nerfmeta.data.bounds import frustum_bounds
from nerfmeta.render.rays import camera_rays


def test_frustum_bounds_use_corner_and_centre_rays() -> None:
    # One camera at the origin looking down -z, 2x2 px, f = 1, a 3x3 grid of rays: the corner rays
    # are (+-1, +-1, -1)/sqrt(3), the edge-middle rays (+-1, 0, -1)/sqrt(2), the centre ray (0, 0, -1).
    pose = torch.eye(4, dtype=torch.float64)[None]
    intrinsics = torch.tensor([[1.0, 1.0, 1.0, 1.0]], dtype=torch.float64)
    box = frustum_bounds(pose, intrinsics, 2, 2, near=1.0, far=2.0, grid=3)
    r2, r3 = math.sqrt(2), math.sqrt(3)
    # x, y extremes: far along the edge-middle rays; z: far along the centre ray, near at the corners
    expected = torch.tensor([[-2 / r2, -2 / r2, -2.0], [2 / r2, 2 / r2, -1 / r3]], dtype=torch.float64)
    torch.testing.assert_close(box, expected)
    o, d = camera_rays(pose[0], intrinsics[0], torch.tensor([[2.0, 1.0]], dtype=torch.float64))
    torch.testing.assert_close((o + 2 * d)[0, 0], expected[1, 0])
    # moving the camera moves the box
    moved = pose.clone()
    moved[0, :3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    shifted = frustum_bounds(moved, intrinsics, 2, 2, near=1.0, far=2.0, grid=3)
    torch.testing.assert_close(shifted, expected + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))


def test_frustum_bounds_contain_every_pixel_ray_segment() -> None:
    gen = torch.Generator().manual_seed(0)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    intrinsics = torch.tensor([7.0, 6.0, 4.0, 3.5], dtype=torch.float64)
    box = frustum_bounds(pose[None], intrinsics[None], 7, 8, near=0.5, far=3.0)
    pixels = torch.rand(200, 2, generator=gen, dtype=torch.float64) * torch.tensor([8.0, 7.0], dtype=torch.float64)
    o, d = camera_rays(pose, intrinsics, pixels)
    for t in (0.5, 1.7, 3.0):
        p = o + t * d
        assert bool(((p >= box[0] - 1e-2) & (p <= box[1] + 1e-2)).all())


def test_frustum_bounds_rejects_a_one_ray_grid() -> None:
    with pytest.raises(ValueError):
        frustum_bounds(torch.eye(4)[None], torch.ones(1, 4), 2, 2, 1.0, 2.0, grid=1)
