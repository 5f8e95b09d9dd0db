"""Checkpoints: one safetensors file holding the model, the optimiser and the RNG, with the
fit state and model structure as JSON in its metadata, written atomically (temp file + rename),
so a kill at any moment leaves either the previous checkpoint or the new one, never half of one.
A checkpoint is only written from finite parameters: a NaN never reaches disk. The divergence
guard's learning-rate factor and events are kept, so a resumed fit continues with the lowered rates.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open

from nerfmeta.errors import NerfmetaError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fit.guard import GuardEvent
from nerfmeta.fit.loop import FitState
from nerfmeta.io import save_tensors

CHECKPOINT_NAME = "checkpoint.safetensors"
_FORMAT = "nerfmeta-checkpoint-1"


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint: model structure and tensors, and the fit state to resume."""

    backbone: str
    structure: dict[str, Any]
    model_state: dict[str, torch.Tensor]
    state: FitState


def save_checkpoint(path: str | os.PathLike, model: RadianceModel, state: FitState) -> None:
    """Write model + optimiser + RNG + fit state to ``path`` atomically."""
    tensors: dict[str, torch.Tensor] = {}
    for name, value in model.state_dict().items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise FloatingPointError(f"refusing to checkpoint non-finite values in {name}")
        tensors[f"model.{name}"] = value
    optim_meta: dict[str, Any] = {}
    if state.optimizer_state is not None:
        groups = []
        for g in state.optimizer_state["param_groups"]:
            groups.append({k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()})
        optim_meta["param_groups"] = groups
        optim_meta["state_keys"] = {}
        for idx, st in state.optimizer_state["state"].items():
            optim_meta["state_keys"][str(idx)] = sorted(st)
            for key, value in st.items():
                tensors[f"optim.{idx}.{key}"] = torch.as_tensor(value)
    if state.rng_state is not None:
        tensors["rng"] = state.rng_state
    meta = {
        "format": _FORMAT,
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
    }
    save_tensors(path, tensors, metadata={"nerfmeta": json.dumps(meta)})


def load_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` (raises a one-line error if unreadable)."""
    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = json.loads((f.metadata() or {}).get("nerfmeta", "{}"))
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as err:  # OSError, JSON errors, or safetensors' own SafetensorError
        raise NerfmetaError(f"{path}: not a readable checkpoint ({type(err).__name__}: {err})") from None
    if meta.get("format") != _FORMAT:
        raise NerfmetaError(f"{path}: not a nerfmeta checkpoint (format {meta.get('format')!r})")
    optimizer_state = None
    om = meta.get("optimizer") or {}
    if om:
        state_dict: dict[int, dict[str, torch.Tensor]] = {}
        for idx, keys in om["state_keys"].items():
            state_dict[int(idx)] = {k: tensors[f"optim.{idx}.{k}"] for k in keys}
        optimizer_state = {"state": state_dict, "param_groups": om["param_groups"]}
    state = FitState(
        step=int(meta["step"]),
        time_s=float(meta["time_s"]),
        eval_time_s=float(meta["eval_time_s"]),
        rng_state=tensors.get("rng"),
        optimizer_state=optimizer_state,
        last_test_psnr=meta.get("last_test_psnr"),
        decisions=meta.get("decisions", {}),
        lr_guard_scale=float(meta.get("lr_guard_scale", 1.0)),
        guard_events=[GuardEvent.from_json(e) for e in meta.get("guard_events", [])],
    )
    model_state = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    return Checkpoint(meta["backbone"], meta["structure"], model_state, state)


def restore_model(model: RadianceModel, checkpoint: Checkpoint) -> None:
    """Reshape ``model`` to the checkpoint's structure and load its tensors."""
    if model.backbone != checkpoint.backbone:
        raise NerfmetaError(f"checkpoint is for backbone {checkpoint.backbone!r}, not {model.backbone!r}")
    model.load_structure(checkpoint.structure)
    device = next(iter(model.state_dict().values())).device
    missing, unexpected = model.load_state_dict({k: v.to(device) for k, v in checkpoint.model_state.items()}, strict=False)
    if missing or unexpected:
        raise NerfmetaError(f"checkpoint does not match the model: missing {missing}, unexpected {unexpected}")
