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
from nerfmeta.route import (BASELINES, PriorFacts, SceneFacts, classify_and_fit, decide_route, prior_facts, prior_checks,
                            scene_facts)
from nerfmeta.zoo import MANIFEST, load_zoo, resolve_zoo_path
from conftest import TINY_MODEL, TINY_ZOO

def _prediction(category: str, unknown: bool) -> dict:
    return {"category": category, "confidence": 0.8, "unknown": unknown, "probabilities": {"chair": 0.8, "mug": 0.2}, "views": 4,
            "score": {"name": "mahalanobis", "value": -3.0, "threshold": -2.0}}


# --- the decision (pure) -------------------------------------------------------------------------

BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
WHITE = (1.0, 1.0, 1.0)
FITS = SceneFacts(box=((-0.5, -0.6, -0.7), (0.5, 0.6, 0.7)), resolution=(16, 16), background=WHITE)
"""A scene every prior of :func:`_priors` applies to."""


def _priors(zoo, **changes) -> dict[str, PriorFacts]:
    """Hand-made facts for every prior of ``zoo``: nerf, the canonical box, 16 px, white (``changes`` replace fields)."""
    return {e.name: PriorFacts(**{"name": e.name, "backbone": "nerf", "box": BOX, "resolution": 16, "background": WHITE, **changes})
            for e in zoo.entries if e.kind in ("category", "meta")}


def _decide(prediction, zoo, *, backbone="nerf", scene=FITS, freeze=1, **prior_changes):
    return decide_route(prediction, zoo, freeze, backbone=backbone, scene=scene, priors=_priors(zoo, **prior_changes) if zoo else {})


def test_no_zoo_routes_to_scratch_and_says_so():
    route = _decide(_prediction("chair", False), None, backbone="grid", freeze=2)
    assert (route.route, route.init, route.freeze, route.backbone) == ("scratch", "scratch", 0, "grid")
    assert "no model zoo" in route.reason and route.checks == ()


def test_known_category_goes_to_its_model_with_frozen_layers_and_unknown_to_meta(zoo_dir: Path):
    zoo = load_zoo(zoo_dir)
    known = _decide(_prediction("chair", False), zoo)
    assert known.route == "category" and known.init == f"category:{zoo.categories['chair'].path}" and known.freeze == 1
    assert known.known_categories == ("chair", "mug") and known.category == "chair" and known.backbone == "nerf"
    assert [(c.name, c.prior, c.passed) for c in known.checks] == [
        ("box", "category/chair", True), ("resolution", "category/chair", True), ("background", "category/chair", True)]
    unknown = _decide(_prediction("chair", True), zoo)
    assert unknown.route == "meta" and unknown.init == f"meta:{zoo.meta.path}" and unknown.freeze == 0
    assert "unknown category" in unknown.reason and {c.prior for c in unknown.checks} == {"meta"}
    # a category the classifier names but the zoo has no model for also goes to meta
    other = _decide({**_prediction("lamp", False), "probabilities": {"lamp": 1.0}}, zoo)
    assert other.route == "meta"


def test_a_zoo_of_nerf_priors_and_a_grid_fit_route_to_the_scratch_grid_with_the_reason(zoo_dir: Path):
    zoo = load_zoo(zoo_dir)
    route = _decide(_prediction("chair", False), zoo, backbone="grid", scene=None)
    assert (route.route, route.init, route.freeze, route.backbone) == ("scratch", "scratch", 0, "grid")
    assert "holds no grid prior" in route.reason and "--backbone nerf" in route.reason
    assert [c.as_json() for c in route.checks] == [{"name": "backbone", "prior": "zoo", "passed": False,
                                                   "figures": {"asked": "grid", "zoo": "nerf"},
                                                   "note": "the zoo holds nerf priors only; this fit is a grid fit"}]
    assert route.as_json()["checks"][0]["figures"] == {"asked": "grid", "zoo": "nerf"}


