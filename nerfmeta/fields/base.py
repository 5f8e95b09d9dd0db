"""The interface every backbone implements: a field, an estimator, the shared renderer, named losses.

A :class:`Field` maps points (and view directions) to density and colour
(:meth:`Field.get_density`, :meth:`Field.get_outputs`, as nerfstudio's fields) and lists its
parameters as ordered *layers* (transfer freezes "the first k layers" of any backbone) and
*parameter groups* that declare their own optimiser hints (:class:`ParamGroup`). It knows nothing
of rays, samplers or optimisers.

A backbone is a :class:`RadianceModel`: a field wired to an estimator (where to sample, see
:mod:`nerfmeta.render.estimators`) and to the one compositor
(:func:`~nerfmeta.render.volume.render_packed`). Its ``forward`` renders a
:class:`~nerfmeta.data.RayBatch` (so ``torch.func.functional_call`` can render with any set of
parameters, which meta-learning needs) and, given the rays' target colours, returns the model's
named loss terms (:meth:`RadianceModel.loss_terms`), which the fit loop and meta-learning sum
alike (:func:`total_loss`). What a backbone can do in meta-learning is declared in its
:class:`MetaHints`, never recognised by name. The fit loop, transfer, meta-learning and the
reports only use this interface.

The parameter names are those of the field's modules (the field *is* the model's root module),
so checkpoints and the model zoo keep loading.
"""

from __future__ import annotations

import abc
import contextlib
from dataclasses import dataclass, field
from typing import Any, Callable, ContextManager

import torch
from torch import nn

from nerfmeta.data.scene import RayBatch
from nerfmeta.render.contraction import fused_contraction_available
from nerfmeta.render.estimators import PackedSamples, fused_march_available
from nerfmeta.render.volume import Composite, fused_compositing, render_packed


@dataclass
class RenderOutput:
    """What rendering a ray batch returns.

    Attributes:
        rgb: (n_rays, 3) composited colour.
        acc: (n_rays,) accumulated opacity, ``1 - T_final``.
        depth: (n_rays,) expected termination distance (``far`` for rays that pass through).
        samples_evaluated: number of (point) samples whose density was actually evaluated,
            after empty-space skipping; divide by ``n_rays`` for samples per ray.
        extras: further named tensors for losses or debugging (e.g. a coarse pass's ``rgb``).
        losses: the model's named loss terms (:meth:`RadianceModel.loss_terms`), when the
            render was given the target colours; empty otherwise.
    """

    rgb: torch.Tensor
    acc: torch.Tensor
    depth: torch.Tensor
    samples_evaluated: int
    extras: dict[str, torch.Tensor] = field(default_factory=dict)
    losses: dict[str, torch.Tensor] = field(default_factory=dict)


def total_loss(losses: dict[str, torch.Tensor]) -> torch.Tensor:
    """The loss to minimise: the sum of a model's named terms (each already weighted by the model)."""
    if not losses:
        raise ValueError("no loss terms: render with target=... to get the model's losses")
    terms = list(losses.values())
    total = terms[0]
    for term in terms[1:]:
        total = total + term
    return total


