"""Reports: curve maths on hand-made logs, snapshots during a fit, one-scene comparisons, `nerfmeta report`."""

import dataclasses
import json
import time

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfmeta.cli import main
from nerfmeta.data import load_scene
from nerfmeta.errors import ConfigError
from nerfmeta.fit.loop import FitConfig
from nerfmeta.fit.run import RunConfig, build_initial_model, read_metrics, run_fit
from nerfmeta.report import snapshots as snapshots_module
from nerfmeta.report.aggregate import route_correct, write_report
from nerfmeta.report.compare import compare_logs, load_fit_log, write_comparison
from nerfmeta.report.curves import ahead_in_time, ahead_of, evaluations, first_reach, mean_band, psnr_at_iter, shifted, speedup
from nerfmeta.report.snapshots import SnapshotWriter, read_snapshots, snapshot_name, to_uint8

TINY_GRID = {"coarse_iters": 6, "growth_steps": [4], "num_voxels": 8000, "coarse_num_voxels": 1000, "occupancy_every": 5}


def _records(points, last_iter, dt):
    """metrics.jsonl records for iterations 1..last_iter (time dt per step) with test PSNR at ``points``."""
    out = []
    for it in range(1, last_iter + 1):
        r = {"iter": it, "time_s": round(it * dt, 4), "train_psnr": 10.0, "samples_per_ray": 8.0, "lr_scale": 1.0}
        if it in points:
            r["test_psnr"] = points[it]
        out.append(r)
    return out


def _write_fit(folder, points, last_iter, dt, **summary):
    folder.mkdir(parents=True)
    records = _records(points, last_iter, dt)
    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    final = points[max(points)] if points else None
    base = {"scene": "/scenes/chair", "category": "chair", "init": "scratch", "iters": last_iter,
            "time_s": round(last_iter * dt, 4), "test_psnr": final}
    (folder / "summary.json").write_text(json.dumps({**base, **summary}))
    return folder


# ----- curve maths, exact ----------------------------------------------------------------------

def test_psnr_at_iter_is_the_last_evaluation_at_or_before_n():
    ev = evaluations(_records({20: 10.0, 40: 20.0, 60: 30.0}, 60, 0.1))
    assert psnr_at_iter(ev, 40, 60) == (20.0, 40)
    assert psnr_at_iter(ev, 59, 60) == (20.0, 40)  # not interpolated
    assert psnr_at_iter(ev, 10, 60) == (None, None)  # no evaluation yet
    assert psnr_at_iter(ev, 100, 60) == (None, None)  # the fit stopped before 100


def test_first_reach_interpolates_iterations_and_time_with_one_fraction():
    ev = evaluations(_records({20: 10.0, 40: 20.0, 60: 30.0}, 60, 0.1))
    r = first_reach(ev, 25.0)  # halfway between (40, 20 dB) and (60, 30 dB)
    assert r.iter == pytest.approx(50.0) and r.time_s == pytest.approx(5.0) and not r.before_first_eval
    r = first_reach(ev, 22.0)
    assert r.iter == pytest.approx(44.0) and r.time_s == pytest.approx(4.4)
    r = first_reach(ev, 30.0)  # exactly at an evaluation
    assert r.iter == pytest.approx(60.0)
    first = first_reach(ev, 5.0)
    assert (first.iter, first.time_s, first.before_first_eval) == (20.0, 2.0, True)
    assert first_reach(ev, 30.5) is None
    assert speedup(60.0, 44.0) == pytest.approx(60 / 44) and speedup(60.0, None) is None


def test_first_reach_uses_the_first_crossing_even_if_the_curve_dips_later():
    ev = evaluations(_records({10: 10.0, 20: 30.0, 30: 5.0, 40: 40.0}, 40, 1.0))
    assert first_reach(ev, 20.0).iter == pytest.approx(15.0)


def test_ahead_is_strict_and_only_at_shared_evaluations():
    base = evaluations(_records({20: 10.0, 40: 20.0, 60: 30.0}, 60, 0.1))
    method = evaluations(_records({20: 11.0, 40: 20.0, 50: 1.0, 60: 35.0}, 60, 0.1))
    a = ahead_of(method, base)
    assert a.ahead is False and a.not_ahead_at == (40,) and a.compared_iters == (20, 40, 60)
    assert ahead_of(evaluations(_records({20: 11.0}, 20, 0.1)), base).ahead is True
    assert ahead_of(evaluations(_records({30: 99.0}, 30, 0.1)), base).ahead is None


