"""A tiny analytic scene for tests and demos: three Lambertian spheres, rendered exactly.

The object is three spheres of different colours (positions jittered by ``seed``) lit by a fixed
directional light plus ambient light, on a transparent background. Each pixel is supersampled
2x2 with exact ray-sphere intersections, so alpha is the covered fraction of the pixel and RGB is
the mean colour of the covered samples (straight alpha). Cameras sit on the upper hemisphere at
radius 4, looking at the origin, on two Fibonacci spirals with different offsets (train, test).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from nerfmeta.data.write import write_blender_scene
from nerfmeta.render.cameras import fibonacci_directions, look_at
from nerfmeta.render.rays import camera_rays

CAMERA_RADIUS = 4.0
CAMERA_ANGLE_X = 0.7
NEAR = 2.0
FAR = 6.0
CATEGORY = "spheres"
# centre xyz, radius, RGB albedo
_BASE_SPHERES = (
    ((0.0, 0.0, 0.0), 0.6, (0.85, 0.25, 0.2)),
    ((0.55, -0.45, -0.25), 0.35, (0.25, 0.75, 0.3)),
    ((-0.45, 0.5, 0.3), 0.3, (0.25, 0.4, 0.9)),
)
_LIGHT = (0.4, 0.3, 0.866)
_AMBIENT = 0.25
_SUBSAMPLES = (0.25, 0.75)


def tiny_spheres(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The spheres of the tiny scene.

    Returns:
        centres (3, 3), radii (3,), albedo (3, 3), float64; centres jittered by up to 0.1 per
        axis with a generator seeded by ``seed``.
    """
    gen = torch.Generator().manual_seed(seed)
    centres = torch.tensor([s[0] for s in _BASE_SPHERES], dtype=torch.float64)
    centres = centres + (torch.rand(centres.shape, generator=gen, dtype=torch.float64) - 0.5) * 0.2
    radii = torch.tensor([s[1] for s in _BASE_SPHERES], dtype=torch.float64)
    albedo = torch.tensor([s[2] for s in _BASE_SPHERES], dtype=torch.float64)
    return centres, radii, albedo


