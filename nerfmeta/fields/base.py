"""The interface every backbone implements.

A backbone is a :class:`RadianceModel`: an ``nn.Module`` whose ``forward`` renders a
:class:`~nerfmeta.data.RayBatch` into colours (so ``torch.func.functional_call`` can render with
any set of parameters, which meta-learning needs), and which lists its parameters as an ordered
sequence of named *layers* from input to output, so transfer learning can freeze "the first k
layers" of any backbone. The fit loop, transfer, meta-learning and the reports only use this
interface.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, Callable

import torch
from torch import nn

from nerfmeta.data.scene import RayBatch


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
    """

    rgb: torch.Tensor
    acc: torch.Tensor
    depth: torch.Tensor
    samples_evaluated: int
    extras: dict[str, torch.Tensor] = field(default_factory=dict)


@dataclass(frozen=True)
class Layer:
    """One named layer: the parameters (by their ``named_parameters`` name) that belong to it."""

    name: str
    param_names: tuple[str, ...]


@dataclass(frozen=True)
class ParamGroup:
    """A group of parameters that share an optimiser learning rate."""

    name: str
    param_names: tuple[str, ...]
    lr: float


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


class RadianceModel(nn.Module, abc.ABC):
    """Base class of all backbones.

    Subclasses set ``self.config`` (a frozen dataclass saved as JSON with every run) and
    implement :meth:`forward`, :meth:`layers` and :meth:`param_groups`. Models whose structure
    changes during training (stages, grid growth, occupancy caches) override
    :meth:`begin_step`, :meth:`structure` and :meth:`load_structure` so checkpoints can rebuild
    them exactly.
    """

    backbone: str = "base"

    @abc.abstractmethod
    def forward(
        self,
        rays: RayBatch,
        *,
        background: torch.Tensor,
        train: bool = False,
        generator: torch.Generator | None = None,
    ) -> RenderOutput:
        """Render ``rays``; ``background`` is (3,) RGB; ``train`` enables jitter and training-only work."""

    @abc.abstractmethod
    def layers(self) -> list[Layer]:
        """Parameter layers ordered from input to output (every trainable parameter in exactly one)."""

    @abc.abstractmethod
    def param_groups(self) -> list[ParamGroup]:
        """Learning-rate groups (every trainable parameter in exactly one)."""

    def begin_step(self, step: int, total_steps: int | None) -> StepEvent:
        """Called before iteration ``step`` (0-based). Default: nothing changes."""
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

    def regularization(self) -> torch.Tensor | None:
        """An extra loss term added to the photometric loss, or None."""
        return None

    def structure(self) -> dict[str, Any]:
        """JSON-able description of the current structure (shapes, stage, box) for checkpoints."""
        return {}

    def load_structure(self, structure: dict[str, Any]) -> None:
        """Reshape this model to ``structure`` so a state dict saved with it loads."""

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
