"""Benchmark the scene classifier and its unknown answer; record the results in BENCHMARKS.md.

Workload (the issue's): a generated collection of all 8 categories at 64 x 64 with 2 categories
held out of training. ``nerfmeta classifier train`` runs as a fresh process (start-up and reading
the views included in its time); then every **test** scene (never used for training, calibration
or picking the score) is classified from all of its views, exactly as ``nerfmeta classify`` does:

- known categories: the fraction of scenes given the right category and not flagged unknown;
  the fraction falsely flagged unknown;
- held-out categories: the fraction flagged unknown;
- the AUROC (known vs held-out test scenes) of every score the classifier calibrates, and each
  score's detection / false-unknown rates at its own calibrated threshold.

The score the classifier decides with is picked by ``classifier train`` itself (``--score auto``:
the best AUROC on the held-out categories' *val* scenes, recorded in ``classifier.json``), never
from these test scenes; the script prints that validation ranking beside the test figures.

Usage::

    .venv/bin/python scripts/bench_classifier.py [--collection DIR] [--work DIR] [--write]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a file: make the checkout's packages importable
    sys.path.insert(0, str(ROOT))

SECTION = "## Classifier"
MACHINE = "2-core CPU, no GPU"
HOLDOUT = "sofa,vase"
COLLECTION_ARGS = [
    "--categories", "airplane,car,chair,lamp,mug,sofa,table,vase", "--scenes-per-category", "40",
    "--views", "16", "--test-views", "8", "--resolution", "64", "--val-fraction", "0.2", "--test-fraction", "0.25",
]
SEED = 1
"""Collection seed. Seed 0's test scenes were looked at while designing ``class_mahalanobis`` (see the
design notes), so the recorded figures come from seed 1, whose scenes played no part in any choice."""
TARGETS = {"known": 0.98, "detect": 0.90, "false_unknown": 0.05, "train_s": 600.0}
FRESH_ARGS = ["--scenes-per-category", "6", "--views", "10", "--test-views", "4", "--val-fraction", "0.2", "--test-fraction", "0.2"]
"""The fresh collection (``--fresh-seed``): other view counts (10 + 4) than the training collection (16 + 8); every scene is judged."""
FRESH_TARGETS = {"known": 0.95, "detect": 0.90}
"""Issue 14's targets on fresh scenes: known scenes right and not flagged, held-out scenes flagged (median of the runs)."""
DEFAULT_EXTRA = "--time-budget 500"  # leaves ~100 s of the 10 minutes for start-up, reading views and calibration

# Measured while designing (dev collection: 8 categories x 30 scenes x 20 views, sofa,vase held
# out, 12 held-out val scenes, so each is 8 points of detection). Kept here so --write keeps them.
DESIGN_NOTES = """\
How the defaults were chosen (validation data only; a dev collection of 8 categories x 30 scenes x (16 + 4) views,
sofa and vase held out, 36 known and 12 held-out validation scenes; CPU shared as above):

- **Unknown score.** On the same trained network, validation AUROC (known vs held-out val scenes): per-view
  Mahalanobis averaged over views 0.91-0.95, max softmax probability 0.83-0.94, energy 0.68-0.95, k-NN to training
  views (cosine, k = 1..50) 0.74-0.94, k-NN to training scenes' mean features 0.91-0.95; Mahalanobis of the
  *scene's mean feature* under the covariance of the training scenes' mean features 0.96-0.99, the best on every
  network tried, so it is the fallback of `--score auto` (which otherwise takes the best validation AUROC of the
  run: on the benchmark collection energy and Mahalanobis trade places from one training run to the next). A
  two-level variant that subtracted the view noise from that covariance, `between + within / n`, scored
  0.92-0.98: the directions in which training scene means barely vary are the informative ones. The covariance is widened by the view noise only for scenes with fewer views than
  the training scenes had, so a single photo is not flagged for being one view. Shrinkage 0.05 against 0.1:
  0.979 against 0.972.
- **Per-class scale (`class_mahalanobis`, added after the seed-0 benchmark missed two targets: `mahalanobis`
  kept 90 % of known test scenes right and not flagged, 10 % false unknown).** On the two networks trained on the seed-0
  benchmark collection, the false unknowns were lamps and one table: the known
  validation scenes sit 1.9x (car) to 4.5x (table) farther from their class mean than the training scenes, so one
  pooled spread is too tight for the broad categories. Dividing each class's distance by its mean on the known
  validation scenes raised the test AUROC from 0.963 / 0.971 to 1.000 / 1.000. With the threshold on those same
  validation scenes, 5.0-8.3 % of known test scenes were still flagged (a scene scored by a scale that includes it
  looks too typical); with leave-one-out validation scores, 0 %, detection 100 %. These were read off seed-0 *test*
  scenes, so the figures above come from a fresh collection (seed 1) that played no part in the choice.
- **Stem.** A 3x3 stride-2 stem without max-pool (`--stem 3x3s2`, 4x the positions) gave better features per
  image (validation AUROC 0.986 after 4 epochs against 0.979 for torchvision's stem after 9 epochs on the dev
  collection) but is 2.5-3x slower per step here: within the 10-minute budget on the benchmark collection it
  reached 2 epochs (validation AUROC 0.962, validation accuracy 94 %) against 7.9 epochs for torchvision's stem
  (0.992, 100 %), so the default stays torchvision's.
- **Threads.** Under the load other jobs put on this machine, one torch thread trained 2-3x faster than two
  (29 against 11 images/s for ResNet-18 at 64 px).
- **Run to run.** The same recipe trained twice under different load (418 and 423 steps in the 500 s budget)
  differs noticeably on 20 held-out and 60 known test scenes. The earlier run (its score was still fixed to
  `mahalanobis`; `auto` would have picked `energy`, validation AUROC 0.997 against 0.990) scored: `mahalanobis`
  test AUROC 0.963, detection 70 %, false unknown 5.0 % (95.0 % of known scenes right and not flagged);
  `energy` 0.988, 85 %, 1.7 % (98.3 %). Category accuracy on the known test scenes was 100 % in both runs; the
  false unknowns are the same few lamps (a category with three sub-types) and table_033, and the missed held-out
  scenes are sofas taken for cars.
"""


