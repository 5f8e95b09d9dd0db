"""Camera paths for videos of a fitted scene (pure functions over camera-to-world poses).

Every pose is a (4, 4) OpenGL camera-to-world matrix (x right, y up, looking along -z), as in
:class:`~nerfmeta.data.scene.Scene`. The paths are made from the training cameras:

- :func:`orbit_path`: a circle around the point the cameras look at (:func:`look_at_centre`), at
  the cameras' mean height and distance, about the axis of their ring (:func:`orbit_up`); every
  frame looks at that point. For cameras around an object.
- :func:`spiral_path`: LLFF's spiral around the mean pose (:func:`mean_pose`), with radii from the
  spread of the camera centres, every frame looking at a point ``focus_depth`` ahead of the mean
  pose. For forward-facing captures.

- :func:`walk_path`: along the training cameras in their order, smoothed (a video's own walk). For
  unbounded captures, where the fit knows the background only from where the camera went.

Which one a video of a scene follows by default is decided by its kind of capture
(:mod:`nerfmeta.data.scene_type`): spiral for forward-facing; walk for an unbounded capture whose
cameras form a walk (:func:`is_walk`); orbit otherwise.
"""

from __future__ import annotations

import math

import torch

from nerfmeta.data.scene_type import axis_normal_equations, view_directions
from nerfmeta.render.cameras import look_at

def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-12)


def mean_up(poses: torch.Tensor) -> torch.Tensor:
    """(3,) the normalised mean of the cameras' up (y) axes; poses: (n, 4, 4)."""
    return _unit(poses[:, :3, 1].mean(0))


def orbit_up(poses: torch.Tensor) -> torch.Tensor:
    """(3,) the axis an orbit turns about: the normal of the plane that best fits the camera centres
    (a ring's, or a dome's base), on the side of :func:`mean_up`; :func:`mean_up` itself when the
    centres lie on a line (no plane). A part of a ring gives the ring's axis, which the mean of
    the tilted camera up vectors would not."""
    up = mean_up(poses)
    centred = poses[:, :3, 3] - poses[:, :3, 3].mean(0)
    if len(poses) < 3:
        return up
    _, sizes, vt = torch.linalg.svd(centred, full_matrices=False)
    if float(sizes[1]) <= 1e-6 * float(sizes[0]):
        return up
    normal = _unit(vt[-1])
    return normal if float(normal @ up) >= 0 else -normal


def look_at_centre(poses: torch.Tensor) -> torch.Tensor:
    """(3,) the point nearest (least squares) to every camera's optical axis; poses: (n, 4, 4).

    Raises:
        ValueError: the axes are (nearly) parallel, so they share no such point.
    """
    a, b = axis_normal_equations(poses[:, :3, 3], view_directions(poses).to(poses.dtype))
    if float(torch.linalg.eigvalsh(a).min()) < 1e-3 * len(poses):
        raise ValueError("the cameras' optical axes are parallel: they look at no common point")
    return torch.linalg.solve(a, b)


def orbit_path(poses: torch.Tensor, n_frames: int, *, centre: torch.Tensor | None = None) -> torch.Tensor:
    """(n_frames, 4, 4) cameras on a circle around ``centre`` (default :func:`look_at_centre`), all looking at it.

    The circle lies in the plane square to :func:`orbit_up` at the cameras' mean height above the
    centre, with their mean horizontal distance as radius; it starts at the first camera's
    azimuth and turns once (the last frame is one step short of the first).
    """
    centre = look_at_centre(poses) if centre is None else centre
    up = orbit_up(poses)
    offsets = poses[:, :3, 3] - centre
    heights = offsets @ up
    flat = offsets - heights[:, None] * up
    radius = torch.linalg.vector_norm(flat, dim=-1).mean()
    x_axis = _unit(flat[0])
    if float(torch.linalg.vector_norm(flat[0])) < 1e-9:  # first camera right above the centre: any horizontal axis
        x_axis = _unit(torch.linalg.cross(up, torch.eye(3, dtype=poses.dtype)[int(torch.argmin(up.abs()))], dim=-1))
    y_axis = torch.linalg.cross(up, x_axis, dim=-1)
    angles = torch.arange(n_frames, dtype=poses.dtype) * (2 * math.pi / n_frames)
    eyes = centre + radius * (torch.cos(angles)[:, None] * x_axis + torch.sin(angles)[:, None] * y_axis) + heights.mean() * up
    return look_at(eyes, centre.expand_as(eyes), up.expand_as(eyes))


def mean_pose(poses: torch.Tensor) -> torch.Tensor:
    """(4, 4) the average camera: mean centre, mean viewing direction, mean up made square to it."""
    back = _unit(poses[:, :3, 2].mean(0))
    right = _unit(torch.linalg.cross(mean_up(poses), back, dim=-1))
    pose = torch.eye(4, dtype=poses.dtype, device=poses.device)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = right, torch.linalg.cross(back, right, dim=-1), back
    pose[:3, 3] = poses[:, :3, 3].mean(0)
    return pose


