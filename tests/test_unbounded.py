"""Unbounded scenes: the voxel grid in a contracted space, chosen per scene type, other scenes unchanged."""

import copy
import dataclasses
import json

import pytest
import torch

from nerfmeta.io import to_jsonable
from nerfmeta.data import load_scene
from nerfmeta.fields.registry import config_from_dict
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.run import RunConfig
from nerfmeta.fit.sampler import view_rays
from nerfmeta.metrics import mse_to_psnr

SMALL = VoxelGridConfig(coarse_iters=30, coarse_num_voxels=16**3, num_voxels=24**3, growth_steps=(20,),
                        occupancy_every=10, mlp_width=16, feature_dim=4)
WHITE = torch.ones(3)


@pytest.fixture(scope="module")
def scenes(tiny_scene):
    return {kind: load_scene(tiny_scene, scene_type=kind) for kind in ("auto", "unbounded")}


def _model(config, scene, seed=0):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return VoxelGrid(config.for_scene(scene), scene.bounds)


def _psnr(model, scene):
    rays = view_rays(scene, scene.splits["test"][0], "cpu")
    with torch.no_grad():
        rgb = model(rays, background=WHITE).rgb
    return float(mse_to_psnr(((rgb - rays.target) ** 2).mean()))


def test_scene_type_picks_the_space(scenes):
    obj = SMALL.for_scene(scenes["auto"])
    assert scenes["auto"].scene_type.kind == "object" and obj.space == "box" and obj.inner_box == ()
    unb = SMALL.for_scene(scenes["unbounded"])
    assert unb.space == "contracted" and len(unb.inner_box) == 4
    # the inner box reaches half way to the cameras
    model = VoxelGrid(unb, scenes["unbounded"].bounds)
    cams = model.box.normalise(scenes["unbounded"].poses[:, :3, 3].double()).abs().amax(-1)
    assert abs(float(cams.median()) - 2.0) < 1e-5
    assert model.bounds.tolist() == [[-2.0] * 3, [2.0] * 3]
    # named explicitly, the space is kept whatever the scene
    assert dataclasses.replace(SMALL, space="box").for_scene(scenes["unbounded"]).space == "box"


def test_object_scenes_render_exactly_as_before(scenes):
    """``auto`` on an object scene is the bounded grid: same parameters, same renders as ``box``."""
    scene = scenes["auto"]
    a, b = _model(SMALL, scene), _model(dataclasses.replace(SMALL, space="box"), scene)
    with torch.no_grad():
        for m in (a, b):
            m.density_coarse.normal_(generator=torch.Generator().manual_seed(1))
            m.color_coarse.normal_(generator=torch.Generator().manual_seed(2))
    rays = view_rays(scene, scene.splits["test"][0], "cpu")
    with torch.no_grad():
        assert torch.equal(a(rays, background=WHITE).rgb, b(rays, background=WHITE).rgb)
    assert a.box is None and torch.equal(a.bounds, scene.bounds)


def test_config_round_trips_through_json(scenes):
    config = SMALL.for_scene(scenes["unbounded"])
    back = config_from_dict("grid", json.loads(json.dumps(to_jsonable(config))))
    assert back == config


def test_contracted_config_needs_an_inner_box():
    with pytest.raises(Exception, match="inner_box"):
        VoxelGrid(dataclasses.replace(SMALL, space="contracted"), torch.tensor([[-1.0] * 3, [1.0] * 3]))


def test_contracted_fit_learns_and_its_structure_round_trips(scenes):
    scene = scenes["unbounded"]
    # A small inner box around the spheres (the cameras stand outside it, in the shell) so a tiny grid resolves them.
    config = dataclasses.replace(SMALL, inner_box=(0.0, 0.0, 0.0, 1.5))
    model = _model(config, scene)
    before = _psnr(model, scene)
    train = dataclasses.replace(scene, splits={"train": scene.splits["train"]})
    fit(model, train, FitConfig(iters=70, batch_rays=512, eval_every=0, lr_decay=1.0), background=WHITE)
    after = _psnr(model, scene)
    assert model.stage == "fine" and after > before + 6.0, (before, after)
    assert torch.equal(model.bounds, torch.tensor([[-2.0] * 3, [2.0] * 3]))  # never tightened
    other = _model(config, scene, seed=1)
    other.load_structure(copy.deepcopy(model.structure()))
    other.load_state_dict(model.state_dict())
    rays = view_rays(scene, scene.splits["test"][1], "cpu")
    with torch.no_grad():
        assert torch.equal(model(rays, background=WHITE).rgb, other(rays, background=WHITE).rgb)


def test_every_scene_defaults_to_the_view_dependence_trial_and_set_still_wins(scenes):
    """An unbounded capture's grid decides per scene whether to keep the colour MLP (``view_dependent="auto"``, the
    scene type's default and, since session 43, every scene's); ``--set`` overrides it on either kind."""
    run = RunConfig(scene="x", backbone="grid")
    assert run.model_config(scenes["unbounded"]).view_dependent == "auto"
    assert run.model_config(scenes["auto"]).view_dependent == "auto"  # the tiny scene is an object on white
    kept = RunConfig(scene="x", backbone="grid", model={"view_dependent": True})
    for kind in ("unbounded", "auto"):
        assert kept.model_config(scenes[kind]).view_dependent is True


def test_unbounded_scenes_march_one_voxel_steps_and_set_still_wins(scenes):
    """An unbounded capture's grid samples every voxel (``stepsize`` 1.0, the scene type's default), an object
    scene every half voxel; ``--set stepsize=...`` overrides either, and a new grid's alpha at raw density 0
    is still ``coarse_alpha_init`` per step of the longer step."""
    run = RunConfig(scene="x", backbone="grid")
    unbounded = run.model_config(scenes["unbounded"])
    assert unbounded.stepsize == 1.0
    assert run.model_config(scenes["auto"]).stepsize == 0.5
    assert RunConfig(scene="x", backbone="grid", model={"stepsize": 0.5}).model_config(scenes["unbounded"]).stepsize == 0.5
    # and its test renders average two marches half a step apart (render_phases), an object's one
    assert unbounded.render_phases == 2 and run.model_config(scenes["auto"]).render_phases == 1
    assert RunConfig(scene="x", backbone="grid", model={"render_phases": 1}).model_config(scenes["unbounded"]).render_phases == 1
    model = _model(unbounded, scenes["unbounded"])  # a new grid: raw density 0 everywhere
    alpha = model.alpha_per_step(model.bounds.mean(0, keepdim=True).expand(4, 3))
    torch.testing.assert_close(alpha, torch.full_like(alpha, unbounded.coarse_alpha_init))
