"""classifier.predict: view averaging, unknown scores, threshold decision, calibration, AUROC."""

from __future__ import annotations

import math

import pytest
import torch

from classifier.predict import (
    FeatureStats,
    auroc,
    calibrate_threshold,
    class_mahalanobis_from_distances,
    decide,
    energy_score,
    fit_class_scale,
    fit_feature_stats,
    is_unknown,
    leave_one_out_class_scores,
    mahalanobis_distances,
    mahalanobis_score,
    msp_score,
    scene_precision,
    scene_probabilities,
    scene_scores,
)

CATS = ("chair", "mug")


def test_scene_probabilities_is_the_mean_of_per_view_softmax():
    # view 1 is sure of class 0; views 2 and 3 lean mildly to class 1
    logits = torch.tensor([[math.log(9.0), 0.0], [0.0, math.log(1.5)], [0.0, math.log(1.5)]])
    # per-view softmax: (0.9, 0.1), (0.4, 0.6), (0.4, 0.6) -> mean (17/30, 13/30)
    probs = scene_probabilities(logits)
    assert torch.allclose(probs, torch.tensor([17 / 30, 13 / 30]), atol=1e-6)
    # not the softmax of the mean logits, which would pick the other class balance
    mean_logit_probs = torch.softmax(logits.mean(0), -1)
    assert not torch.allclose(probs, mean_logit_probs, atol=1e-3)
    assert decide(logits, None, CATS, "msp", 0.0).category == "chair"


