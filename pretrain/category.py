"""Category models: one radiance field trained on the rays of all training scenes of a category.

As in the source work, a category model is a single field fitted to every training view of
every *training* scene of one category at once. With the objects in the collection's canonical
frame (centred, inside ``[-1, 1]^3``, cameras on a sphere), it learns the category's mean shape
and appearance; a new scene of the category then starts from it and fine-tunes
(``nerfmeta fit SCENE --init category:DIR [--freeze K]``).

Training reuses the one fit loop unchanged: the category's training scenes are merged into one
:class:`~nerfmeta.data.Scene` (:func:`category_scene`) whose ``train`` split is every training
view of every scene and whose ``test`` split is every test view, so the loop's ray sampler draws
uniformly over all their pixels and its final evaluation is the mean PSNR over the scenes' test
views. The field lives in the canonical box :data:`CANONICAL_BOX`, not in any one scene's box,
so that every scene of the category (seen or new) is inside it.

The voxel grid is pretrained with its usual recipe, coarse stage included, on the merged scene:
the coarse stage finds the region the category's training objects occupy (the union of their
shapes, dilated) and the fine stage starts in that box with that occupancy cache, which the
saved model keeps. Training only the fine stage over the whole canonical box
(``--set coarse_iters=0``) was measured worse: without a cache, transfer fits evaluate about 2.5x
more samples per ray and, with free voxels all over the box, overfit the training views (see
BENCHMARKS.md). The grid must also finish growing (``iters`` beyond ``coarse_iters`` + the last of
``growth_steps``) so a transfer fit starts from the final grid and never re-creates (and so
un-freezes) a grid.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch

from nerfmeta.budget import check_fit_fits
from nerfmeta.collection.generate import Collection, SceneRecord, load_collection
from nerfmeta.data import load_scene
from nerfmeta.data.scene import Scene
from nerfmeta.errors import ConfigError
from nerfmeta.fields.registry import BACKBONES, build_model, config_from_dict, default_config, model_class
from nerfmeta.fit.loop import Callback, FitConfig, fit
from nerfmeta.fit.checkpoint import save_checkpoint
from nerfmeta.fit.run import MetricsWriter, read_metrics, resume_fit_state
from nerfmeta.init import save_init
from nerfmeta.io import to_jsonable, write_json
from nerfmeta.metrics import mse_to_psnr
from nerfmeta.report.plots import plot_psnr_curves
from nerfmeta.runfolder import CHECKPOINT, check_target, run_folder

log = logging.getLogger(__name__)

CANONICAL_BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
"""The box every category model lives in: generated collections put each object, centred, inside it."""

RECIPE = ("one field trained on the rays of all training scenes of the category together "
          "(uniform over their training pixels), in the canonical box")


@dataclass(frozen=True)
class CategoryPretrainConfig:
    """Everything that defines a category model; saved as ``config.json`` beside it."""

    collection: str
    """Collection folder (or its ``collection.json``), from ``nerfmeta make-collection``."""
    category: str
    """Category whose training scenes are used."""
    backbone: str = "grid"
    """Backbone name (``grid`` or ``nerf``); transfer fits use the same one."""
    model: dict[str, Any] = field(default_factory=dict)
    """Backbone config overrides (JSON form); missing keys take the backbone's defaults."""
    fit: FitConfig = FitConfig(holdout_tile=0.0)
    """Optimisation settings (the same loop, optimiser and schedule as ``nerfmeta fit``; no held-out tiles: a category
    model is fitted to every pixel of its scenes for its whole length, as the shipped zoo's were)."""
    max_scenes: int | None = None
    """Use at most this many training scenes (the first by name); None: all of them."""
    downscale: float = 1.0
    """Image downscale factor applied when loading."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Background the RGBA images are composited on; transfer fits should use the same one."""
    device: str = "cpu"
    """Torch device."""

    def model_config(self, scene: Scene | None = None) -> Any:
        """The backbone config: defaults, then overrides.

        With ``scene`` (the merged category scene), a config class's ``for_scene`` rule sizes its
        "auto" fields for it, as for a scratch fit (the grid's voxel counts from the resolution).
        """
        if self.backbone not in BACKBONES:
            raise ConfigError(f"--backbone {self.backbone!r}: choose one of {', '.join(sorted(BACKBONES))}")
        values = {**dataclasses.asdict(default_config(self.backbone)), **self.model}
        config = config_from_dict(self.backbone, values)
        last = model_class(self.backbone).settles_at(config)
        if last and self.fit.iters <= last:
            raise ConfigError(f"--iters {self.fit.iters}: the {self.backbone} grows until step {last} (its parameters change "
                              f"until then, e.g. the grid's coarse_iters + the last of growth_steps); train past it "
                              f"(--iters > {last}) or change its schedule with --set")
        if scene is not None and hasattr(config, "for_scene"):
            config = config.for_scene(scene)
        return config