def test_mean_band_over_the_shared_range():
    a = evaluations(_records({10: 10.0, 20: 20.0, 30: 30.0}, 30, 1.0))
    b = evaluations(_records({10: 14.0, 30: 18.0, 40: 50.0}, 40, 1.0))
    band = mean_band([a, b], "iter")
    # grid: evaluated iterations inside [10, 30]; b interpolated at 20 -> 16
    np.testing.assert_allclose(band.x, [10, 20, 30])
    np.testing.assert_allclose(band.mean, [12.0, 18.0, 24.0])
    np.testing.assert_allclose(band.sd, [np.std([10, 14], ddof=1), np.std([20, 16], ddof=1), np.std([30, 18], ddof=1)])
    assert band.n_runs == 2
    tband = mean_band([a, b], "time_s")
    assert tband.x[0] == pytest.approx(10.0) and tband.x[-1] == pytest.approx(30.0)
    assert mean_band([a, evaluations(_records({50: 1.0}, 50, 1.0))], "iter") is None  # ranges do not overlap


def test_route_correct_rules():
    known = ["chair", "car"]

    def s(true, route, cat=None):
        return {"category": true, "route": {"route": route, "category": cat, "known_categories": known}}

    assert route_correct(s("chair", "category", "chair")) is True
    assert route_correct(s("chair", "category", "car")) is False
    assert route_correct(s("chair", "meta")) is False
    assert route_correct(s("lamp", "meta")) is True
    assert route_correct(s("lamp", "category", "car")) is False
    assert route_correct(s("lamp", "scratch")) is False
    assert route_correct({"category": "chair"}) is None
    assert route_correct({"category": None, "route": {"route": "meta", "known_categories": known}}) is None
    assert route_correct({"category": "chair", "route": {"route": "meta"}}) is None
    # where the classifier answered, its answer is scored, whatever route the applicability checks left
    assert route_correct({"category": "chair", "route": {"route": "scratch", "category": "chair", "unknown": False,
                                                         "known_categories": known}}) is True
    assert route_correct({"category": "lamp", "route": {"route": "scratch", "category": "car", "unknown": True,
                                                        "known_categories": known}}) is True
    assert route_correct({"category": "chair", "route": {"route": "meta", "category": "chair", "unknown": True,
                                                         "known_categories": known}}) is False
    # no classifier asked (a zoo of another backbone): not scored
    assert route_correct({"category": "chair", "route": {"route": "scratch", "known_categories": []}}) is None


def test_ahead_in_time_against_the_interpolated_baseline():
    base = evaluations(_records({10: 10.0, 20: 20.0}, 20, 1.0))  # 10 dB at 10 s, 20 dB at 20 s
    method = evaluations(_records({5: 30.0, 12: 13.0, 18: 17.0, 30: 30.0}, 30, 1.0))
    # inside [10, 20] s: 13 dB at 12 s (baseline 12) ahead; 17 dB at 18 s (baseline 18) behind by 1 dB
    result = ahead_in_time(method, base)
    assert (result.ahead, result.compared) == (False, 2) and result.behind_db == pytest.approx(1.0)
    late = shifted(method, 1.0)  # 13 dB at 13 s (baseline 13): not strictly ahead; 17 dB at 19 s: behind by 2
    assert ahead_in_time(late, base).behind_db == pytest.approx(2.0) and ahead_in_time(late, base).ahead is False
    assert ahead_in_time(evaluations(_records({40: 1.0}, 40, 1.0)), base).ahead is None


def test_wall_clock_axis_adds_classification_and_loading_to_the_routed_fit(tmp_path):
    """A routed fit that reaches the target at 2.0 s of optimisation after 1.5 s of classifying and 0.5 s of loading
    reaches it at 4.0 s of wall-clock: against a baseline that takes 4.0 s (+ 0.1 s loading) it is 1.025x, not 2x."""
    run = _write_fit(tmp_path / "run", {10: 15.0, 20: 20.0}, 20, 0.1, init="category", init_load_s=0.5,
                     route={"route": "category", "category": "chair", "known_categories": ["chair"], "classify_s": 1.5})
    base = _write_fit(run / "compare" / "scratch", {20: 15.0, 40: 20.0}, 40, 0.1, backbone="grid", init_load_s=0.1)
    result = write_comparison(run, {"scratch": base})
    routed, scratch = result["methods"]["routed"], result["methods"]["scratch"]
    assert (routed["run"], scratch["run"]) == (".", "compare/scratch")  # relative: true after a move or an --overwrite swap
    assert (routed["classify_s"], routed["init_load_s"], routed["start_s"]) == (1.5, 0.5, 2.0)
    assert routed["time_s"] == 2.0 and routed["wall_s"] == 4.0 and scratch["wall_s"] == pytest.approx(4.1)
    assert routed["reach_time_s"] == pytest.approx(2.0) and routed["reach_wall_s"] == pytest.approx(4.0)
    assert routed["speedup_time"] == pytest.approx(2.0) and result["speedup_wall"] == pytest.approx(4.1 / 4.0, abs=1e-4)
    assert result["baseline_backbone"] == "grid" and "wall-clock" in result["axis"]
    md = (run / "report.md").read_text()
    assert "Baseline: **scratch**, a grid fit from scratch" in md and "1.02x" in md