def spiral_path(poses: torch.Tensor, n_frames: int, focus_depth: float, *, rotations: float = 2.0,
                radius_percentile: float = 90.0) -> torch.Tensor:
    """(n_frames, 4, 4) LLFF's spiral: cameras around :func:`mean_pose`, all looking at the point
    ``focus_depth`` in front of it.

    Radii along the mean pose's x, y and z are the ``radius_percentile`` of the camera centres'
    distances from the mean centre along those axes; the spiral makes ``rotations`` turns in x-y
    while moving back and forth in z, so every frame stays within those radii of the mean pose.
    """
    centre_pose = mean_pose(poses)
    rot = centre_pose[:3, :3]
    local = (poses[:, :3, 3] - centre_pose[:3, 3]) @ rot  # camera centres in the mean pose's frame
    radii = torch.quantile(local.abs(), radius_percentile / 100.0, dim=0)
    t = torch.arange(n_frames, dtype=poses.dtype) * (2 * math.pi * rotations / n_frames)
    offsets = torch.stack([torch.cos(t) * radii[0], -torch.sin(t) * radii[1], -torch.sin(0.5 * t) * radii[2]], -1)
    eyes = centre_pose[:3, 3] + offsets @ rot.T
    target = centre_pose[:3, 3] - focus_depth * rot[:, 2]
    return look_at(eyes, target.expand_as(eyes), rot[:, 1].expand_as(eyes))


def nearest_rotation(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) the rotation nearest each ``m`` in the Frobenius norm (its polar factor, via the SVD)."""
    u, _, vt = torch.linalg.svd(m)
    d = torch.linalg.det(u @ vt)
    fix = torch.ones_like(m[..., 0, :])
    fix[..., 2] = d  # flip the last singular direction where the product is a reflection
    return u @ torch.diag_embed(fix) @ vt


TAUBIN_STEPS = (0.5, -0.53)
"""Taubin's smoothing (1995): a step towards the neighbours' mean, then a slightly larger one back. Shake from
one camera to the next is taken out; a smooth curve keeps its size (plain averaging pulls an orbit inwards)."""


def smooth_keys(poses: torch.Tensor, passes: int) -> torch.Tensor:
    """(n, 4, 4) ``poses`` smoothed by ``passes`` of :data:`TAUBIN_STEPS` over their neighbours (centres and
    rotations; rotations projected back with :func:`nearest_rotation`); the first and last are kept. Takes out
    a hand's shake."""
    out = poses.clone()
    for _ in range(passes if len(poses) > 2 else 0):
        for step in TAUBIN_STEPS:
            mid = out[1:-1] + step * (0.5 * (out[:-2] + out[2:]) - out[1:-1])
            out[1:-1, :3, 3] = mid[:, :3, 3]
            out[1:-1, :3, :3] = nearest_rotation(mid[:, :3, :3])
    return out


def walk_path(poses: torch.Tensor, n_frames: int, *, smooth: int = 2) -> torch.Tensor:
    """(n_frames, 4, 4) cameras along the walk the training cameras took, in their order (a video's own path).

    The cameras are first smoothed (:func:`smooth_keys`, ``smooth`` passes); the frames are spread evenly over
    the walk's steps, centres on a Catmull-Rom spline through the cameras' centres, rotations blended between
    neighbouring cameras (chordal, :func:`nearest_rotation`). Frames stay where the capture looked from, so a
    video of an unbounded scene shows what the fit saw. With ``smooth=0`` and ``n_frames = k (n - 1) + 1``
    every k-th frame is a training camera exactly.
    """
    if len(poses) < 2:
        raise ValueError("a walk needs at least two cameras")
    keys = smooth_keys(poses, smooth)
    t = torch.linspace(0, len(keys) - 1, n_frames, dtype=poses.dtype)
    i = t.floor().long().clamp(max=len(keys) - 2)
    f = (t - i)[:, None]
    last = len(keys) - 1
    p0, p1, p2, p3 = (keys[(i + k).clamp(0, last), :3, 3] for k in (-1, 0, 1, 2))
    f2, f3 = f * f, f * f * f
    centres = 0.5 * (2 * p1 + (p2 - p0) * f + (2 * p0 - 5 * p1 + 4 * p2 - p3) * f2 + (3 * p1 - p0 - 3 * p2 + p3) * f3)
    blend = (1 - f)[:, :, None] * keys[i, :3, :3] + f[:, :, None] * keys[i + 1, :3, :3]
    out = torch.eye(4, dtype=poses.dtype).repeat(n_frames, 1, 1)
    out[:, :3, :3] = nearest_rotation(blend)
    out[:, :3, 3] = centres
    return out


def is_walk(poses: torch.Tensor) -> bool:
    """Whether the cameras, in their order, form a walk with no jump (:func:`nerfmeta.data.sfm.walk_jumps`)."""
    from nerfmeta.data.sfm import is_walk as rotations_walk, walk_jumps

    rotations = poses[:, :3, :3].double().cpu().numpy()
    return rotations_walk(rotations) and not walk_jumps(rotations)


def focus_depth(near: float, far: float) -> float:
    """LLFF's depth the spiral looks at: the harmonic blend ``1 / (0.25 / near + 0.75 / far)``."""
    return 1.0 / (0.25 / near + 0.75 / far)
