"""Divergence guard: roll a training loop back to its last good state when its loss goes bad.

Used by the fit loop (:func:`nerfmeta.fit.loop.fit`) and the meta-training loop
(:func:`pretrain.meta_run.meta_train`); one rule for both.

Rule. A step is *bad* when any of these holds:

- its loss is NaN or infinite (one ``isfinite`` of the scalar loss per step);
- its gradients are not finite: one fused check per step, the sum of the per-tensor norms from
  ``torch._foreach_norm``, which is NaN or infinite as soon as one gradient value is (a norm that
  overflows float32 counts too). That reads every gradient once, a few percent of a step for a
  large voxel grid, so models with more than ``grad_check_max_values`` trainable values have
  their *parameters* checked instead, and only on the steps that refresh the snapshot (so a
  snapshot never holds a NaN); a bad gradient in between shows up as a bad loss once the
  affected parameters are rendered, or at the next refresh;
- its loss *explodes*: it exceeds ``explode_factor`` times the median of the last ``window``
  good losses and is above ``explode_min_loss`` (checked once that many good losses have been
  seen; the history is emptied when the model's parameters change shape, since a new stage may
  legitimately start elsewhere). Without divergence the loss of a fit on the tiny scene never
  exceeded 5.3 times that median (batches of 64 to 4096 rays, grid and MLP, 400 steps) and a
  meta-batch's query loss 3.5 times, so the default factor 10 leaves a margin of two.

On a bad step the loop restores the snapshot (parameters, buffers and optimiser moments, copied
tensor by tensor into the live ones, so the optimiser keeps its references), multiplies its
persistent learning-rate scale by ``lr_factor``, records a :class:`GuardEvent` and tries the step
again (the fit loop with fresh rays; the meta loop with the same meta-batch). The snapshot is
refreshed every ``snapshot_every`` good steps, just before the update, so it only ever holds
parameters that passed the checks above; and it is retaken right after any change
of parameter shapes (grid growth, the coarse-to-fine switch), so a rollback never crosses one.
After ``max_retries`` bad steps with no snapshot refresh between them, i.e. without
``snapshot_every`` good steps in a row, the loop gives up with a :class:`~nerfmeta.errors.NerfmetaError`.
With the guard off a non-finite loss still stops the loop with that error (nothing else is
checked), so a NaN never reaches a checkpoint (the checkpoint writers also refuse one).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import statistics
from collections import deque
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import torch
from torch import nn

from nerfmeta.errors import ConfigError, NerfmetaError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GuardConfig:
    """Settings of the divergence guard (see the module docstring for the rule)."""

    enabled: bool = True
    """Roll back and lower the learning rate on a bad step (False: a non-finite loss stops the run with an error)."""
    explode_factor: float = 10.0
    """A loss above this many times the median of the recent good losses counts as an explosion (0: only non-finite values count)."""
    explode_min_loss: float = 1e-4
    """Losses below this never count as explosions (an MSE of 1e-4 is 40 dB: such a picture has not diverged, whatever the median)."""
    window: int = 20
    """Good losses the running median is taken over; the explosion check starts once the window is full."""
    snapshot_every: int = 50
    """Good steps between refreshes of the in-memory snapshot of parameters and optimiser state."""
    lr_factor: float = 0.5
    """Each guard event multiplies the persistent learning-rate scale by this."""
    max_retries: int = 5
    """Rollbacks allowed without a snapshot refresh between them; one more bad step ends the run with an error."""
    grad_check_max_values: int = 1_000_000
    """Check every step's gradients (one fused norm) while the trainable parameters hold at most this many values; larger models (or 0) have their parameters checked before each snapshot refresh instead (the norm costs ~0.1 ms for 0.24 M values, ~3 ms for an 88^3 grid's 7 M, a few % of its step)."""

    def __post_init__(self) -> None:
        checks = (
            ("explode_factor", self.explode_factor == 0 or self.explode_factor > 1.0, "use 0 (off) or a factor > 1, e.g. 10"),
            ("explode_min_loss", self.explode_min_loss >= 0.0, "use 0 or more, e.g. 1e-4"),
            ("window", isinstance(self.window, int) and self.window >= 1, "use 1 or more good losses"),
            ("snapshot_every", isinstance(self.snapshot_every, int) and self.snapshot_every >= 1, "use 1 or more steps"),
            ("lr_factor", 0.0 < self.lr_factor < 1.0, "use a factor in (0, 1), e.g. 0.5"),
            ("max_retries", isinstance(self.max_retries, int) and self.max_retries >= 1, "use 1 or more"),
            ("grad_check_max_values", isinstance(self.grad_check_max_values, int) and self.grad_check_max_values >= 0,
             "use 0 (never) or a number of parameter values"),
        )
        for name, ok, hint in checks:
            if not ok:
                raise ConfigError(f"guard config {name}={getattr(self, name)!r} is not allowed: {hint}")

    @staticmethod
    def coerce(value: "GuardConfig | dict[str, Any]") -> "GuardConfig":
        """A :class:`GuardConfig` from itself or from its JSON form (a dict, as saved in config.json)."""
        if isinstance(value, GuardConfig):
            return value
        if isinstance(value, dict):
            names = {f.name for f in dataclasses.fields(GuardConfig)}
            unknown = sorted(set(value) - names)
            if unknown:
                raise ConfigError(f"guard config has unknown keys {unknown}; known: {', '.join(sorted(names))}")
            return GuardConfig(**value)
        raise ConfigError(f"guard config {value!r}: expected a GuardConfig or a dict of its fields")


@dataclass(frozen=True)
class GuardEvent:
    """One rollback.

    Attributes:
        iter: the step (1-based, as in the metrics records) whose loss or gradients were bad.
        reason: what was bad, e.g. ``"nan loss"``, ``"non-finite gradient"``,
            ``"loss exploded: 0.31 > 10 x median 0.012"``.
        rolled_back_to: the step count (iterations done) whose parameters were restored.
        lr_scale: the persistent learning-rate scale after this event.
    """

    iter: int
    reason: str
    rolled_back_to: int
    lr_scale: float

    def as_json(self) -> dict[str, Any]:
        return {"iter": self.iter, "reason": self.reason, "rolled_back_to": self.rolled_back_to, "lr_scale": self.lr_scale}

    @staticmethod
    def from_json(data: dict[str, Any]) -> "GuardEvent":
        return GuardEvent(int(data["iter"]), str(data["reason"]), int(data["rolled_back_to"]), float(data["lr_scale"]))

    def message(self) -> str:
        """The text logged in the metrics record's ``event`` field."""
        return f"guard: {self.reason}, rolled back to iter {self.rolled_back_to}, lr x{self.lr_scale:g}"


