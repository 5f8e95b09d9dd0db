"""Scene parsers (Blender, nerfstudio, LLFF, NPZ) and the format registry, on small hand-written files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfmeta.data import LoadOptions, Scene, load_scene
from nerfmeta.data.bounds import frustum_bounds
from nerfmeta.data.common import HOLDOUT_EVERY_TEXT
from nerfmeta.data.registry import detect_format
from nerfmeta.data.write import write_blender_scene
from nerfmeta.render.cameras import fibonacci_directions, look_at
from nerfmeta.render.rays import image_rays

H, W = 12, 16
UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def ring_poses(n: int, radius: float = 4.0, offset: float = 0.5) -> torch.Tensor:
    """(n, 4, 4) float64 cameras on the upper hemisphere looking at the origin."""
    eyes = radius * fibonacci_directions(n, offset=offset)
    return look_at(eyes, torch.zeros(3, dtype=torch.float64), UP)


def random_images(n: int, channels: int = 4, seed: int = 0, h: int = H, w: int = W) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(n, h, w, channels), dtype=np.uint8)


def composited(images: np.ndarray, bg: tuple[float, float, float]) -> torch.Tensor:
    x = torch.from_numpy(images).float() / 255
    a = x[..., 3:]
    return x[..., :3] * a + torch.tensor(bg) * (1 - a)


def llff_rows(poses_gl: torch.Tensor, h: float, w: float, f: float, bounds: np.ndarray) -> np.ndarray:
    """poses_bounds.npy rows: [down, right, back | t | hwf] then (near, far)."""
    gl = poses_gl.numpy()
    mats = np.zeros((len(gl), 3, 5))
    mats[:, :, 0] = -gl[:, :3, 1]
    mats[:, :, 1] = gl[:, :3, 0]
    mats[:, :, 2] = gl[:, :3, 2]
    mats[:, :, 3] = gl[:, :3, 3]
    mats[:, :, 4] = [h, w, f]
    return np.concatenate([mats.reshape(len(gl), 15), bounds], axis=1)


def write_images(folder: Path, images: np.ndarray, prefix: str = "img") -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for k, image in enumerate(images):
        iio.imwrite(folder / f"{prefix}_{k:03d}.png", image)
        names.append(f"{prefix}_{k:03d}.png")
    return names


# --- Blender ------------------------------------------------------------------------------------


def test_blender_poses_intrinsics_splits_and_keys(tmp_path: Path) -> None:
    poses = ring_poses(6)
    images = random_images(6)
    splits = {"train": (images[:3], poses[:3]), "val": (images[3:4], poses[3:4]), "test": (images[4:], poses[4:])}
    aabb = [[-1.0, -0.5, -0.25], [1.0, 0.5, 0.75]]
    extra = {"near": 1.5, "far": 5.0, "category": "chair", "aabb": aabb}
    write_blender_scene(tmp_path, splits, camera_angle_x=0.8, extra=extra)

    scene = load_scene(tmp_path, background=(0.0, 1.0, 0.0))
    assert scene.format == "blender" and scene.source == tmp_path
    assert scene.splits == {"train": (0, 1, 2), "val": (3,), "test": (4, 5)}
    assert scene.holdout == "from file"
    assert torch.equal(scene.poses, poses.float())
    fx = 0.5 * W / math.tan(0.4)
    torch.testing.assert_close(scene.intrinsics, torch.tensor([[fx, fx, W / 2, H / 2]] * 6))
    assert (scene.near, scene.far, scene.category) == (1.5, 5.0, "chair")
    assert torch.equal(scene.bounds, torch.tensor(aabb))
    torch.testing.assert_close(scene.images, composited(images, (0.0, 1.0, 0.0)), rtol=0, atol=1e-6)
    torch.testing.assert_close(scene.alphas, torch.from_numpy(images[..., 3]).float() / 255, rtol=0, atol=0)
    assert scene.background == (0.0, 1.0, 0.0)
    assert scene.image_names[0] == "train/r_0.png" and scene.image_names[5] == "test/r_1.png"
    assert scene.downscale == 1.0


def test_blender_train_only_holds_out_every_8th_view(tmp_path: Path) -> None:
    poses = ring_poses(10)
    write_blender_scene(tmp_path, {"train": (random_images(10), poses)}, camera_angle_x=0.7)
    scene = load_scene(tmp_path)
    assert scene.splits == {"train": (1, 2, 3, 4, 5, 6, 7, 9), "test": (0, 8)}
    assert scene.holdout == HOLDOUT_EVERY_TEXT == "every 8th view (no test split in the files)"
    assert (scene.near, scene.far, scene.category) == (2.0, 6.0, None)
    expected = frustum_bounds(poses, scene.intrinsics.double(), H, W, 2.0, 6.0).float()
    torch.testing.assert_close(scene.bounds, expected)
    assert torch.equal(scene.subset("test").poses, poses[[0, 8]].float())


def test_blender_file_path_with_extension_and_camera_angle_y(tmp_path: Path) -> None:
    poses = ring_poses(2)
    write_images(tmp_path / "imgs", random_images(2, channels=3))
    frames = [{"file_path": f"imgs/img_{k:03d}.png", "transform_matrix": poses[k].tolist()} for k in range(2)]
    doc = {"camera_angle_x": 0.9, "camera_angle_y": 0.6, "frames": frames}
    (tmp_path / "transforms_train.json").write_text(json.dumps(doc))
    (tmp_path / "transforms_test.json").write_text(json.dumps(doc))
    scene = load_scene(tmp_path)
    fx, fy = 0.5 * W / math.tan(0.45), 0.5 * H / math.tan(0.3)
    torch.testing.assert_close(scene.intrinsics[0], torch.tensor([fx, fy, W / 2, H / 2]))
    assert scene.alphas is None and scene.background is None
    assert scene.splits == {"train": (0, 1), "test": (2, 3)}


def test_blender_downscale_composites_then_averages_blocks(tmp_path: Path) -> None:
    poses = ring_poses(2)
    images = random_images(2)
    write_blender_scene(tmp_path, {"train": (images, poses)}, camera_angle_x=0.7, extra={"aabb": [[-1] * 3, [1] * 3]})
    scene = load_scene(tmp_path, downscale=2, background=(0.0, 0.0, 0.0))
    full = composited(images, (0.0, 0.0, 0.0))
    blocks = full.reshape(2, H // 2, 2, W // 2, 2, 3).mean(dim=(2, 4))
    assert scene.images.shape == (2, H // 2, W // 2, 3) and scene.downscale == 2.0
    torch.testing.assert_close(scene.images, blocks, rtol=0, atol=1e-6)
    alpha = torch.from_numpy(images[..., 3]).float().div(255).reshape(2, H // 2, 2, W // 2, 2).mean(dim=(2, 4))
    torch.testing.assert_close(scene.alphas, alpha, rtol=0, atol=1e-6)
    fx = 0.5 * W / math.tan(0.35)
    torch.testing.assert_close(scene.intrinsics[0], torch.tensor([fx / 2, fx / 2, W / 4, H / 4]))


# --- nerfstudio ---------------------------------------------------------------------------------


def write_nerfstudio(
    folder: Path, poses: torch.Tensor, doc: dict, per_frame: dict[int, dict] | None = None, images: np.ndarray | None = None
) -> None:
    images = random_images(len(poses), channels=3) if images is None else images
    names = write_images(folder / "images", images, prefix="frame")
    frames = []
    for k, name in enumerate(names):
        frame = {"file_path": f"images/{name}", "transform_matrix": poses[k].tolist()}
        frame.update((per_frame or {}).get(k, {}))
        frames.append(frame)
    (folder / "transforms.json").write_text(json.dumps({**doc, "frames": frames}))


def test_nerfstudio_global_and_per_frame_intrinsics(tmp_path: Path) -> None:
    poses = ring_poses(9)
    doc = {"fl_x": 20.0, "fl_y": 21.0, "cx": 7.5, "cy": 6.5, "w": W, "h": H, "near": 0.5, "far": 9.0, "category": "car"}
    write_nerfstudio(tmp_path, poses, doc, per_frame={3: {"fl_x": 30.0, "cy": 5.0}})
    scene = load_scene(tmp_path)
    assert scene.format == "nerfstudio"
    expected = torch.tensor([[20.0, 21.0, 7.5, 6.5]] * 9)
    expected[3] = torch.tensor([30.0, 21.0, 7.5, 5.0])
    assert torch.equal(scene.intrinsics, expected)
    assert torch.equal(scene.poses, poses.float())
    assert scene.splits == {"train": (1, 2, 3, 4, 5, 6, 7), "test": (0, 8)}
    assert scene.holdout == HOLDOUT_EVERY_TEXT
    assert (scene.near, scene.far, scene.category) == (0.5, 9.0, "car")
    assert scene.alphas is None and scene.background is None
    assert scene.image_names[0] == "images/frame_000.png"


def test_nerfstudio_camera_angle_fallback_and_near_far_heuristic(tmp_path: Path) -> None:
    poses = ring_poses(5)
    write_nerfstudio(tmp_path, poses, {"camera_angle_x": 0.7})
    scene = load_scene(tmp_path, downscale=2)
    fx = 0.5 * W / math.tan(0.35)
    torch.testing.assert_close(scene.intrinsics[0], torch.tensor([fx / 2, fx / 2, W / 4, H / 4]))
    # cameras at radius 4 looking at the origin: near = 0.5 * 4, far = 1.5 * 4
    assert scene.near == pytest.approx(2.0, abs=1e-9) and scene.far == pytest.approx(6.0, abs=1e-9)


# --- LLFF ---------------------------------------------------------------------------------------


def write_llff(folder: Path, n: int = 9, f: float = 20.0) -> tuple[torch.Tensor, np.ndarray]:
    eyes = torch.stack([torch.linspace(-1, 1, n), torch.linspace(0.5, -0.5, n), torch.full((n,), 3.0)], -1).double()
    poses = look_at(eyes, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    bounds = np.stack([np.linspace(1.0, 1.5, n), np.linspace(5.0, 6.0, n)], axis=1)
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "poses_bounds.npy", llff_rows(poses, H, W, f, bounds))
    images = random_images(n, channels=3, seed=1)
    write_images(folder / "images", images)
    write_images(folder / "images_2", np.full((n, H // 2, W // 2, 3), 128, np.uint8))  # distinct content
    return poses, images


def test_llff_poses_intrinsics_near_far_splits(tmp_path: Path) -> None:
    poses, images = write_llff(tmp_path)
    scene = load_scene(tmp_path)
    assert scene.format == "llff"
    torch.testing.assert_close(scene.poses, poses.float(), rtol=0, atol=1e-6)
    assert torch.equal(scene.intrinsics, torch.tensor([[20.0, 20.0, W / 2, H / 2]] * 9))
    assert scene.near == pytest.approx(0.9) and scene.far == pytest.approx(6.6)
    assert scene.splits == {"train": (1, 2, 3, 4, 5, 6, 7), "test": (0, 8)}
    assert scene.holdout == HOLDOUT_EVERY_TEXT
    torch.testing.assert_close(scene.images, torch.from_numpy(images).float() / 255, rtol=0, atol=0)
    assert scene.image_names[0] == "images/img_000.png"


def test_llff_reads_images_n_and_scales_intrinsics(tmp_path: Path) -> None:
    write_llff(tmp_path)
    scene = load_scene(tmp_path, downscale=2)
    assert scene.images.shape == (9, H // 2, W // 2, 3)
    assert torch.equal(scene.images, torch.full_like(scene.images, 128 / 255))  # from images_2/, not images/
    assert torch.equal(scene.intrinsics[0], torch.tensor([10.0, 10.0, W / 4, H / 4]))
    assert scene.image_names[0] == "images_2/img_000.png" and scene.downscale == 2.0


def test_llff_incomplete_images_n_falls_back_to_images(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    # a partial pre-reduced folder (the shared beer capture's images_8/ holds 29 of 71) is passed over
    _, images = write_llff(tmp_path)
    (tmp_path / "images_2" / "img_008.png").unlink()
    with caplog.at_level("WARNING"):
        scene = load_scene(tmp_path, downscale=2)
    assert scene.image_names[0] == "images/img_000.png"
    full = torch.from_numpy(images).float() / 255
    torch.testing.assert_close(scene.images, full.reshape(9, H // 2, 2, W // 2, 2, 3).mean(dim=(2, 4)), rtol=0, atol=1e-6)
    assert "holds 8 images for 9 poses" in caplog.text


def test_llff_without_images_n_area_downscales_images(tmp_path: Path) -> None:
    _, images = write_llff(tmp_path)
    scene = load_scene(tmp_path, downscale=4)
    assert scene.images.shape == (9, H // 4, W // 4, 3)
    full = torch.from_numpy(images).float() / 255
    torch.testing.assert_close(scene.images, full.reshape(9, 3, 4, 4, 4, 3).mean(dim=(2, 4)), rtol=0, atol=1e-6)
    assert torch.equal(scene.intrinsics[0], torch.tensor([5.0, 5.0, W / 8, H / 8]))


# --- NPZ ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("float_images", [False, True])
def test_npz_scene(tmp_path: Path, float_images: bool) -> None:
    poses = ring_poses(9)
    images = random_images(9, channels=3, h=8, w=8)
    stored = images.astype(np.float32) / 255 if float_images else images
    np.savez(tmp_path / "tiny.npz", images=stored, poses=poses.numpy().astype(np.float32), focal=np.float64(10.0))
    scene = load_scene(tmp_path / "tiny.npz", downscale=2)
    assert scene.format == "npz"
    torch.testing.assert_close(scene.poses, poses.float())
    assert torch.equal(scene.intrinsics, torch.tensor([[5.0, 5.0, 2.0, 2.0]] * 9))
    assert (scene.near, scene.far) == (2.0, 6.0)
    assert scene.splits == {"train": (1, 2, 3, 4, 5, 6, 7), "test": (0, 8)}
    full = torch.from_numpy(images).float() / 255
    torch.testing.assert_close(scene.images, full.reshape(9, 4, 2, 4, 2, 3).mean(dim=(2, 4)), rtol=0, atol=1e-6)


# --- conventions shared by every parser ---------------------------------------------------------


def write_format(fmt: str, folder: Path, poses: torch.Tensor, size: int, focal: float) -> Path:
    """Write two views (opaque grey images) of ``poses`` in ``fmt``; return the path to load."""
    n = len(poses)
    images = np.full((n, size, size, 3), 100, np.uint8)
    if fmt == "blender":
        write_blender_scene(folder, {"train": (images, poses)}, camera_angle_x=2 * math.atan(size / (2 * focal)))
        return folder
    if fmt == "nerfstudio":
        write_nerfstudio(folder, poses, {"fl_x": focal, "fl_y": focal, "near": 1.0, "far": 9.0}, images=images)
        return folder
    if fmt == "llff":
        folder.mkdir(parents=True)
        np.save(folder / "poses_bounds.npy", llff_rows(poses, size, size, focal, np.array([[1.0, 9.0]] * n)))
        write_images(folder / "images", images)
        return folder
    folder.mkdir(parents=True)
    np.savez(folder / "s.npz", images=images, poses=poses.numpy(), focal=focal)
    return folder / "s.npz"


@pytest.mark.parametrize("fmt", ["blender", "nerfstudio", "llff", "npz"])
def test_centre_pixel_ray_points_at_the_look_at_target(tmp_path: Path, fmt: str) -> None:
    eye = torch.tensor([[1.0, -2.0, 1.5], [2.0, 1.0, 1.0]], dtype=torch.float64)
    target = torch.tensor([0.2, 0.3, -0.1], dtype=torch.float64)
    poses = look_at(eye, target, UP)
    size = 9  # odd: pixel (4, 4) is centred on the principal point
    scene = load_scene(write_format(fmt, tmp_path / fmt, poses, size, focal=12.0))
    origins, dirs = image_rays(scene.poses[0].double(), scene.intrinsics[0].double(), size, size)
    want = (target - eye[0]) / torch.linalg.vector_norm(target - eye[0])
    torch.testing.assert_close(origins[4, 4], eye[0], rtol=0, atol=1e-5)
    torch.testing.assert_close(dirs[4, 4], want, rtol=0, atol=1e-5)
    # image up is world up-ish (z grows towards row 0), image right is the camera's right
    assert dirs[0, 4, 2] > dirs[4, 4, 2]
    right = poses[0, :3, 0]
    assert float((dirs[4, 8] - dirs[4, 4]) @ right) > 0
    # and the intrinsics are the written focal at the image centre
    torch.testing.assert_close(scene.intrinsics[0], torch.tensor([12.0, 12.0, 4.5, 4.5]))


def test_registry_detects_each_format(tmp_path: Path, tiny_scene: Path) -> None:
    poses = ring_poses(2)
    names = {}
    for fmt in ("blender", "nerfstudio", "llff", "npz"):
        names[fmt] = detect_format(write_format(fmt, tmp_path / fmt, poses, 5, 5.0)).name
    assert names == {"blender": "blender", "nerfstudio": "nerfstudio", "llff": "llff", "npz": "npz"}
    assert detect_format(tiny_scene).name == "blender"


def test_tiny_scene_loads_with_its_aabb(tiny_scene: Path) -> None:
    scene = load_scene(tiny_scene)
    assert isinstance(scene, Scene)
    assert scene.n_views == 12 and scene.splits == {"train": tuple(range(8)), "test": tuple(range(8, 12))}
    assert (scene.height, scene.width, scene.category) == (32, 32, "spheres")
    doc = json.loads((tiny_scene / "transforms_train.json").read_text())
    assert torch.equal(scene.bounds, torch.tensor(doc["aabb"], dtype=torch.float32))
    # every camera looks at the origin
    forward = -scene.poses[:, :3, 2]
    to_origin = -scene.poses[:, :3, 3] / scene.poses[:, :3, 3].norm(dim=-1, keepdim=True)
    assert bool(((forward * to_origin).sum(-1) > 0.9999).all())


def test_load_options_defaults() -> None:
    options = LoadOptions()
    assert (options.downscale, options.background, options.max_pixels) == (1.0, (1.0, 1.0, 1.0), 64_000_000)
