"""Train a scene classifier on a generated collection and calibrate its unknown threshold.

Data use (nothing else is read):

- **training**: every view of the collection's ``train`` scenes of the known categories (all
  categories minus ``holdout_categories``), augmented (:func:`classifier.data.augment_views`);
- **calibration and validation metrics**: the ``val`` scenes of the known categories, all their
  views, without augmentation. The unknown threshold of each score keeps ``keep_fraction`` of
  these scenes (``threshold_rule``; ``combined`` is standardised by their scores too); a
  collection with fewer scenes or views than :data:`~classifier.config.CALIBRATION_NEEDS` is
  warned about (log, ``classifier.json["calibration"]["warnings"]``, the CLI's output);
- **held-out report**: the ``val`` scenes of the held-out categories, scored to report how well
  each score flags them and, with ``score="auto"``, to pick the score with the best AUROC (never
  used for a threshold);
- the ``test`` scenes are not touched (they are for ``scripts/bench_classifier.py``).

The output folder is built under a hidden sibling name and renamed into place at the end, so an
error or an interruption never leaves a partial classifier at ``out`` (:mod:`nerfmeta.runfolder`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
import torch.nn.functional as F

from nerfmeta.collection.generate import Collection, SceneRecord, load_collection
from nerfmeta.errors import ConfigError
from nerfmeta.io import to_jsonable, write_json
from nerfmeta.metrics import LpipsUnavailable
from nerfmeta.runfolder import check_target, run_folder

from classifier.config import (CALIBRATION_NEEDS, CLASS_SCORE_TRAIN_SCENES, DEFAULT_SCORE, SCALE_PRIOR_GRID, SCORES,
                               CalibrationNeeds, TrainConfig)
from classifier.data import ViewSet, augment_views, chimera_partners, chimera_views, load_view_set, normalize
from classifier.model import SceneNet, build_model, load_pretrained
from classifier.plots import plot_training_curve
from classifier.reference import (REFERENCE_SCENES, REFERENCE_SIZE, REFERENCE_VIEWS, fit_reference, fused_threshold, load_trunk,
                                  view_descriptors)
from classifier.predict import (
    FeatureStats,
    auroc,
    combined_score,
    calibrate_threshold,
    fit_class_scale,
    fit_feature_stats,
    fit_score_norm,
    leave_one_out_class_scores,
    scene_distances,
    select_scale_prior,
    scene_probabilities,
    scene_scores,
)
from classifier.store import CURVE_FILE, HISTORY_FILE, META_FILE, Classifier, ClassifierMeta, model_inputs, save_classifier, view_outputs

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainEvent:
    """What a progress callback receives.

    Attributes:
        stage: ``load`` (a scene was read), ``step`` (an optimisation step), ``epoch`` (an epoch
            ended and was validated) or ``calibrate`` (training ended, scoring validation scenes).
        step: optimisation steps done.
        total_steps: steps planned (``epochs * steps_per_epoch``).
        epoch: epochs done (fractional within an epoch).
        time_s: optimisation wall time so far (loading and validation excluded).
        loss: the step's training loss (``step``), or None.
        val_accuracy: scene-level validation accuracy (``epoch``), or None.
        loaded: scenes read so far and ``total`` to read (``load``).
    """

    stage: str
    step: int = 0
    total_steps: int = 0
    epoch: float = 0.0
    time_s: float = 0.0
    loss: float | None = None
    val_accuracy: float | None = None
    loaded: int = 0
    total: int = 0


Callback = Callable[[TrainEvent], None]


@dataclass(frozen=True)
class Splits:
    """The scenes each stage uses."""

    categories: tuple[str, ...]
    """Known categories, in class order."""
    train: tuple[SceneRecord, ...]
    """Training scenes of the known categories."""
    val: tuple[SceneRecord, ...]
    """Validation scenes of the known categories (calibration)."""
    holdout_val: tuple[SceneRecord, ...]
    """Validation scenes of the held-out categories (reported only)."""


def plan_splits(collection: Collection, holdout: Sequence[str]) -> Splits:
    """Known categories and the scenes of each stage; ConfigError when a stage would be empty."""
    present = list(dict.fromkeys(str(c) for c in collection.config.get("categories", ())))
    for record in collection.scenes:
        if record.category not in present:
            present.append(record.category)
    missing = [c for c in holdout if c not in present]
    if missing:
        raise ConfigError(f"--holdout-categories {','.join(missing)}: not in the collection (it has {', '.join(present)})")
    known = tuple(c for c in present if c not in holdout)
    if len(known) < 2:
        raise ConfigError(f"{len(known)} known categor{'y' if len(known) == 1 else 'ies'} left after --holdout-categories; need at least 2")
    train = tuple(r for r in collection.scenes if r.split == "train" and r.category in known)
    val = tuple(r for r in collection.scenes if r.split == "val" and r.category in known)
    for category in known:
        if not any(r.category == category for r in train):
            raise ConfigError(f"{collection.root}: category {category!r} has no 'train' scene")
    if not val:
        raise ConfigError(
            f"{collection.root}: no 'val' scenes of the known categories to calibrate the unknown threshold on; "
            "generate the collection with --val-fraction > 0 and enough scenes per category"
        )
    holdout_val = tuple(r for r in collection.scenes if r.split == "val" and r.category in holdout)
    return Splits(known, train, val, holdout_val)


def lr_factor(progress: float, warmup: float) -> float:
    """One-cycle schedule: linear warm-up over ``warmup`` of the run, then cosine decay to 0.

    Args:
        progress: fraction of the run done, in [0, 1].
        warmup: fraction of the run spent warming up, in [0, 1).
    """
    progress = min(max(progress, 0.0), 1.0)
    if progress < warmup:
        return (progress + 1e-3) / (warmup + 1e-3)
    return 0.5 * (1.0 + math.cos(math.pi * (progress - warmup) / (1.0 - warmup)))


@torch.no_grad()
def scene_outputs(model: SceneNet, views: ViewSet, meta: ClassifierMeta) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per scene of ``views``: (features (n_views, dim), logits (n_views, n_classes)), no augmentation."""
    inputs = model_inputs(views.float_views(slice(None)), meta)
    features, logits = view_outputs(model, inputs, mirror=meta.mirror_views)
    n = len(views)
    rows = [views.scene_views(k) for k in range(len(views.scenes))]
    if meta.mirror_views:  # a view's mirror image is the row n further down
        rows = [torch.cat([idx, idx + n]) for idx in rows]
    return [(features[idx], logits[idx]) for idx in rows]