def load_average() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} / {five:.2f} / {fifteen:.2f}"


def run(cmd: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def evaluate(collection: Path, classifier, split: str | None = "test") -> dict:
    """Classify the scenes of ``split`` (None: every scene); per-score AUROC and rates at each score's calibrated threshold.

    ``classifier`` is a classifier folder or a loaded :class:`classifier.store.Classifier`.
    """
    from classifier.inputs import read_scene_views
    from classifier.reference import spaced_views, view_descriptors
    from classifier.store import cached_trunk, load_classifier, model_inputs, view_outputs
    from nerfmeta.collection.generate import load_collection

    clf = load_classifier(classifier) if isinstance(classifier, (str, Path)) else classifier
    meta = clf.meta
    coll = load_collection(collection)
    rows = []
    for record in (coll.by_split(split) if split else coll.scenes):
        views = read_scene_views(coll.scene_path(record), size=meta.input_size, background=meta.background)
        features, logits = view_outputs(clf.model, model_inputs(views, meta), mirror=meta.mirror_views)
        reference = (view_descriptors(cached_trunk("vgg16"), spaced_views(views), meta.background)
                     if clf.stats.reference is not None else None)
        rows.append({"scene": record.name, "category": record.category, "features": features, "logits": logits,
                     "views": int(views.shape[0]), "reference": reference})
    return judge(rows, meta.categories, meta.score, meta.thresholds, clf.stats)


def _median(values: list[float]) -> float:
    return statistics.median(values)


def _span(values: list[float], fmt: str) -> str:
    """``median (min-max)`` of ``values`` in ``fmt``; just the value when every run gave the same."""
    med = format(_median(values), fmt)
    lo, hi = format(min(values), fmt), format(max(values), fmt)
    return med if lo == hi else f"{med} ({lo}-{hi})"


def errors_lines(runs: list[dict], title: str) -> list[str]:
    """A blank line and ``title: seed S: scene: answer; ... | ...``, or nothing when every run got every scene right."""
    errors = [f"seed {r['train_seed']}: " + "; ".join(r["result"]["errors"]) for r in runs if r["result"]["errors"]]
    return ["", f"{title}: " + " | ".join(errors) + "."] if errors else []


def section_text(runs: list[dict], command: str, threads: int, seed: int) -> str:
    """The BENCHMARKS.md section: targets judged on the median over ``runs`` (one per training seed), then each run.

    Each run: ``{"train_seed", "result" (from :func:`evaluate`), "doc" (classifier.json), "train_s", "load_before",
    "load_after"}``.
    """
    first = runs[0]
    doc, result = first["doc"], first["result"]
    holdout = ",".join(doc["holdout_categories"])
    col = lambda key: [r["result"][key] for r in runs]  # noqa: E731
    med = {k: _median(col(k)) for k in ("known_correct_and_known", "known_accuracy", "holdout_detection_rate", "false_unknown_rate")}
    train = [r["train_s"] for r in runs]
    ok = {
        "known": med["known_correct_and_known"] >= TARGETS["known"],
        "detect": med["holdout_detection_rate"] >= TARGETS["detect"],
        "fu": med["false_unknown_rate"] <= TARGETS["false_unknown"],
        "time": _median(train) <= TARGETS["train_s"],
    }
    mark = {True: "met", False: "**missed**"}
    pct = lambda key: _span([100 * v for v in col(key)], ".1f") + " %"  # noqa: E731
    n = len(runs)
    lines = [
        SECTION,
        "",
        f"`nerfmeta classifier train` on a generated collection of 8 categories x 40 scenes x (16 + 8) views at "
        f"64 x 64 (`make-collection {' '.join(COLLECTION_ARGS)} --seed {seed}`), categories **{holdout}** held out of training; "
        f"judged on the collection's **test** scenes (never used for training, calibration or choosing the score), "
        f"each classified from all its {'/'.join(map(str, result['views_per_scene']))} views as `nerfmeta classify` does. "
        f"Trained {n} time{'s' if n > 1 else ''} (training seeds {', '.join(str(r['train_seed']) for r in runs)}); "
        f"the targets are judged on the median over the runs (min-max in brackets).",
        "",
        f"Recipe: {doc['arch']} from scratch, {doc['recipe']['epochs']} epochs planned within a time budget, "
        f"{doc['training']['train_views']} training views of {doc['training']['train_scenes']} scenes; unknown score picked by "
        f"`--score {doc['recipe']['score']}` ({doc['validation']['score_selection']['rule']}), threshold keeping "
        f"{doc['recipe']['keep_fraction']:.0%} of the {doc['validation']['val_scenes']} known validation scenes.",
        "",
        "| target | result | |",
        "| --- | --- | --- |",
        f"| known categories right and not flagged unknown >= 98 % | {pct('known_correct_and_known')} of {result['known_scenes']} scenes "
        f"(category right: {pct('known_accuracy')}) | {mark[ok['known']]} |",
        f"| held-out categories flagged unknown >= 90 % | {pct('holdout_detection_rate')} of {result['holdout_scenes']} scenes | {mark[ok['detect']]} |",
        f"| known scenes falsely flagged unknown <= 5 % | {pct('false_unknown_rate')} | {mark[ok['fu']]} |",
        f"| training time <= 10 min | {_span(train, '.0f')} s for the whole command | {mark[ok['time']]} |",
        "",
        "Each run:",
        "",
        "| training seed | steps (epochs) | score used | right and not flagged | held-out flagged | false unknown | test AUROC (score used) "
        "| training s (optimising) | load before -> after |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        t, res = r["doc"]["training"], r["result"]
        lines.append(
            f"| {r['train_seed']} | {t['steps']} ({t['epochs_done']:.2f}, {t['stop_reason']}) | {res['score']} | "
            f"{res['known_correct_and_known']:.1%} | {res['holdout_detection_rate']:.1%} | {res['false_unknown_rate']:.1%} | "
            f"{res['per_score'][res['score']]['test_auroc']:.3f} | {r['train_s']:.0f} ({t['optimisation_time_s']:.0f}) | "
            f"{r['load_before']} -> {r['load_after']} |")
    lines += [
        "",
        "Every score, each at its own threshold calibrated on the known validation scenes, median over the runs (the "
        "validation columns chose the score; the test columns were not used for any choice):",
        "",
        "| score | val AUROC (held-out val scenes) | val detection | test AUROC | test detection | test false unknown |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name in result["per_score"]:
        def m(values):
            values = [v for v in values if v is not None]
            return "n/a" if not values else f"{_median(values):.3f}"
        val = [r["doc"]["validation"]["scores"].get(name, {}) for r in runs]
        test = [r["result"]["per_score"][name] for r in runs]
        used = sum(r["result"]["score"] == name for r in runs)
        lines.append(
            f"| {name}{f' (used in {used}/{n})' if used else ''} | {m([v.get('holdout_val_auroc') for v in val])} | "
            f"{m([v.get('holdout_val_detection_rate') for v in val])} | {m([t['test_auroc'] for t in test])} | "
            f"{m([t['test_detection_rate'] for t in test])} | {m([t['test_false_unknown_rate'] for t in test])} |")
    lines += errors_lines(runs, "Test scenes the classifier got wrong")
    lines += [
        "",
        f"Command per run: `{command}` (torch threads: {threads}). Machine: {MACHINE}, shared with other jobs "
        f"(load average 1 / 5 / 15 min per run above). Date: {datetime.date.today().isoformat()}. Reproduce: "
        f"`.venv/bin/python scripts/bench_classifier.py --work runs/bench_classifier --write` (generates the collection; "
        "`--collection DIR` reuses one; finished runs in `--work` are reused).",
        "",
        DESIGN_NOTES,
    ]
    return "\n".join(lines)


def collection_args(scenes_per_category: int, fresh: bool) -> list[str]:
    """:data:`COLLECTION_ARGS` with another number of scenes per category; for the fresh-scene benchmark
    (``fresh``), without the split fractions: ``make-collection``'s defaults (10 % val, 10 % test), what a
    user gets, and what issue 14 measured (12 scenes: one validation scene per category)."""
    args = list(COLLECTION_ARGS)
    args[args.index("--scenes-per-category") + 1] = str(scenes_per_category)
    if fresh:
        args = args[: args.index("--val-fraction")]
    return args


def recipe_config(classifier_dir: Path, **changes):
    """The :class:`~classifier.config.TrainConfig` fields calibration reads, from ``classifier.json``'s recipe, with ``changes``."""
    from classifier.config import TrainConfig

    recipe = json.loads((classifier_dir / "classifier.json").read_text())["recipe"]
    fields = dict(
        arch=recipe["arch"], stem=recipe["stem"], input_size=recipe["input_size"], background=tuple(recipe["background"]),
        mean=tuple(recipe["mean"]), std=tuple(recipe["std"]), keep_fraction=recipe["keep_fraction"],
        stats_views=recipe["stats_views"], covariance_shrinkage=recipe["covariance_shrinkage"], score=recipe["score"],
        holdout_categories=tuple(recipe["holdout_categories"]),
        **{k: recipe[k] for k in ("reference", "reference_keep_fraction") if k in recipe})
    return TrainConfig(**{**fields, **changes})


def cached_outputs(classifier_dir: Path, collection: Path, fresh: Path) -> dict:
    """The network's outputs calibration and judging need, computed once and kept in ``classifier_dir``.

    Returns ``{"categories", "inputs": CalibrationInputs (training collection), "fresh": [{"scene", "category",
    "features", "logits"}, ...] (every scene of ``fresh``)}``; any calibration rule can then be re-run on them
    without the network (:func:`recalibrate`).
    """
    import torch

    from classifier.data import load_view_set
    from classifier.inputs import read_scene_views
    from classifier.store import load_classifier, model_inputs, view_outputs
    from classifier.train import CalibrationInputs, calibration_inputs, plan_splits
    from nerfmeta.collection.generate import load_collection

    config = recipe_config(classifier_dir)
    cache = classifier_dir / f"outputs_{fresh.name}{'_mirror' if config.mirror_views else ''}.pt"
    if cache.is_file():
        saved = torch.load(cache, weights_only=True)
        return with_reference({**saved, "inputs": CalibrationInputs(**saved["inputs"])}, classifier_dir.parent, collection, fresh, config)
    clf = load_classifier(classifier_dir)
    coll = load_collection(collection)
    splits = plan_splits(coll, config.holdout_categories)
    views = [load_view_set(coll, part, splits.categories, size=config.input_size, background=config.background)
             for part in (splits.train, splits.val, splits.holdout_val)]
    inputs = calibration_inputs(clf.model, *views, config, splits.categories)
    rows = []
    fresh_coll = load_collection(fresh)
    for record in fresh_coll.scenes:
        v = read_scene_views(fresh_coll.scene_path(record), size=clf.meta.input_size, background=clf.meta.background)
        features, logits = view_outputs(clf.model, model_inputs(v, clf.meta), mirror=config.mirror_views)
        rows.append({"scene": record.name, "category": record.category, "features": features, "logits": logits,
                     "views": int(v.shape[0])})
    saved = {"categories": list(splits.categories), "inputs": dict(vars(inputs)), "fresh": rows}
    tmp = cache.with_suffix(".tmp")
    torch.save(saved, tmp)
    os.replace(tmp, cache)
    return with_reference({**saved, "inputs": inputs}, classifier_dir.parent, collection, fresh, config)


def with_reference(cached_in: dict, work: Path, collection: Path, fresh: Path, config) -> dict:
    """:func:`cached_outputs` with the ImageNet reference descriptors (``config.reference``) of the training collection's
    scenes (:class:`~classifier.train.CalibrationInputs`' reference fields) and of every fresh scene (``"reference"`` of
    each row), computed once per collection and kept in ``work`` (the trunk does not depend on the network)."""
    from dataclasses import replace

    import torch

    from classifier.train import fewest_scenes_per_class, reference_skip_reason

    data = cached_in["inputs"]
    fewest = fewest_scenes_per_class(data.train_labels, data.train_scene_index, len(cached_in["categories"]))
    if config.reference == "none" or reference_skip_reason(config, fewest):  # as classifier train decides
        return cached_in
    from classifier.data import load_view_set
    from classifier.inputs import read_scene_views
    from classifier.reference import REFERENCE_SCENES, spaced_views, view_descriptors
    from classifier.store import cached_trunk
    from classifier.train import plan_splits, reference_inputs
    from nerfmeta.collection.generate import load_collection

    def cached(name: str, compute):
        path = work / f"reference_inputs_{config.reference}_{name}_{REFERENCE_SCENES}.pt"
        if path.is_file():
            return torch.load(path, weights_only=True)
        value = compute()
        tmp = path.with_suffix(".tmp")
        torch.save(value, tmp)
        os.replace(tmp, path)
        return value

    def known_scenes():
        coll = load_collection(collection)
        splits = plan_splits(coll, config.holdout_categories)
        if list(splits.categories) != list(cached_in["categories"]):
            raise SystemExit(f"{collection}: categories {splits.categories} differ from the network's {cached_in['categories']}")
        views = [load_view_set(coll, part, splits.categories, size=config.input_size, background=config.background)
                 for part in (splits.train, splits.val, splits.holdout_val)]
        return reference_inputs(cached_trunk(config.reference), *views, config.background)  # as calibration_inputs

    def fresh_scenes():
        coll = load_collection(fresh)
        return {r.name: view_descriptors(cached_trunk(config.reference), spaced_views(read_scene_views(
            coll.scene_path(r), size=config.input_size, background=config.background)), config.background) for r in coll.scenes}

    inputs = replace(cached_in["inputs"], **cached(collection.name, known_scenes))
    fresh = cached(fresh.name, fresh_scenes)
    fresh_rows = [{**r, "reference": fresh[r["scene"]]} for r in cached_in["fresh"]]
    return {**cached_in, "inputs": inputs, "fresh": fresh_rows}


def judge(rows: list[dict], categories: tuple[str, ...], score: str, thresholds: dict, stats) -> dict:
    """:func:`evaluate`'s figures from cached scene outputs (``rows`` of :func:`cached_outputs`)."""
    import torch

    from classifier.config import SCORES
    from classifier.predict import auroc, decide, scene_scores

    out_rows = []
    for r in rows:
        pred = decide(r["logits"], r["features"], categories, score, thresholds[score], stats, r.get("reference"))
        out_rows.append({"scene": r["scene"], "category": r["category"], "known": r["category"] in categories,
                         "predicted": pred.category, "unknown": pred.unknown, "views": r.get("views", pred.views),
                         "scores": scene_scores(r["logits"], r["features"], stats, r.get("reference"))})
    known = [r for r in out_rows if r["known"]]
    held = [r for r in out_rows if not r["known"]]
    out = {
        "score": score, "known_scenes": len(known), "holdout_scenes": len(held),
        "views_per_scene": sorted({r["views"] for r in out_rows}),
        "known_correct_and_known": sum(r["predicted"] == r["category"] and not r["unknown"] for r in known) / len(known),
        "known_accuracy": sum(r["predicted"] == r["category"] for r in known) / len(known),
        "false_unknown_rate": sum(r["unknown"] for r in known) / len(known),
        "holdout_detection_rate": sum(r["unknown"] for r in held) / max(1, len(held)),
        "thresholds": dict(thresholds), "per_score": {},
        "errors": [f"{r['scene']}: {r['predicted']}{' (unknown)' if r['unknown'] else ''}" for r in known
                   if r["predicted"] != r["category"] or r["unknown"]]
        + [f"{r['scene']}: {r['predicted']} (not flagged)" for r in held if not r["unknown"]],
    }
    for name in (n for n in SCORES if n in thresholds and all(n in r["scores"] for r in out_rows)):
        k = torch.tensor([r["scores"][name] for r in known], dtype=torch.float64)
        h = torch.tensor([r["scores"][name] for r in held], dtype=torch.float64)
        t = thresholds[name]
        out["per_score"][name] = {
            "test_auroc": auroc(k, h) if len(held) else None,
            "test_detection_rate": float((h < t).double().mean()) if len(held) else None,
            "test_false_unknown_rate": float((k < t).double().mean()),
        }
    return out


def unmirrored(cached: dict) -> dict:
    """:func:`cached_outputs` computed with ``mirror_views`` less the mirrored views (each block's second half)."""
    from dataclasses import replace

    half = lambda t: t[: t.shape[0] // 2]  # noqa: E731
    scenes = lambda rows: [(half(f), half(z)) for f, z in rows]  # noqa: E731
    data = cached["inputs"]
    inputs = replace(data, train_features=half(data.train_features), train_logits=half(data.train_logits),
                     train_labels=half(data.train_labels), train_scene_index=half(data.train_scene_index),
                     val=scenes(data.val), holdout_val=scenes(data.holdout_val))
    fresh = [{**r, "features": half(r["features"]), "logits": half(r["logits"])} for r in cached["fresh"]]
    return {**cached, "inputs": inputs, "fresh": fresh}


def recalibrate(cached: dict, config, before: bool = False) -> dict:
    """The cached network outputs calibrated by ``config`` (as ``classifier train`` would) and judged on the fresh scenes.

    ``before=True``: as the default before session 6 of issue 14 calibrated them: the class scale shrunk towards
    one pooled scale and no mirrored views (``cached`` must then hold mirrored views, which are dropped).
    """
    from dataclasses import replace

    from classifier.train import calibrate_inputs, select_score

    if before:
        config = replace(config, class_scale_prior="pooled", mirror_views=False, reference="none")
        cached = unmirrored(cached)
        cached = {**cached, "inputs": replace(cached["inputs"], reference_known=None),
                  "fresh": [{**r, "reference": None} for r in cached["fresh"]]}
    categories = tuple(cached["categories"])
    stats, thresholds, metrics = calibrate_inputs(cached["inputs"], config, len(categories))
    score, _ = select_score(config.score, metrics)
    result = judge(cached["fresh"], categories, score, thresholds, stats)
    result["calibration"] = metrics["calibration"]
    return result


def ensemble_figures(work: Path, collection: Path, fresh: Path, seeds: list[int]) -> dict:
    """The networks of ``seeds`` (trained in ``work``) judged as one ensemble on every scene of ``fresh``.

    Each network is calibrated as ``classifier train`` does; a scene's category is the argmax of the networks' mean
    scene probabilities and its score the mean of their ``combined`` scores (each already in units of its own known
    validation spread); the threshold is drawn from the known validation scenes' mean scores by the recipe's rule.
    Returns known right and not flagged, held-out flagged, the fresh AUROC and the scenes got wrong.
    """
    import torch

    from classifier.predict import auroc, calibrate_threshold, combined_score, scene_distances, scene_probabilities, scene_scores
    from classifier.train import calibrate_inputs, known_val_scores

    val, probs, scores = [], [], []
    for seed in seeds:
        out = work / f"classifier_seed{seed}"
        cached, config = cached_outputs(out, collection, fresh), recipe_config(out)
        categories, data = tuple(cached["categories"]), cached["inputs"]
        stats, _, metrics = calibrate_inputs(data, config, len(categories))
        distances = torch.stack([scene_distances(f, stats) for f, _ in data.val])
        shape = stats.train_scale if config.class_scale_prior == "train" else None
        known = known_val_scores(data, stats, distances, len(categories), metrics["calibration"]["scale_prior_scenes"], shape)
        val.append(combined_score(known["energy"], known["class_mahalanobis"], stats.score_norm))
        probs.append(torch.stack([scene_probabilities(r["logits"]) for r in cached["fresh"]]))
        scores.append(torch.tensor([scene_scores(r["logits"], r["features"], stats)["combined"] for r in cached["fresh"]]))
    threshold = calibrate_threshold(torch.stack(val).mean(0), config.keep_fraction, config.threshold_rule)
    score, predicted = torch.stack(scores).mean(0), torch.stack(probs).mean(0).argmax(-1)
    rows = cached["fresh"]
    is_known = torch.tensor([r["category"] in categories for r in rows])
    right = torch.tensor([r["category"] == categories[int(k)] for r, k in zip(rows, predicted)]) & (score >= threshold)
    return {
        "known_correct_and_known": float(right[is_known].double().mean()),
        "holdout_detection_rate": float((score[~is_known] < threshold).double().mean()),
        "auroc": auroc(score[is_known], score[~is_known]),
        "errors": [r["scene"] for r, k, ok in zip(rows, is_known, right) if k and not ok]
        + [f"{r['scene']} (not flagged)" for r, k, s in zip(rows, is_known, score) if not k and s >= threshold],
    }


def fresh_section_text(runs: list[dict], heading: str, command: str, train_args: list[str], fresh_args: list[str]) -> str:
    """The BENCHMARKS.md section of the fresh-scene benchmark: the targets on the median over ``runs``, then each run.

    Each run: ``{"train_seed", "result" (:func:`evaluate` of the classifier as trained), "old" (the same network
    recalibrated as before session 6, :func:`recalibrate`), "doc" (classifier.json), "train_s", "load_before", "load_after"}``.
    """
    n = len(runs)
    first = runs[0]
    doc, result = first["doc"], first["result"]
    med = lambda key, which="result": _median([r[which][key] for r in runs])  # noqa: E731
    pct = lambda key, which="result": _span([100 * r[which][key] for r in runs], ".1f") + " %"  # noqa: E731
    mark = lambda ok: "met" if ok else "**missed**"  # noqa: E731
    lines = [
        heading,
        "",
        f"`nerfmeta classifier train` with its defaults (held out: {','.join(doc['holdout_categories'])}) on "
        f"`make-collection {' '.join(train_args)}`; judged on **every** scene of a fresh collection, "
        f"`make-collection {' '.join(fresh_args)}` (another seed and other view counts; each scene classified from all "
        f"its {'/'.join(map(str, result['views_per_scene']))} views, and their mirror images, as `nerfmeta classify` does): "
        f"{result['known_scenes']} scenes of the known categories, {result['holdout_scenes']} of the held-out ones. "
        f"Trained {n} time{'s' if n > 1 else ''} (training seeds {', '.join(str(r['train_seed']) for r in runs)}); "
        "the targets are judged on the median over the runs (min-max in brackets). *Before* is the same network "
        "calibrated as the default before session 6 did (class scale shrunk towards one pooled scale, no mirrored "
        "views), recomputed from the saved network and the training collection.",
        "",
        "| target | now | before |",
        "| --- | --- | --- |",
        f"| known scenes right and not flagged >= 95 % | {pct('known_correct_and_known')} "
        f"{mark(med('known_correct_and_known') >= FRESH_TARGETS['known'])} | {pct('known_correct_and_known', 'old')} |",
        f"| held-out scenes flagged >= 90 % | {pct('holdout_detection_rate')} "
        f"{mark(med('holdout_detection_rate') >= FRESH_TARGETS['detect'])} | {pct('holdout_detection_rate', 'old')} |",
        f"| (known scenes flagged unknown) | {pct('false_unknown_rate')} | {pct('false_unknown_rate', 'old')} |",
        f"| (known scenes, category right) | {pct('known_accuracy')} | {pct('known_accuracy', 'old')} |",
        "",
        "Each run (now / before):",
        "",
        "| training seed | score used | scale prior (scenes) | right and not flagged | held-out flagged | test AUROC of the score used "
        "| training s | load before -> after |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        res, old, cal = r["result"], r["old"], r["doc"].get("calibration", {})
        lines.append(
            f"| {r['train_seed']} | {res['score']} / {old['score']} | {cal.get('scale_prior_scenes', 'n/a')} | "
            f"{res['known_correct_and_known']:.1%} / {old['known_correct_and_known']:.1%} | "
            f"{res['holdout_detection_rate']:.1%} / {old['holdout_detection_rate']:.1%} | "
            f"{res['per_score'][res['score']]['test_auroc']:.3f} / {old['per_score'][old['score']]['test_auroc']:.3f} | "
            f"{r['train_s']:.0f} | {r['load_before']} -> {r['load_after']} |")
    lines += ["", "Every score at its own threshold as calibrated now, median over the runs:", "",
              "| score | fresh AUROC | held-out flagged | known flagged |", "| --- | --- | --- | --- |"]
    for name in result["per_score"]:
        ps = [r["result"]["per_score"][name] for r in runs]
        lines.append(f"| {name} | {_median([p['test_auroc'] for p in ps]):.3f} | {_median([p['test_detection_rate'] for p in ps]):.1%} | "
                     f"{_median([p['test_false_unknown_rate'] for p in ps]):.1%} |")
    warnings = sorted({w for r in runs for w in r["doc"].get("calibration", {}).get("warnings", [])})
    if warnings:
        lines += ["", "`classifier train` warned: " + " | ".join(warnings) + "."]
    lines += errors_lines(runs, "Fresh scenes got wrong (now)")
    lines += [
        "",
        f"Command per run: `{command}`. Machine: {MACHINE}, shared with other jobs (load average 1 / 5 / 15 min per run "
        f"above; the training times are under that load). Date: {datetime.date.today().isoformat()}. Reproduce: "
        f"`.venv/bin/python scripts/bench_classifier.py --scenes-per-category N --fresh-seed S --extra '' --work DIR --write`.",
    ]
    return "\n".join(lines)


def train_run(collection: Path, work: Path, train_seed: int, args: argparse.Namespace) -> dict:
    """Train (or reuse) the classifier of one training seed in ``work/classifier_seedS`` (a subprocess); its facts."""
    out = work / f"classifier_seed{train_seed}"
    record = out / "bench_run.json"
    train_args = ["--holdout-categories", args.holdout, "--threads", str(args.threads), "--seed", str(train_seed),
                  "--overwrite", *shlex.split(args.extra)]
    facts = json.loads(record.read_text()) if record.is_file() else {}
    if facts.get("args") == train_args:  # trained before with the same arguments
        print(f"seed {train_seed}: reusing {out} ({facts['train_s']:.0f} s when it was trained)", flush=True)
    else:
        load_before = load_average()
        print(f"seed {train_seed}: training (load average {load_before}) ...", flush=True)
        train_s = run([sys.executable, "-m", "nerfmeta", "classifier", "train", str(collection), "--out", str(out), *train_args])
        facts = {"args": train_args, "train_s": train_s, "load_before": load_before, "load_after": load_average()}
        record.write_text(json.dumps(facts, indent=1))
        print(f"seed {train_seed}: {train_s:.0f} s (load average {facts['load_after']})", flush=True)
    return {"train_seed": train_seed, "out": out, **{k: facts[k] for k in ("train_s", "load_before", "load_after")}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--collection", type=Path, default=None, help="reuse this collection (default: generate one in --work)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the collection and classifier (default: a temporary one)")
    parser.add_argument("--holdout", default=HOLDOUT, help=f"held-out categories (default {HOLDOUT})")
    parser.add_argument("--threads", type=int, default=1, help="torch threads for training (default 1: fastest on a shared 2-core machine)")
    parser.add_argument("--extra", default=DEFAULT_EXTRA, help=f"more arguments for 'classifier train' (default '{DEFAULT_EXTRA}')")
    parser.add_argument("--seed", type=int, default=SEED, help=f"seed of the generated collection (default {SEED})")
    parser.add_argument("--train-seeds", default="0,1,2", help="training seeds, one run each; the median is judged (default 0,1,2)")
    parser.add_argument("--parallel", type=int, default=2, help="runs trained at a time (default 2: one per core)")
    parser.add_argument("--scenes-per-category", type=int, default=40, help="scenes per category of the generated collection (default 40)")
    parser.add_argument("--fresh-seed", type=int, default=None,
                        help="judge on every scene of a fresh collection of this seed (FRESH_ARGS: other view counts) "
                             "instead of the training collection's test scenes; issue 14's targets")
    parser.add_argument("--ensembles", default="",
                        help="with --fresh-seed: also judge groups of the trained seeds as ensembles, e.g. 0,1,2/3,4,5 "
                             "(mean probabilities and mean combined score; ensemble_figures)")
    parser.add_argument("--write", action="store_true", help="record the results in BENCHMARKS.md")
    args = parser.parse_args()
    holdout = args.holdout
    train_args = collection_args(args.scenes_per_category, args.fresh_seed is not None)

    work = args.work or Path(tempfile.mkdtemp(prefix="bench_classifier_"))
    work.mkdir(parents=True, exist_ok=True)
    collection = args.collection
    if collection is None:
        collection = work / "collection"
        if not (collection / "collection.json").is_file():
            print(f"generating the collection in {collection} ...", flush=True)
            gen_s = run([sys.executable, "-m", "nerfmeta", "make-collection", str(collection), *train_args, "--seed", str(args.seed), "--overwrite"])
            print(f"  {gen_s:.0f} s", flush=True)
    if args.fresh_seed is not None:
        return fresh_benchmark(collection, work, args, train_args)
    seeds = [int(v) for v in args.train_seeds.split(",") if v]
    with ThreadPoolExecutor(max(1, args.parallel)) as pool:  # each run is its own process
        runs = list(pool.map(lambda sd: train_run(collection, work, sd, args), seeds))
    for r in runs:  # one at a time, in this process (importing torchvision from several threads at once is not safe)
        r.update(result=evaluate(collection, r["out"]), doc=json.loads((r["out"] / "classifier.json").read_text()))
    shown = (f"nerfmeta classifier train COLLECTION --out DIR --holdout-categories {holdout} --threads {args.threads} "
             f"--seed S" + (" " + args.extra if args.extra else ""))
    seed = int(json.loads((collection / "collection.json").read_text())["config"]["seed"])
    text = section_text(runs, shown, args.threads, seed)
    print(text)
    (work / "bench_result.json").write_text(json.dumps([{k: r[k] for k in ("train_seed", "result", "train_s")} for r in runs], indent=2))
    if args.write:
        from benchlib.sections import write_section as write_benchmark_section
        write_benchmark_section(ROOT / "BENCHMARKS.md", SECTION, text)
        print(f"updated {ROOT / 'BENCHMARKS.md'} ({SECTION})")
    return 0


def fresh_benchmark(collection: Path, work: Path, args: argparse.Namespace, train_args: list[str]) -> int:
    """Issue 14's benchmark: train each seed, judge it (and its calibration as before issue 14) on a fresh collection."""
    fresh = work / f"fresh_seed{args.fresh_seed}"
    fresh_args = [*FRESH_ARGS, "--resolution", "64", "--categories", COLLECTION_ARGS[1], "--seed", str(args.fresh_seed)]
    if not (fresh / "collection.json").is_file():
        print(f"generating the fresh collection in {fresh} ...", flush=True)
        run([sys.executable, "-m", "nerfmeta", "make-collection", str(fresh), *fresh_args, "--overwrite"])
    seeds = [int(v) for v in args.train_seeds.split(",") if v]
    with ThreadPoolExecutor(max(1, args.parallel)) as pool:
        runs = list(pool.map(lambda sd: train_run(collection, work, sd, args), seeds))
    for r in runs:  # the network as trained, calibrated by the current code and as before issue 14
        cached = cached_outputs(r["out"], collection, fresh)
        config = recipe_config(r["out"])
        r.update(result=recalibrate(cached, config), doc=json.loads((r["out"] / "classifier.json").read_text()),
                 old=recalibrate(cached, config, before=True))
    seed = int(json.loads((collection / "collection.json").read_text())["config"]["seed"])
    heading = f"## Classifier on fresh scenes, {args.scenes_per_category} scenes per category"
    command = (f"nerfmeta classifier train COLLECTION --out DIR --holdout-categories {args.holdout} --threads {args.threads} "
               f"--seed S" + (" " + args.extra if args.extra else ""))
    text = fresh_section_text(runs, heading, command, [*train_args, "--seed", str(seed)], fresh_args)
    print(text)
    for group in filter(None, args.ensembles.split("/")):
        figures = ensemble_figures(work, collection, fresh, [int(v) for v in group.split(",")])
        print(f"ensemble of seeds {group}: known right and not flagged {100 * figures['known_correct_and_known']:.1f} %, "
              f"held-out flagged {100 * figures['holdout_detection_rate']:.1f} %, AUROC {figures['auroc']:.3f}; "
              f"wrong: {', '.join(figures['errors'])}")
    (work / "bench_fresh_result.json").write_text(json.dumps(
        [{k: r[k] for k in ("train_seed", "result", "old", "train_s")} for r in runs], indent=2))
    if args.write:
        from benchlib.sections import write_section as write_benchmark_section
        write_benchmark_section(ROOT / "BENCHMARKS.md", heading, text)
        print(f"updated {ROOT / 'BENCHMARKS.md'} ({heading})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