def render_spheres(
    origins: torch.Tensor,
    directions: torch.Tensor,
    centres: torch.Tensor,
    radii: torch.Tensor,
    albedo: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Shade rays against spheres: Lambert + ambient under a fixed light, nearest hit wins.

    Args:
        origins: (..., 3) ray origins.
        directions: (..., 3) unit directions.
        centres: (k, 3); radii: (k,); albedo: (k, 3) RGB in [0, 1].

    Returns:
        rgb (..., 3) in [0, 1] (0 where nothing is hit) and hit (...) bool.
    """
    oc = origins.unsqueeze(-2) - centres  # (..., k, 3)
    b = (directions.unsqueeze(-2) * oc).sum(-1)
    c = (oc * oc).sum(-1) - radii**2
    disc = b * b - c
    t = -b - torch.sqrt(torch.clamp(disc, min=0.0))
    valid = (disc >= 0) & (t > 0)
    t = torch.where(valid, t, torch.full_like(t, math.inf))
    t_hit, idx = t.min(dim=-1)
    hit = torch.isfinite(t_hit)
    t_safe = torch.where(hit, t_hit, torch.zeros_like(t_hit))
    points = origins + t_safe.unsqueeze(-1) * directions
    normals = (points - centres[idx]) / radii[idx].unsqueeze(-1)
    light = torch.tensor(_LIGHT, dtype=origins.dtype)
    light = light / torch.linalg.vector_norm(light)
    shade = _AMBIENT + (1.0 - _AMBIENT) * torch.clamp((normals * light).sum(-1), min=0.0)
    rgb = albedo[idx] * shade.unsqueeze(-1)
    return torch.where(hit.unsqueeze(-1), rgb, torch.zeros_like(rgb)), hit


def tiny_cameras(
    n: int,
    offset: float,
    size: int,
    *,
    height: int | None = None,
    radius: float = CAMERA_RADIUS,
    angle_x: float = CAMERA_ANGLE_X,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses (n, 4, 4) float64 on the upper hemisphere looking at the origin, and intrinsics (4,).

    Args:
        n: number of cameras; offset: the Fibonacci spiral's offset.
        size: image width in pixels; height: image height (default: ``size``).
        radius: distance of the cameras from the origin.
        angle_x: horizontal field of view in radians (``fx = fy``, principal point at the centre).
    """
    height = size if height is None else height
    eyes = radius * fibonacci_directions(n, offset=offset)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    poses = look_at(eyes, torch.zeros(3, dtype=torch.float64), up)
    focal = 0.5 * size / math.tan(0.5 * angle_x)
    intrinsics = torch.tensor([focal, focal, size / 2, height / 2], dtype=torch.float64)
    return poses, intrinsics


def render_views(
    poses: torch.Tensor, intrinsics: torch.Tensor, size: int, seed: int, *, height: int | None = None
) -> np.ndarray:
    """(n, height, size, 4) uint8 RGBA renders of the spheres, 2x2 supersampled.

    Args:
        poses: (n, 4, 4) camera-to-world; intrinsics: (4,) or (n, 4).
        size: image width in pixels; height: image height (default: ``size``).
        seed: jitters the sphere positions (:func:`tiny_spheres`).
    """
    height = size if height is None else height
    centres, radii, albedo = tiny_spheres(seed)
    sub = torch.tensor(_SUBSAMPLES, dtype=torch.float64)
    ys = (torch.arange(height, dtype=torch.float64)[:, None] + sub[None, :]).reshape(-1)  # (2 height,) sample rows
    xs = (torch.arange(size, dtype=torch.float64)[:, None] + sub[None, :]).reshape(-1)  # (2 size,) sample columns
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    pixels = torch.stack([xx, yy], dim=-1)  # (2 height, 2 size, 2)
    intr = intrinsics if intrinsics.dim() == 1 else intrinsics[:, None, None]
    origins, dirs = camera_rays(poses[:, None, None], intr, pixels)
    rgb, hit = render_spheres(origins, dirs, centres, radii, albedo)
    n = len(poses)
    rgb = rgb.reshape(n, height, 2, size, 2, 3).sum(dim=(2, 4))
    count = hit.reshape(n, height, 2, size, 2).sum(dim=(2, 4)).to(torch.float64)
    colour = rgb / count.clamp(min=1.0).unsqueeze(-1)
    alpha = count / 4.0
    rgba = torch.cat([colour, alpha.unsqueeze(-1)], dim=-1)
    return np.round(rgba.numpy() * 255.0).clip(0, 255).astype(np.uint8)


def tiny_aabb(seed: int = 0, pad: float = 0.05) -> list[list[float]]:
    """The box around the spheres (padded by ``pad``) as ``[[min xyz], [max xyz]]``."""
    centres, radii, _ = tiny_spheres(seed)
    lo = (centres - radii[:, None]).amin(0) - pad
    hi = (centres + radii[:, None]).amax(0) + pad
    return [[round(float(v), 6) for v in lo], [round(float(v), 6) for v in hi]]


def write_tiny_scene(
    folder: str | os.PathLike,
    *,
    n_train: int = 8,
    n_test: int = 4,
    size: int = 32,
    seed: int = 0,
    height: int | None = None,
    angle_x: float = CAMERA_ANGLE_X,
) -> Path:
    """Write the tiny analytic scene in the Blender format and return its folder.

    Deterministic: the same arguments give byte-identical files. ``near``/``far`` are 2 and 6, the
    ``aabb`` is the padded box around the spheres and ``category`` is ``"spheres"``.

    Args:
        folder: destination (created).
        n_train: training views (>= 1).
        n_test: test views (>= 0; with 0 no ``transforms_test.json`` is written).
        size: image width (and, unless ``height`` is given, height) in pixels.
        seed: jitters the sphere positions.
        height: image height in pixels when it differs from the width.
        angle_x: horizontal field of view in radians (0 < angle_x < pi).
    """
    height = size if height is None else height
    if n_train < 1 or n_test < 0 or size < 1 or height < 1:
        raise ValueError(f"need n_train >= 1, n_test >= 0, size >= 1, height >= 1; got {n_train}, {n_test}, {size}, {height}")
    if not 0.0 < angle_x < math.pi:
        raise ValueError(f"angle_x must be in (0, pi) radians, got {angle_x}")
    splits = {}
    for split, n, offset in (("train", n_train, 0.5), ("test", n_test, 0.2)):
        if n == 0:
            continue
        poses, intrinsics = tiny_cameras(n, offset, size, height=height, angle_x=angle_x)
        splits[split] = (render_views(poses, intrinsics, size, seed, height=height), poses)
    extra = {"near": NEAR, "far": FAR, "category": CATEGORY, "aabb": tiny_aabb(seed)}
    write_blender_scene(folder, splits, angle_x, extra=extra)
    return Path(folder)
