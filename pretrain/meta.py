"""Meta-learned initialisations: MAML, first-order MAML and Reptile over a collection's scenes.

Each training scene is a *task*: a batch of support rays for the inner loop and a batch of query
rays for the outer loss, both drawn from the scene's training views. The inner loop is plain SGD
on the photometric MSE; the outer loop updates the shared initial parameters. The API follows
learn2learn: wrap the model (:func:`meta_wrapper`), ``clone()`` a learner per task, let
:func:`fast_adapt` call ``learner.adapt(loss)`` ``steps`` times, then back-propagate the query
loss into the original parameters. :func:`fast_adapt` is the one inner loop, used by
meta-training and by test-time adaptation (:func:`evaluate_adaptation`).

Algorithms (``MetaConfig.algo``), with ``theta`` the initial parameters, ``theta'`` the parameters
after ``inner_steps`` SGD steps on the support rays and ``L_q`` the query MSE:

- ``maml``: the exact meta-gradient ``d L_q(theta'(theta)) / d theta``, back-propagated through
  the inner SGD steps (second order: Hessian-vector products of the support loss).
- ``fomaml``: ``grad L_q(theta')`` used as the meta-gradient (the inner steps are treated as the
  identity, so no second-order terms).
- ``reptile``: no query gradient at all; ``theta <- theta + meta_lr * mean_tasks(theta' - theta)``
  (Nichol et al. 2018), the query MSE is only reported.

MAML and FOMAML update ``theta`` with Adam (``meta_lr``); Reptile with the plain step above.

Backbones and algorithms: what a backbone supports is declared by the backbone itself
(:class:`~nerfmeta.fields.base.MetaHints`: its algorithms, the config values meta-learning forces so
its parameter set never changes, its default size and inner rates); this module never tests a
backbone's name. The NeRF MLP supports all three (its forward is smooth, so second order is exact;
tested); the voxel grid first order only, in one fixed fine stage.

Engines (``MetaConfig.engine``): ``torchfunc`` (default) renders a parameter dict with
``torch.func.functional_call`` and takes inner and outer gradients with ``torch.autograd.grad``
(``create_graph=True`` for MAML). Nesting ``torch.func.grad`` transforms instead gave identical
MAML gradients (difference 0) but ran about 2x slower on CPU (a 4x128 MLP, 256-1024 rays, 3 inner
steps), so the autograd form is used. ``l2l`` uses
``learn2learn.algorithms.MAML`` (optional dependency, imported only when selected); both engines
perform the same floating-point operations, and a test checks they agree.

All randomness is a function of ``(seed, meta-step, task slot)`` (:func:`derive_seed`), so any
number of processes sees the same tasks: see :mod:`pretrain.meta_run`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Protocol, Sequence

import numpy as np
import torch
from torch import nn
from torch.func import functional_call

from nerfmeta.data.scene import RayBatch
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import MetaHints, RadianceModel, total_loss
from nerfmeta.fields.registry import BACKBONES, config_from_dict, default_config, model_class
from nerfmeta.fit.guard import GuardConfig

ALGOS = ("maml", "fomaml", "reptile")
ENGINES = ("torchfunc", "l2l")
GROUP_LR_RAYS = 512
"""Support-batch size the default group rates of a backbone's ``MetaHints.inner_group_lr`` are quoted for."""

CANONICAL_BOUNDS = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
"""The box of every meta-learned model: generated collections put each object in [-1, 1]^3, so one
initialisation means the same place in every scene."""


