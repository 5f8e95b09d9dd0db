"""Bad scenes and bad options: ``nerfmeta inspect`` exits 2 with one line naming the problem.

Every case checks: exit code 2, exactly one line on stderr, no traceback, nothing on stdout and
no ``--out`` folder created.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path
from typing import Any, Callable

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.data.write import write_blender_scene
from nerfmeta.render.cameras import fibonacci_directions, look_at

UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def poses(n: int) -> torch.Tensor:
    return look_at(4.0 * fibonacci_directions(n), torch.zeros(3, dtype=torch.float64), UP)


def blender_scene(folder: Path, n: int = 2, edit: Callable[[dict[str, Any]], None] | None = None) -> Path:
    """A valid 8x8 Blender scene (train only); ``edit`` changes the JSON document in place."""
    images = np.random.default_rng(0).integers(0, 256, (n, 8, 8, 4), dtype=np.uint8)
    write_blender_scene(folder, {"train": (images, poses(n))}, camera_angle_x=0.7)
    if edit is not None:
        file = folder / "transforms_train.json"
        doc = json.loads(file.read_text())
        edit(doc)
        file.write_text(json.dumps(doc))
    return folder


def nerfstudio_scene(folder: Path, doc: dict[str, Any], cams: torch.Tensor | None = None) -> Path:
    cams = poses(3) if cams is None else cams
    (folder / "images").mkdir(parents=True)
    frames = []
    for k, pose in enumerate(cams):
        iio.imwrite(folder / "images" / f"{k}.png", np.zeros((6, 8, 3), np.uint8))
        frames.append({"file_path": f"images/{k}.png", "transform_matrix": pose.tolist()})
    (folder / "transforms.json").write_text(json.dumps({**doc, "frames": frames}))
    return folder


def llff_scene(folder: Path, focal: float = 10.0, n_images: int = 3) -> Path:
    cams = poses(3).numpy()
    mats = np.zeros((3, 3, 5))
    mats[:, :, 0], mats[:, :, 1], mats[:, :, 2] = -cams[:, :3, 1], cams[:, :3, 0], cams[:, :3, 2]
    mats[:, :, 3] = cams[:, :3, 3]
    mats[:, :, 4] = [6, 8, focal]
    folder.mkdir(parents=True)
    np.save(folder / "poses_bounds.npy", np.concatenate([mats.reshape(3, 15), [[1.0, 5.0]] * 3], axis=1))
    (folder / "images").mkdir()
    for k in range(n_images):
        iio.imwrite(folder / "images" / f"{k}.png", np.zeros((6, 8, 3), np.uint8))
    return folder


def huge_png_header(path: Path, width: int, height: int) -> None:
    """A PNG whose header claims width x height (the pixel data is a few bytes)."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


@pytest.fixture
def fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> Callable[..., str]:
    """Run ``nerfmeta inspect ARGS --out DIR``; assert the one-line failure; return the line."""

    def run(*args: Any) -> str:
        out = tmp_path / "inspect_out"
        code = main(["inspect", *[str(a) for a in args], "--out", str(out)])
        captured = capsys.readouterr()
        lines = captured.err.rstrip("\n").split("\n")
        assert code == 2, captured.err
        assert len(lines) == 1 and lines[0].startswith("nerfmeta inspect: error: "), captured.err
        assert "Traceback" not in captured.err
        assert captured.out == ""
        assert not out.exists()
        return lines[0]

    return run


# --- paths, folders, formats --------------------------------------------------------------------


def test_missing_scene(tmp_path: Path, fails: Callable[..., str]) -> None:
    line = fails(tmp_path / "nowhere")
    assert "nowhere: scene not found" in line


def test_empty_folder_lists_formats(tmp_path: Path, fails: Callable[..., str]) -> None:
    (tmp_path / "empty").mkdir()
    line = fails(tmp_path / "empty")
    assert "empty: folder is empty" in line
    for expected in ("transforms_train.json", "transforms.json", "poses_bounds.npy", ".npz"):
        assert expected in line


