"""Calibration that holds on few validation scenes: the shrunk class scale, its prior, the margin threshold, the warnings."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from classifier.config import CALIBRATION_NEEDS, DEFAULT_SCORE, SCALE_PRIOR_GRID, CalibrationNeeds, TrainConfig
from classifier.predict import (
    calibrate_threshold,
    class_mahalanobis_from_distances,
    combined_score,
    fit_class_scale,
    fit_score_norm,
    leave_one_out_class_scores,
    leave_one_out_scales,
    scale_prior_loss,
    scene_scores,
    select_scale_prior,
    student_t_cdf,
    student_t_quantile,
    training_class_scale,
)
from classifier.train import CalibrationInputs, calibrate_inputs, calibration_warnings, select_score
from nerfmeta.errors import ConfigError

T_99_1DOF = 31.820515953773935  # scipy.stats.t.ppf(0.99, 1)


def _own(distances: list[list[float]]) -> tuple[torch.Tensor, torch.Tensor]:
    """Distances of scenes to their own class only (every other class far away): (n, C) distances and labels."""
    rows, labels = [], []
    for c, values in enumerate(distances):
        for v in values:
            row = [1e6] * len(distances)
            row[c] = v
            rows.append(row)
            labels.append(c)
    return torch.tensor(rows, dtype=torch.float64), torch.tensor(labels)


def test_shrunk_class_scale_by_hand():
    d, y = _own([[1.0, 3.0], [10.0], []])
    pooled = 14.0 / 3.0  # mean of the three own distances
    scale = fit_class_scale(d, y, 3, prior_scenes=2.0)
    assert scale.tolist() == pytest.approx([(4.0 + 2 * pooled) / 4, (10.0 + 2 * pooled) / 3, pooled])
    assert fit_class_scale(d, y, 3, prior_scenes=0.0).tolist() == pytest.approx([2.0, 10.0, 6.0])
    huge = fit_class_scale(d, y, 3, prior_scenes=1e9)
    assert huge.tolist() == pytest.approx([pooled] * 3)  # all prior: the pooled scale
    with pytest.raises(ValueError):
        fit_class_scale(d, y, 3, prior_scenes=-1.0)


def test_leave_one_out_scales_are_fits_without_each_scene():
    d, y = _own([[1.0, 3.0, 2.0], [10.0, 14.0]])
    scales = leave_one_out_scales(d, y, 2, prior_scenes=2.0)
    for i in range(5):
        keep = torch.arange(5) != i
        assert scales[i].tolist() == pytest.approx(fit_class_scale(d[keep], y[keep], 2, 2.0).tolist())
    # scene 0 (distance 1): class 0 without it is (3 + 2) plus 2 scenes of the pooled (3 + 2 + 10 + 14) / 4
    assert float(scales[0, 0]) == pytest.approx((5.0 + 2 * 29.0 / 4) / 4)
    loo = leave_one_out_class_scores(d, y, 2, prior_scenes=2.0)
    assert float(loo[0]) == pytest.approx(-math.log(1.0 / float(scales[0, 0])))
    with pytest.raises(ValueError):
        leave_one_out_scales(d[:1], y[:1], 2)


def test_scale_prior_loss_by_hand():
    d, y = _own([[1.0, 3.0], [1.0, 3.0]])
    # prior 0: each scene is scored by the other scene of its class
    expected = 0.5 * ((math.log(3.0) + 1.0 / 3.0) + (math.log(1.0) + 3.0))
    assert scale_prior_loss(d, y, 2, 0.0) == pytest.approx(expected)


def test_prior_is_large_when_classes_share_one_spread_and_small_when_they_do_not():
    same, y = _own([[1.0, 3.0], [3.0, 1.0], [2.0, 2.5]])
    assert select_scale_prior(same, y, 3, SCALE_PRIOR_GRID) == max(SCALE_PRIOR_GRID)
    far = [[0.9, 1.1, 1.0, 0.95, 1.05, 1.0, 0.98, 1.02], [90.0, 110.0, 100.0, 95.0, 105.0, 100.0, 98.0, 102.0]]
    d, y = _own(far)
    assert select_scale_prior(d, y, 2, SCALE_PRIOR_GRID) == min(SCALE_PRIOR_GRID)


def test_student_t_matches_tables():
    assert student_t_quantile(0.99, 1) == pytest.approx(T_99_1DOF, rel=1e-9)
    assert student_t_quantile(0.975, 2) == pytest.approx(4.302652729749462, rel=1e-9)
    assert student_t_quantile(0.99, 11) == pytest.approx(2.718079183813862, rel=1e-9)
    assert student_t_quantile(0.2, 4) == pytest.approx(-0.9409645772351811, rel=1e-9)
    assert student_t_cdf(0.0, 7) == 0.5
    assert student_t_cdf(2.0, 2) == pytest.approx(0.5 * (1 + 2.0 / math.sqrt(6.0)))  # closed form for 2 dof


def test_margin_threshold_with_two_scenes_is_the_prediction_bound():
    scores = torch.tensor([0.0, 1.0], dtype=torch.float64)
    assert calibrate_threshold(scores, 0.99) == pytest.approx(0.01)  # the quantile: just above the lower score
    bound = 0.5 - T_99_1DOF * math.sqrt(0.5) * math.sqrt(1.5)  # mean - t * sd * sqrt(1 + 1/n)
    assert calibrate_threshold(scores, 0.99, "margin") == pytest.approx(bound, rel=1e-9)
    # one scene or keeping everything: no spread to build a margin from, the quantile rule
    assert calibrate_threshold(scores[:1], 0.99, "margin") == 0.0
    assert calibrate_threshold(scores, 1.0, "margin") == 0.0
    with pytest.raises(ValueError):
        calibrate_threshold(scores, 0.99, "median")


def test_margin_threshold_adds_little_when_there_are_many_scenes():
    normal = torch.distributions.Normal(0.0, 1.0)
    scores = normal.icdf((torch.arange(1, 2001, dtype=torch.float64) - 0.5) / 2000)  # 2000 evenly spread normal scores
    quantile = calibrate_threshold(scores, 0.99)
    margin = calibrate_threshold(scores, 0.99, "margin")
    assert margin <= quantile and margin == pytest.approx(quantile, abs=0.02)
    # never above the quantile, however the scores lie
    skewed = torch.tensor([0.0, 0.0, 0.0, 0.0, 10.0], dtype=torch.float64)
    assert calibrate_threshold(skewed, 0.9, "margin") <= calibrate_threshold(skewed, 0.9)


def test_a_class_with_tiny_validation_spread_does_not_flag_its_fresh_scenes():
    """Two validation scenes per class; class 0's happen to lie very close to its mean."""
    d, y = _own([[0.01, 0.012], [10.0, 12.0], [9.0, 11.0]])
    fresh = torch.tensor([[10.0, 1e6, 1e6]], dtype=torch.float64)  # a new class-0 scene at a typical distance

    def flagged(prior: float, rule: str) -> bool:
        threshold = calibrate_threshold(leave_one_out_class_scores(d, y, 3, prior), 0.99, rule)
        return bool(class_mahalanobis_from_distances(fresh, fit_class_scale(d, y, 3, prior))[0] < threshold)

    assert flagged(0.0, "quantile")  # the rule before: the class's scale is 0.011, the fresh scene 900x farther
    prior = select_scale_prior(d, y, 3, SCALE_PRIOR_GRID)
    assert prior >= 1.0 and not flagged(prior, "margin")
    # each half alone is not enough: the shrunk scale under the plain quantile, the margin on the unshrunk scale
    assert flagged(prior, "quantile") and flagged(0.0, "margin")


