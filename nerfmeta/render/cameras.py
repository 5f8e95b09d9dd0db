"""Camera poses: look-at matrices and view directions on a sphere (pure functions)."""

from __future__ import annotations

import math

import torch


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """Camera-to-world matrices (OpenGL convention) of cameras at ``eye`` looking at ``target``.

    Args:
        eye: (..., 3) camera centres.
        target: (..., 3) points looked at (broadcast against ``eye``).
        up: (..., 3) world up; must not be parallel to the viewing direction.

    Returns:
        (..., 4, 4) camera-to-world matrices whose -z axis points from ``eye`` to ``target``.
    """
    eye, target, up = torch.broadcast_tensors(eye, target, up)
    back = eye - target
    back = back / torch.linalg.vector_norm(back, dim=-1, keepdim=True)
    right = torch.linalg.cross(up, back, dim=-1)
    norm = torch.linalg.vector_norm(right, dim=-1, keepdim=True)
    if bool((norm < 1e-8).any()):
        raise ValueError("look_at: 'up' is parallel to the viewing direction")
    right = right / norm
    true_up = torch.linalg.cross(back, right, dim=-1)
    c2w = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype, device=eye.device)
    c2w[..., :3, 0] = right
    c2w[..., :3, 1] = true_up
    c2w[..., :3, 2] = back
    c2w[..., :3, 3] = eye
    c2w[..., 3, 3] = 1.0
    return c2w


def spherical_directions(azimuth: torch.Tensor, elevation: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit vectors, z up: azimuth around z from +x, elevation above the xy-plane (radians)."""
    ce = torch.cos(elevation)
    return torch.stack([ce * torch.cos(azimuth), ce * torch.sin(azimuth), torch.sin(elevation)], dim=-1)


def fibonacci_directions(n: int, *, upper_only: bool = True, offset: float = 0.5, dtype=torch.float64) -> torch.Tensor:
    """(n, 3) near-uniform unit vectors (z up) on the upper hemisphere or the full sphere.

    A deterministic spiral; ``offset`` in (0, 1) shifts the spiral so two calls with different
    offsets give disjoint direction sets (train vs test views).
    """
    i = torch.arange(n, dtype=dtype) + offset
    z = 1.0 - i / n if upper_only else 1.0 - 2.0 * i / n
    golden = math.pi * (3.0 - math.sqrt(5.0))
    phi = golden * i
    r = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)