@dataclass(frozen=True)
class CategoryData:
    """The training scenes of one category merged into one scene.

    Attributes:
        scene: ``train`` split = every training view of every scene, ``test`` split = every test
            view; ``bounds`` = :data:`CANONICAL_BOX`; ``category`` set.
        scene_names: the scenes merged, in order.
        view_scene: (n_views,) index into ``scene_names`` of each view of ``scene``.
    """

    scene: Scene
    scene_names: tuple[str, ...]
    view_scene: tuple[int, ...]


def category_records(collection: Collection, category: str, *, max_scenes: int | None = None) -> tuple[SceneRecord, ...]:
    """The training scenes of ``category``; one-line :class:`ConfigError` when there are none."""
    if len(collection.scenes) < 2:
        raise ConfigError(f"{collection.root}: the collection holds {len(collection.scenes)} scene(s); a category model "
                          "needs training scenes and other scenes to transfer to (make-collection --scenes-per-category 2 or more)")
    present = sorted({s.category for s in collection.scenes})
    if category not in present:
        raise ConfigError(f"--category {category!r} is not in {collection.root}; it holds {', '.join(present)}")
    records = tuple(s for s in collection.by_category(category) if s.split == "train")
    if not records:
        with_train = sorted({s.category for s in collection.scenes if s.split == "train"})
        raise ConfigError(f"--category {category!r} has no training scenes in {collection.root} (all are val/test); "
                          f"categories with training scenes: {', '.join(with_train) or 'none'}")
    if max_scenes is not None:
        if max_scenes < 1:
            raise ConfigError(f"--max-scenes {max_scenes}: must be 1 or more")
        records = records[:max_scenes]
    return records


