"""The fit loop and `nerfmeta fit`: smoke tests per backbone, resume after a kill, freezing, bad input."""

import json

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.fields.registry import build_model, config_from_dict, default_config
from nerfmeta.fit.loop import FitConfig, fit, fit_progress, lr_scale
from nerfmeta.fit.run import RunConfig, read_metrics, run_fit

# coarse stage, the switch to the fine stage and one growth step all happen within the 90 iterations
GRID_FAST = ["--set", "coarse_iters=30", "--set", "growth_steps=[20]"]
NERF_FAST = ["--set", "depth=2", "--set", "width=32", "--set", "skips=[]", "--set", "n_samples=16",
             "--set", "pos_freqs=4", "--set", "lr=0.01"]


@pytest.mark.parametrize("backbone,extra", [("grid", GRID_FAST), ("nerf", NERF_FAST)])
def test_fit_cli_writes_run_folder_and_psnr_rises(tiny_scene, tmp_path, backbone, extra):
    out = tmp_path / "run"
    code = main(["fit", str(tiny_scene), "--out", str(out), "--backbone", backbone, "--iters", "90",
                 "--batch-rays", "512", "--eval-every", "20", *extra])
    assert code == 0
    for name in ("config.json", "metrics.jsonl", "summary.json", "psnr_vs_iter.png", "psnr_vs_time.png",
                 "checkpoint.safetensors"):
        assert (out / name).is_file(), name
    assert list((out / "renders").glob("test_*.png"))
    records = read_metrics(out / "metrics.jsonl")
    assert [r["iter"] for r in records] == list(range(1, 91))
    assert all({"iter", "time_s", "train_psnr"} <= set(r) for r in records)
    assert all(b["time_s"] >= a["time_s"] for a, b in zip(records, records[1:]))
    tests = [r["test_psnr"] for r in records if "test_psnr" in r]
    assert len(tests) == 5  # iterations 20, 40, 60, 80 and the final 90
    summary = json.loads((out / "summary.json").read_text())
    for key in ("scene", "backbone", "init", "iters", "time_s", "test_psnr", "test_ssim", "samples_per_ray", "peak_rss_mb"):
        assert key in summary, key
    assert summary["backbone"] == backbone and summary["iters"] == 90
    assert summary["test_psnr"] == tests[-1]
    first_train = sum(r["train_psnr"] for r in records[:5]) / 5
    last_train = sum(r["train_psnr"] for r in records[-5:]) / 5
    assert last_train > first_train + 2.0, (first_train, last_train)
    config = json.loads((out / "config.json").read_text())
    assert config["backbone"] == backbone and config["fit"]["iters"] == 90


RESUME_MODELS = {
    "grid": {"coarse_iters": 6, "growth_steps": [4], "num_voxels": 8000, "coarse_num_voxels": 1000, "occupancy_every": 5},
    "nerf": {"estimator": "occupancy", "depth": 2, "width": 16, "skips": [], "n_samples": 16, "occupancy_warmup": 3,
             "occupancy_every": 4, "occupancy_resolution": 12},  # grid refreshes before and after the kill
}


def _grid_run_config(scene, iters, checkpoint_every, backbone="grid"):
    return RunConfig(
        scene=str(scene), backbone=backbone, model=RESUME_MODELS[backbone],
        fit=FitConfig(iters=iters, batch_rays=256, eval_every=0, checkpoint_every=checkpoint_every),
    )


class _Kill(Exception):
    pass


@pytest.mark.parametrize("backbone", sorted(RESUME_MODELS))
def test_resume_after_kill_equals_uninterrupted_run(tiny_scene, tmp_path, backbone):
    # uninterrupted
    full = tmp_path / "full"
    run_fit(_grid_run_config(tiny_scene, 16, 4, backbone), full)
    # killed at iteration 10 (last checkpoint at 8), then resumed
    killed = tmp_path / "killed"

    def kill_at_10(record, model, state):
        if record.iter == 10:
            raise _Kill

    with pytest.raises(_Kill):
        run_fit(_grid_run_config(tiny_scene, 16, 4, backbone), killed, callbacks=[kill_at_10])
    assert not (killed / "summary.json").exists()
    run_fit(_grid_run_config(tiny_scene, 16, 4, backbone), killed, resume=True)
    from safetensors.torch import load_file

    a = load_file(str(full / "checkpoint.safetensors"))
    b = load_file(str(killed / "checkpoint.safetensors"))
    assert sorted(a) == sorted(b)
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)
    ra, rb = read_metrics(full / "metrics.jsonl"), read_metrics(killed / "metrics.jsonl")
    assert [r["iter"] for r in rb] == list(range(1, 17))
    assert [r["train_psnr"] for r in ra] == [r["train_psnr"] for r in rb]