def test_calibration_warnings_name_what_is_short():
    assert calibration_warnings({"a": 30, "b": 20}, {"a": 8, "b": 5}, 24) == []
    lines = calibration_warnings({"a": 7, "b": 30}, {"a": 2}, 8)
    assert len(lines) == 3
    assert "validation scenes" in lines[0] and "a 2" in lines[0] and "b 0" in lines[0] and ">= 5" in lines[0]
    assert "training scenes" in lines[1] and "a 7" in lines[1] and "b 30" not in lines[1]
    assert "8 views" in lines[2]
    strict = CalibrationNeeds(val_scenes_per_category=9)
    assert len(calibration_warnings({"a": 30}, {"a": 8}, 24, strict)) == 1


def test_auto_score_needs_enough_held_out_scenes():
    metrics = {"holdout_val_scenes": CALIBRATION_NEEDS.holdout_val_scenes - 1,
               "scores": {"msp": {"holdout_val_auroc": 0.99}, "energy": {"holdout_val_auroc": 0.5},
                          "mahalanobis": {"holdout_val_auroc": 0.5}, "class_mahalanobis": {"holdout_val_auroc": 0.6}}}
    score, why = select_score("auto", metrics)
    assert score == DEFAULT_SCORE and "held-out validation scenes" in why
    assert select_score("auto", metrics, min_holdout_scenes=0)[0] == "msp"
    assert select_score("auto", {**metrics, "holdout_val_scenes": 8})[0] == "msp"


