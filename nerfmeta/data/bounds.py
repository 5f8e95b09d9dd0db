"""Scene bounds from camera frusta (pure functions)."""

from __future__ import annotations

import torch

from nerfmeta.render.rays import camera_rays


def frustum_bounds(
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    height: int,
    width: int,
    near: float,
    far: float,
    *,
    grid: int = 9,
) -> torch.Tensor:
    """Axis-aligned box of everything the cameras see between ``near`` and ``far``.

    Like DirectVoxGO's ``compute_bbox_by_cam_frustrm``: the box of the points at distance
    ``near`` and ``far`` along rays of every camera. Rays go through a ``grid x grid`` lattice of
    image positions from edge to edge (so the four image corners are included); distances are
    along unit directions, so the centre rays reach deeper than the corner rays.

    Args:
        poses: (n_views, 4, 4) camera-to-world.
        intrinsics: (n_views, 4) ``(fx, fy, cx, cy)``.
        height, width: image size in pixels.
        near, far: ray distances.
        grid: rays per image side (>= 2).

    Returns:
        (2, 3) ``[min_xyz, max_xyz]`` in the dtype of ``poses``.
    """
    if grid < 2:
        raise ValueError(f"grid must be >= 2, got {grid}")
    xs = torch.linspace(0.0, float(width), grid, dtype=poses.dtype, device=poses.device)
    ys = torch.linspace(0.0, float(height), grid, dtype=poses.dtype, device=poses.device)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    pixels = torch.stack([xx, yy], dim=-1).reshape(1, -1, 2)  # (1, grid*grid, 2)
    origins, dirs = camera_rays(poses.unsqueeze(1), intrinsics.to(poses.dtype).unsqueeze(1), pixels)
    points = torch.cat([origins + near * dirs, origins + far * dirs], dim=1).reshape(-1, 3)
    return torch.stack([points.amin(dim=0), points.amax(dim=0)])
