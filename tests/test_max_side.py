"""Large images are read at a reduced size by default (RunConfig.max_side): powers of two, LLFF's images_N used."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.data.common import side_factor
from nerfmeta.data.images import MAX_SIDE
from nerfmeta.fit.run import RunConfig


@pytest.mark.parametrize("height,width,factor,max_side,want", [
    (3024, 4032, 1.0, 1600, 4.0),  # an LLFF phone capture: 1008 x 756
    (720, 1280, 1.0, 1600, 1.0),  # beer: as it is
    (3024, 4032, 2.0, 1600, 4.0),  # 2016 is still over: one more halving
    (1000, 2000, 1.0, 1600, 2.0),
    (3024, 4032, 1.0, 0, 1.0),  # no limit
    (1600, 1600, 1.0, 1600, 1.0),  # at the limit: kept
])
def test_side_factor_is_the_smallest_power_of_two_within_the_limit(height, width, factor, max_side, want):
    assert side_factor(height, width, factor, max_side) == want


def test_a_limited_load_equals_the_downscaled_one(tiny_scene):
    limited = load_scene(tiny_scene, max_side=16)  # 32 x 32 -> 16 x 16
    halved = load_scene(tiny_scene, downscale=2)
    assert (limited.height, limited.width, limited.downscale) == (16, 16, 2.0)
    torch.testing.assert_close(limited.images, halved.images, rtol=0, atol=0)
    torch.testing.assert_close(limited.intrinsics, halved.intrinsics, rtol=0, atol=0)
    assert load_scene(tiny_scene, max_side=32).downscale == 1.0


def test_an_llff_capture_over_the_limit_is_read_from_its_reduced_folder(tmp_path):
    from llff_scenes import CONFIG as config, write_classic_llff

    scene_dir = tmp_path / "fern_like"
    small = write_classic_llff(scene_dir, reduced_offset=1)  # images_4/ told apart from images/ reduced
    scene = load_scene(scene_dir, max_side=12)  # 48 wide: 1/4, from images_4/
    assert (scene.height, scene.width, scene.downscale) == (9, 12, 4.0)
    assert torch.allclose(scene.images[0], torch.from_numpy(small[0]).float() / 255)
    assert torch.allclose(scene.intrinsics[0], torch.tensor([config.focal / 4, config.focal / 4, 6.0, 4.5]))
    (scene_dir / "images_4").rename(tmp_path / "gone")  # without it: images/ read and reduced, the same factor
    assert load_scene(scene_dir, max_side=12).downscale == 4.0
    # images/ already smaller than column 5 says: sized by its files, not reduced again
    for image in (tmp_path / "gone").iterdir():
        (scene_dir / "images" / image.name).write_bytes(image.read_bytes())
    scene = load_scene(scene_dir, max_side=12)
    assert (scene.height, scene.width, scene.downscale) == (9, 12, 1.0)


def test_fit_limits_by_default_and_a_downscale_given_is_the_one_used(tiny_scene, tmp_path):
    args = ["fit", str(tiny_scene), "--init", "scratch", "--iters", "2", "--eval-views", "1", "--renders", "0",
            "--no-eval-ssim", "--no-final-lpips"]
    for extra, max_side, size in (([], MAX_SIDE, 32), (["--max-side", "16"], 16, 16), (["--downscale", "2"], 0, 16)):
        out = tmp_path / f"run{len(extra)}{max_side}"
        assert main([*args, "--out", str(out), *extra]) == 0
        assert json.loads((out / "config.json").read_text())["max_side"] == max_side
        assert json.loads((out / "summary.json").read_text())["resolution"] == [size, size]
    # a run saved before the limit existed keeps reading its images whole
    assert RunConfig.from_json({"scene": "s"}).max_side == 0


def _nerfstudio_scene(folder: Path, size: tuple[int, int], copies: dict[int, int]) -> None:
    """A 4-view nerfstudio scene of grey images at ``size`` (h, w), and ``images_N/`` copies of value ``copies[N]``
    (a value the full-size images do not have, to tell which folder was read)."""
    (folder / "images").mkdir(parents=True)
    frames = []
    for k in range(4):
        name = f"frame_{k:05d}.png"
        Image.fromarray(np.full((*size, 3), 100, np.uint8)).save(folder / "images" / name)
        for n, value in copies.items():
            (folder / f"images_{n}").mkdir(exist_ok=True)
            Image.fromarray(np.full((size[0] // n, size[1] // n, 3), value, np.uint8)).save(folder / f"images_{n}" / name)
        a = 2 * math.pi * k / 4
        pose = [[-math.sin(a), 0, math.cos(a), 4 * math.cos(a)], [math.cos(a), 0, math.sin(a), 4 * math.sin(a)],
                [0, 1, 0, 0], [0, 0, 0, 1]]
        frames.append({"file_path": f"images/{name}", "transform_matrix": pose})
    doc = {"fl_x": 50.0, "fl_y": 50.0, "cx": size[1] / 2, "cy": size[0] / 2, "near": 1.0, "far": 8.0, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(doc))


def test_nerfstudio_reduced_copies_are_read_when_the_factor_matches(tmp_path: Path,
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    """ns-process-data writes images_2/4/8 beside images/: a fit at 1/4 decodes the quarter-size copies."""
    _nerfstudio_scene(tmp_path / "s", (64, 96), {2: 20, 4: 40})
    full = load_scene(tmp_path / "s", normalize=False)
    quarter = load_scene(tmp_path / "s", normalize=False, max_side=24)  # 96 -> 24: a factor of 4
    assert (quarter.height, quarter.width, quarter.downscale) == (16, 24, 4.0)
    assert float(quarter.images.mean()) == pytest.approx(40 / 255, abs=1e-6)  # from images_4/
    assert quarter.image_names == full.image_names  # named as in transforms.json (--drop-views keeps working)
    torch.testing.assert_close(quarter.intrinsics, full.intrinsics / 4)
    given = load_scene(tmp_path / "s", normalize=False, downscale=2)
    assert float(given.images.mean()) == pytest.approx(20 / 255, abs=1e-6) and given.downscale == 2.0
    eighth = load_scene(tmp_path / "s", normalize=False, downscale=8)  # no images_8/: images/ reduced on load
    assert float(eighth.images.mean()) == pytest.approx(100 / 255, abs=1e-6) and eighth.width == 12
    assert "images_" not in caplog.text  # nothing to say while the copies are whole
    (tmp_path / "s" / "images_4" / "frame_00003.png").unlink()  # an incomplete copy is passed over, and said so
    with caplog.at_level("WARNING"):
        assert float(load_scene(tmp_path / "s", normalize=False, max_side=24).images.mean()) == pytest.approx(
            100 / 255, abs=1e-6)
    assert "images_4 holds 3 of the 4 frames' images" in caplog.text
    caplog.clear()
    Image.fromarray(np.full((8, 12, 3), 40, np.uint8)).save(tmp_path / "s" / "images_2" / "frame_00000.png")
    with caplog.at_level("WARNING"):  # a copy of another size (a factor of 8 filed as images_2/)
        assert float(load_scene(tmp_path / "s", normalize=False, downscale=2).images.mean()) == pytest.approx(
            100 / 255, abs=1e-6)
    assert "holds 12 x 8 images, not images/ reduced 2 times (48 x 32)" in caplog.text
