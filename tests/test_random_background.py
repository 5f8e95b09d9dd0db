"""Random training backgrounds (``FitConfig.random_background``): a capture whose rays all end on something must be opaque."""

import dataclasses

import pytest
import torch

from nerfmeta.data import load_scene
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.sampler import view_rays

COARSE = VoxelGridConfig(coarse_iters=100, coarse_num_voxels=16**3, num_voxels=24**3, growth_steps=(), mlp_width=16,
                         feature_dim=4)
WHITE = torch.ones(3)


@pytest.fixture(scope="module")
def white_room(tiny_scene):
    """The tiny scene's cameras, every photo plain white and opaque (no alpha), read as an unbounded capture."""
    scene = load_scene(tiny_scene, scene_type="unbounded")
    return dataclasses.replace(scene, images=torch.ones_like(scene.images), alphas=None, background=None)


def _coarse_fit(scene, **fit_options):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = VoxelGrid(COARSE.for_scene(scene), scene.bounds)
    config = FitConfig(iters=COARSE.coarse_iters, batch_rays=256, eval_every=0, checkpoint_every=0, final_ssim=False,
                       final_lpips=False, **fit_options)
    result = fit(model, scene, config, background=WHITE)
    return model, result


def _opacity(model, scene):
    rays = view_rays(scene, scene.splits["train"][0], "cpu")
    with torch.no_grad():
        return float(model(rays, background=WHITE).acc.mean())


def test_a_white_capture_is_not_fitted_by_transparency(white_room):
    """On a fixed white background a clear grid already renders a white photo exactly, so nothing makes it opaque;
    with a random colour behind, every ray has to end on something."""
    fixed, fixed_result = _coarse_fit(white_room, random_background=())
    drawn, drawn_result = _coarse_fit(white_room, random_background=("unbounded",))
    assert _opacity(fixed, white_room) < 0.01
    assert _opacity(drawn, white_room) > 0.9
    assert drawn_result.state.decisions["random_background"]["value"] is True
    assert "random_background" not in fixed_result.state.decisions  # not asked for: nothing said
    # test renders keep the fixed background: the opaque white fit still scores well on its white test views
    assert drawn_result.final.psnr > 20.0 and fixed_result.final.psnr > 40.0


def test_other_kinds_and_scenes_with_alpha_keep_the_fixed_background(tiny_scene):
    """A scene of a kind not named (an object scene with the forward-facing kind named), and an unbounded one whose
    photos have alpha (whatever the setting), fit exactly as on the fixed background: the same parameters, the same
    random draws."""
    with_alpha = load_scene(tiny_scene, scene_type="unbounded")
    opaque_object = dataclasses.replace(load_scene(tiny_scene), alphas=None, background=None)
    assert with_alpha.alphas is not None and opaque_object.scene_type.kind == "object"
    for scene, drawn in ((opaque_object, ("forward",)), (with_alpha, ("unbounded",))):
        a, result = _coarse_fit(scene, random_background=drawn)
        b, _ = _coarse_fit(scene, random_background=())
        assert result.state.decisions["random_background"]["value"] is False
        assert ("alpha" if scene is with_alpha else "an object scene, not one of random_background=forward") in \
            result.state.decisions["random_background"]["reason"]
        for name, value in a.state_dict().items():
            assert torch.equal(value, b.state_dict()[name]), name


def test_saved_configs_without_the_field_resume_on_the_fixed_background():
    assert FitConfig().random_background == ()
    assert FitConfig.from_json({"iters": 10}).random_background == ()
    assert FitConfig.from_json({"iters": 10, "random_background": ["unbounded"]}).random_background == ("unbounded",)
    with pytest.raises(Exception, match="random_background"):
        FitConfig(random_background=("sky",))