def test_config_refuses_bad_calibration_values():
    TrainConfig().validate()
    with pytest.raises(ConfigError, match="--threshold-rule"):
        TrainConfig(threshold_rule="median").validate()
    with pytest.raises(ConfigError, match="--scale-prior-scenes"):
        TrainConfig(scale_prior_scenes=-1.0).validate()
    TrainConfig(scale_prior_scenes=0.0).validate()


def test_combined_score_by_hand():
    norm = fit_score_norm(torch.tensor([1.0, 3.0]), torch.tensor([-1.0, 0.0, ]))
    assert norm.tolist() == pytest.approx([2.0, math.sqrt(2.0), -0.5, math.sqrt(0.5)])
    value = combined_score(torch.tensor(4.0), torch.tensor(0.5), norm)
    assert float(value) == pytest.approx(2.0 / math.sqrt(2.0) + 1.0 / math.sqrt(0.5))
    one = fit_score_norm(torch.tensor([5.0]), torch.tensor([2.0]))  # one scene: no spread, unit scale
    assert one.tolist() == [5.0, 1.0, 2.0, 1.0]
    with pytest.raises(ValueError):
        fit_score_norm(torch.tensor([1.0]), torch.tensor([1.0, 2.0]))


def _synthetic_scenes(centres: torch.Tensor, n_scenes: int, n_views: int, generator: torch.Generator):
    """Per scene of each centre: (features (n_views, dim), logits (n_views, n_known)), and the centre of each scene.

    A scene's mean lies at its centre plus N(0, 1) noise, its views around the mean with N(0, 0.5^2) noise; the
    logits are ``-|f - known centre|^2 / 8`` (a classifier that learnt the three known centres)."""
    known = centres[:3]
    scenes, owners = [], []
    for c, centre in enumerate(centres):
        for _ in range(n_scenes):
            mean = centre + torch.randn(centre.shape, generator=generator)
            f = mean + 0.5 * torch.randn(n_views, centre.numel(), generator=generator)
            scenes.append((f, -((f[:, None, :] - known[None]) ** 2).sum(-1) / 8.0))
            owners.append(c)
    return scenes, owners


def test_default_rule_flags_a_nearby_unknown_cluster_and_keeps_fresh_known_scenes():
    """Three known Gaussian clusters, two validation scenes each (6 known scores, as a 12-scene collection of six
    known categories has), and a fourth cluster beside one of them: the default calibration flags the fourth and
    keeps fresh scenes of the three; the Student-t margin, the default before, lets the fourth through. With one
    validation scene per cluster the thresholds stay finite and the collection is warned about."""
    g = torch.Generator().manual_seed(0)
    centres = torch.zeros(4, 8)
    centres[0, 0], centres[1, 1], centres[2, 2] = 12.0, 12.0, 12.0
    centres[3] = torch.tensor([12.0, 0.0, 0.0, 5.0, 0, 0, 0, 0])  # unknown: beside cluster 0, 5 scene spreads away
    train, owners = _synthetic_scenes(centres[:3], 10, 24, g)
    val, val_owners = _synthetic_scenes(centres[:3], 2, 24, g)
    data = CalibrationInputs(
        train_features=torch.cat([f for f, _ in train]), train_logits=torch.cat([z for _, z in train]),
        train_labels=torch.tensor(owners).repeat_interleave(24), train_scene_index=torch.arange(len(train)).repeat_interleave(24),
        val=val, val_labels=torch.tensor(val_owners), holdout_val=[])
    fresh, fresh_owners = _synthetic_scenes(centres, 20, 14, g)

    def flagged(config: TrainConfig) -> tuple[float, float]:
        stats, thresholds, metrics = calibrate_inputs(data, config, 3)
        assert all(math.isfinite(t) for t in thresholds.values())
        score = DEFAULT_SCORE
        out = torch.tensor([scene_scores(z, f, stats)[score] < thresholds[score] for f, z in fresh])
        owner = torch.tensor(fresh_owners)
        return float(out[owner < 3].double().mean()), float(out[owner == 3].double().mean())

    known, unknown = flagged(TrainConfig())
    # a threshold at the smallest of n exchangeable known scores flags a new one 1 / (n + 1) of the time (1/7 here)
    assert known <= 0.1 and unknown >= 0.9, (known, unknown)
    _, unknown_margin = flagged(TrainConfig(threshold_rule="margin"))
    assert unknown_margin < 0.5
    one = [0, 2, 4]  # one validation scene per cluster
    data = replace(data, val=[val[i] for i in one], val_labels=data.val_labels[one])
    flagged(TrainConfig())  # finite thresholds
    # one validation scene per category is warned about
    lines = calibration_warnings({"a": 10, "b": 10, "c": 10}, {"a": 1, "b": 1, "c": 1}, 24)
    assert any("validation scenes" in line and "a 1" in line for line in lines)


