"""Held-out tiles: pixels the fit never trains on, scored to pick the parameters it ends with and when it stops."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.data.scene_type import SCENE_TYPES, SceneType
from nerfmeta.fields.dense_grid import DenseGrid, DenseGridConfig
from nerfmeta.fit.holdout import MIN_TILED_VIEWS, place_tiles, tile_pixels, tile_side, tiled_views
from nerfmeta.fit.loop import FitConfig, fit
from nerfmeta.fit.run import RunConfig, read_metrics, run_fit
from nerfmeta.fit.sampler import RaySampler


@pytest.mark.parametrize("height,width,fraction,side", [
    (96, 96, 0.17, 16), (128, 96, 0.17, 16), (32, 32, 0.17, 5), (4, 4, 0.17, 1),
    (2, 2, 0.5, 1),  # one pixel held out, three trained on
    (1, 1, 0.17, 0),  # a one-pixel view keeps its pixel
    (96, 96, 0.0, 0),
])
def test_tile_side_is_the_fraction_of_the_shorter_side_and_leaves_pixels_to_train_on(height, width, fraction, side):
    assert tile_side(height, width, fraction) == side


@pytest.mark.parametrize("n_views,side,pixels,tiled", [
    (16, 16, 4096, 16),  # a 16-view scene at 96 px: every view
    (40, 22, 4096, 9),  # 40 views at 128 px: 4096 / 484 -> 9 views
    (100, 136, 4096, MIN_TILED_VIEWS),  # 800 px views: one tile would hold 4096 pixels, but a score of one view is its quirks
    (5, 22, 4096, 5),
    (40, 22, 0, 40),  # 0: every view
])
def test_as_many_views_get_a_tile_as_hold_the_scored_pixels(n_views, side, pixels, tiled):
    assert tiled_views(n_views, side, pixels) == tiled


def test_views_without_a_tile_keep_every_pixel():
    tiles = place_tiles(40, 128, 128, 0.17, seed=0, pixels=4096)
    assert tiles.side == 22 and len(tiles.views) == 9
    assert tiles.held_fraction(128, 128) == pytest.approx(9 * 484 / (40 * 128 * 128))
    untiled = torch.tensor(sorted(set(range(40)) - set(tiles.views.tolist())))
    rows, cols = torch.meshgrid(torch.arange(128), torch.arange(128), indexing="ij")
    for v in untiled.tolist():
        assert not bool(tiles.contains(torch.full((128 * 128,), v), rows.reshape(-1), cols.reshape(-1)).any())
    for v in tiles.views.tolist():
        assert int(tiles.contains(torch.full((128 * 128,), v), rows.reshape(-1), cols.reshape(-1)).sum()) == 484


def test_tiles_lie_inside_their_views_and_follow_the_seed():
    tiles = place_tiles(50, 20, 30, 0.25, seed=3)
    assert tiles.side == 5
    assert bool((tiles.rows >= 0).all() and (tiles.rows + tiles.side <= 20).all())
    assert bool((tiles.cols >= 0).all() and (tiles.cols + tiles.side <= 30).all())
    tiles = place_tiles(50, 20, 30, 0.25, seed=3)
    again, other = place_tiles(50, 20, 30, 0.25, seed=3), place_tiles(50, 20, 30, 0.25, seed=4)
    assert torch.equal(tiles.rows, again.rows) and torch.equal(tiles.cols, again.cols)
    assert not (torch.equal(tiles.rows, other.rows) and torch.equal(tiles.cols, other.cols))
    assert tiles.held_fraction(20, 30) == pytest.approx(25 / 600)


@pytest.mark.parametrize("max_rays,expected", [(0, 3 * 25), (75, 3 * 25), (74, 3 * 9), (27, 3 * 9), (26, 3 * 4), (3, 3)])
def test_scored_tile_pixels_are_a_regular_subsample_within_the_ray_budget(max_rays, expected):
    tiles = place_tiles(3, 20, 30, 0.25, seed=0)  # 5 x 5 tiles; strides 1, 2 (3 x 3), 3 (2 x 2), 5 (1)
    view, row, col = tile_pixels(tiles, max_rays)
    assert len(view) == expected
    assert bool(tiles.contains(view, row, col).all())
    assert sorted(set(view.tolist())) == [0, 1, 2]


def _coded(scene):
    """``scene`` with each pixel's colour naming it: (view, row, col) scaled into [0, 1]."""
    v, h, w = scene.images.shape[:3]
    grid = torch.meshgrid(torch.arange(v), torch.arange(h), torch.arange(w), indexing="ij")
    code = torch.stack([g.float() / 64 for g in grid], -1)
    return dataclasses.replace(scene, images=code)


