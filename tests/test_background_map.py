"""The learned background of forward-facing and unbounded scenes: an equirectangular colour table looked up by ray direction."""

import dataclasses
import math

import pytest
import torch

from nerfmeta.collection.forward import ForwardSceneConfig, make_forward_scene
from nerfmeta.data import load_scene
from nerfmeta.data.scene import RayBatch
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import check_partition
from nerfmeta.fields.registry import config_from_dict
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig
from nerfmeta.fit.run import RunConfig
from nerfmeta.fit.sampler import fit_space, view_rays
from nerfmeta.io import to_jsonable
from nerfmeta.render.background import clamp_inward, equirect_coords, equirect_lookup

SMALL = VoxelGridConfig(coarse_iters=30, coarse_num_voxels=16**3, num_voxels=24**3, growth_steps=(20,),
                        occupancy_every=10, mlp_width=16, feature_dim=4)
WHITE = torch.ones(3)


def _direction(lon: float, lat: float) -> torch.Tensor:
    return torch.tensor([[math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]],
                        dtype=torch.float64)


def _table(h: int = 4, w: int = 8) -> torch.Tensor:
    """(2, h, w): channel 0 the column index, channel 1 ten times the row index."""
    cols = torch.arange(w, dtype=torch.float64).expand(h, w)
    rows = torch.arange(h, dtype=torch.float64)[:, None].expand(h, w)
    return torch.stack([cols, 10.0 * rows])


def test_inward_clamp_is_a_clamp_whose_gradient_only_brings_values_back():
    x = torch.tensor([-0.5, -0.5, 0.0, 0.3, 1.0, 1.5, 1.5], dtype=torch.float64, requires_grad=True)
    upstream = torch.tensor([-1.0, 1.0, 1.0, 2.0, -1.0, 1.0, -1.0], dtype=torch.float64)
    out = clamp_inward(x)
    assert torch.equal(out, x.detach().clamp(0.0, 1.0))
    out.backward(upstream)
    # inside (ends included) the identity; outside, only a gradient whose descent step points back in
    assert x.grad.tolist() == [-1.0, 0.0, 1.0, 2.0, -1.0, 1.0, 0.0]


@pytest.mark.parametrize("clamp,recovers", [(lambda v: v.clamp(0.0, 1.0), False), (clamp_inward, True)])
def test_a_colour_pushed_below_black_comes_back_only_through_the_inward_clamp(clamp, recovers):
    # A channel that overshot 0 (as the forward-facing scenes' colour does on its way to black) and a target that
    # later wants grey: a plain clamp gives it no gradient, so it stays black for ever.
    value = torch.tensor([-0.5], requires_grad=True)
    opt = torch.optim.Adam([value], lr=0.05)
    for _ in range(200):
        opt.zero_grad()
        ((clamp(value) - 0.3) ** 2).sum().backward()
        opt.step()
    assert (abs(float(clamp(value.detach())) - 0.3) < 0.02) == recovers


def test_inward_clamp_does_not_push_a_value_further_out():
    value = torch.tensor([-0.5], requires_grad=True)
    opt = torch.optim.Adam([value], lr=0.05)
    for _ in range(50):
        opt.zero_grad()
        ((clamp_inward(value) + 0.2) ** 2).sum().backward()  # the target is below black: black is the best it can do
        opt.step()
    assert float(value.detach()) == -0.5


def test_texel_centres_give_their_values_exactly():
    table = _table()
    for i in range(4):
        for j in range(8):
            lon, lat = (j + 0.5) / 8 * 2 * math.pi - math.pi, (i + 0.5) / 4 * math.pi - math.pi / 2
            value = equirect_lookup(table, _direction(lon, lat))[0]
            assert torch.allclose(value, torch.tensor([float(j), 10.0 * i], dtype=torch.float64), atol=1e-9)


def test_longitude_wraps_round_and_latitude_clamps_at_the_poles():
    table = _table()
    lat = 1.5 / 4 * math.pi - math.pi / 2  # row 1's centre
    for lon in (math.pi - 1e-12, -math.pi + 1e-12):  # the seam: half the last column, half the first
        assert equirect_lookup(table, _direction(lon, lat))[0, 0].item() == pytest.approx(3.5, abs=1e-6)
    # either side of the seam, linear between the last column (7) and the first (0): no jump from 7 to 0
    slope = 7.0 / (2 * math.pi / 8)  # value per radian across the seam
    assert equirect_lookup(table, _direction(math.pi - 0.01, lat))[0, 0].item() == pytest.approx(3.5 + 0.01 * slope)
    assert equirect_lookup(table, _direction(-math.pi + 0.01, lat))[0, 0].item() == pytest.approx(3.5 - 0.01 * slope)
    up, down = equirect_lookup(table, _direction(0.3, math.pi / 2)), equirect_lookup(table, _direction(0.3, -math.pi / 2))
    assert up[0, 1].item() == pytest.approx(30.0) and down[0, 1].item() == pytest.approx(0.0)