@dataclass(frozen=True)
class MetaConfig:
    """Everything that defines a meta-training run; saved as ``config.json`` beside it."""

    backbone: str = "nerf"
    """Backbone to meta-learn: ``nerf`` (MLP; maml, fomaml, reptile) or ``grid`` (fomaml, reptile); see its ``meta_hints``."""
    model: dict[str, Any] = field(default_factory=dict)
    """Backbone config overrides (JSON form) on top of the meta-learning defaults for that backbone."""
    algo: str = "reptile"
    """Meta-learning algorithm: ``maml`` (second order), ``fomaml`` (first order) or ``reptile`` (cheapest; best in our runs)."""
    engine: str = "torchfunc"
    """``torchfunc`` (functional_call + autograd.grad) or ``l2l`` (learn2learn's MAML; optional package)."""
    inner_steps: int = 3
    """SGD steps on a task's support rays in the inner loop."""
    inner_lr: float | None = None
    """Inner SGD rate of every parameter; unset: the backbone's ``meta_hints.inner_lr`` (30 for nerf, 10 for the grid's MLP)."""
    inner_lr_groups: dict[str, float] = field(default_factory=dict)
    """Inner SGD rates of named parameter groups over the defaults (grid: density=1e5, features=3e4, times support_rays/512)."""
    meta_lr: float | None = None
    """Outer learning rate; unset: 1e-3 for maml/fomaml (Adam), 0.5 for reptile (its step size)."""
    meta_batch: int = 4
    """Tasks (scenes) per meta-step; their meta-gradients are averaged."""
    support_rays: int = 512
    """Rays of a task's support batch (inner loop)."""
    query_rays: int = 512
    """Rays of a task's query batch (outer loss and the reported query PSNR)."""
    meta_steps: int = 200
    """Outer steps in total (a resumed run may raise it)."""
    seed: int = 0
    """Seed of the initial weights, the task sampling, the rays and the sample jitter."""
    checkpoint_every: int = 25
    """Write a checkpoint every this many meta-steps (0: only at the end)."""
    categories: tuple[str, ...] = ()
    """Categories of the collection to learn from (empty: all)."""
    eval_tasks: int = 8
    """Held-out (val split, else test split) scenes adapted at the end to report query PSNR (0: none)."""
    jitter: bool = True
    """Jitter the samples along rays while rendering tasks (as the fit loop does)."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Background the RGBA images are composited on (and rendered over)."""
    downscale: float = 1.0
    """Image downscale factor applied when loading the scenes."""
    device: str = "cpu"
    """Torch device; under torchrun ``cuda`` means each process's ``cuda:LOCAL_RANK``."""
    guard: GuardConfig = GuardConfig(snapshot_every=5)
    """Divergence guard on the meta-steps: a non-finite meta-gradient or an exploding query MSE rolls back, lowers the outer rate and retries."""

    def __post_init__(self) -> None:
        # JSON has no tuples or nested dataclasses: accept lists and dicts so a saved config loads back equal.
        object.__setattr__(self, "guard", GuardConfig.coerce(self.guard))
        object.__setattr__(self, "categories", tuple(self.categories))
        object.__setattr__(self, "background", tuple(float(v) for v in self.background))
        object.__setattr__(self, "model", {k: tuple(v) if isinstance(v, list) else v for k, v in dict(self.model).items()})
        object.__setattr__(self, "inner_lr_groups", {str(k): float(v) for k, v in dict(self.inner_lr_groups).items()})

    @property
    def inner_lr_resolved(self) -> tuple[float, dict[str, float]]:
        """(inner rate of every parameter, rates of named groups) with the backbone defaults filled in."""
        hints = self.hints()
        lr, groups = hints.inner_lr, hints.inner_group_lr
        scale = self.support_rays / GROUP_LR_RAYS  # a voxel's share of a mean loss shrinks with the batch
        groups = {name: value * scale for name, value in groups.items()}
        return (lr if self.inner_lr is None else float(self.inner_lr)), {**groups, **self.inner_lr_groups}

    @property
    def outer_lr(self) -> float:
        """``meta_lr`` with its per-algorithm default filled in."""
        if self.meta_lr is not None:
            return float(self.meta_lr)
        return 0.5 if self.algo == "reptile" else 1e-3

    def validate(self) -> None:
        """Raise a one-line :class:`ConfigError` for any value that cannot be meta-trained."""
        if self.backbone not in BACKBONES:
            raise ConfigError(f"unknown backbone {self.backbone!r}; choose one of {', '.join(BACKBONES)}")
        if self.algo not in ALGOS:
            raise ConfigError(f"unknown --algo {self.algo!r}; choose one of {', '.join(ALGOS)}")
        if self.engine not in ENGINES:
            raise ConfigError(f"unknown --engine {self.engine!r}; choose one of {', '.join(ENGINES)}")
        hints = self.hints()
        if self.algo not in hints.algos:
            raise ConfigError(hints.why_not or f"--algo {self.algo} is not supported for --backbone {self.backbone}; "
                              f"use one of {', '.join(hints.algos)}")
        positive = (("--inner-steps", self.inner_steps), ("--meta-batch", self.meta_batch), ("--support-rays", self.support_rays),
                    ("--query-rays", self.query_rays), ("--meta-steps", self.meta_steps))
        for name, value in positive:
            if not isinstance(value, int) or value < 1:
                raise ConfigError(f"{name} {value!r}: must be a positive integer")
        lr, groups = self.inner_lr_resolved
        rates = [("--inner-lr", lr), ("--meta-lr", self.outer_lr)] + [(f"--inner-lr-group {k}", v) for k, v in groups.items()]
        for name, value in rates:
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} {value!r}: must be a positive number")
        for name, value in (("--checkpoint-every", self.checkpoint_every), ("--eval-tasks", self.eval_tasks), ("--seed", self.seed)):
            if not isinstance(value, int) or value < 0:
                raise ConfigError(f"{name} {value!r}: must be an integer >= 0")
        if not self.downscale >= 1.0:
            raise ConfigError(f"--downscale {self.downscale!r}: must be >= 1")
        if len(self.background) != 3 or not all(0.0 <= v <= 1.0 for v in self.background):
            raise ConfigError(f"background {self.background!r}: must be three values in [0, 1]")
        self.model_config()

    def hints(self) -> MetaHints:
        """What the backbone declares about meta-learning (:class:`~nerfmeta.fields.base.MetaHints`)."""
        if self.backbone not in BACKBONES:
            raise ConfigError(f"unknown backbone {self.backbone!r}; choose one of {', '.join(BACKBONES)}")
        return model_class(self.backbone).meta_hints

    def model_config(self) -> Any:
        """The backbone config: its defaults, its meta-learning defaults, then ``model`` overrides.

        The values the backbone fixes for meta-learning (``MetaHints.fixed``, e.g. the grid's one
        fixed fine stage) are forced; an override that contradicts them is an error.
        """
        hints = self.hints()
        values = {**dataclasses.asdict(default_config(self.backbone)), **hints.model_defaults, **self.model}
        for key, forced in hints.fixed.items():
            if key in self.model and _plain(self.model[key]) != _plain(forced):
                raise ConfigError(f"--set {key}={self.model[key]!r}: {hints.fixed_reason} "
                                  f"({', '.join(f'{k}={_plain(v)}' for k, v in hints.fixed.items())})")
        values.update(hints.fixed)
        return config_from_dict(self.backbone, values)

    @staticmethod
    def from_json(data: dict[str, Any]) -> "MetaConfig":
        names = {f.name for f in dataclasses.fields(MetaConfig)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"meta-train config has unknown keys {unknown}")
        return MetaConfig(**data)


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, (tuple, list)) else value


