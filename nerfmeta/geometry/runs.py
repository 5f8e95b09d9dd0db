"""Geometry of fitted models: mesh them in the scene file's frame, compare them with ground truth (a fit's ``geometry``)."""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np
import torch

from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import RadianceModel
from nerfmeta.geometry.extract import NoSurfaceError, extract_mesh
from nerfmeta.geometry.mesh import Mesh, mesh_topology
from nerfmeta.geometry.metrics import GeometryConfig, GeometryMetrics, compare_surfaces, sampling_floor
from nerfmeta.geometry.truth import SurfaceSamples, sample_mesh_surface, sample_sdf_surfaces, scene_sdf_of

log = logging.getLogger(__name__)

FIT_GEOMETRY = GeometryConfig(n_points=20000, resolution=64)
"""What a fit measures on a scene with known geometry (small: it runs after every such fit)."""


def mesh_in_file_frame(model: RadianceModel, scene: Any, resolution: int, *, level: float | None = None, colors: bool = True) -> Mesh:
    """``model``'s surface over the scene's box, in the scene file's own coordinates (the load-time normalisation undone)."""
    mesh = extract_mesh(model, scene.bounds, resolution, level=level, colors=colors)
    norm = scene.normalization
    return mesh.transformed(norm.scale, np.asarray(norm.offset, dtype=np.float64))


def evaluate_mesh(mesh: Mesh, gt: SurfaceSamples, config: GeometryConfig, twin: SurfaceSamples | None = None) -> GeometryMetrics:
    """Sample ``mesh`` and compare it with the ground-truth samples (both in the scene file's frame).

    ``twin``: a second, independent sampling of the ground truth; with it the metrics carry the
    sampling floor (``floor_pct_diagonal``, :func:`~nerfmeta.geometry.metrics.sampling_floor`).
    """
    pred = sample_mesh_surface(mesh, config.n_points, seed=config.seed)
    metrics = compare_surfaces(pred.points, gt.points, pred_normals=pred.normals, gt_normals=gt.normals,
                               threshold=config.threshold, tolerance=config.tolerance)
    if twin is None:
        return metrics
    floor = sampling_floor(gt.points, twin.points, threshold=config.threshold, tolerance=config.tolerance)
    return dataclasses.replace(metrics, floor_pct_diagonal=floor)


def topology_summary(mesh: Mesh) -> dict[str, Any]:
    """The mesh's topology for a report: all components, the main ones (>= 1 % of the faces) and their genus."""
    topo = mesh_topology(mesh)
    main, genus = topo.main()
    return {"components": topo.components, "main_components": main, "main_genus": genus,
            "boundary_edges": topo.boundary_edges, "boundary_loops": topo.boundary_loops,
            "nonmanifold_edges": topo.nonmanifold_edges}


def fit_geometry(model: RadianceModel, scene: Any, config: GeometryConfig = FIT_GEOMETRY) -> dict[str, Any] | None:
    """Geometry metrics of a fitted model against its generated scene's exact SDF (``summary.json``'s ``geometry``).

    None when the scene has no known geometry; ``{"error": ...}`` when it has but no figure could be
    made (the field has no surface yet, or scikit-image/SciPy are not installed: ``pip install nerfmeta[mesh]``).
    """
    found = scene_sdf_of(scene.source)
    if found is None:
        return None
    try:
        seeds = (config.seed, config.seed + 1) if config.floor else (config.seed,)
        gt, *rest = sample_sdf_surfaces(*found, config.n_points, resolution=config.resolution, seeds=seeds)
        twin = rest[0] if rest else None
        with torch.random.fork_rng(devices=[]):
            mesh = mesh_in_file_frame(model, scene, config.resolution, colors=False)
        metrics = evaluate_mesh(mesh, gt, config, twin)
    except NoSurfaceError as err:  # an expected outcome of a short or unconverged fit: in summary.json, not a warning
        log.info("geometry not measured: %s", err)
        return {"error": str(err)}
    except (ConfigError, ImportError) as err:
        log.warning("geometry not measured: %s", err)
        return {"error": str(err)}
    return {**dataclasses.asdict(metrics), "resolution": config.resolution, "ground_truth": "exact SDF",
            "topology": topology_summary(mesh)}