# ----- the rule (pure functions) -------------------------------------------------------------------


def loss_verdict(loss: float, recent: Sequence[float], explode_factor: float, window: int,
                 min_loss: float = 0.0) -> str | None:
    """Why a step with this loss is bad, or None when it is good.

    Args:
        loss: the step's scalar loss.
        recent: the most recent good losses, oldest first (only the last ``window`` are used).
        explode_factor: a loss above this many times their median is an explosion (0: off).
        window: how many good losses the median needs before explosions are checked.
        min_loss: losses up to this are never explosions.
    """
    if math.isnan(loss):
        return "nan loss"
    if math.isinf(loss):
        return "inf loss"
    if explode_factor > 0 and len(recent) >= window and loss > min_loss:
        median = statistics.median(list(recent)[-window:])
        if loss > explode_factor * median:
            return f"loss exploded: {loss:.4g} > {explode_factor:g} x median {median:.4g}"
    return None


def norm_sum(tensors: Sequence[torch.Tensor]) -> torch.Tensor | None:
    """() the sum of the 2-norms of ``tensors`` (one fused kernel, no sync), None for no tensors.

    It is NaN or infinite as soon as one value is; finite but enormous values (a norm beyond
    float range) also read as infinite, which is as much a divergence.
    """
    if not tensors:
        return None
    return torch.stack(torch._foreach_norm(list(tensors))).sum()


def grad_norm_sum(params: Iterable[torch.Tensor]) -> torch.Tensor | None:
    """:func:`norm_sum` of the gradients of ``params`` (those without one are skipped)."""
    return norm_sum([p.grad for p in params if p.grad is not None])


