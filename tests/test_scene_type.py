"""Scene-type detection: exact layouts of cameras and image borders (nerfmeta.data.scene_type)."""

from __future__ import annotations

import math

import pytest
import torch

from nerfmeta.data.scene_type import (
    SceneType,
    border_spread,
    camera_layout,
    classify_scene,
    detect_scene_type,
    focus_point,
    view_directions,
)


def look_at(centre: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(3,), (3,) -> (4, 4) OpenGL camera-to-world looking from ``centre`` at ``target``."""
    back = centre - target
    back = back / back.norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    if abs(float(back @ up)) > 0.99:
        up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    right = torch.linalg.cross(up, back)
    right = right / right.norm()
    true_up = torch.linalg.cross(back, right)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, true_up, back, centre
    return pose


def ring(n: int, radius: float = 4.0, height: float = 1.0) -> torch.Tensor:
    """Cameras on a circle around the origin, looking at it."""
    target = torch.zeros(3, dtype=torch.float64)
    angles = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    return torch.stack([look_at(torch.stack([radius * a.cos(), radius * a.sin(), torch.tensor(height, dtype=torch.float64)]), target) for a in angles])


def patch(n_side: int = 3, spacing: float = 0.1, depth: float = 5.0) -> torch.Tensor:
    """Cameras on a small grid in the plane y = 0, all looking along +y at a point ``depth`` away."""
    poses = []
    for i in range(n_side):
        for j in range(n_side):
            c = torch.tensor([(i - 1) * spacing, 0.0, (j - 1) * spacing], dtype=torch.float64)
            poses.append(look_at(c, torch.tensor([0.0, depth, 0.0], dtype=torch.float64)))
    return torch.stack(poses)


def test_view_direction_is_minus_z() -> None:
    pose = look_at(torch.tensor([0.0, -3.0, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    assert torch.allclose(view_directions(pose[None]), torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64))


def test_focus_point_of_lines_through_one_point() -> None:
    point = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    origins = torch.randn(6, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 3
    dirs = (point - origins) / (point - origins).norm(dim=-1, keepdim=True)
    assert torch.allclose(focus_point(origins, dirs), point, atol=1e-9)


def test_focus_point_of_parallel_lines_is_none() -> None:
    origins = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.0, 0, 1]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 1.0, 0.0]] * 3, dtype=torch.float64)
    assert focus_point(origins, dirs) is None


def test_ring_of_cameras_is_around() -> None:
    layout = camera_layout(ring(12))
    assert layout.max_angle_deg > 70  # the mean direction points down; each view is 76 deg from it
    assert not layout.looks_one_way


def test_patch_of_cameras_is_forward() -> None:
    layout = camera_layout(patch(depth=5.0))
    assert layout.max_angle_deg < 5
    assert layout.focus_distance == pytest.approx(5.0, rel=1e-6)
    assert layout.on_a_patch
    assert classify_scene(layout, has_alpha=False, border_std=0.3).kind == "forward"


def test_arc_of_cameras_close_to_an_object_is_not_forward() -> None:
    # a 60-degree arc at radius 2: the views look one way but the cameras spread widely
    target = torch.zeros(3, dtype=torch.float64)
    poses = torch.stack([look_at(torch.tensor([2 * math.sin(a), -2 * math.cos(a), 0.3], dtype=torch.float64), target)
                         for a in torch.linspace(-math.pi / 6, math.pi / 6, 7).tolist()])
    layout = camera_layout(poses)
    assert layout.looks_one_way and not layout.on_a_patch
    assert classify_scene(layout, has_alpha=False, border_std=0.0).kind == "object"


def test_background_decides_object_or_unbounded() -> None:
    layout = camera_layout(ring(8))
    assert classify_scene(layout, has_alpha=True, border_std=0.5).kind == "object"
    assert classify_scene(layout, has_alpha=False, border_std=0.01).kind == "object"
    assert classify_scene(layout, has_alpha=False, border_std=0.2).kind == "unbounded"


def test_border_spread_flat_and_textured() -> None:
    flat = torch.full((2, 20, 30, 3), 0.7)
    flat[:, 8:12, 10:20] = 0.0  # content in the middle does not count
    assert border_spread(flat) == pytest.approx(0.0, abs=1e-7)
    textured = torch.rand(2, 20, 30, 3, generator=torch.Generator().manual_seed(1))
    assert border_spread(textured) > 0.2


def test_detect_and_override() -> None:
    images = torch.rand(8, 16, 16, 3, generator=torch.Generator().manual_seed(2))
    assert detect_scene_type(ring(8).float(), images, None).kind == "unbounded"
    assert detect_scene_type(ring(8).float(), images, torch.ones(8, 16, 16)).kind == "object"
    named = detect_scene_type(ring(8).float(), images, None, "forward")
    assert named == SceneType("forward", "set by the user", detected=False)
    with pytest.raises(ValueError, match="scene type"):
        detect_scene_type(ring(8).float(), images, None, "planar")


def test_loaded_scene_records_its_type(tiny_scene) -> None:
    from nerfmeta.data import load_scene

    scene = load_scene(tiny_scene)
    assert scene.scene_type.kind == "object"  # RGBA views of spheres, cameras around
    assert scene.scene_type.detected
    assert load_scene(tiny_scene, scene_type="unbounded").scene_type.kind == "unbounded"