# ----- one-scene comparison on hand-made logs -----------------------------------------------------

@pytest.fixture
def hand_runs(tmp_path):
    run = _write_fit(tmp_path / "run", {25: 15.0, 50: 21.0, 75: 17.5, 100: 23.0}, 100, 0.05, init="category",
                     route={"route": "category", "category": "chair", "known_categories": ["chair"], "confidence": 0.9})
    scratch = _write_fit(run / "compare" / "scratch", {25: 10.0, 50: 14.0, 75: 18.0, 100: 20.0}, 100, 0.04)
    meta = _write_fit(run / "compare" / "meta", {25: 11.0, 50: 12.0, 75: 13.0, 100: 19.0}, 100, 0.04, init="meta")
    return run, scratch, meta


def test_comparison_numbers_on_hand_made_logs(hand_runs, tmp_path):
    run, scratch, meta = hand_runs
    result = write_comparison(run, {"scratch": scratch, "meta": meta}, iters=(25, 60, 100, 200))
    assert result["target_psnr"] == 20.0 and result["method"] == "routed"
    routed, base, m = (result["methods"][k] for k in ("routed", "scratch", "meta"))
    # scratch reaches its final 20 dB at its last evaluation: 100 iterations, 4.0 s
    assert base["reach_iter"] == pytest.approx(100.0) and base["reach_time_s"] == pytest.approx(4.0)
    assert base["speedup_iters"] == pytest.approx(1.0)
    # routed: 15 dB at 25, 21 dB at 50 -> 20 dB at 25 + 25 * 5/6 iterations, 1.25 + 1.25 * 5/6 s
    assert routed["reach_iter"] == pytest.approx(25 + 25 * 5 / 6, abs=1e-3)
    assert routed["reach_time_s"] == pytest.approx(1.25 + 1.25 * 5 / 6, abs=1e-4)
    assert routed["speedup_iters"] == pytest.approx(100 / (25 + 25 * 5 / 6), abs=1e-4)
    assert routed["speedup_time"] == pytest.approx(4.0 / (1.25 + 1.25 * 5 / 6), abs=1e-4)
    assert result["speedup_iters"] == routed["speedup_iters"] and result["speedup_time"] == routed["speedup_time"]
    assert m["reached"] is False and m["speedup_iters"] is None and m["reach_iter"] is None
    # table: last evaluation at or before N; null past the end of the fit
    assert routed["test_psnr_at_iter"] == {"25": 15.0, "60": 21.0, "100": 23.0, "200": None}
    assert routed["test_psnr_at_iter_from"] == {"25": 25, "60": 50, "100": 100, "200": None}
    # ahead of scratch except at 75 (17.5 < 18)
    assert result["ahead_at_every_eval"] is False and result["not_ahead_at"] == [75]
    assert routed["compared_iters"] == [25, 50, 75, 100]
    assert m["ahead_at_every_eval"] is False and m["not_ahead_at"] == [50, 75, 100]  # 12 < 14, 13 < 18, 19 < 20
    # files, and the dict stored in the run's summary
    for name in ("psnr_vs_iter.png", "psnr_vs_time.png", "report.md"):
        assert (run / name).is_file(), name
    assert result["renders"] == []  # no snapshots in hand-made runs
    assert json.loads((run / "summary.json").read_text())["comparison"] == json.loads(json.dumps(result))
    md = (run / "report.md").read_text()
    assert "2.18x" in md and "never" in md and "not at 75" in md and "21.00 @50" in md


