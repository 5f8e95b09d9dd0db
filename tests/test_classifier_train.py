"""classifier.train on a tiny generated collection, and the two CLI commands end to end."""

from __future__ import annotations

import copy
import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from classifier.config import CLASS_SCORE_TRAIN_SCENES, DEFAULT_SCORE, NO_AUGMENT, SCORES, TrainConfig
from classifier.data import chimera_partners, chimera_views, composite, load_view_set, normalize
from classifier.inputs import read_scene_views
from classifier.model import build_model
from classifier.store import CURVE_FILE, HISTORY_FILE, META_FILE, WEIGHTS_FILE, classify_views, load_classifier
from classifier.train import (fewest_scenes_per_class, fit_network, lr_factor, plan_splits, select_score, train_classifier,
                              uniform_cross_entropy)
from nerfmeta.cli import main
from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection
from nerfmeta.errors import ConfigError

TINY = TrainConfig(input_size=16, batch_size=4, epochs=1, augment=NO_AUGMENT)


@pytest.fixture(scope="module")
def collection(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 categories x 3 scenes (one train, one val, one test each), 4 + 1 views of 16 x 16."""
    config = CollectionConfig(
        categories=("airplane", "chair", "mug"), scenes_per_category=3, views=4, test_views=1, resolution=16,
        val_fraction=0.34, test_fraction=0.34,
    )
    path = generate_collection(config, tmp_path_factory.mktemp("classifier") / "coll")
    return path.parent


def test_plan_splits_uses_train_scenes_and_keeps_holdout_out_of_calibration(collection: Path):
    splits = plan_splits(load_collection(collection), ("airplane",))
    assert splits.categories == ("chair", "mug")
    assert {r.category for r in splits.train} == {"chair", "mug"} and all(r.split == "train" for r in splits.train)
    assert {r.category for r in splits.val} == {"chair", "mug"} and all(r.split == "val" for r in splits.val)
    assert [r.category for r in splits.holdout_val] == ["airplane"]
    with pytest.raises(ConfigError, match="not in the collection"):
        plan_splits(load_collection(collection), ("sofa",))
    with pytest.raises(ConfigError, match="need at least 2"):
        plan_splits(load_collection(collection), ("airplane", "chair"))


def test_lr_factor_warms_up_then_decays_to_zero():
    assert lr_factor(0.0, 0.2) < 0.01
    assert lr_factor(0.2, 0.2) == pytest.approx(1.0)
    assert lr_factor(0.6, 0.2) == pytest.approx(0.5)
    assert lr_factor(1.0, 0.2) == pytest.approx(0.0, abs=1e-12)
    values = [lr_factor(p / 100, 0.2) for p in range(20, 101)]
    assert all(a >= b for a, b in zip(values, values[1:]))


def test_auto_score_picks_the_best_validation_auroc_else_the_default():
    with_holdout = {"holdout_val_scenes": 8, "scores": {"msp": {"holdout_val_auroc": 0.9}, "energy": {"holdout_val_auroc": 0.97},
                               "mahalanobis": {"holdout_val_auroc": 0.95}, "class_mahalanobis": {"holdout_val_auroc": 0.96}}}
    assert select_score("auto", with_holdout)[0] == "energy"
    tie = {"holdout_val_scenes": 8, "scores": {k: {"holdout_val_auroc": 0.9} for k in SCORES if k != "fused"}}
    assert select_score("auto", tie)[0] == DEFAULT_SCORE == "combined"
    # with a reference network (``fused`` calibrated) the fallback is fused
    tie_fused = {"holdout_val_scenes": 8, "scores": {k: {"holdout_val_auroc": 0.9} for k in SCORES}}
    assert select_score("auto", tie_fused)[0] == "fused"
    without = {"scores": {k: {} for k in SCORES if k != "fused"}}
    assert select_score("auto", without) == (DEFAULT_SCORE, select_score("auto", without)[1])
    assert select_score("msp", with_holdout) == ("msp", "given")


def test_auto_score_falls_back_to_the_class_score_only_with_enough_training_scenes_per_category():
    tie = {"holdout_val_scenes": 8, "scores": {k: {"holdout_val_auroc": 1.0} for k in SCORES}}
    few_held = {"holdout_val_scenes": 2, "scores": {k: {"holdout_val_auroc": 1.0} for k in SCORES}}
    enough, short = CLASS_SCORE_TRAIN_SCENES, CLASS_SCORE_TRAIN_SCENES - 1
    score, why = select_score("auto", {**tie, "fewest_train_scenes": enough})
    assert score == "class_mahalanobis" and "tied" in why
    assert select_score("auto", {**few_held, "fewest_train_scenes": enough})[0] == "class_mahalanobis"
    assert select_score("auto", {**tie, "fewest_train_scenes": short})[0] == "fused"
    assert select_score("auto", {**few_held, "fewest_train_scenes": short})[0] == "fused"
    no_reference = {"holdout_val_scenes": 2, "scores": {k: {"holdout_val_auroc": 1.0} for k in SCORES if k != "fused"}}
    assert select_score("auto", {**no_reference, "fewest_train_scenes": short})[0] == DEFAULT_SCORE
    better = {**tie, "fewest_train_scenes": enough, "scores": {**tie["scores"], "class_mahalanobis": {"holdout_val_auroc": 0.9}}}
    assert select_score("auto", better)[0] == DEFAULT_SCORE  # a measured difference still wins over the fallback


def test_fewest_scenes_per_class_exact_small_case():
    labels = torch.tensor([0, 0, 0, 1, 1, 1, 1])
    scenes = torch.tensor([0, 0, 1, 2, 3, 4, 4])  # class 0: scenes 0, 1; class 1: scenes 2, 3, 4
    assert fewest_scenes_per_class(labels, scenes, 2) == 2
    assert fewest_scenes_per_class(labels, scenes, 3) == 0  # a class without views


def _loss(model, views, config) -> float:
    """Cross-entropy of all views, batch-statistics BatchNorm, on a copy (the model is untouched)."""
    probe = copy.deepcopy(model).train()
    inputs = normalize(composite(views.float_views(slice(None)), config.background), config.mean, config.std)
    with torch.no_grad():
        return float(F.cross_entropy(probe(inputs)[1], views.labels))


def test_a_few_training_steps_lower_the_loss(collection: Path):
    coll = load_collection(collection)
    splits = plan_splits(coll, ())
    config = TrainConfig(input_size=16, batch_size=5, epochs=4, lr=3e-3, augment=NO_AUGMENT, warmup_fraction=0.0)
    train = load_view_set(coll, splits.train, splits.categories, size=16, background=config.background)
    val = load_view_set(coll, splits.val, splits.categories, size=16, background=config.background)
    assert len(train) == 3 * 5 and set(train.labels.tolist()) == {0, 1, 2}
    model = build_model("resnet18", 3, seed=0)
    before = _loss(model, train, config)
    history = fit_network(model, train, val, config)
    after = _loss(model, train, config)
    assert history["steps"] == 4 * 3 and len(history["epochs"]) == 4
    assert after < 0.5 * before, (before, after)


def test_uniform_cross_entropy_is_the_kl_divergence_from_uniform():
    logits = torch.randn(7, 5, dtype=torch.float64) * 3
    log_p = logits.log_softmax(-1)
    expected = (0.2 * (torch.log(torch.tensor(0.2, dtype=torch.float64)) - log_p)).sum(-1).mean()
    assert torch.allclose(uniform_cross_entropy(logits), expected)
    assert abs(float(uniform_cross_entropy(torch.full((3, 4), 2.5)))) < 1e-6
    assert float(uniform_cross_entropy(torch.tensor([[10.0, 0.0, 0.0]]))) > 5.0  # a confident row pays


def test_outlier_exposure_makes_chimeras_less_confident(collection: Path):
    coll = load_collection(collection)
    splits = plan_splits(coll, ())
    train = load_view_set(coll, splits.train, splits.categories, size=16, background=TINY.background)
    g = torch.Generator().manual_seed(5)
    first, second = chimera_partners(train.labels, 32, g)
    chimeras = chimera_views(train.float_views(first), train.float_views(second), g)

    def fit(weight: float) -> tuple[float, float]:
        config = replace(TINY, batch_size=6, epochs=24, lr=3e-3, warmup_fraction=0.0, outlier_exposure=weight)
        model = build_model("resnet18", 3, seed=0)
        fit_network(model, train, train, config)
        with torch.no_grad():
            known = model(normalize(composite(train.float_views(slice(None)), config.background), config.mean, config.std))[1]
            odd = model(normalize(composite(chimeras, config.background), config.mean, config.std))[1]
        accuracy = float((known.argmax(-1) == train.labels).float().mean())
        return accuracy, float(odd.softmax(-1).max(-1).values.mean())

    (plain_accuracy, plain_msp), (oe_accuracy, oe_msp) = fit(0.0), fit(1.0)
    assert oe_accuracy >= plain_accuracy - 0.2, (plain_accuracy, oe_accuracy)
    assert oe_msp < plain_msp - 0.1, (plain_msp, oe_msp)
    for bad in (-0.5, float("nan")):
        with pytest.raises(ConfigError, match="outlier-exposure"):
            TrainConfig(outlier_exposure=bad).validate()


def test_train_classifier_writes_a_complete_folder_and_reloads(collection: Path, tmp_path: Path):
    out = tmp_path / "clf"
    config = TrainConfig(input_size=16, batch_size=4, epochs=1, holdout_categories=("airplane",), score="energy")
    doc = train_classifier(config, collection, out)
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".nerfmeta-")) == sorted(
        [WEIGHTS_FILE, META_FILE, HISTORY_FILE, CURVE_FILE])  # besides the run folder's marker and lock
    assert doc["categories"] == ["chair", "mug"] and doc["holdout_categories"] == ["airplane"]
    assert doc["unknown"]["score"] == "energy" and set(doc["unknown"]["thresholds"]) == set(SCORES)
    assert doc["input"]["normalization"]["mean"] == list(config.mean) and doc["recipe"]["epochs"] == 1
    scores = doc["validation"]["scores"]
    assert "holdout_val_auroc" in scores["mahalanobis"] and doc["validation"]["holdout_val_scenes"] == 1
    # the 1 % quantile of two known val scenes lies just above the lower one (linear interpolation)
    assert scores["energy"]["val_false_unknown_rate"] == 0.5
    # one validation and one training scene per category: too few to calibrate, said in classifier.json
    calibration = doc["calibration"]
    assert calibration["threshold_rule"] == "quantile" and calibration["scale_prior_scenes"] >= 1.0
    assert len(calibration["warnings"]) == 3 and "chair 1, mug 1" in calibration["warnings"][0]
    clf = load_classifier(out)
    views = read_scene_views(collection / "chair" / "chair_002", size=16, background=clf.meta.background)
    assert classify_views(clf, views).views == 5
    with pytest.raises(ConfigError, match="not empty"):
        train_classifier(config, collection, out)


def test_bad_training_input_writes_nothing(collection: Path, tmp_path: Path):
    out = tmp_path / "clf"
    with pytest.raises(ConfigError):
        train_classifier(TrainConfig(input_size=16, holdout_categories=("sofa",)), collection, out)
    with pytest.raises(ConfigError):
        train_classifier(TrainConfig(input_size=16, epochs=0), collection, out)
    with pytest.raises(ConfigError, match="make-collection"):
        train_classifier(TINY, tmp_path / "no_collection", out)
    assert list(tmp_path.iterdir()) == []


# --- CLI ---------------------------------------------------------------------------------------


def test_cli_train_then_classify(collection: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    out = tmp_path / "clf"
    args = ["classifier", "train", str(collection), "--out", str(out), "--epochs", "1", "--input-size", "16",
            "--batch-size", "4", "--holdout-categories", "airplane"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "validation:" in printed and str(out) in printed
    assert "warning: too few known validation scenes to calibrate the unknown threshold (chair 1, mug 1" in printed
    json_out = tmp_path / "answer.json"
    scene = collection / "mug" / "mug_000"
    assert main(["classify", str(scene), "--classifier", str(out), "--json-out", str(json_out)]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert {"category", "confidence", "unknown", "probabilities", "views"} <= set(answer)
    assert answer["views"] == 5 and set(answer["probabilities"]) == {"chair", "mug"}
    assert answer["category"] in ("chair", "mug") and isinstance(answer["unknown"], bool)
    assert json.loads(json_out.read_text()) == answer
    # a single image works too
    assert main(["classify", str(scene / "train" / "r_0.png"), "--classifier", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["views"] == 1


@pytest.fixture(scope="module")
def trained(collection: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("trained") / "clf"
    train_classifier(TINY, collection, out)
    return out


@pytest.mark.parametrize(
    "args, message",
    [
        (["classify", "{empty}", "--classifier", "{clf}"], "empty"),
        (["classify", "{scene}"], "--classifier DIR"),
        (["classify", "{scene}", "--classifier", "{empty}"], "classifier.json: file missing"),
        (["classify", "{scene}", "--classifier", "{clf}", "--score", "best"], "no calibrated threshold"),
        (["classifier", "train", "{coll}", "--out", "{new}", "--epochs", "0"], "--epochs must be a positive integer"),
        (["classifier", "train", "{coll}", "--out", "{new}", "--holdout-categories", "spaceship"], "not in the collection"),
    ],
)
def test_cli_bad_input_is_one_line_exit_2(args, message, collection: Path, trained: Path, tmp_path: Path, capsys):
    (tmp_path / "empty").mkdir()
    values = {"empty": tmp_path / "empty", "clf": trained, "scene": collection / "mug" / "mug_000", "coll": collection,
              "new": tmp_path / "new"}
    filled = [a.format(**values) for a in args]
    assert main(filled) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "new").exists()