def test_the_sampler_never_draws_a_held_out_pixel_and_scores_exactly_them(tiny_scene):
    scene = _coded(load_scene(tiny_scene))
    train = scene.split_indices("train")
    tiles = place_tiles(len(train), scene.height, scene.width, 0.4, seed=0)  # 13 x 13 of 32 x 32: 16.5 % held out
    sampler = RaySampler(scene, "train", "cpu", tiles)
    gen = torch.Generator().manual_seed(0)
    drawn = torch.cat([sampler.draw(4096, gen)[0].target for _ in range(10)])
    position = torch.full((scene.n_views,), -1, dtype=torch.long)
    position[train] = torch.arange(len(train))  # a view's place in the split, which the tiles are indexed by
    view, row, col = (drawn * 64).round().long().unbind(-1)
    view = position[view]
    assert bool((view >= 0).all())
    assert not bool(tiles.contains(view, row, col).any())
    assert len(set(zip(view.tolist(), row.tolist(), col.tolist()))) > 0.95 * (sampler.n_pixels - len(train) * 169)
    scored = sampler.held_out(0)
    sv, sr, sc = (scored.target * 64).round().long().unbind(-1)
    sv = position[sv]
    assert len(scored) == len(train) * 13 * 13 and bool(tiles.contains(sv, sr, sc).all())
    assert len(set(zip(sv.tolist(), sr.tolist(), sc.tolist()))) == len(scored)


def _spoiler(start: int, end: int, seen: dict):
    """A callback that keeps the parameters after ``start``'s step and spoils them after each step until ``end`` (the
    fit's last step: callbacks run after its final evaluation): the held-out PSNR peaks at ``start``."""
    def spoil(record, model, state):
        if record.iter == start:
            seen["best"] = {k: v.detach().clone() for k, v in model.state_dict().items()}
        if start <= state.step < end:
            with torch.no_grad():
                model.grid.normal_(generator=torch.Generator().manual_seed(state.step)).mul_(5.0)
    return spoil


def _fit_grid(tiny_scene, callbacks=(), kind="object", **options):
    """A dense grid (seeded) fitted to the tiny scene, taken as a scene of ``kind``, with ``options`` of
    :class:`FitConfig` over quiet defaults: the model and the fit's result."""
    scene = load_scene(tiny_scene)
    scene = dataclasses.replace(scene, scene_type=SceneType(kind, "given by the test", detected=False))
    torch.manual_seed(0)
    model = DenseGrid(DenseGridConfig(side=12), scene.bounds)
    config = FitConfig(**{"batch_rays": 256, "eval_every": 0, "final_ssim": False, "final_lpips": False, **options})
    return model, fit(model, scene, config, background=torch.ones(3), callbacks=list(callbacks))


def test_the_fit_stops_patience_steps_after_its_best_held_out_score_and_ends_with_those_parameters(tiny_scene):
    seen: dict = {}
    model, result = _fit_grid(tiny_scene, [_spoiler(40, 70, seen)], iters=200, holdout_every=10, patience=30)
    assert result.state.step == 70  # scored at 50, 60, 70 below step 40's score; 30 steps after it, the fit stops
    assert "step 40" in result.state.stop_reason and "30 steps" in result.state.stop_reason
    assert all(torch.equal(v, seen["best"][k]) for k, v in model.state_dict().items())
    assert result.state.best.step == 40
    scores = {r.iter: r.holdout_psnr for r in result.history if r.holdout_psnr is not None}
    assert sorted(scores) == [10, 20, 30, 40, 50, 60, 70]
    assert max(scores, key=scores.get) == 40 and scores[50] < scores[40] - 3
    assert result.state.decisions["holdout_best"]["evidence"]["step"] == 40
    assert "parameters of step 40" in (result.history[-1].event or "")


