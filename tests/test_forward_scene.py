"""The generated forward-facing scene (nerfmeta.collection.forward) read back through the LLFF loader."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfmeta.collection.forward import (
    ForwardSceneConfig,
    capture_poses,
    depth_bounds,
    forward_shape,
    layout_offsets,
    make_forward_scene,
    opengl_to_llff,
)
from nerfmeta.data import load_scene
from nerfmeta.data.llff import llff_to_opengl

TINY = ForwardSceneConfig(width=24, height=18, grid=(3, 3), supersample=1)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return make_forward_scene(tmp_path_factory.mktemp("fwd") / "scene", TINY)


def test_opengl_to_llff_inverts_the_loader():
    poses = capture_poses(TINY)
    rows = opengl_to_llff(poses, 18, 24, 20.0)
    assert np.allclose(llff_to_opengl(rows[:, :, :4]), poses.numpy(), atol=1e-12)
    assert np.all(rows[:, :, 4] == (18, 24, 20.0))


def test_cameras_stand_on_a_plane_and_look_one_way():
    poses = capture_poses(ForwardSceneConfig(jitter=0.0))
    assert torch.allclose(poses[:, 1, 3], torch.zeros(20, dtype=torch.float64))
    view = -poses[:, :3, 2]
    assert float(view[:, 1].min()) > 0.99  # all within ~8 degrees of +y


def test_depth_bounds_bracket_every_object_and_end_at_the_wall():
    config = ForwardSceneConfig(jitter=0.0, grid=(1, 2))
    shape = forward_shape(config.wall_distance)
    poses = capture_poses(config)
    bounds = depth_bounds(shape, poses)
    assert np.all(bounds[:, 0] > 0.5) and np.all(bounds[:, 0] < bounds[:, 1])
    # the wall's face is at y = wall_distance; a camera at y = 0 looking nearly along +y sees it a bit further
    assert np.all(bounds[:, 1] >= config.wall_distance - 1e-9) and np.all(bounds[:, 1] < 1.02 * config.wall_distance)


def test_written_scene_loads_as_a_forward_llff_scene(tiny_scene):
    scene = load_scene(tiny_scene)
    assert scene.format == "llff" and scene.scene_type.kind == "forward"
    assert (scene.height, scene.width, scene.n_views) == (18, 24, 9)
    assert torch.allclose(scene.poses.double(), capture_poses(TINY), atol=1e-6)
    assert torch.allclose(scene.intrinsics[0], torch.tensor([TINY.focal, TINY.focal, 12.0, 9.0]))
    assert scene.alphas is None  # opaque RGB: the wall fills every view


def test_same_config_same_bytes(tiny_scene, tmp_path):
    again = make_forward_scene(tmp_path / "again", TINY)
    for name in ("poses_bounds.npy", "images/view_004.png"):
        assert (again / name).read_bytes() == (tiny_scene / name).read_bytes()


def test_refuses_a_folder_with_files(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        make_forward_scene(tmp_path, TINY)
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="grid"):
        ForwardSceneConfig(grid=(1, 1))


def test_layout_zero_is_the_fixed_layout_and_another_moves_the_objects_within_their_ranges():
    fixed = forward_shape(16.0)
    assert forward_shape(16.0, 0) == fixed and np.all(layout_offsets(0) == 0.0)
    moved = forward_shape(16.0, 3)
    shift = np.array([np.subtract(m.position, f.position) for m, f in zip(moved.parts[1:], fixed.parts[1:])])
    assert np.allclose(shift, layout_offsets(3)) and np.all(np.abs(shift) <= [0.4, 0.6, 0.25]) and np.any(shift != 0.0)
    assert moved.parts[0].position == fixed.parts[0].position  # the wall stays
    config = ForwardSceneConfig(jitter=0.0, grid=(2, 2), layout_seed=3)
    bounds = depth_bounds(moved, capture_poses(config))
    assert np.all(bounds[:, 0] > 0.5) and np.all(bounds[:, 0] < bounds[:, 1])
