"""The pure parts of :mod:`nerfmeta.data.sfm`: pose and camera conversions, near/far, cache keys, sizes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from nerfmeta.data.sfm import (
    SfmConfig,
    camera_from_colmap,
    jump_advice,
    colmap_world_to_camera,
    essential_matrix,
    matrix_to_quaternion,
    near_far_from_depths,
    opengl_camera_to_world,
    photo_hash,
    WORLD_FROM_COLMAP,
    prepared_size,
    quaternion_to_matrix,
    axis_steps_deg,
    rotation_steps_deg,
    sampson_distances,
    walk_jumps,
)
from nerfmeta.errors import SceneError


def test_quarter_turn_about_z() -> None:
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    expected = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(quaternion_to_matrix([c, 0, 0, s]), expected, atol=1e-12)
    np.testing.assert_allclose(matrix_to_quaternion(expected), [c, 0, 0, s], atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_quaternion_round_trip(seed: int) -> None:
    q = np.random.default_rng(seed).normal(size=4)
    q = q / np.linalg.norm(q) * (1 if q[0] >= 0 else -1)
    np.testing.assert_allclose(matrix_to_quaternion(quaternion_to_matrix(q)), q, atol=1e-12)


def test_half_turn_round_trips() -> None:  # w = 0: the branch that does not divide by w
    for axis in np.eye(3):
        rotation = quaternion_to_matrix([0.0, *axis])
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(rotation)), rotation, atol=1e-12)


def test_identity_colmap_camera_looks_along_minus_z_of_opengl() -> None:
    """COLMAP's identity camera sits at the origin looking along world +z; with the world kept, its
    OpenGL pose has -z (the viewing direction) = +z world and y up = -y world (OpenCV's y is down)."""
    c2w = opengl_camera_to_world([1, 0, 0, 0], [0, 0, 0], world=np.eye(3))
    np.testing.assert_allclose(c2w[:3, 3], 0)
    np.testing.assert_allclose(-c2w[:3, 2], [0, 0, 1])
    np.testing.assert_allclose(c2w[:3, 1], [0, -1, 0])


def test_point_in_front_of_colmap_camera_has_negative_opengl_depth() -> None:
    rng = np.random.default_rng(3)
    q = rng.normal(size=4)
    t = rng.normal(size=3)
    point_cam = np.array([0.2, -0.1, 3.0])  # in front of an OpenCV camera (z > 0)
    rotation = quaternion_to_matrix(q)
    point_world = rotation.T @ (point_cam - t)
    c2w = opengl_camera_to_world(q, t)
    in_gl = np.linalg.inv(c2w) @ np.append(WORLD_FROM_COLMAP @ point_world, 1.0)
    np.testing.assert_allclose(in_gl[:3], [0.2, 0.1, -3.0], atol=1e-9)


def test_camera_centre_is_minus_r_transpose_t() -> None:
    q, t = [math.cos(0.3), 0, math.sin(0.3), 0], [1.0, 2.0, 3.0]
    c2w = opengl_camera_to_world(q, t, world=np.eye(3))
    np.testing.assert_allclose(c2w[:3, 3], -quaternion_to_matrix(q).T @ np.array(t))


@pytest.mark.parametrize("seed", range(3))
def test_world_to_camera_round_trip(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q = q / np.linalg.norm(q) * np.sign(q[0])
    t = rng.normal(size=3)
    q2, t2 = colmap_world_to_camera(opengl_camera_to_world(q, t))
    np.testing.assert_allclose(q2, q, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    c2w = opengl_camera_to_world(q, t)
    np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)


def test_cameras_from_colmap_models() -> None:
    cam = camera_from_colmap("SIMPLE_RADIAL", [500.0, 320.0, 240.0, -0.05], 640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion) == (500.0, 500.0, 320.0, 240.0, {"k1": -0.05})
    cam = camera_from_colmap("PINHOLE", [500.0, 510.0, 320.0, 240.0], 640, 480)
    assert (cam.fx, cam.fy, cam.distortion) == (500.0, 510.0, {})
    cam = camera_from_colmap("OPENCV", [1, 2, 3, 4, 0.1, 0.0, 0.0, 0.2], 8, 6)
    assert cam.distortion == {"k1": 0.1, "p2": 0.2}
    with pytest.raises(SceneError, match="OPENCV_FISHEYE is not supported"):
        camera_from_colmap("OPENCV_FISHEYE", [1] * 8, 8, 6)
    with pytest.raises(SceneError, match="needs 4 parameters"):
        camera_from_colmap("PINHOLE", [1, 2, 3], 8, 6)


def test_near_far_hold_the_points() -> None:
    near, far = near_far_from_depths([np.array([2.0, 3.0]), np.array([4.0, -1.0, np.nan])], margin=0.0)
    assert 2.0 <= near < 2.01 and 3.99 < far <= 4.0  # the 0.1 / 99.9 percentiles; the point behind and NaN ignored
    near, far = near_far_from_depths([np.array([2.0, 4.0])], margin=0.5)
    assert near == pytest.approx(0.5 * np.percentile([2.0, 4.0], 0.1)) and far == pytest.approx(1.5 * np.percentile([2.0, 4.0], 99.9))
    with pytest.raises(SceneError, match="no 3-D points"):
        near_far_from_depths([np.array([-1.0])])


def test_photo_hash_follows_contents_names_and_config(tmp_path: Path) -> None:
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    a.write_bytes(b"one")
    b.write_bytes(b"two")
    key = photo_hash([a, b], SfmConfig())
    assert photo_hash([a, b], SfmConfig()) == key
    assert photo_hash([a, b], SfmConfig(max_side=800)) != key
    b.write_bytes(b"three")
    assert photo_hash([a, b], SfmConfig()) != key


def test_prepared_size() -> None:
    assert prepared_size(1280, 720, 1600) == (1280, 720)
    assert prepared_size(3000, 4000, 1600) == (1200, 1600)
    assert prepared_size(1000, 10, 100) == (100, 1)


def _turns_about_z(degrees: list[float]) -> np.ndarray:
    a = np.radians(np.asarray(degrees, dtype=np.float64))
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s, 0 * a], -1), np.stack([s, c, 0 * a], -1), np.stack([0 * a, 0 * a, 1 + 0 * a], -1)], 1)


