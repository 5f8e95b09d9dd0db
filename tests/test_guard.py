"""The divergence guard (nerfmeta/fit/guard.py) in the fit loop and the meta-training loop.

NaN and explosions are injected by wrapping a backbone's ``render`` (or the meta-batch outcome), so
every case is exact: the step that fails, the snapshot it rolls back to, the rate it leaves.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from nerfmeta.data import load_scene
from nerfmeta.errors import ConfigError, NerfmetaError
from nerfmeta.fields.registry import build_model, config_from_dict, default_config
from nerfmeta.fields.voxel_grid import VoxelGrid
from nerfmeta.fit.guard import (
    DivergenceGuard,
    GuardConfig,
    GuardEvent,
    grads_finite,
    loss_verdict,
    restore_snapshot,
    take_snapshot,
)
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.run import RunConfig, read_metrics, run_fit

SMALL_GRID = {"coarse_iters": 0, "growth_steps": [], "num_voxels": 4096, "occupancy_every": 0}
WHITE = torch.ones(3)


# ----- the rule --------------------------------------------------------------------------------------


def test_loss_verdict_names_nan_inf_and_explosions_against_the_median():
    recent = [0.125, 0.25, 0.0625, 4.0, 0.125]  # median 0.125; one outlier does not move it
    assert loss_verdict(float("nan"), recent, 10.0, 5) == "nan loss"
    assert loss_verdict(float("inf"), recent, 10.0, 5) == "inf loss"
    assert loss_verdict(1.25, recent, 10.0, 5) is None  # exactly 10 x the median is still good
    assert loss_verdict(1.26, recent, 10.0, 5) == "loss exploded: 1.26 > 10 x median 0.125"
    assert loss_verdict(1.26, recent[:4], 10.0, 5) is None  # window not full yet
    assert loss_verdict(1.26, recent, 0.0, 5) is None  # explosions off
    assert loss_verdict(0.03, [9.0, 9.0, 0.001, 0.002, 0.003], 10.0, 3) == "loss exploded: 0.03 > 10 x median 0.002"
    assert loss_verdict(1e-6, [0.0] * 5, 10.0, 5) == "loss exploded: 1e-06 > 10 x median 0"
    assert loss_verdict(1e-6, [0.0] * 5, 10.0, 5, min_loss=1e-4) is None  # a near-perfect picture has not diverged


def test_grads_finite_is_false_for_any_nan_or_inf_value():
    a, b = torch.zeros(3, requires_grad=True), torch.zeros(2, 2, requires_grad=True)
    assert grads_finite([a, b])  # no gradients at all
    a.grad, b.grad = torch.tensor([1.0, -2.0, 3.0]), torch.ones(2, 2)
    assert grads_finite([a, b])
    b.grad[1, 0] = float("nan")
    assert not grads_finite([a, b])
    b.grad[1, 0] = -float("inf")
    assert not grads_finite([a, b])
    b.grad = None
    assert grads_finite([a, b])


@pytest.mark.parametrize("change", [{"window": 0}, {"lr_factor": 1.0}, {"explode_factor": 0.5}, {"max_retries": 0},
                                    {"snapshot_every": 0}, {"grad_check_max_values": -1},
                                    {"explode_min_loss": -1.0}])
def test_bad_guard_settings_are_one_line_config_errors(change):
    with pytest.raises(ConfigError, match=f"guard config {next(iter(change))}="):
        GuardConfig(**change)


def test_fit_config_reads_the_guard_back_from_json():
    config = FitConfig(guard=GuardConfig(window=7, enabled=False))
    again = FitConfig(**json.loads(json.dumps(dataclasses.asdict(config))))
    assert again == config and isinstance(again.guard, GuardConfig)
    with pytest.raises(ConfigError, match="unknown keys"):
        FitConfig(guard={"windw": 3})


# ----- snapshots ------------------------------------------------------------------------------------


def _adam_steps(model: torch.nn.Module, opt: torch.optim.Optimizer, n: int, seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    for _ in range(n):
        opt.zero_grad()
        model(torch.randn(4, 3, generator=gen)).square().mean().backward()
        opt.step()


def test_snapshot_restores_parameters_buffers_and_adam_moments_exactly():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4), torch.nn.Linear(4, 2))
    opt = torch.optim.Adam(model.parameters(), lr=0.1, fused=True)
    _adam_steps(model, opt, 3, seed=1)
    snap = take_snapshot(3, model, opt)
    params = {n: p.detach().clone() for n, p in model.named_parameters()}
    buffers = {n: b.clone() for n, b in model.named_buffers()}
    moments = {n: {k: v.clone() for k, v in opt.state[p].items()} for n, p in model.named_parameters()}
    ids = [id(p) for p in model.parameters()]
    for _ in range(2):  # restoring leaves the snapshot intact: a second rollback gives the same state
        _adam_steps(model, opt, 2, seed=2)
        assert not torch.equal(model[0].weight, params["0.weight"])
        restore_snapshot(snap, model, opt)
        assert [id(p) for p in model.parameters()] == ids  # the optimiser keeps its references
        for n, p in model.named_parameters():
            assert torch.equal(p, params[n]), n
            assert p.grad is None
            assert opt.state[p].keys() == moments[n].keys()
            for k, v in moments[n].items():
                assert torch.equal(opt.state[p][k], v), (n, k)
        for n, b in model.named_buffers():
            assert torch.equal(b, buffers[n]), n
    # state taken before any step: restoring forgets the moments made since
    fresh = torch.nn.Linear(2, 2)
    opt2 = torch.optim.Adam(fresh.parameters(), lr=0.1)
    snap2 = take_snapshot(0, fresh, opt2)
    _adam_steps(torch.nn.Sequential(torch.nn.Linear(3, 2), fresh), opt2, 1, seed=3)
    restore_snapshot(snap2, fresh, opt2)
    assert all(p not in opt2.state for p in fresh.parameters())


def test_a_snapshot_of_other_shapes_is_refused():
    model = torch.nn.Linear(3, 2)
    snap = take_snapshot(0, model, None)
    model.weight = torch.nn.Parameter(torch.zeros(4, 3))
    with pytest.raises(RuntimeError, match="retake it after shape changes"):
        restore_snapshot(snap, model, None)


def test_the_guard_gives_up_after_max_retries_without_a_refresh():
    model = torch.nn.Linear(2, 1)
    guard = DivergenceGuard(GuardConfig(max_retries=2, snapshot_every=3), what="fit")
    guard.retake(10, model, None)
    for k in (1, 2):
        event = guard.rollback(10 + k, "nan loss", model, None, "lower the rates")
        assert event == GuardEvent(10 + k, "nan loss", 10, 0.5**k)
    for step in (12, 13, 14):  # three good steps refresh the snapshot and reset the count
        guard.accept(0.1, step, model, None)
    assert guard.snapshot.step == 14 and guard.failures == 0
    guard.rollback(16, "inf loss", model, None, "x")
    guard.rollback(16, "inf loss", model, None, "x")
    with pytest.raises(NerfmetaError, match=r"fit step 16: inf loss, after 2 rollbacks to step 14 in a row .*lower"):
        guard.rollback(16, "inf loss", model, None, "lower the rates")
    assert guard.lr_scale == 0.5**4 and len(guard.events) == 4


def test_above_the_size_limit_the_parameters_are_checked_on_refresh_steps_only():
    model = torch.nn.Linear(3, 1)  # 4 values
    params = list(model.parameters())
    for p in params:
        p.grad = torch.full_like(p, float("nan"))
    loss = torch.tensor(0.25)
    assert DivergenceGuard(GuardConfig(grad_check_max_values=4)).check_step(loss, params, 1, "") == (0.25, "non-finite gradient")
    guard = DivergenceGuard(GuardConfig(grad_check_max_values=3, snapshot_every=2))
    guard.retake(0, model, None)
    assert guard.check_step(loss, params, 1, "") == (0.25, None)  # gradients not read, no refresh due
    guard.accept(0.25, 0, model, None)
    with torch.no_grad():
        model.bias.fill_(float("inf"))
    assert guard.check_step(loss, params, 2, "") == (0.25, "non-finite parameters")  # this step would refresh


# ----- the fit loop ---------------------------------------------------------------------------------


def inject(monkeypatch, calls: set[int], mode: str = "nan") -> dict:
    """Make the training renders numbered ``calls`` (1-based, counted from now) of every VoxelGrid bad.

    ``mode``: ``nan`` (NaN colours), ``black`` (all black: an explosion on the white tiny scene) or
    ``nan-grad`` (a finite render whose gradient is NaN).
    Returns a record of the parameters each training render saw, in order.
    """
    original = VoxelGrid.render  # the render the model's losses are computed from
    seen: dict = {"params": []}

    def render(self, rays, **kwargs):
        out = original(self, rays, **kwargs)
        if kwargs.get("train"):
            seen["params"].append({n: p.detach().clone() for n, p in self.named_parameters()})
            if len(seen["params"]) in calls and mode == "nan-grad":
                out.rgb.register_hook(lambda grad: grad * float("nan"))
            elif len(seen["params"]) in calls:
                out.rgb = out.rgb * (float("nan") if mode == "nan" else 0.0)
        return out

    monkeypatch.setattr(VoxelGrid, "render", render)
    return seen


def small_grid(scene):
    config = config_from_dict("grid", {**dataclasses.asdict(default_config("grid")), **SMALL_GRID})
    return build_model("grid", config, scene.bounds, seed=0)


def test_a_nan_step_rolls_back_to_the_snapshot_halves_the_rate_and_is_retried(tiny_scene, monkeypatch):
    scene = load_scene(tiny_scene)
    model = small_grid(scene)
    seen = inject(monkeypatch, {7})  # the first try of step 7 (0-based 6)
    config = FitConfig(iters=10, batch_rays=128, eval_every=0, lr_decay=1.0, guard=GuardConfig(snapshot_every=2))
    result = fit(model, scene, config, background=WHITE)
    # snapshots after 1, 3, 5 steps (every 2 good ones, taken before the update of steps 1, 3, 5)
    assert result.state.guard_events == [GuardEvent(7, "nan loss", 5, 0.5)]
    assert result.state.step == 10 and len(seen["params"]) == 11  # 10 good steps + the bad try
    retry, failed, snapshot = seen["params"][7], seen["params"][6], seen["params"][5]
    for name in retry:
        assert torch.equal(retry[name], snapshot[name]), name
    assert any(not torch.equal(failed[n], snapshot[n]) for n in failed)
    assert [r.lr_scale for r in result.history] == [1.0] * 6 + [0.5] * 4
    assert result.history[6].event == "guard: nan loss, rolled back to iter 5, lr x0.5"
    assert all(r.event is None for i, r in enumerate(result.history) if i != 6)
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())


def test_an_exploding_loss_rolls_back(tiny_scene, monkeypatch):
    scene = load_scene(tiny_scene)
    inject(monkeypatch, {9}, mode="black")
    config = FitConfig(iters=10, batch_rays=128, eval_every=0, lr_decay=1.0, guard=GuardConfig(window=4, snapshot_every=3))
    result = fit(small_grid(scene), scene, config, background=WHITE)
    (event,) = result.state.guard_events
    assert (event.iter, event.rolled_back_to, event.lr_scale) == (9, 5, 0.5)  # snapshots after 2 and 5 steps
    assert event.reason.startswith("loss exploded: ") and " > 10 x median " in event.reason


@pytest.mark.parametrize("max_values,expected", [
    (10**6, GuardEvent(4, "non-finite gradient", 1, 0.5)),  # caught before the update (snapshots after 1 and 3 steps)
    (0, GuardEvent(5, "nan loss", 3, 0.5)),  # applied, then the NaN colour MLP makes the next loss NaN
])
def test_a_nan_gradient_is_caught(tiny_scene, monkeypatch, max_values, expected):
    scene = load_scene(tiny_scene)
    model = small_grid(scene)
    inject(monkeypatch, {4}, mode="nan-grad")
    config = FitConfig(iters=6, batch_rays=128, eval_every=0, guard=GuardConfig(snapshot_every=2, grad_check_max_values=max_values))
    result = fit(model, scene, config, background=WHITE)
    assert result.state.guard_events == [expected]
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())


def test_a_rollback_never_crosses_a_grid_growth(tiny_scene, monkeypatch):
    scene = load_scene(tiny_scene)
    config = config_from_dict("grid", {**dataclasses.asdict(default_config("grid")),
                                       **SMALL_GRID, "num_voxels": 8000, "growth_steps": [4]})
    model = build_model("grid", config, scene.bounds, seed=0)
    inject(monkeypatch, {6})  # two steps after the growth at step 4
    fit_config = FitConfig(iters=8, batch_rays=128, eval_every=0, lr_decay=1.0, guard=GuardConfig(snapshot_every=50))
    result = fit(model, scene, fit_config, background=WHITE)
    (event,) = result.state.guard_events
    assert event.rolled_back_to == 4  # the snapshot retaken right after the growth, not the one of step 0
    assert "grid grown" in (result.history[4].event or "")


def test_with_the_guard_off_a_nan_stops_the_fit_with_a_clear_error(tiny_scene, monkeypatch):
    scene = load_scene(tiny_scene)
    model = small_grid(scene)
    inject(monkeypatch, {3})
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    config = FitConfig(iters=6, batch_rays=128, eval_every=0, guard=GuardConfig(enabled=False))
    with pytest.raises(NerfmetaError, match=r"fit step 3: the loss is nan; .*lower the learning rates.*guard\.enabled=True"):
        fit(model, scene, config, background=WHITE)
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())  # the NaN step was not applied
    assert any(not torch.equal(p, before[n]) for n, p in model.named_parameters())


def test_a_guard_that_cannot_recover_gives_up_with_an_error(tiny_scene, monkeypatch):
    scene = load_scene(tiny_scene)
    inject(monkeypatch, set(range(4, 100)))  # every render from step 4 on
    config = FitConfig(iters=10, batch_rays=128, eval_every=0, guard=GuardConfig(max_retries=3))
    with pytest.raises(NerfmetaError, match=r"fit step 4: nan loss, after 3 rollbacks to step 0 in a row"):
        fit(small_grid(scene), scene, config, background=WHITE)


def _run_config(scene: Path, **guard) -> RunConfig:
    return RunConfig(scene=str(scene), backbone="grid", model=SMALL_GRID, renders=0,
                     fit=FitConfig(iters=12, batch_rays=128, eval_every=0, checkpoint_every=4, lr_decay=1.0,
                                   guard=GuardConfig(snapshot_every=2, **guard)))


class _Kill(Exception):
    pass


def test_run_logs_the_event_keeps_nan_out_of_checkpoints_and_resumes_with_the_lowered_rate(tiny_scene, tmp_path, monkeypatch):
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    inject(monkeypatch, {7})
    summary = run_fit(_run_config(tiny_scene), whole)
    expected = [{"iter": 7, "reason": "nan loss", "rolled_back_to": 5, "lr_scale": 0.5}]
    assert summary["guard_events"] == expected
    assert json.loads((whole / "summary.json").read_text())["guard_events"] == expected
    records = read_metrics(whole / "metrics.jsonl")
    assert [r["iter"] for r in records] == list(range(1, 13))
    assert records[6]["event"] == "guard: nan loss, rolled back to iter 5, lr x0.5"
    assert [r["lr_scale"] for r in records] == [1.0] * 6 + [0.5] * 6
    tensors = load_file(str(whole / "checkpoint.safetensors"))
    assert all(bool(torch.isfinite(v).all()) for v in tensors.values() if v.is_floating_point())

    # the same run killed after step 10 (checkpoint at 8, after the event), then resumed
    inject(monkeypatch, {7})

    def kill_at_10(record, model, state):
        if record.iter == 10:
            raise _Kill

    with pytest.raises(_Kill):
        run_fit(_run_config(tiny_scene), killed, callbacks=[kill_at_10])
    resumed = run_fit(_run_config(tiny_scene), killed, resume=True)
    assert resumed["guard_events"] == expected
    assert [r["lr_scale"] for r in read_metrics(killed / "metrics.jsonl")] == [1.0] * 6 + [0.5] * 6
    a, b = load_file(str(whole / "checkpoint.safetensors")), load_file(str(killed / "checkpoint.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_run_without_guard_raises_and_its_checkpoint_holds_no_nan(tiny_scene, tmp_path, monkeypatch):
    out = tmp_path / "run"
    inject(monkeypatch, {6})
    with pytest.raises(NerfmetaError, match="fit step 6: the loss is nan"):
        run_fit(_run_config(tiny_scene, enabled=False), out)
    tensors = load_file(str(out / "checkpoint.safetensors"))  # the one of step 4
    assert all(bool(torch.isfinite(v).all()) for v in tensors.values() if v.is_floating_point())
    assert not (out / "summary.json").exists()


# ----- meta-training --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def collection(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from nerfmeta.collection.generate import CollectionConfig, generate_collection
    from nerfmeta.collection.render import RenderConfig

    out = tmp_path_factory.mktemp("guard_coll") / "coll"
    generate_collection(CollectionConfig(categories=("mug",), scenes_per_category=3, views=3, test_views=1, resolution=8,
                                         val_fraction=0.0, test_fraction=0.34, render=RenderConfig(supersample=1, max_steps=32)), out)
    return out


def _meta_config(**changes):
    from pretrain.meta import MetaConfig

    base = dict(algo="fomaml", meta_steps=5, checkpoint_every=2, meta_batch=2, support_rays=32, query_rays=32,
                inner_steps=1, eval_tasks=0, model={"depth": 2, "width": 16, "skips": (), "n_samples": 8, "pos_freqs": 2},
                guard=GuardConfig(snapshot_every=2))
    return MetaConfig(**{**base, **changes})


def inject_meta(monkeypatch, calls: set[int]) -> dict:
    """Make the meta-batch outcomes numbered ``calls`` (1-based, from now) NaN; record the parameters each one started from."""
    import pretrain.meta_run as meta_run

    original = meta_run.meta_direction
    seen: dict = {"params": []}

    def meta_direction(model, *args, **kwargs):
        seen["params"].append([p.detach().clone() for p in model.parameters()])
        d = original(model, *args, **kwargs)
        if len(seen["params"]) in calls:
            d.mean[0] = d.mean[0] * float("nan")
            d.finite = False
        return d

    monkeypatch.setattr(meta_run, "meta_direction", meta_direction)
    return seen


def test_meta_training_rolls_back_a_nan_meta_step_and_resumes_with_the_lowered_rate(collection, tmp_path, monkeypatch):
    from pretrain.meta_run import load_meta_checkpoint, meta_train, read_metrics as read_meta

    whole, broken = tmp_path / "whole", tmp_path / "broken"
    seen = inject_meta(monkeypatch, {4})  # the first try of meta-step 4; snapshots after 0 and 1 meta-steps
    summary = meta_train(_meta_config(), collection, whole)
    expected = [{"iter": 4, "reason": "non-finite meta-gradient", "rolled_back_to": 1, "lr_scale": 0.5}]
    assert summary["guard_events"] == expected
    assert json.loads((whole / "summary.json").read_text())["guard_events"] == expected
    assert all(torch.equal(a, b) for a, b in zip(seen["params"][4], seen["params"][1]))  # the retry starts from the snapshot
    records = read_meta(whole / "metrics.jsonl")
    assert [r["step"] for r in records] == [1, 2, 3, 4, 5]
    assert records[3]["event"] == "guard: non-finite meta-gradient, rolled back to iter 1, lr x0.5"
    assert [("event" in r) for r in records] == [False, False, False, True, False]
    ckpt = load_meta_checkpoint(whole / "checkpoint.safetensors")
    assert ckpt.lr_guard_scale == 0.5 and [e.as_json() for e in ckpt.guard_events] == expected
    assert all(bool(torch.isfinite(v).all()) for v in ckpt.model_state.values())

    # killed after meta-step 4 (checkpoint at 4, after the event) and resumed: the same parameters,
    # so the resumed steps used the lowered rate
    inject_meta(monkeypatch, {4})

    def kill_at_5(record) -> None:
        if record.step == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        meta_train(_meta_config(), collection, broken, progress=kill_at_5)
    assert load_meta_checkpoint(broken / "checkpoint.safetensors").step == 4
    assert meta_train(_meta_config(), collection, broken, resume=True)["guard_events"] == expected
    a, b = load_meta_checkpoint(whole / "checkpoint.safetensors"), load_meta_checkpoint(broken / "checkpoint.safetensors")
    assert all(torch.equal(a.model_state[k], b.model_state[k]) for k in a.model_state)


def test_meta_training_without_guard_raises_on_a_nan_meta_step(collection, tmp_path, monkeypatch):
    from pretrain.meta_run import meta_train

    inject_meta(monkeypatch, {2})
    with pytest.raises(NerfmetaError, match=r"meta-step 2: the meta-gradient is not finite; lower --inner-lr or --meta-lr"):
        meta_train(_meta_config(guard=GuardConfig(enabled=False)), collection, tmp_path / "run")


def test_meta_guard_settings_resume_and_load_from_json():
    from pretrain.meta import MetaConfig

    config = _meta_config(guard={"window": 3})
    assert config.guard == GuardConfig(window=3)
    assert MetaConfig.from_json(json.loads(json.dumps(dataclasses.asdict(config)))) == config
    assert math.isclose(MetaConfig().guard.lr_factor, 0.5)