def grads_finite(params: Iterable[torch.Tensor]) -> bool:
    """True when every gradient of ``params`` is finite (parameters without a gradient are skipped)."""
    total = grad_norm_sum(params)
    return total is None or bool(torch.isfinite(total))


# ----- snapshots -------------------------------------------------------------------------------------


@dataclass
class Snapshot:
    """Copies of a model's trainable parameters and buffers and of its optimiser's per-parameter state.

    Attributes:
        step: the step count (iterations done) the copies belong to.
        tensors: name -> copy, for the trainable parameters and the floating/bool buffers.
        optimizer_state: parameter name -> {state key -> copy} (absent: no state yet).
    """

    step: int
    tensors: dict[str, torch.Tensor]
    optimizer_state: dict[str, dict[str, Any]]


def _live_tensors(model: nn.Module) -> dict[str, torch.Tensor]:
    out = {n: p for n, p in model.named_parameters() if p.requires_grad}
    out.update((n, b) for n, b in model.named_buffers() if b is not None)
    return out


def _copy(value: Any, into: Any = None) -> Any:
    """A copy of ``value`` (tensors cloned, or copied into ``into`` when it has the same layout)."""
    if not isinstance(value, torch.Tensor):
        return value
    if isinstance(into, torch.Tensor) and (into.shape, into.dtype, into.device) == (value.shape, value.dtype, value.device):
        return into.copy_(value)
    return value.detach().clone()


def take_snapshot(step: int, model: nn.Module, optimizer: torch.optim.Optimizer | None, *,
                  reuse: Snapshot | None = None) -> Snapshot:
    """Copy the trainable parameters, the buffers and the optimiser state (tensor copies, no module copy).

    With ``reuse`` (an older snapshot, given up), its tensors of the same shape are overwritten
    instead of allocating new ones: about 3x faster for a large grid.
    """
    old_tensors = reuse.tensors if reuse is not None else {}
    old_optim = reuse.optimizer_state if reuse is not None else {}
    tensors = {n: _copy(t, old_tensors.get(n)) for n, t in _live_tensors(model).items()}
    optim: dict[str, dict[str, Any]] = {}
    if optimizer is not None:
        for name, p in model.named_parameters():
            st = optimizer.state.get(p)
            if st:
                old = old_optim.get(name, {})
                optim[name] = {k: _copy(v, old.get(k)) for k, v in st.items()}
    return Snapshot(step, tensors, optim)


@torch.no_grad()
def restore_snapshot(snapshot: Snapshot, model: nn.Module, optimizer: torch.optim.Optimizer | None) -> None:
    """Copy ``snapshot`` back into the live tensors of ``model`` and ``optimizer`` (the snapshot stays intact).

    Raises:
        RuntimeError: the model's tensors no longer match the snapshot (it was not retaken after
            a change of parameter shapes: a bug in the calling loop).
    """
    live = _live_tensors(model)
    if set(live) != set(snapshot.tensors):
        raise RuntimeError(f"snapshot of step {snapshot.step} does not match the model's tensors "
                           f"({sorted(set(live) ^ set(snapshot.tensors))[:3]}); retake it after shape changes")
    for name, value in snapshot.tensors.items():
        if live[name].shape != value.shape:
            raise RuntimeError(f"snapshot of step {snapshot.step}: {name} has shape {tuple(value.shape)}, "
                               f"the model {tuple(live[name].shape)}; retake it after shape changes")
        live[name].copy_(value)
    if optimizer is not None:
        for name, p in model.named_parameters():
            if name in snapshot.optimizer_state:
                optimizer.state[p] = {k: _copy(v) for k, v in snapshot.optimizer_state[name].items()}
            else:
                optimizer.state.pop(p, None)
        optimizer.zero_grad(set_to_none=True)


# ----- the guard -----------------------------------------------------------------------------------