def category_scene(
    collection: Collection,
    records: Sequence[SceneRecord],
    *,
    downscale: float = 1.0,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> CategoryData:
    """Load ``records`` and merge them into one scene in the canonical box (see :class:`CategoryData`)."""
    box = torch.tensor(CANONICAL_BOX, dtype=torch.float32)
    images, poses, intrinsics, names, owner = [], [], [], [], []
    splits: dict[str, list[int]] = {"train": [], "test": []}
    first: Scene | None = None
    offset = 0
    for k, record in enumerate(records):
        path = collection.scene_path(record)
        scene = load_scene(path, downscale=downscale, background=background)
        if first is None:
            first = scene
        elif (scene.height, scene.width, scene.near, scene.far, scene.normalization) != (
                first.height, first.width, first.near, first.far, first.normalization):
            raise ConfigError(f"{path}: {scene.width}x{scene.height} px, near/far {scene.near:g}/{scene.far:g} differ from "
                              f"{first.source}'s {first.width}x{first.height}, {first.near:g}/{first.far:g} (or the load-time "
                              "normalisation differs, see nerfmeta inspect); a category model needs one camera set-up")
        if bool((scene.bounds[0] < box[0] - 1e-4).any() or (scene.bounds[1] > box[1] + 1e-4).any()):
            raise ConfigError(f"{path}: its box {scene.bounds.tolist()} is not inside the canonical box {list(CANONICAL_BOX)}; "
                              "category models need a collection in the canonical frame")
        for split in ("train", "test"):
            splits[split] += [offset + i for i in scene.splits.get(split, ())]
        images.append(scene.images)
        poses.append(scene.poses)
        intrinsics.append(scene.intrinsics)
        names += [f"{record.name}/{n}" for n in scene.image_names] or [record.name] * scene.n_views
        owner += [k] * scene.n_views
        offset += scene.n_views
    if first is None:
        raise ConfigError("no scenes to merge")
    merged = Scene(
        images=torch.cat(images),
        poses=torch.cat(poses),
        intrinsics=torch.cat(intrinsics),
        near=first.near,
        far=first.far,
        bounds=box,
        splits={s: tuple(v) for s, v in splits.items()},
        holdout=f"test views of the {len(records)} training scenes",
        source=Path(collection.root),
        format="category",
        category=records[0].category,
        background=background,
        image_names=tuple(names),
        downscale=downscale,
        normalization=first.normalization,
    )
    return CategoryData(merged, tuple(r.name for r in records), tuple(owner))


def saved_config(out: Path) -> CategoryPretrainConfig:
    """The config a category run in ``out`` was started with (its ``config.json``; ``model`` as resolved then)."""
    path = out / "config.json"
    try:
        data = json.loads(path.read_text())
        data["fit"] = FitConfig.from_json(data.get("fit", {}))
        data["background"] = tuple(data.get("background", (1.0, 1.0, 1.0)))
        return CategoryPretrainConfig(**data)
    except (OSError, ValueError, TypeError) as err:
        raise ConfigError(f"{path}: not readable ({err}); nothing to resume") from None


def pretrain_category(
    config: CategoryPretrainConfig,
    out: str | Path,
    *,
    overwrite: bool = False,
    resume: bool = False,
    callbacks: Sequence[Callback] = (),
) -> dict[str, Any]:
    """Train the category model of ``config.category`` into the folder ``out``; return its manifest entry.

    ``out`` receives ``model.safetensors`` + ``init.json`` (:func:`nerfmeta.init.save_init`, kind
    ``category``, whose ``meta`` is the manifest entry returned here), ``config.json``,
    ``metrics.jsonl``, ``checkpoint.safetensors`` (the fit loop's, for ``resume``) and
    ``psnr_vs_iter.png``. ``init.json`` is written last, so an interrupted run never leaves a
    loadable half-trained model. The folder follows :mod:`nerfmeta.runfolder`'s rules (``overwrite``
    replaces only a category run of ours, built aside; ``resume`` continues one from its checkpoint
    with its saved settings, which must name the same collection and category).
    """
    out = Path(out)
    config.model_config()  # validates backbone, overrides and iterations before any slow work
    protect = (config.collection,)  # never the collection read, nor a folder holding it
    check_target(out, "category", resume=resume, overwrite=overwrite, protect=protect)
    if resume:
        saved = saved_config(out)
        if (Path(saved.collection).resolve(), saved.category) != (Path(config.collection).resolve(), config.category):
            raise ConfigError(f"{out} was a category run on {saved.category} of {saved.collection}, not {config.category} "
                              f"of {config.collection}")
        if not (out / CHECKPOINT).is_file():
            raise ConfigError(f"{out}: nothing to resume (no {CHECKPOINT} there)")
        config = saved
    if config.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"--device {config.device}: CUDA is not available on this machine")
    collection = load_collection(config.collection)
    records = category_records(collection, config.category, max_scenes=config.max_scenes)
    data = category_scene(collection, records, downscale=config.downscale, background=config.background)
    device = torch.device(config.device)
    model_config = config.model_config(data.scene)
    check_fit_fits(config.backbone, model_config, data.scene, batch_rays=config.fit.batch_rays, device=device)
    model = build_model(config.backbone, model_config, data.scene.bounds, seed=config.fit.seed, device=device)
    with run_folder(out, "category", resume=resume, overwrite=overwrite, protect=protect) as run:
        return _train_category(run.dir, config, collection, records, data, model, model_config, device, resume, callbacks)


