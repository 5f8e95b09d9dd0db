"""Classify-and-fit: the route decision, a real tiny zoo built here, hash checks, and `nerfmeta fit --init auto`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from nerfmeta.cli import main
from nerfmeta.collection.generate import load_collection
from nerfmeta.errors import ConfigError
from nerfmeta.fit.loop import FitConfig
from nerfmeta.fit.run import RunConfig, read_metrics
from nerfmeta.route import classify_and_fit, decide_route
from nerfmeta.zoo import MANIFEST, load_zoo, resolve_zoo_path
from conftest import TINY_MODEL, TINY_ZOO

def _prediction(category: str, unknown: bool) -> dict:
    return {"category": category, "confidence": 0.8, "unknown": unknown, "probabilities": {"chair": 0.8, "mug": 0.2}, "views": 4,
            "score": {"name": "mahalanobis", "value": -3.0, "threshold": -2.0}}


# --- the decision (pure) -------------------------------------------------------------------------


def test_no_zoo_routes_to_scratch_and_says_so():
    route = decide_route(_prediction("chair", False), None, freeze=2)
    assert (route.route, route.init, route.freeze) == ("scratch", "scratch", 0)
    assert "no model zoo" in route.reason


def test_known_category_goes_to_its_model_with_frozen_layers_and_unknown_to_meta(zoo_dir: Path):
    zoo = load_zoo(zoo_dir)
    known = decide_route(_prediction("chair", False), zoo, freeze=1)
    assert known.route == "category" and known.init == f"category:{zoo.categories['chair'].path}" and known.freeze == 1
    assert known.known_categories == ("chair", "mug") and known.category == "chair"
    unknown = decide_route(_prediction("chair", True), zoo, freeze=1)
    assert unknown.route == "meta" and unknown.init == f"meta:{zoo.meta.path}" and unknown.freeze == 0
    assert "unknown category" in unknown.reason
    # a category the classifier names but the zoo has no model for also goes to meta
    other = decide_route({**_prediction("lamp", False), "probabilities": {"lamp": 1.0}}, zoo, freeze=1)
    assert other.route == "meta"


# --- the zoo ---------------------------------------------------------------------------------------


def test_tiny_zoo_lists_every_file_with_its_hash(zoo_dir: Path):
    zoo = load_zoo(zoo_dir)
    assert {e.name for e in zoo.entries} == {"classifier", "category/chair", "category/mug", "meta"}
    doc = json.loads((zoo_dir / MANIFEST).read_text())
    assert doc["fit"]["backbone"] == "nerf" and doc["fit"]["model"] == TINY_MODEL and doc["fit"]["freeze"] == 1
    assert doc["known_categories"] == ["chair", "mug"] and doc["unseen_categories"] == ["vase"]
    for entry in doc["entries"]:
        assert set(entry["files"]) >= {"model.safetensors"}
        assert entry["bytes"] == sum((zoo_dir / entry["path"] / f).stat().st_size for f in entry["files"])
    classifier = json.loads((zoo_dir / "classifier" / "classifier.json").read_text())
    assert classifier["weights"]["dtype"] == "float16"


def test_zoo_with_a_changed_file_is_refused_naming_it(zoo_dir: Path, tmp_path: Path, tiny_scene: Path, capsys):
    bad = Path(shutil.copytree(zoo_dir, tmp_path / "zoo"))
    weights = bad / "category" / "mug" / "model.safetensors"
    data = bytearray(weights.read_bytes())
    data[-1] ^= 0xFF
    weights.write_bytes(bytes(data))
    with pytest.raises(ConfigError, match=r"category/mug/model\.safetensors: SHA-256"):
        load_zoo(bad)
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "run"), "--zoo", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model.safetensors" in err[0]
    assert not (tmp_path / "run").exists()
    (bad / MANIFEST).write_text("{not json")
    with pytest.raises(ConfigError, match="manifest.json: not readable JSON"):
        load_zoo(bad)


def test_zoo_path_resolution(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    assert resolve_zoo_path("none") is None
    assert resolve_zoo_path(tmp_path) == tmp_path
    monkeypatch.setenv("NERFMETA_ZOO", str(tmp_path))
    assert resolve_zoo_path(None) == tmp_path
    monkeypatch.setenv("NERFMETA_ZOO", "none")
    assert resolve_zoo_path(None) is None


# --- classify-and-fit ------------------------------------------------------------------------------


def _config(scene: Path) -> RunConfig:
    return RunConfig(scene=str(scene), backbone="nerf", model=TINY_MODEL, fit=FitConfig(iters=6, batch_rays=64, eval_every=3,
                                                                                      checkpoint_every=0))


@pytest.mark.parametrize("which, answer, route", [("known", ("chair", False), "category"), ("unseen", ("chair", True), "meta")])
def test_routed_fit_with_scratch_comparison(zoo_dir, new_scenes, tmp_path, monkeypatch, which, answer, route):
    """The route follows the classifier's answer (pinned here: a classifier trained for seconds guesses), and the
    baseline differs from the routed fit only in its start."""
    import nerfmeta.route as route_module

    monkeypatch.setattr(route_module, "classify_scene", lambda scene, zoo, background: _prediction(*answer))
    out = tmp_path / which
    summary = classify_and_fit(_config(new_scenes[which]), out, zoo=load_zoo(zoo_dir), compare=("scratch",))
    assert summary["route"]["route"] == route and summary["init"] == route
    saved = json.loads((out / "summary.json").read_text())
    assert saved["route"] == summary["route"]
    routed_cfg = json.loads((out / "config.json").read_text())
    base_cfg = json.loads((out / "compare" / "scratch" / "config.json").read_text())
    assert base_cfg["init"] == "scratch" and base_cfg["freeze"] == 0
    start = ("init", "freeze", "init_kind", "init_path", "init_sha256", "frozen_layers", "route")
    assert {k: v for k, v in base_cfg.items() if k not in start} == {k: v for k, v in routed_cfg.items() if k not in start}
    assert routed_cfg["route"] == summary["route"] and "route" not in base_cfg
    if route == "category":
        assert routed_cfg["freeze"] == 1 and len(routed_cfg["frozen_layers"]) == 1
    comparison = summary["comparison"]
    assert comparison is not None
    for name, folder in (("scratch", out / "compare" / "scratch"), (f"routed ({route})", out)):
        records = read_metrics(folder / "metrics.jsonl")
        final = json.loads((folder / "summary.json").read_text())["test_psnr"]
        assert records[-1]["test_psnr"] == pytest.approx(final, abs=1e-3)
    assert (out / "psnr_vs_iter.png").is_file() and (out / "psnr_vs_time.png").is_file()


def test_a_routed_fit_writes_its_summary_once_with_route_and_comparison(zoo_dir, new_scenes, tmp_path, monkeypatch):
    """summary.json of a routed fit is assembled in memory and written once, when the comparison is known."""
    import nerfmeta.io as io_module
    import nerfmeta.route as route_module

    monkeypatch.setattr(route_module, "classify_scene", lambda scene, zoo, background: _prediction("chair", False))
    writes: list[Path] = []
    real = io_module.write_bytes_atomic

    def counting(path, data):
        writes.append(Path(path))
        real(path, data)

    monkeypatch.setattr(io_module, "write_bytes_atomic", counting)
    out = tmp_path / "routed"
    summary = classify_and_fit(_config(new_scenes["known"]), out, zoo=load_zoo(zoo_dir), compare=("scratch",))
    routed_writes = [p for p in writes if p.name == "summary.json" and p.parent.name != "scratch"]
    assert len(routed_writes) == 1
    saved = json.loads((out / "summary.json").read_text())
    assert saved == summary and {"route", "comparison", "test_psnr", "iters"} <= set(saved)
    assert saved["comparison"]["headline"]


def test_real_classifier_route_matches_its_answer(zoo_dir, new_scenes, tmp_path, capsys):
    """End to end through the CLI with the zoo's own classifier: whatever it answers, the route is the decision for it."""
    out = tmp_path / "run"
    code = main(["fit", str(new_scenes["known"]), "--out", str(out), "--zoo", str(zoo_dir), "--compare", "scratch"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    route = summary["route"]
    expected = decide_route({k: route[k] for k in ("category", "confidence", "unknown", "probabilities", "views", "score")},
                            load_zoo(zoo_dir), freeze=1)
    assert route["route"] == expected.route and route["init"] == expected.init
    assert route["views"] == 4  # training views only: the test views are the fit's evaluation
    assert f"route: {route['route']}" in capsys.readouterr().out
    assert summary["iters"] == TINY_ZOO.fit_iters  # the zoo's fit settings


def test_auto_without_zoo_fits_from_scratch(tiny_scene: Path, tmp_path: Path, capsys):
    out = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--iters", "3", "--batch-rays", "32", "--set", "coarse_iters=2",
                 "--set", "growth_steps=[1]"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["route"]["route"] == "scratch" and summary["init"] == "scratch"
    assert "no model zoo" in capsys.readouterr().out


def test_compare_needs_auto_and_a_known_baseline(tiny_scene: Path, tmp_path: Path, zoo_dir: Path):
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "a"), "--init", "scratch", "--compare", "scratch"]) == 2
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "b"), "--zoo", str(zoo_dir), "--compare", "grid"]) == 2
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "c"), "--zoo", str(zoo_dir), "--backbone", "grid"]) == 2
    assert not any((tmp_path / n).exists() for n in "abc")


