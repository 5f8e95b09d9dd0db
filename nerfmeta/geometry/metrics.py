"""Geometry metrics between two surfaces given as oriented point samples (DTU's definitions).

With ``d(p, Q)`` the distance from ``p`` to the nearest point of ``Q`` (a k-d tree, SciPy's
``cKDTree``), predicted samples ``P`` and ground-truth samples ``G``:

- accuracy = mean of ``d(p, G)`` over the ``p`` in ``P`` with ``d(p, G) < threshold`` (DTU drops
  farther outliers: its ``max_dist``, 20 mm there);
- completeness = mean of ``d(g, P)`` over the ``g`` in ``G`` with ``d(g, P) < threshold``;
- Chamfer = (accuracy + completeness) / 2;
- outliers_pred / outliers_gt = fraction of ``P`` / ``G`` that accuracy / completeness left out (farther than
  ``threshold``): read them beside the Chamfer, which says nothing of a part of the surface put wholly elsewhere (a
  cup's floor fitted a fifth of the diagonal too high drops out of both means instead of counting as an error);
- precision / recall = fraction of ``P`` / ``G`` within ``tolerance`` of the other; F-score their
  harmonic mean (Tanks and Temples);
- normal consistency = mean of ``|n_p . n_nearest|`` over both directions (Occupancy Networks).

The figures are of *samples*: two independent samplings of one and the same surface are not at
distance 0 but at about half the mean spacing of the samples, ``~0.5 sqrt(area / n)``. That
*sampling floor* is what a perfect reconstruction scores; on a generated mug (diagonal ~2) it is
0.46 % of the diagonal at 20k points, 0.21 % at 100k and 0.07 % at 1M, so a figure is only read
against it (:func:`sampling_floor`; ``floor_pct_diagonal`` in the reports). DTU samples at 0.2 mm
for Chamfer figures of ~1 mm, a floor well below what it measures; ``n_points`` plays that role here.

Thresholds are given as fractions of the ground truth's bounding-box diagonal, so scenes of any
scale compare alike; the figures are in the samples' own units (and as % of the diagonal).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GeometryConfig:
    """Settings of the geometry evaluation (``nerfmeta eval-geometry`` and fits on scenes with known geometry)."""

    threshold: float = 0.05
    """Distances above this fraction of the ground truth's bounding-box diagonal are outliers in accuracy and completeness (DTU's max_dist)."""
    tolerance: float = 0.01
    """F-score tolerance, as a fraction of the ground truth's bounding-box diagonal."""
    n_points: int = 1000000
    """Points sampled on each surface (the sampling floor falls as 1 / sqrt(n_points): 0.07 % of a mug's diagonal at 1M)."""
    resolution: int = 128
    """Marching-cubes corners per axis for the predicted mesh (and for a generated scene's exact SDF)."""
    seed: int = 0
    """Seed of the surface sampling."""
    floor: bool = True
    """Also report the sampling floor: the Chamfer between two independent samplings of the ground truth (what a perfect surface scores)."""


@dataclass(frozen=True)
class GeometryMetrics:
    """The figures of one comparison (lengths in the samples' units; see the module docstring)."""

    accuracy: float
    completeness: float
    chamfer: float
    chamfer_pct_diagonal: float
    precision: float
    recall: float
    fscore: float
    normal_consistency: float | None
    threshold: float
    tolerance: float
    diagonal: float
    n_pred: int
    n_gt: int
    outliers_pred: float
    outliers_gt: float
    floor_pct_diagonal: float | None = None


def nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every point of ``a`` (Na, 3) the distance to the nearest point of ``b`` (Nb, 3) and its index: (Na,), (Na,).

    The queries run on as many threads as torch may use (``torch.get_num_threads()``, so a ``--threads`` limit or a
    worker's single thread holds here too; the same answers): on a bad fit's mesh (film left inside a cup, 49
    components) the queries of its points against the truth took most of a 9-minute ``eval-geometry`` on one thread.
    """
    import torch
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(b).query(a, k=1, workers=max(1, torch.get_num_threads()))
    return np.asarray(dist, dtype=np.float64), np.asarray(idx, dtype=np.int64)


def _mean_below(d: np.ndarray, limit: float) -> float:
    kept = d[d < limit]
    return float(kept.mean()) if kept.size else float("inf")


def compare_surfaces(pred: np.ndarray, gt: np.ndarray, *, pred_normals: np.ndarray | None = None,
                     gt_normals: np.ndarray | None = None, threshold: float = 0.05, tolerance: float = 0.01) -> GeometryMetrics:
    """Accuracy, completeness, Chamfer, F-score and normal consistency of samples ``pred`` (Np, 3) against ``gt`` (Ng, 3).

    ``threshold`` and ``tolerance`` are fractions of ``gt``'s bounding-box diagonal; normals (unit,
    same shapes as the points) are optional (no normal consistency without both).
    """
    diagonal = float(np.linalg.norm(gt.max(0) - gt.min(0)))
    max_dist, tol = threshold * diagonal, tolerance * diagonal
    d_pred, i_pred = nearest(pred, gt)
    d_gt, i_gt = nearest(gt, pred)
    acc, comp = _mean_below(d_pred, max_dist), _mean_below(d_gt, max_dist)
    precision, recall = float((d_pred < tol).mean()), float((d_gt < tol).mean())
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    nc = None
    if pred_normals is not None and gt_normals is not None:
        nc = 0.5 * (float(np.abs(np.sum(pred_normals * gt_normals[i_pred], -1)).mean())
                    + float(np.abs(np.sum(gt_normals * pred_normals[i_gt], -1)).mean()))
    chamfer = 0.5 * (acc + comp)
    return GeometryMetrics(acc, comp, chamfer, 100.0 * chamfer / diagonal, precision, recall, fscore, nc,
                           max_dist, tol, diagonal, len(pred), len(gt),
                           float((d_pred >= max_dist).mean()), float((d_gt >= max_dist).mean()))


def sampling_floor(gt: np.ndarray, twin: np.ndarray, *, threshold: float = 0.05, tolerance: float = 0.01) -> float:
    """Chamfer, % of the diagonal, between two independent samplings ``gt`` and ``twin`` (N, 3) of one surface.

    What a perfect reconstruction sampled with as many points scores (see the module docstring).
    """
    return compare_surfaces(twin, gt, threshold=threshold, tolerance=tolerance).chamfer_pct_diagonal
