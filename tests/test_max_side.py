"""Large images are read at a reduced size by default (RunConfig.max_side): powers of two, LLFF's images_N used."""

from __future__ import annotations

import json

import pytest
import torch

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
