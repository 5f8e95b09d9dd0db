"""What kind of capture a scene is, read off its cameras and the borders of its images.

Three kinds, each rendered in its own space (see :mod:`nerfmeta.render`):

- ``object``: cameras around (or on an arc in front of) one object on a blank background, or with
  an alpha channel. A bounded box holds everything that matters (NeRF's Blender scenes).
- ``forward``: cameras on a small patch, all looking one way at a scene that may go on for ever
  behind (LLFF captures). Rendered with normalised device coordinates (NeRF, DirectVoxGO).
- ``unbounded``: cameras around an object with a real background (a phone walked around a can
  on a floor). Rendered in a contracted space (mip-NeRF 360, DirectVoxGO v2, nerfacc).

The rule (every threshold below is a named constant):

1. The cameras *look one way* when every viewing direction lies within
   :data:`FORWARD_MAX_ANGLE_DEG` of their mean direction, and *stand on a patch* when the
   camera centres spread (RMS about their mean) less than :data:`FORWARD_MAX_SPREAD` of the
   distance to the point they look at. Both -> ``forward``.
2. Otherwise the cameras are around the content. Images with an alpha channel, or whose border
   pixels are one flat colour across all views (RMS spread below :data:`BLANK_BORDER_STD`),
   are ``object``; any other background is ``unbounded``.

A user can always say which kind a scene is (``--scene-type``); the reason is kept either way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

SCENE_TYPES = ("object", "forward", "unbounded")
"""Every kind of scene, in the order ``--scene-type`` lists them."""
FORWARD_MAX_ANGLE_DEG = 40.0
"""Largest angle between one view direction and the mean one for cameras that look one way."""
FORWARD_MAX_SPREAD = 0.2
"""Largest RMS spread of the camera centres, as a fraction of their distance to the look-at point,
for cameras that stand on a patch."""
BLANK_BORDER_STD = 0.04
"""Largest RMS deviation (RGB in [0, 1]) of the image-border pixels from their median colour for
a background to count as blank."""
BORDER_FRACTION = 0.04
"""Width of the image border sampled, as a fraction of the shorter image side (at least 1 px)."""


@dataclass(frozen=True)
class CameraLayout:
    """How a set of cameras is arranged (all lengths in the scene's units).

    Attributes:
        max_angle_deg: largest angle between a view direction and the mean view direction.
        centre_spread: RMS distance of the camera centres from their mean.
        focus_distance: distance from the mean centre to the point the cameras look at (the
            least-squares nearest point to all optical axes, measured along the mean direction);
            ``inf`` when the axes are parallel or meet behind the cameras.
    """

    max_angle_deg: float
    centre_spread: float
    focus_distance: float

    @property
    def looks_one_way(self) -> bool:
        return self.max_angle_deg <= FORWARD_MAX_ANGLE_DEG

    @property
    def on_a_patch(self) -> bool:
        return self.centre_spread <= FORWARD_MAX_SPREAD * self.focus_distance


@dataclass(frozen=True)
class SceneType:
    """The kind of a scene and why.

    Attributes:
        kind: one of :data:`SCENE_TYPES`.
        reason: one line saying what decided it, for ``inspect`` and ``summary.json``.
        detected: False when the user named the kind.
    """

    kind: str = "object"
    reason: str = "default"
    detected: bool = True

    def __post_init__(self) -> None:
        if self.kind not in SCENE_TYPES:
            raise ValueError(f"scene type must be one of {', '.join(SCENE_TYPES)}, got {self.kind!r}")

    def as_json(self) -> dict:
        return {"kind": self.kind, "reason": self.reason, "detected": self.detected}


def view_directions(poses: torch.Tensor) -> torch.Tensor:
    """(n, 4, 4) camera-to-world (OpenGL: the camera looks along -z) -> (n, 3) unit directions."""
    d = -poses[:, :3, 2].double()
    return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True).clamp_min(1e-12)


def axis_normal_equations(origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(A (3, 3), b (3,))`` with ``A x = b`` the least-squares point nearest every line ``o + t d``.

    Args:
        origins: (n, 3) points on the lines.
        directions: (n, 3) unit directions (same dtype).
    """
    eye = torch.eye(3, dtype=origins.dtype, device=origins.device)
    proj = eye - directions[:, :, None] * directions[:, None, :]  # (n, 3, 3): removes the part along each line
    return proj.sum(0), (proj @ origins[:, :, None]).sum(0)[:, 0]


def focus_point(origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor | None:
    """The point nearest, in least squares, to every line ``o + t d`` (None when they are parallel).

    Args:
        origins: (n, 3) points on the lines.
        directions: (n, 3) unit directions.
    Returns:
        (3,) float64 point, or None when the normal equations are singular to working precision.
    """
    a, b = axis_normal_equations(origins.double(), directions.double())
    eig = torch.linalg.eigvalsh(a)
    if eig[0] <= 1e-6 * eig[-1].clamp_min(1e-300):
        return None
    return torch.linalg.solve(a, b)


def camera_layout(poses: torch.Tensor) -> CameraLayout:
    """Measure how the cameras of ``poses`` (n, 4, 4) are arranged (see :class:`CameraLayout`)."""
    dirs = view_directions(poses)
    centres = poses[:, :3, 3].double()
    mean_dir = dirs.sum(0)
    norm = float(torch.linalg.vector_norm(mean_dir))
    if norm < 1e-9:  # directions cancel: cameras all around
        return CameraLayout(180.0, _rms_spread(centres), math.inf)
    mean_dir = mean_dir / norm
    max_angle = math.degrees(float(torch.arccos((dirs @ mean_dir).clamp(-1.0, 1.0)).max()))
    mean_centre = centres.mean(0)
    point = focus_point(centres, dirs)
    distance = math.inf if point is None else float((point - mean_centre) @ mean_dir)
    if distance <= 0:
        distance = math.inf
    return CameraLayout(max_angle, _rms_spread(centres), distance)


def _rms_spread(points: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(points - points.mean(0), dim=-1).square().mean().sqrt())


def border_width(height: int, width: int, fraction: float = BORDER_FRACTION) -> int:
    """Pixels in a frame ``fraction`` of the shorter image side wide (at least 1)."""
    return max(1, int(round(fraction * min(height, width))))


def border_pixels(images: torch.Tensor, width: int) -> torch.Tensor:
    """(n, H, W, C) images -> (m, C) the pixels within ``width`` pixels of each image's edge."""
    _, h, w, c = images.shape
    edge = torch.zeros(h, w, dtype=torch.bool, device=images.device)
    edge[:width], edge[-width:], edge[:, :width], edge[:, -width:] = True, True, True, True
    return images[:, edge].reshape(-1, c)


def border_spread(images: torch.Tensor) -> float:
    """RMS distance (RGB) of the border pixels of ``images`` (n, H, W, 3) from their median colour."""
    px = border_pixels(images, border_width(images.shape[1], images.shape[2])).double()
    median = px.median(dim=0).values
    return float(torch.linalg.vector_norm(px - median, dim=-1).square().mean().sqrt())


def classify_scene(layout: CameraLayout, *, has_alpha: bool, border_std: float) -> SceneType:
    """The rule of the module docstring, on measured figures (pure)."""
    if layout.looks_one_way and layout.on_a_patch:
        return SceneType(
            "forward",
            f"cameras look one way (all within {layout.max_angle_deg:.0f} deg of their mean direction) "
            f"from a patch (spread {layout.centre_spread:.3g}, {layout.centre_spread / layout.focus_distance:.0%} "
            "of the distance to what they look at)"
            if math.isfinite(layout.focus_distance)
            else f"cameras look one way (all within {layout.max_angle_deg:.0f} deg) along parallel axes",
        )
    around = f"cameras around the content (views up to {layout.max_angle_deg:.0f} deg from their mean direction)"
    if has_alpha:
        return SceneType("object", f"{around}, images with an alpha channel")
    if border_std <= BLANK_BORDER_STD:
        return SceneType("object", f"{around}, blank background (border spread {border_std:.3f})")
    return SceneType("unbounded", f"{around}, a real background (border spread {border_std:.3f})")


def detect_scene_type(
    poses: torch.Tensor, images: torch.Tensor, alphas: torch.Tensor | None, override: str = "auto"
) -> SceneType:
    """The kind of a scene from its cameras and images, or the one the user named.

    Args:
        poses: (n, 4, 4) camera-to-world.
        images: (n, H, W, 3) RGB in [0, 1].
        alphas: (n, H, W) alpha or None.
        override: ``"auto"`` or one of :data:`SCENE_TYPES`.
    """
    if override != "auto":
        if override not in SCENE_TYPES:
            raise ValueError(f"scene type must be auto or one of {', '.join(SCENE_TYPES)}, got {override!r}")
        return SceneType(override, "set by the user", detected=False)
    layout = camera_layout(poses)
    border = 0.0 if alphas is not None else border_spread(images)
    return classify_scene(layout, has_alpha=alphas is not None, border_std=border)
