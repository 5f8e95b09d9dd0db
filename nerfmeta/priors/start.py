"""Apply a carved start to a voxel grid about to fit a scene (see :mod:`nerfmeta.priors.carve`)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import torch

from nerfmeta.data.scene import Scene
from nerfmeta.fields.grid_ops import grid_points
from nerfmeta.priors.carve import CarveStart, carve

HULL_ALPHA = 0.1
"""Alpha of one coarse marching step inside the carved hull: opaque within about ten voxels, the fit carves the rest.
0.3 (the first choice) is too dense to unlearn where the hull is loose (a lamp's shade): on the seed-7 design lamp it
ended 0.30 dB below scratch at 1000 iterations and was behind from the 150th on; 0.1 and 0.05 ended 0.06 and 0.08 dB
above, and 0.1 was the furthest ahead of the three after 50 steps (BENCHMARKS.md, *Carved start: never behind*)."""
EMPTY_ALPHA = 1e-6
"""Alpha of one coarse marching step outside the hull (scratch's 1e-4 instead lets faint floaters into the fine
stage's occupancy cache: 82 % of the fine voxels against 32 % on the design lamp, and 0.48 dB lower at 1000 steps)."""
CARVE_COARSE_ITERS = 100
"""Coarse steps a carved start keeps: scratch's 100, so only the start differs (on a design scene, 20 steps were 1.3 dB
ahead at 2 s but ended 0.7 dB below scratch at 1000 iterations; 100 ended 0.15 dB below, within run-to-run noise)."""


@dataclass(frozen=True)
class StartReport:
    """What a feed-forward start did to a fit.

    Attributes:
        applied: whether the model's grids were started from it.
        kind: the start's name (``carve``).
        reason: one sentence: what was applied, or why not.
        build_s: wall seconds spent building it (part of the fit's wall-clock time).
        figures: JSON-able numbers (hull fraction, mask source, background).
    """

    applied: bool
    kind: str
    reason: str
    build_s: float
    figures: dict[str, Any]

    def as_json(self) -> dict[str, Any]:
        return {"applied": self.applied, "kind": self.kind, "reason": self.reason, "build_s": self.build_s,
                "figures": dict(self.figures)}


def sigma_for_alpha(alpha: float, step: float) -> float:
    """Density per world unit giving ``alpha`` over a marching step of ``step`` world units."""
    return -math.log1p(-alpha) / step


def load_occupied_start(model, occupied: torch.Tensor, rgb: torch.Tensor, unknown: torch.Tensor | None = None) -> None:
    """Load a start into ``model``'s coarse grids: (N,) bool ``occupied`` coarse points at :data:`HULL_ALPHA` a step with
    their (N, 3) ``rgb``, ``unknown`` ones at scratch's alpha, the rest at :data:`EMPTY_ALPHA` (N: the coarse points in
    ``grid_points`` order)."""
    step = model.config.stepsize * model.voxel
    empty = torch.full(occupied.shape, sigma_for_alpha(EMPTY_ALPHA, step), device=occupied.device)
    if unknown is not None:
        empty = torch.where(unknown, sigma_for_alpha(model.config.coarse_alpha_init, step), empty)
    sigma = torch.where(occupied, sigma_for_alpha(HULL_ALPHA, step), empty)
    model.load_coarse_start(sigma.view(model.size), rgb.t().reshape(3, *model.size))


def carve_blocker(model, scene: Scene) -> str:
    """Why ``model`` (a voxel grid) cannot be carved for ``scene`` before looking at its images ("" when it can).

    Carving projects the grid's points with the scene's cameras, so it needs a bounded object scene whose grid lives
    in the scene's own frame: not a forward-facing scene (its grid is in NDC), not an unbounded one (a contracted
    space), and a coarse stage to start.
    """
    kind = scene.scene_type.kind
    if kind != "object" or scene.ndc is not None:
        return f"a {kind} scene{' fitted in NDC' if scene.ndc is not None else ''}: carving needs a bounded object scene, not carved"
    if getattr(model, "box", None) is not None:
        return "the grid lives in a contracted space: carving needs the scene's own box, not carved"
    if getattr(model, "stage", None) != "coarse":
        return "the grid has no coarse stage to start (coarse_iters = 0): not carved"
    return ""


def carve_grid_start(model, scene: Scene, background: torch.Tensor) -> StartReport:
    """Start ``model``'s coarse stage (a :class:`~nerfmeta.fields.voxel_grid.VoxelGrid`) from the visual hull of
    ``scene``'s training views; leave it untouched, with the reason, where the views cannot be carved."""
    t0 = time.perf_counter()
    why_not = carve_blocker(model, scene)
    if why_not:
        return StartReport(False, "carve", why_not, 0.0, {})
    train = scene.subset("train")
    device = model.bounds.device
    pts = grid_points(model.bounds, model.size).reshape(-1, 3)
    result = carve(pts, train.images.to(device), None if train.alphas is None else train.alphas.to(device),
                   train.poses.to(device), train.intrinsics.to(device), background.to(device), voxel=model.voxel)
    if not isinstance(result, CarveStart):
        return StartReport(False, "carve", result.reason, round(time.perf_counter() - t0, 4), {"source": result.source})
    load_occupied_start(model, result.occupied, result.rgb, result.unknown)
    figures = {"source": result.silhouettes.source, "hull_fraction": round(result.hull_fraction, 4),
               "background": result.silhouettes.background, "views": train.n_views, "margin_px": result.margin_px,
               "unknown_fraction": round(float(result.unknown.float().mean()), 4)}
    reason = f"{result.silhouettes.reason}: the coarse grid starts from the visual hull ({100 * result.hull_fraction:.1f}% of it)"
    return StartReport(True, "carve", reason, round(time.perf_counter() - t0, 4), figures)