def test_comparison_of_a_fit_with_itself_is_one(hand_runs):
    _, scratch, _ = hand_runs
    log = load_fit_log(scratch)
    result = compare_logs({"a": log, "scratch": log}, baseline="scratch", method="a")
    assert result["speedup_iters"] == 1.0 and result["speedup_time"] == 1.0
    assert result["ahead_at_every_eval"] is False  # equal is not ahead
    with pytest.raises(ConfigError, match="baseline 'nope'"):
        compare_logs({"a": log}, baseline="nope")


def test_report_numbers_on_hand_made_logs(hand_runs, tmp_path):
    run, _, _ = hand_runs
    other = _write_fit(tmp_path / "run2", {25: 12.0, 50: 16.0, 100: 22.0}, 100, 0.05, init="meta", category="lamp",
                       init_load_s=0.5, route={"route": "meta", "category": None, "known_categories": ["chair"], "classify_s": 1.0})
    _write_fit(other / "compare" / "scratch", {25: 10.0, 50: 12.0, 100: 16.0}, 100, 0.05, category="lamp")
    report = write_report([run, other], tmp_path / "out")
    assert report["routing"]["n_scored"] == 2 and report["routing"]["accuracy"] == 1.0
    assert report["routing"]["known"]["n"] == 1 and report["routing"]["unknown"]["n"] == 1
    assert set(report["groups"]) == {"all", "category", "meta"}
    # run 2: scratch's final 16 dB is reached at its last evaluation (100); routed has 16 dB at 50 -> speedup 2
    meta_group = report["groups"]["meta"]
    assert meta_group["speedup"]["iters"]["mean"] == pytest.approx(2.0)
    first = 100 / (25 + 25 * 5 / 6)
    assert report["groups"]["all"]["speedup"]["iters"]["mean"] == pytest.approx((first + 2.0) / 2, abs=1e-4)
    assert report["groups"]["all"]["speedup"]["iters"]["geomean"] == pytest.approx((first * 2.0) ** 0.5, abs=1e-4)
    assert report["groups"]["all"]["speedup"]["n_ahead_at_every_eval"] == 1  # run 2 is ahead everywhere
    routed = report["groups"]["all"]["methods"]["routed"]
    assert routed["final_test_psnr_mean"] == pytest.approx(22.5) and routed["final_test_psnr_sd"] == pytest.approx(np.std([23, 22], ddof=1), abs=1e-4)
    # the iteration band: evaluations shared range [25, 100], run 1 has 75, run 2 is interpolated there (19 dB)
    band = routed["curves"]["iter"]
    assert band["x"] == [25, 50, 75, 100] and band["mean"] == [13.5, 18.5, pytest.approx((17.5 + 19.0) / 2), 22.5]
    assert report["groups"]["all"]["methods"]["meta"]["n_runs"] == 1
    # the wall-clock band is the optimisation-time band moved by what each fit spent before its first step
    timed = report["groups"]["meta"]["methods"]["routed"]["curves"]
    start = load_fit_log(other).start_s
    assert start == pytest.approx(1.5)
    assert timed["wall_s"]["x"] == pytest.approx([x + start for x in timed["time_s"]["x"]], abs=1e-3)
    assert timed["wall_s"]["mean"] == pytest.approx(timed["time_s"]["mean"], abs=1e-3)
    for name in ("report.md", "report.json", "psnr_vs_iter.png", "psnr_vs_time.png", "psnr_vs_iter_meta.png",
                 "psnr_vs_time_category.png"):
        assert (tmp_path / "out" / name).is_file(), name
    assert json.loads((tmp_path / "out" / "report.json").read_text()) == json.loads(json.dumps(report))


# ----- snapshots during a real fit ------------------------------------------------------------------

def _config(scene, seed=0, snapshot_iters=(0, 4, 8), iters=10):
    return RunConfig(scene=str(scene), backbone="grid", model=TINY_GRID, snapshot_iters=tuple(snapshot_iters),
                     fit=FitConfig(iters=iters, batch_rays=256, eval_every=4, checkpoint_every=0, seed=seed))


