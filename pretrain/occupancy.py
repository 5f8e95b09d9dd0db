"""Training the learned occupancy start's network (:class:`nerfmeta.priors.occupancy.OccupancyNet`).

The network reads per-voxel multi-view features of a scene's coarse grid
(:func:`nerfmeta.priors.occupancy.occupancy_inputs`) and guesses which coarse voxels the object fills. Generated
scenes know their exact signed distance, so the target is exact: the coarse points within one coarse voxel of the
surface or inside it (the ``truth:1`` start, which ends above the scratch grid on every design scene at 128 px,
BENCHMARKS.md). The loss is binary cross-entropy over the points the start may fill (the visual hull with a margin),
with the occupied points weighted up (:attr:`OccupancyTrainConfig.pos_weight`): a voxel started empty behind a
filled one is never sampled again, so recall comes first. Scenes are drawn one at a time, mirrored along x half the
time. Deterministic for a seed on one thread.

Used by ``scripts/build_model_zoo`` (the zoo's ``occupancy`` entry) and ``scripts/probe_occupancy_start.py train``.
"""

from __future__ import annotations

import json
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import torch
import torch.nn.functional as F

from nerfmeta.data import load_scene
from nerfmeta.fields.grid_ops import grid_points
from nerfmeta.fields.registry import build_model
from nerfmeta.fields.voxel_grid import VoxelGridConfig
from nerfmeta.geometry.truth import in_loaded_frame, scene_sdf_of
from nerfmeta.priors.occupancy import OccupancyNet, grid_views, occupancy_inputs


@dataclass(frozen=True)
class OccupancyTrainConfig:
    """How the occupancy network is trained (the shipped zoo's values are the defaults)."""

    width: int = 16
    """Channels of every hidden 3-D convolution (16: 33k weights; the design scenes did not gain from more)."""
    steps: int = 2000
    """Adam steps, one scene each."""
    lr: float = 2e-3
    """Adam's learning rate."""
    pos_weight: float = 3.0
    """Weight of the occupied points' loss against the empty ones' (recall first)."""
    true_distance: float = 1.0
    """A coarse point is a target 'occupied' when the exact SDF there is below this many coarse voxels."""
    seed: int = 0
    """Seed of the weights and of the scene order."""


@dataclass(frozen=True)
class OccupancyVolume:
    """One scene's training example on its scratch grid's coarse points.

    Attributes:
        features: (F, X, Y, Z) the network's input.
        allowed: (X, Y, Z) bool, the points the start may fill (where the loss is taken).
        target: (X, Y, Z) bool, the exact occupancy.
    """

    features: torch.Tensor
    allowed: torch.Tensor
    target: torch.Tensor


def scratch_grid(scene):
    """The scratch voxel grid for ``scene`` (its coarse grid is the one a start fills)."""
    return build_model("grid", VoxelGridConfig().for_scene(scene), scene.bounds, seed=0)


def true_distance(scene_path: str | Path, scene, model) -> torch.Tensor:
    """(X, Y, Z) a generated scene's exact signed distance at ``model``'s coarse points, in coarse voxels."""
    exact = in_loaded_frame(scene_sdf_of(Path(scene_path))[0], scene.normalization)
    points = grid_points(model.bounds, model.size).reshape(-1, 3)
    with torch.no_grad():
        return torch.cat([exact(c) for c in points.split(1 << 15)]).reshape(model.size) / model.voxel


def occupancy_volume(scene_path: str | Path, *, distance: float = 1.0) -> OccupancyVolume:
    """A generated scene's training example (``distance``: :attr:`OccupancyTrainConfig.true_distance`).

    Raises:
        ValueError: the scene's views give no silhouettes (neither alpha nor a uniform background).
    """
    scene = load_scene(scene_path)
    model = scratch_grid(scene)
    views = grid_views(model, scene)
    if isinstance(views, str):
        raise ValueError(f"{scene_path}: {views}")
    features, allowed = occupancy_inputs(views, model.size)
    return OccupancyVolume(features, allowed, true_distance(scene_path, scene, model) < distance)


def train_occupancy_net(volumes: Sequence[OccupancyVolume], config: OccupancyTrainConfig = OccupancyTrainConfig(), *,
                        log_every: int = 200, on_log: Callable[[dict], None] | None = None) -> tuple[OccupancyNet, list[dict]]:
    """Fit an :class:`OccupancyNet` to ``volumes``; returns it (in eval mode) and its loss log, one record every
    ``log_every`` steps and at the last: ``{"step", "loss", "s"}`` (the loss of that step's scene)."""
    if not volumes:
        raise ValueError("train_occupancy_net: no training scenes")
    torch.manual_seed(config.seed)
    rng = random.Random(config.seed)
    net = OccupancyNet(config.width)
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    pos_weight = torch.tensor(config.pos_weight)
    log: list[dict] = []
    t0 = time.perf_counter()
    for step in range(config.steps):
        v = rng.choice(volumes)
        feats, allowed, target = v.features, v.allowed, v.target
        if rng.random() < 0.5:  # mirrored along x
            feats, allowed, target = feats.flip(1), allowed.flip(0), target.flip(0)
        logits = net(feats)
        loss = F.binary_cross_entropy_with_logits(logits[allowed], target[allowed].float(), pos_weight=pos_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % log_every == 0 or step == config.steps - 1:
            log.append({"step": step, "loss": round(loss.item(), 4), "s": round(time.perf_counter() - t0, 1)})
            if on_log is not None:
                on_log(log[-1])
    return net.eval(), log


def print_log(record: dict) -> None:
    """An ``on_log`` for scripts: one JSON line per record."""
    print(json.dumps(record), flush=True)
