"""The generated unbounded scene (nerfmeta.collection.unbounded) read back through the LLFF loader."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfmeta.collection.unbounded import (
    UnboundedSceneConfig,
    make_unbounded_scene,
    ring_bounds,
    ring_poses,
    unbounded_shape,
)
from nerfmeta.data import load_scene

TINY = UnboundedSceneConfig(width=24, height=18, views=8, supersample=1)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return make_unbounded_scene(tmp_path_factory.mktemp("unb") / "scene", TINY)


def test_cameras_walk_round_the_middle_each_looking_at_it():
    config = UnboundedSceneConfig(jitter=0.0, views=12)
    poses = ring_poses(config)
    centres = poses[:, :3, 3]
    assert torch.allclose(centres[:, :2].norm(dim=1), torch.full((12,), config.radius, dtype=torch.float64))
    assert torch.allclose(centres[:, 2], torch.full((12,), config.camera_height, dtype=torch.float64))
    angles = torch.atan2(centres[:, 1], centres[:, 0])
    steps = torch.remainder(angles.diff(), 2 * math.pi)
    assert torch.allclose(steps, torch.full((11,), 2 * math.pi / 12, dtype=torch.float64))  # in order: a walk
    target = torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)
    to_target = (target - centres) / (target - centres).norm(dim=1, keepdim=True)
    assert torch.allclose(-poses[:, :3, 2], to_target, atol=1e-12)


def test_no_surface_is_nearer_a_camera_than_the_near_bound_and_the_far_bound_reaches_the_room():
    config = UnboundedSceneConfig(views=16)
    shape = unbounded_shape(config.room)
    poses = ring_poses(config)
    bounds = ring_bounds(config, poses)
    centres = poses[:, :3, 3].numpy()
    distance = shape.sdf(torch.tensor(centres, dtype=torch.float32)).numpy()  # exact distance to the nearest surface
    assert np.all(distance > bounds[:, 0])
    assert np.all(bounds[:, 1] > config.room + config.radius - 0.5)  # at least the far wall's distance across the room


def test_written_scene_loads_as_an_unbounded_llff_scene(tiny_scene):
    scene = load_scene(tiny_scene)
    assert scene.format == "llff" and scene.scene_type.kind == "unbounded"
    assert (scene.height, scene.width, scene.n_views) == (18, 24, 8)
    assert torch.allclose(scene.poses.double(), ring_poses(TINY), atol=1e-6)
    assert scene.alphas is None  # the room fills every view


def test_same_config_same_bytes_and_another_layout_other_bytes(tiny_scene, tmp_path):
    again = make_unbounded_scene(tmp_path / "again", TINY)
    for name in ("poses_bounds.npy", "images/view_003.png"):
        assert (again / name).read_bytes() == (tiny_scene / name).read_bytes()
    other = make_unbounded_scene(tmp_path / "other", UnboundedSceneConfig(width=24, height=18, views=8, supersample=1,
                                                                          layout_seed=3))
    assert (other / "images/view_003.png").read_bytes() != (tiny_scene / "images/view_003.png").read_bytes()


def test_refuses_a_folder_with_files(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        make_unbounded_scene(tmp_path, TINY)
    assert (tmp_path / "keep.txt").read_text() == "mine"


@pytest.mark.parametrize("bad", [{"views": 2}, {"room": 4.0}, {"radius": 1.0}, {"width": 3}])
def test_bad_config_is_refused(bad):
    with pytest.raises(ValueError, match="unbounded scene"):
        UnboundedSceneConfig(**bad)
