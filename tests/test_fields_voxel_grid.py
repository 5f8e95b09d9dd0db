"""Voxel-grid backbone: grid maths (gather gradients, packed marching and compositing against the
dense reference), the initial-alpha shift, layer partition per stage, warm starts across the
coarse->fine switch and growth, occupancy skipping, checkpoint structure, and a short fit."""

import copy
import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch

from nerfmeta.data import load_scene
from nerfmeta.data.scene import RayBatch
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import check_partition
from nerfmeta.fields.grid_ops import (
    channels_last,
    corner_indices_weights,
    corners_from_coords,
    grid_coords,
    grid_points,
    interp_cf,
    interp_coords,
    interp_gather,
    project_cf,
    resample_cf,
    total_variation,
    trilinear_gather,
)
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig, growth_mode, march_phases
from nerfmeta.fit.loop import FitConfig, FitState, fit
from nerfmeta.fit.sampler import view_rays
from nerfmeta.metrics import mse_to_psnr

SMALL = VoxelGridConfig(coarse_iters=40, coarse_num_voxels=16**3, num_voxels=24**3, growth_steps=(20,),
                        occupancy_every=10, mlp_width=16, feature_dim=4, view_dependent=True)  # the MLP path
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
WHITE = torch.ones(3)


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def _model(config=SMALL, bounds=BOX, seed=0):
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return VoxelGrid(config, bounds)


def _fit(model, scene, iters, start=0, batch_rays=512):
    """Steps ``start`` .. ``iters - 1`` of the fit loop on ``scene`` (constant LR, no evaluation)."""
    config = FitConfig(iters=iters, batch_rays=batch_rays, eval_every=0, seed=start, lr_decay=1.0)
    scene = dataclasses.replace(scene, splits={"train": scene.splits["train"]})
    fit(model, scene, config, background=WHITE, state=FitState(step=start))


@pytest.fixture(scope="module")
def stages(scene):
    """One SMALL model fitted through its schedule, copied at the end of the coarse stage (step 40),
    just before the growth step (step 60) and after 100 steps; plus the untrained model."""
    model = _model(bounds=scene.bounds)
    untrained = copy.deepcopy(model)
    _fit(model, scene, SMALL.coarse_iters)
    coarse = copy.deepcopy(model)
    grow_at = SMALL.coarse_iters + SMALL.growth_steps[0]
    _fit(model, scene, grow_at, start=SMALL.coarse_iters)
    before_growth = copy.deepcopy(model)
    _fit(model, scene, 100, start=grow_at)
    return SimpleNamespace(untrained=untrained, coarse=coarse, before_growth=before_growth, final=model, grow_at=grow_at)


def _render(model, rays):
    with torch.no_grad():
        return model(rays, background=WHITE)


def _psnr(a, b):
    return float(mse_to_psnr(((a - b) ** 2).mean()))


def _test_view(scene, k=0):
    return view_rays(scene, scene.splits["test"][k], "cpu")


# -- grid maths ------------------------------------------------------------------------------


@pytest.mark.parametrize("channels", [1, 3])
def test_trilinear_gather_gradcheck_float64(channels):
    g = torch.Generator().manual_seed(0)
    size = (3, 4, 5)
    grid = torch.randn(channels, 60, generator=g, dtype=torch.float64, requires_grad=True)
    points = torch.rand(7, 3, generator=g, dtype=torch.float64) * 2 - 1
    idx, w = corner_indices_weights(points, BOX.double(), size)
    torch.autograd.gradcheck(lambda v: trilinear_gather(v, idx, w), (grid,))
    torch.autograd.gradgradcheck(lambda v: trilinear_gather(v, idx, w) ** 2, (grid,))


