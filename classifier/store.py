"""A classifier folder on disk, and classifying views with a loaded classifier.

Layout (written by ``nerfmeta classifier train``)::

    DIR/model.safetensors    network weights (``net.*``), feature statistics (``feature_stats.*``) and, with a
                             reference network, the ImageNet reference statistics (``reference_stats.*``)
    DIR/classifier.json      categories, input size, background, normalisation, unknown score and
                             threshold, the SHA-256 of model.safetensors, training recipe, metrics
    DIR/training_curve.png   loss and validation accuracy during training
    DIR/history.json         the numbers behind the curve

:func:`load_classifier` checks everything before use (files present, JSON valid, hash of the
weights, tensor names and shapes) and raises :class:`ClassifierError`, one line, otherwise.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from nerfmeta.errors import NerfmetaError
from nerfmeta.io import load_tensors, save_tensors, sha256_file, write_json
from nerfmeta.metrics import LpipsUnavailable

from classifier.config import ARCHITECTURES, SCORES, STEMS
from classifier.data import RGB, composite, normalize
from classifier.model import SceneNet, empty_model
from classifier.predict import FeatureStats, Prediction, decide
from classifier.reference import ReferenceModel, load_trunk, spaced_views, view_descriptors

log = logging.getLogger(__name__)

FORMAT = "nerfmeta-classifier"
VERSION = 1
WEIGHTS_FILE = "model.safetensors"
META_FILE = "classifier.json"
MAX_INPUT_SIZE = 1024
"""Largest input side a classifier.json may ask for (views are resized to it; bigger is a memory bomb)."""
CURVE_FILE = "training_curve.png"
HISTORY_FILE = "history.json"
STATS_PREFIX = "feature_stats."
REFERENCE_PREFIX = "reference_stats."
REFERENCE_FIELDS = ("means", "between", "norm")
"""What a saved reference model holds (classifiers of session 21 also hold an unused ``within`` and ``reference_views``)."""
NO_CLASSIFIER_HINT = (
    "pass --classifier DIR, a folder written by 'nerfmeta classifier train', or --zoo DIR, a model zoo with a classifier"
)


class ClassifierError(NerfmetaError):
    """A classifier folder is missing, incomplete, corrupted or inconsistent."""


@dataclass(frozen=True)
class ClassifierMeta:
    """What a model needs besides its weights to classify a scene (from ``classifier.json``)."""

    categories: tuple[str, ...]
    """Class names in logit order."""
    arch: str
    """torchvision builder name (``resnet18`` or ``resnet50``)."""
    stem: str
    """ResNet stem (see :data:`classifier.config.STEMS`)."""
    input_size: int
    """Side of the square input, in pixels."""
    background: RGB
    """RGB views are composited on."""
    mean: RGB
    """Normalisation mean per channel."""
    std: RGB
    """Normalisation standard deviation per channel."""
    score: str
    """Unknown score the decision uses."""
    threshold: float
    """Scenes whose score is below this are unknown."""
    thresholds: dict[str, float] = field(default_factory=dict)
    """Calibrated threshold of every score (same keep fraction), for comparisons."""
    mirror_views: bool = False
    """Each view is also classified mirrored left-right (False in folders written before it existed)."""


@dataclass(frozen=True)
class Classifier:
    """A ready-to-use classifier: network (eval mode), feature statistics and metadata."""

    meta: ClassifierMeta
    model: SceneNet
    stats: FeatureStats

    def with_score(self, score: str) -> "Classifier":
        """The same classifier deciding with another calibrated score."""
        if score not in self.meta.thresholds:
            raise ClassifierError(f"score {score!r} has no calibrated threshold (have {', '.join(self.meta.thresholds)})")
        meta = ClassifierMeta(**{**self.meta.__dict__, "score": score, "threshold": self.meta.thresholds[score]})
        return Classifier(meta, self.model, self.stats)


def model_inputs(views: torch.Tensor, meta: ClassifierMeta) -> torch.Tensor:
    """(n, 4, S, S) premultiplied RGBA -> (n, 3, S, S) composited on the background and normalised."""
    return normalize(composite(views, meta.background).clamp(0.0, 1.0), meta.mean, meta.std)


@torch.no_grad()
def view_outputs(model: SceneNet, inputs: torch.Tensor, batch_size: int = 128, *, mirror: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (m, dim) and logits (m, n_classes) of normalised inputs (n, 3, S, S), in eval mode.

    ``mirror``: the inputs mirrored left-right follow them as more views, ``m = 2n`` (rows ``n + i`` are input ``i``
    mirrored); otherwise ``m = n``.
    """
    if mirror:
        inputs = torch.cat([inputs, inputs.flip(-1)])
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    feats, logits = [], []
    try:
        for start in range(0, inputs.shape[0], batch_size):
            f, z = model(inputs[start : start + batch_size].to(device))
            feats.append(f.float().cpu())
            logits.append(z.float().cpu())
    finally:
        model.train(was_training)
    return torch.cat(feats), torch.cat(logits)


