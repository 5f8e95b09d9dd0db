"""The tiny analytic scene (nerfmeta.data.synthetic)."""

from __future__ import annotations

import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from nerfmeta.data import load_scene
from nerfmeta.data.synthetic import render_spheres, tiny_aabb, write_tiny_scene


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_tiny_scene_is_deterministic_and_fast(tmp_path: Path) -> None:
    start = time.perf_counter()
    write_tiny_scene(tmp_path / "a")
    elapsed = time.perf_counter() - start
    write_tiny_scene(tmp_path / "b")
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert sorted(a) == sorted(b) and len(a) == 2 + 8 + 4
    assert a == b
    assert elapsed < 1.0
    write_tiny_scene(tmp_path / "c", seed=1)
    assert _files(tmp_path / "c")["train/r_0.png"] != a["train/r_0.png"]


def test_tiny_scene_alpha_is_pixel_coverage(tiny_scene: Path) -> None:
    rgba = np.stack([iio.imread(tiny_scene / "train" / f"r_{k}.png") for k in range(8)])
    assert rgba.shape == (8, 32, 32, 4)
    alpha = rgba[..., 3]
    # 2x2 supersampling: alpha is 0, 1/4, 2/4, 3/4 or 1
    assert set(np.unique(alpha).tolist()) <= {0, 64, 128, 191, 255}
    assert (alpha == 0).any() and (alpha == 255).any() and ((alpha > 0) & (alpha < 255)).any()
    assert (rgba[..., :3][alpha == 0] == 0).all()
    # the object is in view and not clipped by the image border
    for view in alpha:
        assert view[0].max() == 0 and view[-1].max() == 0 and view[:, 0].max() == 0 and view[:, -1].max() == 0
        assert (view == 255).sum() > 20


def test_tiny_scene_aabb_holds_the_spheres(tiny_scene: Path) -> None:
    scene = load_scene(tiny_scene)
    assert torch.equal(scene.bounds, torch.tensor(tiny_aabb(0), dtype=torch.float32))
    assert (scene.near, scene.far) == (2.0, 6.0)
    # near/far contain the box for every camera
    lo, hi = scene.bounds.double()
    corners = torch.stack(torch.meshgrid(*[torch.stack([lo[i], hi[i]]) for i in range(3)], indexing="ij"), -1).reshape(-1, 3)
    dist = torch.cdist(scene.poses[:, :3, 3].double(), corners)
    assert float(dist.min()) > scene.near and float(dist.max()) < scene.far


def test_render_spheres_hand_case() -> None:
    # A ray straight down onto a unit sphere at the origin hits the top at t = 2, normal +z.
    origins = torch.tensor([[0.0, 0.0, 3.0], [5.0, 5.0, 3.0]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    rgb, hit = render_spheres(
        origins, dirs, torch.zeros(1, 3, dtype=torch.float64), torch.ones(1, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64)
    )
    assert hit.tolist() == [True, False]
    light_z = 0.866 / float(torch.linalg.vector_norm(torch.tensor([0.4, 0.3, 0.866])))
    torch.testing.assert_close(rgb[0], torch.full((3,), 0.25 + 0.75 * light_z, dtype=torch.float64))
    assert torch.equal(rgb[1], torch.zeros(3, dtype=torch.float64))