def test_trilinear_gather_matches_grid_sample_and_hits_corners_exactly():
    g = torch.Generator().manual_seed(1)
    size = (4, 5, 6)
    grid = torch.randn(3, *size, generator=g, dtype=torch.float64)
    points = torch.rand(50, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2  # some outside: clamped
    box = BOX.double()
    torch.testing.assert_close(interp_gather(grid, points, box), interp_cf(grid, points, box))
    corners = grid_points(box, size).reshape(-1, 3)
    torch.testing.assert_close(interp_gather(grid, corners, box), grid.reshape(3, -1).t(), rtol=0, atol=1e-12)
    idx, w = corner_indices_weights(points, box, size)
    assert idx.shape == w.shape == (8, 50)
    assert (w >= 0).all() and torch.allclose(w.sum(0), torch.ones(50, dtype=torch.float64))


def test_interp_coords_equals_the_gather_in_either_memory_layout():
    g = torch.Generator().manual_seed(2)
    size = (4, 5, 6)
    grid = torch.randn(5, *size, generator=g, dtype=torch.float64)
    points = torch.rand(60, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2  # some outside: clamped to the faces
    x = grid_coords(points, BOX.double(), size).contiguous()
    want = trilinear_gather(grid.reshape(5, -1), *corners_from_coords(x, size))
    for g_ in (grid, channels_last(grid)):
        torch.testing.assert_close(interp_coords(g_, x), want, rtol=0, atol=1e-12)
    corners = grid_coords(grid_points(BOX.double(), size).reshape(-1, 3), BOX.double(), size).contiguous()
    torch.testing.assert_close(interp_coords(grid, corners), grid.reshape(5, -1), rtol=0, atol=1e-12)


def _hat_field(values: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The 1-D piecewise-linear function with ``values`` on evenly spaced corners of [0, 1], at ``t`` (float64)."""
    x = t * (len(values) - 1)
    i = x.floor().clamp(max=len(values) - 2).long()
    return values[i] + (x - i) * (values[i + 1] - values[i])


def test_projection_leaves_a_residual_orthogonal_to_every_new_hat_and_interpolation_does_not():
    """The L2 projection, checked against brute-force quadrature (a million points) rather than its own exact formula."""
    old = torch.randn(1, 7, 2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    t = (torch.arange(1_000_000, dtype=torch.float64) + 0.5) / 1_000_000
    f = _hat_field(old[0, :, 0, 0], t)
    hats = [_hat_field(torch.eye(10, dtype=torch.float64)[i], t) for i in range(10)]
    for move, orthogonal in ((project_cf, True), (resample_cf, False)):
        new = move(old, (10, 2, 2))[0, :, 0, 0]
        residual = f - _hat_field(new, t)
        inner = torch.stack([(residual * h).mean() for h in hats]).abs().max()
        assert (inner < 1e-9) == orthogonal, (move.__name__, float(inner))


def test_projection_keeps_the_mean_fields_the_lattice_holds_and_the_same_lattice():
    gen = torch.Generator().manual_seed(1)
    old = torch.randn(2, 5, 6, 7, dtype=torch.float64, generator=gen)

    def mean(g):  # the exact mean of a trilinear field: trapezoid weights per axis
        w = [torch.full((n,), 1.0 / (n - 1), dtype=torch.float64) for n in g.shape[1:]]
        for v in w:
            v[0] = v[-1] = 0.5 / (len(v) - 1)
        return torch.einsum("cijk,i,j,k->c", g, *w)

    new = project_cf(old, (9, 8, 12))
    assert torch.allclose(mean(new), mean(old), atol=1e-12)
    assert not torch.allclose(mean(resample_cf(old, (9, 8, 12))), mean(old), atol=1e-3)
    assert torch.allclose(project_cf(old, (5, 6, 7)), old, atol=1e-12)
    nested = project_cf(old, (9, 11, 13))  # every old corner is a new one: the field fits, nothing changes
    assert torch.allclose(nested, resample_cf(old, (9, 11, 13)), atol=1e-12)
    axes = torch.meshgrid(*(torch.linspace(0, 1, n, dtype=torch.float64) for n in (5, 6, 7)), indexing="ij")
    affine = (0.3 + 2 * axes[0] - axes[1] + 0.5 * axes[2])[None]
    assert torch.allclose(project_cf(affine, (8, 9, 11)), resample_cf(affine, (8, 9, 11)), atol=1e-12)


def test_total_variation_and_its_written_out_gradient_match_autograd_on_the_plain_formula_float64():
    grid = torch.randn(2, 4, 5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2), requires_grad=True)
    plain = sum((grid.diff(dim=a) ** 2).mean() for a in (1, 2, 3)) / 3
    (want,) = torch.autograd.grad(plain, grid)
    value = total_variation(grid)
    (got,) = torch.autograd.grad(value, grid)
    torch.testing.assert_close(value, plain.detach(), rtol=0, atol=1e-14)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-14)
    assert torch.autograd.gradgradcheck(total_variation, (grid,))  # second-order meta-learning differentiates it again


def test_test_time_render_equals_the_training_path(stages, scene):
    """Without gradient the grid interpolates with grid_sample; the render is the gather path's to float rounding."""
    view = view_rays(scene, 0, "cpu")
    centre = (scene.height // 2) * scene.width + scene.width // 2
    cases = [(stages.coarse, view), (stages.final, view), (stages.final, view[centre - 2 : centre + 2])]  # few: gather
    for model, rays in cases:  # the colour grid, and the feature grid + MLP
        with torch.no_grad():
            fast = model(rays, background=WHITE)
        slow = model(rays, background=WHITE)  # with gradient: corner gathers
        assert fast.samples_evaluated == slow.samples_evaluated > 0
        torch.testing.assert_close(fast.rgb, slow.rgb.detach(), rtol=0, atol=1e-5)
        torch.testing.assert_close(fast.depth, slow.depth.detach(), rtol=1e-5, atol=1e-5)


def test_march_phases_spread_evenly_and_symmetrically_over_a_step():
    assert march_phases(1) == (0.5,)
    assert march_phases(2) == (0.25, 0.75)
    assert march_phases(4) == (0.125, 0.375, 0.625, 0.875)
    with pytest.raises(ValueError, match="count 0"):
        march_phases(0)


def test_a_test_render_of_n_marches_is_their_mean_and_nearer_the_jittered_average(stages, scene):
    """``render_phases`` n: a test render is the mean of the n single marches shifted by :func:`march_phases`
    (colour, opacity, depth; samples summed), and closer to the average over many shifts (what training's random
    jitter fits) than the one march at the bins' middles; training renders are not averaged."""
    model = copy.deepcopy(stages.final)
    model.config = dataclasses.replace(model.config, stepsize=1.0)  # one-voxel steps, where the shift shows most
    rays = _test_view(scene)

    def march(phase):
        return model.render_plan(rays, model.sample(rays, train=False, generator=None, phase=phase), background=WHITE)

    with torch.no_grad():
        one = model(rays, background=WHITE)
        assert torch.equal(one.rgb, march(0.5).rgb)
        parts = [march(p) for p in (0.25, 0.75)]
        dense = torch.stack([march(p).rgb for p in march_phases(32)]).mean(0)
        model.config = dataclasses.replace(model.config, render_phases=2)
        two = model(rays, background=WHITE)
    for name in ("rgb", "acc", "depth"):
        torch.testing.assert_close(getattr(two, name), (getattr(parts[0], name) + getattr(parts[1], name)) / 2)
    assert two.samples_evaluated == parts[0].samples_evaluated + parts[1].samples_evaluated
    assert ((two.rgb - dense) ** 2).mean() < 0.5 * ((one.rgb - dense) ** 2).mean()
    train = []
    for count in (2, 1):
        model.config = dataclasses.replace(model.config, render_phases=count)
        train.append(model(rays[:256], background=WHITE, train=True, generator=torch.Generator().manual_seed(0)).rgb)
    assert torch.equal(train[0], train[1])


# -- config ----------------------------------------------------------------------------------


@pytest.mark.parametrize("pixels,side", [(100, 88), (800, 160), (32, 28), (10, 16)])
def test_for_scene_sizes_auto_grids_from_resolution(scene, pixels, side):
    images = torch.zeros(1, pixels, pixels, 3)
    sized = dataclasses.replace(scene, images=images)
    config = VoxelGridConfig().for_scene(sized)
    assert config.num_voxels == side**3
    assert config.coarse_num_voxels == max(16, round(side / 2)) ** 3
    assert VoxelGridConfig(num_voxels=1000, coarse_num_voxels=64).for_scene(sized).num_voxels == 1000


def test_auto_sizes_must_be_resolved_and_bad_values_are_refused():
    with pytest.raises(ConfigError, match="for_scene"):
        VoxelGrid(VoxelGridConfig(), BOX)
    with pytest.raises(ConfigError, match="growth_steps"):
        VoxelGridConfig(growth_steps=(200, 100))
    assert VoxelGridConfig(growth_steps=[10, 20]).growth_steps == (10, 20)  # JSON lists load back
    for bad in (0, 1.5):
        with pytest.raises(ConfigError, match="render_phases"):
            VoxelGridConfig(render_phases=bad)


# -- model -----------------------------------------------------------------------------------


@pytest.mark.parametrize("view_dependent", [True, False])
def test_layers_and_groups_partition_parameters_in_both_stages(view_dependent):
    model = _model(dataclasses.replace(SMALL, view_dependent=view_dependent))
    assert model.stage == "coarse"
    check_partition(model)
    assert [layer.name for layer in model.layers()] == ["density_coarse", "color_coarse"]
    event = model.begin_step(SMALL.coarse_iters, None)
    assert event.params_changed and model.stage == "fine"
    check_partition(model)
    names = [layer.name for layer in model.layers()]
    assert names[:2] == ["density", "features"]
    assert len(names) == (2 + SMALL.mlp_depth if view_dependent else 2)


def _axis_ray(length_box=BOX):
    """One ray along +x through the middle of the box, starting outside it."""
    o = torch.tensor([[-3.0, 0.1, -0.2]])
    d = torch.tensor([[1.0, 0.0, 0.0]])
    return RayBatch(o, d, torch.tensor([0.0]), torch.tensor([10.0]))


@pytest.mark.parametrize("stage", ["coarse", "fine"])
def test_raw_zero_gives_alpha_init_per_step(stage):
    config = dataclasses.replace(SMALL, growth_steps=(), coarse_iters=40 if stage == "coarse" else 0)
    model = _model(config)
    alpha = config.coarse_alpha_init if stage == "coarse" else config.alpha_init
    with torch.no_grad():
        (model.density_coarse if stage == "coarse" else model.density).zero_()
    points = torch.rand(10, 3) * 2 - 1
    torch.testing.assert_close(model.alpha_per_step(points), torch.full((10,), alpha), rtol=1e-5, atol=0)
    # Through rendering: a ray crossing the whole box (length 2, any partial last step) keeps
    # (1 - alpha) per step of ``stepsize * unit``.
    out = _render(model, _axis_ray())
    steps = 2.0 / (config.stepsize * model.unit)
    assert out.acc.item() == pytest.approx(1 - (1 - alpha) ** steps, rel=1e-5)


def test_coarse_to_fine_switch_keeps_the_render(scene, stages):
    model = copy.deepcopy(stages.coarse)
    assert model.stage == "coarse"
    rays = _test_view(scene)
    before = _render(model, rays)
    assert _psnr(before.rgb, rays.target) > 14.0  # the coarse stage learnt something
    event = model.begin_step(SMALL.coarse_iters, None)
    assert model.stage == "fine" and event.params_changed
    after = _render(model, rays)
    assert _psnr(after.rgb, before.rgb) > 30.0, _psnr(after.rgb, before.rgb)


def test_growth_keeps_the_render(scene, stages):
    model = copy.deepcopy(stages.before_growth)
    rays = _test_view(scene)
    before = _render(model, rays)
    size = model.size
    event = model.begin_step(stages.grow_at, None)
    assert event.params_changed and math.prod(model.size) > math.prod(size)
    after = _render(model, rays)
    assert _psnr(after.rgb, before.rgb) > 30.0, _psnr(after.rgb, before.rgb)


def test_a_growth_due_late_in_the_fit_is_skipped_with_the_ones_after_it():
    config = dataclasses.replace(SMALL, coarse_iters=0, growth_steps=(5, 10, 15), growth_cutoff=0.8)
    model = _model(config)
    size = model.size
    assert model.begin_step(5, 0.5).message == f"grid grown to {model.size}" and model.size != size  # 50 % done: grown
    size = model.size
    event = model.begin_step(10, 0.85)
    assert model.size == size and not event.params_changed and "growth skipped" in event.message and "85%" in event.message
    assert not model.begin_step(15, 0.9).message and model.size == size  # later growths stay skipped, said once
    never = _model(dataclasses.replace(config, growth_cutoff=1.0))
    first = never.size
    assert "grid grown" in never.begin_step(5, 0.99).message and "grid grown" in never.begin_step(10, 0.999).message
    assert math.prod(never.size) > math.prod(first)


def test_growth_cutoff_must_be_a_fraction():
    with pytest.raises(Exception, match="growth_cutoff"):
        dataclasses.replace(SMALL, growth_cutoff=0.0)


def test_growth_density_names_one_of_its_two_ways_or_one_per_growth():
    assert SMALL.growth_density == "interp"  # the default: its smoothing pays later in the fit (BENCHMARKS.md)
    for bad in ("cubic", "project,cubic", "project,", ""):
        with pytest.raises(ConfigError, match="growth_density=.*project or interp"):
            dataclasses.replace(SMALL, growth_density=bad)
    assert [growth_mode("project,interp", g) for g in range(4)] == ["project", "interp", "interp", "interp"]
    assert [growth_mode("interp,project,interp", g) for g in range(4)] == ["interp", "project", "interp", "interp"]
    assert [growth_mode("project", g) for g in range(3)] == ["project"] * 3


def test_a_list_of_growth_ways_moves_each_growth_its_own_way(scene):
    config = dataclasses.replace(SMALL, coarse_iters=0, growth_steps=(1, 2), growth_density="project,interp")
    model = _model(config, bounds=scene.bounds)
    with torch.no_grad():
        model.density.normal_(generator=torch.Generator().manual_seed(5))
    for step, move in ((1, project_cf), (2, resample_cf)):
        old = model.density.detach().clone()
        assert model.begin_step(step, None).params_changed
        assert torch.equal(model.density.detach(), move(old, model.size)), step
    assert not torch.equal(project_cf(old, model.size), resample_cf(old, model.size))  # the two ways differ here


def test_a_projected_density_renders_closer_to_the_grid_before_its_growth_than_an_interpolated_one(scene, stages):
    rays = _test_view(scene)
    before = _render(stages.before_growth, rays)
    after = {}
    for how in ("project", "interp"):
        model = copy.deepcopy(stages.before_growth)
        model.config = dataclasses.replace(model.config, growth_density=how)
        model.begin_step(stages.grow_at, None)
        after[how] = _psnr(_render(model, rays).rgb, before.rgb)
        assert torch.equal(model.features, resample_cf(stages.before_growth.features, model.size))  # features: interpolated
    assert after["project"] > after["interp"] + 1.0, after


def _ball_model(skipping=True):
    """A fine-stage model whose density is a dense ball (raw 8) in empty space (raw -30)."""
    config = dataclasses.replace(SMALL, coarse_iters=0, growth_steps=(), empty_space_skipping=skipping)
    model = _model(config)
    pts = grid_points(model.bounds, model.size)
    ball = pts.norm(dim=-1) < 0.5
    with torch.no_grad():
        model.density.copy_(torch.where(ball, 8.0, -30.0)[None])
        model.features.normal_(generator=torch.Generator().manual_seed(3))
        for p in model.mlp.parameters():
            p.normal_(std=0.3, generator=torch.Generator().manual_seed(4))
    return model, ball


def _rays(n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 4.0
    aim = 0.6 * torch.randn(n, 3, generator=g)
    directions = torch.nn.functional.normalize(aim - origins, dim=-1)
    return RayBatch(origins, directions, torch.full((n,), 2.0), torch.full((n,), 6.0))


def test_occupancy_skipping_renders_the_same_with_fewer_samples():
    model, ball = _ball_model()
    rays = _rays()
    full = _render(model, rays)
    model.mask = torch.ones(model.size, dtype=torch.bool)  # a full cache: nothing skipped yet
    model._prune_mask()  # conservative: ball voxels (alpha ~1) dilated by one voxel
    assert model.mask.sum() < 0.3 * model.mask.numel() and bool(model.mask[ball].all())
    skipped = _render(model, rays)
    torch.testing.assert_close(skipped.rgb, full.rgb, rtol=0, atol=1e-5)
    torch.testing.assert_close(skipped.acc, full.acc, rtol=0, atol=1e-5)
    assert skipped.samples_evaluated < 0.5 * full.samples_evaluated
    no_skip, _ = _ball_model(skipping=False)
    no_skip.mask = model.mask.clone()  # ignored when empty_space_skipping is off
    other = _render(no_skip, rays)
    assert other.samples_evaluated == full.samples_evaluated
    torch.testing.assert_close(other.rgb, full.rgb, rtol=0, atol=1e-6)


@pytest.mark.parametrize("stage", ["coarse", "final"])  # coarse stage; fine stage after a growth step
def test_structure_round_trip_restores_identical_renders(scene, stages, stage):
    model = getattr(stages, stage)
    structure, state = model.structure(), model.state_dict()
    # Rebuilt elsewhere (placeholder bounds, as saved initialisations are), then reshaped.
    other = _model(bounds=BOX * 3, seed=1)
    other.load_structure(structure)
    other.load_state_dict(state)
    assert other.structure() == structure
    rays = _test_view(scene)
    a, b = _render(model, rays), _render(other, rays)
    assert torch.equal(a.rgb, b.rgb) and a.samples_evaluated == b.samples_evaluated


@pytest.mark.parametrize("overrides", [None, {"view_dependent": False}, {"empty_space_skipping": False}])
def test_short_fit_raises_psnr(scene, stages, overrides):
    if overrides is None:  # the defaults: the fixture's model
        start, model = stages.untrained, stages.final
    else:
        model = _model(dataclasses.replace(SMALL, **overrides), bounds=scene.bounds)
        start = copy.deepcopy(model)
        _fit(model, scene, 100)
    rays = _test_view(scene)
    before = _psnr(_render(start, rays).rgb, rays.target)
    after = _psnr(_render(model, rays).rgb, rays.target)
    assert model.stage == "fine" and model.level == 1
    assert after > before + 8.0, (before, after)


def test_state_saved_channels_last_still_loads(stages):
    """Grids saved as flat (X*Y*Z, C) rows, as before they were stored channels-first, load the same."""
    model = stages.final
    state = {k: v.clone() for k, v in model.state_dict().items()}
    state["features"] = state["features"].reshape(state["features"].shape[0], -1).t().contiguous()
    other = copy.deepcopy(model)
    with torch.no_grad():
        other.features.zero_()
    other.load_state_dict(state)
    assert torch.equal(other.features, model.features)


def test_growth_keeps_frozen_grids_frozen(stages):
    model = copy.deepcopy(stages.before_growth)
    model.freeze_first(1)
    model.begin_step(stages.grow_at, None)
    assert not model.density.requires_grad and model.features.requires_grad


def test_distortion_term_only_when_weighted_and_it_reaches_the_density(scene):
    rays = view_rays(scene, 0, "cpu")[:256]
    for weight in (0.0, 0.5):
        model = _model(dataclasses.replace(SMALL, distortion_weight=weight), bounds=scene.bounds)
        with torch.no_grad():
            model.density_coarse.add_(torch.rand(model.density_coarse.shape, generator=torch.Generator().manual_seed(0)) * 4)
        out = model(rays, background=WHITE, train=True, generator=torch.Generator().manual_seed(1), target=rays.target)
        assert ("distortion" in out.losses) == (weight > 0)
        if weight:
            term = out.losses["distortion"]
            assert torch.isfinite(term) and term > 0
            (grad,) = torch.autograd.grad(term, model.density_coarse)
            assert grad.abs().sum() > 0
        with torch.no_grad():
            assert "distortion" not in model(rays, background=WHITE).extras  # test renders skip it


def test_feature_tv_is_its_weight_times_the_feature_grids_total_variation():
    """A feature grid that rises by 1 per voxel along x has total variation exactly 1/3 (x differences 1, y and
    z differences 0): ``tv_features`` is its weight over 3; with the weight 0 there is no such term."""
    config = VoxelGridConfig(coarse_iters=0, num_voxels=6**3, growth_steps=(), tv_features_weight=0.3)
    model = _model(config)
    with torch.no_grad():
        model.features.copy_(torch.arange(model.size[0], dtype=torch.float32).view(1, -1, 1, 1).expand_as(model.features))
    rays = RayBatch(torch.tensor([[0.0, 0.0, -2.0]]), torch.tensor([[0.0, 0.0, 1.0]]), torch.zeros(1), torch.full((1,), 4.0))
    out = model.render(rays, background=WHITE)
    terms = model.loss_terms(out, torch.zeros(1, 3))
    assert set(terms) == {"mse", "tv_features"} and terms["tv_features"].item() == pytest.approx(0.1, rel=1e-6)
    assert set(_model(dataclasses.replace(config, tv_features_weight=0.0)).loss_terms(out, torch.zeros(1, 3))) == {"mse"}
    terms["tv_features"].backward()
    assert model.features.grad is not None and float(model.features.grad.abs().sum()) > 0


def test_voxels_per_pixel_sets_the_auto_grid(scene):
    sized = dataclasses.replace(scene, images=torch.zeros(1, 100, 160, 3))
    assert VoxelGridConfig(voxels_per_pixel=0.25).for_scene(sized).num_voxels == 40**3
    assert VoxelGridConfig(voxels_per_pixel=0.05).for_scene(sized).num_voxels == 16**3  # the clamp still holds
    with pytest.raises(ConfigError, match="voxels_per_pixel"):
        VoxelGridConfig(voxels_per_pixel=0.0)


def test_max_side_caps_the_auto_grid_whatever_the_images_size(scene):
    large = dataclasses.replace(scene, images=torch.zeros(1, 378, 504, 3))
    assert VoxelGridConfig(voxels_per_pixel=0.25).for_scene(large).num_voxels == 126**3
    assert VoxelGridConfig(voxels_per_pixel=0.25, max_side=64).for_scene(large).num_voxels == 64**3
    assert VoxelGridConfig(max_side=64).for_scene(dataclasses.replace(scene, images=torch.zeros(1, 40, 40, 3))).num_voxels == 35**3
    assert VoxelGridConfig(max_side=64, num_voxels=1000).for_scene(large).num_voxels == 1000  # an explicit count wins
    with pytest.raises(ConfigError, match="max_side"):
        VoxelGridConfig(max_side=8)
