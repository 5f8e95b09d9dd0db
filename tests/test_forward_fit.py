"""Forward-facing scenes are fitted in NDC (nerfmeta.fit.sampler.fit_space); other scenes as before."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from nerfmeta.collection.forward import ForwardSceneConfig, make_forward_scene
from nerfmeta.data import load_scene
from nerfmeta.fit.evaluate import evaluate_views
from nerfmeta.fit.loop import FitConfig
from nerfmeta.fit.restore import load_fitted_run
from nerfmeta.fit.run import RunConfig, read_metrics, run_fit
from nerfmeta.fit.sampler import NDC_DEPTH_SCALE, RaySampler, fit_space, view_rays
from nerfmeta.render.rays import image_rays

TINY = ForwardSceneConfig(width=24, height=18, grid=(3, 3), supersample=1)


@pytest.fixture(scope="module")
def forward_scene(tmp_path_factory):
    return make_forward_scene(tmp_path_factory.mktemp("fwd") / "scene", TINY)


def test_an_object_scene_is_left_as_it_was(tiny_scene):
    scene = load_scene(tiny_scene)
    assert scene.scene_type.kind == "object" and fit_space(scene) is scene
    rays = view_rays(scene, 1, "cpu")
    o, d = image_rays(scene.poses[1], scene.intrinsics[1], scene.height, scene.width)
    assert torch.equal(rays.origins, o.reshape(-1, 3)) and torch.equal(rays.directions, d.reshape(-1, 3))
    assert torch.all(rays.near == scene.near) and torch.all(rays.far == scene.far)
    g = torch.Generator().manual_seed(3)
    batch = RaySampler(scene, "train", "cpu").sample(64, g)
    assert torch.all(batch.near == scene.near) and torch.all(batch.far == scene.far)
    assert torch.allclose(batch.directions.norm(dim=-1), torch.ones(64))


def test_a_forward_scene_is_fitted_in_ndc(forward_scene):
    scene = fit_space(load_scene(forward_scene))
    assert scene.ndc is not None and scene.near == 0.0
    assert fit_space(scene) is scene  # once is enough
    box = scene.bounds
    assert box[0, 2] == -NDC_DEPTH_SCALE and box[1, 2] == NDC_DEPTH_SCALE
    assert torch.all(box[0, :2] <= -0.9) and torch.all(box[1, :2] >= 0.9)  # the reference frustum and a margin
    for view in range(scene.n_views):
        rays = view_rays(scene, view, "cpu")
        assert torch.allclose(rays.directions.norm(dim=-1), torch.ones(len(rays)))
        assert torch.all(rays.near == 0.0)
        for t in (rays.near, rays.far):  # every pixel ray, near plane to infinity, lies in the box
            p = rays.origins + t[:, None] * rays.directions
            assert torch.all(p >= box[0] - 1e-5) and torch.all(p <= box[1] + 1e-5)
        far_end = (rays.origins + rays.far[:, None] * rays.directions)[:, 2]
        assert torch.allclose(far_end, torch.full((len(rays),), NDC_DEPTH_SCALE), atol=1e-5)  # infinity
    batch = RaySampler(scene, "train", "cpu").sample(32, torch.Generator().manual_seed(0))
    assert torch.all(batch.near == 0.0)
    ends = batch.origins + batch.far[:, None] * batch.directions
    assert torch.allclose(ends[:, 2], torch.full((32,), NDC_DEPTH_SCALE), atol=1e-5) and torch.all(ends >= box[0] - 1e-5)


@pytest.mark.parametrize("scene_type,ndc", [("auto", True), ("object", False)])
def test_fit_records_the_space_and_learns(forward_scene, tmp_path, scene_type, ndc):
    config = RunConfig(scene=str(forward_scene), scene_type=scene_type, renders=0,
                       model={"coarse_iters": 10, "growth_steps": [10], "num_voxels": 24**3, "coarse_num_voxels": 12**3,
                              "coarse_alpha_init": 1e-2},
                       fit=FitConfig(iters=40, batch_rays=256, eval_every=0, checkpoint_every=0, final_ssim=False))
    summary = run_fit(config, tmp_path / "run")
    assert ("ndc" in summary["scene_type"]) is ndc
    assert summary["scene_type"]["kind"] == ("forward" if ndc else "object")
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["scene_type"] == scene_type
    records = read_metrics(tmp_path / "run" / "metrics.jsonl")
    assert records[-1]["train_psnr"] > records[0]["train_psnr"] + 3.0
    # loaded back (render, mesh, eval-geometry), the run sees its scene in the space it was fitted in
    fitted = load_fitted_run(tmp_path / "run")
    assert (fitted.scene.ndc is not None) is ndc
    again = evaluate_views(fitted.model, fitted.scene, list(fitted.scene.splits["test"]), torch.ones(3), with_ssim=False)
    assert again.psnr == pytest.approx(summary["test_psnr"], abs=1e-3)


def test_forward_scenes_get_the_grids_forward_defaults_and_set_still_wins(forward_scene, tiny_scene):
    forward = fit_space(load_scene(forward_scene))
    assert RunConfig(scene="x").model_config(forward).coarse_iters == 50
    assert RunConfig(scene="x").model_config(forward).coarse_alpha_init == 1e-2
    assert RunConfig(scene="x", model={"coarse_iters": 7}).model_config(forward).coarse_iters == 7
    assert RunConfig(scene="x").model_config(load_scene(tiny_scene)).coarse_iters == 100
    # one-voxel steps: test renders average two marches (render_phases), objects one
    assert RunConfig(scene="x").model_config(forward).render_phases == 2
    assert RunConfig(scene="x", model={"render_phases": 1}).model_config(forward).render_phases == 1
    assert RunConfig(scene="x").model_config(load_scene(tiny_scene)).render_phases == 1


def test_a_forward_grid_has_a_quarter_voxel_per_pixel_and_an_object_grid_keeps_its_own(forward_scene, tiny_scene):
    """The NDC grid is sized from the image at 0.25 voxels per pixel (DirectVoxGO's LLFF ratio), not at the
    object grid's 0.88, and at most 64 voxels across; an explicit count, ratio or cap still wins."""
    forward = fit_space(load_scene(forward_scene))
    sized = dataclasses.replace(forward, images=torch.zeros(1, 120, 160, 3))
    assert RunConfig(scene="x").model_config(sized).num_voxels == 40**3
    assert RunConfig(scene="x").model_config(sized).lr_density == 0.3
    assert RunConfig(scene="x", model={"voxels_per_pixel": 0.5, "max_side": 160}).model_config(sized).num_voxels == 80**3
    # at most 64 across, whatever the images' size (LLFF's 504 x 378 would give 126)
    assert RunConfig(scene="x", model={"voxels_per_pixel": 0.5}).model_config(sized).num_voxels == 64**3
    large = dataclasses.replace(forward, images=torch.zeros(1, 378, 504, 3))
    assert RunConfig(scene="x").model_config(large).num_voxels == 64**3
    assert RunConfig(scene="x", model={"num_voxels": 1000}).model_config(sized).num_voxels == 1000
    obj = load_scene(tiny_scene)
    side = round(0.88 * max(obj.height, obj.width))
    assert RunConfig(scene="x").model_config(obj).num_voxels == max(16, min(160, side)) ** 3


def test_a_classic_llff_folder_fits_end_to_end_in_ndc(tmp_path):
    """images/ at full size, images_4/ reduced, (h, w, f) of the full size: `fit --downscale 4` reads images_4/."""
    from llff_scenes import CONFIG as config, write_classic_llff
    from nerfmeta.cli import main

    scene_dir = tmp_path / "fern_like"
    write_classic_llff(scene_dir)
    scene = load_scene(scene_dir, downscale=4)
    assert (scene.height, scene.width) == (9, 12) and scene.scene_type.kind == "forward"
    assert torch.allclose(scene.intrinsics[0], torch.tensor([config.focal / 4, config.focal / 4, 6.0, 4.5]))
    out = tmp_path / "run"
    assert main(["fit", str(scene_dir), "--out", str(out), "--downscale", "4", "--init", "scratch", "--iters", "12",
                 "--batch-rays", "128", "--eval-every", "0", "--checkpoint-every", "0", "--set", "coarse_iters=6"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene_type"]["kind"] == "forward" and "ndc" in summary["scene_type"]
    assert summary["resolution"] == [9, 12] and summary["iters"] == 12 and summary["test_psnr"] is not None
    assert json.loads((out / "config.json").read_text())["model"]["coarse_alpha_init"] == 1e-2  # the forward defaults


def test_a_forward_scene_ndc_cannot_hold_is_refused_in_one_line(forward_scene):
    from dataclasses import replace

    from nerfmeta.data.scene_type import SceneType
    from nerfmeta.errors import ConfigError

    scene = load_scene(forward_scene)
    turned = scene.poses.clone()
    c, s = 0.0, 1.0  # the first camera turned 90 degrees about the up axis: it looks sideways
    turn = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    turned[0, :3, :3] = turned[0, :3, :3] @ turn
    with pytest.raises(ConfigError, match="--scene-type object"):
        fit_space(replace(scene, poses=turned, scene_type=SceneType("forward", "set by the user", detected=False)))


def test_the_ndc_near_plane_is_recorded_per_run_and_old_runs_keep_nerfs_factor(forward_scene):
    """A run's NDC space comes from its own ``ndc_near_factor`` (default 0.9); a ``config.json`` written before
    the factor was recorded reloads with NeRF's 0.75, so its checkpoint stays in the space it was fitted in."""
    from nerfmeta.errors import ConfigError
    from nerfmeta.fit.run import run_scene
    from nerfmeta.io import to_jsonable
    from nerfmeta.render.ndc import BD_FACTOR, NEAR_FACTOR, ndc_space

    loaded = load_scene(forward_scene)
    new = run_scene(RunConfig(scene=str(forward_scene)))
    assert new.ndc.near_factor == NEAR_FACTOR == 0.9
    assert fit_space(loaded).ndc.near_factor == NEAR_FACTOR  # the library default is the runs' default
    assert new.ndc.scene_near == pytest.approx(loaded.near)  # the render path's focus depth is the scene's near
    assert new.ndc.scale == pytest.approx(1.0 / (0.9 * loaded.near))
    old_json = {k: v for k, v in to_jsonable(RunConfig(scene=str(forward_scene))).items() if k != "ndc_near_factor"}
    old = run_scene(RunConfig.from_json(old_json))
    assert old.ndc.near_factor == BD_FACTOR == 0.75 and old.ndc.scale == pytest.approx(1.0 / (0.75 * loaded.near))
    assert RunConfig.from_json(to_jsonable(RunConfig(scene="x", ndc_near_factor=0.8))).ndc_near_factor == 0.8
    # a nearer plane moves every NDC point: the two spaces differ where it matters, in depth
    assert not torch.allclose(view_rays(new, 0, "cpu").origins, view_rays(old, 0, "cpu").origins)
    with pytest.raises(ValueError, match="near factor"):
        ndc_space(loaded.poses, loaded.intrinsics, loaded.height, loaded.width, loaded.near, near_factor=1.5)
    from nerfmeta.config import check_fields

    with pytest.raises(ConfigError, match="ndc_near_factor"):
        check_fields(RunConfig(scene="x", ndc_near_factor=0.0), "run config")