# ---------------------------------------------------------------------------------------------
# Tasks


@dataclass(frozen=True)
class Task:
    """One task: a scene's support and query rays, and the seed of its sample jitter.

    Attributes:
        name: the scene's name.
        support: rays (n_support) with targets, for the inner loop.
        query: rays (n_query) with targets, for the outer loss.
        seed: seeds the generator of the sample jitter of every render in :func:`fast_adapt`.
    """

    name: str
    support: RayBatch
    query: RayBatch
    seed: int


def derive_seed(*keys: int) -> int:
    """A 63-bit seed from integer keys (e.g. ``(seed, step, slot)``); independent streams per key."""
    return int(np.random.SeedSequence([int(k) for k in keys]).generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


# ---------------------------------------------------------------------------------------------
# Learners (the learn2learn interface: clone(), adapt(loss), __call__ renders, parameters())


class Learner(Protocol):
    def __call__(self, rays: RayBatch, *, background: torch.Tensor, train: bool, generator: torch.Generator | None) -> Any: ...
    def adapt(self, loss: torch.Tensor) -> None: ...
    def parameters(self) -> Iterable[torch.Tensor]: ...


class MetaModule(Protocol):
    def clone(self) -> Learner: ...


class FunctionalLearner:
    """A task's copy of the parameters as a dict, rendered with ``torch.func.functional_call``.

    ``adapt(loss)`` takes one SGD step ``p <- p + (-lr * dloss/dp)`` (written as learn2learn
    writes it, so both engines do the same floating-point operations). With ``first_order`` the
    gradient is not differentiated again (``create_graph=False``), so back-propagating through
    the adapted parameters treats the step as the identity (FOMAML); otherwise the step stays in
    the graph and the meta-gradient is exact second-order MAML.
    """

    def __init__(self, model: RadianceModel, params: dict[str, torch.Tensor], lrs: dict[str, float], first_order: bool):
        self.model = model
        self.params = dict(params)
        self.lrs = lrs
        self.first_order = first_order

    def __call__(self, rays: RayBatch, **kwargs: Any) -> Any:
        return functional_call(self.model, self.params, (rays,), kwargs)

    def adapt(self, loss: torch.Tensor) -> None:
        names = list(self.params)
        grads = torch.autograd.grad(loss, [self.params[n] for n in names], create_graph=not self.first_order, allow_unused=True)
        self.params = {n: self.params[n] if g is None else self.params[n] + (-self.lrs[n] * g) for n, g in zip(names, grads)}

    def parameters(self) -> Iterable[torch.Tensor]:
        return self.params.values()


class FunctionalMAML:
    """The ``torchfunc`` engine's wrapper: ``clone()`` a :class:`FunctionalLearner` over the model's parameters."""

    def __init__(self, model: RadianceModel, lrs: dict[str, float], first_order: bool):
        self.model = model
        self.lrs = lrs
        self.first_order = first_order

    def clone(self) -> FunctionalLearner:
        return FunctionalLearner(self.model, dict(self.model.named_parameters()), self.lrs, self.first_order)


class L2LGroupLearner:
    """A learn2learn MAML clone whose SGD step has one learning rate per parameter.

    learn2learn's ``MAML.adapt`` takes a single ``lr``. With per-group rates the gradients are
    scaled by ``lr_p / lr`` and applied with learn2learn's own ``maml_update``, which then computes
    ``p + (-lr * (g * lr_p / lr))``: the same step up to rounding.
    """

    def __init__(self, clone: Any, lrs: Sequence[float], first_order: bool):
        self.clone = clone
        self.lr = float(clone.lr)
        self.scales = [lr / self.lr for lr in lrs]
        self.first_order = first_order

    def __call__(self, rays: RayBatch, **kwargs: Any) -> Any:
        return self.clone(rays, **kwargs)

    def adapt(self, loss: torch.Tensor) -> None:
        from learn2learn.algorithms.maml import maml_update

        params = list(self.clone.module.parameters())
        grads = torch.autograd.grad(loss, params, create_graph=not self.first_order, retain_graph=not self.first_order, allow_unused=True)
        grads = [None if g is None else g * s for g, s in zip(grads, self.scales)]
        self.clone.module = maml_update(self.clone.module, self.lr, grads)

    def parameters(self) -> Iterable[torch.Tensor]:
        return self.clone.parameters()


class L2LMAML:
    """The ``l2l`` engine's wrapper around ``learn2learn.algorithms.MAML`` (one rate: pure learn2learn)."""

    def __init__(self, model: RadianceModel, lrs: dict[str, float], first_order: bool):
        l2l = _import_learn2learn()
        self.lrs = [lrs[n] for n, _ in model.named_parameters()]
        self.uniform = len(set(self.lrs)) == 1
        self.maml = l2l.algorithms.MAML(model, lr=max(self.lrs), first_order=first_order, allow_unused=True)
        self.first_order = first_order

    def clone(self) -> Learner:
        clone = self.maml.clone()
        return clone if self.uniform else L2LGroupLearner(clone, self.lrs, self.first_order)


def learn2learn_available() -> tuple[bool, str]:
    """(True, version) when learn2learn imports, else (False, the reason)."""
    try:
        l2l = _import_learn2learn()
    except ImportError as err:
        return False, f"learn2learn is not installed ({err}); pip install 'nerfmeta[meta]' or scripts/install_learn2learn.sh"
    return True, str(getattr(l2l, "__version__", "?"))


def _import_learn2learn() -> Any:
    """Import learn2learn lazily (it imports torchvision, which needs :mod:`nerfmeta.compat` here)."""
    import contextlib
    import io
    import warnings

    from nerfmeta.compat import import_torchvision

    import_torchvision()
    # learn2learn imports gym, which prints a deprecation banner on import: keep it off the terminal.
    with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        import learn2learn

    return learn2learn


def inner_lrs(model: RadianceModel, inner_lr: float, groups: dict[str, float] | None = None) -> dict[str, float]:
    """Inner SGD rate of every parameter: ``inner_lr``, or ``groups[g]`` for the parameters of the
    model's parameter group ``g`` (see ``param_groups()``; an unknown group name is an error)."""
    groups = dict(groups or {})
    known = {g.name: g.param_names for g in model.param_groups()}
    unknown = sorted(set(groups) - set(known))
    if unknown:
        raise ConfigError(f"inner-lr group {', '.join(unknown)}: the {model.backbone} backbone's groups are {', '.join(known)}")
    lrs = {n: float(inner_lr) for n, _ in model.named_parameters()}
    for name, lr in groups.items():
        for param in known[name]:
            lrs[param] = float(lr)
    return lrs


def meta_wrapper(model: RadianceModel, engine: str, lrs: dict[str, float] | float, first_order: bool) -> MetaModule:
    """Wrap ``model`` for meta-learning with ``engine``; ``clone()`` gives a learner.

    Args:
        model: the model whose parameters are the initialisation.
        engine: ``torchfunc`` or ``l2l``.
        lrs: the inner SGD rate, one for all or one per parameter name (:func:`inner_lrs`).
        first_order: treat the inner steps as the identity when back-propagating (FOMAML, Reptile).
    """
    if not isinstance(lrs, dict):
        lrs = {n: float(lrs) for n, _ in model.named_parameters()}
    if engine == "torchfunc":
        return FunctionalMAML(model, lrs, first_order)
    if engine == "l2l":
        ok, why = learn2learn_available()
        if not ok:
            raise ConfigError(f"--engine l2l: {why}; or use --engine torchfunc")
        return L2LMAML(model, lrs, first_order)
    raise ConfigError(f"unknown --engine {engine!r}; choose one of {', '.join(ENGINES)}")


# ---------------------------------------------------------------------------------------------
# The inner loop and the meta-gradients


def task_loss(learner: Learner | nn.Module, rays: RayBatch, background: torch.Tensor, generator: torch.Generator | None,
              jitter: bool = True) -> torch.Tensor:
    """The model's loss (a scalar) on ``rays`` (n_rays) against ``rays.target``: the sum of its named terms,
    as the fit loop sums them (the photometric MSE, plus e.g. the grid's TV when its weight is set)."""
    out = learner(rays, background=background, train=jitter, generator=generator, target=rays.target)
    return total_loss(out.losses)


@dataclass
class Adaptation:
    """What :func:`fast_adapt` returns.

    Attributes:
        query_mse: () the query loss after adaptation (differentiable back to the initial parameters);
            the MSE unless the model adds loss terms (:func:`task_loss`).
        support_mse: the support loss before each inner step (``support_mse[0]``: the initialisation's).
    """

    query_mse: torch.Tensor
    support_mse: list[float]


def fast_adapt(task: Task, learner: Learner, steps: int, *, background: torch.Tensor, jitter: bool = True) -> Adaptation:
    """Adapt ``learner`` in place with ``steps`` SGD steps on ``task.support``; return the query loss.

    The one inner loop of meta-training (every algorithm, both engines) and of test-time
    adaptation. Every render draws its jitter from one generator seeded with ``task.seed``, in a
    fixed order (support renders, then the query), so the result is a function of the task.
    """
    generator = torch.Generator().manual_seed(task.seed)
    support_mse = []
    for _ in range(steps):
        loss = task_loss(learner, task.support, background, generator, jitter)
        support_mse.append(float(loss.detach()))
        learner.adapt(loss)
    query = task_loss(learner, task.query, background, generator, jitter)
    return Adaptation(query, support_mse)


def maml_meta_grad(meta: MetaModule, params: Sequence[torch.Tensor], task: Task, steps: int, *, background: torch.Tensor,
                   jitter: bool = True) -> tuple[list[torch.Tensor], Adaptation]:
    """MAML / FOMAML meta-gradient of one task: ``d L_q(theta') / d theta`` for the initial ``params``.

    Second order when ``meta`` was wrapped with ``first_order=False`` (the inner steps stay in
    the graph), first order otherwise (the same call then yields ``grad L_q(theta')``).

    Returns:
        one gradient per parameter (zeros where the loss does not depend on it) and the adaptation.
    """
    learner = meta.clone()
    adaptation = fast_adapt(task, learner, steps, background=background, jitter=jitter)
    grads = torch.autograd.grad(adaptation.query_mse, list(params), allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)], adaptation