def classify_views(classifier: Classifier, views: torch.Tensor) -> Prediction:
    """Scene-level prediction from all of a scene's views.

    Args:
        classifier: a loaded classifier.
        views: (n_views, 4, S, S) premultiplied RGBA at the classifier's input size.
    """
    meta = classifier.meta
    if views.dim() != 4 or views.shape[1] != 4 or tuple(views.shape[-2:]) != (meta.input_size, meta.input_size):
        raise ValueError(f"views must be (n, 4, {meta.input_size}, {meta.input_size}), got {tuple(views.shape)}")
    reference = None
    if meta.score == "fused":
        try:
            reference = view_descriptors(cached_trunk("vgg16"), spaced_views(views), meta.background)
        except LpipsUnavailable as err:
            log.warning("deciding with 'combined' instead of 'fused': %s", err)
            classifier = classifier.with_score("combined")
            meta = classifier.meta
    features, logits = view_outputs(classifier.model, model_inputs(views, meta), mirror=meta.mirror_views)
    prediction = decide(logits, features, meta.categories, meta.score, meta.threshold, classifier.stats, reference)
    return replace(prediction, views=int(views.shape[0]))  # the views given, mirrored ones not counted


@functools.lru_cache(maxsize=1)
def cached_trunk(net: str) -> torch.nn.Sequential:
    """:func:`classifier.reference.load_trunk`, loaded once per process."""
    return load_trunk(net)


# --- saving ------------------------------------------------------------------------------------


def classifier_tensors(model: SceneNet, stats: FeatureStats) -> dict[str, torch.Tensor]:
    tensors = {k: v for k, v in model.state_dict().items()}
    tensors[STATS_PREFIX + "means"] = stats.means
    tensors[STATS_PREFIX + "between"] = stats.between
    tensors[STATS_PREFIX + "within"] = stats.within
    tensors[STATS_PREFIX + "reference_views"] = stats.reference_views
    if stats.class_scale is not None:
        tensors[STATS_PREFIX + "class_scale"] = stats.class_scale
    for name in ("score_norm", "train_scale"):
        if getattr(stats, name) is not None:
            tensors[STATS_PREFIX + name] = getattr(stats, name)
    if stats.reference is not None:
        ref = stats.reference
        tensors.update({REFERENCE_PREFIX + k: getattr(ref, k).float() for k in REFERENCE_FIELDS})
    return tensors