def photometric_mse(rgb: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """() mean squared error of colours (n_rays, 3) against targets (n_rays, 3): the photometric loss."""
    return torch.mean((rgb - target) ** 2)


@dataclass(frozen=True)
class Layer:
    """One named layer: the parameters (by their ``named_parameters`` name) that belong to it."""

    name: str
    param_names: tuple[str, ...]


@dataclass(frozen=True)
class ParamGroup:
    """A group of parameters that share an optimiser learning rate, with the optimiser hints it needs.

    Attributes:
        name: the group's name (logs, ``--inner-lr-group``).
        param_names: its parameters, by their ``named_parameters`` name.
        lr: learning rate.
        adam_eps: Adam's epsilon this group needs, or None for the fit's ``adam_eps``.
    """

    name: str
    param_names: tuple[str, ...]
    lr: float
    adam_eps: float | None = None


@dataclass(frozen=True)
class MetaHints:
    """How a backbone can be meta-learned, declared by the backbone (read by ``pretrain/meta.py``)."""

    algos: tuple[str, ...] = ("maml", "fomaml", "reptile")
    """Meta-learning algorithms it supports (``maml`` needs second-order gradients through its forward)."""
    why_not: str = ""
    """One line for the user when an algorithm outside ``algos`` is asked for."""
    model_defaults: dict[str, Any] = field(default_factory=dict)
    """Config overrides for meta-learning (sized so a meta-step takes seconds on a 2-core CPU)."""
    fixed: dict[str, Any] = field(default_factory=dict)
    """Config values forced for meta-learning so the parameter set never changes (an override contradicting them is an error)."""
    fixed_reason: str = "its parameter set must not change during meta-learning"
    """Why ``fixed`` is forced, for the error an override contradicting it gets."""
    inner_lr: float = 30.0
    """Default inner SGD rate of every parameter."""
    inner_group_lr: dict[str, float] = field(default_factory=dict)
    """Default inner SGD rates of named parameter groups (quoted for 512 support rays, scaled with their number)."""


@dataclass(frozen=True)
class Decision:
    """A per-scene choice made from the data during a fit (recorded in ``summary.json``).

    Attributes:
        name: what was decided, e.g. ``"view_dependent"``.
        value: the choice (JSON-able: a bool, a number, a string).
        reason: one line for the logs and ``metrics.jsonl``.
        evidence: the figures the choice was made from (JSON-able).
    """

    name: str
    value: Any
    reason: str
    evidence: dict[str, Any] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        return {"value": self.value, "reason": self.reason, "evidence": dict(self.evidence)}


@dataclass(frozen=True)
class StepEvent:
    """What a model did at the start of an iteration (see :meth:`RadianceModel.begin_step`).

    Attributes:
        params_changed: parameters were added, removed or resized: the optimiser must be rebuilt.
        message: a short human-readable note for the logs (``""`` when nothing happened).
        decisions: per-scene choices the model made in this step (e.g. the box of a new stage).
    """

    params_changed: bool = False
    message: str = ""
    decisions: tuple[Decision, ...] = ()


class Field(nn.Module, abc.ABC):
    """Points (and view directions) to density and colour; parameters as layers and groups.

    Densities are per world unit of length, so the optical depth of a sample is ``sigma * delta``
    with ``delta`` in world units, whatever the field's own units.
    """

    @abc.abstractmethod
    def get_density(self, points: torch.Tensor) -> tuple[torch.Tensor, Any]:
        """Density at world points.

        Args:
            points: (N, 3) world positions.

        Returns:
            sigma (N,) non-negative density per world unit, and an *embedding*: whatever
            :meth:`get_outputs` needs to colour these points without recomputing (nerfstudio's
            ``density_embedding``; e.g. an MLP's trunk features, a grid's corner weights).
        """

    @abc.abstractmethod
    def get_outputs(self, embedding: Any, sel: torch.Tensor | None, directions: torch.Tensor, ray_idx: torch.Tensor) -> torch.Tensor:
        """Colour of some of the points given to :meth:`get_density`.

        Args:
            embedding: what :meth:`get_density` returned for the N points.
            sel: (K,) indices of the points to colour, or None for all N.
            directions: (n_rays, 3) unit view direction of each ray.
            ray_idx: (K,) the ray of each point to colour (its direction is ``directions[ray_idx]``).

        Returns:
            (K, 3) RGB in [0, 1].
        """

    @abc.abstractmethod
    def layers(self) -> list[Layer]:
        """Parameter layers ordered from input to output (every trainable parameter in exactly one)."""

    @abc.abstractmethod
    def param_groups(self) -> list[ParamGroup]:
        """Learning-rate groups (every trainable parameter in exactly one), with their optimiser hints."""


@dataclass(frozen=True)
class SamplingPlan:
    """How a model renders right now: where to sample and how much colour decoding to skip.

    Attributes:
        samples: the packed samples of the ray batch.
        color_thres: samples whose compositing weight is not above this get no colour (0: all do).
    """

    samples: PackedSamples
    color_thres: float = 0.0


class RadianceModel(Field):
    """Base class of all backbones: a field wired to an estimator and the shared renderer.

    Subclasses set ``self.config`` (a frozen dataclass saved as JSON with every run), implement
    the :class:`Field` methods and :meth:`sample` (the estimator: where along each ray to
    evaluate the field); :meth:`forward` then evaluates and composites with
    :func:`~nerfmeta.render.volume.render_packed`, the same for every backbone. Models whose
    structure changes during training (stages, grid growth, occupancy grids) override
    :meth:`begin_step`, :meth:`structure` and :meth:`load_structure` so checkpoints can rebuild
    them exactly.
    """

    backbone: str = "base"
    meta_hints: MetaHints = MetaHints()
    """What meta-learning may do with this backbone (see :class:`MetaHints`)."""

    @classmethod
    def settles_at(cls, config: Any) -> int:
        """The step after which the parameter set stops changing (0: it never changes); a pretrained
        model must train past it so transfer fits start from the final structure."""
        return 0

    @classmethod
    def warm_up(cls) -> None:
        """Load or compile, once per process, what this backbone's steps use (e.g. compiled kernels), so that
        one-off cost lands before a fit's clock starts, as imports do, and not in the first step of whichever fit
        runs first (default: the fused kernels of the compositor and of the contracted space, which every backbone
        renders with: :func:`~nerfmeta.render.volume.fused_compositing`,
        :func:`~nerfmeta.render.contraction.fused_contraction_available`,
        :func:`~nerfmeta.render.estimators.fused_march_available`)."""
        fused_compositing()
        fused_contraction_available()
        fused_march_available()

    def recipe_notes(self) -> dict[str, Any]:
        """Config values worth quoting in a pretrained model's recipe line (default: none)."""
        return {}

    def render_session(self) -> ContextManager[None]:
        """A block in which the model renders test-time chunks of one or more whole views and is not trained,
        so it may keep derived tensors across chunks (default: nothing kept)."""
        return contextlib.nullcontext()

    def sample(self, rays: RayBatch, *, train: bool, generator: torch.Generator | None) -> SamplingPlan:
        """The estimator: packed samples of ``rays`` (jittered with ``generator`` when ``train``)."""
        raise NotImplementedError(f"{type(self).__name__} must implement sample() or override forward()")

    def forward(
        self,
        rays: RayBatch,
        *,
        background: torch.Tensor,
        train: bool = False,
        generator: torch.Generator | None = None,
        target: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Render ``rays``; ``background`` is (3,) RGB; ``train`` enables jitter and training-only work.

        With ``target`` (n_rays, 3), the output's ``losses`` holds :meth:`loss_terms` (computed
        here, so a ``functional_call`` or a meta-learning clone uses its own parameters).
        """
        out = self.render(rays, background=background, train=train, generator=generator)
        if target is not None:
            out.losses = self.loss_terms(out, target)
        return out

    def render(
        self,
        rays: RayBatch,
        *,
        background: torch.Tensor,
        train: bool = False,
        generator: torch.Generator | None = None,
        view_dirs: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Estimator, field and compositor; ``view_dirs`` (n_rays, 3) replaces the rays' directions for colour."""
        return self.render_plan(rays, self.sample(rays, train=train, generator=generator), background=background,
                                train=train, view_dirs=view_dirs)

    def render_plan(
        self,
        rays: RayBatch,
        plan: SamplingPlan,
        *,
        background: torch.Tensor,
        train: bool = False,
        view_dirs: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Field and compositor over the samples of ``plan`` (see :meth:`render`)."""
        samples = plan.samples
        sigma, embedding = self.get_density(samples.points(rays.origins, rays.directions))
        directions = rays.directions if view_dirs is None else view_dirs
        comp = render_packed(sigma * samples.delta, samples.t, samples.ray_idx, samples.far, background,
                             lambda sel, ray_idx: self.get_outputs(embedding, sel, directions, ray_idx),
                             color_thres=plan.color_thres)
        extras = self.render_extras(rays, samples, comp) if train else {}
        return RenderOutput(rgb=comp.rgb, acc=comp.acc, depth=comp.depth, samples_evaluated=len(samples), extras=extras)

    def render_extras(self, rays: RayBatch, samples: PackedSamples, comp: Composite) -> dict[str, torch.Tensor]:
        """Training renders only: per-ray tensors a loss term needs beyond colour (``RenderOutput.extras``).

        Default: none. Called by :meth:`render` with the rays, their packed samples and the composite
        (whose ``weights`` still carry the gradient).
        """
        return {}

    def loss_terms(self, out: RenderOutput, target: torch.Tensor) -> dict[str, torch.Tensor]:
        """Named, weighted loss terms of a render against ``target`` (n_rays, 3): ``mse`` (photometric)
        plus whatever the backbone adds (e.g. ``tv``); the loss is their sum (:func:`total_loss`)."""
        return {"mse": photometric_mse(out.rgb, target)}

    def begin_step(self, step: int, progress: float | None) -> StepEvent:
        """Called before iteration ``step`` (0-based). Default: nothing changes.

        ``progress`` is how far the fit is towards its end, in [0, 1] (by iterations or by the time budget,
        :func:`nerfmeta.fit.loop.fit_progress`), for schedules set in fractions of a fit; None where the model
        is stepped outside a fit with a planned end.
        """
        return StepEvent()

    def stage_ending(self, step: int) -> str | None:
        """The name of the stage that ends before iteration ``step``, else None (the default: one stage).

        A model with stages returns its current stage's name when ``begin_step(step)`` would start
        the next one. The fit loop then evaluates the model when it has a target PSNR (a stage
        that already meets it ends the fit, so the next stage is never built), and otherwise calls
        :meth:`decide` before ``begin_step``.
        """
        return None

    def decide(self, draw_rays: Callable[[int], RayBatch], *, background: torch.Tensor) -> list[Decision]:
        """Make the choices due at the end of the current stage from training data; default: none.

        Args:
            draw_rays: ``draw_rays(n)`` returns ``n`` random training rays with their target colours
                (seeded, independent of the fit's own ray stream).
            background: (3,) RGB the scene is composited on.

        Returns:
            The decisions made (the model has applied them to itself).
        """
        return []

    def structure(self) -> dict[str, Any]:
        """JSON-able description of the current structure (shapes, stage, box) for checkpoints."""
        return {}

    def load_structure(self, structure: dict[str, Any]) -> None:
        """Reshape this model to ``structure`` so a state dict saved with it loads."""

    def load_state(self, structure: dict[str, Any], tensors: dict[str, torch.Tensor]) -> None:
        """Reshape this model to ``structure`` (:meth:`load_structure`) and load ``tensors`` (a state dict saved with
        it, moved to the model's device): a checkpoint's model, or the fit's best held-out parameters.

        Raises:
            ValueError: a tensor the model has is missing from ``tensors``, or one there is not the model's.
        """
        self.load_structure(structure)
        device = next(iter(self.state_dict().values())).device
        missing, unexpected = self.load_state_dict({k: v.to(device) for k, v in tensors.items()}, strict=False)
        if missing or unexpected:
            raise ValueError(f"missing {missing}, unexpected {unexpected}")

    def freeze_first(self, k: int) -> list[str]:
        """Freeze the parameters of the first ``k`` layers (``requires_grad=False``); return their names.

        Frozen parameters get no gradient at all, so autograd computes nothing through them
        beyond what later layers need.
        """
        layers = self.layers()
        if not 0 <= k <= len(layers):
            from nerfmeta.errors import ConfigError

            raise ConfigError(
                f"--freeze {k}: {self.backbone} has {len(layers)} layers "
                f"({', '.join(layer.name for layer in layers)}); choose 0..{len(layers)}"
            )
        params = dict(self.named_parameters())
        frozen = [name for layer in layers[:k] for name in layer.param_names]
        for name in frozen:
            params[name].requires_grad_(False)
        return frozen


def check_partition(model: RadianceModel) -> None:
    """Raise if ``layers()`` or ``param_groups()`` do not each cover every parameter exactly once."""
    names = [n for n, _ in model.named_parameters()]
    for what, lists in (("layers", [layer.param_names for layer in model.layers()]),
                        ("param_groups", [g.param_names for g in model.param_groups()])):
        flat = [n for names_ in lists for n in names_]
        if sorted(flat) != sorted(names):
            raise AssertionError(f"{type(model).__name__}.{what} does not partition the parameters: {flat} vs {names}")


def module_device(module: nn.Module) -> torch.device:
    """The device of ``module``'s first parameter (or buffer); the CPU for a module that has neither."""
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return torch.device("cpu")
