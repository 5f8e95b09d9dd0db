"""The maths of meta-learning (pretrain/meta.py): inner steps, meta-gradients, Reptile, engines, tasks."""

from __future__ import annotations

import copy
import math

import pytest
import torch
import torch.nn.functional as F

from nerfmeta.data.scene import RayBatch
from nerfmeta.errors import ConfigError
from nerfmeta.fields.nerf_mlp import NerfMLP, NerfMLPConfig
from pretrain.meta import (
    CANONICAL_BOUNDS,
    MetaConfig,
    Task,
    derive_seed,
    fast_adapt,
    inner_lrs,
    learn2learn_available,
    maml_meta_grad,
    meta_wrapper,
    task_loss,
    reptile_update,
    task_direction,
)

TINY_NERF = NerfMLPConfig(pos_freqs=2, dir_freqs=1, depth=2, width=16, skips=(), n_samples=8)
BG = torch.ones(3)


def tiny_model(dtype: torch.dtype = torch.float32, seed: int = 0) -> NerfMLP:
    gen = torch.Generator().manual_seed(seed)
    model = NerfMLP(TINY_NERF, torch.tensor(CANONICAL_BOUNDS), generator=gen)
    return model.to(dtype)


def rays(n: int, seed: int, dtype: torch.dtype = torch.float32) -> RayBatch:
    """Rays from a sphere of radius 3 through points near the origin, with random target colours."""
    gen = torch.Generator().manual_seed(seed)
    origins = F.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1) * 3.0
    aim = 0.5 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    dirs = F.normalize(aim - origins, dim=-1)
    target = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    batch = RayBatch(origins, dirs, torch.full((n,), 1.0, dtype=torch.float64), torch.full((n,), 5.0, dtype=torch.float64), target)
    return RayBatch(*(t.to(dtype) for t in (batch.origins, batch.directions, batch.near, batch.far, batch.target)))


def task(seed: int = 1, dtype: torch.dtype = torch.float32, n: int = 32) -> Task:
    return Task(f"t{seed}", rays(n, 10 * seed, dtype), rays(n, 10 * seed + 1, dtype), seed)


def flat(tensors) -> torch.Tensor:
    return torch.cat([t.reshape(-1) for t in tensors])


def hand_sgd(model: NerfMLP, t: Task, steps: int, lr: float) -> tuple[NerfMLP, torch.Generator]:
    """A copy of ``model`` after ``steps`` SGD steps written out by hand (loss.backward, p -= lr * grad),
    and the jitter generator in the state fast_adapt's query render finds it."""
    model = copy.deepcopy(model)
    gen = torch.Generator().manual_seed(t.seed)
    for _ in range(steps):
        model.zero_grad()
        out = model(t.support, background=BG.to(t.support.target.dtype), train=True, generator=gen)
        torch.mean((out.rgb - t.support.target) ** 2).backward()
        with torch.no_grad():
            for p in model.parameters():
                p -= lr * p.grad
    return model, gen


# --- learners and the inner loop ------------------------------------------------------------------


@pytest.mark.parametrize("engine", ["torchfunc", "l2l"])
def test_clone_renders_like_the_original(engine):
    if engine == "l2l" and not learn2learn_available()[0]:
        pytest.skip(learn2learn_available()[1])
    model, t = tiny_model(), task()
    learner = meta_wrapper(model, engine, 1.0, first_order=False).clone()
    a = learner(t.query, background=BG, train=False, generator=None).rgb
    b = model(t.query, background=BG, train=False).rgb
    assert torch.equal(a, b)


@pytest.mark.parametrize("engine", ["torchfunc", "l2l"])
def test_one_inner_step_equals_a_hand_written_sgd_step(engine):
    if engine == "l2l" and not learn2learn_available()[0]:
        pytest.skip(learn2learn_available()[1])
    model, t, lr = tiny_model(), task(), 3.0
    learner = meta_wrapper(model, engine, lr, first_order=False).clone()
    fast_adapt(t, learner, 1, background=BG)
    expected = dict(hand_sgd(model, t, 1, lr)[0].named_parameters())
    for (name, _), adapted in zip(model.named_parameters(), learner.parameters()):
        torch.testing.assert_close(adapted, expected[name], rtol=1e-6, atol=1e-7, msg=name)
    # the original is untouched
    assert all(torch.equal(p, q) for p, q in zip(model.parameters(), tiny_model().parameters()))


