"""Concavities that silhouettes cannot show, and how much of them a fit carved.

A cup's inside, a vase's neck, the space under a chair's seat reached only past its legs: free space
inside the *visual hull* (every training view sees it on the object's silhouette), so a mask says
nothing about it and only the photometric loss can carve it. An SDF fit that grows from a sphere
fills the visual hull first; where the fill stays, the mesh has a lid (a cup closed at its rim).
Chamfer hides a lid farther than its outlier cut from the truth, so :func:`concavity_figures`
measures it directly: of the points that are free in the truth (true SDF above a margin) yet inside
the visual hull, the fraction the fitted surface leaves outside.

A cup carved open can still be carved too little: its inner wall too thick. Chamfer does not say where its
error lies, nor which way, so :func:`surface_offsets` reads a fitted SDF at points of the true surface (its
signed distance there: negative where the fit is too fat, its surface outside the truth) and splits them in
two: surface on the visual hull (silhouettes see it, so the mask pins it) and hidden surface (a cup's
inner wall and inner bottom: only the photometric loss places it). :func:`surface_gradient_norm` reads the same
points for whether the fit is still a signed distance there (mean ``|grad f|`` near 1).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Callable

import torch

from nerfmeta.fields.base import RadianceModel, module_device
from nerfmeta.geometry.extract import surface_function
from nerfmeta.geometry.truth import SurfaceSamples
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


def in_training_hull(scene: Any, points: torch.Tensor) -> torch.Tensor:
    """(N,) bool: which loaded-frame points (N, 3) lie inside every training view's silhouette (alpha > 0.5), no misses allowed."""
    idx = scene.split_indices("train")
    inside, _ = visual_hull(points, scene.alphas[idx] > 0.5, scene.poses[idx].to(points), scene.intrinsics[idx].to(points), misses=0)
    return inside


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
    box = scene.bounds.to(torch.float32)
    gen = torch.Generator().manual_seed(seed)
    points = box[0] + (box[1] - box[0]) * torch.rand(n_points, 3, generator=gen)
    in_hull = in_training_hull(scene, points)
    file_points = scene.normalization.invert_points(points.double())
    with torch.no_grad():
        truth = true_sdf(file_points)
        surface = surface_function(model, scene.bounds)
        values = torch.cat([surface.values(p) for p in points.split(65536)])
    diagonal = float((file_points.max(0).values - file_points.min(0).values).norm())
    outside = values < surface.level if surface.inside_above else values > surface.level
    return carved_fraction(in_hull, truth > HIDDEN_MARGIN * diagonal, outside)


@dataclass(frozen=True)
class OffsetFigures:
    """A fitted SDF's signed distance at points of one part of the true surface (the scene file's units).

    Attributes:
        share: the part's fraction of the true surface's samples.
        mean: mean signed distance (negative: the fitted surface lies outside the truth, the fit is too fat).
        mean_abs: mean absolute distance.
        mean_pct_diagonal, mean_abs_pct_diagonal: the same as % of the true surface's bounding-box diagonal.
    """

    share: float
    mean: float
    mean_abs: float
    mean_pct_diagonal: float
    mean_abs_pct_diagonal: float


def offset_figures(offsets: torch.Tensor, parts: dict[str, torch.Tensor], diagonal: float) -> dict[str, OffsetFigures]:
    """Figures of ``offsets`` (N,) over all samples (``all``) and over each part, a (N,) bool mask (an empty part is left out)."""
    out = {}
    n = offsets.shape[0]
    for name, keep in {"all": torch.ones(n, dtype=torch.bool), **parts}.items():
        if int(keep.sum()) == 0:
            continue
        o = offsets[keep].double()
        mean, mean_abs = float(o.mean()), float(o.abs().mean())
        out[name] = OffsetFigures(int(keep.sum()) / n, mean, mean_abs, 100.0 * mean / diagonal, 100.0 * mean_abs / diagonal)
    return out


def surface_offsets(model: RadianceModel, scene: Any, gt: SurfaceSamples, *, n_points: int = 100_000) -> dict[str, dict] | None:
    """A fitted SDF's signed distance on the true surface, overall, on the visual hull and on hidden surface.

    A true-surface point is on the visual hull when the point ``HIDDEN_MARGIN`` of the diagonal outward along its
    normal is outside the hull (no view's silhouette covers it), else hidden (inside a concavity).

    Args:
        model: a fitted model with ``sdf_world`` (an SDF backbone); others give None.
        scene: the loaded scene (its training ``alphas`` make the visual hull).
        gt: samples of the true surface in the scene file's frame; the first ``n_points`` are used.

    Returns:
        ``{"all": ..., "on_hull": ..., "hidden": ...}`` of :class:`OffsetFigures` as dicts, or None.
    """
    if not hasattr(model, "sdf_world") or scene.alphas is None:
        return None
    points = torch.as_tensor(gt.points[:n_points], dtype=torch.float64)
    normals = torch.as_tensor(gt.normals[:n_points], dtype=torch.float64)
    diagonal = float((points.max(0).values - points.min(0).values).norm())
    norm = scene.normalization
    outward = norm.apply_points(points + HIDDEN_MARGIN * diagonal * normals).float()
    in_hull = in_training_hull(scene, outward)
    loaded = norm.apply_points(points).to(scene.bounds.dtype)
    sdf = surface_function(model, scene.bounds).values  # the SDF on the model's device, values back on the CPU
    with torch.no_grad():
        offsets = torch.cat([sdf(p) for p in loaded.split(65536)]).double() / float(norm.scale)
    figures = offset_figures(offsets, {"on_hull": ~in_hull, "hidden": in_hull}, diagonal)
    return {name: asdict(f) for name, f in figures.items()}


def surface_gradient_norm(model: RadianceModel, scene: Any, gt: SurfaceSamples, *, n_points: int = 20_000) -> float | None:
    """Mean ``|grad f|`` of a fitted SDF at the first ``n_points`` points of the true surface (1 for a signed distance).

    The gradient of ``sdf_world`` by autograd in the loaded frame: a uniform scale of the scene changes
    distances and lengths alike, so the figure is unitless. None for a model without ``sdf_world``.
    """
    if not hasattr(model, "sdf_world"):
        return None
    loaded = scene.normalization.apply_points(torch.as_tensor(gt.points[:n_points], dtype=torch.float64))
    device = module_device(model)
    norms = []
    for chunk in loaded.to(scene.bounds.dtype).split(8192):
        p = chunk.to(device).requires_grad_(True)
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(model.sdf_world(p).sum(), p)
        norms.append(grad.detach().norm(dim=-1).double().cpu())
    return float(torch.cat(norms).mean())