def test_a_scene_outside_the_priors_box_routes_to_scratch(zoo_dir: Path):
    zoo = load_zoo(zoo_dir)
    big = SceneFacts(box=((-1.5, -1.0, -1.0), (1.0, 1.0, 1.0)), resolution=(16, 16), background=WHITE)
    route = _decide(_prediction("chair", False), zoo, scene=big)
    assert (route.route, route.init, route.backbone) == ("scratch", "scratch", "nerf")
    failed = [(c.prior, c.name) for c in route.checks if not c.passed]
    assert failed == [("category/chair", "box"), ("meta", "box")]  # both candidates tried, in order
    box = route.checks[0]
    assert box.figures == {"scene_box": [[-1.5, -1.0, -1.0], [1.0, 1.0, 1.0]], "prior_box": [list(BOX[0]), list(BOX[1])]}
    assert "is not inside the prior's box" in route.reason
    # inside by less than the tolerance counts as inside
    edge = SceneFacts(box=((-1.0005, -1.0, -1.0), (1.0, 1.0, 1.0)), resolution=(16, 16), background=WHITE)
    assert _decide(_prediction("chair", False), zoo, scene=edge).route == "category"


@pytest.mark.parametrize("resolution, background, failing", [
    ((16, 25), WHITE, "resolution"),       # 25 px > 1.5 x 16
    ((10, 10), WHITE, "resolution"),       # 10 px < 16 / 1.5
    ((24, 12), WHITE, None),               # 24 px = 1.5 x 16: inside
    ((16, 16), (0.0, 0.0, 0.0), "background"),
    ((16, 16), None, "background"),        # opaque images (a photograph)
])
def test_resolution_and_background_outside_the_zoos_route_to_scratch(zoo_dir, resolution, background, failing):
    zoo = load_zoo(zoo_dir)
    scene = SceneFacts(box=FITS.box, resolution=resolution, background=background)
    route = _decide(_prediction("chair", False), zoo, scene=scene)
    if failing is None:
        assert route.route == "category" and all(c.passed for c in route.checks)
    else:
        assert route.route == "scratch"
        assert {c.name for c in route.checks if not c.passed} == {failing}


def test_a_scene_no_prior_applies_to_is_not_classified(zoo_dir: Path, tiny_scene: Path, monkeypatch):
    """A photograph, or a 32 px scene outside the box of a zoo trained at 16 px: no prior can apply, so the classifier is
    not asked (its answer could not change the route) and the route says why, with every prior's checks."""
    import nerfmeta.route as route_module

    zoo = load_zoo(zoo_dir)
    photo = SceneFacts(box=FITS.box, resolution=(16, 16), background=None)
    assert not route_module.any_prior_applies(_priors(zoo), photo) and route_module.any_prior_applies(_priors(zoo), FITS)
    route = decide_route(None, zoo, 1, backbone="nerf", scene=photo, priors=_priors(zoo), unclassified=True)
    assert route.route == "scratch" and route.category is None and "without classifying it" in route.reason
    assert "opaque (no alpha): not an object scene like the zoo's (every prior)" in route.reason  # each note once
    assert {c.prior for c in route.checks} == set(_priors(zoo)) and not any(c.passed for c in route.checks if c.name == "background")

    def no_classifying(*args, **kwargs):
        raise AssertionError("the classifier was asked")

    monkeypatch.setattr(route_module, "classify_scene", no_classifying)
    routed = route_module.route_scene(RunConfig(scene=str(tiny_scene), backbone="nerf"), zoo, 1)
    assert routed.route == "scratch" and "without classifying it" in routed.reason
    assert "resolution" in {c.name for c in routed.checks if not c.passed}  # 32 px views, a 16 px zoo


def test_a_category_model_that_does_not_apply_falls_back_to_the_meta_init_that_does(zoo_dir: Path):
    zoo = load_zoo(zoo_dir)
    priors = _priors(zoo)
    priors["category/chair"] = PriorFacts("category/chair", "nerf", ((-0.1,) * 3, (0.1,) * 3), 16, WHITE)
    route = decide_route(_prediction("chair", False), zoo, 1, backbone="nerf", scene=FITS, priors=priors)
    assert route.route == "meta" and route.freeze == 0 and "category/chair: the scene's object box is not inside" in route.reason