def test_averaging_over_views_can_overturn_a_single_confident_view():
    logits = torch.tensor([[5.0, 0.0], [0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])
    pred = decide(logits, None, CATS, "msp", 0.0)
    # softmax rows: (0.9933, 0.0067) and 3 x (0.2689, 0.7311): mean class-1 prob 0.550
    assert pred.category == "mug" and pred.views == 4
    assert pred.confidence == pytest.approx((3 * 0.7310586 + 0.0066929) / 4, abs=1e-6)
    assert sum(pred.probabilities.values()) == pytest.approx(1.0)


def test_msp_and_energy_scores_by_hand():
    logits = torch.tensor([[2.0, 0.0], [0.0, 0.0]])
    e2 = math.exp(2.0)
    assert float(msp_score(logits)) == pytest.approx((e2 / (e2 + 1) + 0.5) / 2)
    assert float(energy_score(logits)) == pytest.approx((math.log(e2 + 1) + math.log(2.0)) / 2)


def _stats(between: float, within: float, dim: int = 2, means=None, reference: float = 4.0) -> FeatureStats:
    means = torch.tensor([[0.0, 0.0], [3.0, 4.0]]) if means is None else means
    return FeatureStats(means, torch.eye(dim) * between, torch.eye(dim) * within, torch.tensor(reference))


def test_mahalanobis_scores_the_scene_mean_feature():
    feats = torch.tensor([[1.0, 0.0], [3.0, 0.0]])  # mean (2, 0): 4 from class 0, 1 + 16 from class 1
    d2 = mahalanobis_distances(feats.mean(0, keepdim=True), _stats(1, 0).means, torch.eye(2))
    assert torch.allclose(d2, torch.tensor([[4.0, 17.0]], dtype=d2.dtype))
    # between = I: the distance of the mean under the identity; within does not count at the reference views
    assert float(mahalanobis_score(feats.repeat(2, 1), _stats(1.0, 5.0, reference=4.0))) == pytest.approx(-4.0)


def test_mahalanobis_spread_widens_for_scenes_with_fewer_views():
    # between = I, within = 4 I, reference 4 views: n views get I + 4 (1/n - 1/4) I
    stats = _stats(1.0, 4.0, reference=4.0)
    assert torch.allclose(scene_precision(stats, 4), torch.eye(2, dtype=torch.float64))
    assert torch.allclose(scene_precision(stats, 8), torch.eye(2, dtype=torch.float64))  # never narrower than between
    assert torch.allclose(scene_precision(stats, 1), torch.eye(2, dtype=torch.float64) / 4.0)
    one = torch.tensor([[2.0, 0.0]])
    assert float(mahalanobis_score(one, stats)) == pytest.approx(-1.0)  # 4 / (1 + 4 * 3/4)
    assert float(mahalanobis_score(one.repeat(4, 1), stats)) == pytest.approx(-4.0)


def test_threshold_decision_flips_at_the_threshold():
    logits = torch.tensor([[2.0, 0.0], [1.0, 0.0]])
    score = float(msp_score(logits))
    assert not decide(logits, None, CATS, "msp", score - 1e-6).unknown
    assert not decide(logits, None, CATS, "msp", score).unknown  # equal to the threshold is still known
    assert decide(logits, None, CATS, "msp", score + 1e-6).unknown
    # the category is still reported for an unknown scene
    assert decide(logits, None, CATS, "msp", 0.99).category == "chair"
    assert is_unknown(torch.tensor([0.2, 0.5, 0.8]), 0.5).tolist() == [True, False, False]


def test_mahalanobis_decision_needs_features():
    logits = torch.zeros(2, 2)
    with pytest.raises(ValueError, match="features"):
        decide(logits, None, CATS, "mahalanobis", 0.0)
    stats = _stats(1.0, 0.0, dim=3, means=torch.zeros(2, 3))
    near = decide(logits, torch.full((2, 3), 0.1), CATS, "mahalanobis", -1.0, stats)
    far = decide(logits, torch.full((2, 3), 2.0), CATS, "mahalanobis", -1.0, stats)
    assert not near.unknown and far.unknown
    assert far.score == pytest.approx(-12.0)


def test_calibrate_threshold_keeps_the_requested_fraction():
    scores = torch.arange(1, 101, dtype=torch.float64)  # 1..100
    t = calibrate_threshold(scores, 0.9)
    assert (scores >= t).double().mean() == pytest.approx(0.9, abs=0.011)
    assert calibrate_threshold(scores, 1.0) == 1.0  # keep all: the smallest score
    with pytest.raises(ValueError):
        calibrate_threshold(torch.zeros(0), 0.9)


def test_auroc_exact_cases():
    assert auroc(torch.tensor([3.0, 4.0]), torch.tensor([1.0, 2.0])) == 1.0
    assert auroc(torch.tensor([1.0, 2.0]), torch.tensor([3.0, 4.0])) == 0.0
    # pairs: (2>1) (2<3) (4>1) (4>3) -> 3 of 4; a tie counts half
    assert auroc(torch.tensor([2.0, 4.0]), torch.tensor([1.0, 3.0])) == 0.75
    assert auroc(torch.tensor([1.0]), torch.tensor([1.0])) == 0.5


def test_fit_feature_stats_measures_scene_and_view_spread():
    g = torch.Generator().manual_seed(0)
    class_means = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    n_scenes, n_views = 2000, 5
    scene_labels = torch.arange(n_scenes) % 2
    scene_means = class_means[scene_labels] + torch.randn(n_scenes, 2, generator=g) * torch.tensor([2.0, 0.5])
    scene_index = torch.arange(n_scenes).repeat_interleave(n_views)
    feats = scene_means[scene_index] + torch.randn(n_scenes * n_views, 2, generator=g) * torch.tensor([1.0, 3.0])
    stats = fit_feature_stats(feats, scene_labels[scene_index], scene_index, 2, shrinkage=0.0)
    assert torch.allclose(stats.means, class_means, atol=0.2)
    assert float(stats.reference_views) == pytest.approx(5.0)
    # the spread of 5-view means: between-scene variance + view variance / 5
    expected = torch.diag(torch.tensor([4.0 + 1.0 / 5, 0.25 + 9.0 / 5]))
    assert torch.allclose(stats.between, expected, rtol=0.1, atol=0.05)
    assert torch.allclose(stats.within, torch.diag(torch.tensor([1.0, 9.0])), rtol=0.05, atol=0.1)
    # shrinkage keeps everything invertible with one scene per class and one view per scene
    one = fit_feature_stats(torch.tensor([[1.0, 2.0], [3.0, 4.0]]), torch.tensor([0, 1]), torch.tensor([0, 1]), 2, 0.5)
    assert torch.isfinite(scene_precision(one, 1)).all()


def test_class_scale_is_the_mean_own_class_distance_and_fills_absent_classes():
    d = torch.tensor([[2.0, 50.0, 9.0], [4.0, 30.0, 9.0], [70.0, 10.0, 9.0]], dtype=torch.float64)
    scale = fit_class_scale(d, torch.tensor([0, 0, 1]), 3)
    # class 0: mean(2, 4) = 3; class 1: 10; class 2 has no scene: mean of the others, 6.5
    assert scale.tolist() == pytest.approx([3.0, 10.0, 6.5])


def test_class_mahalanobis_divides_by_each_class_scale_before_taking_the_nearest():
    scale = torch.tensor([1.0, 100.0], dtype=torch.float64)
    # raw distances say class 0 is nearer (4 < 50); scaled, class 1 is (0.5 < 4)
    score = class_mahalanobis_from_distances(torch.tensor([4.0, 50.0], dtype=torch.float64), scale)
    assert float(score) == pytest.approx(-math.log(0.5))
    # a broad class (large scale) no longer flags its own far-out scenes; the pooled score would
    assert float(class_mahalanobis_from_distances(torch.tensor([400.0, 300.0]), scale)) > float(
        class_mahalanobis_from_distances(torch.tensor([20.0, 2000.0]), scale))
    assert math.isfinite(float(class_mahalanobis_from_distances(torch.zeros(2), scale)))


def test_leave_one_out_scores_leave_each_scene_out_of_its_own_class_scale():
    d = torch.tensor([[1.0, 90.0], [3.0, 80.0], [8.0, 70.0], [60.0, 5.0]], dtype=torch.float64)
    labels = torch.tensor([0, 0, 0, 1])
    scale = fit_class_scale(d, labels, 2)  # class 0: 4, class 1: 5
    loo = leave_one_out_class_scores(d, labels, 2)
    # scene 2 (distance 8) against the mean of the other two (2): ratio 4, not 8 / 4 = 2
    assert float(loo[2]) == pytest.approx(-math.log(4.0))
    assert float(loo[0]) == pytest.approx(-math.log(1.0 / 5.5))
    # without scene 3 its class has no scene and takes the others' mean scale, 4: nearest is 5 / 4
    assert float(loo[3]) == pytest.approx(-math.log(5.0 / 4.0))
    # leaving a scene out makes the atypical ones (farther than their class's mean) look less typical
    full = class_mahalanobis_from_distances(d, scale)
    assert float(loo[2]) < float(full[2]) and float(loo[0]) > float(full[0])


def test_scene_scores_include_class_mahalanobis_only_with_a_class_scale():
    feats = torch.tensor([[1.0, 0.0], [3.0, 0.0]])
    logits = torch.zeros(2, 2)
    assert "class_mahalanobis" not in scene_scores(logits, feats, _stats(1.0, 0.0, reference=2.0))
    stats = FeatureStats(*_stats(1.0, 0.0, reference=2.0).__dict__.values())
    stats = FeatureStats(stats.means, stats.between, stats.within, stats.reference_views, torch.tensor([2.0, 1.0]))
    scores = scene_scores(logits, feats, stats)
    # distances (4, 17) -> ratios (2, 17): -log 2
    assert scores["mahalanobis"] == pytest.approx(-4.0)
    assert scores["class_mahalanobis"] == pytest.approx(-math.log(2.0))