def test_loss_drops_after_inner_steps():
    model, t = tiny_model(), task()
    learner = meta_wrapper(model, "torchfunc", 5.0, first_order=True).clone()
    adaptation = fast_adapt(t, learner, 4, background=BG, jitter=False)
    after = float(task_loss(learner, t.support, BG, None, jitter=False).detach())
    assert after < adaptation.support_mse[0]
    assert all(b < a for a, b in zip(adaptation.support_mse, adaptation.support_mse[1:]))


def test_per_group_inner_rates_follow_the_param_groups():
    model = tiny_model()
    lrs = inner_lrs(model, 2.0, {"mlp": 7.0})
    assert set(lrs) == {n for n, _ in model.named_parameters()} and set(lrs.values()) == {7.0}
    with pytest.raises(ConfigError, match="groups are mlp"):
        inner_lrs(model, 2.0, {"density": 1.0})


# --- meta-gradients -------------------------------------------------------------------------------


def test_maml_outer_gradient_reaches_the_initial_parameters_and_matches_finite_differences():
    """d L_q(theta - lr * grad L_s(theta)) / d theta against a central difference, in float64."""
    model, t, lr, steps = tiny_model(torch.float64), task(dtype=torch.float64), 2.0, 2
    bg = BG.double()
    params = list(model.parameters())
    meta = meta_wrapper(model, "torchfunc", lr, first_order=False)
    grads, _ = maml_meta_grad(meta, params, t, steps, background=bg)
    for (name, _), g in zip(model.named_parameters(), grads):
        assert g.abs().sum() > 0, f"no meta-gradient reaches {name}"

    def outer_loss(shift: float, direction: list[torch.Tensor]) -> float:
        with torch.no_grad():
            for p, d in zip(params, direction):
                p.add_(shift * d)
        try:
            learner = meta_wrapper(model, "torchfunc", lr, first_order=True).clone()
            return float(fast_adapt(t, learner, steps, background=bg).query_mse.detach())
        finally:
            with torch.no_grad():
                for p, d in zip(params, direction):
                    p.sub_(shift * d)

    gen = torch.Generator().manual_seed(3)
    direction = [torch.randn(p.shape, generator=gen, dtype=p.dtype) for p in params]
    eps = 1e-6  # small enough not to cross a ReLU kink (1e-5 does for this seed)
    numeric = (outer_loss(eps, direction) - outer_loss(-eps, direction)) / (2 * eps)
    analytic = float(sum((g * d).sum() for g, d in zip(grads, direction)))
    assert analytic == pytest.approx(numeric, rel=1e-5)


def test_fomaml_gradient_is_the_query_gradient_at_the_adapted_parameters():
    model, t, lr, steps = tiny_model(torch.float64), task(dtype=torch.float64), 2.0, 2
    bg = BG.double()
    params = list(model.parameters())
    fo, _ = maml_meta_grad(meta_wrapper(model, "torchfunc", lr, first_order=True), params, t, steps, background=bg)
    so, _ = maml_meta_grad(meta_wrapper(model, "torchfunc", lr, first_order=False), params, t, steps, background=bg)
    adapted, gen = hand_sgd(model, t, steps, lr)
    out = adapted(t.query, background=bg, train=True, generator=gen)
    expected = torch.autograd.grad(torch.mean((out.rgb - t.query.target) ** 2), list(adapted.parameters()))
    for a, b in zip(fo, expected):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert (flat(fo) - flat(so)).norm() > 1e-6 * flat(so).norm(), "second-order terms are missing from MAML"


def test_reptile_update_is_the_mean_of_adapted_minus_initial_times_its_step():
    model, steps, lr, eps = tiny_model(), 3, 4.0, 0.5
    tasks = [task(1), task(2)]
    params = list(model.parameters())
    initial = [p.detach().clone() for p in params]
    meta = meta_wrapper(model, "torchfunc", lr, first_order=True)
    directions = [task_direction("reptile", meta, params, t, steps, background=BG)[0] for t in tasks]
    mean = [sum(ds) / len(ds) for ds in zip(*directions)]
    reptile_update(params, mean, eps)
    adapted = [list(hand_sgd(tiny_model(), t, steps, lr)[0].parameters()) for t in tasks]
    for k, p in enumerate(params):
        expected = initial[k] + eps * sum(a[k].detach() - initial[k] for a in adapted) / len(tasks)
        torch.testing.assert_close(p.detach(), expected, rtol=1e-5, atol=1e-6)