class _Killed(Exception):
    pass


def _kill_at(fit_name: str, iteration: int):
    """A ``callbacks_for`` that raises :class:`_Killed` at ``iteration`` of the fit ``fit_name`` (a kill)."""
    def callbacks_for(name):
        def callback(record, model, state):
            if name == fit_name and record.iter == iteration:
                raise _Killed
        return [callback]
    return callbacks_for


def test_auto_fit_killed_during_the_routed_fit_resumes_on_the_recorded_route(zoo_dir, new_scenes, tmp_path, monkeypatch):
    import nerfmeta.route as route_module

    monkeypatch.setattr(route_module, "classify_scene", lambda scene, zoo, background: _prediction("chair", False))
    config = RunConfig(scene=str(new_scenes["known"]), backbone="nerf", model=TINY_MODEL,
                       fit=FitConfig(iters=6, batch_rays=64, eval_every=3, checkpoint_every=2))
    out = tmp_path / "run"
    with pytest.raises(_Killed):
        classify_and_fit(config, out, zoo=load_zoo(zoo_dir), callbacks_for=_kill_at("routed", 5))
    assert json.loads((out / "config.json").read_text())["route"]["route"] == "category"
    # resuming must continue the recorded route, not ask the classifier again
    monkeypatch.setattr(route_module, "classify_scene", lambda *a: pytest.fail("resume asked the classifier again"))
    summary = classify_and_fit(config, out, zoo=load_zoo(zoo_dir), resume=True)
    assert summary["route"]["route"] == "category" and summary["init"] == "category" and summary["iters"] == 6
    assert json.loads((out / "route.json").read_text())["route"] == "category"


