"""Memory a fit will need, estimated from its configs before anything is allocated.

A backbone config and a scene's size fix how many parameters a model holds and how many values
one batch of rays produces, so an impossible setting (``--set num_voxels=1e12``) can be refused
with the estimate before the first tensor is made, instead of dying in the allocator or being
killed mid-run. The estimate reads only config fields and the parameter layouts that
:class:`~nerfmeta.fields.voxel_grid.VoxelGrid` and :class:`~nerfmeta.fields.nerf_mlp.NerfMLP`
document; it is an upper-bound-minded guide (every sample of a ray kept, every parameter trained),
not an exact account.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import torch

from nerfmeta.errors import ConfigError
from nerfmeta.fields.encoding import encoding_dim
from nerfmeta.fields.grid_ops import voxel_layout

FLOAT_BYTES = 4
"""Parameters and activations are float32."""
TRAINING_COPIES = 4
"""A trained parameter is held four times: the value, its gradient and Adam's two moments."""
GRID_SAMPLE_BYTES = 160
"""Bytes a grid keeps per ray sample besides its channels: 8 int64 corner indices, 8 weights, t, delta, ray index, tau, weight."""
MLP_SAMPLE_COPIES = 3
"""Values an MLP keeps per sample and unit for the backward pass (pre-activation, activation, gradient)."""
RAY_BYTES = 9 * FLOAT_BYTES
"""Per training pixel: a ray's origin and direction and its target colour."""


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a fit needs at its peak, by part."""

    parameters: int
    """Parameters of the largest stage of the model (one copy)."""
    optimizer: int
    """Gradients and Adam's moments of those parameters."""
    batch: int
    """Values one training batch of rays produces and keeps for the backward pass."""
    rays: int
    """The training rays and target colours the sampler holds."""

    @property
    def total(self) -> int:
        return self.parameters + self.optimizer + self.batch + self.rays

    def describe(self) -> str:
        """One line: the total and its parts, e.g. ``about 3.1 GiB (parameters 800 MiB, ...)``."""
        return (f"about {format_bytes(self.total)} (parameters {format_bytes(self.parameters)}, gradients and Adam state "
                f"{format_bytes(self.optimizer)}, one batch {format_bytes(self.batch)}, rays {format_bytes(self.rays)})")