def scene_accuracy(outputs: list[tuple[torch.Tensor, torch.Tensor]], views: ViewSet) -> float:
    """Fraction of scenes whose view-averaged probabilities pick their own category."""
    labels = [int(views.labels[views.scene_views(k)[0]]) for k in range(len(outputs))]
    hits = [int(scene_probabilities(z).argmax()) == y for (_, z), y in zip(outputs, labels)]
    return sum(hits) / max(1, len(hits))


def _meta(config: TrainConfig, categories: tuple[str, ...], score: str = "msp", thresholds: dict | None = None) -> ClassifierMeta:
    thresholds = thresholds or {}
    return ClassifierMeta(
        categories=categories, arch=config.arch, stem=config.stem,
        input_size=config.input_size, background=config.background, mean=config.mean, std=config.std,
        score=score, threshold=float(thresholds.get(score, 0.0)), thresholds=dict(thresholds), mirror_views=config.mirror_views,
    )


def uniform_cross_entropy(logits: torch.Tensor) -> torch.Tensor:
    """Mean KL divergence from the uniform distribution over the classes to softmax(``logits``): the outlier-exposure loss.

    ``logsumexp(z) - mean(z) - log C`` per row (the cross-entropy to uniform less its minimum): 0 exactly when every
    logit of a row is equal.
    """
    return (torch.logsumexp(logits, -1) - logits.mean(-1)).mean() - math.log(logits.shape[-1])


