"""Concavities that silhouettes cannot show, and how much of them a fit carved.

A cup's inside, a vase's neck, the space under a chair's seat reached only past its legs: free space
inside the *visual hull* (every training view sees it on the object's silhouette), so a mask says
nothing about it and only the photometric loss can carve it. An SDF fit that grows from a sphere
fills the visual hull first; where the fill stays, the mesh has a lid (a cup closed at its rim).
Chamfer hides a lid farther than its outlier cut from the truth, so :func:`concavity_figures`
measures it directly: of the points that are free in the truth (true SDF above a margin) yet inside
the visual hull, the fraction the fitted surface leaves outside.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import torch

from nerfmeta.fields.base import RadianceModel
from nerfmeta.geometry.extract import surface_function
from nerfmeta.priors.carve import visual_hull

HIDDEN_MARGIN = 0.02
"""A point is free in the truth when its true distance to the surface exceeds this fraction of the box diagonal."""


@dataclass(frozen=True)
class ConcavityFigures:
    """How much hidden concavity a scene has and how much of it a fit carved.

    Attributes:
        hidden_fraction: of the sampled box points inside the visual hull, the fraction free in the truth.
        carved: of those hidden free points, the fraction the fitted surface leaves outside (1: all carved, 0: filled).
        n_hidden: how many hidden free points the figures rest on.
    """

    hidden_fraction: float
    carved: float
    n_hidden: int


def carved_fraction(in_hull: torch.Tensor, true_free: torch.Tensor, fitted_outside: torch.Tensor) -> ConcavityFigures:
    """The figures from per-point booleans, each (N,): in the visual hull, free in the truth, outside the fitted surface."""
    hidden = in_hull & true_free
    n_hull, n_hidden = int(in_hull.sum()), int(hidden.sum())
    carved = float((fitted_outside & hidden).sum()) / n_hidden if n_hidden else float("nan")
    return ConcavityFigures(n_hidden / n_hull if n_hull else 0.0, carved, n_hidden)


def concavity_figures(model: RadianceModel, scene: Any, true_sdf: Callable[[torch.Tensor], torch.Tensor], *,
                      n_points: int = 200_000, seed: int = 0) -> ConcavityFigures:
    """Sample ``n_points`` uniformly in the (loaded) scene's box and measure its hidden concavity's carving.

    Args:
        model: the fitted model (any backbone: its surface as :func:`~nerfmeta.geometry.extract.surface_function` says).
        scene: the loaded scene (training ``alphas`` give the silhouettes; ``normalization`` maps to the file's frame).
        true_sdf: (M, 3) points in the scene file's frame -> (M,) exact signed distances there.
    """
    if scene.alphas is None:
        raise ValueError(f"{scene.source}: no alpha channel, so no silhouettes to build the visual hull from")
    idx = scene.split_indices("train")
    box = scene.bounds.to(torch.float32)
    gen = torch.Generator().manual_seed(seed)
    points = box[0] + (box[1] - box[0]) * torch.rand(n_points, 3, generator=gen)
    in_hull, _ = visual_hull(points, scene.alphas[idx] > 0.5, scene.poses[idx].to(points), scene.intrinsics[idx].to(points), misses=0)
    file_points = scene.normalization.invert_points(points.double())
    with torch.no_grad():
        truth = true_sdf(file_points)
        surface = surface_function(model, scene.bounds)
        values = torch.cat([surface.values(p) for p in points.split(65536)])
    diagonal = float((file_points.max(0).values - file_points.min(0).values).norm())
    outside = values < surface.level if surface.inside_above else values > surface.level
    return carved_fraction(in_hull, truth > HIDDEN_MARGIN * diagonal, outside)
