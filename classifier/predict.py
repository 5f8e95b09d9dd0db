"""Scene-level prediction and the unknown-category decision: pure functions over tensors.

A scene is classified from all the views given for it: each view's logits go through a softmax
and the probabilities are averaged over the views (as in the source work). The unknown decision
compares a scene score with a threshold; every score here is oriented so that **higher means
more like a known category**, and a scene is unknown when its score is below the threshold.

Scores (names as in :data:`classifier.config.SCORES`):

- ``msp``: the largest averaged probability (maximum softmax probability).
- ``energy``: the negative free energy ``logsumexp(logits)`` of each view, averaged over views.
- ``mahalanobis``: minus the squared Mahalanobis distance of the scene's mean penultimate
  feature (over its views) to the nearest class, under the spread of the training scenes' mean
  features (:class:`FeatureStats`).
- ``class_mahalanobis``: the same distances, each divided by its class's typical distance on
  *validation* scenes, shrunk towards the pooled one (``FeatureStats.class_scale``,
  :func:`fit_class_scale`), and minus the log of the smallest ratio. The
  training scenes' spread is one pooled covariance, and the network fits its training scenes more
  tightly than new ones by a margin that differs per class (measured 1.9x for cars, 3.7x for lamps,
  4.5x for tables: categories with sub-types generalise least), so the pooled distance flags new
  scenes of the broad categories; the per-class scale puts every class on the same footing.
- ``combined``: ``energy`` plus ``class_mahalanobis``, each in units of its spread on the known validation scenes.
- ``fused``: ``combined`` plus the same kind of distance in a frozen ImageNet network's features, in units of its
  leave-one-out spread over every known scene (:mod:`classifier.reference`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import torch

from classifier.config import SCORES


@dataclass(frozen=True)
class FeatureStats:
    """Gaussian model of a scene's mean penultimate feature, per class, with one shared spread.

    ``between`` is the covariance of the training scenes' mean features (each the mean of
    ``reference_views`` views) around their class mean. A scene seen in fewer views has a noisier
    mean; the model widens the spread for it by the view covariance: the mean of ``n`` views is
    compared under ``between + within * max(0, 1/n - 1/reference_views)``, so a single photo is
    not flagged unknown just for being one view. Scenes with more views keep ``between`` (a
    measured, slightly conservative spread).

    Attributes:
        means: (n_classes, dim) class means of the training scenes' mean features.
        between: (dim, dim) covariance of scene means around their class mean (shrunk, positive definite).
        within: (dim, dim) covariance of view features around their scene mean (shrunk).
        reference_views: (,) how many views each training scene mean averaged (harmonic mean).
        class_scale: (n_classes,) mean squared distance of known validation scenes to their own
            class mean, shrunk towards the pooled mean (see :func:`fit_class_scale`), needed by
            ``class_mahalanobis``; None in classifiers saved before it existed.
        score_norm: (4,) mean and standard deviation of ``energy`` and of ``class_mahalanobis`` over the
            known validation scenes (:func:`fit_score_norm`), needed by ``combined``; None before it existed.
        train_scale: (n_classes,) mean leave-one-out squared distance of each class's training scenes to
            their class mean (:func:`training_class_scale`): which classes are broad, read off many
            scenes; calibration scales it to the validation scenes (:func:`fit_class_scale`). None in
            classifiers saved before it existed.
        reference: the ImageNet reference model of the ``fused`` score (:mod:`classifier.reference`), or None.
    """

    means: torch.Tensor
    between: torch.Tensor
    within: torch.Tensor
    reference_views: torch.Tensor
    class_scale: torch.Tensor | None = None
    score_norm: torch.Tensor | None = None
    train_scale: torch.Tensor | None = None
    reference: "ReferenceModel | None" = None


@dataclass(frozen=True)
class ReferenceModel:
    """The statistics and scale of the ImageNet reference score (:mod:`classifier.reference`).

    A scene is scored by its mean descriptor alone, whatever its number of views (the threshold comes from known
    scenes scored the same way), so no view covariance is kept.

    Attributes:
        means: (n_classes, dim) class means of the known scenes' mean descriptors.
        between: (dim, dim) covariance of the scene means around their class mean (shrunk, positive definite).
        norm: (2,) mean and standard deviation of the known scenes' leave-one-out reference scores.
    """

    means: torch.Tensor
    between: torch.Tensor
    norm: torch.Tensor

    @cached_property
    def precision(self) -> torch.Tensor:
        """(dim, dim) inverse of ``between`` in float64, computed once (every scene scored is measured under it)."""
        return torch.linalg.inv(self.between.double())

    def z(self, descriptors: torch.Tensor) -> float:
        """A scene's reference score in units of the known scenes' spread. descriptors: (n_views, dim)."""
        return float((reference_score(descriptors, self.means, self.precision) - self.norm[0].double()) / self.norm[1].double())


def reference_score(descriptors: torch.Tensor, means: torch.Tensor, precision: torch.Tensor) -> torch.Tensor:
    """Minus the squared Mahalanobis distance (under ``precision``, the inverse covariance) of the scene's mean
    descriptor to the nearest class mean (float64). descriptors: (n_views, dim); means: (n_classes, dim)."""
    return -mahalanobis_distances(descriptors.mean(dim=0, keepdim=True), means, precision)[0].min()


def scene_probabilities(logits: torch.Tensor) -> torch.Tensor:
    """Average of the per-view softmax.

    Args:
        logits: (n_views, n_classes) one row per view of the scene.

    Returns:
        (n_classes,) probabilities summing to 1.
    """
    if logits.dim() != 2 or logits.shape[0] < 1:
        raise ValueError(f"logits must be (n_views >= 1, n_classes), got {tuple(logits.shape)}")
    return torch.softmax(logits, dim=-1).mean(dim=0)


def msp_score(logits: torch.Tensor) -> torch.Tensor:
    """Maximum of the view-averaged softmax. logits: (n_views, n_classes) -> scalar in (0, 1]."""
    return scene_probabilities(logits).max()


def energy_score(logits: torch.Tensor) -> torch.Tensor:
    """Mean over views of ``logsumexp(logits)`` (negative free energy). logits: (n_views, n_classes) -> scalar."""
    return torch.logsumexp(logits, dim=-1).mean()


def scene_precision(stats: FeatureStats, n_views: int) -> torch.Tensor:
    """(dim, dim) inverse of ``between + within * max(0, 1/n_views - 1/reference_views)``, in float64."""
    extra = max(0.0, 1.0 / max(1, n_views) - 1.0 / float(stats.reference_views))
    cov = stats.between.double() + stats.within.double() * extra
    return torch.linalg.inv(cov)


def mahalanobis_distances(points: torch.Tensor, means: torch.Tensor, precision: torch.Tensor) -> torch.Tensor:
    """Squared Mahalanobis distance of each point to each mean.

    Args:
        points: (n, dim).
        means: (n_classes, dim).
        precision: (dim, dim) symmetric positive definite.

    Returns:
        (n, n_classes) non-negative distances, in ``precision``'s dtype.
    """
    diff = points.to(precision.dtype)[:, None, :] - means.to(precision.dtype)[None, :, :]  # (n, C, D)
    return torch.einsum("ncd,de,nce->nc", diff, precision, diff).clamp_min(0.0)


def mahalanobis_score(features: torch.Tensor, stats: FeatureStats) -> torch.Tensor:
    """Minus the squared Mahalanobis distance of the scene's mean feature to the nearest class.

    Args:
        features: (n_views, dim) penultimate features of the scene's views.
        stats: the two-level feature model (see :class:`FeatureStats`).

    Returns:
        scalar (float64), at most 0; the spread is widened for scenes with few views (see :class:`FeatureStats`).
    """
    return -scene_distances(features, stats).min()


def scene_distances(features: torch.Tensor, stats: FeatureStats) -> torch.Tensor:
    """(n_classes,) squared Mahalanobis distances of the scene's mean feature to each class mean (float64).

    Args:
        features: (n_views, dim) penultimate features of the scene's views.
        stats: the two-level feature model (the spread is widened for scenes with few views).
    """
    precision = scene_precision(stats, features.shape[0])
    return mahalanobis_distances(features.mean(dim=0, keepdim=True), stats.means, precision)[0]


def class_mahalanobis_from_distances(distances: torch.Tensor, class_scale: torch.Tensor) -> torch.Tensor:
    """``-log(min_c distances[..., c] / class_scale[c])``: higher = closer to a known class.

    Args:
        distances: (..., n_classes) squared distances to each class mean.
        class_scale: (n_classes,) positive typical distance of each class's own scenes, or (..., n_classes)
            scales per row (the leave-one-out scores).

    Returns:
        (...,) float64 scores; a distance of exactly 0 scores as ``-log(1e-12)``, not infinity.
    """
    ratio = distances.double() / class_scale.double()
    return -torch.log(ratio.min(dim=-1).values.clamp_min(1e-12))


def fit_class_scale(
    distances: torch.Tensor, labels: torch.Tensor, n_classes: int, prior_scenes: float = 0.0,
    train_scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """Each class's typical squared distance, shrunk towards a prior scale.

    The prior of class ``c`` is ``S_c = t_c * mean_i(d_i / t_{y_i})``, ``d_i`` the own-class distance
    of scene ``i``: the training scenes' per-class scale ``t`` (``train_scale``; which classes are
    broad), inflated by how much farther the given scenes lie than the training scenes do on average.
    Without ``train_scale`` (``t = 1``) it is the pooled mean distance. Class ``c`` with ``n_c`` scenes
    gets ``(sum of its own distances + prior_scenes * S_c) / (n_c + prior_scenes)``: the prior counts
    as ``prior_scenes`` extra scenes. ``prior_scenes = 0`` is the plain per-class mean (a class with no
    scene then gets ``S_c``, or without ``train_scale`` the mean of the other classes' scales), and a
    class seen in two scenes that happen to lie close to its mean no longer gets a scale so small
    that every new scene of it is flagged.

    Args:
        distances: (n_scenes, n_classes) squared distances of validation scenes to each class mean.
        labels: (n_scenes,) the class of each scene.
        n_classes: number of classes.
        prior_scenes: weight of the prior scale, in scenes, >= 0.
        train_scale: (n_classes,) positive per-class scale of the training scenes, or None (pooled prior).

    Returns:
        (n_classes,) positive float64 scales.
    """
    if distances.shape[0] < 1:
        raise ValueError("the class scale needs at least one known validation scene")
    if not prior_scenes >= 0.0:
        raise ValueError(f"prior_scenes must be >= 0, got {prior_scenes}")
    own = distances.double()[torch.arange(distances.shape[0]), labels]
    sums = torch.zeros(n_classes, dtype=torch.float64).index_add_(0, labels, own)
    counts = torch.bincount(labels, minlength=n_classes).double()
    shape = torch.ones(n_classes, dtype=torch.float64) if train_scale is None else train_scale.double().clamp_min(1e-12)
    prior = shape * (own / shape[labels]).mean()
    if prior_scenes > 0.0:
        scale = (sums + prior_scenes * prior) / (counts + prior_scenes)
    else:
        scale = sums / counts.clamp_min(1)
        fallback = scale[counts > 0].mean() if train_scale is None else prior
        scale = torch.where(counts > 0, scale, fallback)
    return scale.clamp_min(1e-12)


def training_class_scale(scene_means: torch.Tensor, scene_labels: torch.Tensor, precision: torch.Tensor, n_classes: int) -> torch.Tensor:
    """Per class, the mean squared distance of its training scenes to the mean of its *other* training scenes.

    Leaving scene ``i`` of a class of ``n`` scenes out of the class mean moves the mean away from it:
    ``m_i - mean_without_i = n / (n - 1) * (m_i - mean)``, so its distance is ``(n / (n - 1))^2`` times
    the in-sample one. A class with fewer than two scenes gets the mean of the other classes (1 if none has two).

    Args:
        scene_means: (n_scenes, dim) mean feature of each training scene.
        scene_labels: (n_scenes,) class of each.
        precision: (dim, dim) inverse scene-mean covariance.
        n_classes: number of classes.

    Returns:
        (n_classes,) positive float64 scales.
    """
    m = scene_means.double()
    counts = torch.bincount(scene_labels, minlength=n_classes).double()
    means = torch.zeros(n_classes, m.shape[1], dtype=torch.float64).index_add_(0, scene_labels, m) / counts.clamp_min(1)[:, None]
    dev = m - means[scene_labels]
    n = counts[scene_labels]
    d = torch.einsum("nd,de,ne->n", dev, precision.double(), dev) * (n / (n - 1).clamp_min(1)) ** 2
    sums = torch.zeros(n_classes, dtype=torch.float64).index_add_(0, scene_labels, d)
    ok = counts >= 2
    scale = sums / counts.clamp_min(1)
    fallback = scale[ok].mean() if bool(ok.any()) else torch.tensor(1.0, dtype=torch.float64)
    return torch.where(ok, scale, fallback).clamp_min(1e-12)


def leave_one_out_scales(
    distances: torch.Tensor, labels: torch.Tensor, n_classes: int, prior_scenes: float = 0.0,
    train_scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """Row ``i``: :func:`fit_class_scale` of all the scenes but scene ``i`` (its pooled share left out too).

    Args:
        distances: (n_scenes, n_classes), n_scenes >= 2.
        labels: (n_scenes,).
        n_classes: number of classes.
        prior_scenes, train_scale: as in :func:`fit_class_scale`.

    Returns:
        (n_scenes, n_classes) float64 scales.
    """
    n = distances.shape[0]
    if n < 2:
        raise ValueError("leave-one-out scales need at least two known validation scenes")
    keep = ~torch.eye(n, dtype=torch.bool)
    return torch.stack([fit_class_scale(distances[keep[i]], labels[keep[i]], n_classes, prior_scenes, train_scale)
                        for i in range(n)])


def leave_one_out_class_scores(
    distances: torch.Tensor, labels: torch.Tensor, n_classes: int, prior_scenes: float = 0.0,
    train_scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """``class_mahalanobis`` of the scenes the scale is fitted on, each scored by scales fitted without it.

    A scene scored by a scale that includes its own distance looks more typical than a new scene
    of the class would; calibrating a threshold on such scores flags too many new scenes (measured:
    false unknowns 5-8 % of known test scenes against 0 % with these scores). Without the prior, a
    class with one scene scores that scene against the other classes' mean scale.

    Args:
        distances: (n_scenes, n_classes) distances of the known validation scenes, n_scenes >= 2.
        labels: (n_scenes,) their classes.
        n_classes: number of classes.
        prior_scenes, train_scale: as in :func:`fit_class_scale`.

    Returns:
        (n_scenes,) float64 scores.
    """
    scales = leave_one_out_scales(distances, labels, n_classes, prior_scenes, train_scale)
    return class_mahalanobis_from_distances(distances.double(), scales)


def scale_prior_loss(
    distances: torch.Tensor, labels: torch.Tensor, n_classes: int, prior_scenes: float, train_scale: torch.Tensor | None = None
) -> float:
    """Mean leave-one-out negative log-likelihood of the own-class distances, ``log s + d / s``.

    Each scene's distance ``d`` to its own class is scored by its class's scale ``s`` fitted
    without it; the loss is that of an exponential (chi-square-like) model of the distance with
    mean ``s``, smallest for the prior that predicts unseen scenes' distances best.

    Args:
        distances: (n_scenes, n_classes), n_scenes >= 2.
        labels: (n_scenes,).
        n_classes: number of classes.
        prior_scenes, train_scale: as in :func:`fit_class_scale`.
    """
    rows = torch.arange(distances.shape[0])
    own = distances.double()[rows, labels].clamp_min(1e-12)
    s = leave_one_out_scales(distances, labels, n_classes, prior_scenes, train_scale)[rows, labels]
    return float((torch.log(s) + own / s).mean())


def select_scale_prior(
    distances: torch.Tensor, labels: torch.Tensor, n_classes: int, grid: tuple[float, ...], train_scale: torch.Tensor | None = None
) -> float:
    """The prior of ``grid`` with the smallest :func:`scale_prior_loss` (ties: the larger prior, the safer one).

    Args:
        distances: (n_scenes, n_classes) known validation scenes, n_scenes >= 2.
        labels: (n_scenes,).
        n_classes: number of classes.
        grid: candidate priors, in scenes (each >= 0).
        train_scale: as in :func:`fit_class_scale`.
    """
    losses = {k: scale_prior_loss(distances, labels, n_classes, k, train_scale) for k in grid}
    best = min(losses.values())
    return max(k for k, v in losses.items() if v <= best + 1e-12)


def scene_scores(logits: torch.Tensor, features: torch.Tensor | None, stats: FeatureStats | None,
                 reference: torch.Tensor | None = None) -> dict[str, float]:
    """Every unknown score of one scene (the Mahalanobis ones only when features and stats are given;
    ``class_mahalanobis`` only when the stats hold a class scale, ``combined`` only when they also hold a score norm,
    ``fused`` only when there is ``combined``, a reference model in the stats and the scene's reference descriptors).

    Args:
        logits: (n_views, n_classes).
        features: (n_views, dim) penultimate features, or None.
        stats: feature statistics of the training views, or None.
        reference: (n_views', dim') the views' ImageNet descriptors (:func:`classifier.reference.view_descriptors`), or None.
    """
    scores = {"msp": float(msp_score(logits)), "energy": float(energy_score(logits))}
    if features is not None and stats is not None:
        distances = scene_distances(features, stats)
        scores["mahalanobis"] = float(-distances.min())
        if stats.class_scale is not None:
            scores["class_mahalanobis"] = float(class_mahalanobis_from_distances(distances, stats.class_scale))
            if stats.score_norm is not None:
                scores["combined"] = float(combined_score(torch.tensor(scores["energy"]), torch.tensor(scores["class_mahalanobis"]),
                                                          stats.score_norm))
                if stats.reference is not None and reference is not None:
                    scores["fused"] = scores["combined"] + stats.reference.z(reference)
    return scores


def is_unknown(score: float | torch.Tensor, threshold: float) -> bool | torch.Tensor:
    """True where the score falls below the threshold (works on floats and on tensors)."""
    return score < threshold


def calibrate_threshold(known_scores: torch.Tensor, keep_fraction: float, rule: str = "quantile") -> float:
    """Threshold that keeps ``keep_fraction`` of the known scenes (scores at or above it).

    ``quantile``: the ``1 - keep_fraction`` quantile of the scores (linear interpolation);
    ``keep_fraction = 1`` gives the smallest score, so every calibration scene is kept. With few
    scenes this is about their smallest score, and a new scene falls below it far more often
    than ``1 - keep_fraction`` of the time.

    ``margin``: the lower of that quantile and the normal prediction bound
    ``mean - t * sd * sqrt(1 + 1 / n)``, with ``t`` the ``keep_fraction`` quantile of Student's t
    with ``n - 1`` degrees of freedom (:func:`student_t_quantile`): where a new scene's score
    would fall, given ``n`` scores, if scores were normal. The margin grows as ``n`` shrinks (with
    2 scenes, ``t = 31.8`` at 99 %), so a small calibration set lowers the threshold instead of
    fitting it to the few scores seen. With one scene, or ``keep_fraction = 1``, it is the quantile.

    Args:
        known_scores: (n,) scores of validation scenes of known categories, n >= 1.
        keep_fraction: in (0, 1].
        rule: ``quantile`` or ``margin``.
    """
    if known_scores.numel() < 1:
        raise ValueError("calibration needs at least one known scene")
    if not 0.0 < keep_fraction <= 1.0:
        raise ValueError(f"keep_fraction must be in (0, 1], got {keep_fraction}")
    if rule not in ("quantile", "margin"):
        raise ValueError(f"unknown threshold rule {rule!r}")
    scores = known_scores.double().flatten()
    quantile = float(torch.quantile(scores, 1.0 - keep_fraction))
    n = scores.numel()
    if rule == "quantile" or n < 2 or keep_fraction >= 1.0:
        return quantile
    bound = float(scores.mean()) - student_t_quantile(keep_fraction, n - 1) * float(scores.std()) * math.sqrt(1.0 + 1.0 / n)
    return min(quantile, bound)


def student_t_cdf(t: float, dof: int) -> float:
    """P(T <= t) for Student's t with an integer number of degrees of freedom (closed form, A&S 26.7.3-4)."""
    if dof < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {dof}")
    theta = math.atan(abs(t) / math.sqrt(dof))
    c2, sin = math.cos(theta) ** 2, math.sin(theta)
    if dof % 2:  # odd: (2/pi) (theta + sin (cos + 2/3 cos^3 + ...)), (dof - 1) / 2 terms
        term, total = math.cos(theta), 0.0
        for k in range(1, (dof - 1) // 2 + 1):
            total += term
            term *= c2 * (2 * k) / (2 * k + 1)
        both = 2.0 / math.pi * (theta + sin * total)
    else:  # even: sin (1 + 1/2 cos^2 + 3/8 cos^4 + ...), dof / 2 terms
        term, total = 1.0, 0.0
        for k in range(1, dof // 2 + 1):
            total += term
            term *= c2 * (2 * k - 1) / (2 * k)
        both = sin * total
    return 0.5 + math.copysign(0.5 * both, t)


def student_t_quantile(q: float, dof: int) -> float:
    """The ``q`` quantile of Student's t with ``dof`` degrees of freedom, by bisection of :func:`student_t_cdf`."""
    if not 0.0 < q < 1.0:
        raise ValueError(f"quantile level must be in (0, 1), got {q}")
    if q < 0.5:
        return -student_t_quantile(1.0 - q, dof)
    lo, hi = 0.0, 1.0
    while student_t_cdf(hi, dof) < q:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if student_t_cdf(mid, dof) < q else (lo, mid)
    return 0.5 * (lo + hi)


def auroc(known_scores: torch.Tensor, unknown_scores: torch.Tensor) -> float:
    """Area under the ROC curve of telling known (higher score) from unknown scenes.

    The probability that a random known scene scores above a random unknown one, ties counting
    half (Mann-Whitney U). 1 is perfect, 0.5 is chance.

    Args:
        known_scores: (n_known,), n_known >= 1.
        unknown_scores: (n_unknown,), n_unknown >= 1.
    """
    k = known_scores.double().flatten()[:, None]
    u = unknown_scores.double().flatten()[None, :]
    if k.numel() < 1 or u.numel() < 1:
        raise ValueError("AUROC needs at least one known and one unknown score")
    return float(((k > u).double() + 0.5 * (k == u).double()).mean())


def _shrink(cov: torch.Tensor, shrinkage: float) -> torch.Tensor:
    """``(1 - shrinkage) * cov + shrinkage * mean(diag cov) * I``, plus a tiny floor on the diagonal."""
    eye = torch.eye(cov.shape[0], dtype=cov.dtype)
    scale = float(cov.diagonal().mean())
    return (1.0 - shrinkage) * cov + (shrinkage * scale + 1e-6 * max(scale, 1e-6)) * eye


def fit_feature_stats(
    features: torch.Tensor, labels: torch.Tensor, scene_index: torch.Tensor, n_classes: int, shrinkage: float
) -> FeatureStats:
    """Fit :class:`FeatureStats` to the views of training scenes.

    ``between`` is the pooled covariance of the scene means around their class means, ``within``
    that of the views around their scene mean; both are shrunk towards a multiple of the identity,
    ``(1 - shrinkage) * S + shrinkage * mean(diag S) * I`` (the scene-mean covariance has rank at
    most the number of scenes, so shrinkage is what makes it invertible).

    Args:
        features: (n_views, dim) penultimate features of the training views (not augmented).
        labels: (n_views,) class of each view; every class present.
        scene_index: (n_views,) scene of each view (views of a scene share a label).
        n_classes: number of classes.
        shrinkage: in [0, 1].
    """
    f = features.double()
    scenes, inverse, counts = torch.unique(scene_index, return_inverse=True, return_counts=True)
    n_scenes = scenes.numel()
    scene_means = torch.zeros(n_scenes, f.shape[1], dtype=torch.float64).index_add_(0, inverse, f) / counts[:, None]
    scene_labels = torch.zeros(n_scenes, dtype=torch.long).scatter_(0, inverse, labels)
    view_dev = f - scene_means[inverse]
    within = view_dev.T @ view_dev / max(1, f.shape[0] - n_scenes)
    means = torch.zeros(n_classes, f.shape[1], dtype=torch.float64)
    for c in range(n_classes):
        rows = scene_means[scene_labels == c]
        if rows.shape[0] == 0:
            raise ValueError(f"class {c} has no training scene")
        means[c] = rows.mean(dim=0)
    scene_dev = scene_means - means[scene_labels]
    between = scene_dev.T @ scene_dev / max(1, n_scenes - n_classes)
    reference = n_scenes / float((1.0 / counts.double()).sum())
    between = _shrink(between, shrinkage).float()
    return FeatureStats(
        means=means.float(),
        between=between,
        within=_shrink(within, shrinkage).float(),
        reference_views=torch.tensor(reference, dtype=torch.float32),
        train_scale=training_class_scale(scene_means, scene_labels, torch.linalg.inv(between.double()), n_classes).float(),
    )


@dataclass(frozen=True)
class Prediction:
    """The answer for one scene.

    Attributes:
        category: the most probable known category (reported even when ``unknown``).
        confidence: its view-averaged probability.
        unknown: True when the scene's score is below the calibrated threshold.
        probabilities: category -> view-averaged probability.
        views: number of views the prediction averaged over.
        score_name: the unknown score used (``msp``, ``energy`` or ``mahalanobis``).
        score: the scene's value of that score.
        threshold: the calibrated threshold it was compared with.
    """

    category: str
    confidence: float
    unknown: bool
    probabilities: dict[str, float]
    views: int
    score_name: str
    score: float
    threshold: float

    def to_json(self) -> dict:
        """The document ``nerfmeta classify`` prints."""
        return {
            "category": self.category,
            "confidence": self.confidence,
            "unknown": self.unknown,
            "probabilities": dict(self.probabilities),
            "views": self.views,
            "score": {"name": self.score_name, "value": self.score, "threshold": self.threshold},
        }


def decide(
    logits: torch.Tensor,
    features: torch.Tensor | None,
    categories: tuple[str, ...],
    score_name: str,
    threshold: float,
    stats: FeatureStats | None = None,
    reference: torch.Tensor | None = None,
) -> Prediction:
    """Scene-level prediction from per-view outputs.

    Args:
        logits: (n_views, n_classes) per-view logits.
        features: (n_views, dim) per-view penultimate features (needed by ``mahalanobis``).
        categories: class names, in logit order.
        score_name: one of :data:`classifier.config.SCORES`.
        threshold: scenes scoring below it are unknown.
        stats: feature statistics (needed by ``mahalanobis``).
        reference: (n_views, dim') ImageNet descriptors of the views (needed by ``fused``).
    """
    if score_name not in SCORES:
        raise ValueError(f"unknown score {score_name!r}")
    if logits.shape[-1] != len(categories):
        raise ValueError(f"{logits.shape[-1]} logits per view for {len(categories)} categories")
    probs = scene_probabilities(logits)
    scores = scene_scores(logits, features, stats, reference)
    if score_name not in scores:
        raise ValueError(f"score {score_name!r} needs features and feature statistics")
    best = int(probs.argmax())
    return Prediction(
        category=categories[best],
        confidence=float(probs[best]),
        unknown=bool(is_unknown(scores[score_name], threshold)),
        probabilities={c: float(p) for c, p in zip(categories, probs)},
        views=int(logits.shape[0]),
        score_name=score_name,
        score=scores[score_name],
        threshold=float(threshold),
    )



def fit_score_norm(energy: torch.Tensor, class_scores: torch.Tensor) -> torch.Tensor:
    """(4,) float64 ``(mean, sd)`` of ``energy`` then of ``class_mahalanobis`` over the known validation scenes.

    A standard deviation is floored at 1e-6 (and is 1 with a single scene), so the combined score stays finite.

    Args:
        energy: (n,) ``energy`` of the known validation scenes, n >= 1.
        class_scores: (n,) their (leave-one-out) ``class_mahalanobis``.
    """
    if energy.numel() < 1 or energy.numel() != class_scores.numel():
        raise ValueError(f"the score norm needs matching scores of at least one scene, got {energy.numel()} and {class_scores.numel()}")
    spread = lambda v: float(v.std()) if v.numel() > 1 else 1.0  # noqa: E731
    e, c = energy.double().flatten(), class_scores.double().flatten()
    return torch.tensor([float(e.mean()), max(spread(e), 1e-6), float(c.mean()), max(spread(c), 1e-6)], dtype=torch.float64)


def combined_score(energy: torch.Tensor, class_scores: torch.Tensor, norm: torch.Tensor) -> torch.Tensor:
    """``(energy - m_e) / s_e + (class_mahalanobis - m_c) / s_c``: the two scores in units of their known spread, summed.

    The logits (``energy``) and the features' distances (``class_mahalanobis``) miss different unknown scenes: a
    sofa taken for a car can have a car's logits yet lie off the cars' features, and the reverse; the sum ranks
    fresh scenes better than either (design runs: AUROC 0.984 against 0.944-0.965).

    Args:
        energy: (...,) energy scores.
        class_scores: (...,) class_mahalanobis scores, same shape.
        norm: (4,) from :func:`fit_score_norm`.

    Returns:
        (...,) float64 scores, higher = more like a known category.
    """
    n = norm.double()
    return (energy.double() - n[0]) / n[1] + (class_scores.double() - n[2]) / n[3]
