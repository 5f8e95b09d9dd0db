"""Backbone registry: name -> (config class, model class, default config)."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.fields.dense_grid import DenseGrid, DenseGridConfig
from nerfmeta.fields.nerf_mlp import NERF_SMALL, NerfMLP, NerfMLPConfig
from nerfmeta.fields.sdf import SdfConfig, SdfField
from nerfmeta.fields.voxel_grid import VoxelGrid, VoxelGridConfig

BACKBONES: dict[str, tuple[type, type[RadianceModel], Any]] = {
    "grid": (VoxelGridConfig, VoxelGrid, VoxelGridConfig()),
    "nerf": (NerfMLPConfig, NerfMLP, NERF_SMALL),
    "dense": (DenseGridConfig, DenseGrid, DenseGridConfig()),  # the example of docs/new_field.md
    "sdf": (SdfConfig, SdfField, SdfConfig()),  # NeuS-style surfaces (issue 19)
}


def default_config(backbone: str) -> Any:
    _check(backbone)
    return BACKBONES[backbone][2]


def config_from_dict(backbone: str, values: dict[str, Any]) -> Any:
    """Rebuild a backbone config from its JSON form (unknown keys are an error)."""
    _check(backbone)
    cls = BACKBONES[backbone][0]
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"{backbone} config has unknown keys {unknown}; known: {sorted(names)}")
    fixed = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    return cls(**fixed)


def model_class(backbone: str) -> type[RadianceModel]:
    """The model class of ``backbone`` (its capabilities, e.g. ``meta_hints``, are class attributes)."""
    _check(backbone)
    return BACKBONES[backbone][1]


def build_model(backbone: str, config: Any, bounds: torch.Tensor, *, seed: int, device: torch.device | str = "cpu") -> RadianceModel:
    """Build a backbone with its initial weights drawn from ``seed`` (global RNG state untouched)."""
    _check(backbone)
    cls = BACKBONES[backbone][1]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = cls(config, bounds.float())
    return model.to(device)


def _check(backbone: str) -> None:
    if backbone not in BACKBONES:
        raise ConfigError(f"unknown backbone {backbone!r}; choose one of {', '.join(BACKBONES)}")
