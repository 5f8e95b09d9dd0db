"""Hostile input files (issue 15): each case is a real CLI call that must end in a complete run or in
one line on stderr with exit code 2, never a traceback after work was done or a silently wrong result."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.lib import format as npy_format

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.data.arrays import npz_headers
from nerfmeta.data.synthetic import write_tiny_scene
from nerfmeta.errors import SceneError


def one_line_error(capsys: pytest.CaptureFixture[str], code: int, command: str) -> str:
    """The single stderr line of a refused command (exit 2, no traceback)."""
    err = capsys.readouterr().err
    lines = err.rstrip("\n").split("\n")
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith(f"nerfmeta {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


# --- images too small for a metric ----------------------------------------------------------------


@pytest.mark.parametrize(("size", "extra"), [(8, []), (32, ["--downscale", "4"]), (32, ["--downscale", "64"])])
def test_images_smaller_than_the_ssim_window_fit_and_record_why_ssim_is_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], size: int, extra: list[str]
) -> None:
    scene = write_tiny_scene(tmp_path / "small", n_train=2, n_test=1, size=size)
    out = tmp_path / "run"
    code = main(["fit", str(scene), "--out", str(out), "--init", "scratch", "--iters", "2", *extra])
    assert code == 0, capsys.readouterr().err
    summary: dict[str, Any] = json.loads((out / "summary.json").read_text())
    assert summary["test_ssim"] is None
    decision = summary["decisions"]["final_ssim"]
    assert decision["value"] is False and "smaller than its 11x11 window" in decision["reason"]
    assert (out / "checkpoint.safetensors").is_file()


# --- size bombs in containers ----------------------------------------------------------------------


def npy_bytes(shape: tuple[int, ...], dtype: str, data: bytes = b"") -> bytes:
    """A .npy file whose header declares ``shape`` followed by ``data`` (as many bytes as we like)."""
    buf = io.BytesIO()
    npy_format.write_array_header_1_0(buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape})
    return buf.getvalue() + data


def write_npz(path: Path, members: dict[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> Path:
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(f"{name}.npy", data)
    return path


def tiny_npz_members(images: tuple[int, ...] = (2, 4, 4, 3), n_poses: int = 2) -> dict[str, bytes]:
    pixels = np.zeros(images, np.uint8)
    poses = np.broadcast_to(np.eye(4), (n_poses, 4, 4)).copy()
    poses[:, 2, 3] = 4.0
    return {"images": npy_bytes(images, "u1", pixels.tobytes()), "poses": npy_bytes(poses.shape, "<f8", poses.tobytes()),
            "focal": npy_bytes((), "<f8", np.float64(5.0).tobytes())}


@pytest.mark.parametrize(
    ("members", "message"),
    [
        ({"images": npy_bytes((1, 60000, 60000, 3), "u1", b"\0" * 64)}, "declares shape (1, 60000, 60000, 3)"),
        ({"images": npy_bytes((1, 9000, 9000, 3), "u1", b"\0" * 64)}, "the file is truncated or forged"),
        ({"poses": npy_bytes((10**9, 4, 4), "<f8", b"\0" * 64)}, "poses: header declares shape (1000000000, 4, 4)"),
        ({"images": npy_bytes((2, 4, 4, 3), "|O", b"\0" * 64)}, "holds Python objects"),
        ({"images": b"not an npy header"}, "images: cannot read as a .npy array (bad header"),
        ({"images": npy_bytes((2, 4, 4), "u1", b"\0" * 32)}, "images must be (N, H, W, 3)"),
        ({"poses": npy_bytes((3, 4, 4), "<f8", b"\0" * 384)}, "poses must be (N, 4, 4) with N = 2"),
    ],
)
def test_npz_declared_shapes_are_checked_before_reading(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], members: dict[str, bytes], message: str
) -> None:
    path = write_npz(tmp_path / "scene.npz", {**tiny_npz_members(), **members})
    line = one_line_error(capsys, main(["inspect", str(path)]), "inspect")
    assert "scene.npz" in line and message in line


def test_npz_pixel_limit_applies_to_the_declared_size_without_reading(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write_npz(tmp_path / "scene.npz", tiny_npz_members((2, 16, 16, 3)))
    assert load_scene(path).height == 16

    def no_read(*args: object, **kwargs: object) -> None:
        raise AssertionError("arrays read before the declared sizes were checked")

    monkeypatch.setattr(np, "load", no_read)
    with pytest.raises(SceneError, match=r"scene\.npz: images: image is 16x16 .* over the limit"):
        load_scene(path, max_pixels=255)


def test_npz_headers_give_declared_shapes_and_sizes(tmp_path: Path) -> None:
    members = tiny_npz_members()
    path = write_npz(tmp_path / "scene.npz", members)
    headers = npz_headers(path)
    assert headers["images"].shape == (2, 4, 4, 3) and headers["images"].data_bytes == 96
    assert headers["focal"].shape == () and headers["poses"].dtype == np.float64


def test_llff_poses_bounds_header_is_checked_before_reading(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "llff"
    (folder / "images").mkdir(parents=True)
    (folder / "poses_bounds.npy").write_bytes(npy_bytes((10**9, 17), "<f8", b"\0" * 136))
    line = one_line_error(capsys, main(["inspect", str(folder)]), "inspect")
    assert "poses_bounds.npy: header declares shape (1000000000, 17)" in line
    (folder / "poses_bounds.npy").write_bytes(npy_bytes((2, 5), "<f8", b"\0" * 80))
    line = one_line_error(capsys, main(["inspect", str(folder)]), "inspect")
    assert "poses_bounds.npy: expected an (N, 17) array, got shape (2, 5)" in line