@pytest.fixture(scope="module")
def real_runs(tiny_scene, tmp_path_factory):
    """A 'routed' fit (seed 1) with its scratch baseline (seed 0) in compare/scratch, both with snapshots."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        run = tmp_path_factory.mktemp("report") / "run"
        run_fit(_config(tiny_scene, seed=1), run)
        run_fit(_config(tiny_scene, seed=0), run / "compare" / "scratch")
    finally:
        torch.set_num_threads(threads)
    summary = json.loads((run / "summary.json").read_text())
    summary["route"] = {"route": "category", "category": "spheres", "known_categories": ["spheres", "chairs"],
                        "confidence": 0.9, "probabilities": {"spheres": 0.9, "chairs": 0.1}}
    (run / "summary.json").write_text(json.dumps(summary))
    return run


def test_snapshots_written_at_the_asked_iterations_and_the_end(real_runs, tiny_scene):
    scene = load_scene(tiny_scene)
    views = scene.splits["test"][:2]
    snaps = read_snapshots(real_runs / "snapshots")
    assert sorted(snaps) == list(views)
    for v in views:
        assert sorted(snaps[v]) == [0, 4, 8, 10]  # 10: the final iteration
        assert (real_runs / "snapshots" / f"target_view_{v:03d}.png").is_file()
        target = iio.imread(real_runs / "snapshots" / f"target_view_{v:03d}.png")
        np.testing.assert_array_equal(target, to_uint8(scene.images[v].numpy()))
    summary = json.loads((real_runs / "summary.json").read_text())
    assert summary["snapshots"]["iters"] == [0, 4, 8, 10] and summary["snapshots"]["views"] == list(views)
    assert json.loads((real_runs / "config.json").read_text())["snapshot_iters"] == [0, 4, 8]


def test_snapshot_at_iteration_0_is_the_initial_model(real_runs, tiny_scene):
    from nerfmeta.fit.evaluate import render_view

    config = _config(tiny_scene, seed=1)
    scene = load_scene(tiny_scene)
    model, _, _ = build_initial_model(config, scene, torch.device("cpu"))
    view = scene.splits["test"][0]
    expected = to_uint8(render_view(model.eval(), scene, view, torch.ones(3)).rgb.numpy())
    np.testing.assert_array_equal(iio.imread(real_runs / "snapshots" / snapshot_name(0, view)), expected)
    later = iio.imread(real_runs / "snapshots" / snapshot_name(10, view))
    assert not np.array_equal(later, expected)


def test_snapshots_change_neither_the_fit_nor_its_time(tiny_scene, tmp_path, monkeypatch, real_runs):
    plain = tmp_path / "plain"
    run_fit(_config(tiny_scene, seed=1, snapshot_iters=()), plain)
    assert not (plain / "snapshots").exists()
    with_snaps = read_metrics(real_runs / "metrics.jsonl")
    without = read_metrics(plain / "metrics.jsonl")
    assert [(r["train_psnr"], r.get("test_psnr")) for r in with_snaps] == [(r["train_psnr"], r.get("test_psnr")) for r in without]

    delay = 0.5  # large beside a tiny-scene iteration even on a loaded machine (0.2 s flaked at load 10)
    real_render = snapshots_module.render_view

    def slow_render(*args, **kwargs):
        time.sleep(delay)
        return real_render(*args, **kwargs)

    monkeypatch.setattr(snapshots_module, "render_view", slow_render)
    slow = tmp_path / "slow"
    summary = run_fit(_config(tiny_scene, seed=1, snapshot_iters=(0, 2, 4), iters=6), slow)
    assert summary["snapshots"]["render_time_s"] >= 4 * 2 * delay  # iterations 0, 2, 4, 6; two views each
    records = read_metrics(slow / "metrics.jsonl")
    steps = np.diff([0.0] + [r["time_s"] for r in records])
    assert steps.max() < 2 * delay, steps  # no step carries a snapshot's two renders
    assert summary["time_s"] < summary["snapshots"]["render_time_s"] / 2  # the 8 renders are not in the fit's time


class _Kill(Exception):
    pass


def test_snapshots_of_a_resumed_fit_equal_an_uninterrupted_one(tiny_scene, tmp_path, real_runs):
    # the routed fit of real_runs, with checkpoints every 4 iterations, killed at 6 and resumed from 4
    config = dataclasses.replace(_config(tiny_scene, seed=1),
                                 fit=FitConfig(iters=10, batch_rays=256, eval_every=4, checkpoint_every=4, seed=1))
    killed = tmp_path / "killed"

    def kill_at_6(record, model, state):
        if record.iter == 6:
            raise _Kill

    with pytest.raises(_Kill):
        run_fit(config, killed, callbacks=[kill_at_6])
    view = load_scene(tiny_scene).splits["test"][0]
    assert sorted(read_snapshots(killed / "snapshots")[view]) == [0, 4]
    summary = run_fit(config, killed, resume=True)
    assert summary["snapshots"]["iters"] == [0, 4, 8, 10]
    for v, its in read_snapshots(real_runs / "snapshots").items():
        for it, path in its.items():
            np.testing.assert_array_equal(iio.imread(killed / "snapshots" / path.name), iio.imread(path), err_msg=path.name)


def test_snapshot_writer_restores_mode_and_computes_no_gradient(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene)
    model, _, _ = build_initial_model(_config(tiny_scene), scene, torch.device("cpu"))
    writer = SnapshotWriter(scene, [0], [3], tmp_path / "snaps", torch.ones(3))
    for mode in (True, False):
        model.train(mode)
        writer.write(7, model)
        assert model.training is mode
    assert all(p.grad is None for p in model.parameters())
    assert (tmp_path / "snaps" / snapshot_name(7, 0)).is_file()
    with pytest.raises(ConfigError, match=r"\[-1\]"):
        SnapshotWriter(scene, [0], [-1, 5], tmp_path / "snaps", torch.ones(3))
    with pytest.raises(ConfigError, match="views"):
        SnapshotWriter(scene, [scene.n_views], [5], tmp_path / "snaps", torch.ones(3))


# ----- comparison and report on real runs -----------------------------------------------------------

def test_comparison_of_real_runs_matches_their_logs(real_runs, tmp_path):
    out = tmp_path / "cmp"
    result = write_comparison(real_runs, {"scratch": real_runs / "compare" / "scratch"}, out, iters=(4, 8, 10, 20),
                              update_summary=False)
    routed = read_metrics(real_runs / "metrics.jsonl")
    scratch = read_metrics(real_runs / "compare" / "scratch" / "metrics.jsonl")
    tests = {r["iter"]: r["test_psnr"] for r in routed if "test_psnr" in r}
    assert sorted(tests) == [4, 8, 10]
    assert result["methods"]["routed"]["test_psnr_at_iter"] == {"4": tests[4], "8": tests[8], "10": tests[10], "20": None}
    scratch_final = json.loads((real_runs / "compare" / "scratch" / "summary.json").read_text())["test_psnr"]
    assert result["target_psnr"] == scratch_final == scratch[-1]["test_psnr"]
    base_tests = {r["iter"]: r["test_psnr"] for r in scratch if "test_psnr" in r}
    behind = [it for it in (4, 8, 10) if not tests[it] > base_tests[it]]
    assert result["not_ahead_at"] == behind and result["ahead_at_every_eval"] == (not behind)
    assert result["renders"] == [f"comparison_renders_view_{v:03d}.png" for v in sorted(read_snapshots(real_runs / "snapshots"))]
    for name in ("psnr_vs_iter.png", "psnr_vs_time.png", "report.md", *result["renders"]):
        assert (out / name).is_file(), name
    assert "comparison" not in json.loads((real_runs / "summary.json").read_text())
    assert "Route: **category** (spheres)" in (out / "report.md").read_text()


def test_report_cli_on_real_runs(real_runs, tmp_path, capsys):
    out = tmp_path / "report"
    plain = real_runs / "compare" / "scratch"  # a plain fit run is accepted too
    code = main(["report", str(real_runs), str(plain), "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert "routing accuracy 1/1" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert set(report["groups"]) == {"all", "category", "no route"}
    assert report["methods"] == ["routed", "scratch"]
    finals = [json.loads((p / "summary.json").read_text())["test_psnr"] for p in (real_runs, plain)]
    scratch = report["groups"]["all"]["methods"]["scratch"]
    assert scratch["n_runs"] == 2 and scratch["final_test_psnr_mean"] == pytest.approx(finals[1], abs=1e-4)
    assert report["groups"]["all"]["methods"]["routed"]["final_test_psnr_mean"] == pytest.approx(finals[0], abs=1e-4)
    assert report["runs"][0]["comparison"]["target_psnr"] == finals[1] and report["runs"][1]["comparison"] is None
    for name in ("report.md", "psnr_vs_iter.png", "psnr_vs_time.png", "psnr_vs_iter_category.png", "psnr_vs_time_no_route.png"):
        assert (out / name).is_file(), name


@pytest.mark.parametrize("make,needle", [
    (lambda p: p, "nope"),
    (lambda p: (p.mkdir(), (p / "summary.json").write_text("{}"), p)[-1], "metrics.jsonl"),
    (lambda p: (_write_fit(p, {10: 1.0}, 10, 0.1), (p / "compare" / "scratch").mkdir(parents=True), p)[-1],
     "compare/scratch"),
])
def test_report_bad_run_exits_2_naming_it(tmp_path, capsys, make, needle):
    run = make(tmp_path / "nope")
    code = main(["report", str(run), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and needle in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "out").exists()
