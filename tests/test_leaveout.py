"""Leaving out what a scene does not need: each decision is made, recorded and switchable (issue #8).

Decisions: the view-dependent colour MLP (``view_dependent="auto"``: a trial that :meth:`VoxelGrid.decide`
ends), the tightened box and the occupancy cache (recorded when the fine stage starts), the fine stage skipped
when the coarse stage meets ``--target-psnr`` (the loop's stage-end evaluation), no autograd graph
through frozen layers, and the optional evaluation work (SSIM, renders).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math

import pytest
import torch
from autograd_graph import count_nodes
from torch.func import functional_call

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.data.scene import RayBatch
from nerfmeta.fields.grid_kernels import fused_available, fused_lookups
from nerfmeta.fields.nerf_mlp import NerfMLP, NerfMLPConfig
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig
from nerfmeta.fit.checkpoint import CHECKPOINT_NAME, load_checkpoint, restore_model
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.run import RunConfig, read_metrics, run_fit
from nerfmeta.init import load_init, save_init

# A coarse stage, a growth step, and the view trial decided at fine step 20.
GRID = {"coarse_iters": 30, "coarse_num_voxels": 16**3, "num_voxels": 24**3, "growth_steps": [10], "view_dependent": "auto",
        "view_probe_step": 20, "view_probe_rays": 2048, "mlp_width": 8, "mlp_depth": 2, "feature_dim": 2,
        "growth_cutoff": 1.0}  # the growth falls at 80 % of these short fits: keep it, as the tests expect
FIT = FitConfig(iters=60, batch_rays=512, eval_every=0, checkpoint_every=0)
PROBE = GRID["coarse_iters"] + GRID["view_probe_step"]
CPU = torch.device("cpu")
WHITE = torch.ones(3)


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def _grid(scene, **overrides) -> VoxelGrid:
    config = dataclasses.replace(VoxelGridConfig(**GRID), **overrides).for_scene(scene)
    torch.manual_seed(0)
    return VoxelGrid(config, scene.bounds)


# ----- view_dependent: auto | true | false -----------------------------------------------------------


def _probe(scene, seed: int = 0):
    from nerfmeta.fit.sampler import RaySampler

    sampler = RaySampler(scene, "train", CPU)
    gen = torch.Generator().manual_seed(seed)
    return lambda n: sampler.sample(n, gen)


def _trial_done(scene, **overrides) -> VoxelGrid:
    """A grid fitted until ``auto`` is due to decide (fine stage, MLP on trial, ``view_probe_step`` steps in)."""
    model = _grid(scene, **overrides)
    fit(model, scene, dataclasses.replace(FIT, iters=PROBE), background=WHITE)
    assert model.stage == "fine"
    return model


@pytest.mark.parametrize("thres_db,expected", [(-100.0, True), (100.0, False)])
def test_auto_measures_and_applies_the_decision(scene, thres_db, expected):
    model = _trial_done(scene, view_gain_db=thres_db)
    # Undecided: the MLP is on trial (feature channels and MLP present) until the decision is due.
    assert model.view_dependent is None and "mlp" in model._modules
    assert model.features.shape[0] == 3 + model.config.feature_dim
    assert model.stage_ending(PROBE - 1) is None and model.stage_ending(PROBE) == "view trial"
    rays = _probe(scene, seed=3)(512)
    with torch.no_grad():
        before = model(rays, background=WHITE).rgb
    (decision,) = model.decide(_probe(scene), background=WHITE)
    ev = decision.evidence
    assert decision.name == "view_dependent" and decision.value is expected and model.view_dependent is expected
    assert ev["rays"] == GRID["view_probe_rays"] and ev["threshold_db"] == thres_db
    # The gain is what the view input buys: the MSEs it compares, in dB.
    assert ev["gain_db"] == pytest.approx(10 * math.log10(ev["mse_view_averaged"] / ev["mse_view"]), abs=1e-3)
    event = model.begin_step(PROBE, None)
    assert event.params_changed is not expected and model.stage_ending(PROBE + 1) is None
    assert ("mlp" in model._modules) is expected
    assert any(layer.name.startswith("mlp.") for layer in model.layers()) is expected
    assert model.features.shape[0] == 3 + (model.config.feature_dim if expected else 0)
    assert model.structure()["view_dependent"] is expected
    with torch.no_grad():
        after = model(rays, background=WHITE).rgb
    if expected:
        assert torch.equal(after, before)
    else:  # the fold keeps the picture up to interpolating the MLP's output instead of its input
        assert (after - before).abs().mean() < 0.01
    assert model.decide(_probe(scene), background=WHITE) == []  # decided once


def test_the_trial_measures_one_march_whatever_the_test_renders_average(scene):
    """``render_phases`` shapes evaluation and videos only: the view trial's two errors are the same with it at 1 or 2."""
    model = _trial_done(scene)
    twin = copy.deepcopy(model)
    twin.config = dataclasses.replace(twin.config, render_phases=2)
    (a,), (b,) = (m.decide(_probe(scene), background=WHITE) for m in (model, twin))
    assert (a.evidence["mse_view"], a.evidence["mse_view_averaged"]) == (b.evidence["mse_view"], b.evidence["mse_view_averaged"])