fomaml_meta_grad = maml_meta_grad
"""First-order MAML uses the same call with a ``first_order=True`` wrapper (see :func:`maml_meta_grad`)."""


def reptile_direction(meta: MetaModule, params: Sequence[torch.Tensor], task: Task, steps: int, *, background: torch.Tensor,
                      jitter: bool = True) -> tuple[list[torch.Tensor], Adaptation]:
    """Reptile's direction of one task: ``theta' - theta`` (detached), with the adaptation for reporting."""
    learner = meta.clone()
    adaptation = fast_adapt(task, learner, steps, background=background, jitter=jitter)
    adaptation.query_mse = adaptation.query_mse.detach()
    return [(a.detach() - p.detach()) for a, p in zip(learner.parameters(), params)], adaptation


@torch.no_grad()
def reptile_update(params: Sequence[torch.Tensor], mean_direction: Sequence[torch.Tensor], step_size: float) -> None:
    """In place: ``theta <- theta + step_size * mean_tasks(theta' - theta)`` (Nichol et al. 2018)."""
    for p, d in zip(params, mean_direction):
        p.add_(d, alpha=step_size)


def task_direction(algo: str, meta: MetaModule, params: Sequence[torch.Tensor], task: Task, steps: int, *,
                   background: torch.Tensor, jitter: bool = True) -> tuple[list[torch.Tensor], Adaptation]:
    """The per-task quantity averaged over a meta-batch: the meta-gradient (maml, fomaml) or ``theta' - theta`` (reptile)."""
    if algo == "reptile":
        return reptile_direction(meta, params, task, steps, background=background, jitter=jitter)
    return maml_meta_grad(meta, params, task, steps, background=background, jitter=jitter)


def evaluate_adaptation(model: RadianceModel, tasks: Sequence[Task], steps: int, lrs: dict[str, float] | float, *,
                        background: torch.Tensor, engine: str = "torchfunc") -> tuple[float, float]:
    """Mean query MSE over ``tasks`` before and after ``steps`` inner SGD steps (test-time adaptation).

    Uses :func:`fast_adapt` with a first-order learner; the model is not changed. Renders without
    jitter so the figure depends only on the parameters and the rays.
    """
    meta = meta_wrapper(model, engine, lrs, first_order=True)
    before, after = [], []
    for task in tasks:
        with torch.no_grad():
            before.append(float(task_loss(model, task.query, background, None, jitter=False)))
        adaptation = fast_adapt(task, meta.clone(), steps, background=background, jitter=False)
        after.append(float(adaptation.query_mse.detach()))
    return sum(before) / len(before), sum(after) / len(after)
