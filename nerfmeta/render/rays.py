"""Camera rays and ray/box intersection.

Pure functions: tensors in, tensors out; device and dtype follow the inputs.
Camera convention is OpenGL/Blender (x right, y up, looking along -z), pixel centres at
``(i + 0.5, j + 0.5)`` for column ``i`` and row ``j``.
"""

from __future__ import annotations

import torch


def pixel_directions_camera(
    intrinsics: torch.Tensor, pixels: torch.Tensor
) -> torch.Tensor:
    """Un-normalised camera-space directions through pixel positions.

    Args:
        intrinsics: (..., 4) ``(fx, fy, cx, cy)``, broadcastable against ``pixels[..., 0]``.
        pixels: (..., 2) pixel coordinates ``(x, y)`` in pixels (use ``i + 0.5`` for centres).

    Returns:
        (..., 3) directions with z = -1.
    """
    fx, fy, cx, cy = intrinsics.unbind(-1)
    x = (pixels[..., 0] - cx) / fx
    y = -(pixels[..., 1] - cy) / fy
    return torch.stack([x, y, -torch.ones_like(x)], dim=-1)


def camera_rays(
    c2w: torch.Tensor, intrinsics: torch.Tensor, pixels: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays through pixel positions.

    Args:
        c2w: (..., 4, 4) or (..., 3, 4) camera-to-world matrices.
        intrinsics: (..., 4) ``(fx, fy, cx, cy)``.
        pixels: (..., 2) pixel coordinates ``(x, y)``.

    Returns:
        origins (..., 3) and unit directions (..., 3).
    """
    d_cam = pixel_directions_camera(intrinsics, pixels)
    rot = c2w[..., :3, :3]
    d_world = (rot @ d_cam.unsqueeze(-1)).squeeze(-1)
    d_world = d_world / torch.linalg.vector_norm(d_world, dim=-1, keepdim=True)
    origins = c2w[..., :3, 3].expand_as(d_world)
    return origins, d_world


def pixel_grid(height: int, width: int, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H, W, 2) pixel-centre coordinates ``(x, y)`` for an image of ``height`` x ``width``."""
    ys = torch.arange(height, device=device, dtype=dtype) + 0.5
    xs = torch.arange(width, device=device, dtype=dtype) + 0.5
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx, yy], dim=-1)


def image_rays(
    c2w: torch.Tensor, intrinsics: torch.Tensor, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """All pixel-centre rays of one camera.

    Args:
        c2w: (4, 4) camera-to-world.
        intrinsics: (4,) ``(fx, fy, cx, cy)``.

    Returns:
        origins (H, W, 3) and unit directions (H, W, 3).
    """
    pix = pixel_grid(height, width, device=c2w.device, dtype=c2w.dtype)
    return camera_rays(c2w, intrinsics, pix)


def frustum_corners(
    c2w: torch.Tensor, intrinsics: torch.Tensor, height: int, width: int, depth: torch.Tensor | float
) -> torch.Tensor:
    """World positions of the four image corners at a distance along each corner ray.

    Args:
        c2w: (..., 4, 4) camera-to-world.
        intrinsics: (..., 4) ``(fx, fy, cx, cy)``.
        depth: distance along the (unit) corner rays; scalar or (...,).

    Returns:
        (..., 4, 3) corners in the order top-left, top-right, bottom-right, bottom-left.
    """
    corners = torch.tensor(
        [[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]], dtype=c2w.dtype, device=c2w.device
    )
    batch = c2w.shape[:-2]
    pix = corners.expand(*batch, 4, 2)
    o, d = camera_rays(c2w.unsqueeze(-3), intrinsics.unsqueeze(-2), pix)
    depth = torch.as_tensor(depth, dtype=c2w.dtype, device=c2w.device)
    if depth.dim() > 0:
        depth = depth[..., None, None]
    return o + depth * d


def intersect_aabb(
    origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab-method intersection of rays with an axis-aligned box.

    Exact for axis-aligned directions: a zero direction component never divides; that axis
    is a hit for all t when the origin lies within the slab and a miss otherwise.

    Args:
        origins: (n, 3).
        directions: (n, 3), need not be unit.
        aabb: (2, 3) ``[min_xyz, max_xyz]``.

    Returns:
        t_enter (n,), t_exit (n,), hit (n,) bool. ``t_enter`` may be negative when the origin is
        inside the box; for a miss both are 0 and ``hit`` is False.
    """
    lo, hi = aabb[0], aabb[1]
    zero = directions == 0
    safe = torch.where(zero, torch.ones_like(directions), directions)
    t0 = (lo - origins) / safe
    t1 = (hi - origins) / safe
    t_near = torch.minimum(t0, t1)
    t_far = torch.maximum(t0, t1)
    inside = (origins >= lo) & (origins <= hi)
    inf = torch.full_like(t_near, float("inf"))
    t_near = torch.where(zero, torch.where(inside, -inf, inf), t_near)
    t_far = torch.where(zero, torch.where(inside, inf, -inf), t_far)
    t_enter = t_near.amax(dim=-1)
    t_exit = t_far.amin(dim=-1)
    hit = (t_enter <= t_exit) & torch.isfinite(t_enter) & torch.isfinite(t_exit)
    zeros = torch.zeros_like(t_enter)
    return torch.where(hit, t_enter, zeros), torch.where(hit, t_exit, zeros), hit


def clip_to_aabb(
    origins: torch.Tensor,
    directions: torch.Tensor,
    near: torch.Tensor,
    far: torch.Tensor,
    aabb: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Clip ``[near, far]`` to the part of each ray inside ``aabb``.

    Returns:
        near (n,), far (n,) with ``far >= near``, and hit (n,) bool; rays that miss the box (or
        meet it only outside ``[near, far]``) get ``near == far`` (a zero-length interval).
    """
    t_in, t_out, hit = intersect_aabb(origins, directions, aabb)
    new_near = torch.maximum(near, t_in)
    new_far = torch.minimum(far, t_out)
    hit = hit & (new_far > new_near)
    new_near = torch.where(hit, new_near, near)
    new_far = torch.where(hit, new_far, near)
    return new_near, new_far, hit
