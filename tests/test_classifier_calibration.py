"""Calibration that holds on few validation scenes: the shrunk class scale, its prior, the margin threshold, the warnings."""

from __future__ import annotations

import math

import pytest
import torch

from classifier.config import CALIBRATION_NEEDS, SCALE_PRIOR_GRID, CalibrationNeeds, TrainConfig
from classifier.predict import (
    calibrate_threshold,
    class_mahalanobis_from_distances,
    fit_class_scale,
    leave_one_out_class_scores,
    leave_one_out_scales,
    scale_prior_loss,
    select_scale_prior,
    student_t_cdf,
    student_t_quantile,
)
from classifier.train import calibration_warnings, select_score
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
    assert score == "class_mahalanobis" and "held-out validation scenes" in why
    assert select_score("auto", metrics, min_holdout_scenes=0)[0] == "msp"
    assert select_score("auto", {**metrics, "holdout_val_scenes": 8})[0] == "msp"


def test_config_refuses_bad_calibration_values():
    TrainConfig().validate()
    with pytest.raises(ConfigError, match="--threshold-rule"):
        TrainConfig(threshold_rule="median").validate()
    with pytest.raises(ConfigError, match="--scale-prior-scenes"):
        TrainConfig(scale_prior_scenes=-1.0).validate()
    TrainConfig(scale_prior_scenes=0.0).validate()
