"""Ground-truth surfaces: a generated scene's exact SDF (sampled on its zero level set) or a mesh file.

A generated collection (``nerfmeta make-collection``) records every scene's exact shape in
``collection.json``; :func:`scene_sdf_of` finds it from the scene folder. Its surface samples come
from marching cubes of the exact SDF, then every sample is moved onto the zero level set by two
Newton steps ``p <- p - f(p) grad f / |grad f|^2`` (central differences), so they lie on the true
surface to far below the lattice spacing; normals are the SDF's normalised gradient.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from nerfmeta.geometry.extract import grid_values, marching_cubes
from nerfmeta.geometry.mesh import Mesh, read_mesh, sample_surface

SdfFn = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class SurfaceSamples:
    """Oriented points on a surface: ``points`` (N, 3) and unit ``normals`` (N, 3), in the scene file's frame."""

    points: np.ndarray
    normals: np.ndarray
    source: str


def scene_sdf_of(scene: str | os.PathLike) -> tuple[SdfFn, np.ndarray] | None:
    """The exact SDF of a generated scene and its (2, 3) box, from the ``collection.json`` above it; None if it has none."""
    from nerfmeta.collection.generate import load_collection

    path = Path(scene).resolve()
    for parent in path.parents:
        if (parent / "collection.json").is_file():
            collection = load_collection(parent)
            for record in collection.scenes:
                if (collection.root / record.path).resolve() == path:
                    return record.sdf, record.aabb
            return None
    return None


def in_loaded_frame(sdf: SdfFn, normalization) -> SdfFn:
    """A scene file's exact ``sdf`` as a function of (N, 3) points of the *loaded* (normalised) scene, in its units:
    the points mapped back to the file's frame (float64), the distances scaled as the scene was."""
    def loaded(points: torch.Tensor) -> torch.Tensor:
        return sdf(normalization.invert_points(points.double())) * normalization.scale

    return loaded


def project_to_zero_set(sdf: SdfFn, points: np.ndarray, h: float, steps: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Move points (N, 3) onto ``sdf``'s zero set by Newton steps; return them and the unit gradients there."""
    p = torch.as_tensor(points, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64) * h
    grad = torch.zeros_like(p)
    for _ in range(steps + 1):
        f = sdf(p)
        grad = torch.stack([(sdf(p + eye[k]) - sdf(p - eye[k])) / (2 * h) for k in range(3)], -1)
        norm2 = (grad * grad).sum(-1, keepdim=True).clamp(min=1e-12)
        if _ < steps:
            p = p - f[:, None] * grad / norm2
    return p.numpy(), torch.nn.functional.normalize(grad, dim=-1).numpy()


def sample_sdf_surface(sdf: SdfFn, box: np.ndarray, n: int, *, resolution: int = 128, seed: int = 0) -> SurfaceSamples:
    """``n`` oriented samples on the zero level set of an exact SDF inside ``box`` (2, 3) (see the module docstring)."""
    return sample_sdf_surfaces(sdf, box, n, resolution=resolution, seeds=(seed,))[0]


def sample_sdf_surfaces(sdf: SdfFn, box: np.ndarray, n: int, *, resolution: int = 128,
                        seeds: tuple[int, ...] = (0,)) -> list[SurfaceSamples]:
    """One independent :func:`sample_sdf_surface` per seed, all from one marching-cubes mesh of the SDF
    (a ground truth and its twin for the sampling floor cost one mesh, not two)."""
    pad = 0.02 * (box[1] - box[0])
    grid_box = torch.as_tensor(np.stack([box[0] - pad, box[1] + pad]), dtype=torch.float64)
    values = grid_values(sdf, grid_box, resolution, chunk=1 << 18)
    mesh = marching_cubes(values, grid_box.numpy(), 0.0, inside_above=False)
    h = 1e-4 * float(np.linalg.norm(box[1] - box[0]))
    out = []
    for seed in seeds:
        points, _ = sample_surface(mesh, n, np.random.default_rng(seed))
        points, normals = project_to_zero_set(sdf, points, h)
        out.append(SurfaceSamples(points, normals, "exact SDF"))
    return out


def sample_mesh_surface(mesh: Mesh, n: int, *, seed: int = 0) -> SurfaceSamples:
    """``n`` area-uniform samples on a mesh with their face normals."""
    points, normals = sample_surface(mesh, n, np.random.default_rng(seed))
    return SurfaceSamples(points, normals, "mesh")


def ground_truth(spec: str | os.PathLike, n: int, *, resolution: int = 128, seed: int = 0) -> SurfaceSamples:
    """Ground-truth samples from a generated scene folder (its exact SDF) or a PLY/OBJ mesh file."""
    return ground_truths(spec, n, resolution=resolution, seeds=(seed,))[0]


def ground_truths(spec: str | os.PathLike, n: int, *, resolution: int = 128, seeds: tuple[int, ...] = (0,)) -> list[SurfaceSamples]:
    """One independent :func:`ground_truth` sampling per seed, the file read (or the SDF meshed) once."""
    from nerfmeta.errors import ConfigError

    path = Path(spec)
    if path.is_file():
        mesh = read_mesh(path)
        return [SurfaceSamples(out.points, out.normals, f"mesh {path}")
                for out in (sample_mesh_surface(mesh, n, seed=seed) for seed in seeds)]
    found = scene_sdf_of(path) if path.is_dir() else None
    if found is None:
        raise ConfigError(f"--gt {spec}: neither a PLY/OBJ mesh nor a scene of a generated collection (no collection.json "
                          "above it lists it), so no ground-truth geometry")
    sdf, box = found
    return [SurfaceSamples(out.points, out.normals, f"exact SDF of {path}")
            for out in sample_sdf_surfaces(sdf, box, n, resolution=resolution, seeds=seeds)]
