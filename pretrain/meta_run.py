"""A meta-training run folder: what ``nerfmeta meta-train`` writes, and how it resumes.

Layout of ``RUN/``::

    config.json               the MetaConfig (plus the resolved backbone config)
    metrics.jsonl             one line per meta-step: step, time_s, query_psnr, init_psnr, tasks
    checkpoint.safetensors    latest checkpoint: parameters, Adam moments, step, clock (atomic; the one
                              checkpoint format of nerfmeta.runfolder)
    model.safetensors         the meta-learned initialisation, and
    init.json                 its description (nerfmeta.init format, kind "meta"):
                              ``nerfmeta fit SCENE --init meta:RUN`` starts from it
    summary.json              final figures, incl. the held-out adaptation PSNR
    query_psnr_vs_step.png    query PSNR (after adaptation) against meta-steps

Every file is written atomically, and only by rank 0 of a distributed run, which also holds the
folder's lock; :mod:`nerfmeta.runfolder`'s rules apply (``--overwrite`` replaces only a meta-train
run of ours, built aside and swapped in at the end). A resumed run
continues from the checkpoint's step and produces the same parameters as an uninterrupted run
(tasks are a function of (seed, step), see :mod:`pretrain.meta_tasks`).

A divergence guard (:mod:`nerfmeta.fit.guard`, ``MetaConfig.guard``) watches every meta-step: a
non-finite meta-gradient (or Reptile direction) or a query MSE that explodes rolls the parameters
and Adam moments back to the last snapshot, lowers the outer rate (``meta_lr``, Adam's rate or
Reptile's step; the inner rates are part of what is learned and stay as set) and retries the same
meta-batch. The decision is taken from all-reduced values, so every process takes the same one.
Events go to the record's ``event`` field and ``summary.json["guard_events"]``; the lowered rate
is kept in the checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from nerfmeta.budget import refuse_if_too_big
from nerfmeta.collection.generate import Collection, load_collection
from nerfmeta.errors import ConfigError, NerfmetaError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fields.registry import build_model
from nerfmeta.fit.guard import DivergenceGuard, GuardEvent
from nerfmeta.fit.run import read_metrics  # the same metrics.jsonl reader as fit runs (torn last line ignored)
from nerfmeta.init import save_init
from nerfmeta.io import atomic_path, to_jsonable, write_json
from nerfmeta.metrics import mse_to_psnr
from nerfmeta.runfolder import (
    CHECKPOINT,
    RunFolder,
    check_target,
    load_checkpoint,
    open_run,
    optimizer_state,
    optimizer_tensors,
    save_checkpoint,
)
from pretrain.meta import (
    CANONICAL_BOUNDS,
    MetaConfig,
    evaluate_adaptation,
    inner_lrs,
    meta_wrapper,
    reptile_update,
    task_direction,
)
from pretrain.meta_dist import SINGLE, DistContext
from pretrain.meta_tasks import TaskSampler, load_task_scenes, select_scenes

log = logging.getLogger(__name__)

CONFIG = "config.json"
METRICS = "metrics.jsonl"
SUMMARY = "summary.json"
CURVE = "query_psnr_vs_step.png"
CHECKPOINT_KIND = "meta"
RESUMABLE_CHANGES = ("meta_steps", "checkpoint_every", "eval_tasks", "device", "guard")
"""Fields a resumed run may change; any other difference from the saved config is refused."""


@dataclass
class MetaStepRecord:
    """One meta-step (after its outer update).

    Attributes:
        step: meta-steps done (1-based).
        time_s: wall time of the meta-steps so far (this run and the runs it resumed).
        query_psnr: PSNR of the meta-batch's mean query MSE after adaptation.
        init_psnr: PSNR of the mean support MSE before adaptation (the initialisation's own).
        tasks: the scenes of the meta-batch, in slot order.
        event: the divergence guard's rollbacks before this step succeeded, if any.
    """

    step: int
    time_s: float
    query_psnr: float
    init_psnr: float
    tasks: list[str] = field(default_factory=list)
    event: str | None = None

    def as_json(self) -> dict[str, Any]:
        out = {"step": self.step, "time_s": round(self.time_s, 4), "query_psnr": round(self.query_psnr, 4),
               "init_psnr": round(self.init_psnr, 4), "tasks": self.tasks}
        if self.event:
            out["event"] = self.event
        return out


Progress = Callable[[MetaStepRecord], None]


# ---------------------------------------------------------------------------------------------
# Checkpoints


def save_meta_checkpoint(path: str | os.PathLike, model: RadianceModel, optimizer: torch.optim.Optimizer | None,
                         step: int, time_s: float, config: MetaConfig, *, lr_guard_scale: float = 1.0,
                         guard_events: Sequence[GuardEvent] = ()) -> None:
    """Parameters, buffers, Adam moments, step, clock and the guard's rate factor and events, atomically, in the
    one checkpoint format of :mod:`nerfmeta.runfolder`; refuses non-finite values."""
    tensors: dict[str, torch.Tensor] = {f"model.{name}": value for name, value in model.state_dict().items()}
    optim_meta: dict[str, Any] = {}
    if optimizer is not None:
        optim, optim_meta = optimizer_tensors(optimizer.state_dict())
        tensors.update(optim)
    state = {"backbone": model.backbone, "structure": model.structure(), "algo": config.algo, "step": step, "time_s": time_s,
             "lr_guard_scale": lr_guard_scale, "guard_events": [e.as_json() for e in guard_events], "optimizer": optim_meta}
    save_checkpoint(path, CHECKPOINT_KIND, tensors, state)


@dataclass(frozen=True)
class MetaCheckpoint:
    """A meta-training checkpoint read back (``optim_state``: the optimiser's ``state_dict()``, None for Reptile)."""

    step: int
    time_s: float
    backbone: str
    model_state: dict[str, torch.Tensor]
    optim_state: dict[str, Any] | None
    lr_guard_scale: float = 1.0
    guard_events: tuple[GuardEvent, ...] = ()


def load_meta_checkpoint(path: str | os.PathLike) -> MetaCheckpoint:
    """Read a checkpoint written by :func:`save_meta_checkpoint` (one-line error if unreadable)."""
    ckpt = load_checkpoint(path, CHECKPOINT_KIND)
    meta = ckpt.state
    events = tuple(GuardEvent.from_json(e) for e in meta.get("guard_events", []))
    return MetaCheckpoint(int(meta["step"]), float(meta["time_s"]), str(meta["backbone"]), ckpt.prefixed("model."),
                          optimizer_state(ckpt, meta.get("optimizer")), float(meta.get("lr_guard_scale", 1.0)), events)


def restore(model: RadianceModel, optimizer: torch.optim.Optimizer | None, ckpt: MetaCheckpoint, path: Path) -> None:
    """Load a checkpoint into ``model`` and ``optimizer``; one-line error if its backbone or shapes differ."""
    if ckpt.backbone != model.backbone:
        raise ConfigError(f"{path}: holds a {ckpt.backbone} model, but this run builds a {model.backbone} model")
    own = model.state_dict()
    if set(own) != set(ckpt.model_state):
        diff = sorted(set(own) ^ set(ckpt.model_state))
        raise ConfigError(f"{path}: its tensors do not match this {model.backbone} model ({', '.join(diff[:3])} ...)")
    for name, value in own.items():
        if tuple(value.shape) != tuple(ckpt.model_state[name].shape):
            raise ConfigError(f"{path}: {name} has shape {tuple(ckpt.model_state[name].shape)}, "
                              f"this config builds {tuple(value.shape)}; resume with the run's own settings")
    device = next(iter(own.values())).device
    model.load_state_dict({k: v.to(device) for k, v in ckpt.model_state.items()})
    if optimizer is not None and ckpt.optim_state:
        state = {i: {k: v.to(device) if k != "step" else v for k, v in st.items()} for i, st in ckpt.optim_state["state"].items()}
        optimizer.load_state_dict({"state": state, "param_groups": optimizer.state_dict()["param_groups"]})


# ---------------------------------------------------------------------------------------------
# The run folder


def saved_config(out: str | Path) -> MetaConfig:
    """The :class:`MetaConfig` saved in ``out/config.json``."""
    path = Path(out) / CONFIG
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"{path}: not readable ({err}); nothing to resume") from None
    data.pop("model_config", None)
    return MetaConfig.from_json(data)


def resume_config(out: str | Path, overrides: dict[str, Any]) -> MetaConfig:
    """The saved config of the run in ``out`` with ``overrides`` (the options given again) applied."""
    return dataclasses.replace(saved_config(out), **overrides)


def check_resumable(saved: MetaConfig, config: MetaConfig, out: Path) -> None:
    """Refuse to resume ``out`` with settings that change what is being learned."""
    resolved = {"inner_lr": lambda c: c.inner_lr_resolved[0], "inner_lr_groups": lambda c: c.inner_lr_resolved[1],
                "meta_lr": lambda c: c.outer_lr}  # "unset" and the default it stands for are the same setting
    for f in dataclasses.fields(MetaConfig):
        if f.name in RESUMABLE_CHANGES:
            continue
        value = resolved.get(f.name, lambda c, name=f.name: getattr(c, name))
        old, new = value(saved), value(config)
        if to_jsonable(old) != to_jsonable(new):
            raise ConfigError(f"{out} was meta-trained with {f.name}={to_jsonable(old)!r}, not {to_jsonable(new)!r}; "
                              f"resume it with its own settings or start a new --out")


def check_run_dir(out: Path, config: MetaConfig, *, resume: bool, overwrite: bool,
                  protect: Sequence[str | os.PathLike] = ()) -> MetaCheckpoint | None:
    """Check ``out`` can hold this run (before any work; :mod:`nerfmeta.runfolder`'s rules); on resume,
    read and check its checkpoint."""
    check_target(out, "meta", resume=resume, overwrite=overwrite, protect=protect)
    if not resume:
        return None
    if not (out / CHECKPOINT).is_file() or not (out / CONFIG).is_file():
        raise ConfigError(f"{out}: nothing to resume (no {CHECKPOINT} and {CONFIG} there)")
    check_resumable(saved_config(out), config, out)
    return load_meta_checkpoint(out / CHECKPOINT)


def training_scenes(collection: Collection, config: MetaConfig) -> list:
    """The scenes tasks are drawn from (the collection's train split); at least two."""
    records = select_scenes(collection, "train", config.categories)
    if len(records) < 2:
        names = ", ".join(r.name for r in records) or "none"
        raise ConfigError(f"{collection.root}: {len(records)} training scene{'s' if len(records) != 1 else ''} ({names}); "
                          "meta-learning needs at least 2 (generate more with make-collection --scenes-per-category)")
    return records


def held_out_scenes(collection: Collection, config: MetaConfig) -> list:
    """Up to ``eval_tasks`` scenes of the val split (else the test split), spread evenly over the sorted names."""
    records = select_scenes(collection, "val", config.categories) or select_scenes(collection, "test", config.categories)
    n = min(config.eval_tasks, len(records))
    return [records[(i * len(records)) // n] for i in range(n)] if n else []


def build_meta_model(config: MetaConfig, device: torch.device) -> RadianceModel:
    """The initial model: the backbone config of ``config``, in the canonical [-1, 1]^3 box, weights from ``seed``."""
    bounds = torch.tensor(CANONICAL_BOUNDS, dtype=torch.float32)
    refuse_if_too_big(config.backbone, config.model_config(), bounds, batch_rays=config.support_rays * config.inner_steps
                      + config.query_rays, train_pixels=0, device=device)  # a task's graph: inner steps and the query
    return build_model(config.backbone, config.model_config(), bounds, seed=config.seed, device=device)


def build_outer_optimizer(model: RadianceModel, config: MetaConfig) -> torch.optim.Adam | None:
    """Adam over every parameter for maml/fomaml (``meta_lr``); None for Reptile (its own step)."""
    if config.algo == "reptile":
        return None
    return torch.optim.Adam(model.parameters(), lr=config.outer_lr)


# ---------------------------------------------------------------------------------------------
# Meta-training


@dataclass
class MetaDirection:
    """The all-reduced outcome of one meta-batch, before the outer update.

    Attributes:
        mean: per parameter (its shape), the mean over the meta-batch of the meta-gradient
            (maml, fomaml) or of ``theta' - theta`` (reptile).
        query_mse: the meta-batch's mean query MSE after adaptation.
        init_mse: its mean support MSE before adaptation.
        tasks: the names of this process's tasks.
        finite: every value above is finite.
    """

    mean: list[torch.Tensor]
    query_mse: float
    init_mse: float
    tasks: list[str]
    finite: bool


def meta_direction(model: RadianceModel, sampler: TaskSampler, step: int, config: MetaConfig, lrs: dict[str, float],
                   background: torch.Tensor, dist: DistContext = SINGLE) -> MetaDirection:
    """Adapt to the tasks of meta-batch ``step`` (this process's slots) and all-reduce their mean direction."""
    params = list(model.parameters())
    meta = meta_wrapper(model, config.engine, lrs, first_order=config.algo != "maml")
    total = [torch.zeros_like(p) for p in params]
    query_sum = init_sum = 0.0
    tasks = sampler.tasks(step, config.meta_batch, dist.rank, dist.world_size)
    for task in tasks:
        direction, adaptation = task_direction(config.algo, meta, params, task, config.inner_steps,
                                               background=background, jitter=config.jitter)
        for acc, d in zip(total, direction):
            acc.add_(d.detach())
        query_sum += float(adaptation.query_mse.detach())
        init_sum += adaptation.support_mse[0]
    flat = torch.cat([t.reshape(-1) for t in total] + [torch.tensor([query_sum, init_sum], dtype=total[0].dtype, device=total[0].device)])
    dist.all_reduce_sum_(flat)
    flat /= config.meta_batch
    mean = [m.view_as(p) for m, p in zip(torch.split(flat[:-2], [p.numel() for p in params]), params)]
    return MetaDirection(mean, float(flat[-2]), float(flat[-1]), [t.name for t in tasks], bool(torch.isfinite(flat).all()))


def apply_meta_update(model: RadianceModel, optimizer: torch.optim.Optimizer | None, mean: Sequence[torch.Tensor],
                      config: MetaConfig, lr_scale: float = 1.0) -> None:
    """The outer update with rate ``config.outer_lr * lr_scale``: a Reptile step, or an Adam step on ``mean`` as the gradient."""
    params = list(model.parameters())
    with torch.no_grad():
        if optimizer is None:
            reptile_update(params, mean, config.outer_lr * lr_scale)
        else:
            for g in optimizer.param_groups:
                g["lr"] = config.outer_lr * lr_scale
            for p, m in zip(params, mean):
                p.grad = m.clone()
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)


_META_HINT = "lower --inner-lr or --meta-lr"


def _not_finite(d: MetaDirection) -> str:
    """What was not finite in a meta-batch's outcome, for the error message."""
    return f"the query loss is {d.query_mse}" if not math.isfinite(d.query_mse) else "the meta-gradient is not finite"


def meta_step(model: RadianceModel, optimizer: torch.optim.Optimizer | None, sampler: TaskSampler, step: int,
              config: MetaConfig, lrs: dict[str, float], background: torch.Tensor, dist: DistContext = SINGLE,
              ) -> tuple[float, float, list[str]]:
    """One unguarded outer step of ``config.algo`` over meta-batch ``step``; this process takes its slots.

    Returns:
        the meta-batch's mean query MSE after adaptation, mean support MSE before it, and the
        names of this process's tasks.

    Raises:
        NerfmetaError: the meta-gradient is not finite (nothing was updated).
    """
    d = meta_direction(model, sampler, step, config, lrs, background, dist)
    if not d.finite:
        raise NerfmetaError(f"meta-step {step + 1}: {_not_finite(d)}; {_META_HINT}")
    apply_meta_update(model, optimizer, d.mean, config)
    return d.query_mse, d.init_mse, d.tasks


def guarded_meta_step(model: RadianceModel, optimizer: torch.optim.Optimizer | None, sampler: TaskSampler, step: int,
                      config: MetaConfig, lrs: dict[str, float], background: torch.Tensor, guard: DivergenceGuard,
                      dist: DistContext = SINGLE) -> tuple[MetaDirection, list[GuardEvent]]:
    """:func:`meta_step` under ``guard``: a bad meta-batch is rolled back to the snapshot and retried.

    Returns:
        the accepted meta-batch's outcome and the rollbacks it took (empty when the first try was good).

    Raises:
        NerfmetaError: the guard is off and the meta-gradient is not finite, or the guard gave up.
    """
    events: list[GuardEvent] = []
    while True:
        d = meta_direction(model, sampler, step, config, lrs, background, dist)
        if not d.finite:
            if not guard.config.enabled:
                raise NerfmetaError(f"meta-step {step + 1}: {_not_finite(d)}; {_META_HINT}, or turn the divergence guard on")
            bad = "nan query loss" if math.isnan(d.query_mse) else "inf query loss" if math.isinf(d.query_mse) \
                else "non-finite meta-gradient"
        else:
            bad = guard.check_loss(d.query_mse, step + 1, _META_HINT)
        if bad is None:
            break
        events.append(guard.rollback(step + 1, bad, model, optimizer, _META_HINT))
    guard.accept(d.query_mse, step, model, optimizer)  # before the update: the snapshot holds checked values
    apply_meta_update(model, optimizer, d.mean, config, guard.lr_scale)
    return d, events


def meta_train(
    config: MetaConfig,
    collection: str | os.PathLike,
    out: str | os.PathLike,
    *,
    resume: bool = False,
    overwrite: bool = False,
    progress: Progress | None = None,
    dist: DistContext = SINGLE,
) -> dict[str, Any]:
    """Meta-learn an initialisation over a collection's training scenes into the run folder ``out``.

    Args:
        config: the run's settings (validated before any work).
        collection: a collection folder or its ``collection.json``.
        out: the run folder: new or empty, or with ``overwrite`` a previous run to replace, or with
            ``resume`` a run to continue (``config`` must then equal its saved one, except for
            :data:`RESUMABLE_CHANGES`; see :func:`resume_config`).
        progress: called on rank 0 after every meta-step.
        dist: this process's place in a distributed run (:func:`pretrain.meta_dist.distributed_from_env`).

    Returns:
        the summary (also ``summary.json``; rank 0's, the others return the same figures
        without the held-out evaluation).
    """
    config.validate()
    out = Path(out)
    coll = load_collection(collection)
    train_records = training_scenes(coll, config)
    eval_records = held_out_scenes(coll, config)
    device = dist.device(config.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {config.device}: CUDA is not available on this machine")

    model = build_meta_model(config, device)
    optimizer = build_outer_optimizer(model, config)
    lrs = inner_lrs(model, *config.inner_lr_resolved)

    def prepare() -> tuple[int, float, float, list[dict[str, Any]]]:
        ckpt = check_run_dir(out, config, resume=resume, overwrite=overwrite, protect=(coll.root,))
        if ckpt is None:
            return 0, 0.0, 1.0, []
        restore(model, optimizer, ckpt, out / CHECKPOINT)
        return ckpt.step, ckpt.time_s, ckpt.lr_guard_scale, [e.as_json() for e in ckpt.guard_events]

    start, time_s, guard_scale, guard_events = dist.broadcast_object(dist.on_main(prepare))
    if resume and not dist.is_main:  # rank 0 has checked the checkpoint: the same file loads here
        restore(model, optimizer, load_meta_checkpoint(out / CHECKPOINT), out / CHECKPOINT)
    background = torch.tensor(config.background, dtype=torch.float32, device=device)
    sampler = TaskSampler(load_task_scenes(coll, train_records, device=device, downscale=config.downscale,
                                           background=config.background), config.seed, config.support_rays, config.query_rays)

    def start_files() -> RunFolder:
        run = open_run(out, "meta", resume=resume, overwrite=overwrite, protect=(coll.root,))  # locked; aside with overwrite
        try:
            if resume:
                kept = [r for r in read_metrics(run.dir / METRICS) if r["step"] <= start]
                with atomic_path(run.dir / METRICS) as tmp:
                    tmp.write_text("".join(json.dumps(r) + "\n" for r in kept))
            else:
                write_json(run.dir / CONFIG, {**to_jsonable(config), "model_config": to_jsonable(config.model_config())})
        except BaseException:
            run.close()
            raise
        return run

    run = dist.on_main(start_files)  # only now, once every input has been read and checked
    try:
        summary = _train_into(run.dir if run is not None else out, config, model, optimizer, sampler, coll, train_records,
                              eval_records, lrs, background, start, time_s, guard_scale, guard_events, progress, dist)
        if run is not None:
            run.commit()
    finally:
        if run is not None:
            run.close()
    dist.barrier()
    return summary if summary is not None else {"meta_steps": config.meta_steps, "time_s": time_s}


def _train_into(folder: Path, config: MetaConfig, model: RadianceModel, optimizer: torch.optim.Optimizer | None,
                sampler: TaskSampler, coll: Collection, train_records: Sequence, eval_records: Sequence,
                lrs: dict[str, float], background: torch.Tensor, start: int, time_s: float, guard_scale: float,
                guard_events: list[dict[str, Any]], progress: Progress | None, dist: DistContext) -> dict[str, Any] | None:
    """The meta-steps from ``start`` on, then (rank 0) the outputs, written into the open run folder ``folder``."""
    device = background.device
    if config.meta_batch < dist.world_size:
        log.warning("meta-batch %d is smaller than the %d processes: some processes idle", config.meta_batch, dist.world_size)
    log.info("meta-training %s/%s on %d scenes, %d process(es), from step %d", config.backbone, config.algo,
             len(train_records), dist.world_size, start)

    guard = DivergenceGuard(config.guard, lr_scale=guard_scale, events=[GuardEvent.from_json(e) for e in guard_events],
                            what="meta-train")
    guard.retake(start, model, optimizer)
    metrics = open(folder / METRICS, "a", encoding="utf-8") if dist.is_main else None
    try:
        for step in range(start, config.meta_steps):
            t0 = time.perf_counter()
            d, rollbacks = guarded_meta_step(model, optimizer, sampler, step, config, lrs, background, guard, dist)
            query_mse, init_mse = d.query_mse, d.init_mse
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            time_s += time.perf_counter() - t0
            done = step + 1
            if not dist.is_main:
                continue
            names = [sampler.scenes[i].record.name for i in sampler.scene_indices(step, config.meta_batch)]
            record = MetaStepRecord(done, time_s, float(mse_to_psnr(query_mse)), float(mse_to_psnr(init_mse)), names,
                                    "; ".join(e.message() for e in rollbacks) or None)
            metrics.write(json.dumps(record.as_json()) + "\n")
            metrics.flush()
            if progress is not None:
                progress(record)
            if config.checkpoint_every > 0 and done % config.checkpoint_every == 0 and done < config.meta_steps:
                save_meta_checkpoint(folder / CHECKPOINT, model, optimizer, done, time_s, config,
                                     lr_guard_scale=guard.lr_scale, guard_events=guard.events)
    finally:
        if metrics is not None:
            metrics.close()

    def finish() -> dict[str, Any]:
        save_meta_checkpoint(folder / CHECKPOINT, model, optimizer, max(start, config.meta_steps), time_s, config,
                             lr_guard_scale=guard.lr_scale, guard_events=guard.events)
        return write_outputs(folder, config, model, coll, train_records, eval_records, lrs, time_s, dist.world_size, background,
                             guard_events=guard.events)

    return dist.on_main(finish)


@dataclass(frozen=True)
class MetaSummary:
    """The final figures of a meta-training run: ``summary.json`` and ``init.json``'s ``meta``, written once
    at the end (keys in this order; reports and the zoo read them: keep them stable)."""

    algo: str
    """maml, fomaml or reptile."""
    engine: str
    """The meta-gradient engine."""
    backbone: str
    """Backbone name."""
    inner_steps: int
    """Inner-loop steps per task."""
    inner_lr: dict[str, float]
    """Inner rate per parameter group."""
    meta_lr: float
    """Outer rate."""
    outer_update: str
    """Adam or the Reptile step."""
    meta_batch: int
    """Tasks per meta-step."""
    support_rays: int
    """Support rays per task."""
    query_rays: int
    """Query rays per task."""
    meta_steps: int
    """Meta-steps done."""
    scenes: list[str]
    """The training scenes."""
    categories: list[str]
    """Their categories."""
    collection: str
    """The collection folder."""
    seed: int
    """Seed of weights and tasks."""
    final_query_psnr: float | None
    """Mean query PSNR of the last 10 meta-steps."""
    final_query_psnr_note: str
    """How final_query_psnr is taken."""
    held_out: dict[str, Any] | None
    """Adaptation on held-out scenes (before/after)."""
    time_s: float
    """Wall time of the meta-steps."""
    world_size: int
    """Processes."""
    n_parameters: int
    """Parameters of the model."""
    guard_events: list[dict[str, Any]]
    """The divergence guard's rollbacks."""

    def as_json(self) -> dict[str, Any]:
        return {f.name: to_jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}


def write_outputs(out: Path, config: MetaConfig, model: RadianceModel, coll: Collection, train_records: Sequence,
                  eval_records: Sequence, lrs: dict[str, float], time_s: float, world_size: int,
                  background: torch.Tensor, *, guard_events: Sequence[GuardEvent] = ()) -> dict[str, Any]:
    """The initialisation (``nerfmeta.init`` format), the held-out evaluation, the curve and ``summary.json``."""
    records = read_metrics(out / METRICS)
    last = records[-10:]
    final_query = sum(r["query_psnr"] for r in last) / len(last) if last else None
    held_out = None
    if eval_records:
        device = background.device
        scenes = load_task_scenes(coll, eval_records, device=device, downscale=config.downscale, background=config.background)
        tasks = TaskSampler(scenes, config.seed, config.support_rays, config.query_rays).eval_tasks(len(scenes))
        before, after = evaluate_adaptation(model, tasks, config.inner_steps, lrs, background=background, engine="torchfunc")
        held_out = {"split": eval_records[0].split, "scenes": [r.name for r in eval_records],
                    "query_psnr_before": round(float(mse_to_psnr(before)), 4),
                    "query_psnr_after": round(float(mse_to_psnr(after)), 4), "inner_steps": config.inner_steps}
    group_lrs = {g.name: lrs[g.param_names[0]] for g in model.param_groups()}
    summary = MetaSummary(
        algo=config.algo,
        engine=config.engine,
        backbone=config.backbone,
        inner_steps=config.inner_steps,
        inner_lr=group_lrs,
        meta_lr=config.outer_lr,
        outer_update="reptile step" if config.algo == "reptile" else "Adam",
        meta_batch=config.meta_batch,
        support_rays=config.support_rays,
        query_rays=config.query_rays,
        meta_steps=records[-1]["step"] if records else 0,
        scenes=[r.name for r in train_records],
        categories=sorted({r.category for r in train_records}),
        collection=str(coll.root),
        seed=config.seed,
        final_query_psnr=None if final_query is None else round(final_query, 4),
        final_query_psnr_note="mean over the last 10 meta-steps of the meta-batch query PSNR after adaptation",
        held_out=held_out,
        time_s=round(time_s, 3),
        world_size=world_size,
        n_parameters=sum(p.numel() for p in model.parameters()),
        guard_events=[e.as_json() for e in guard_events],
    ).as_json()
    save_init(out, model, "meta", summary)
    plot_query_curve(records, out / CURVE, title=f"{config.backbone} {config.algo}: {len(train_records)} scenes, "
                                                   f"{config.inner_steps} inner steps, meta-batch {config.meta_batch}")
    write_json(out / SUMMARY, summary)  # once, at the end
    return summary


def plot_query_curve(records: Sequence[dict[str, Any]], path: Path, *, title: str = "") -> None:
    """Query PSNR after adaptation, and the initialisation's support PSNR, against meta-steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from nerfmeta.report.plots import save_figure

    steps = np.array([r["step"] for r in records], dtype=float)
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    for key, label, color in (("query_psnr", "query PSNR after adaptation", "C0"), ("init_psnr", "initialisation (before adaptation)", "C1")):
        ys = np.array([r[key] for r in records], dtype=float)
        if len(ys):
            ax.plot(steps, ys, color=color, lw=0.8, alpha=0.35)
            ax.plot(steps, _smooth(ys), color=color, lw=1.6, label=f"{label}, smoothed")
    ax.set_xlabel("meta-step")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    save_figure(fig, path)


def _smooth(values, window: int = 10):
    import numpy as np

    csum = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(0, idx - window)
    return (csum[idx] - csum[lo]) / (idx - lo)