def test_without_patience_the_fit_runs_on_and_still_ends_with_its_best_parameters(tiny_scene):
    seen: dict = {}
    model, result = _fit_grid(tiny_scene, [_spoiler(40, 90, seen)], iters=90, holdout_every=10, patience=0)
    assert result.state.step == 90 and result.state.best.step == 40
    assert all(torch.equal(v, seen["best"][k]) for k, v in model.state_dict().items())


def test_a_fit_that_keeps_improving_ends_with_its_last_parameters(tiny_scene):
    _, result = _fit_grid(tiny_scene, iters=60, holdout_every=20, holdout_release=1.0)
    assert result.state.step == 60 and result.state.best.step == 60
    assert "holdout_best" not in result.state.decisions
    assert result.state.decisions["holdout_tiles"]["value"] == 5  # 0.17 of 32 px


def test_a_fit_still_at_its_best_late_gives_its_tiles_back_to_training(tiny_scene):
    _, result = _fit_grid(tiny_scene, iters=100, holdout_every=20, holdout_release=0.75)
    released = result.state.decisions["holdout_released"]
    assert released["value"] == 80  # the first score at 3/4 of the fit, still the best
    scores = [r.iter for r in result.history if r.holdout_psnr is not None]
    assert scores == [20, 40, 60, 80]  # nothing scored, stopped or put back after it
    assert result.state.best is None and "holdout_best" not in result.state.decisions


def test_no_tiles_means_every_pixel_trained_on_and_no_scores(tiny_scene):
    _, result = _fit_grid(tiny_scene, [_spoiler(10, 1000, {})], iters=30, holdout_tile=0.0, holdout_every=10,
                          patience=10)
    assert result.state.step == 30 and result.state.best is None
    assert all(r.holdout_psnr is None for r in result.history)
    assert not {"holdout_tiles", "holdout_best"} & set(result.state.decisions)


class _Kill(Exception):
    pass


def test_a_resumed_fit_keeps_its_best_snapshot_and_stops_where_the_uninterrupted_one_did(tiny_scene, tmp_path):
    model = {"coarse_iters": 6, "growth_steps": [4], "num_voxels": 8000, "coarse_num_voxels": 1000, "occupancy_every": 5}

    def config():
        return RunConfig(scene=str(tiny_scene), model=model, renders=0, fit=FitConfig(
            iters=80, batch_rays=256, eval_every=0, checkpoint_every=10, holdout_every=5, patience=15, final_lpips=False))

    full = run_fit(config(), tmp_path / "full", callbacks=[_grid_spoiler(20, 35)])

    def kill_at_27(record, model, state):
        if record.iter == 27:
            raise _Kill

    with pytest.raises(_Kill):
        run_fit(config(), tmp_path / "killed", callbacks=[_grid_spoiler(20, 35), kill_at_27])
    resumed = run_fit(config(), tmp_path / "killed", resume=True, callbacks=[_grid_spoiler(20, 35)])
    assert full["iters"] == resumed["iters"] == 35  # best at 20, scored below it at 25, 30, 35
    assert resumed["test_psnr"] == full["test_psnr"]
    a, b = (read_metrics(tmp_path / name / "metrics.jsonl") for name in ("full", "killed"))
    assert [r.get("holdout_psnr") for r in a] == [r.get("holdout_psnr") for r in b]


def _grid_spoiler(start: int, end: int):
    """:func:`_spoiler` for the voxel grid: its fine density emptied after every step from ``start`` until ``end``."""
    def spoil(record, model, state):
        if start <= state.step < end and model.stage == "fine":
            with torch.no_grad():
                model.density.fill_(-20.0)
    return spoil


def test_the_concave_preset_trains_on_every_pixel(tiny_scene, tmp_path):
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--preset", "concave", "--iters", "3", "--eval-every", "0",
                 "--renders", "0", "--no-final-lpips"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["fit"]["holdout_tile"] == 0.0
    assert "holdout_tiles" not in json.loads((out / "summary.json").read_text())["decisions"]


