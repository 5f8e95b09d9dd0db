"""Scene bounds from camera frusta (pure functions)."""

from __future__ import annotations

import numpy as np
import torch

from nerfmeta.render.rays import camera_rays

NEAR_SYNTHETIC = 2.0
FAR_SYNTHETIC = 6.0
"""NeRF-synthetic's near/far (cameras at radius 4.03 around a unit-size object)."""
SYNTHETIC_SCALE_FACTOR = 1.5
"""Derived near/far within this factor of NeRF-synthetic's (each) keep its values exactly."""


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


def near_far_from_cameras(poses: np.ndarray) -> tuple[float, float] | None:
    """Guess ``(near, far)`` from inward-looking cameras, or None when they share no focus.

    The centre of interest ``c`` minimises the summed squared distance to the cameras' optical
    axes. With ``d_i = |o_i - c|``: ``near = 0.5 * min(d)``, ``far = 1.5 * max(d)``. Returns None
    when the axes are nearly parallel or ``c`` lies behind the cameras.

    Args:
        poses: (n, 4, 4) camera-to-world (OpenGL: the camera looks along -z).
    """
    if not np.abs(poses[:, :3, 3]).max() < 1e150:  # squared distances would overflow: no guess (the range checks refuse it)
        return None
    origins = poses[:, :3, 3]
    forward = -poses[:, :3, 2]
    forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    proj = np.eye(3)[None] - forward[:, :, None] * forward[:, None, :]  # (n, 3, 3)
    a = proj.sum(axis=0) / len(poses)
    b = (proj @ origins[:, :, None]).sum(axis=0)[:, 0] / len(poses)
    if np.linalg.eigvalsh(a).min() < 1e-2:
        return None
    centre = np.linalg.solve(a, b)
    ahead = ((centre[None] - origins) * forward).sum(axis=-1)
    if np.median(ahead) <= 0:
        return None
    dist = np.linalg.norm(origins - centre[None], axis=-1)
    if dist.min() <= 0:
        return None
    return 0.5 * float(dist.min()), 1.5 * float(dist.max())


def default_near_far(poses: np.ndarray) -> tuple[float, float, str]:
    """``(near, far, source)`` for a Blender or tiny-NeRF file without them.

    The rule of :func:`near_far_from_cameras`, except that values within a factor
    :data:`SYNTHETIC_SCALE_FACTOR` of NeRF-synthetic's (``NEAR_SYNTHETIC``, ``FAR_SYNTHETIC``) give
    exactly those, so scenes at its scale (lego: 2.02 / 6.05 derived) load as they always did.

    Args:
        poses: (n, 4, 4) camera-to-world (OpenGL).
    """
    guess = near_far_from_cameras(poses)
    if guess is None:
        return NEAR_SYNTHETIC, FAR_SYNTHETIC, "NeRF-synthetic default (not in the file; the cameras share no point of focus)"
    near, far = guess
    k = SYNTHETIC_SCALE_FACTOR
    if 1 / k <= near / NEAR_SYNTHETIC <= k and 1 / k <= far / FAR_SYNTHETIC <= k:
        return NEAR_SYNTHETIC, FAR_SYNTHETIC, "NeRF-synthetic default (not in the file; the cameras are at its scale)"
    return near, far, ("derived from the cameras (not in the file): 0.5 x nearest and 1.5 x farthest camera distance "
                       "to the point they look at")