def test_unknown_format_lists_formats(tmp_path: Path, fails: Callable[..., str]) -> None:
    (tmp_path / "odd").mkdir()
    (tmp_path / "odd" / "notes.txt").write_text("hello")
    line = fails(tmp_path / "odd")
    assert "odd: unknown scene format" in line and "blender: transforms_train.json" in line
    assert "llff: poses_bounds.npy" in line and "nerfstudio: transforms.json" in line
    (tmp_path / "scene.obj").write_text("v 0 0 0")
    assert "scene.obj: unknown scene format" in fails(tmp_path / "scene.obj")


@pytest.mark.parametrize("sub", ["", "images"])
def test_images_without_poses(tmp_path: Path, fails: Callable[..., str], sub: str) -> None:
    folder = tmp_path / "photos"
    (folder / sub).mkdir(parents=True)
    iio.imwrite(folder / sub / "a.jpg", np.zeros((4, 4, 3), np.uint8))
    line = fails(folder)
    assert "photos: has images but no camera poses" in line
    assert "imgs2poses.py" in line and "ns-process-data" in line and "COLMAP" in line


def test_out_is_a_file(tmp_path: Path, tiny_scene: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "taken"
    out.write_text("x")
    assert main(["inspect", str(tiny_scene), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out " in err and "taken: exists and is not a folder" in err
    assert out.read_text() == "x"


# --- JSON ---------------------------------------------------------------------------------------


def test_no_train_file(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = blender_scene(tmp_path / "s")
    (scene / "transforms_train.json").rename(scene / "transforms_test.json")
    assert "has no transforms_train.json" in fails(scene)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"camera_angle_x": 0.7, "frames": [', "invalid JSON at line 1"),
        ("[1, 2]", "expected a JSON object"),
        ('{"camera_angle_x": 0.7, "frames": []}', "'frames' must be a non-empty list"),
        ('{"frames": [{"file_path": "a", "transform_matrix": []}]}', "missing camera_angle_x"),
        ('{"camera_angle_x": 0.7, "frames": [{"file_path": "train/r_0"}]}', "frame 0: needs file_path and transform_matrix"),
    ],
)
def test_bad_json(tmp_path: Path, fails: Callable[..., str], text: str, message: str) -> None:
    scene = blender_scene(tmp_path / "s")
    (scene / "transforms_train.json").write_text(text)
    line = fails(scene)
    assert "transforms_train.json" in line and message in line


def test_unreadable_json(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = blender_scene(tmp_path / "s")
    (scene / "transforms_train.json").write_bytes(b"\xff\xfe\x00garbage")
    assert "transforms_train.json: cannot read file" in fails(scene)


# --- frames and images --------------------------------------------------------------------------


def test_missing_frame_image(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = blender_scene(tmp_path / "s")
    (scene / "train" / "r_1.png").unlink()
    line = fails(scene)
    assert "transforms_train.json: frame 1: image './train/r_1' not found" in line


def test_unreadable_frame_image(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = blender_scene(tmp_path / "s")
    (scene / "train" / "r_1.png").write_bytes(b"\x89PNG not really")
    assert "r_1.png: not a readable PNG, JPEG or HEIC image" in fails(scene)


def test_truncated_frame_image(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = blender_scene(tmp_path / "s")
    iio.imwrite(scene / "train" / "r_1.png", np.random.default_rng(1).integers(0, 256, (8, 8, 4), dtype=np.uint8))
    data = (scene / "train" / "r_1.png").read_bytes()
    (scene / "train" / "r_1.png").write_bytes(data[: len(data) // 2])
    assert "r_1.png: cannot decode image" in fails(scene)


def test_frame_image_of_another_size(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = blender_scene(tmp_path / "s")
    iio.imwrite(scene / "train" / "r_1.png", np.zeros((8, 9, 4), np.uint8))
    line = fails(scene)
    assert "r_1.png: image is 9x8 but r_0.png is 8x8" in line


@pytest.mark.parametrize("escape", ["../outside/r_0", "./train/../../outside/r_0", "ABSOLUTE"])
def test_file_path_escaping_the_folder(tmp_path: Path, fails: Callable[..., str], escape: str) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    iio.imwrite(outside / "r_0.png", np.zeros((8, 8, 4), np.uint8))
    target = str(outside / "r_0") if escape == "ABSOLUTE" else escape

    def edit(doc: dict[str, Any]) -> None:
        doc["frames"][1]["file_path"] = target

    line = fails(blender_scene(tmp_path / "s", edit=edit))
    assert "frame 1: file_path" in line
    assert ("is absolute" in line) if escape == "ABSOLUTE" else ("leaves the scene folder" in line)


def test_image_over_the_pixel_limit(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = blender_scene(tmp_path / "s")
    huge_png_header(scene / "train" / "r_0.png", 9000, 9000)
    line = fails(scene)
    assert "r_0.png: image is 9000x9000 = 81.0 megapixels, over the limit of 64 megapixels (resize the file or raise max_pixels)" in line


# --- poses --------------------------------------------------------------------------------------


def _set_pose(value: Any) -> Callable[[dict[str, Any]], None]:
    def edit(doc: dict[str, Any]) -> None:
        doc["frames"][1]["transform_matrix"] = value

    return edit


def _scaled(scale: float) -> list[list[float]]:
    pose = poses(2)[1].clone()
    pose[:3, :3] *= scale
    return pose.tolist()


def _with(row: int, col: int, value: float) -> list[list[float]]:
    pose = poses(2)[1].clone()
    pose[row, col] = value
    return pose.tolist()


def _reflected() -> list[list[float]]:
    pose = poses(2)[1].clone()
    pose[:3, 0] *= -1
    return pose.tolist()


@pytest.mark.parametrize(
    ("matrix", "message"),
    [
        (_with(0, 3, float("nan")), "pose contains NaN or inf"),
        (_with(1, 1, float("inf")), "pose contains NaN or inf"),
        (_scaled(1.01), "pose is not rigid (rotation not orthonormal"),
        (_with(3, 2, 1.0), "pose bottom row must be [0, 0, 0, 1]"),
        (_reflected(), "pose rotation is a reflection"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "pose must be 4x4, got shape (3, 4)"),
        ("identity", "pose is not a 4x4 matrix of numbers"),
    ],
)
def test_bad_pose(tmp_path: Path, fails: Callable[..., str], matrix: Any, message: str) -> None:
    line = fails(blender_scene(tmp_path / "s", edit=_set_pose(matrix)))
    assert "transforms_train.json: frame 1" in line and message in line


def test_slightly_noisy_rotation_is_accepted(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = blender_scene(tmp_path / "s", edit=_set_pose(_scaled(1.0002)))
    assert main(["inspect", str(scene)]) == 0
    assert "format" in capsys.readouterr().out


# --- focal lengths and near/far -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("angle", "message"),
    [
        (0.0, "camera_angle_x must be > 0, got 0"),
        (-0.5, "camera_angle_x must be > 0, got -0.5"),
        (float("nan"), "camera_angle_x must be finite, got nan"),
        ("wide", "camera_angle_x must be a number, got 'wide'"),
        (3.5, "camera_angle_x must be below pi radians"),
    ],
)
def test_bad_camera_angle(tmp_path: Path, fails: Callable[..., str], angle: Any, message: str) -> None:
    line = fails(blender_scene(tmp_path / "s", edit=lambda doc: doc.update(camera_angle_x=angle)))
    assert "transforms_train.json" in line and message in line


def test_bad_near_far(tmp_path: Path, fails: Callable[..., str]) -> None:
    line = fails(blender_scene(tmp_path / "s", edit=lambda doc: doc.update(near=3.0, far=1.0)))
    assert "transforms_train.json: need 0 <= near < far, got near=3 far=1" in line


def test_bad_aabb(tmp_path: Path, fails: Callable[..., str]) -> None:
    line = fails(blender_scene(tmp_path / "s", edit=lambda doc: doc.update(aabb=[[1, 1, 1], [0, 0, 0]])))
    assert "transforms_train.json: aabb must be" in line


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"fl_x": 0.0, "near": 1, "far": 5}, "frame 0: fl_x must be > 0, got 0"),
        ({"fl_x": 10.0, "fl_y": -3.0, "near": 1, "far": 5}, "frame 0: fl_y must be > 0, got -3"),
        ({"fl_x": float("inf"), "near": 1, "far": 5}, "frame 0: fl_x must be finite"),
        ({"near": 1, "far": 5}, "frame 0: needs fl_x or camera_angle_x"),
        ({"fl_x": 10.0, "w": 9, "near": 1, "far": 5}, "frame 0: w is 9 but the image is 8x6"),
        ({"fl_x": 10.0, "near": 1}, "give both near and far"),
        ({"fl_x": 10.0, "camera_model": "OPENCV_FISHEYE"}, "camera_model OPENCV_FISHEYE is not supported"),
    ],
)
def test_bad_nerfstudio(tmp_path: Path, fails: Callable[..., str], doc: dict[str, Any], message: str) -> None:
    line = fails(nerfstudio_scene(tmp_path / "ns", doc))
    assert "transforms.json" in line and message in line


def test_nerfstudio_near_far_cannot_be_guessed(tmp_path: Path, fails: Callable[..., str]) -> None:
    # forward-facing, parallel cameras: no common point of interest
    eyes = torch.tensor([[x, 0.0, 3.0] for x in (-1.0, 0.0, 1.0)], dtype=torch.float64)
    cams = look_at(eyes, eyes - torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    line = fails(nerfstudio_scene(tmp_path / "ns", {"fl_x": 10.0}, cams))
    assert "transforms.json: cannot guess near/far" in line and "add top-level 'near' and 'far'" in line


def test_llff_bad_focal(tmp_path: Path, fails: Callable[..., str]) -> None:
    line = fails(llff_scene(tmp_path / "llff", focal=0.0))
    assert "poses_bounds.npy: image height, width and focal (column 5) must be > 0" in line


def test_llff_image_count_mismatch(tmp_path: Path, fails: Callable[..., str]) -> None:
    line = fails(llff_scene(tmp_path / "llff", n_images=2))
    assert "poses_bounds.npy: has 3 poses but" in line and "holds 2 images" in line


def test_llff_bad_array(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = llff_scene(tmp_path / "llff")
    np.save(scene / "poses_bounds.npy", np.zeros((3, 15)))
    assert "poses_bounds.npy: expected an (N, 17) array, got shape (3, 15)" in fails(scene)
    (scene / "poses_bounds.npy").write_bytes(b"nonsense")
    assert "poses_bounds.npy: cannot read as a .npy array" in fails(scene)


def test_llff_only_reduced_images(tmp_path: Path, fails: Callable[..., str]) -> None:
    scene = llff_scene(tmp_path / "llff")
    (scene / "images").rename(scene / "images_4")
    assert "no images in images/ (found images_4: use that factor as the downscale)" in fails(scene)


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"focal": 0.0}, "focal must be > 0, got 0"),
        ({"focal": float("nan")}, "focal must be finite"),
        ({"focal": None}, "missing array(s) focal"),
        ({"poses": np.zeros((2, 4, 4))}, "poses[0]: pose bottom row must be [0, 0, 0, 1]"),
    ],
)
def test_bad_npz(tmp_path: Path, fails: Callable[..., str], arrays: dict[str, Any], message: str) -> None:
    content = {"images": np.zeros((2, 4, 4, 3), np.uint8), "poses": poses(2).numpy(), "focal": 5.0}
    content.update(arrays)
    np.savez(tmp_path / "t.npz", **{k: v for k, v in content.items() if v is not None})
    line = fails(tmp_path / "t.npz")
    assert "t.npz" in line and message in line


def test_corrupt_npz(tmp_path: Path, fails: Callable[..., str]) -> None:
    (tmp_path / "t.npz").write_bytes(b"PK nonsense")
    assert "t.npz: cannot read as a .npz archive" in fails(tmp_path / "t.npz")


# --- options ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--downscale", "0.5"], "downscale must be a number >= 1, got 0.5"),
        (["--downscale", "nan"], "downscale must be a number >= 1, got nan"),
        (["--background", "purple"], "background 'purple' must be white, black or R,G,B"),
        (["--background", "2,0,0"], "background '2,0,0' must be white, black or R,G,B"),
    ],
)
def test_bad_options(tiny_scene: Path, fails: Callable[..., str], flags: list[str], message: str) -> None:
    assert message in fails(tiny_scene, *flags)


@pytest.mark.parametrize(("side", "message"), [(10_000, "100.0 megapixels, over the limit"), (15_000, "too large to open safely")])
def test_image_over_pillows_own_limits(tmp_path: Path, fails: Callable[..., str], side: int, message: str) -> None:
    # Pillow warns above ~89 MP and refuses above ~179 MP; both must still give one line.
    scene = blender_scene(tmp_path / "s")
    huge_png_header(scene / "train" / "r_1.png", side, side)
    line = fails(scene)
    assert "r_1.png: image" in line and message in line