def save_classifier(folder: str | os.PathLike, classifier: Classifier, extra: dict[str, Any] | None = None, *,
                    weights_dtype: torch.dtype = torch.float32) -> Path:
    """Write ``model.safetensors`` and ``classifier.json`` into ``folder`` (each atomically).

    Args:
        folder: created if missing.
        classifier: what to save.
        extra: more top-level entries for ``classifier.json`` (recipe, metrics, ...).
        weights_dtype: dtype the network's floating-point weights are stored in; ``torch.float16``
            halves the file (ResNet-18: 45 -> 22 MB) for shipping, and loading widens them back to
            float32. The statistics of the unknown scores (``feature_stats.*``, ``reference_stats.*``) always stay
            float32: their thresholds were calibrated on the float32 values.

    Returns:
        the path of ``classifier.json``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    weights = folder / WEIGHTS_FILE
    tensors = {k: v.to(weights_dtype) if v.is_floating_point() and not k.startswith((STATS_PREFIX, REFERENCE_PREFIX)) else v
               for k, v in classifier_tensors(classifier.model, classifier.stats).items()}
    save_tensors(weights, tensors, metadata={"format": FORMAT})
    meta = classifier.meta
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "categories": list(meta.categories),
        "arch": meta.arch,
        "stem": meta.stem,
        "input": {
            "size": meta.input_size,
            "background": list(meta.background),
            "normalization": {"mean": list(meta.mean), "std": list(meta.std)},
            "mirror_views": meta.mirror_views,
        },
        "unknown": {"score": meta.score, "threshold": meta.threshold, "thresholds": dict(meta.thresholds)},
        "weights": {"file": WEIGHTS_FILE, "sha256": sha256_file(weights), "dtype": str(weights_dtype).removeprefix("torch.")},
        **(extra or {}),
    }
    write_json(folder / META_FILE, doc)
    return folder / META_FILE


# --- loading -----------------------------------------------------------------------------------


def _rgb(value: Any, where: str) -> RGB:
    if not isinstance(value, list) or len(value) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value):
        raise ClassifierError(f"{where} must be a list of three numbers")
    return (float(value[0]), float(value[1]), float(value[2]))


def read_meta(folder: str | os.PathLike) -> tuple[ClassifierMeta, dict[str, Any]]:
    """Parse and check ``classifier.json``; returns the metadata and the whole document."""
    path = Path(folder) / META_FILE
    if not path.is_file():
        raise ClassifierError(f"{path}: file missing; is {Path(folder)} a folder written by 'nerfmeta classifier train'?")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise ClassifierError(f"{path}: cannot read ({err})") from None
    except json.JSONDecodeError as err:
        raise ClassifierError(f"{path}: invalid JSON at line {err.lineno} column {err.colno} (corrupted? retrain)") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ClassifierError(f"{path}: not a nerfmeta classifier (format {doc.get('format') if isinstance(doc, dict) else None!r})")
    if doc.get("version") != VERSION:
        raise ClassifierError(f"{path}: classifier format version {doc.get('version')!r}, this nerfmeta reads {VERSION}")
    try:
        categories = doc["categories"]
        inp, unknown, norm = doc["input"], doc["unknown"], doc["input"]["normalization"]
        if not isinstance(categories, list) or len(categories) < 2 or not all(isinstance(c, str) and c for c in categories):
            raise ClassifierError(f"{path}: 'categories' must list at least two names")
        if len(set(categories)) != len(categories):
            raise ClassifierError(f"{path}: 'categories' lists a name twice")
        if doc["arch"] not in ARCHITECTURES:
            raise ClassifierError(f"{path}: arch {doc['arch']!r} is not one of {', '.join(ARCHITECTURES)}")
        if doc["stem"] not in STEMS:
            raise ClassifierError(f"{path}: stem {doc['stem']!r} is not one of {', '.join(STEMS)}")
        if unknown["score"] not in SCORES:
            raise ClassifierError(f"{path}: unknown score {unknown['score']!r} is not one of {', '.join(SCORES)}")
        size = inp["size"]
        if isinstance(size, bool) or not isinstance(size, int) or not 8 <= size <= MAX_INPUT_SIZE:
            raise ClassifierError(f"{path}: input size {size!r} must be an integer from 8 to {MAX_INPUT_SIZE}")
        threshold = unknown["threshold"]
        thresholds = {str(k): float(v) for k, v in dict(unknown.get("thresholds", {})).items()}
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not math.isfinite(threshold):
            raise ClassifierError(f"{path}: unknown threshold {threshold!r} must be a finite number")
        if not all(math.isfinite(v) for v in thresholds.values()):
            raise ClassifierError(f"{path}: unknown.thresholds must be finite numbers, got {thresholds}")
        background = _rgb(inp["background"], f"{path}: input.background")
        if not all(0.0 <= v <= 1.0 for v in background):
            raise ClassifierError(f"{path}: input.background must be three values in [0, 1], got {list(background)}")
        std = _rgb(norm["std"], f"{path}: input.normalization.std")
        if min(std) <= 0:
            raise ClassifierError(f"{path}: input.normalization.std must be positive")
        meta = ClassifierMeta(
            categories=tuple(categories),
            arch=doc["arch"],
            stem=doc["stem"],
            input_size=size,
            background=background,
            mean=_rgb(norm["mean"], f"{path}: input.normalization.mean"),
            std=std,
            score=unknown["score"],
            threshold=float(threshold),
            thresholds=thresholds or {unknown["score"]: float(threshold)},
            mirror_views=inp.get("mirror_views", False),
        )
        if not isinstance(meta.mirror_views, bool):
            raise ClassifierError(f"{path}: input.mirror_views must be true or false, got {meta.mirror_views!r}")
        if not isinstance(doc["weights"]["sha256"], str):
            raise ClassifierError(f"{path}: weights.sha256 must be a string")
    except (KeyError, TypeError, ValueError) as err:
        raise ClassifierError(f"{path}: missing or malformed entry ({type(err).__name__}: {err}); retrain or restore the file") from None
    return meta, doc


def load_classifier(folder: str | os.PathLike | None, device: str | torch.device = "cpu") -> Classifier:
    """Load and check a classifier folder.

    Raises:
        ClassifierError: no folder given, a missing or corrupted file, a SHA-256 mismatch, or
            weights that do not fit the recorded architecture (one line each).
    """
    if folder is None:
        raise ClassifierError(f"no classifier given: {NO_CLASSIFIER_HINT}")
    folder = Path(folder)
    if not folder.is_dir():
        raise ClassifierError(f"{folder}: classifier folder not found; {NO_CLASSIFIER_HINT}")
    meta, doc = read_meta(folder)
    weights = folder / WEIGHTS_FILE
    if not weights.is_file():
        raise ClassifierError(f"{weights}: weights file missing; retrain with 'nerfmeta classifier train' or restore it")
    digest = sha256_file(weights)
    if digest != doc["weights"]["sha256"]:
        raise ClassifierError(
            f"{weights}: SHA-256 {digest[:12]}... does not match {str(doc['weights']['sha256'])[:12]}... recorded in "
            f"{META_FILE} (file changed or corrupted); retrain or restore it"
        )
    try:
        tensors = load_tensors(weights)
    except Exception as err:  # safetensors raises several types for a damaged file
        raise ClassifierError(f"{weights}: cannot read as safetensors ({type(err).__name__})") from None
    model = empty_model(meta.arch, len(meta.categories), stem=meta.stem)
    own = model.state_dict()
    state = {k: v for k, v in tensors.items() if not k.startswith((STATS_PREFIX, REFERENCE_PREFIX))}
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    wrong = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or wrong:
        what = f"missing {missing[0]}" if missing else f"unexpected {unexpected[0]}" if unexpected else f"shape of {wrong[0]}"
        raise ClassifierError(f"{weights}: tensors do not fit a {meta.arch} with {len(meta.categories)} categories ({what})")
    # Weights stored in half precision (``save_classifier(..., weights_dtype=torch.float16)``, as the
    # model zoo ships them) are widened back: the network always runs in float32.
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    model.load_state_dict(state, assign=True)
    try:
        stats = FeatureStats(*(tensors[STATS_PREFIX + k] for k in ("means", "between", "within", "reference_views")),
                             class_scale=tensors.get(STATS_PREFIX + "class_scale"), score_norm=tensors.get(STATS_PREFIX + "score_norm"),
                             train_scale=tensors.get(STATS_PREFIX + "train_scale"))
    except KeyError:
        raise ClassifierError(f"{weights}: feature statistics missing ({STATS_PREFIX}means/between/within/reference_views)") from None
    dim = model.feature_dim
    if tuple(stats.means.shape) != (len(meta.categories), dim) or any(
        tuple(m.shape) != (dim, dim) for m in (stats.between, stats.within)
    ) or stats.reference_views.numel() != 1 or not float(stats.reference_views) >= 1:
        raise ClassifierError(f"{weights}: feature statistics have the wrong shape for {meta.arch}")
    if stats.class_scale is not None and (tuple(stats.class_scale.shape) != (len(meta.categories),)
                                          or not bool((stats.class_scale > 0).all())):
        raise ClassifierError(f"{weights}: {STATS_PREFIX}class_scale must hold one positive value per category")
    if stats.class_scale is None and "class_mahalanobis" in meta.thresholds:
        raise ClassifierError(f"{weights}: {STATS_PREFIX}class_scale is missing but classifier.json calibrates class_mahalanobis")
    if stats.score_norm is not None and (tuple(stats.score_norm.shape) != (4,) or not bool((stats.score_norm[1::2] > 0).all())):
        raise ClassifierError(f"{weights}: {STATS_PREFIX}score_norm must hold a mean and a positive spread of energy and class_mahalanobis")
    if (stats.score_norm is None or stats.class_scale is None) and "combined" in meta.thresholds:
        raise ClassifierError(f"{weights}: {STATS_PREFIX}score_norm is missing but classifier.json calibrates combined")
    if any(k.startswith(REFERENCE_PREFIX) for k in tensors):
        try:
            means, between, norm = (tensors[REFERENCE_PREFIX + k] for k in REFERENCE_FIELDS)
        except KeyError:
            raise ClassifierError(f"{weights}: reference statistics incomplete (need {REFERENCE_PREFIX}"
                                  f"{'/'.join(REFERENCE_FIELDS)})") from None
        dim = means.shape[-1]
        if (means.dim() != 2 or means.shape[0] != len(meta.categories) or tuple(between.shape) != (dim, dim)
                or tuple(norm.shape) != (2,) or not float(norm[1]) > 0):
            raise ClassifierError(f"{weights}: reference statistics have the wrong shape for {len(meta.categories)} categories")
        stats = replace(stats, reference=ReferenceModel(means, between, norm))
    if stats.reference is None and "fused" in meta.thresholds:
        raise ClassifierError(f"{weights}: {REFERENCE_PREFIX}* is missing but classifier.json calibrates fused")
    model.to(device).eval()
    return Classifier(meta, model, stats)
