"""Fit checkpoints: the model, the optimiser and the RNG, with the fit state and model structure as
JSON, in the one checkpoint format of :mod:`nerfmeta.runfolder` (safetensors, written atomically,
so a kill at any moment leaves either the previous checkpoint or the new one, never half of one).
A checkpoint is only written from finite parameters: a NaN never reaches disk. The divergence
guard's learning-rate factor and events are kept, so a resumed fit continues with the lowered rates.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from nerfmeta.errors import NerfmetaError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fit.guard import GuardEvent
from nerfmeta.fit.holdout import BestSnapshot
from nerfmeta.fit.loop import FitState
from nerfmeta.runfolder import CHECKPOINT, load_checkpoint as load_checkpoint_file, optimizer_state, optimizer_tensors
from nerfmeta.runfolder import save_checkpoint as save_checkpoint_file

CHECKPOINT_NAME = CHECKPOINT
_KIND = "fit"
_BEST = "best."
"""Prefix of the best held-out snapshot's tensors (:class:`~nerfmeta.fit.holdout.BestSnapshot`) beside ``model.``."""


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint: model structure and tensors, and the fit state to resume."""

    backbone: str
    structure: dict[str, Any]
    model_state: dict[str, torch.Tensor]
    state: FitState


def save_checkpoint(path: str | os.PathLike, model: RadianceModel, state: FitState) -> None:
    """Write model + optimiser + RNG + fit state to ``path`` atomically (refuses non-finite values)."""
    tensors: dict[str, torch.Tensor] = {f"model.{name}": value for name, value in model.state_dict().items()}
    optim_meta: dict[str, Any] = {}
    if state.optimizer_state is not None:
        optim, optim_meta = optimizer_tensors(state.optimizer_state)
        tensors.update(optim)
    if state.rng_state is not None:
        tensors["rng"] = state.rng_state
    if state.best is not None:  # the parameters the fit will end with if nothing scores better on the held-out tiles
        tensors.update({f"{_BEST}{name}": value for name, value in state.best.tensors.items()})
    meta = {
        "backbone": model.backbone,
        "structure": model.structure(),
        "step": state.step,
        "time_s": state.time_s,
        "eval_time_s": state.eval_time_s,
        "last_test_psnr": state.last_test_psnr,
        "decisions": state.decisions,
        "lr_guard_scale": state.lr_guard_scale,
        "guard_events": [e.as_json() for e in state.guard_events],
        "optimizer": optim_meta,
        "best": None if state.best is None else state.best.meta(),
        "holdout_psnr": None if state.holdout_psnr == -math.inf else state.holdout_psnr,
    }
    save_checkpoint_file(path, _KIND, tensors, meta)


def load_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` (raises a one-line error if unreadable)."""
    ckpt = load_checkpoint_file(Path(path), _KIND)
    meta = ckpt.state
    state = FitState(
        step=int(meta["step"]),
        time_s=float(meta["time_s"]),
        eval_time_s=float(meta["eval_time_s"]),
        rng_state=ckpt.tensors.get("rng"),
        optimizer_state=optimizer_state(ckpt, meta.get("optimizer")),
        last_test_psnr=meta.get("last_test_psnr"),
        decisions=meta.get("decisions", {}),
        lr_guard_scale=float(meta.get("lr_guard_scale", 1.0)),
        guard_events=[GuardEvent.from_json(e) for e in meta.get("guard_events", [])],
        best=_best(meta.get("best"), ckpt.prefixed(_BEST)),
        holdout_psnr=-math.inf if meta.get("holdout_psnr") is None else float(meta["holdout_psnr"]),
    )
    return Checkpoint(meta["backbone"], meta["structure"], ckpt.prefixed("model."), state)


def _best(meta: dict[str, Any] | None, tensors: dict[str, torch.Tensor]) -> BestSnapshot | None:
    """The best held-out snapshot a checkpoint holds (None in checkpoints of fits without held-out tiles, or older)."""
    if not meta:
        return None
    return BestSnapshot(int(meta["step"]), float(meta["psnr"]), meta["structure"], tensors)


def restore_model(model: RadianceModel, checkpoint: Checkpoint) -> None:
    """Reshape ``model`` to the checkpoint's structure and load its tensors."""
    if model.backbone != checkpoint.backbone:
        raise NerfmetaError(f"checkpoint is for backbone {checkpoint.backbone!r}, not {model.backbone!r}")
    try:
        model.load_state(checkpoint.structure, checkpoint.model_state)
    except ValueError as err:
        raise NerfmetaError(f"checkpoint does not match the model: {err}") from None
