"""`nerfmeta sweep`: the CLI on a tiny scene, resuming, retrying killed trials once, outliers and fronts."""

from __future__ import annotations

import json

import pytest

from nerfmeta.cli import main
from nerfmeta.data.synthetic import write_tiny_scene
from nerfmeta.sweep.report import pareto_mask
from nerfmeta.sweep.spec import parse_spec
from nerfmeta.sweep.study import (completed, enqueue_retries, mad_outliers, open_storage, open_study, reconcile, slot_of,
                                  used_slots)

FIXED = {"iters": 8, "eval_every": 0, "checkpoint_every": 0, "coarse_iters": 3, "growth_steps": [], "num_voxels": 2000,
         "coarse_num_voxels": 500, "renders": 0}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    write_tiny_scene(root / "scene")
    return root


def test_mad_outliers_flags_only_far_repeats():
    assert mad_outliers([1.0, 1.1, 0.9, 5.0]) == [3]  # median 1.05, MAD 0.1: 5.0 is 39 MADs away
    assert mad_outliers([1.0, 1.1, 0.9, 1.2]) == []
    assert mad_outliers([1.0, 9.0]) == []  # two repeats: each is exactly one MAD from their median
    assert mad_outliers([2.0, 2.0, 2.0, 3.0]) == []  # MAD 0: no scale to judge by


def test_pareto_mask_of_a_hand_made_plane():
    # (cost, quality): (1, 10) and (2, 12) are the front; (2, 9) is beaten by (1, 10); (3, 12) by (2, 12)
    points = [(1.0, 10.0), (2.0, 12.0), (2.0, 9.0), (3.0, 12.0)]
    assert pareto_mask(points, maximise_y=True) == [True, True, False, False]
    assert pareto_mask(points, maximise_y=False) == [True, False, True, False]  # lower is better (LPIPS): (2, 9) joins


def test_killed_trials_are_retried_once_and_never_counted_twice(root, tmp_path):
    spec = parse_spec({"scenes": ["scene"], "search": {"batch_rays": {"values": [64, 128, 256]}}}, root)
    storage = open_storage(tmp_path, None)
    study = open_study(spec, storage)
    assert [t.user_attrs["slot"] for t in study.get_trials()] == ["p0", "p1", "p2"]
    first = study.ask()  # a worker takes p0 and is killed
    assert open_study(spec, storage).user_attrs["planned"] == 3  # a second start enqueues nothing more
    assert len(study.get_trials()) == 3
    assert reconcile(study, exclusive=True) == [first.number]
    assert enqueue_retries(study) == []  # idempotent: already retried
    trials = study.get_trials()
    assert sorted(slot_of(t) for t in trials if t.state.name != "FAIL") == ["p0", "p1", "p2"]
    assert used_slots(trials) == {"p0", "p1", "p2"}
    retry = [t for t in trials if t.state.name == "WAITING" and slot_of(t) == "p0"]
    assert len(retry) == 1 and retry[0].params == first.params and retry[0].user_attrs["retry"] == 1


def test_sweep_cli_runs_resumes_and_redraws(root, tmp_path, capsys):
    spec = root / "spec.yaml"
    spec.write_text(json.dumps({"scenes": ["scene"], "backbone": "grid", "fixed": FIXED,
                                "search": {"batch_rays": {"values": [64, 128], "default": 64}},
                                "objectives": {"test_psnr": "max", "time_s": "min", "peak_rss_mb": "min"}, "repeats": 1}))
    out = tmp_path / "sweep"
    assert main(["sweep", str(spec), "--out", str(out)]) == 0
    assert "trial 0 [p0] batch_rays=64" in capsys.readouterr().out
    for run in ("p0-r0", "p1-r0"):
        summary = json.loads((out / "trials" / run / "summary.json").read_text())
        measure = json.loads((out / "trials" / run / "sweep.json").read_text())
        assert summary["iters"] == 8 and measure["peak_rss_mb"] > 50
    report = (out / "report.md").read_text()
    assert "| p0 | 64 |" in report and "| p1 | 128 |" in report
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert len([p for p in pngs if p.startswith("pareto_")]) == 6 and "knob_batch_rays.png" in pngs
    stamp = (out / "trials" / "p0-r0" / "summary.json").stat().st_mtime_ns
    assert main(["sweep", str(spec), "--out", str(out)]) == 0  # the same command again: nothing left to run
    assert (out / "trials" / "p0-r0" / "summary.json").stat().st_mtime_ns == stamp
    (out / "report.md").unlink()
    assert main(["sweep", str(out), "--report"]) == 0
    assert (out / "report.md").read_text() == report
    study = open_study(parse_spec(json.loads(spec.read_text()), root), open_storage(out, None), create=False)
    assert sorted(slot_of(t) for t in completed(study)) == ["p0", "p1"]
    other = root / "other.json"
    other.write_text(json.dumps({"scenes": ["scene"], "search": {"batch_rays": {"values": [32]}}}))
    assert main(["sweep", str(other), "--out", str(out)]) == 2
    assert "another SPEC" in capsys.readouterr().err


def test_a_repeat_far_from_the_others_is_flagged_and_rerun_once(root, tmp_path, monkeypatch):
    import nerfmeta.sweep.study as study_module

    spec = parse_spec({"scenes": ["scene"], "search": {"batch_rays": {"values": [64]}}, "repeats": 3}, root)
    calls = []

    def fake_repeat(spec, out, name, scene, params, seed):
        calls.append(name)
        time_s = {"p0-r0": 1.0, "p0-r1": 1.1, "p0-r2": 9.0, "p0-r2.rerun": 1.2}[name]
        figures = {"test_psnr": 20.0, "time_s": time_s, "peak_rss_mb": 300.0, "wall_s": time_s + 1}
        return study_module.RepeatResult(str(tmp_path / name), seed, figures)

    monkeypatch.setattr(study_module, "run_repeat", fake_repeat)
    result = study_module.run_trial(spec, tmp_path, "p0", {"batch_rays": 64})
    assert calls == ["p0-r0", "p0-r1", "p0-r2", "p0-r2.rerun"]
    assert [(f["repeat"], f["figure"], f["value"], f["rerun"]) for f in result["flags"]] == [(2, "time_s", 9.0, 1.2)]
    assert result["figures"]["time_s"]["values"] == [1.0, 1.1, 1.2]
    assert result["figures"]["time_s"]["mean"] == pytest.approx(1.1)
    assert result["figures"]["test_lpips"] is None  # not reported: no figure rather than a made-up one


def test_two_workers_do_not_propose_the_same_configurations(root):
    import optuna

    from nerfmeta.sweep.study import distributions, make_sampler

    spec = parse_spec({"scenes": ["scene"], "search": {"lr_decay": {"float": [0.01, 0.5], "log": True}},
                       "sampler": "random", "n_trials": 4}, root)
    drawn = []
    for worker in (0, 1):
        study = optuna.create_study(sampler=make_sampler(spec, worker), directions=spec.directions)
        drawn.append([study.ask(distributions(spec)).params["lr_decay"] for _ in range(3)])
    assert not set(drawn[0]) & set(drawn[1])