def test_training_class_scale_is_the_leave_one_out_distance_by_hand():
    # class 0: scene means 0, 2, 4 on one axis (mean 2): without each, the mean is 3, 2, 1 -> distances 9, 0, 9
    # class 1: one scene, so it takes class 0's scale; identity precision
    means = torch.tensor([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0], [10.0, 10.0]])
    scale = training_class_scale(means, torch.tensor([0, 0, 0, 1]), torch.eye(2), 2)
    assert scale.tolist() == pytest.approx([6.0, 6.0])
    scale = training_class_scale(means, torch.tensor([0, 0, 0, 1]), 2.0 * torch.eye(2), 2)
    assert scale.tolist() == pytest.approx([12.0, 12.0])


def test_class_scale_prior_takes_its_shape_from_the_training_scenes_by_hand():
    d, y = _own([[4.0], [30.0], []])
    train = torch.tensor([1.0, 10.0, 5.0])
    inflation = (4.0 / 1.0 + 30.0 / 10.0) / 2  # validation scenes lie 3.5x farther than training scenes
    scale = fit_class_scale(d, y, 3, prior_scenes=1.0, train_scale=train)
    assert scale.tolist() == pytest.approx([(4.0 + 3.5) / 2, (30.0 + 35.0) / 2, 17.5])
    assert fit_class_scale(d, y, 3, prior_scenes=1e9, train_scale=train).tolist() == pytest.approx((inflation * train).tolist())
    assert fit_class_scale(d, y, 3, prior_scenes=0.0, train_scale=train).tolist() == pytest.approx([4.0, 30.0, 17.5])
    # without training scales the prior is the pooled mean, as before
    assert fit_class_scale(d, y, 3, 1.0).tolist() == pytest.approx([(4.0 + 17.0) / 2, (30.0 + 17.0) / 2, 17.0])
    # leave-one-out: a class's only scene is scored by the training shape, inflated by the other scenes
    loo = leave_one_out_scales(d, y, 3, 64.0, train)
    assert loo[0, 0] == pytest.approx(1.0 * 3.0) and loo[1, 1] == pytest.approx(10.0 * 4.0)


def test_a_broad_class_with_one_validation_scene_is_scored_like_a_tight_one():
    """Two known clusters, one broad (scene spread 3) and one tight (spread 1), one validation scene each. Shrunk
    towards one pooled scale (the rule before; the leave-one-out prior picks the largest weight), fresh scenes of
    the broad class score about log 9 lower than the tight class's, so a threshold flags the broad class first;
    with the scale's shape taken from the training scenes (the default) both classes score alike."""
    g = torch.Generator().manual_seed(3)
    dim, views = 6, 16
    centres = torch.zeros(2, dim)
    centres[0, 0], centres[1, 1] = 30.0, 30.0
    spread = torch.tensor([3.0, 1.0])

    def scenes(n: int):
        out, owners = [], []
        for c in range(2):
            for _ in range(n):
                mean = centres[c] + spread[c] * torch.randn(dim, generator=g)
                f = mean + 0.3 * torch.randn(views, dim, generator=g)
                out.append((f, -((f[:, None, :] - centres[None]) ** 2).sum(-1) / 50.0))
                owners.append(c)
        return out, torch.tensor(owners)

    train, owners = scenes(30)
    fresh, fresh_owners = scenes(100)
    val, val_owners = scenes(1)
    data = CalibrationInputs(
        train_features=torch.cat([f for f, _ in train]), train_logits=torch.cat([z for _, z in train]),
        train_labels=owners.repeat_interleave(views), train_scene_index=torch.arange(len(train)).repeat_interleave(views),
        val=val, val_labels=val_owners, holdout_val=[])
    gap = {}
    for prior in ("pooled", "train"):
        stats, _, _ = calibrate_inputs(data, TrainConfig(class_scale_prior=prior), 2)
        scores = torch.tensor([scene_scores(z, f, stats)["class_mahalanobis"] for f, z in fresh])
        gap[prior] = float(scores[fresh_owners == 1].median() - scores[fresh_owners == 0].median())
    assert gap["pooled"] > 1.5 and abs(gap["train"]) < 0.5, gap
