"""Camera paths for videos (:mod:`nerfmeta.render.paths`): orbits look at the centre, spirals stay near the mean pose."""

from __future__ import annotations

import math

import pytest
import torch

from nerfmeta.render.cameras import look_at
from nerfmeta.render.paths import (
    focus_depth,
    is_walk,
    look_at_centre,
    mean_pose,
    nearest_rotation,
    orbit_path,
    smooth_keys,
    spiral_path,
    walk_path,
)

UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def ring(n: int, centre=(0.5, -1.0, 0.25), radius: float = 4.0, height: float = 2.0, turn: float = 1.0) -> torch.Tensor:
    c = torch.tensor(centre, dtype=torch.float64)
    az = torch.arange(n, dtype=torch.float64) * (2 * math.pi * turn / n)
    eyes = c + torch.stack([radius * torch.cos(az), radius * torch.sin(az), torch.full_like(az, height)], -1)
    return look_at(eyes, c.expand_as(eyes), UP.expand_as(eyes))


def forward_facing(n: int = 12, seed: int = 0) -> torch.Tensor:
    """Cameras on a 1 x 0.6 patch of the plane y = 0, all looking along +y at a wall 5 units away."""
    g = torch.Generator().manual_seed(seed)
    eyes = torch.stack([torch.rand(n, generator=g, dtype=torch.float64) - 0.5, torch.zeros(n, dtype=torch.float64),
                        0.6 * (torch.rand(n, generator=g, dtype=torch.float64) - 0.5)], -1)
    targets = eyes + torch.tensor([0.0, 5.0, 0.0], dtype=torch.float64) + 0.1 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    return look_at(eyes, targets, UP.expand_as(eyes))


def test_look_at_centre_of_a_ring() -> None:
    torch.testing.assert_close(look_at_centre(ring(7)), torch.tensor([0.5, -1.0, 0.25], dtype=torch.float64))


def test_parallel_axes_have_no_centre() -> None:
    poses = look_at(torch.tensor([[0.0, 0, 0], [1.0, 0, 0]], dtype=torch.float64),
                    torch.tensor([[0.0, 5, 0], [1.0, 5, 0]], dtype=torch.float64), UP.expand(2, 3))
    with pytest.raises(ValueError, match="parallel"):
        look_at_centre(poses)


def test_orbit_looks_at_the_centre_at_the_cameras_distance_and_height() -> None:
    cams = ring(5, turn=0.5)  # half a ring: the orbit still goes all the way round
    path = orbit_path(cams, 24)
    centre = torch.tensor([0.5, -1.0, 0.25], dtype=torch.float64)
    to_centre = centre - path[:, :3, 3]
    to_centre = to_centre / to_centre.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(-path[:, :3, 2], to_centre)  # every frame looks at the centre
    offsets = path[:, :3, 3] - centre
    torch.testing.assert_close(offsets[:, 2], torch.full((24,), 2.0, dtype=torch.float64))
    torch.testing.assert_close(offsets[:, :2].norm(dim=-1), torch.full((24,), 4.0, dtype=torch.float64))
    torch.testing.assert_close(path[0], cams[0])  # it starts at the first camera
    angles = torch.atan2(offsets[:, 1], offsets[:, 0])
    assert float(torch.remainder(angles[12] - angles[0], 2 * math.pi)) == pytest.approx(math.pi)  # a full turn
    rot = path[:, :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(24, 3, 3))


def test_spiral_stays_near_the_mean_pose_and_looks_at_the_focus() -> None:
    cams = forward_facing()
    mean = mean_pose(cams)
    depth = focus_depth(1.0, 10.0)
    path = spiral_path(cams, 40, depth)
    local = (path[:, :3, 3] - mean[:3, 3]) @ mean[:3, :3]
    spread = ((cams[:, :3, 3] - mean[:3, 3]) @ mean[:3, :3]).abs().max(0).values
    assert bool((local.abs() <= spread + 1e-9).all())  # within the cameras' own spread, axis by axis
    focus = mean[:3, 3] - depth * mean[:3, 2]
    to_focus = focus - path[:, :3, 3]
    torch.testing.assert_close(-path[:, :3, 2], to_focus / to_focus.norm(dim=-1, keepdim=True))
    angle = torch.rad2deg(torch.acos((-path[:, :3, 2] @ -mean[:3, 2]).clamp(-1, 1)))
    assert float(angle.max()) < 10.0  # they all look roughly the mean way