def test_a_fit_of_more_views_than_holdout_max_views_trains_on_every_pixel_and_says_so(tiny_scene):
    _, result = _fit_grid(tiny_scene, [_spoiler(10, 30, {})], iters=30, holdout_every=10, patience=10,
                          holdout_max_views=7)  # 8 training views
    assert result.state.step == 30 and result.state.best is None
    decision = result.state.decisions["holdout_tiles"]
    assert decision["value"] is False and "8 training views > holdout_max_views=7" in decision["reason"]


@pytest.mark.parametrize("kind,article", [("forward", "a"), ("unbounded", "an")])
def test_a_fit_of_another_kind_than_an_object_trains_on_every_pixel_and_says_so(tiny_scene, kind, article):
    _, result = _fit_grid(tiny_scene, [_spoiler(10, 30, {})], kind=kind, iters=30, holdout_every=10, patience=10)
    assert result.state.step == 30 and result.state.best is None
    decision = result.state.decisions["holdout_tiles"]
    assert decision["value"] is False and f"{article} {kind} scene, not one of holdout_scene_types=object" in decision["reason"]


def test_a_kind_named_in_holdout_scene_types_holds_tiles_out_and_stops(tiny_scene):
    _, result = _fit_grid(tiny_scene, [_spoiler(10, 60, {})], kind="forward", holdout_scene_types=("object", "forward"),
                          iters=60, holdout_every=10, patience=20)
    assert result.state.step < 60 and result.state.best is not None
    assert result.state.decisions["holdout_tiles"]["value"] > 0


@pytest.mark.parametrize("args,needle", [(["--holdout-tile", "0.6"], "holdout"), (["--patience", "-1"], "patience"),
                                         (["--holdout-every", "0"], "holdout"),
                                         (["--holdout-scene-types", "object,indoor"], "holdout-scene-types")])
def test_bad_holdout_options_exit_2_with_one_line(tiny_scene, tmp_path, capsys, args, needle):
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--iters", "2", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not out.exists()


def test_a_run_saved_before_held_out_tiles_resumes_training_on_every_pixel():
    assert FitConfig.from_json({"iters": 7}).holdout_tile == 0.0
    assert FitConfig.from_json({"iters": 7, "holdout_tile": 0.17}).holdout_tile == 0.17
    assert RunConfig.from_json({"scene": "s", "fit": {"iters": 7}}).fit.holdout_tile == 0.0
    assert FitConfig().holdout_tile == 0.17  # new fits hold tiles out
    assert FitConfig().holdout_scene_types == ("object",)  # ... of objects


def test_a_run_saved_before_scene_kinds_were_chosen_resumes_with_tiles_in_any_kind_and_new_ones_load_back_equal():
    assert FitConfig.from_json({"iters": 7, "holdout_tile": 0.17}).holdout_scene_types == SCENE_TYPES
    config = FitConfig(holdout_scene_types=("object", "forward"))
    assert FitConfig.from_json(json.loads(json.dumps(dataclasses.asdict(config)))) == config


def test_a_fit_resumed_after_its_release_keeps_training_on_every_pixel(tiny_scene, tmp_path):
    def config():
        return RunConfig(scene=str(tiny_scene), model={"side": 12}, backbone="dense", renders=0, fit=FitConfig(
            iters=40, batch_rays=256, eval_every=0, checkpoint_every=10, holdout_every=10, holdout_release=0.5,
            final_lpips=False))

    full = run_fit(config(), tmp_path / "full")

    def kill_at_35(record, model, state):
        if record.iter == 35:
            raise _Kill

    with pytest.raises(_Kill):
        run_fit(config(), tmp_path / "killed", callbacks=[kill_at_35])
    resumed = run_fit(config(), tmp_path / "killed", resume=True)  # from the checkpoint at 30, after the release at 20
    assert full["decisions"]["holdout_released"]["value"] == 20
    assert resumed["test_psnr"] == full["test_psnr"] and resumed["iters"] == 40
    records = read_metrics(tmp_path / "killed" / "metrics.jsonl")
    assert [r["iter"] for r in records if "holdout_psnr" in r] == [10, 20]