def test_rotation_steps_between_neighbours() -> None:
    assert rotation_steps_deg(_turns_about_z([0, 10, 30, 25])) == pytest.approx([10, 20, 5])
    assert rotation_steps_deg(_turns_about_z([0, 180])) == pytest.approx([180])


def _walk(degrees: list[float]) -> np.ndarray:
    """Camera-to-world rotations of cameras looking level (their optical axis horizontal), turned about the vertical."""
    level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # camera z (backward) along world -y
    return _turns_about_z(degrees) @ level


def test_walk_jumps_name_a_folded_stretch() -> None:
    # a walk of 9-degree steps whose frames 8-13 were put a half turn away, as a fold of look-alike sides does
    angles = [9.0 * i + (180.0 if 8 <= i < 14 else 0.0) for i in range(24)]
    assert walk_jumps(_walk(angles)) == [8, 14]
    assert walk_jumps(np.transpose(_walk(angles), (0, 2, 1)), world_to_camera=True) == [8, 14]  # COLMAP's way round
    assert walk_jumps(_walk([9.0 * i for i in range(24)])) == []  # a whole walk (past 360 degrees too)


def test_a_camera_that_only_rolls_is_no_jump() -> None:
    """Photos taken with the phone turned (a quarter, or upside down): the camera rolls about its own axis."""
    walk = _walk([9.0 * i for i in range(24)])
    walk[5] = walk[5] @ _turns_about_z([180.0])[0]  # about the camera's own z: upside down
    walk[11] = walk[11] @ _turns_about_z([90.0])[0]
    assert rotation_steps_deg(walk)[4] == pytest.approx(180.0)  # the whole rotation says half a turn
    assert axis_steps_deg(walk)[4] == pytest.approx(9.0) and walk_jumps(walk) == []
    assert walk_jumps(np.transpose(walk, (0, 2, 1)), world_to_camera=True) == []


def test_photos_in_no_order_have_no_walk() -> None:
    rng = np.random.default_rng(0)
    rotations = np.array([quaternion_to_matrix(q / np.linalg.norm(q)) for q in rng.normal(size=(30, 4))])
    assert np.median(rotation_steps_deg(rotations)) > 30 and walk_jumps(rotations) == []
    assert walk_jumps(_turns_about_z([0, 170])) == []  # two photos are no walk


def test_jump_advice_names_the_photos_and_the_option() -> None:
    names = [f"{i:04d}.jpg" for i in range(8)]
    assert "0000.jpg, 0001.jpg" in jump_advice(names, SfmConfig()) and "and 2 more" in jump_advice(names, SfmConfig())
    assert "--matcher sequential" in jump_advice(names[:1], SfmConfig())
    assert "--no-far-pairs" in jump_advice(names[:1], SfmConfig(matcher="sequential", far_pairs=True))
    assert "smaller --overlap than 10" in jump_advice(names[:1], SfmConfig(matcher="sequential"))


def _project(rotation: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    cam = points @ rotation.T + t
    return cam[:, :2] / cam[:, 2:]


def test_true_correspondences_have_no_sampson_distance() -> None:
    rng = np.random.default_rng(0)
    r1 = quaternion_to_matrix(rng.normal(size=4))
    r2 = quaternion_to_matrix(rng.normal(size=4))
    t1, t2 = np.array([0.1, -0.2, 5.0]), np.array([-0.5, 0.3, 6.0])
    points = rng.uniform(-1, 1, size=(50, 3))
    e = essential_matrix(r1, t1, r2, t2)
    assert sampson_distances(e, _project(r1, t1, points), _project(r2, t2, points)).max() < 1e-12
    moved = _project(r2, t2, points) + rng.normal(scale=1e-2, size=(50, 2))
    assert sampson_distances(e, _project(r1, t1, points), moved).min() > 0.0


def test_sampson_distance_of_a_vertical_disparity_across_a_sideways_baseline() -> None:
    # cameras side by side (baseline along x): epipolar lines are the rows, and a point seen d higher in the second
    # image is d / sqrt(2) from the geometry (the nearest consistent pair moves each point by d / 2)
    e = essential_matrix(np.eye(3), np.zeros(3), np.eye(3), np.array([-1.0, 0.0, 0.0]))
    x1 = np.array([[0.3, 0.1], [-0.2, 0.4]])
    x2 = x1 + np.array([[0.7, 0.02], [-0.1, -0.05]])  # any horizontal shift, vertical 0.02 and -0.05
    assert np.allclose(sampson_distances(e, x1, x2), np.array([0.02, 0.05]) / math.sqrt(2), rtol=1e-12)