def test_a_baseline_killed_before_its_first_checkpoint_is_started_again_on_resume(zoo_dir, new_scenes, tmp_path,
                                                                                   monkeypatch):
    import nerfmeta.route as route_module

    monkeypatch.setattr(route_module, "classify_scene", lambda scene, zoo, background: _prediction("chair", False))
    config = RunConfig(scene=str(new_scenes["known"]), backbone="nerf", model=TINY_MODEL,
                       fit=FitConfig(iters=6, batch_rays=64, eval_every=3, checkpoint_every=4))
    out = tmp_path / "run"
    with pytest.raises(_Killed):
        classify_and_fit(config, out, zoo=load_zoo(zoo_dir), compare=("scratch",), callbacks_for=_kill_at("scratch", 2))
    assert (out / "compare" / "scratch" / "config.json").is_file()
    assert not (out / "compare" / "scratch" / "checkpoint.safetensors").exists() and not (out / "summary.json").exists()
    summary = classify_and_fit(config, out, zoo=load_zoo(zoo_dir), compare=("scratch",), resume=True)
    assert summary["comparison"]["headline"] and summary["iters"] == 6
    assert [r["iter"] for r in read_metrics(out / "compare" / "scratch" / "metrics.jsonl")] == list(range(1, 7))


def test_resume_without_init_resumes_a_run_made_with_an_explicit_init(tiny_scene: Path, tmp_path: Path):
    out = tmp_path / "run"
    args = ["--iters", "4", "--batch-rays", "32", "--checkpoint-every", "2", "--set", "coarse_iters=2", "--set", "growth_steps=[1]"]
    assert main(["fit", str(tiny_scene), "--out", str(out), "--init", "scratch", *args]) == 0
    # --init defaults to auto; the run's config.json holds no route, so this is a plain resume of its own init
    assert main(["fit", str(tiny_scene), "--out", str(out), "--resume"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["init"] == "scratch" and "route" not in summary and summary["iters"] == 4
