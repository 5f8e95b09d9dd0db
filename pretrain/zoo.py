"""Building a model zoo (``scripts/build_model_zoo``): classifier, category models, meta-init, occupancy network, manifest.

Reproducible from its seed: every step is a library call with a fixed recipe (:class:`ZooRecipe`)
on a collection generated from the seed. Steps, each skipped when the work folder already holds
its finished output (so an interrupted build continues):

1. generate the training collection: the :attr:`ZooRecipe.known` categories and the
   :attr:`ZooRecipe.unseen` ones; unseen scenes are used only to calibrate and measure the
   classifier's "unknown" answer (its held-out categories), never to train a model;
2. train the ResNet classifier on the known categories (stored in float16 so the zoo stays
   small: ResNet-18 is 22 MB);
3. pretrain one category model per known category (``nerfmeta pretrain category``);
4. meta-train a Reptile initialisation of the same backbone over the known categories' training
   scenes (``nerfmeta meta-train``);
5. train the learned occupancy start's network (:mod:`pretrain.occupancy`) on collections of its own (the known
   categories at 64 and 128 px, seeds ``seed + 1`` and ``seed + 2``); :func:`add_occupancy` puts it into an
   existing zoo without rebuilding the rest;
6. copy what a fit needs (weights + JSON, plus the training curves) into the zoo folder and write
   ``manifest.json`` with every file's SHA-256, the recipes, the training data and the metrics
   (:mod:`nerfmeta.zoo`), built under a hidden name, verified, then renamed into place.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from nerfmeta.collection.generate import CollectionConfig, generate_collection, load_collection
from nerfmeta.collection.render import RenderConfig
from nerfmeta.fit.loop import FitConfig
from nerfmeta.errors import ConfigError
from nerfmeta.io import save_tensors, to_jsonable, write_json
from nerfmeta.zoo import load_zoo, write_manifest, zoo_entry

log = logging.getLogger(__name__)

NERF_ZOO_MODEL = {"depth": 4, "width": 64, "skips": [2], "n_samples": 32, "pos_freqs": 6, "alpha_init": 1e-3, "lr": 1e-2}
"""The MLP of every shipped zoo model (and so of every routed fit and its scratch baseline): a 4 x 64 trunk,
6 position octaves, 32 samples per ray, learning rate 1e-2 (the best of 5e-4..1e-2 for *scratch* fits on
32 x 32 views, so the baseline is not handicapped), initial alpha 1e-3 (thin objects do not collapse to empty)."""


@dataclass(frozen=True)
class ZooRecipe:
    """Everything that defines a zoo build; saved in its manifest."""

    known: tuple[str, ...] = ("airplane", "car", "chair", "lamp", "mug", "table")
    """Categories the zoo has a category model for and the classifier names."""
    unseen: tuple[str, ...] = ("sofa", "vase")
    """Categories no model is trained on (the classifier's held-out categories: they calibrate its unknown score)."""
    scenes_per_category: int = 30
    """Generated scenes per category (the classifier needs many; category models and meta-learning use the training ones)."""
    views: int = 16
    """Training views per scene."""
    test_views: int = 8
    """Test views per scene."""
    resolution: int = 64
    """Image size of the collection (what the classifier reads)."""
    val_fraction: float = 0.2
    """Fraction of each category's scenes for validation (classifier calibration)."""
    test_fraction: float = 0.1
    """Fraction of each category's scenes for test (not used by the build)."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """How the collection is rendered."""
    classifier_budget_s: float = 480.0
    """Classifier training time budget (seconds)."""
    classifier: dict[str, Any] = field(default_factory=dict)
    """Overrides of :class:`classifier.config.TrainConfig` (e.g. ``epochs``, ``input_size`` in tests)."""
    backbone: str = "nerf"
    """Backbone of the category models and the meta-initialisation."""
    model: dict[str, Any] = field(default_factory=lambda: dict(NERF_ZOO_MODEL))
    """Backbone config of every zoo model (JSON form)."""
    downscale: float = 2.0
    """Downscale of the collection's views for the radiance fields (64 -> 32 px)."""
    batch_rays: int = 256
    """Rays per iteration for category models and (recorded in the manifest) for routed fits."""
    category_iters: int = 800
    """Iterations of each category model."""
    meta_steps: int = 300
    """Reptile meta-steps."""
    meta: dict[str, Any] = field(default_factory=dict)
    """Overrides of :class:`pretrain.meta.MetaConfig` (e.g. ``meta_batch``, ``support_rays`` in tests)."""
    fit_iters: int = 300
    """Iterations a routed fit runs by default (recorded in the manifest)."""
    fit_eval_every: int = 25
    """Test PSNR interval of routed fits by default (recorded in the manifest)."""
    freeze: int = 0
    """Layers a category-route fit freezes by default (recorded in the manifest; see BENCHMARKS.md for how it was chosen)."""
    seed: int = 0
    """Seed of the collection and of every model."""
    occupancy_resolutions: tuple[int, ...] = (64, 128)
    """Image sizes of the occupancy network's training collections, one collection each, generated from seeds
    ``seed + 1``, ``seed + 2``, ... (the known categories only; the network is measured on held-out seeds)."""
    occupancy_scenes_per_category: int = 6
    """Scenes per known category in each occupancy collection (every split is used: the target is exact geometry)."""
    occupancy_views: int = 24
    """Training views per scene of the occupancy collections (24 + 8, as ``scripts/bench_priors.py`` generates)."""
    occupancy: dict[str, Any] = field(default_factory=dict)
    """Overrides of :class:`pretrain.occupancy.OccupancyTrainConfig` (e.g. ``steps`` in tests)."""

    def collection_config(self) -> CollectionConfig:
        return CollectionConfig(categories=self.known + self.unseen, scenes_per_category=self.scenes_per_category, views=self.views,
                                test_views=self.test_views, resolution=self.resolution, val_fraction=self.val_fraction,
                                test_fraction=self.test_fraction, render=self.render, seed=self.seed)

    def occupancy_collections(self) -> list[CollectionConfig]:
        """The occupancy network's training collections (:attr:`occupancy_resolutions`)."""
        return [CollectionConfig(categories=self.known, scenes_per_category=self.occupancy_scenes_per_category,
                                 views=self.occupancy_views, test_views=self.test_views, resolution=r, render=self.render, seed=self.seed + 1 + k)
                for k, r in enumerate(self.occupancy_resolutions)]

    def fit_defaults(self) -> dict[str, Any]:
        """What the manifest's ``fit`` records: the settings routed fits and their baselines share."""
        return {"backbone": self.backbone, "model": dict(self.model), "batch_rays": self.batch_rays, "iters": self.fit_iters,
                "eval_every": self.fit_eval_every, "eval_views": 0, "freeze": self.freeze,
                "trained_resolution": int(self.resolution / self.downscale)}


TIMINGS = "build_times.json"
"""File in the work folder with the seconds each step took when it actually ran (a reused step keeps its time)."""


def _step(name: str, timings: dict[str, float], work: Path):
    class _Timer:
        def __enter__(self):
            self.t0 = time.perf_counter()

        def __exit__(self, *exc):
            if exc[0] is not None:
                return
            elapsed = round(time.perf_counter() - self.t0, 1)
            path = work / TIMINGS
            saved = json.loads(path.read_text()) if path.is_file() else {}
            if elapsed >= 1.0 or name not in saved:  # a reused step takes no time: keep the time it took when built
                saved[name] = elapsed
                write_json(path, saved)
            timings[name] = saved[name]
            log.info("%s: %.0f s", name, elapsed)

    return _Timer()


def build_zoo(recipe: ZooRecipe, out: str | os.PathLike, work: str | os.PathLike, *, threads: int = 0) -> Path:
    """Build the zoo of ``recipe`` into ``out`` (replaced atomically at the end), using ``work`` for everything else.

    Returns:
        the path of the written ``manifest.json``.
    """
    from classifier.config import TrainConfig
    from classifier.store import load_classifier, save_classifier
    from classifier.train import train_classifier
    from pretrain.category import CategoryPretrainConfig, pretrain_category
    from pretrain.meta import MetaConfig
    from pretrain.meta_run import meta_train

    if threads:
        torch.set_num_threads(threads)
    out, work = Path(out), Path(work)
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    with _step("collection", timings, work):
        index = _collection(recipe.collection_config(), work / "collection")

    clf_dir = work / "classifier"
    with _step("classifier", timings, work):
        if not (clf_dir / "classifier.json").is_file():
            config = TrainConfig(**{"holdout_categories": recipe.unseen, "time_budget_s": recipe.classifier_budget_s,
                                    "seed": recipe.seed, **recipe.classifier})
            train_classifier(config, index, clf_dir, overwrite=True)
            doc = json.loads((clf_dir / "classifier.json").read_text())
            keep = {k: v for k, v in doc.items() if k not in {"format", "version", "categories", "arch", "stem", "input", "unknown", "weights"}}
            save_classifier(clf_dir, load_classifier(clf_dir), keep, weights_dtype=torch.float16)
    clf_doc = json.loads((clf_dir / "classifier.json").read_text())

    fit = FitConfig(iters=recipe.category_iters, batch_rays=recipe.batch_rays, seed=recipe.seed, eval_every=0, checkpoint_every=0,
                    holdout_tile=0.0)  # category models fit every pixel for their whole length (nerfmeta.commands.pretrain)
    category_dirs = {}
    with _step("category_models", timings, work):
        for category in recipe.known:
            folder = work / "category" / category
            if not (folder / "init.json").is_file():
                config = CategoryPretrainConfig(collection=str(index), category=category, backbone=recipe.backbone, model=recipe.model,
                                                fit=fit, downscale=recipe.downscale)
                pretrain_category(config, folder, overwrite=True)
            category_dirs[category] = folder

    meta_dir = work / "meta"
    with _step("meta", timings, work):
        if not (meta_dir / "init.json").is_file():
            config = MetaConfig(**{"backbone": recipe.backbone, "model": recipe.model, "algo": "reptile", "categories": recipe.known,
                                   "downscale": recipe.downscale, "meta_steps": recipe.meta_steps, "seed": recipe.seed, **recipe.meta})
            meta_train(config, index, meta_dir, overwrite=True)

    with _step("occupancy", timings, work):
        occupancy_dir = train_zoo_occupancy(recipe, work)

    staging = out.with_name(f".{out.name}.building")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    if (out / "README.md").is_file():
        shutil.copy2(out / "README.md", staging / "README.md")
    weights = ("init.json", "model.safetensors")
    entries = [zoo_entry(staging, "classifier", "classifier", _copy(clf_dir, staging / "classifier", ("classifier.json", "model.safetensors",
                                                                                                       "training_curve.png")),
                         ("classifier.json", "model.safetensors"),
                         config={"recipe": clf_doc.get("recipe"), "categories": clf_doc.get("categories"),
                                 "holdout_categories": list(recipe.unseen), "weights_dtype": "float16"},
                         metrics={"validation": clf_doc.get("validation"), "training": clf_doc.get("training")})]
    for category, folder in category_dirs.items():
        dst = _copy(folder, staging / "category" / category, weights + ("psnr_vs_iter.png",))
        meta = json.loads((folder / "init.json").read_text())["meta"]
        entries.append(zoo_entry(staging, f"category/{category}", "category", dst, weights, category=category,
                                 config=json.loads((folder / "config.json").read_text()),
                                 metrics={k: meta.get(k) for k in ("final_psnr", "final_psnr_note", "scenes", "steps", "time_s")}))
    dst = _copy(meta_dir, staging / "meta", weights + ("summary.json", "query_psnr_vs_step.png"))
    summary = json.loads((meta_dir / "summary.json").read_text())
    entries.append(zoo_entry(staging, "meta", "meta", dst, weights, config=json.loads((meta_dir / "config.json").read_text()),
                             metrics={k: summary.get(k) for k in ("final_query_psnr", "held_out", "time_s", "meta_steps")}))
    entries.append(occupancy_entry(staging, _copy(occupancy_dir, staging / "occupancy", OCCUPANCY_FILES)))
    coll = load_collection(index)
    manifest = write_manifest(
        staging, entries,
        built_by="scripts/build_model_zoo", recipe=to_jsonable(recipe), seed=recipe.seed, date=datetime.date.today().isoformat(),
        machine=f"{os.cpu_count()}-core CPU" + (", CUDA" if torch.cuda.is_available() else ", no GPU"), torch=torch.__version__,
        backbone=recipe.backbone, fit=recipe.fit_defaults(), known_categories=list(recipe.known), unseen_categories=list(recipe.unseen),
        training_data={"generator": "nerfmeta make-collection", "config": dict(coll.config),
                       "scenes": {s: sum(1 for r in coll.scenes if r.split == s) for s in ("train", "val", "test")}},
        build_time_s={**timings, "total": round(sum(timings.values()), 1)},
        build_note="seconds each step took when it ran (steps reused from the work folder keep that time)",
    )
    load_zoo(staging)  # verify before replacing the old zoo
    if out.exists():
        shutil.rmtree(out)
    os.replace(staging, out)
    return out / manifest.name


def _collection(config: CollectionConfig, folder: Path) -> Path:
    """``folder/collection.json``, generated unless ``folder`` already holds a collection of ``config``."""
    index = folder / "collection.json"
    if not (index.is_file() and json.loads(index.read_text()).get("config") == to_jsonable(config)):
        generate_collection(config, folder, overwrite=True)
    return index


OCCUPANCY_FORMAT = "nerfmeta-occupancy-1"
OCCUPANCY_FILES = ("occupancy.json", "model.safetensors")
"""The zoo's ``occupancy/`` entry: the training record and the network (:func:`nerfmeta.io.save_tensors`)."""


def train_zoo_occupancy(recipe: ZooRecipe, work: Path) -> Path:
    """``work/occupancy/`` with the recipe's occupancy network trained (:mod:`pretrain.occupancy`) on its own
    collections (:meth:`ZooRecipe.occupancy_collections`), unless it already holds one of the same recipe."""
    from nerfmeta.priors.occupancy import THRESHOLD
    from pretrain.occupancy import OccupancyTrainConfig, occupancy_volume, train_occupancy_net

    folder = work / "occupancy"
    config = OccupancyTrainConfig(**{"seed": recipe.seed, **recipe.occupancy})
    collections = recipe.occupancy_collections()
    wanted = {"config": to_jsonable(config), "collections": to_jsonable(collections)}
    index = folder / OCCUPANCY_FILES[0]
    if index.is_file() and (folder / OCCUPANCY_FILES[1]).is_file():
        doc = json.loads(index.read_text())
        if {k: doc.get(k) for k in wanted} == wanted:
            return folder
    volumes = []
    for c in collections:
        coll = load_collection(_collection(c, work / f"occupancy_{c.resolution}px_seed{c.seed}"))
        log.info("occupancy: features of %d scenes at %d px", len(coll.scenes), c.resolution)
        volumes += [occupancy_volume(coll.root / r.path, distance=config.true_distance) for r in coll.scenes]
    t0 = time.perf_counter()
    net, losses = train_occupancy_net(volumes, config, on_log=lambda r: log.info("occupancy step %d: loss %.4f (%.0f s)",
                                                                                  r["step"], r["loss"], r["s"]))
    save_tensors(folder / OCCUPANCY_FILES[1], net.state_dict())
    write_json(index, {"format": OCCUPANCY_FORMAT, **wanted, "threshold": THRESHOLD, "scenes": len(volumes),
                       "weights": sum(p.numel() for p in net.parameters()), "train_s": round(time.perf_counter() - t0, 1),
                       "training": losses})
    return folder


def occupancy_entry(root: Path, folder: Path) -> dict[str, Any]:
    """The manifest entry of an occupancy folder made by :func:`train_zoo_occupancy` (inside ``root``)."""
    doc = json.loads((folder / OCCUPANCY_FILES[0]).read_text())
    return zoo_entry(root, "occupancy", "occupancy", folder, OCCUPANCY_FILES,
                     config={k: doc[k] for k in ("config", "collections", "threshold")},
                     metrics={"scenes": doc["scenes"], "weights": doc["weights"], "train_s": doc["train_s"],
                              "final_loss": doc["training"][-1]["loss"]})


def add_occupancy(recipe: ZooRecipe, out: str | os.PathLike, work: str | os.PathLike, *, threads: int = 0) -> Path:
    """Train the recipe's occupancy network (or reuse ``work``'s) and put it into the existing zoo ``out`` as its
    ``occupancy`` entry, keeping every other entry; ``out`` must have been built with the same recipe otherwise.

    Returns:
        the path of the rewritten ``manifest.json``.

    Raises:
        ConfigError: ``out`` is not a valid zoo, was built with another recipe, or has an ``occupancy/`` folder that its
            manifest does not list (not the build's to replace).
    """
    if threads:
        torch.set_num_threads(threads)
    out, work = Path(out), Path(work)
    zoo = load_zoo(out)
    mine, recorded = to_jsonable(recipe), zoo.manifest.get("recipe", {})
    differ = [k for k in mine if k in recorded and recorded[k] != mine[k]]
    if differ:
        raise ConfigError(f"{out}: built with another recipe ({', '.join(differ)} differ); rebuild the whole zoo instead")
    target, listed = out / "occupancy", any(e.kind == "occupancy" for e in zoo.entries)
    if target.exists() and not listed:
        raise ConfigError(f"{target}: exists but the zoo's manifest does not list it; move it away first")
    work.mkdir(parents=True, exist_ok=True)
    timings = {k: v for k, v in zoo.manifest.get("build_time_s", {}).items() if k != "total"}
    with _step("occupancy", timings, work):
        folder = train_zoo_occupancy(recipe, work)
    staging, old = out / ".occupancy.building", out / ".occupancy.old"
    for leftover in (staging, old):
        if leftover.exists():
            shutil.rmtree(leftover)
    _copy(folder, staging, OCCUPANCY_FILES)
    if target.exists():
        os.replace(target, old)
    os.replace(staging, target)
    entries = [e for e in zoo.manifest["entries"] if e.get("kind") != "occupancy"] + [occupancy_entry(out, target)]
    fields = {k: v for k, v in zoo.manifest.items() if k not in ("format", "entries", "total_bytes")}
    manifest = write_manifest(out, entries, **{**fields, "recipe": mine,
                                               "build_time_s": {**timings, "total": round(sum(timings.values()), 1)}})
    if old.exists():
        shutil.rmtree(old)
    load_zoo(out)
    return manifest


def _copy(src: Path, dst: Path, files: tuple[str, ...]) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    for f in files:
        if (src / f).is_file():
            shutil.copy2(src / f, dst / f)
    return dst


def recipe_with(**changes: Any) -> ZooRecipe:
    """The default recipe with some fields changed."""
    return dataclasses.replace(ZooRecipe(), **changes)