def test_prior_checks_without_recorded_facts_fail_safe():
    checks = prior_checks(PriorFacts("meta", "nerf", None, None, None), FITS)
    assert [(c.name, c.passed) for c in checks] == [("box", False), ("resolution", False), ("background", False)]


def test_prior_facts_of_the_zoo_are_read_from_its_files(zoo_dir: Path, new_scenes):
    zoo = load_zoo(zoo_dir)
    facts = prior_facts(zoo, zoo.meta)
    assert facts.backbone == "nerf" and facts.resolution == 16 and facts.background == WHITE
    assert facts.box is not None and all(lo < hi for lo, hi in zip(*facts.box))
    scene = scene_facts(RunConfig(scene=str(new_scenes["known"]), backbone="nerf"))
    assert scene.resolution == (16, 16) and scene.background == WHITE
    assert all(c.passed for c in prior_checks(facts, scene))  # the zoo's own kind of scene


# --- the zoo ---------------------------------------------------------------------------------------


def test_tiny_zoo_lists_every_file_with_its_hash(zoo_dir: Path):
    zoo = load_zoo(zoo_dir)
    assert {e.name for e in zoo.entries} == {"classifier", "category/chair", "category/mug", "meta", "occupancy"}
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
    scratch-nerf baseline differs from the routed fit only in its start."""
    import nerfmeta.route as route_module

    monkeypatch.setattr(route_module, "classify_scene", lambda scene, zoo, background: _prediction(*answer))
    out = tmp_path / which
    summary = classify_and_fit(_config(new_scenes[which]), out, zoo=load_zoo(zoo_dir), compare=("scratch-nerf",))
    assert summary["route"]["route"] == route and summary["init"] == route
    saved = json.loads((out / "summary.json").read_text())
    assert saved["route"] == summary["route"]
    routed_cfg = json.loads((out / "config.json").read_text())
    base_cfg = json.loads((out / "compare" / "scratch-nerf" / "config.json").read_text())
    assert base_cfg["init"] == "scratch" and base_cfg["freeze"] == 0
    start = ("init", "freeze", "init_kind", "init_path", "init_sha256", "frozen_layers", "route")
    assert {k: v for k, v in base_cfg.items() if k not in start} == {k: v for k, v in routed_cfg.items() if k not in start}
    assert routed_cfg["route"] == summary["route"] and "route" not in base_cfg
    if route == "category":
        assert routed_cfg["freeze"] == 1 and len(routed_cfg["frozen_layers"]) == 1
    comparison = summary["comparison"]
    assert comparison is not None and comparison["baseline"] == "scratch-nerf"
    for name, folder in (("scratch-nerf", out / "compare" / "scratch-nerf"), (f"routed ({route})", out)):
        records = read_metrics(folder / "metrics.jsonl")
        final = json.loads((folder / "summary.json").read_text())["test_psnr"]
        assert records[-1]["test_psnr"] == pytest.approx(final, abs=1e-3)
    assert (out / "psnr_vs_iter.png").is_file() and (out / "psnr_vs_time.png").is_file()


def test_compare_scratch_is_the_tuned_grid_on_a_wall_clock_axis_that_includes_classification(zoo_dir, new_scenes, tmp_path,
                                                                                              monkeypatch):
    """--compare scratch fits the voxel grid with its tuned defaults (not the prior's MLP); the routed fit's time axis
    starts after its classification and the loading of its start; scratch-nerf stays as a second baseline."""
    import time

    import nerfmeta.route as route_module

    def slow_classifier(scene, zoo, background):
        time.sleep(0.3)  # a classification that takes time: it must show on the routed fit's wall-clock axis
        return _prediction("chair", False)

    monkeypatch.setattr(route_module, "classify_scene", slow_classifier)
    out = tmp_path / "run"
    summary = classify_and_fit(_config(new_scenes["known"]), out, zoo=load_zoo(zoo_dir), compare=("scratch", "scratch-nerf"))
    route = summary["route"]
    assert route["route"] == "category" and route["classify_s"] >= 0.3 and summary["init_load_s"] > 0
    grid = json.loads((out / "compare" / "scratch" / "config.json").read_text())
    defaults = FitConfig()
    assert grid["backbone"] == "grid" and grid["init"] == "scratch"
    assert grid["fit"]["batch_rays"] == defaults.batch_rays and grid["fit"]["iters"] == defaults.iters
    wall = route["classify_s"] + summary["init_load_s"] + summary["time_s"]
    assert grid["fit"]["time_budget_s"] == pytest.approx(max(round(wall, 1), 0.1))  # the routed fit's whole wall-clock time
    nerf = json.loads((out / "compare" / "scratch-nerf" / "config.json").read_text())
    assert nerf["backbone"] == "nerf" and nerf["fit"] == json.loads((out / "config.json").read_text())["fit"]
    comparison = summary["comparison"]
    assert comparison["baseline"] == "scratch" and comparison["baseline_backbone"] == "grid" and "wall-clock" in comparison["axis"]
    routed = comparison["methods"]["routed"]
    assert routed["classify_s"] == pytest.approx(route["classify_s"], abs=1e-3)
    assert routed["start_s"] == pytest.approx(route["classify_s"] + summary["init_load_s"], abs=2e-3)
    assert routed["wall_s"] == pytest.approx(summary["time_s"] + routed["start_s"], abs=2e-3)
    assert routed["time_s"] == summary["time_s"]  # the fit loop's own time is unchanged
    assert comparison["methods"]["scratch"]["classify_s"] == 0.0 and set(comparison["methods"]) == {"routed", "scratch", "scratch-nerf"}
    if routed["reached"]:
        assert routed["reach_wall_s"] == pytest.approx(routed["reach_time_s"] + routed["start_s"], abs=1e-3)
    assert comparison["headline"][0].startswith("baseline scratch: the voxel grid from scratch with its tuned defaults")
    assert "wall-clock" in comparison["headline"][0]
    report = (out / "report.md").read_text()
    assert "Baseline: **scratch**, a grid fit from scratch" in report and "wall-clock" in report


def test_fit_backbone_grid_with_a_zoo_is_no_longer_refused(tiny_scene: Path, tmp_path: Path, zoo_dir: Path, capsys):
    out = tmp_path / "grid"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--zoo", str(zoo_dir), "--backbone", "grid", "--iters", "3",
                 "--batch-rays", "32", "--set", "coarse_iters=2", "--set", "growth_steps=[1]"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["backbone"] == "grid" and summary["init"] == "scratch" and summary["iters"] == 3  # not the zoo's 6
    assert summary["route"]["route"] == "scratch" and summary["route"]["checks"][0]["name"] == "backbone"
    assert "holds no grid prior" in capsys.readouterr().out
    # no --backbone: the default backbone is the grid too, so a zoo of nerf priors gives the scratch grid
    out = tmp_path / "default"
    assert main(["fit", str(tiny_scene), "--out", str(out), "--zoo", str(zoo_dir), "--iters", "3", "--batch-rays", "32",
                 "--set", "coarse_iters=2", "--set", "growth_steps=[1]"]) == 0
    assert json.loads((out / "summary.json").read_text())["backbone"] == "grid"


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
    summary = classify_and_fit(_config(new_scenes["known"]), out, zoo=load_zoo(zoo_dir), compare=("scratch-nerf",))
    routed_writes = [p for p in writes if p.name == "summary.json" and p.parent.name != "scratch-nerf"]
    assert len(routed_writes) == 1
    saved = json.loads((out / "summary.json").read_text())
    assert saved == summary and {"route", "comparison", "test_psnr", "iters"} <= set(saved)
    assert saved["comparison"]["headline"]


def test_real_classifier_route_matches_its_answer(zoo_dir, new_scenes, tmp_path, capsys):
    """End to end through the CLI with the zoo's own classifier: whatever it answers, the route is the decision for it."""
    out = tmp_path / "run"
    code = main(["fit", str(new_scenes["known"]), "--out", str(out), "--zoo", str(zoo_dir), "--backbone", "nerf",
                 "--compare", "scratch-nerf"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    route = summary["route"]
    zoo = load_zoo(zoo_dir)
    expected = decide_route({k: route[k] for k in ("category", "confidence", "unknown", "probabilities", "views", "score")},
                            zoo, 1, backbone="nerf", scene=scene_facts(RunConfig(scene=str(new_scenes["known"]), backbone="nerf")),
                            priors={e.name: prior_facts(zoo, e) for e in zoo.entries if e.kind in ("category", "meta")})
    assert route["route"] == expected.route and route["init"] == expected.init
    assert route["views"] == 4  # training views only: the test views are the fit's evaluation
    assert f"route: {route['route']}" in capsys.readouterr().out
    assert summary["iters"] == TINY_ZOO.fit_iters  # the zoo's fit settings


def test_classify_without_a_classifier_asks_the_zoos_and_without_a_zoo_says_what_to_pass(zoo_dir, new_scenes, monkeypatch,
                                                                                          capsys):
    scene = str(new_scenes["known"])
    assert main(["classify", scene, "--classifier", str(zoo_dir / "classifier")]) == 0
    direct = json.loads(capsys.readouterr().out)
    assert main(["classify", scene, "--zoo", str(zoo_dir)]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == direct and "the model zoo's classifier" in err
    monkeypatch.setenv("NERFMETA_ZOO", str(zoo_dir))  # what the shipped zoo is to a user
    assert main(["classify", scene]) == 0 and json.loads(capsys.readouterr().out) == direct
    # the zoo's files are inputs: --json-out never replaces one of them
    manifest = (zoo_dir / MANIFEST).read_bytes()
    assert main(["classify", scene, "--json-out", str(zoo_dir / MANIFEST)]) == 2
    assert "would replace a file of the input" in capsys.readouterr().err and (zoo_dir / MANIFEST).read_bytes() == manifest
    monkeypatch.setenv("NERFMETA_ZOO", "none")
    assert main(["classify", scene]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--classifier DIR" in err[0] and "--zoo DIR" in err[0]


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
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "c"), "--zoo", str(zoo_dir), "--freeze", "1"]) == 2  # grid: no prior
    assert not any((tmp_path / n).exists() for n in "abc")
    assert set(BASELINES) == {"scratch", "scratch-nerf"}


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
        classify_and_fit(config, out, zoo=load_zoo(zoo_dir), compare=("scratch-nerf",), callbacks_for=_kill_at("scratch-nerf", 2))
    assert (out / "compare" / "scratch-nerf" / "config.json").is_file()
    assert not (out / "compare" / "scratch-nerf" / "checkpoint.safetensors").exists() and not (out / "summary.json").exists()
    summary = classify_and_fit(config, out, zoo=load_zoo(zoo_dir), compare=("scratch-nerf",), resume=True)
    assert summary["comparison"]["headline"] and summary["iters"] == 6
    assert [r["iter"] for r in read_metrics(out / "compare" / "scratch-nerf" / "metrics.jsonl")] == list(range(1, 7))


def test_resume_without_init_resumes_a_run_made_with_an_explicit_init(tiny_scene: Path, tmp_path: Path):
    out = tmp_path / "run"
    args = ["--iters", "4", "--batch-rays", "32", "--checkpoint-every", "2", "--set", "coarse_iters=2", "--set", "growth_steps=[1]"]
    assert main(["fit", str(tiny_scene), "--out", str(out), "--init", "scratch", *args]) == 0
    # --init defaults to auto; the run's config.json holds no route, so this is a plain resume of its own init
    assert main(["fit", str(tiny_scene), "--out", str(out), "--resume"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["init"] == "scratch" and "route" not in summary and summary["iters"] == 4