def fit_network(
    model: SceneNet,
    train: ViewSet,
    val: ViewSet,
    config: TrainConfig,
    callbacks: Sequence[Callback] = (),
) -> dict[str, Any]:
    """Optimise ``model`` on augmented training views; validate on ``val`` after every epoch.

    The validation after each epoch uses ``config.monitor_views`` evenly spaced views of each
    scene (a cheap monitor for the curve); ``time_s`` and the time budget count it.

    Returns:
        history: ``step_loss`` (per step), ``step_time_s``, ``epochs`` (one record per epoch with
        ``epoch``, ``step``, ``time_s``, ``train_loss``, ``val_scene_accuracy``, ``val_view_accuracy``),
        ``steps``, ``time_s`` and ``stop_reason``.
    """
    device = torch.device(config.device)
    model.to(device).train()
    generator = torch.Generator().manual_seed(config.seed)
    meta = replace(_meta(config, tuple(str(i) for i in range(model.num_classes))), mirror_views=False)  # the monitor: plain views
    decay, no_decay = [], []
    for p in model.parameters():
        (no_decay if p.dim() == 1 else decay).append(p)  # no weight decay on BatchNorm and biases
    optimizer = torch.optim.AdamW(
        [{"params": decay, "weight_decay": config.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
        lr=config.lr,
        fused=device.type in ("cpu", "cuda"),  # one kernel for all parameters: much faster on CPU too
    )
    n = len(train)
    steps_per_epoch = max(1, n // config.batch_size)  # drop the last partial batch (BatchNorm)
    total = steps_per_epoch * config.epochs
    history: dict[str, Any] = {"step_loss": [], "step_time_s": [], "epochs": [], "steps_per_epoch": steps_per_epoch}
    monitor = val.subset(config.monitor_views)
    step, elapsed, stop = 0, 0.0, "epochs"
    t0 = time.perf_counter()
    for epoch in range(config.epochs):
        order = torch.randperm(n, generator=generator)
        losses = []
        for b in range(steps_per_epoch):
            progress = step / total
            if config.time_budget_s:
                progress = max(progress, elapsed / config.time_budget_s)
            for group in optimizer.param_groups:
                group["lr"] = config.lr * lr_factor(progress, config.warmup_fraction)
            idx = order[b * config.batch_size : (b + 1) * config.batch_size]
            rgb = augment_views(train.float_views(idx), config.augment, config.background, generator)
            if config.outlier_exposure > 0:
                first, second = chimera_partners(train.labels, len(idx) // 2, generator)
                chimeras = chimera_views(train.float_views(first), train.float_views(second), generator)
                rgb = torch.cat([rgb, augment_views(chimeras, config.augment, config.background, generator)])
            inputs = normalize(rgb, config.mean, config.std).to(device)
            _, logits = model(inputs)
            loss = F.cross_entropy(logits[: len(idx)], train.labels[idx].to(device))
            if config.outlier_exposure > 0:
                loss = loss + config.outlier_exposure * uniform_cross_entropy(logits[len(idx):])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            elapsed = time.perf_counter() - t0  # validation included: the budget bounds wall time
            step += 1
            value = float(loss.detach())
            if not math.isfinite(value):
                raise ConfigError(f"training diverged at step {step} (loss {value}); lower --lr")
            losses.append(value)
            history["step_loss"].append(value)
            history["step_time_s"].append(elapsed)
            for cb in callbacks:
                cb(TrainEvent("step", step, total, epoch + (b + 1) / steps_per_epoch, elapsed, loss=value))
            if config.time_budget_s and elapsed >= config.time_budget_s:
                stop = "time budget"
                break
        outputs = scene_outputs(model, monitor, meta)
        logits = torch.cat([z for _, z in outputs])
        labels = torch.cat([monitor.labels[monitor.scene_views(k)] for k in range(len(outputs))])
        record = {
            "epoch": epoch + len(losses) / steps_per_epoch,
            "step": step,
            "time_s": elapsed,
            "train_loss": sum(losses) / max(1, len(losses)),
            "val_loss": float(F.cross_entropy(logits, labels)),
            "val_scene_accuracy": scene_accuracy(outputs, monitor),
            "val_view_accuracy": float((logits.argmax(-1) == labels).float().mean()),
        }
        history["epochs"].append(record)
        elapsed = time.perf_counter() - t0
        log.info("epoch %.2f: loss %.4f, val scene accuracy %.3f", record["epoch"], record["train_loss"], record["val_scene_accuracy"])
        for cb in callbacks:
            cb(TrainEvent("epoch", step, total, record["epoch"], elapsed, loss=record["train_loss"],
                          val_accuracy=record["val_scene_accuracy"]))
        if stop != "epochs":
            break
    model.eval()
    history.update(steps=step, time_s=elapsed, stop_reason=stop)
    return history


def score_table(outputs: list[tuple[torch.Tensor, torch.Tensor]], stats: FeatureStats) -> dict[str, torch.Tensor]:
    """Score name -> (n_scenes,) scores of each scene (the scores ``stats`` can compute)."""
    rows = [scene_scores(z, f, stats) for f, z in outputs]
    return {name: torch.tensor([r[name] for r in rows], dtype=torch.float64) for name in SCORES if all(name in r for r in rows)}


@dataclass(frozen=True)
class CalibrationInputs:
    """Everything calibration reads from the network, so a rule can be re-run without it (``scripts/bench_classifier.py``).

    Attributes:
        train_features: (n_views, dim) features of the training views the statistics use (not augmented).
        train_logits: (n_views, n_classes) their logits.
        train_labels: (n_views,) class of each view.
        train_scene_index: (n_views,) training scene of each view.
        val: per known validation scene, (features (n_views, dim), logits (n_views, n_classes)).
        val_labels: (n_val,) class of each known validation scene.
        holdout_val: per held-out validation scene, (features, logits).
        reference_known: per known scene (training scenes, at most :data:`REFERENCE_SCENES` per category, then every
            validation scene), (n_views, dim') ImageNet descriptors (:mod:`classifier.reference`); None without a
            reference network.
        reference_labels: (n_known,) class of each of them.
        reference_val_index: (n_val,) row of ``reference_known`` of each known validation scene, in ``val``'s order.
        reference_holdout_val: per held-out validation scene, its descriptors.
    """

    train_features: torch.Tensor
    train_logits: torch.Tensor
    train_labels: torch.Tensor
    train_scene_index: torch.Tensor
    val: list[tuple[torch.Tensor, torch.Tensor]]
    val_labels: torch.Tensor
    holdout_val: list[tuple[torch.Tensor, torch.Tensor]]
    reference_known: list[torch.Tensor] | None = None
    reference_labels: torch.Tensor | None = None
    reference_val_index: torch.Tensor | None = None
    reference_holdout_val: list[torch.Tensor] | None = None


def scene_descriptors(trunk: torch.nn.Sequential, views: ViewSet, background, per_scene: int) -> list[torch.Tensor]:
    """Per scene of ``views``, the ImageNet descriptors of its first ``per_scene`` views (evenly spaced)."""
    sample = views.subset(per_scene)
    desc = view_descriptors(trunk, sample.float_views(slice(None)), background)
    return [desc[sample.scene_index == k] for k in range(len(sample.scenes))]


def reference_inputs(trunk: torch.nn.Sequential, train: ViewSet, val: ViewSet, holdout_val: ViewSet, background) -> dict[str, Any]:
    """:class:`CalibrationInputs`' reference fields: the descriptors of :data:`REFERENCE_VIEWS` views of
    :data:`REFERENCE_SCENES` training scenes per category, of every known validation scene and every held-out one."""
    train = train.limit_scenes(REFERENCE_SCENES)
    known = scene_descriptors(trunk, train, background, REFERENCE_VIEWS)
    val_desc = scene_descriptors(trunk, val, background, REFERENCE_VIEWS)
    labels = [int(v.labels[v.scene_views(k)[0]]) for v in (train, val) for k in range(len(v.scenes))]
    return dict(
        reference_known=known + val_desc,
        reference_labels=torch.tensor(labels, dtype=torch.long),
        reference_val_index=torch.arange(len(known), len(known) + len(val_desc)),
        reference_holdout_val=scene_descriptors(trunk, holdout_val, background, REFERENCE_VIEWS) if len(holdout_val.scenes) else [],
    )


@torch.no_grad()
def calibration_inputs(
    model: SceneNet, train: ViewSet, val: ViewSet, holdout_val: ViewSet, config: TrainConfig, categories: tuple[str, ...],
    trunk: torch.nn.Sequential | None = None,
) -> CalibrationInputs:
    """The network's outputs on the first ``config.stats_views`` views of each training scene and on every view of
    the validation scenes (no augmentation); with ``trunk``, the ImageNet descriptors of :data:`REFERENCE_VIEWS` views of
    :data:`REFERENCE_SCENES` training scenes per category, every known validation scene and every held-out one too."""
    meta = _meta(config, categories)
    sample = train.subset(config.stats_views)
    features, logits = view_outputs(model, model_inputs(sample.float_views(slice(None)), meta), mirror=config.mirror_views)
    copies = 2 if config.mirror_views else 1  # mirrored views follow, in the same order
    val_out = scene_outputs(model, val, meta)
    labels = torch.tensor([int(val.labels[val.scene_views(k)[0]]) for k in range(len(val_out))], dtype=torch.long)
    held = scene_outputs(model, holdout_val, meta) if len(holdout_val.scenes) else []
    reference = reference_inputs(trunk, train, val, holdout_val, config.background) if trunk is not None else {}
    return CalibrationInputs(features, logits, sample.labels.repeat(copies), sample.scene_index.repeat(copies), val_out, labels, held,
                             **reference)


def calibrate(
    model: SceneNet,
    train: ViewSet,
    val: ViewSet,
    holdout_val: ViewSet,
    config: TrainConfig,
    categories: tuple[str, ...],
    trunk: torch.nn.Sequential | None = None,
) -> tuple[FeatureStats, dict[str, float], dict[str, Any]]:
    """:func:`calibrate_inputs` of the network's :func:`calibration_inputs`."""
    return calibrate_inputs(calibration_inputs(model, train, val, holdout_val, config, categories, trunk), config, len(categories))


def calibrate_inputs(
    data: CalibrationInputs, config: TrainConfig, n_classes: int
) -> tuple[FeatureStats, dict[str, float], dict[str, Any]]:
    """Feature statistics of the training scenes, a threshold per score, and validation metrics.

    The class scale of ``class_mahalanobis`` comes from the known validation scenes, shrunk towards
    the pooled scale by ``config.scale_prior_scenes`` (or the prior of
    :data:`~classifier.config.SCALE_PRIOR_GRID` with the best leave-one-out likelihood,
    :func:`~classifier.predict.select_scale_prior`); their own ``class_mahalanobis`` scores, for its
    threshold and validation metrics, are leave-one-out scores
    (:func:`~classifier.predict.leave_one_out_class_scores`), so they are as unbiased as a new scene's.
    The threshold of each score is drawn by ``config.threshold_rule`` (:func:`threshold_for_rule`), except ``fused``'s
    (only with reference descriptors in ``data``): :func:`~classifier.reference.fused_threshold` at
    ``config.reference_keep_fraction``, over the validation scenes' ``combined`` and every known scene's leave-one-out
    reference score.

    Returns:
        stats, thresholds (score -> threshold), metrics (``metrics["calibration"]`` says which prior
        and rule were used).
    """
    stats = fit_feature_stats(data.train_features, data.train_labels, data.train_scene_index, n_classes,
                              config.covariance_shrinkage)
    y = data.val_labels
    labels = y.tolist()
    distances = torch.stack([scene_distances(f, stats) for f, _ in data.val])
    shape = stats.train_scale if config.class_scale_prior == "train" else None
    prior, chosen_by = config.scale_prior_scenes, "given"
    if prior is None:
        prior, chosen_by = SCALE_PRIOR_GRID[0], "smallest of the grid (one validation scene: nothing to choose on)"
        if len(labels) >= 2:
            prior = select_scale_prior(distances, y, n_classes, SCALE_PRIOR_GRID, shape)
            chosen_by = "leave-one-out likelihood of the validation distances"
    stats = replace(stats, class_scale=fit_class_scale(distances, y, n_classes, prior, shape).float())
    known = known_val_scores(data, stats, distances, n_classes, prior, shape)
    stats = replace(stats, score_norm=fit_score_norm(known["energy"], known["class_mahalanobis"]).float())
    known["combined"] = combined_score(known["energy"], known["class_mahalanobis"], stats.score_norm)
    thresholds, rule_notes = threshold_for_rule(data, stats, known, distances, config, prior)
    held = score_table(data.holdout_val, stats) if data.holdout_val else None
    if data.reference_known is not None:
        reference, loo = fit_reference(data.reference_known, data.reference_labels, n_classes, config.covariance_shrinkage)
        stats = replace(stats, reference=reference)
        loo_z = (loo - reference.norm[0].double()) / reference.norm[1].double()
        known["fused"] = known["combined"] + loo_z[data.reference_val_index]
        thresholds["fused"] = fused_threshold(known["combined"], loo_z, config.reference_keep_fraction)
        if held is not None:
            held["fused"] = held["combined"] + torch.tensor([reference.z(d) for d in data.reference_holdout_val], dtype=torch.float64)
    correct = torch.tensor([int(scene_probabilities(z).argmax()) == c for (_, z), c in zip(data.val, labels)])
    metrics: dict[str, Any] = {
        "val_scenes": len(labels),
        "val_views": sum(int(f.shape[0]) for f, _ in data.val),
        "val_scene_accuracy": float(correct.float().mean()),
        "calibration": {"threshold_rule": config.threshold_rule, "keep_fraction": config.keep_fraction,
                        "class_scale_prior": config.class_scale_prior, "mirror_views": config.mirror_views,
                        "scale_prior_scenes": prior, "scale_prior_chosen_by": chosen_by, **rule_notes},
        "scores": {},
    }
    metrics["holdout_val_scenes"] = len(data.holdout_val)
    metrics["fewest_train_scenes"] = fewest_scenes_per_class(data.train_labels, data.train_scene_index, n_classes)
    for name in (name for name in SCORES if name in thresholds):
        flagged = known[name] < thresholds[name]
        entry = {
            "threshold": thresholds[name],
            "val_false_unknown_rate": float(flagged.double().mean()),
            "val_correct_and_known": float((correct & ~flagged).double().mean()),
        }
        if held is not None:
            entry["holdout_val_detection_rate"] = float((held[name] < thresholds[name]).double().mean())
            entry["holdout_val_auroc"] = auroc(known[name], held[name])
        metrics["scores"][name] = entry
    return stats, thresholds, metrics


def known_val_scores(
    data: CalibrationInputs, stats: FeatureStats, distances: torch.Tensor, n_classes: int, prior: float,
    shape: torch.Tensor | None,
) -> dict[str, torch.Tensor]:
    """Score name -> (n_val,) scores of the known validation scenes, ``class_mahalanobis`` leave-one-out where
    there are two scenes or more (:func:`calibrate_inputs`; ``combined`` is left to the caller, it needs the norm
    these scores give).

    Args:
        data: the network's outputs.
        stats: the fitted statistics, class scale included.
        distances: (n_val, n_classes) the scenes' distances to each class mean.
        n_classes: number of known classes.
        prior: the class scale's prior, in scenes; shape: its per-class shape (None: pooled).
    """
    known = score_table(data.val, stats)
    if len(data.val_labels) >= 2:
        known["class_mahalanobis"] = leave_one_out_class_scores(distances, data.val_labels, n_classes, prior, shape)
    return known


def threshold_for_rule(
    data: CalibrationInputs, stats: FeatureStats, known: dict[str, torch.Tensor], distances: torch.Tensor,
    config: TrainConfig, prior: float,
) -> tuple[dict[str, float], dict[str, Any]]:
    """Score name -> threshold by ``config.threshold_rule``, and notes for ``classifier.json["calibration"]``.

    Args:
        data: the network's outputs.
        stats: the fitted statistics, class scale included.
        known: score name -> (n_val,) scores of the known validation scenes (``class_mahalanobis`` leave-one-out).
        distances: (n_val, n_classes) their distances to each class mean.
        config: the recipe.
        prior: the class scale's prior, in scenes.
    """
    return {name: calibrate_threshold(known[name], config.keep_fraction, config.threshold_rule) for name in SCORES
            if name in known}, {}


def calibration_warnings(
    train_scenes: dict[str, int], val_scenes: dict[str, int], val_views: int, needs: CalibrationNeeds = CALIBRATION_NEEDS
) -> list[str]:
    """One line per need of ``needs`` the collection falls short of (empty when it has enough).

    Args:
        train_scenes: known category -> its training scenes.
        val_scenes: known category -> its known validation scenes (absent = 0).
        val_views: the fewest views of any known validation scene.
        needs: the minimums.
    """
    def short(counts: dict[str, int], need: int) -> str:
        low = sorted((n, c) for c, n in counts.items() if n < need)
        return ", ".join(f"{c} {n}" for n, c in low)

    lines = []
    val = {c: val_scenes.get(c, 0) for c in train_scenes}
    if short(val, needs.val_scenes_per_category):
        lines.append(
            f"too few known validation scenes to calibrate the unknown threshold ({short(val, needs.val_scenes_per_category)}; "
            f"need >= {needs.val_scenes_per_category} per category): fresh scenes of these categories may be flagged unknown; "
            "generate more scenes per category or a larger --val-fraction")
    if short(train_scenes, needs.train_scenes_per_category):
        lines.append(
            f"too few training scenes per category for the unknown score ({short(train_scenes, needs.train_scenes_per_category)}; "
            f"need >= {needs.train_scenes_per_category}): generate more scenes per category")
    if val_views < needs.views_per_scene:
        lines.append(f"validation scenes have as few as {val_views} views (need >= {needs.views_per_scene} to calibrate): "
                     "generate the collection with more --views")
    return lines


def fewest_scenes_per_class(labels: torch.Tensor, scene_index: torch.Tensor, n_classes: int) -> int:
    """The fewest distinct scenes any of the ``n_classes`` classes has among (n_views,) views labelled ``labels``
    and numbered by scene ``scene_index`` (0 for a class without views)."""
    return min(int(scene_index[labels == c].unique().numel()) for c in range(n_classes))


def fallback_score(metrics: dict[str, Any]) -> str:
    """The score ``auto`` falls back to: ``class_mahalanobis`` when every known category has
    :data:`CLASS_SCORE_TRAIN_SCENES` training scenes (``metrics["fewest_train_scenes"]``), else ``fused`` when it was
    calibrated (a reference network), else :data:`DEFAULT_SCORE`."""
    if metrics.get("fewest_train_scenes", 0) >= CLASS_SCORE_TRAIN_SCENES:
        return "class_mahalanobis"
    return "fused" if "fused" in metrics.get("scores", {}) else DEFAULT_SCORE


def select_score(requested: str, metrics: dict[str, Any], min_holdout_scenes: int = CALIBRATION_NEEDS.holdout_val_scenes) -> tuple[str, str]:
    """The score the decision uses, and why.

    ``auto`` takes the highest AUROC on the held-out categories' validation scenes (ties go to the
    fallback (:func:`fallback_score`), then :data:`DEFAULT_SCORE`, then :data:`SCORES` order); with fewer than
    ``min_holdout_scenes`` of them (an AUROC on a handful of scenes picks noise) it takes the fallback.
    Any other value is used as given.
    """
    if requested != "auto":
        return requested, "given"
    aurocs = {name: entry.get("holdout_val_auroc") for name, entry in metrics["scores"].items()}
    held = metrics.get("holdout_val_scenes", 0)
    fallback = fallback_score(metrics)
    why = (f"{metrics.get('fewest_train_scenes', 0)} training scenes in the smallest category"
           f"{'' if fallback == DEFAULT_SCORE else f' (>= {CLASS_SCORE_TRAIN_SCENES})'}")
    if any(v is None for v in aurocs.values()) or held < max(1, min_holdout_scenes):
        return fallback, (f"fallback for {why} ({held} held-out validation scenes to compare the scores on; "
                          f"auto compares them from {max(1, min_holdout_scenes)})")
    order = [s for s in dict.fromkeys((fallback, DEFAULT_SCORE, *SCORES)) if s in aurocs]
    best = max(order, key=lambda s: (aurocs[s], -order.index(s)))
    if best == fallback and sum(aurocs[s] == aurocs[best] for s in order) > 1:
        return best, f"best AUROC on the held-out categories' validation scenes, tied: the fallback for {why}"
    return best, "best AUROC on the held-out categories' validation scenes"


def train_classifier(
    config: TrainConfig,
    collection_path: str | os.PathLike,
    out: str | os.PathLike,
    *,
    overwrite: bool = False,
    callbacks: Sequence[Callback] = (),
) -> dict[str, Any]:
    """Train, calibrate and write a classifier folder (see :mod:`classifier.store` for the files).

    Args:
        config: the recipe (validated first; nothing is written if it is invalid).
        collection_path: a collection folder or its ``collection.json``.
        out: the classifier folder; must be absent or empty, or an earlier classifier with ``overwrite``.
        callbacks: progress callbacks (see :class:`TrainEvent`).

    Returns:
        the ``classifier.json`` document written.
    """
    config.validate()
    out = Path(os.path.abspath(out))
    check_output(out, overwrite)
    wall_start = time.perf_counter()
    collection = load_collection(collection_path)
    splits = plan_splits(collection, config.holdout_categories)
    model = build_model(config.arch, len(splits.categories), stem=config.stem, seed=config.seed)
    fresh = load_pretrained(model, config.weights) if config.weights else None

    total = len(splits.train) + len(splits.val) + len(splits.holdout_val)
    loaded = [0]

    def progress(record: SceneRecord) -> None:
        loaded[0] += 1
        for cb in callbacks:
            cb(TrainEvent("load", loaded=loaded[0], total=total))

    kwargs = dict(size=config.input_size, background=config.background, progress=progress)
    train = load_view_set(collection, splits.train, splits.categories, **kwargs)
    val = load_view_set(collection, splits.val, splits.categories, **kwargs)
    holdout_val = load_view_set(collection, splits.holdout_val, splits.categories, **kwargs)
    load_s = time.perf_counter() - wall_start

    history = fit_network(model, train, val, config, callbacks)
    for cb in callbacks:
        cb(TrainEvent("calibrate", history["steps"], history["steps"], time_s=history["time_s"]))
    model.cpu()
    fewest = fewest_scenes_per_class(train.labels, train.scene_index, len(splits.categories))
    trunk, reference_note = reference_trunk(config.reference, reference_skip_reason(config, fewest))
    calibration_start = time.perf_counter()
    stats, thresholds, metrics = calibrate(model, train, val, holdout_val, replace(config, device="cpu"), splits.categories, trunk)
    calibration_s = time.perf_counter() - calibration_start
    score, rule = select_score(config.score, metrics)
    metrics["score_selection"] = {"score": score, "rule": rule}
    count = lambda records: {c: sum(r.category == c for r in records) for c in splits.categories}  # noqa: E731
    warnings = calibration_warnings(count(splits.train), count(splits.val),
                                    min(len(val.scene_views(k)) for k in range(len(val.scenes))))
    for line in warnings:
        log.warning("%s: %s", collection.root, line)
    calibration = {**metrics.pop("calibration"), "needs": to_jsonable(CALIBRATION_NEEDS), "warnings": warnings}
    meta = _meta(config, splits.categories, score, thresholds)
    wall_s = time.perf_counter() - wall_start

    extra = {
        "holdout_categories": list(config.holdout_categories),
        "recipe": to_jsonable(config),
        "training": {
            "collection": str(collection.root),
            "train_scenes": len(splits.train),
            "train_views": len(train),
            "val_scenes": len(splits.val),
            "steps": history["steps"],
            "epochs_done": history["epochs"][-1]["epoch"] if history["epochs"] else 0.0,
            "stop_reason": history["stop_reason"],
            "optimisation_time_s": round(history["time_s"], 2),
            "load_time_s": round(load_s, 2),
            "calibration_time_s": round(calibration_s, 2),
            "wall_time_s": round(wall_s, 2),
            "pretrained_weights": config.weights,
            "fresh_parameters": fresh,
            "torch_threads": torch.get_num_threads(),
        },
        "reference": reference_note,
        "validation": metrics,
        "calibration": calibration,
    }
    with run_folder(out, "classifier", overwrite=overwrite, aside=True) as run:  # built aside, swapped in when complete
        save_classifier(run.dir, Classifier(meta, model, stats), extra)
        write_json(run.dir / HISTORY_FILE, history)
        plot_training_curve(history, run.dir / CURVE_FILE, title=f"{config.arch}, {len(splits.categories)} categories")
    return json.loads((out / META_FILE).read_text())


def reference_skip_reason(config: TrainConfig, fewest_train_scenes: int) -> str | None:
    """Why the reference network is not worth its cost for this training (one line), or None when it is.

    With ``--score auto`` and :data:`CLASS_SCORE_TRAIN_SCENES` training scenes in every known category, ``auto`` falls
    back to ``class_mahalanobis``; measured at 40 scenes per category it kept it with ``fused`` on offer (every held-out
    validation AUROC tied at 1.0), while the trunk would add minutes to a training meant to fit in ten.
    """
    if config.reference != "none" and config.score == "auto" and fewest_train_scenes >= CLASS_SCORE_TRAIN_SCENES:
        return (f"not computed: {fewest_train_scenes} training scenes in the smallest category (>= {CLASS_SCORE_TRAIN_SCENES}), "
                "so --score auto falls back to class_mahalanobis; --score fused asks for it")
    return None


def reference_trunk(net: str, skip: str | None = None) -> tuple[torch.nn.Sequential | None, dict[str, Any]]:
    """The frozen ImageNet network of the ``fused`` score, or None (``none``, ``skip`` given, or its weights missing:
    warned), and the note ``classifier.json["reference"]`` keeps."""
    if net == "none":
        return None, {"net": "none"}
    if skip:
        return None, {"net": net, "used": False, "why": skip}
    try:
        trunk = load_trunk(net)
    except LpipsUnavailable as err:
        log.warning("no fused score: %s", err)
        return None, {"net": net, "used": False, "why": str(err)}
    return trunk, {"net": net, "used": True, "size": REFERENCE_SIZE, "views_per_scene": REFERENCE_VIEWS,
                   "train_scenes_per_category": REFERENCE_SCENES}


def check_output(out: Path, overwrite: bool) -> None:
    """Raise a one-line error if ``out`` cannot become a classifier folder (:mod:`nerfmeta.runfolder`'s rules)."""
    check_target(out, "classifier", overwrite=overwrite)
