"""Meshes from fields: marching cubes (scikit-image) over a field's box, vertex colours from the field.

What is meshed depends on what the field says (:func:`surface_function`): an SDF backbone (one
with ``sdf_world``) is meshed at its zero level set; a density backbone at a density threshold
``sigma = ln 2 / (DENSITY_LENGTH * box diagonal)`` per world unit, i.e. where a layer 1 % of the
box's diagonal thick would stop half the light (``level`` overrides it). Vertex colours are the
field's colour at each vertex seen head-on (view direction ``-normal``). Positions are in the loaded
frame of the scene; :meth:`~nerfmeta.geometry.mesh.Mesh.transformed` with the scene's normalisation
puts them back in the scene file's own coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import RadianceModel, module_device
from nerfmeta.geometry.mesh import Mesh

DENSITY_LENGTH = 0.01
"""A density backbone's surface is where a layer this fraction of the box diagonal thick has alpha 0.5."""


@dataclass(frozen=True)
class Surface:
    """What to mesh: ``values(points (N, 3)) -> (N,)`` at world points, its ``level``, and whether inside is above it.

    ``values`` takes points on any device and returns its values on the CPU (the field runs on its own device)."""

    values: Callable[[torch.Tensor], torch.Tensor]
    level: float
    inside_above: bool
    kind: str


def surface_function(model: RadianceModel, box: torch.Tensor, level: float | None = None) -> Surface:
    """The surface of ``model``: its SDF's zero set, or a density threshold (see the module docstring)."""
    device = module_device(model)
    if hasattr(model, "sdf_world"):
        return Surface(lambda p: model.sdf_world(p.to(device)).cpu(), 0.0 if level is None else level, False, "sdf")
    diagonal = float((box[1] - box[0]).norm())
    threshold = math.log(2.0) / (DENSITY_LENGTH * diagonal) if level is None else level
    return Surface(lambda p: model.get_density(p.to(device))[0].cpu(), threshold, True, "density")


def grid_values(fn: Callable[[torch.Tensor], torch.Tensor], box: torch.Tensor, resolution: int, chunk: int = 65536) -> np.ndarray:
    """(R, R, R) float32 values of ``fn`` at the corners of a ``resolution``^3 lattice spanning ``box`` (2, 3), without gradient."""
    axes = [torch.linspace(float(box[0, a]), float(box[1, a]), resolution) for a in range(3)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).to(box)
    out = []
    with torch.no_grad():
        for start in range(0, points.shape[0], chunk):
            out.append(fn(points[start:start + chunk]).float().cpu())
    return torch.cat(out).reshape(resolution, resolution, resolution).numpy()


class NoSurfaceError(ConfigError):
    """The field has no surface at the asked level (e.g. a short fit whose density stays below it everywhere)."""


def marching_cubes(values: np.ndarray, box: np.ndarray, level: float, inside_above: bool) -> Mesh:
    """Triangles of the level set of ``values`` (R, R, R) on a lattice spanning ``box`` (2, 3), faces wound outward.

    Raises:
        NoSurfaceError: the level is not crossed anywhere (nothing to mesh; say the field's range).
    """
    from skimage import measure

    lo, hi = float(np.nanmin(values)), float(np.nanmax(values))
    if not lo < level < hi or not np.isfinite(values).all():
        raise NoSurfaceError(f"the field never crosses the level {level:g} in its box (values {lo:.4g} .. {hi:.4g}); "
                             "nothing to mesh (try another --level)")
    spacing = tuple(float(s) for s in (box[1] - box[0]) / (np.array(values.shape) - 1))
    # scikit-image's normals point to lower values whatever gradient_direction says, and its winding
    # is outward with "descent" for inside-low values, with "ascent" for inside-high (checked by a test)
    verts, faces, normals, _ = measure.marching_cubes(values, level=level, spacing=spacing,
                                                      gradient_direction="ascent" if inside_above else "descent")
    normals = normals.astype(np.float64) * (1.0 if inside_above else -1.0)
    return Mesh(verts.astype(np.float64) + box[0], faces.astype(np.int64), None, normals)


def vertex_colors(model: RadianceModel, mesh: Mesh, chunk: int = 16384) -> np.ndarray:
    """(V, 3) uint8 colour of the field at every vertex, seen along ``-normal`` (the field runs on its own device)."""
    device = module_device(model)
    out = []
    for start in range(0, len(mesh.vertices), chunk):
        p = torch.as_tensor(mesh.vertices[start:start + chunk], dtype=torch.float32, device=device)
        n = torch.as_tensor(mesh.normals[start:start + chunk], dtype=torch.float32, device=device)
        dirs = -torch.nn.functional.normalize(n, dim=-1)
        with torch.no_grad():
            _, embedding = model.get_density(p)
            rgb = model.get_outputs(embedding, None, dirs, torch.arange(p.shape[0], device=device))
        out.append(rgb.clamp(0, 1).cpu().numpy())
    return (np.concatenate(out) * 255.0 + 0.5).astype(np.uint8) if out else np.zeros((0, 3), np.uint8)


def extract_mesh(model: RadianceModel, box: torch.Tensor, resolution: int, *, level: float | None = None, colors: bool = True) -> Mesh:
    """Marching cubes of ``model``'s surface over ``box`` (2, 3) (loaded frame) at ``resolution`` corners per axis."""
    if resolution < 8:
        raise ConfigError(f"--resolution {resolution}: use 8 or more")
    model.eval()
    surface = surface_function(model, box, level)
    values = grid_values(surface.values, box.float(), resolution)
    mesh = marching_cubes(values, box.double().numpy(), surface.level, surface.inside_above)
    if colors:
        mesh.colors = vertex_colors(model, mesh)
    return mesh
