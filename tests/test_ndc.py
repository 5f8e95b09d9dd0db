"""NDC rays (nerfmeta.render.ndc) against float64 references from the projective map itself."""

from __future__ import annotations

import math

import pytest
import torch

from nerfmeta.render.ndc import (
    average_pose,
    metric_depth,
    ndc_box,
    ndc_rays,
    ndc_space,
    ndc_z_to_camera_z,
    to_ndc,
)
from nerfmeta.render.rays import camera_rays

F64 = torch.float64
FOCAL, W, H = 50.0, 64.0, 48.0


def ndc_point(p: torch.Tensor, near: float = 1.0) -> torch.Tensor:
    """(n, 3) camera-frame points -> NDC by the definition (NeRF appendix C)."""
    ax, ay = 2 * FOCAL / W, 2 * FOCAL / H
    x, y, z = p.unbind(-1)
    return torch.stack([-ax * x / z, -ay * y / z, 1 + 2 * near / z], -1)


def random_rays(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    o = (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * 0.4
    d = torch.cat([(torch.rand(n, 2, generator=g, dtype=F64) - 0.5), -torch.ones(n, 1, dtype=F64)], -1)
    return o, d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("near", [1.0, 0.5])
def test_points_on_a_ray_lie_on_the_ndc_ray_at_nerfs_parameter(near):
    o, d = random_rays(16)
    o_ndc, d_ndc = ndc_rays(o, d, FOCAL, W, H, near)
    t_near = -(near + o[:, 2]) / d[:, 2]
    o_near = o + t_near[:, None] * d  # on the near plane
    for t in (0.0, 0.3, 2.0, 17.0, 1e4):
        p = o_near + t * d
        t_ndc = 1 - o_near[:, 2] / p[:, 2]  # NeRF's t' for the point
        assert torch.allclose(ndc_point(p, near), o_ndc + t_ndc[:, None] * d_ndc, atol=1e-12, rtol=0)


def test_near_plane_goes_to_minus_one_and_infinity_to_plus_one():
    o, d = random_rays(8)
    o_ndc, d_ndc = ndc_rays(o, d, FOCAL, W, H, 1.0)
    assert torch.allclose(o_ndc[:, 2], torch.full((8,), -1.0, dtype=F64), atol=1e-14)
    assert torch.allclose((o_ndc + d_ndc)[:, 2], torch.ones(8, dtype=F64), atol=1e-14)
    z = torch.tensor([-1.0, -2.0, -4.0, -1e9], dtype=F64)
    z_ndc = ndc_point(torch.stack([torch.zeros(4, dtype=F64), torch.zeros(4, dtype=F64), z], -1))[:, 2]
    assert torch.allclose(z_ndc, 1 - 2 / z.abs(), atol=1e-15)
    assert torch.allclose(ndc_z_to_camera_z(z_ndc[:3]), z[:3], atol=1e-12)


def test_the_frustum_maps_to_the_unit_square():
    # rays through the image corners from the camera centre hit x', y' = +-1
    corners = torch.tensor([[0.0, 0.0], [W, 0.0], [W, H], [0.0, H]], dtype=F64)
    o, d = camera_rays(torch.eye(4, dtype=F64), torch.tensor([FOCAL, FOCAL, W / 2, H / 2], dtype=F64), corners)
    o_ndc, d_ndc = ndc_rays(o, d, FOCAL, W, H)
    expected = torch.tensor([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]], dtype=F64)
    assert torch.allclose(o_ndc[:, :2], expected, atol=1e-12)
    assert torch.allclose(d_ndc[:, :2], torch.zeros(4, 2, dtype=F64), atol=1e-12)  # centre rays stay put


def test_average_pose_of_one_pose_is_that_pose():
    c, s = math.cos(0.3), math.sin(0.3)
    pose = torch.tensor([[c, 0, s, 1.0], [0, 1, 0, 2.0], [-s, 0, c, 3.0], [0, 0, 0, 1]], dtype=F64)
    assert torch.allclose(average_pose(torch.stack([pose, pose])), pose, atol=1e-12)
    # two cameras turned +-0.3 about y average to the unturned camera at their mean centre
    other = pose.clone()
    other[0, 2], other[2, 0], other[:3, 3] = -s, s, torch.tensor([3.0, 2.0, 3.0])
    other[0, 0] = other[2, 2] = c
    mean = average_pose(torch.stack([pose, other]))
    assert torch.allclose(mean[:3, :3], torch.eye(3, dtype=F64), atol=1e-12)
    assert torch.allclose(mean[:3, 3], torch.tensor([2.0, 2.0, 3.0], dtype=F64))


def scene_cameras():
    poses = torch.eye(4, dtype=F64).repeat(4, 1, 1)
    poses[:, :3, 3] = torch.tensor([[0.1, 0.0, 5.0], [-0.1, 0.0, 5.0], [0.0, 0.1, 5.1], [0.0, -0.1, 4.9]], dtype=F64)
    intr = torch.tensor([FOCAL, FOCAL, W / 2, H / 2], dtype=F64).expand(4, 4)
    return poses, intr


@pytest.mark.parametrize("depth_scale", [1.0, 0.5])
def test_metric_depth_inverts_the_map_and_the_box_holds_every_ray(depth_scale):
    poses, intr = scene_cameras()
    space = ndc_space(poses, intr, int(H), int(W), near=2.0, depth_scale=depth_scale)
    assert space.scale == pytest.approx(1 / (0.75 * 2.0))
    g = torch.Generator().manual_seed(1)
    pix = torch.rand(64, 2, generator=g, dtype=F64) * torch.tensor([W, H], dtype=F64)
    view = torch.randint(4, (64,), generator=g)
    o, d = camera_rays(poses[view], intr[view], pix)
    t_world = 2.0 + 50 * torch.rand(64, generator=g, dtype=F64)
    o_ndc, u, length = to_ndc(space, o, d)
    assert torch.allclose(u.norm(dim=-1), torch.ones(64, dtype=F64))
    assert torch.allclose((o_ndc + length[:, None] * u)[:, 2], torch.full((64,), depth_scale, dtype=F64))
    # the NDC image of the world point at t_world, and its distance along the unit NDC ray
    o_ref = (o + t_world[:, None] * d - space.reference[:3, 3]) @ space.reference[:3, :3] * space.scale
    p_ndc = ndc_point(o_ref) * torch.tensor([1.0, 1.0, depth_scale], dtype=F64)
    s = ((p_ndc - o_ndc) * u).sum(-1)
    assert torch.allclose(o_ndc + s[:, None] * u, p_ndc, atol=1e-10)  # on the NDC ray
    assert torch.allclose(metric_depth(space, o, d, s), t_world, rtol=1e-9)
    box = ndc_box(space, poses, intr, int(H), int(W))
    assert torch.all(p_ndc >= box[0] - 1e-12) and torch.all(p_ndc <= box[1] + 1e-12)
    assert box[0, 2] == -depth_scale and box[1, 2] == depth_scale


def test_ndc_space_needs_a_positive_near():
    poses, intr = scene_cameras()
    with pytest.raises(ValueError, match="near"):
        ndc_space(poses, intr, 48, 64, near=0.0)