@pytest.mark.parametrize("backbone,overrides,k", [
    ("nerf", {"depth": 3, "width": 32, "skips": [], "n_samples": 16}, 2),
    ("grid", {"coarse_iters": 0, "growth_steps": [], "num_voxels": 4096}, 1),
])
def test_freezing_first_layers_leaves_exactly_them_unchanged(tiny_scene, backbone, overrides, k):
    scene = load_scene(tiny_scene)
    config = config_from_dict(backbone, {**vars_of(default_config(backbone)), **overrides})
    model = build_model(backbone, config, scene.bounds, seed=0)
    frozen = set(model.freeze_first(k))
    expected = {n for layer in model.layers()[:k] for n in layer.param_names}
    assert frozen == expected and frozen
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    fit(model, scene, FitConfig(iters=5, batch_rays=256, eval_every=0), background=torch.ones(3))
    for name, p in model.named_parameters():
        if name in frozen:
            assert torch.equal(p, before[name]), name
            assert p.grad is None, name  # no gradient was computed for it at all
        else:
            assert not torch.equal(p, before[name]), name


def vars_of(config):
    import dataclasses

    return dataclasses.asdict(config)


def test_freeze_beyond_layer_count_is_a_clear_error(tiny_scene, tmp_path, capsys):
    code = main(["fit", str(tiny_scene), "--out", str(tmp_path / "r"), "--backbone", "nerf", "--iters", "1", *NERF_FAST,
                 "--set", "depth=2"])
    assert code == 0
    from nerfmeta.errors import ConfigError

    scene = load_scene(tiny_scene)
    model = build_model("nerf", default_config("nerf"), scene.bounds, seed=0)
    with pytest.raises(ConfigError, match="--freeze 99"):
        model.freeze_first(99)


