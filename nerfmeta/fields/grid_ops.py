"""Dense voxel-grid operations (pure functions).

Grids are stored like DirectVoxGO's: a value per voxel corner over an axis-aligned box
``bounds`` (2, 3), corner ``(i, j, k)`` at ``bounds[0] + (i, j, k) * (bounds[1] - bounds[0]) / (size - 1)``.
Two layouts: channels-first ``(C, X, Y, Z)`` for :func:`interp_cf` (``grid_sample``, fastest for
one channel on CPU) and channels-last ``(X*Y*Z, C)`` for :func:`interp_cl` (a gather with
``embedding_bag``, fastest for many channels on CPU since each corner's channels are contiguous).
Points outside the box are clamped to its faces.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def voxel_layout(bounds: torch.Tensor, num_voxels: int) -> tuple[tuple[int, int, int], float]:
    """Grid size per axis and voxel side for about ``num_voxels`` cubic voxels in ``bounds`` (2, 3).

    As in DirectVoxGO: ``voxel = (volume / num_voxels) ** (1/3)``, ``size = extent / voxel``.
    """
    extent = (bounds[1] - bounds[0]).double()
    voxel = float((extent.prod() / num_voxels) ** (1.0 / 3.0))
    size = tuple(max(2, int(math.floor(e / voxel)) + 1) for e in extent.tolist())
    return size, voxel  # type: ignore[return-value]


def to_unit(points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """(N, 3) points to [0, 1]^3 box coordinates (not clamped)."""
    return (points - bounds[0]) / (bounds[1] - bounds[0])


def interp_cf(grid: torch.Tensor, points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of a channels-first grid.

    Args:
        grid: (C, X, Y, Z).
        points: (N, 3) world points.
        bounds: (2, 3) the grid's box.

    Returns:
        (N, C).
    """
    n = points.shape[0]
    coords = (to_unit(points, bounds) * 2.0 - 1.0).flip(-1)  # grid_sample wants (z, y, x) -> (W, H, D)
    out = F.grid_sample(
        grid.unsqueeze(0), coords.view(1, 1, 1, n, 3), mode="bilinear", padding_mode="border", align_corners=True
    )
    return out.view(grid.shape[0], n).t()


_CORNERS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


def corner_indices_weights(
    points: torch.Tensor, bounds: torch.Tensor, size: tuple[int, int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat indices (N, 8) of the 8 voxel corners around each point and their trilinear weights (N, 8)."""
    sx, sy, sz = size
    scale = torch.tensor([sx - 1, sy - 1, sz - 1], dtype=points.dtype, device=points.device)
    x = (to_unit(points, bounds) * scale).clamp(min=0.0)
    x = torch.minimum(x, scale)
    i0 = torch.minimum(x.floor(), scale - 1).long()
    f = x - i0.to(x.dtype)
    base = (i0[:, 0] * sy + i0[:, 1]) * sz + i0[:, 2]
    offs = torch.tensor([(dx * sy + dy) * sz + dz for dx, dy, dz in _CORNERS], device=points.device)
    fx, fy, fz = f.unbind(-1)
    wx = torch.stack([1 - fx, fx], -1)
    wy = torch.stack([1 - fy, fy], -1)
    wz = torch.stack([1 - fz, fz], -1)
    w = (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)
    return base[:, None] + offs, w


def interp_cl(grid: torch.Tensor, points: torch.Tensor, bounds: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """Trilinear interpolation of a channels-last grid.

    Args:
        grid: (X*Y*Z, C) values, flattened in (x, y, z) order.
        points: (N, 3); bounds: (2, 3); size: (X, Y, Z).

    Returns:
        (N, C).
    """
    idx, w = corner_indices_weights(points, bounds, size)
    return F.embedding_bag(idx, grid, per_sample_weights=w, mode="sum")


def nearest_lookup(mask: torch.Tensor, points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Value of a (X, Y, Z) grid at the voxel corner nearest each (N, 3) point; False/0 outside the box."""
    size = torch.tensor(mask.shape, device=points.device)
    u = to_unit(points, bounds)
    inside = ((u >= 0) & (u <= 1)).all(-1)
    idx = torch.round(u.clamp(0, 1) * (size - 1).to(u.dtype)).long()
    return mask[idx[:, 0], idx[:, 1], idx[:, 2]] & inside


def grid_points(bounds: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """(X, Y, Z, 3) world positions of the grid corners."""
    axes = [torch.linspace(float(bounds[0, a]), float(bounds[1, a]), size[a], dtype=bounds.dtype, device=bounds.device) for a in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)


def resample_cf(grid: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """Trilinearly resample a (C, X, Y, Z) grid to ``size`` corners (same box)."""
    return F.interpolate(grid.unsqueeze(0), size=size, mode="trilinear", align_corners=True).squeeze(0)


def total_variation(grid: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between neighbouring voxels of a (C, X, Y, Z) grid (a scalar)."""
    dx = (grid[:, 1:] - grid[:, :-1]).pow(2).mean()
    dy = (grid[:, :, 1:] - grid[:, :, :-1]).pow(2).mean()
    dz = (grid[:, :, :, 1:] - grid[:, :, :, :-1]).pow(2).mean()
    return (dx + dy + dz) / 3.0
