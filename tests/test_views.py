"""Training views the fit cannot reconcile with the others: measured per view, named, and dropped on request."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import replace
from pathlib import PurePath

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.errors import SceneError
from nerfmeta.fields.registry import build_model, config_from_dict, default_config
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.views import MIN_RAYS, ViewErrors, suspect_views


def test_view_errors_are_a_decayed_mean_per_view_in_float64():
    errors = ViewErrors.empty(3, window=2)  # decay 0.5
    f64 = torch.float64
    rgb, target = torch.zeros(4, 3, dtype=f64), torch.tensor([[0.1] * 3, [0.2] * 3, [0.1] * 3, [0.0] * 3], dtype=f64)
    errors.add(torch.tensor([0, 1, 0, 2]), rgb, target)
    errors.add(torch.tensor([0]), torch.zeros(1, 3, dtype=f64), torch.full((1, 3), 0.3, dtype=f64))
    # view 0: (0.01 + 0.01) * 0.5 + 0.09 over 2 * 0.5 + 1 rays
    assert errors.sse[0].item() == pytest.approx(0.1, rel=1e-12) and errors.rays[0].item() == 2.0
    assert errors.sse[1].item() == pytest.approx(0.02, rel=1e-12) and errors.rays[1].item() == 0.5
    assert errors.sse.dtype == torch.float64


def test_a_view_with_too_few_rays_is_not_judged():
    errors = ViewErrors.empty(2)
    n = int(MIN_RAYS)
    errors.add(torch.zeros(n, dtype=torch.long), torch.zeros(n, 3), torch.full((n, 3), 0.1))
    psnr = errors.psnr()
    assert psnr[0].item() == pytest.approx(20.0) and math.isnan(psnr[1].item())


def test_suspects_are_the_views_far_below_the_median_worst_first():
    psnr = torch.tensor([30.0, 29.0, 22.5, 31.0, float("nan"), 19.0, 23.5])
    # median of the judged six: 23.5 (the lower middle); 22.5 is 1 dB under, 19.0 4.5 dB under
    assert suspect_views(psnr, below_db=4.0) == [(5, pytest.approx(4.5))]
    assert suspect_views(torch.tensor([30.0, 10.0, 30.0])) == []  # three judged views: too few to tell
    assert suspect_views(torch.full((6,), 25.0)) == []


def _scene_with_a_wrong_view(tiny_scene):
    scene = load_scene(tiny_scene)
    train = scene.splits["train"]
    images = scene.images.clone()
    # another view's image with its content moved by half the frame: no pose of this scene sees it (after 200 steps
    # 12.7 dB below the median training view, where the clean scene's views are within 1.2 dB of it)
    images[train[2]] = torch.roll(images[train[5]], (16, 16), (0, 1))
    return scene, replace(scene, images=images)


def test_a_fit_names_the_one_view_that_no_pose_fits(tiny_scene):
    grid = {**dataclasses.asdict(default_config("grid")), "coarse_iters": 0, "growth_steps": [], "num_voxels": 8000,
            "view_dependent": False}
    found = {}
    for name, scene in zip(("clean", "one wrong"), _scene_with_a_wrong_view(tiny_scene)):
        model = build_model("grid", config_from_dict("grid", grid), scene.bounds, seed=0)
        result = fit(model, scene, FitConfig(iters=200, batch_rays=256, eval_every=0, final_ssim=False,
                                             final_lpips=False), background=torch.ones(3))
        found[name] = [i for i, _ in suspect_views(result.view_psnr)]
    assert found == {"clean": [], "one wrong": [2]}


def test_fit_writes_suspect_views_and_drop_views_leaves_them_out(tiny_scene, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["fit", str(tiny_scene), "--init", "scratch", "--iters", "3", "--eval-views", "1", "--renders", "0",
            "--no-eval-ssim", "--no-final-lpips"]
    scene = load_scene(tiny_scene)
    train_names = [scene.image_names[i] for i in scene.splits["train"]]
    test_name = scene.image_names[scene.splits["test"][0]]
    assert main([*args, "--out", str(run), "--drop-views", f"{train_names[1]},{test_name}"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["suspect_views"] == [] and summary["test_views"] == len(scene.splits["test"]) - 1
    assert json.loads((run / "config.json").read_text())["drop_views"] == [train_names[1], test_name]
    # a name that is no view: one line, exit 2, no run folder
    assert main([*args, "--out", str(tmp_path / "bad"), "--drop-views", "nope.png"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--drop-views names nope.png, not a view of this scene" in err
    assert not (tmp_path / "bad").exists()


def test_dropping_every_training_view_is_refused(tiny_scene):
    scene = load_scene(tiny_scene)
    train_name, test_name = scene.image_names[scene.splits["train"][1]], scene.image_names[scene.splits["test"][1]]
    assert PurePath(train_name).name == PurePath(test_name).name  # train/r_1.png and test/r_1.png
    with pytest.raises(SceneError, match="is more than one view"):  # so the file name alone is not enough
        scene.without_views([PurePath(train_name).name])
    assert scene.without_views([train_name]).n_views == scene.n_views - 1
    with pytest.raises(SceneError, match="leaves no training view"):
        scene.without_views([scene.image_names[i] for i in scene.splits["train"]])
    fewer = scene.without_views([scene.image_names[scene.splits["train"][0]]])
    assert fewer.n_views == scene.n_views - 1 and len(fewer.splits["test"]) == len(scene.splits["test"])
    torch.testing.assert_close(fewer.images[fewer.splits["test"][0]], scene.images[scene.splits["test"][0]])


def test_a_held_out_view_far_below_the_others_is_named_only_when_no_training_view_is(tiny_scene):
    from nerfmeta.fit.evaluate import EvalResult
    from nerfmeta.fit.loop import FitResult, FitState
    from nerfmeta.fit.run import _suspect_views

    scene = load_scene(tiny_scene)
    test_names = [scene.image_names[i] for i in scene.splits["test"]]
    final = EvalResult(psnr=26.0, ssim=None, samples_per_ray=1.0, renders=(), view_psnrs=(30.0, 29.0, 15.0, 31.0))
    clean_train = torch.full((len(scene.splits["train"]),), 25.0)
    rows = _suspect_views(scene, FitResult(FitState(), final, view_psnr=clean_train))
    assert [(r["view"], r["split"], r["below_median_db"]) for r in rows] == [(test_names[2], "test", 14.0)]
    one_bad = clean_train.clone()
    one_bad[3] = 10.0  # a training view far below: it is named, the held-out ones wait for the next fit
    assert [r["split"] for r in _suspect_views(scene, FitResult(FitState(), final, view_psnr=one_bad))] == ["train"]
    near = EvalResult(psnr=26.0, ssim=None, samples_per_ray=1.0, renders=(), view_psnrs=(30.0, 29.0, 20.0, 31.0))
    assert _suspect_views(scene, FitResult(FitState(), near, view_psnr=clean_train)) == []  # 9 dB: under the line
