"""Normalised device coordinates (NDC) for forward-facing scenes (NeRF, Mildenhall et al. 2020, appendix C).

A forward-facing capture sees a scene that may go on for ever behind its subject. NDC is the
projective map of the reference camera's frustum (near plane ``z = -n`` to infinity, looking along
-z) onto a box: ``x' = -(2 f_x / W) x / z``, ``y' = -(2 f_y / H) y / z``, ``z' = 1 + 2 n / z``.
The near plane goes to ``z' = -1`` and infinity to ``z' = +1``; ``z'`` is linear in disparity, so
samples spaced evenly in NDC are dense near the cameras and sparse far away, as the image
resolution asks. Straight lines stay straight: a ray ``o + t d`` (started on the near plane) is
``o' + t' d'`` with ``t'`` in ``[0, 1]`` covering near plane to infinity (:func:`ndc_rays`).

nerfmeta's rays keep unit directions (:class:`~nerfmeta.data.scene.RayBatch`), so a ray in NDC is
``o' + s u`` with ``u = d' / |d'|`` and ``s`` in ``[0, |d'|]`` (:func:`to_ndc`); the estimator's step
and the renderer's ``delta`` are then NDC lengths, and the colour's view direction is ``u``.

Before the map the scene is moved LLFF's way (:class:`NDCSpace`): into the frame of the average
camera (:func:`average_pose`, LLFF's ``poses_avg``) and scaled so the scene's near distance sits at
``1 / near_factor`` (NeRF's ``bd_factor = 0.75``) in front of the near plane ``n = 1``, so the
near plane is at ``near_factor`` x the scene's near bound. Optionally the
NDC depth axis is scaled by ``depth_scale`` (< 1: a grid of cubic voxels then has more voxels across
than in depth, as DirectVoxGO's LLFF grids do).

Pure functions: tensors in, tensors out; dtype and device follow the inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from nerfmeta.render.rays import camera_rays

MIN_FORWARD = 0.1
"""Smallest cosine between a pixel ray and the reference camera's axis that NDC takes (84 degrees)."""
BD_FACTOR = 0.75
"""NeRF's LLFF setting: the scene's near distance is scaled to ``1 / BD_FACTOR`` in front of the near plane
(the near plane sits at 0.75 x the scene's near bound). Runs record their own factor
(``RunConfig.ndc_near_factor``); runs saved before it was recorded used this one."""
NEAR_FACTOR = 0.9
"""The near plane a fit uses by default (``RunConfig.ndc_near_factor``, :func:`~nerfmeta.fit.sampler.fit_space`), as a
fraction of the scene's near bound: 0.9 beat NeRF's 0.75 on the generated forward scenes at equal steps (BENCHMARKS.md,
forward-facing scenes). :func:`ndc_space` itself keeps NeRF's :data:`BD_FACTOR` as its default."""