def test_coordinates_ignore_length_and_stay_in_range():
    d = torch.randn(1000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    uv = equirect_coords(d)
    assert torch.allclose(uv, equirect_coords(3.7 * d)) and bool((uv.abs() <= 1.0).all())


@pytest.fixture(scope="module")
def unbounded(tiny_scene):
    return load_scene(tiny_scene, scene_type="unbounded")


def _model(config, scene):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        return VoxelGrid(config.for_scene(scene), scene.bounds)


def test_a_new_table_renders_exactly_the_fixed_background_and_is_a_parameter_group(unbounded):
    plain, learned = _model(SMALL, unbounded), _model(dataclasses.replace(SMALL, background_map=8), unbounded)
    learned.load_state_dict({**plain.state_dict(), "background_map": learned.background_map.detach()})
    rays = view_rays(unbounded, unbounded.splits["test"][0], "cpu")
    with torch.no_grad():
        assert torch.equal(plain(rays, background=WHITE).rgb, learned(rays, background=WHITE).rgb)
    assert tuple(learned.background_map.shape) == (3, 8, 16)
    check_partition(learned)
    assert [g.name for g in learned.param_groups()][-1] == "background"
    assert [layer.name for layer in learned.layers()][-1] == "background_map"


def test_the_table_learns_the_colour_along_each_direction(unbounded):
    """Rays through an empty grid end on the table alone: fitted through the render to a colour that varies with
    direction, it reproduces that colour along directions it was not fitted on (the gradient reaches the table)."""
    model = _model(dataclasses.replace(SMALL, background_map=16), unbounded)
    with torch.no_grad():
        model.density_coarse.fill_(-30.0)  # nothing anywhere: every ray's light is the background's

    def rays(seed: int, n: int = 4096) -> tuple[RayBatch, torch.Tensor]:
        d = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed)), dim=-1)
        origin = torch.tensor(model.config.inner_box[:3]).expand(n, 3)
        batch = RayBatch(origins=origin.clone(), directions=d, near=torch.zeros(n), far=torch.full((n,), 1e6))
        target = 0.5 + 0.4 * torch.stack([d[:, 0], d[:, 1] * d[:, 2], torch.sin(3 * d[:, 1])], dim=-1)
        return batch, target

    test, truth = rays(1)
    with torch.no_grad():
        before = float(((model(test, background=WHITE).rgb - truth) ** 2).mean())
    opt = torch.optim.Adam([model.background_map], lr=0.05)
    for step in range(200):
        batch, target = rays(100 + step)
        loss = ((model(batch, background=WHITE, train=True).rgb - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = float(((model(test, background=WHITE).rgb - truth) ** 2).mean())
    assert before > 0.05 and after < 2e-4, (before, after)


def test_bad_values_are_refused():
    for bad in ({"background_map": -1}, {"background_map": 2.5}, {"background_map": True}, {"lr_background": 0.0}):
        with pytest.raises(ConfigError):
            dataclasses.replace(SMALL, **bad)


def test_forward_and_unbounded_scenes_learn_a_background_and_objects_keep_the_fixed_one(tiny_scene, tmp_path):
    obj, unb = load_scene(tiny_scene), load_scene(tiny_scene, scene_type="unbounded")
    fwd = fit_space(load_scene(make_forward_scene(tmp_path / "fwd", ForwardSceneConfig(width=24, height=18, grid=(3, 3),
                                                                                       supersample=1))))
    run = RunConfig(scene="x")
    assert run.model_config(obj).background_map == 0
    assert run.model_config(unb).background_map == 1 and run.model_config(fwd).background_map == 1
    assert RunConfig(scene="x", model={"background_map": 0}).model_config(unb).background_map == 0  # --set wins
    # a run saved before the table existed resumes without it (its config.json holds the whole model config)
    saved = to_jsonable(run.model_config(unb))
    del saved["background_map"], saved["lr_background"]
    assert config_from_dict("grid", saved).background_map == 0