class DivergenceGuard:
    """The guard's running state for one loop: recent good losses, the snapshot, the failure count.

    The persistent part (learning-rate scale and events) lives in the loop's own state and is
    passed in and read back (``lr_scale``, ``events``), so checkpoints keep it.
    """

    def __init__(self, config: GuardConfig, *, lr_scale: float = 1.0, events: Sequence[GuardEvent] = (), what: str = "fit"):
        self.config = config
        self.lr_scale = float(lr_scale)
        self.events: list[GuardEvent] = list(events)
        self.what = what
        self.recent: deque[float] = deque(maxlen=config.window)
        self.snapshot: Snapshot | None = None
        self.good_since_snapshot = 0
        self.failures = 0

    def retake(self, step: int, model: nn.Module, optimizer: torch.optim.Optimizer | None, *, shape_changed: bool = False) -> None:
        """Take a fresh snapshot now (at the start, and after any change of parameter shapes)."""
        if not self.config.enabled:
            return
        self.snapshot = take_snapshot(step, model, optimizer, reuse=self.snapshot)
        self.good_since_snapshot = 0
        if shape_changed:
            self.recent.clear()

    def check_loss(self, loss: float, iter_: int, hint: str) -> str | None:
        """Why the loss of step ``iter_`` (1-based) is bad, or None.

        Raises:
            NerfmetaError: the guard is off and the loss is not finite (``hint`` says what to do).
        """
        if not self.config.enabled:
            if not math.isfinite(loss):
                raise NerfmetaError(f"{self.what} step {iter_}: the loss is {loss}; the run diverged and nothing was saved "
                                    f"from this step. {hint}, or turn the divergence guard on (guard.enabled=True)")
            return None
        return loss_verdict(loss, self.recent, self.config.explode_factor, self.config.window, self.config.explode_min_loss)

    def _refreshes_next(self) -> bool:
        """Whether the next good step refreshes the snapshot."""
        return self.snapshot is None or self.good_since_snapshot + 1 >= self.config.snapshot_every

    def check_step(self, loss: torch.Tensor, params: Sequence[torch.Tensor], iter_: int, hint: str) -> tuple[float, str | None]:
        """The loss value of step ``iter_`` (after its backward, before its update) and why the step is bad, or None.

        Reads the loss and the fused norm of the gradients (of the parameters instead, and only on
        steps that will refresh the snapshot, above ``grad_check_max_values``) in one transfer: one
        sync per step on a GPU. With the guard off only the loss is read and checked (see :meth:`check_loss`).
        """
        total, what = None, ""
        if self.config.enabled and sum(p.numel() for p in params) <= self.config.grad_check_max_values:
            total, what = grad_norm_sum(params), "non-finite gradient"
        elif self.config.enabled and self._refreshes_next():
            total, what = norm_sum(params), "non-finite parameters"
        if total is None:
            value = float(loss.detach())
            return value, self.check_loss(value, iter_, hint)
        value, norm = torch.stack([loss.detach().to(total.dtype), total]).tolist()
        bad = self.check_loss(value, iter_, hint)
        if bad is None and not math.isfinite(norm):
            bad = what
        return value, bad

    def accept(self, loss: float, step: int, model: nn.Module, optimizer: torch.optim.Optimizer | None) -> None:
        """Record a good step (call before its update): remember its loss, refresh the snapshot when due."""
        if not self.config.enabled:
            return
        due = self._refreshes_next()
        self.recent.append(loss)
        self.good_since_snapshot += 1
        if due:
            self.snapshot = take_snapshot(step, model, optimizer, reuse=self.snapshot)
            self.good_since_snapshot = 0
            self.failures = 0

    def rollback(self, iter_: int, reason: str, model: nn.Module, optimizer: torch.optim.Optimizer | None, hint: str) -> GuardEvent:
        """Restore the snapshot, lower the learning-rate scale and record the event.

        Raises:
            NerfmetaError: ``max_retries`` bad steps in a row without a snapshot refresh.
        """
        assert self.snapshot is not None, "retake() must be called before the first step"
        self.failures += 1
        if self.failures > self.config.max_retries:
            raise NerfmetaError(f"{self.what} step {iter_}: {reason}, after {self.config.max_retries} rollbacks to step "
                                f"{self.snapshot.step} in a row (learning rates already x{self.lr_scale:g}); the run keeps "
                                f"diverging: {hint}")
        restore_snapshot(self.snapshot, model, optimizer)
        self.lr_scale *= self.config.lr_factor
        self.good_since_snapshot = 0
        event = GuardEvent(iter_, reason, self.snapshot.step, self.lr_scale)
        self.events.append(event)
        log.warning("%s step %d: %s", self.what, iter_, event.message())
        return event
