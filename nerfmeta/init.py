"""Saved initialisations: category models and meta-learned initialisations.

An initialisation folder holds::

    model.safetensors   the model's state dict (parameters and buffers), with its SHA-256 in init.json
    init.json           {"format", "kind": "category" | "meta", "backbone", "model_config",
                         "structure", "sha256", "meta": {...training facts: category, scenes, seed,
                         steps, final PSNR, algorithm...}}

``nerfmeta fit SCENE --init category:DIR`` / ``--init meta:DIR`` starts from one. Loading checks
the hash and that the backbone and shapes match the fit, and refuses anything else with one line.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from nerfmeta import validate
from nerfmeta.errors import ConfigError, message_line
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fields.registry import BACKBONES, build_model, config_from_dict
from nerfmeta.io import check_sha256, load_tensors, read_json_index, save_tensors, sha256_file, to_jsonable, write_json

INIT_FORMAT = "nerfmeta-init-1"
KINDS = ("category", "meta")
WEIGHTS = "model.safetensors"
INDEX = "init.json"


@dataclass(frozen=True)
class SavedInit:
    """A loaded initialisation (tensors on CPU)."""

    path: Path
    kind: str
    backbone: str
    model_config: Any
    structure: dict[str, Any]
    state: dict[str, torch.Tensor]
    meta: dict[str, Any]

    def build(self, *, device: torch.device | str = "cpu", seed: int = 0) -> RadianceModel:
        """A model of the saved backbone, shaped like the saved one, holding its weights."""
        placeholder = torch.tensor([[-1.0] * 3, [1.0] * 3])  # the real bounds are buffers in ``state``
        model = build_model(self.backbone, self.model_config, placeholder, seed=seed, device=device)
        try:
            model.load_structure(self.structure)
        except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as err:
            raise ConfigError(f"{self.path / INDEX}: structure does not describe a {self.backbone} model ({err!r})") from None
        try:
            missing, unexpected = model.load_state_dict({k: v.to(device) for k, v in self.state.items()}, strict=False)
        except RuntimeError as err:  # a tensor of another shape
            raise ConfigError(f"{self.path}: weights do not fit a {self.backbone} model ({message_line(err, last=True)})") from None
        if missing or unexpected:
            raise ConfigError(f"{self.path}: weights do not fit a {self.backbone} model (missing {missing[:3]}, unexpected {unexpected[:3]})")
        return model


def save_init(folder: str | os.PathLike, model: RadianceModel, kind: str, meta: dict[str, Any]) -> Path:
    """Write ``model`` as an initialisation of ``kind`` into ``folder`` (atomically, hash recorded)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    folder = Path(folder)
    save_tensors(folder / WEIGHTS, model.state_dict())
    doc = {
        "format": INIT_FORMAT,
        "kind": kind,
        "backbone": model.backbone,
        "model_config": to_jsonable(model.config),
        "structure": model.structure(),
        "sha256": sha256_file(folder / WEIGHTS),
        "meta": to_jsonable(meta),
    }
    write_json(folder / INDEX, doc)
    return folder


def load_init(folder: str | os.PathLike, *, expect_kind: str | None = None) -> SavedInit:
    """Read an initialisation folder; one-line :class:`ConfigError` for anything missing or wrong."""
    folder = Path(folder)
    index, weights = folder / INDEX, folder / WEIGHTS
    doc = read_json_index(index, INIT_FORMAT, what="a nerfmeta initialisation",
                          missing=f"an initialisation folder needs {INDEX} and {WEIGHTS}")
    if not weights.is_file():
        raise ConfigError(f"{weights}: missing; an initialisation folder needs {INDEX} and {WEIGHTS}")
    kind = validate.text(doc.get("kind"), where=f"{index}: kind", choices=KINDS)
    if expect_kind is not None and kind != expect_kind:
        raise ConfigError(f"{folder}: is a {kind!r} initialisation, not {expect_kind!r}")
    backbone = validate.text(doc.get("backbone"), where=f"{index}: backbone", choices=tuple(BACKBONES))
    values = validate.mapping(doc.get("model_config"), where=f"{index}: model_config")
    structure = validate.mapping(doc.get("structure", {}), where=f"{index}: structure")
    meta = validate.mapping(doc.get("meta", {}), where=f"{index}: meta")
    check_sha256(weights, doc.get("sha256"), index, "the file is corrupted or was replaced")
    try:
        config = config_from_dict(backbone, values)
    except (ConfigError, TypeError, ValueError) as err:
        raise ConfigError(f"{index}: model_config is not a valid {backbone} configuration ({err})") from None
    try:
        state = load_tensors(weights)
    except Exception as err:  # safetensors' own error types
        raise ConfigError(f"{weights}: not readable ({err})") from None
    return SavedInit(folder, kind, backbone, config, structure, state, meta)


FEED_FORWARD = ("carve", "occupancy")
"""Starts computed from the scene's own views, grid only (:mod:`nerfmeta.priors`): ``carve`` (the visual hull, no
weights) and ``occupancy:NET`` (the learned occupancy start, whose network file is ``NET``; the command line's bare
``occupancy`` names the model zoo's, :attr:`nerfmeta.zoo.Zoo.occupancy`)."""


def parse_init(spec: str) -> tuple[str, Path | None]:
    """``scratch`` | ``carve`` | ``occupancy:NET`` | ``category:DIR`` | ``meta:DIR`` -> (kind, folder or file)."""
    if spec in ("scratch", "carve"):
        return spec, None
    kind, sep, folder = spec.partition(":")
    if not sep or kind not in KINDS + ("occupancy",) or not folder:
        raise ConfigError(f"--init {spec!r}: use scratch, carve, occupancy[:NET.safetensors], category:DIR or meta:DIR")
    return kind, Path(folder)