def _train_category(out: Path, config: CategoryPretrainConfig, collection: Collection, records: Sequence[SceneRecord],
                    data: CategoryData, model, model_config, device: torch.device, resume: bool,
                    callbacks: Sequence[Callback]) -> dict[str, Any]:
    """Train (or continue) the category model in the open run folder ``out``; return its manifest entry."""
    state = resume_fit_state(out, model) if resume else None
    if not resume:
        write_json(out / "config.json", {**to_jsonable(config), "model": to_jsonable(model_config)})
    writer = MetricsWriter(out / "metrics.jsonl")
    background = torch.tensor(config.background, dtype=torch.float32, device=device)
    log.info("category %s: %d scenes, %d training views", config.category, len(records), len(data.scene.splits["train"]))
    try:
        result = fit(model, data.scene, config.fit, background=background, callbacks=[writer, *callbacks], state=state,
                     should_checkpoint=lambda st: save_checkpoint(out / CHECKPOINT, model, st))
    finally:
        writer.close()
    per_scene: dict[str, list[float]] = {name: [] for name in data.scene_names}
    final_psnr = None
    if result.final is not None:
        for r in result.final.renders:
            per_scene[data.scene_names[data.view_scene[r.view]]].append(float(mse_to_psnr(((r.rgb - r.target) ** 2).mean())))
        final_psnr = result.final.psnr
    records_out = read_metrics(out / "metrics.jsonl")
    manifest = {
        "kind": "category",
        "category": config.category,
        "backbone": config.backbone,
        "collection": str(Path(collection.root).resolve()),
        "scenes": list(data.scene_names),
        "train_views": len(data.scene.splits["train"]),
        "test_views": len(data.scene.splits["test"]),
        "resolution": [data.scene.height, data.scene.width],
        "box": [list(CANONICAL_BOX[0]), list(CANONICAL_BOX[1])],
        "model_box": [[round(float(v), 5) for v in row] for row in model.bounds.tolist()] if hasattr(model, "bounds") else None,
        "background": list(config.background),
        "seed": config.fit.seed,
        "steps": result.state.step,
        "time_s": round(result.state.time_s, 3),
        "final_psnr": None if final_psnr is None else round(final_psnr, 4),
        "final_psnr_note": "mean PSNR over the test views of the scenes used (their held-out views)",
        "scene_psnr": {k: round(sum(v) / len(v), 4) for k, v in per_scene.items() if v},
        "final_train_psnr": round(records_out[-1]["train_psnr"], 4) if records_out else None,
        "optimizer": {
            "name": "Adam",
            "eps": config.fit.adam_eps,
            "lr_groups": {g.name: g.lr for g in model.param_groups()},
            "lr_decay": f"exponential to x{config.fit.lr_decay:g} over {config.fit.iters} iterations",
            "batch_rays": config.fit.batch_rays,
        },
        "recipe": RECIPE + "".join(f", {key}={value}" for key, value in model.recipe_notes().items()),
    }
    plot_psnr_curves({f"{config.category} ({config.backbone})": records_out}, "iter", out / "psnr_vs_iter.png",
                     title=f"category model {config.category}: {len(records)} scenes, {config.backbone}")
    save_init(out, model, "category", manifest)
    return manifest


def read_manifest(folder: str | Path) -> dict[str, Any]:
    """The manifest entry (``init.json``'s ``meta``) of a saved category model, without loading weights."""
    return json.loads((Path(folder) / "init.json").read_text()).get("meta", {})