@pytest.mark.parametrize("args,needle", [
    (["--iters", "0"], "--iters"),
    (["--time-budget", "-1"], "--time-budget"),
    (["--set", "nonsense=1"], "nonsense"),
    (["--set", "novalue"], "novalue"),
    (["--resume"], "nothing to resume"),
    (["--device", "cuda:7"], "cuda"),
])
def test_bad_fit_arguments_exit_2_with_one_line(tiny_scene, tmp_path, capsys, args, needle):
    if needle == "cuda" and torch.cuda.is_available():
        pytest.skip("CUDA present: --device cuda:7 may be valid")
    out = tmp_path / "run"
    code = main(["fit", str(tiny_scene), "--out", str(out), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len([line for line in err if "error" in line]) == 1 and needle in err[-1]
    assert "Traceback" not in "\n".join(err)
    assert not out.exists()


def test_existing_run_folder_is_refused_without_overwrite(tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    code = main(["fit", str(tiny_scene), "--out", str(out), "--iters", "1"])
    assert code == 2 and "--overwrite" in capsys.readouterr().err
    assert (out / "keep.txt").read_text() == "mine"


def test_missing_scene_writes_nothing(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["fit", str(tmp_path / "nope"), "--out", str(out)])
    assert code == 2 and not out.exists()
    assert "nope" in capsys.readouterr().err


@pytest.mark.parametrize("alpha", [1e-6, 1e-4, 1e-2])
def test_a_grid_started_at_any_initial_alpha_learns(tiny_scene, alpha):
    """The density gradients scale with the initial alpha; Adam's epsilon for the density group must not stall them.

    Test PSNR after 120 steps for alpha 1e-6, 1e-4 and 1e-2 (from 10.1, 10.1 and 11.9 dB): with the
    shared epsilon 1e-8 10.2, 24.8 and 27.3 dB (the 1e-6 grid barely moves); with
    the density groups' declared epsilon 1e-15 (``DENSITY_ADAM_EPS``) 19.6, 24.9 and 27.3 dB.
    """
    from nerfmeta.fit.evaluate import evaluate_views

    scene = load_scene(tiny_scene)
    overrides = {"coarse_iters": 0, "growth_steps": [], "num_voxels": 8000, "view_dependent": False, "alpha_init": alpha}
    model = build_model("grid", config_from_dict("grid", {**vars_of(default_config("grid")), **overrides}), scene.bounds, seed=0)
    white = torch.ones(3)
    before = evaluate_views(model, scene, list(scene.splits["test"]), white, with_ssim=False).psnr
    result = fit(model, scene, FitConfig(iters=120, batch_rays=256, eval_every=0, lr_decay=1.0, final_ssim=False),
                 background=white)
    assert result.final.psnr > before + 5.0, (alpha, before, result.final.psnr)


def test_optimizer_takes_the_epsilon_each_group_declares_not_its_name():
    from nerfmeta.fields.base import ParamGroup
    from nerfmeta.fields.dense_grid import DenseGrid, DenseGridConfig
    from nerfmeta.fields.voxel_grid import DENSITY_ADAM_EPS
    from nerfmeta.fit.loop import build_optimizer

    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    config = FitConfig(adam_eps=1e-7)
    grid = build_model("grid", config_from_dict("grid", {**vars_of(default_config("grid")), "num_voxels": 8**3,
                                                         "coarse_num_voxels": 8**3}), box, seed=0)
    eps = {g["name"]: g["eps"] for g in build_optimizer(grid, config).param_groups}
    assert eps == {"density": DENSITY_ADAM_EPS, "features": 1e-7}

    class Named(DenseGrid):  # a group merely *named* density declares nothing
        def param_groups(self):
            return [ParamGroup("density", ("grid",), 0.1)]

    assert [g["eps"] for g in build_optimizer(Named(DenseGridConfig(side=4), box), config).param_groups] == [1e-7]


def test_the_fit_loop_minimises_the_sum_of_the_models_named_terms(tiny_scene):
    """A term the model adds (here a strong pull of the grid to 0) is minimised with the photometric one."""
    from nerfmeta.fields.dense_grid import DenseGrid, DenseGridConfig

    class Pulled(DenseGrid):
        def loss_terms(self, out, target):
            return {**super().loss_terms(out, target), "pull": 10.0 * self.grid.square().mean()}

    scene = load_scene(tiny_scene)
    sizes = {}
    for cls in (DenseGrid, Pulled):
        torch.manual_seed(0)
        model = cls(DenseGridConfig(side=12), scene.bounds)
        fit(model, scene, FitConfig(iters=30, batch_rays=128, eval_every=0, final_ssim=False), background=torch.ones(3))
        sizes[cls.__name__] = float(model.grid.detach().square().mean())
    assert sizes["Pulled"] < 0.5 * sizes["DenseGrid"], sizes


def test_config_of_an_older_run_with_a_retired_key_loads() -> None:
    from nerfmeta.fit.run import RunConfig

    saved = {"scene": "s", "fit": {"iters": 7, "adam_eps_density": 1e-15}}
    assert RunConfig.from_json(saved).fit.iters == 7
    with pytest.raises(TypeError):  # an unknown key that was never ours is still an error
        RunConfig.from_json({"scene": "s", "fit": {"iters": 7, "no_such_key": 1}})


def test_a_run_saved_before_scene_types_resumes_as_a_bounded_object() -> None:
    from nerfmeta.fit.run import RunConfig

    # no scene_type key: fitted in a box, so --resume must not rebuild it in NDC or a contracted space
    assert RunConfig.from_json({"scene": "s"}).scene_type == "object"
    assert RunConfig.from_json({"scene": "s", "scene_type": "auto"}).scene_type == "auto"
    assert RunConfig("s").scene_type == "auto"  # new runs detect


def test_fit_progress_is_the_further_of_iterations_and_time_and_drives_the_lr_decay():
    by_iters = FitConfig(iters=200)
    assert [fit_progress(by_iters, s, 1e9) for s in (0, 50, 200, 400)] == [0.0, 0.25, 1.0, 1.0]  # no budget: time plays no part
    budget = FitConfig(iters=1000, time_budget_s=60.0)
    assert fit_progress(budget, 100, 30.0) == 0.5 and fit_progress(budget, 800, 30.0) == 0.8
    assert lr_scale(budget, 100, 30.0) == pytest.approx(0.1 ** 0.5)


def test_the_loop_tells_the_model_its_progress_before_each_step(tiny_scene):
    from nerfmeta.fields.dense_grid import DenseGrid, DenseGridConfig

    class Recording(DenseGrid):
        def begin_step(self, step, progress):
            seen.append((step, progress))
            return super().begin_step(step, progress)

    seen: list = []
    scene = load_scene(tiny_scene)
    fit(Recording(DenseGridConfig(side=4), scene.bounds), scene, FitConfig(iters=4, batch_rays=16, eval_every=0, final_ssim=False,
                                                                        final_lpips=False), background=torch.ones(3))
    assert seen == [(0, 0.0), (1, 0.25), (2, 0.5), (3, 0.75)]


def test_callbacks_that_watch_the_final_evaluation_hear_each_view(tiny_scene, tmp_path):
    heard: list[tuple[int, int]] = []

    class Watcher:
        def __call__(self, record, model, state) -> None:
            pass

        def evaluating(self, done: int, total: int) -> None:
            heard.append((done, total))

    steps: list[int] = []
    summary = run_fit(_grid_run_config(tiny_scene, 3, 0), tmp_path / "run",
                      callbacks=[Watcher(), lambda record, model, state: steps.append(record.iter)])
    n = summary["test_views"]
    assert n == 4 and heard == [(k, n) for k in range(n + 1)] and steps == [1, 2, 3]  # a plain callback still works


@pytest.mark.parametrize(("n_views", "height", "width", "max_rays", "stride"), [
    (4, 1263, 710, 262144, 4),  # beer at full size: 4 x 316 x 177 = 224k rays (3: 4 x 421 x 237 = 399k, too many)
    (4, 178, 316, 262144, 1),  # beer at --downscale 4: every pixel fits
    (4, 1263, 710, 0, 1),  # 0: no limit
    (1, 10, 10, 25, 2),  # exactly at the limit: 5 x 5
    (1, 10, 10, 24, 3),  # one ray over it: 3 x 3 (rows 1, 4, 7)
    (3, 10, 7, 1, 10),  # never less than one pixel a view
])
def test_intermediate_evaluations_take_the_smallest_pixel_stride_within_their_ray_budget(n_views, height, width, max_rays, stride):
    from nerfmeta.fit.evaluate import pixel_stride, strided_rays

    assert pixel_stride(n_views, height, width, max_rays) == stride
    if 1 < stride < max(height, width):  # the smallest that fits (the last case: one pixel a view, over the budget)
        assert strided_rays(n_views, height, width, stride) <= max_rays < strided_rays(n_views, height, width, stride - 1)


def test_a_strided_render_is_the_full_renders_pixels_on_that_grid(tiny_scene):
    from nerfmeta.fit.evaluate import render_view, strided_rays

    scene = load_scene(tiny_scene)
    model = build_model("grid", config_from_dict("grid", {**vars_of(default_config("grid")), "coarse_iters": 0,
                                                          "num_voxels": 4096}), scene.bounds, seed=0)
    view, white = scene.splits["test"][0], torch.ones(3)
    full, strided = render_view(model, scene, view, white), render_view(model, scene, view, white, stride=3)
    assert strided.rgb.shape == (11, 11, 3) == full.rgb[1::3, 1::3].shape  # 32 px: rows and columns 1, 4, ..., 31
    assert len(strided.rgb.reshape(-1, 3)) == strided_rays(1, 32, 32, 3)
    torch.testing.assert_close(strided.rgb, full.rgb[1::3, 1::3], rtol=0, atol=1e-6)
    torch.testing.assert_close(strided.target, full.target[1::3, 1::3], rtol=0, atol=0)


@pytest.mark.parametrize("max_rays", [0, 1000])
def test_intermediate_evaluations_over_their_ray_budget_score_a_pixel_grid_and_say_so(tiny_scene, max_rays):
    scene = load_scene(tiny_scene)  # 4 test views of 32 x 32: 4096 rays
    model = build_model("grid", config_from_dict("grid", {**vars_of(default_config("grid")), "coarse_iters": 0,
                                                          "num_voxels": 4096}), scene.bounds, seed=0)
    config = FitConfig(iters=4, batch_rays=64, eval_every=2, eval_views=0, eval_max_rays=max_rays, final_ssim=False)
    result = fit(model, scene, config, background=torch.ones(3))
    assert [r.test_psnr is not None for r in result.history] == [False, True, False, True]
    decision = result.state.decisions.get("eval_stride")
    if max_rays == 0:
        assert decision is None
    else:  # 4 x 16 x 16 = 1024 > 1000, 4 x 11 x 11 = 484: every third pixel
        assert decision["value"] == 3 and decision["evidence"]["rays"] == 484
        assert decision["reason"] in result.history[2].event  # noted in the next record, as every decision
    assert all(r.rgb.shape == (32, 32, 3) for r in result.final.renders)  # the final evaluation: every pixel