def test_a_reptile_meta_step_moves_by_the_mean_task_step(tiny_scene):
    """The whole outer step of the loop (flatten, reduce, divide by the meta-batch, update)."""
    from nerfmeta.data import load_scene
    from nerfmeta.fit.sampler import RaySampler
    from pretrain.meta_run import meta_step
    from pretrain.meta_tasks import TaskSampler, TaskScene

    scene = load_scene(tiny_scene)
    record = type("R", (), {"name": "spheres"})()
    sampler = TaskSampler([TaskScene(record, RaySampler(scene, "train", "cpu"))] * 2, 0, 24, 8)
    config = MetaConfig(algo="reptile", meta_batch=3, inner_steps=2, inner_lr=4.0, meta_lr=0.3)
    model = tiny_model()
    initial = [p.detach().clone() for p in model.parameters()]
    lrs = inner_lrs(model, 4.0)
    meta_step(model, None, sampler, 5, config, lrs, BG)
    adapted = [list(hand_sgd(tiny_model(), t, 2, 4.0)[0].parameters()) for t in sampler.tasks(5, 3)]
    for k, p in enumerate(model.parameters()):
        expected = initial[k] + 0.3 * sum(a[k].detach() - initial[k] for a in adapted) / 3
        torch.testing.assert_close(p.detach(), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("algo", ["maml", "fomaml"])
def test_learn2learn_and_torchfunc_give_the_same_meta_gradient(algo):
    ok, why = learn2learn_available()
    if not ok:
        pytest.skip(f"learn2learn cross-check skipped: {why}")
    model, t, lr, steps = tiny_model(), task(n=48), 3.0, 3
    params = list(model.parameters())
    first_order = algo == "fomaml"
    ours, a1 = maml_meta_grad(meta_wrapper(model, "torchfunc", lr, first_order), params, t, steps, background=BG)
    theirs, a2 = maml_meta_grad(meta_wrapper(model, "l2l", lr, first_order), params, t, steps, background=BG)
    rel = float((flat(ours) - flat(theirs)).norm() / flat(theirs).norm())
    print(f"learn2learn vs torchfunc {algo} meta-gradient relative error: {rel:.3e}")
    assert rel <= 1e-5
    assert float(a1.query_mse.detach()) == pytest.approx(float(a2.query_mse.detach()), rel=1e-6)


def test_learn2learn_with_per_group_rates_matches_torchfunc():
    """The grid's per-group inner rates go through learn2learn's maml_update with scaled gradients."""
    ok, why = learn2learn_available()
    if not ok:
        pytest.skip(f"learn2learn cross-check skipped: {why}")
    from nerfmeta.fields.registry import build_model

    config = MetaConfig(backbone="grid", model={"num_voxels": 6**3, "feature_dim": 2, "mlp_width": 8})
    model = build_model("grid", config.model_config(), torch.tensor(CANONICAL_BOUNDS), seed=0)
    lrs = inner_lrs(model, 1.0, {"density": 300.0, "features": 100.0})
    params, t = list(model.parameters()), task(n=48)
    ours, _ = maml_meta_grad(meta_wrapper(model, "torchfunc", lrs, True), params, t, 2, background=BG)
    theirs, _ = maml_meta_grad(meta_wrapper(model, "l2l", lrs, True), params, t, 2, background=BG)
    rel = float((flat(ours) - flat(theirs)).norm() / flat(theirs).norm())
    assert rel <= 1e-5, rel


# --- what each backbone supports ----------------------------------------------------------------------


def test_grid_refuses_maml_with_the_reason():
    with pytest.raises(ConfigError, match="second-order"):
        MetaConfig(backbone="grid", algo="maml").validate()
    for algo in ("fomaml", "reptile"):
        MetaConfig(backbone="grid", algo=algo).validate()
    for algo in ("maml", "fomaml", "reptile"):
        MetaConfig(backbone="nerf", algo=algo).validate()


def test_the_grid_feature_lookup_has_no_double_backward():
    """The reason above: if PyTorch ever adds it, this fails and grid MAML can be reconsidered."""
    grid = torch.randn(27, 4, requires_grad=True)
    idx, w = torch.randint(27, (5, 8)), torch.rand(5, 8)
    out = F.embedding_bag(idx, grid, per_sample_weights=w, mode="sum")
    (g,) = torch.autograd.grad(torch.sigmoid(out).square().sum(), grid, create_graph=True)
    with pytest.raises((NotImplementedError, RuntimeError), match="not implemented"):
        torch.autograd.grad(g.square().sum(), grid)


def test_grid_is_meta_learned_in_a_fixed_fine_stage():
    config = MetaConfig(backbone="grid").model_config()
    assert (config.coarse_iters, config.growth_steps, config.empty_space_skipping) == (0, (), False)
    with pytest.raises(ConfigError, match="fixed fine stage"):
        MetaConfig(backbone="grid", model={"coarse_iters": 100}).validate()


@pytest.mark.parametrize("change", [{"inner_steps": 0}, {"meta_batch": 0}, {"inner_lr": -1.0}, {"meta_lr": math.nan},
                                    {"algo": "sgd"}, {"engine": "jax"}, {"backbone": "mesh"}, {"support_rays": 0}])
def test_bad_settings_are_one_line_config_errors(change):
    with pytest.raises(ConfigError) as err:
        MetaConfig(**change).validate()
    assert "\n" not in str(err.value)


# --- tasks ---------------------------------------------------------------------------------------------


def test_derive_seed_gives_independent_streams():
    seeds = {derive_seed(0, 1, step, slot) for step in range(20) for slot in range(8)}
    assert len(seeds) == 160 and all(0 <= s < 2**63 for s in seeds)
    assert derive_seed(0, 1, 2, 3) == derive_seed(0, 1, 2, 3) != derive_seed(1, 1, 2, 3)


def test_processes_take_interleaved_slots_of_the_same_meta_batch(tiny_scene):
    from nerfmeta.data import load_scene
    from nerfmeta.fit.sampler import RaySampler
    from pretrain.meta_tasks import TaskSampler, TaskScene

    scene = load_scene(tiny_scene)
    record = type("R", (), {"name": "spheres"})()
    sampler = TaskSampler([TaskScene(record, RaySampler(scene, "train", "cpu"))] * 3, 7, 16, 8)
    whole = sampler.tasks(5, 5)
    parts = [sampler.tasks(5, 5, rank, 2) for rank in range(2)]
    interleaved = [parts[slot % 2][slot // 2] for slot in range(5)]
    for a, b in zip(whole, interleaved):
        assert a.seed == b.seed and torch.equal(a.support.origins, b.support.origins) and torch.equal(a.query.target, b.query.target)
    assert sorted(sampler.scene_indices(5, 3)) == [0, 1, 2]  # distinct scenes while the batch fits
    assert whole[0].seed != sampler.tasks(6, 5)[0].seed


# --- what a backbone declares, not what it is called -------------------------------------------


def test_meta_learning_reads_a_backbones_declared_hints_not_its_name(monkeypatch):
    from nerfmeta.fields import registry
    from nerfmeta.fields.base import MetaHints
    from nerfmeta.fields.dense_grid import DenseGrid, DenseGridConfig

    class Toy(DenseGrid):
        backbone = "toy"
        meta_hints = MetaHints(algos=("reptile",), why_not="toy: reptile only", fixed={"side": 8},
                               fixed_reason="the toy keeps 8 corners", inner_lr=3.0, inner_group_lr={"grid": 7.0})

    monkeypatch.setitem(registry.BACKBONES, "toy", (DenseGridConfig, Toy, DenseGridConfig()))
    with pytest.raises(ConfigError, match="toy: reptile only"):
        MetaConfig(backbone="toy", algo="fomaml").validate()
    config = MetaConfig(backbone="toy", algo="reptile", support_rays=1024)
    config.validate()
    assert config.model_config().side == 8
    assert config.inner_lr_resolved == (3.0, {"grid": 14.0})  # group rates scale with the support batch
    with pytest.raises(ConfigError, match="the toy keeps 8 corners"):
        MetaConfig(backbone="toy", algo="reptile", model={"side": 9}).validate()


def test_the_inner_loss_is_the_sum_of_the_models_terms():
    """The grid's TV term is part of the inner loss, as in the fit loop, and follows the learner's parameters."""
    from nerfmeta.fields.grid_ops import total_variation
    from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig

    model = VoxelGrid(VoxelGridConfig(coarse_iters=0, num_voxels=6**3, growth_steps=(), tv_weight=0.5,
                                      view_dependent=False), torch.tensor(CANONICAL_BOUNDS))
    with torch.no_grad():
        model.density.normal_(generator=torch.Generator().manual_seed(0))
    t = task(3)
    out = model(t.support, background=BG, train=False)
    expected = torch.mean((out.rgb - t.support.target) ** 2) + 0.5 * total_variation(model.density)
    torch.testing.assert_close(task_loss(model, t.support, BG, None, jitter=False), expected)
    learner = meta_wrapper(model, "torchfunc", 1.0, first_order=True).clone()
    learner.params = {**learner.params, "density": learner.params["density"] * 2}
    out2 = learner(t.support, background=BG, train=False)
    expected2 = torch.mean((out2.rgb - t.support.target) ** 2) + 0.5 * total_variation(model.density * 2)
    torch.testing.assert_close(task_loss(learner, t.support, BG, None, jitter=False), expected2)