def ndc_rays(
    origins: torch.Tensor,
    directions: torch.Tensor,
    focal: float,
    width: float,
    height: float,
    near: float = 1.0,
    focal_y: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of the camera frame (looking along -z) in NDC (NeRF's appendix C).

    The origin is first moved along its ray onto the near plane ``z = -near``; then
    ``o' = (-a_x o_x / o_z, -a_y o_y / o_z, 1 + 2 near / o_z)`` and
    ``d' = (-a_x (d_x / d_z - o_x / o_z), -a_y (d_y / d_z - o_y / o_z), -2 near / o_z)`` with
    ``a_x = 2 f_x / W``, ``a_y = 2 f_y / H``, so ``o' + t d'`` for ``t`` in [0, 1) is the ray from the near
    plane to infinity.

    Args:
        origins: (..., 3) ray origins in the camera frame.
        directions: (..., 3) directions (any length), ``d_z < 0`` (rays going forward).
        focal: focal length ``f_x`` in pixels; ``focal_y`` defaults to it.
        width, height: image size in pixels.
        near: distance of the near plane (NeRF: 1).

    Returns:
        origins (..., 3) and directions (..., 3) in NDC (directions not normalised).
    """
    fy = focal if focal_y is None else focal_y
    ax, ay = 2.0 * focal / width, 2.0 * fy / height
    t = -(near + origins[..., 2]) / directions[..., 2]
    o = origins + t[..., None] * directions
    ox, oy, oz = o.unbind(-1)
    dx, dy, dz = directions.unbind(-1)
    o_ndc = torch.stack([-ax * ox / oz, -ay * oy / oz, 1.0 + 2.0 * near / oz], -1)
    d_ndc = torch.stack([-ax * (dx / dz - ox / oz), -ay * (dy / dz - oy / oz), -2.0 * near / oz], -1)
    return o_ndc, d_ndc


def ndc_z_to_camera_z(z_ndc: torch.Tensor, near: float = 1.0) -> torch.Tensor:
    """Camera-frame ``z`` (negative in front) of NDC depths ``z'`` (...) in [-1, 1]: ``z = 2 near / (z' - 1)``.

    ``z' = 1`` (infinity) gives ``-inf``.
    """
    return 2.0 * near / (z_ndc - 1.0)


def average_pose(poses: torch.Tensor) -> torch.Tensor:
    """(4, 4) the mean camera of (n, 4, 4) camera-to-world poses (LLFF's ``poses_avg``).

    Centre: the mean centre. Back axis: the normalised sum of the back (z) axes; right axis: the
    summed up (y) axes crossed with it; up: back x right. Orthonormal, in the dtype of ``poses``.
    """
    centre = poses[:, :3, 3].mean(0)
    back = poses[:, :3, 2].sum(0)
    back = back / torch.linalg.vector_norm(back)
    right = torch.linalg.cross(poses[:, :3, 1].sum(0), back, dim=-1)
    right = right / torch.linalg.vector_norm(right)
    up = torch.linalg.cross(back, right, dim=-1)
    out = torch.eye(4, dtype=poses.dtype, device=poses.device)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, up, back, centre
    return out


@dataclass(frozen=True)
class NDCSpace:
    """Where a forward-facing scene's rays are taken to before the NDC map, and the map's camera.

    A world point ``x`` (the scene's loaded frame) goes to the reference frame as
    ``scale * R^T (x - c)`` (``R``, ``c``: rotation and centre of ``reference``), then to NDC by
    the reference camera (:func:`ndc_rays` with ``near = 1``), then its depth is multiplied by
    ``depth_scale``.

    Attributes:
        reference: (4, 4) float64 camera-to-world of the reference camera (the average camera).
        scale: world-to-reference length factor (the scene's near distance goes to ``1 / near_factor``).
        focal_x, focal_y: the reference camera's focal lengths in pixels.
        width, height: its image size in pixels.
        depth_scale: factor on the NDC depth axis (the box's depth then spans ``[-depth_scale, depth_scale]``).
        near_factor: the near plane's distance as a fraction of the scene's near bound (NeRF's ``bd_factor``).
    """

    reference: torch.Tensor
    scale: float
    focal_x: float
    focal_y: float
    width: int
    height: int
    depth_scale: float = 1.0
    near_factor: float = BD_FACTOR

    @property
    def scene_near(self) -> float:
        """The scene's near bound (world units) the space was made from; the near plane is at ``near_factor`` x it."""
        return 1.0 / (self.scale * self.near_factor)

    def as_json(self) -> dict:
        return {"reference": self.reference.tolist(), "scale": self.scale, "focal": [self.focal_x, self.focal_y],
                "image": [self.width, self.height], "depth_scale": self.depth_scale, "near_factor": self.near_factor}


def ndc_space(poses: torch.Tensor, intrinsics: torch.Tensor, height: int, width: int, near: float,
              depth_scale: float = 1.0, near_factor: float = BD_FACTOR) -> NDCSpace:
    """The NDC space of a forward-facing scene (see :class:`NDCSpace`).

    Args:
        poses: (n, 4, 4) camera-to-world.
        intrinsics: (n, 4) ``(fx, fy, cx, cy)``; the first view's focal lengths are the reference camera's.
        near: the scene's near distance (world units), scaled to ``1 / near_factor``.
        near_factor: in (0, 1]: the near plane's distance as a fraction of ``near`` (NeRF: 0.75).
    """
    if near <= 0:
        raise ValueError(f"NDC needs a positive near distance, got {near}")
    if not 0.0 < near_factor <= 1.0:
        raise ValueError(f"NDC near factor must be in (0, 1], got {near_factor}")
    fx, fy = float(intrinsics[0, 0]), float(intrinsics[0, 1])
    return NDCSpace(average_pose(poses.double()), 1.0 / (near_factor * near), fx, fy, int(width), int(height),
                    float(depth_scale), float(near_factor))


def to_reference(space: NDCSpace, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3) world rays -> the reference frame: origins scaled by ``space.scale``, directions rotated only."""
    ref = space.reference.to(origins)
    rot, centre = ref[:3, :3], ref[:3, 3]
    return (origins - centre) @ rot * space.scale, directions @ rot


def to_ndc(space: NDCSpace, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World rays (n, 3) each -> NDC origins (n, 3), unit NDC directions (n, 3) and lengths (n,) to infinity.

    The NDC ray is ``o' + s u`` for ``s`` in ``[0, length]`` (near plane to infinity).
    """
    o, d = to_reference(space, origins, directions)
    o, d = ndc_rays(o, d, space.focal_x, space.width, space.height, 1.0, space.focal_y)
    if space.depth_scale != 1.0:
        depth = torch.tensor([1.0, 1.0, space.depth_scale], dtype=o.dtype, device=o.device)
        o, d = o * depth, d * depth
    length = torch.linalg.vector_norm(d, dim=-1)
    return o, d / length[:, None], length


def metric_depth(space: NDCSpace, origins: torch.Tensor, directions: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """Distances (n,) along NDC rays back to distances along the world rays (world units; ``inf`` at infinity).

    Args:
        origins, directions: (n, 3) the *world* rays (unit directions) the NDC rays were made from.
        depth: (n,) distance along the unit NDC ray (a rendered depth).
    """
    o_ndc, u, _ = to_ndc(space, origins, directions)
    z_ndc = (o_ndc[:, 2] + depth * u[:, 2]) / space.depth_scale
    z_ref = ndc_z_to_camera_z(z_ndc.clamp(max=1.0))
    o_ref, d_ref = to_reference(space, origins, directions)
    return (z_ref - o_ref[:, 2]) / (space.scale * d_ref[:, 2])


def ndc_box(space: NDCSpace, poses: torch.Tensor, intrinsics: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(2, 3) the box holding every pixel ray of every view from the near plane to infinity, in NDC.

    Each view's frustum maps to a convex set whose corners are the images of its four corner rays at
    the near plane and at infinity (a projective map keeps lines and convexity), so their extremes
    bound it (DirectVoxGO takes the box of its NDC rays' end points the same way).

    Raises:
        ValueError: a corner ray is more than ``acos(MIN_FORWARD)`` (84 degrees) off the reference axis;
            NDC cannot hold it (it meets the near plane far outside the frustum, or never).
    """
    corners = torch.tensor([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]], dtype=torch.float64)
    o, d = camera_rays(poses.double()[:, None], intrinsics.double()[:, None], corners.expand(len(poses), 4, 2))
    forward = float(-(d.reshape(-1, 3) @ space.reference[:3, 2]).max())  # least cosine to the viewing axis
    if forward < MIN_FORWARD:
        raise ValueError(f"an image corner looks {math.degrees(math.acos(max(-1.0, min(1.0, forward)))):.0f} deg away "
                         "from the average camera's axis: NDC needs every ray to go forward")
    o_ndc, u, length = to_ndc(space, o.reshape(-1, 3), d.reshape(-1, 3))
    ends = torch.cat([o_ndc, o_ndc + u * length[:, None]])
    lo, hi = ends.amin(0), ends.amax(0)
    lo[2], hi[2] = -space.depth_scale, space.depth_scale
    return torch.stack([lo, hi])