def format_bytes(n: float) -> str:
    """``1536`` -> ``1.5 KiB``; binary units up to EiB."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} EiB"


def mlp_parameters(dims: list[int]) -> int:
    """Weights and biases of a chain of linear layers with widths ``dims`` (input first)."""
    return sum(a * b + b for a, b in zip(dims[:-1], dims[1:]))


def grid_parameter_count(config: Any, bounds: torch.Tensor) -> int:
    """Parameters of a voxel grid's largest stage, from a resolved ``VoxelGridConfig`` and the scene box (2, 3).

    Coarse: density (1) and RGB (3) channels on ``coarse_num_voxels``. Fine, fully grown: density
    (1) and features (3 + ``feature_dim`` unless ``view_dependent`` is False) on ``num_voxels``,
    plus the colour MLP. The fine box is at most the scene box, so its layout is taken there.
    """
    fine_size, _ = voxel_layout(bounds, config.num_voxels)
    view = config.view_dependent is not False
    channels = 1 + 3 + (config.feature_dim if view else 0)
    fine = channels * math.prod(fine_size)
    if view:
        fine += mlp_parameters([config.feature_dim + encoding_dim(3, config.dir_freqs)]
                               + [config.mlp_width] * (config.mlp_depth - 1) + [3])
    coarse = 0
    if config.coarse_iters > 0:
        coarse = 4 * math.prod(voxel_layout(bounds, config.coarse_num_voxels)[0])
    return max(fine, coarse)


def nerf_parameter_count(config: Any) -> int:
    """Parameters of a ``NerfMLP`` built from ``config`` (its documented layer list)."""
    w, pos = config.width, encoding_dim(3, config.pos_freqs)
    trunk = sum(((pos if i == 0 else w) + (pos if i in config.skips else 0)) * w + w for i in range(config.depth))
    heads = mlp_parameters([w, 1])
    if config.view_dependent:
        heads += mlp_parameters([w, w]) + mlp_parameters([w + encoding_dim(3, config.dir_freqs), w // 2, 3])
    else:
        heads += mlp_parameters([w, 3])
    return trunk + heads


def estimate_fit_memory(backbone: str, config: Any, bounds: torch.Tensor, *, batch_rays: int, train_pixels: int) -> MemoryEstimate:
    """Peak memory of a fit of ``backbone`` with resolved ``config`` in box ``bounds`` (2, 3).

    Args:
        backbone: ``grid`` or ``nerf`` (anything else: parameters unknown, counted as 0).
        config: the backbone config with every "auto" field resolved (``for_scene``).
        bounds: (2, 3) the scene box.
        batch_rays: rays per training step.
        train_pixels: pixels of all training views (one ray each).
    """
    if backbone == "grid":
        params = grid_parameter_count(config, bounds)
        size, _ = voxel_layout(bounds, config.num_voxels)
        samples_per_ray = math.sqrt(sum(s * s for s in size)) / config.stepsize  # the box's diagonal, every step kept
        channels = 4 + config.feature_dim + config.mlp_width  # colour is decoded only where a sample has weight
        batch = int(batch_rays * samples_per_ray * (GRID_SAMPLE_BYTES + channels * FLOAT_BYTES))
    elif backbone == "nerf":
        params = nerf_parameter_count(config)
        samples = batch_rays * (config.n_samples + config.n_importance)
        units = config.width * (config.depth + 2) + encoding_dim(3, config.pos_freqs) + encoding_dim(3, config.dir_freqs)
        batch = samples * units * MLP_SAMPLE_COPIES * FLOAT_BYTES
    else:
        params, batch = 0, 0
    return MemoryEstimate(parameters=params * FLOAT_BYTES, optimizer=params * FLOAT_BYTES * (TRAINING_COPIES - 1),
                          batch=batch, rays=train_pixels * RAY_BYTES)


def available_memory(device: torch.device | str = "cpu") -> int | None:
    """Bytes that can still be allocated on ``device``: free CUDA memory, else the host's available memory.

    Host: ``MemAvailable`` of ``/proc/meminfo``, else ``os.sysconf`` available pages. None when unknown.
    """
    device = torch.device(device)
    if device.type == "cuda" and torch.cuda.is_available():
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_fit_memory(estimate: MemoryEstimate, available: int | None, *, what: str) -> None:
    """Refuse (one-line :class:`ConfigError`) when ``estimate`` exceeds ``available`` bytes (None: unknown, allowed).

    ``what`` names the setting in the message, e.g. ``grid config num_voxels=1000000000000``.
    """
    if available is not None and estimate.total > available:
        raise ConfigError(f"{what} needs {estimate.describe()}, but only {format_bytes(available)} is available on this "
                          f"machine; lower num_voxels (grid), width/n_samples (nerf) or --batch-rays")


def refuse_if_too_big(backbone: str, config: Any, bounds: torch.Tensor, *, batch_rays: int, train_pixels: int,
                      device: torch.device | str) -> MemoryEstimate:
    """:func:`estimate_fit_memory`, refused (one-line :class:`ConfigError`) when over :func:`available_memory` of ``device``.

    Call it before the model is built; returns the estimate.
    """
    estimate = estimate_fit_memory(backbone, config, bounds, batch_rays=batch_rays, train_pixels=train_pixels)
    sizes = {"grid": ("num_voxels", "coarse_num_voxels"), "nerf": ("width", "depth", "n_samples")}.get(backbone, ())
    what = f"{backbone} config " + ", ".join(f"{name}={getattr(config, name)}" for name in sizes) + f" with {batch_rays} rays a step"
    check_fit_memory(estimate, available_memory(device), what=what)
    return estimate


def check_fit_fits(backbone: str, config: Any, scene: Any, *, batch_rays: int, device: torch.device | str) -> MemoryEstimate:
    """:func:`refuse_if_too_big` for a fit of ``scene`` (a :class:`~nerfmeta.data.scene.Scene`, its training pixels one ray each)."""
    pixels = len(scene.splits.get("train", ())) * scene.height * scene.width
    return refuse_if_too_big(backbone, config, scene.bounds, batch_rays=batch_rays, train_pixels=pixels, device=device)