def test_folding_is_exact_at_the_voxel_corners(scene):
    model = _trial_done(scene)
    with torch.no_grad():
        for p in model.mlp.parameters():  # a non-trivial MLP
            p.normal_(std=0.5, generator=torch.Generator().manual_seed(1))
    dirs = torch.nn.functional.normalize(torch.randn(3, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    feats = model.features.detach().view(model.features.shape[0], -1)
    from nerfmeta.fields.encoding import positional_encoding

    idx = torch.zeros(feats.shape[1], dtype=torch.long)
    expected = torch.stack([torch.sigmoid(feats[:3].t() + model.mlp(feats[3:].t(), positional_encoding(d[None], 4), idx))
                            for d in dirs]).mean(0)
    model._fold_view_branch(dirs)
    assert "mlp" not in model._modules and model.features.shape[0] == 3
    torch.testing.assert_close(torch.sigmoid(model.features.detach().view(3, -1).t()), expected, rtol=0, atol=1e-5)


def test_the_decision_is_recorded_in_a_fit(tiny_scene, tmp_path):
    out = tmp_path / "run"
    summary = run_fit(RunConfig(scene=str(tiny_scene), model=GRID, fit=FIT), out)
    decision = summary["decisions"]["view_dependent"]
    evidence = decision["evidence"]
    assert decision["value"] is (evidence["gain_db"] >= evidence["threshold_db"]), decision
    assert summary["decisions"]["tighten_box"]["value"] is True and summary["decisions"]["empty_space_skipping"]["value"] is True
    events = [r for r in read_metrics(out / "metrics.jsonl") if r.get("event") and "view_dependent" in r["event"]]
    assert [r["iter"] for r in events] == [PROBE + 1]
    ckpt = load_checkpoint(out / CHECKPOINT_NAME)
    assert ckpt.structure["view_dependent"] is decision["value"] and "view_dependent" in ckpt.state.decisions
    # The resolved structure rebuilds (resume, saved inits).
    placeholder = torch.tensor([[-1.0] * 3, [1.0] * 3])  # the real bounds are buffers in the checkpoint
    model = VoxelGrid(VoxelGridConfig(**json.loads((out / "config.json").read_text())["model"]), placeholder)
    restore_model(model, ckpt)
    assert model.view_dependent is decision["value"] and ("mlp" in model._modules) is decision["value"]


@pytest.mark.parametrize("value", [True, False])
def test_a_fixed_view_dependent_is_recorded_not_measured(scene, value):
    model = _grid(scene, view_dependent=value)
    calls = []
    (decision,) = model.decide(lambda n: calls.append(n), background=WHITE)  # at the end of the coarse stage
    assert calls == [] and decision.value is value and "set in the config" in decision.reason
    model.begin_step(model.config.coarse_iters, None)
    assert ("mlp" in model._modules) is value and model.stage_ending(PROBE) is None
    assert model.decide(lambda n: calls.append(n), background=WHITE) == [] and calls == []


def test_view_dependent_config_values_and_json():
    assert VoxelGridConfig().view_dependent == "auto"  # every scene's default since session 43 (BENCHMARKS.md)
    for value in (True, False, "auto"):
        assert VoxelGridConfig(view_dependent=value).view_dependent == value
    with pytest.raises(Exception, match="view_dependent"):
        VoxelGridConfig(view_dependent="sometimes")
    # Without a decide() call (a model driven by hand), "auto" keeps the MLP once the trial is over.
    model = VoxelGrid(VoxelGridConfig(coarse_iters=0, num_voxels=8**3, view_dependent="auto", view_probe_step=5),
                      torch.tensor([[-1.0] * 3, [1.0] * 3]))
    assert model.view_dependent is None and "mlp" in model._modules and model.stage_ending(5) == "view trial"
    assert model.begin_step(5, None).params_changed is False and model.view_dependent is True and "mlp" in model._modules


def test_a_saved_init_keeps_the_resolved_view_dependence(scene, tmp_path):
    model = _trial_done(scene, view_gain_db=100.0)
    model.decide(_probe(scene), background=WHITE)
    model.begin_step(PROBE, None)
    save_init(tmp_path / "init", model, "category", {})
    built = load_init(tmp_path / "init").build()
    assert built.config.view_dependent == "auto" and built.view_dependent is False
    assert [layer.name for layer in built.layers()] == ["density", "features"]


def test_cli_sets_view_dependent_auto_true_false(tiny_scene, tmp_path):
    for value, expected in (("auto", "auto"), ("true", True), ("false", False)):
        out = tmp_path / value
        code = main(["fit", str(tiny_scene), "--out", str(out), "--init", "scratch", "--iters", "2", "--batch-rays", "64",
                     "--eval-every", "0", "--set", f"view_dependent={value}", "--set", "coarse_iters=1",
                     "--set", "growth_steps=[5]", "--no-eval-ssim", "--renders", "0"])
        assert code == 0
        assert json.loads((out / "config.json").read_text())["model"]["view_dependent"] == expected


# ----- box tightening and empty-space skipping --------------------------------------------------------


def _blob_grid(**overrides) -> VoxelGrid:
    """A coarse grid over [-1, 1]^3 whose only content is a dense block around (0.3, 0, 0)."""
    config = VoxelGridConfig(coarse_iters=1, coarse_num_voxels=16**3, num_voxels=24**3, growth_steps=(), **overrides)
    model = VoxelGrid(config, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    from nerfmeta.fields.grid_ops import grid_points

    pts = grid_points(model.bounds, model.size)
    inside = ((pts - torch.tensor([0.3, 0.0, 0.0])).abs() < 0.25).all(-1)
    with torch.no_grad():
        model.density_coarse[0] = torch.where(inside, torch.tensor(10.0), torch.tensor(-10.0))
    return model


def test_box_tightening_and_its_switch():
    tight, loose = _blob_grid(), _blob_grid(tighten_box=False)
    event = tight.begin_step(1, None)
    decisions = {d.name: d for d in event.decisions}
    assert decisions["tighten_box"].value is True
    assert decisions["tighten_box"].evidence["volume_fraction"] < 0.2
    block = torch.tensor([[0.05, -0.25, -0.25], [0.55, 0.25, 0.25]])
    pad = 2 * (2.0 / 15)  # a coarse voxel of padding, then the 1.05 scale, within two voxels
    assert bool((tight.bounds[0] <= block[0]).all() and (tight.bounds[0] >= block[0] - pad).all())
    assert bool((tight.bounds[1] >= block[1]).all() and (tight.bounds[1] <= block[1] + pad).all())
    event = {d.name: d for d in loose.begin_step(1, None).decisions}
    assert event["tighten_box"].value is False and event["tighten_box"].evidence["volume_fraction"] == 1.0
    assert torch.equal(loose.bounds, loose.scene_bounds)
    # Both still skip empty space: the occupancy cache covers the block only.
    assert event["empty_space_skipping"].value is True and event["empty_space_skipping"].evidence["occupied_fraction"] < 0.2


def _rays(n: int = 256, seed: int = 0) -> RayBatch:
    gen = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1) * 3.0
    target = torch.rand(n, 3, generator=gen) * 0.6 - 0.3
    dirs = torch.nn.functional.normalize(target - origins, dim=-1)
    return RayBatch(origins, dirs, torch.full((n,), 1.0), torch.full((n,), 5.0), torch.zeros(n, 3))


def test_empty_space_skipping_switch_and_equal_results():
    on, off = _blob_grid(), _blob_grid(empty_space_skipping=False)
    decisions = {d.name: d for d in off.begin_step(1, None).decisions}
    assert decisions["empty_space_skipping"].value is False and off.mask.numel() == 1
    on.begin_step(1, None)
    assert on.mask.numel() > 1
    rays = _rays()
    with torch.no_grad():
        skipped = on(rays, background=WHITE)
        # The same model rendering every sample: what it skipped had (numerically) no density.
        on.config = dataclasses.replace(on.config, empty_space_skipping=False)
        full = on(rays, background=WHITE)
    assert skipped.samples_evaluated < 0.8 * full.samples_evaluated
    torch.testing.assert_close(skipped.rgb, full.rgb, atol=1e-4, rtol=0)
    torch.testing.assert_close(skipped.depth, full.depth, atol=1e-3, rtol=0)


# ----- the fine stage skipped when the coarse stage meets the target ---------------------------------


@pytest.mark.parametrize("target,stage_end_eval,stops", [(5.0, True, True), (5.0, False, False), (60.0, True, False)])
def test_fine_stage_skipped_when_the_coarse_stage_meets_the_target(scene, target, stage_end_eval, stops):
    model = _grid(scene, view_dependent=True)
    config = dataclasses.replace(FIT, target_psnr=target, stage_end_eval=stage_end_eval)
    result = fit(model, scene, config, background=WHITE)
    coarse_iters = model.config.coarse_iters
    if stops:
        assert result.state.step == coarse_iters and model.stage == "coarse"
        assert result.state.stop_reason.endswith("at the end of the coarse stage")
        assert result.state.decisions["stop_after_coarse"]["value"] is True
    else:
        assert result.state.step == FIT.iters and model.stage == "fine"
    if stage_end_eval:
        decision = result.state.decisions["stop_after_coarse"]
        assert decision["value"] is stops and decision["evidence"]["step"] == coarse_iters
        assert (decision["evidence"]["test_psnr"] >= target) is stops
    else:
        assert "stop_after_coarse" not in result.state.decisions


# ----- frozen layers: no gradient and no graph --------------------------------------------------------

NERF = NerfMLPConfig(pos_freqs=3, dir_freqs=2, depth=4, width=16, skips=(2,), n_samples=8)


def _nerf() -> NerfMLP:
    return NerfMLP(NERF, torch.tensor([[-1.0] * 3, [1.0] * 3]), generator=torch.Generator().manual_seed(0))


def _trunk_outputs(model: NerfMLP, run):
    outputs = []
    hooks = [layer.register_forward_hook(lambda m, i, o: outputs.append(o)) for layer in model.trunk]
    try:
        result = run()
    finally:
        for h in hooks:
            h.remove()
    return result, outputs


@pytest.mark.parametrize("k", [1, 3])
def test_frozen_nerf_layers_build_no_graph_and_get_no_gradient(k):
    rays = _rays(64)
    reference, frozen = _nerf(), _nerf()
    frozen.freeze_first(k)
    ref_out = reference(rays, background=WHITE).rgb
    out, trunk = _trunk_outputs(frozen, lambda: frozen(rays, background=WHITE).rgb)
    assert [t.grad_fn is None for t in trunk] == [i < k for i in range(NERF.depth)]
    torch.testing.assert_close(out, ref_out, rtol=0, atol=0)
    out.sum().backward()
    ref_out.sum().backward()
    params, ref_params = dict(frozen.named_parameters()), dict(reference.named_parameters())
    frozen_names = {n for layer in frozen.layers()[:k] for n in layer.param_names}
    for name, p in params.items():
        if name in frozen_names:
            assert p.grad is None, name
        else:  # the trainable layers get exactly the gradient they get without freezing
            torch.testing.assert_close(p.grad, ref_params[name].grad, rtol=1e-5, atol=1e-7)


def test_functional_call_with_trainable_tensors_still_differentiates_frozen_layers():
    # Meta-learning passes its own tensors: they decide, not the module's requires_grad flags.
    model = _nerf()
    model.freeze_first(2)
    params = {n: p.detach().clone().requires_grad_(True) for n, p in model.named_parameters()}
    out, trunk = _trunk_outputs(model, lambda: functional_call(model, params, (_rays(16),), {"background": WHITE}).rgb)
    assert all(t.grad_fn is not None for t in trunk)
    out.sum().backward()
    assert params["trunk.0.weight"].grad is not None


@pytest.mark.parametrize("fused", [True, False])
def test_frozen_density_grid_builds_no_gather_backward(fused):
    if fused and not fused_available():
        pytest.skip("numba is not installed")
    model = _blob_grid(view_dependent=True)
    model.begin_step(1, None)
    rays = _rays()
    with fused_lookups(fused):  # the lookup nodes: _TrilinearCoordsBackward (fused) or _TrilinearGatherBackward
        assert count_nodes(model(rays, background=WHITE).rgb, "Trilinear") == 2  # density and features
        model.freeze_first(1)
        out = model(rays, background=WHITE).rgb
        assert count_nodes(out, "Trilinear") == 1  # features only: no graph through the density
        out.sum().backward()
    assert model.density.grad is None and model.features.grad is not None


# ----- evaluation work only when asked for ------------------------------------------------------------


def test_ssim_and_renders_switches(tiny_scene, tmp_path):
    small = {**GRID, "coarse_iters": 2, "growth_steps": [2]}
    fit_config = dataclasses.replace(FIT, iters=4, final_ssim=False)
    summary = run_fit(RunConfig(scene=str(tiny_scene), model=small, fit=fit_config, renders=0), tmp_path / "lean")
    assert summary["test_psnr"] is not None and summary["test_ssim"] is None
    assert not list((tmp_path / "lean").glob("renders/*.png"))
    summary = run_fit(RunConfig(scene=str(tiny_scene), model=small, fit=dataclasses.replace(fit_config, final_ssim=True),
                                renders=2), tmp_path / "full")
    assert summary["test_ssim"] is not None and len(list((tmp_path / "full").glob("renders/*.png"))) == 2
