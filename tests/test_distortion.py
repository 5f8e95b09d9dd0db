"""Lens distortion removed on load (nerfmeta.data.distortion): the OpenCV/COLMAP model on exact small cases, the
resampling against a float64 analytic reference, and the nerfstudio loader applying it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from nerfmeta.data.distortion import distort_normalised, undistort_image
from nerfmeta.data.registry import load_scene


def _coeffs(k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0) -> torch.Tensor:
    return torch.tensor([k1, k2, k3, p1, p2], dtype=torch.float64)


def test_the_model_on_hand_computed_points() -> None:
    xd, yd = distort_normalised(torch.tensor(0.5, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64),
                                _coeffs(k1=0.1))
    assert (float(xd), float(yd)) == pytest.approx((0.5 * 1.025, 0.0))  # r^2 = 0.25
    xd, yd = distort_normalised(torch.tensor(0.2, dtype=torch.float64), torch.tensor(0.1, dtype=torch.float64),
                                _coeffs(p1=0.01, p2=0.02))
    assert (float(xd), float(yd)) == pytest.approx((0.2 + 0.0004 + 0.0026, 0.1 + 0.0007 + 0.0008))
    xd, _ = distort_normalised(torch.tensor(0.5, dtype=torch.float64), torch.tensor(0.5, dtype=torch.float64),
                               _coeffs(k1=0.1, k2=0.01, k3=0.001))
    assert float(xd) == pytest.approx(0.5 * (1 + 0.1 * 0.5 + 0.01 * 0.25 + 0.001 * 0.125))


def test_no_distortion_leaves_the_image_as_it_is() -> None:
    image = torch.rand(12, 17, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    intrinsics = torch.tensor([20.0, 21.0, 8.0, 6.5], dtype=torch.float64)
    torch.testing.assert_close(undistort_image(image, intrinsics, _coeffs()), image, rtol=0, atol=1e-12)


def _smooth(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return torch.sin(u / 9.0) + torch.cos(v / 7.0) + 0.01 * u


def test_each_pixel_shows_the_photo_where_the_lens_moved_it() -> None:
    """A photo whose value at each pixel position is a smooth known function: the undistorted image at pixel p
    must read that function at distort(p), to bilinear sampling's error: |h''| / 8 per axis, 1/648 + 1/392."""
    height, width = 60, 80
    fx, fy, cx, cy = 70.0, 72.0, 41.0, 29.5
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                          torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    photo = _smooth(u, v)
    coeffs = _coeffs(k1=-0.12, k2=0.03, p1=0.002, p2=-0.001)
    out = undistort_image(photo, torch.tensor([fx, fy, cx, cy], dtype=torch.float64), coeffs)
    xd, yd = distort_normalised((u - cx) / fx, (v - cy) / fy, coeffs)
    su, sv = fx * xd + cx, fy * yd + cy
    expected = _smooth(su, sv)
    inside = (su > 1) & (su < width - 1) & (sv > 1) & (sv < height - 1)
    assert inside.float().mean() > 0.9  # barrel distortion pulls the corners in: most pixels have a source
    assert (out - expected)[inside].abs().max() < 1 / 648 + 1 / 392
    assert (photo - expected)[inside].abs().max() > 0.2  # and the lens moved them by far more than that


def test_nerfstudio_scene_with_distortion_is_undistorted_on_load(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    images = (rng.random((3, 24, 32, 3)) * 255).astype(np.uint8)
    folder = tmp_path / "scene"
    (folder / "images").mkdir(parents=True)
    frames = []
    for k, image in enumerate(images):
        Image.fromarray(image).save(folder / "images" / f"v{k}.png")
        angle = 2 * math.pi * k / 3
        pose = np.eye(4)
        pose[:3, 3] = [4 * math.cos(angle), 4 * math.sin(angle), 0.0]
        forward = -pose[:3, 3] / 4  # look at the origin: camera -z along it
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        pose[:3, :3] = np.stack([right, np.cross(right, forward), -forward], axis=1)
        frames.append({"file_path": f"images/v{k}.png", "transform_matrix": pose.tolist()})
    doc = {"fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 12.0, "w": 32, "h": 24, "near": 1.0, "far": 8.0,
           "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(doc))
    plain = load_scene(folder, normalize=False)
    (folder / "transforms.json").write_text(json.dumps({**doc, "k1": -0.2, "p1": 0.001}))
    lens = load_scene(folder, normalize=False)
    torch.testing.assert_close(lens.intrinsics, plain.intrinsics)
    for i in range(3):
        expected = undistort_image(plain.images[i].double(), plain.intrinsics[i].double(), _coeffs(k1=-0.2, p1=0.001))
        torch.testing.assert_close(lens.images[i].double(), expected, rtol=0, atol=1e-5)
    assert (lens.images - plain.images).abs().max() > 0.1