def test_mean_pose_of_identical_cameras_is_that_camera() -> None:
    cam = ring(3)[1]
    torch.testing.assert_close(mean_pose(cam.expand(4, 4, 4)), cam)


def test_focus_depth_is_llffs_harmonic_blend() -> None:
    assert focus_depth(2.0, 8.0) == pytest.approx(1.0 / (0.25 / 2.0 + 0.75 / 8.0))




def test_an_unsmoothed_walk_passes_through_every_camera() -> None:
    cams = ring(12, turn=0.5)
    path = walk_path(cams, 3 * 11 + 1, smooth=0)
    torch.testing.assert_close(path[::3], cams, rtol=0, atol=1e-12)


def test_walk_frames_are_cameras_between_their_neighbours() -> None:
    cams = ring(24, turn=1.5, radius=4.0)  # one and a half times round, as a phone video walks
    path = walk_path(cams, 100)
    rot = path[:, :3, :3]
    torch.testing.assert_close(rot.transpose(-1, -2) @ rot, torch.eye(3, dtype=torch.float64).expand(100, 3, 3), rtol=0, atol=1e-9)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(100, dtype=torch.float64))
    offsets = path[:, :3, 3] - torch.tensor([0.5, -1.0, 0.25], dtype=torch.float64)
    radius = torch.linalg.vector_norm(offsets[:, :2], dim=-1)
    assert float((radius - 4.0).abs().max()) < 0.1 and float((offsets[:, 2] - 2.0).abs().max()) < 1e-9  # 2.5 % on 22.5-degree steps
    forward = -path[:, :3, 2]  # every frame still looks at the ring's centre, to within two degrees
    cosine = (forward * -offsets).sum(-1) / torch.linalg.vector_norm(offsets, dim=-1)
    assert float(cosine.min()) > math.cos(math.radians(2.0))


def test_smoothing_takes_out_a_shake_and_keeps_the_ends() -> None:
    cams = ring(30, turn=0.5)
    shaken = cams.clone()
    shaken[1:-1, :3, 3] += 0.2 * torch.tensor([1.0, -1.0, 0.5], dtype=torch.float64) * (
        (-1.0) ** torch.arange(28, dtype=torch.float64))[:, None]
    smooth = smooth_keys(shaken, 2)
    torch.testing.assert_close(smooth[[0, -1]], shaken[[0, -1]])
    error = lambda poses: float(torch.linalg.vector_norm(poses[2:-2, :3, 3] - cams[2:-2, :3, 3], dim=-1).max())
    assert error(smooth) < 0.1 * error(shaken)


def test_nearest_rotation_of_a_rotation_is_itself_and_never_a_reflection() -> None:
    cams = ring(5)
    torch.testing.assert_close(nearest_rotation(cams[:, :3, :3]), cams[:, :3, :3], rtol=0, atol=1e-12)
    flipped = nearest_rotation(torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)) + 1e-3)
    assert float(torch.linalg.det(flipped)) == pytest.approx(1.0)


def test_is_walk() -> None:
    assert is_walk(ring(24, turn=1.5))  # 22.5-degree steps
    assert not is_walk(ring(6))  # 60-degree steps: views around, not a walk
    folded = ring(24, turn=1.5)
    folded[8:14] = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64)) @ folded[8:14]
    assert not is_walk(folded)
    with pytest.raises(ValueError, match="two cameras"):
        walk_path(ring(1), 5)
