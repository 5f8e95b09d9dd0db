"""A generated unbounded 360-degree scene in the LLFF format, for tests and benchmarks.

The layout of a phone walked around a subject indoors (mip-NeRF 360's captures, ``../shared``'s beer): a few
textured objects on a tiled floor in the middle of a room with textured walls, photographed from a ring of cameras
around them, every camera looking at the middle. World frame: z up, the floor's top at ``z = 0``, the walls at
``x, y = +-room``. Rendered by the collection's sphere tracer like :mod:`nerfmeta.collection.forward` and written
the same way (``images/`` plus ``poses_bounds.npy``), so it goes through the real loader and is detected as
``unbounded`` (cameras around, a background that is not blank; :mod:`nerfmeta.data.scene_type`). Same config, same
bytes.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfmeta.collection.forward import check_views, layout_offsets, make_llff_folder, object_parts, render_capture
from nerfmeta.collection.shapes import Box, Material, Part, Shape
from nerfmeta.data.blender import focal_from_angle
from nerfmeta.render.cameras import look_at


@dataclass(frozen=True)
class UnboundedSceneConfig:
    """A generated unbounded scene (defaults: 40 views of 160 x 120 on a ring, every 8th held out by the loader)."""

    width: int = 160
    """Image width in pixels."""
    height: int = 120
    """Image height in pixels."""
    fov_degrees: float = 60.0
    """Horizontal field of view."""
    views: int = 40
    """Cameras on the ring, evenly spaced in angle (then jittered)."""
    radius: float = 3.0
    """Radius of the camera ring around the middle of the floor (the objects' centres lie within 1.3 of the middle)."""
    camera_height: float = 0.8
    """Height of the cameras above the floor (they look at a point 0.3 above the middle)."""
    room: float = 8.0
    """Half-side of the room: its walls stand ``room`` from the middle, well beyond the cameras."""
    jitter: float = 0.05
    """Largest random offset of each camera position along each axis, world units (a hand-held walk)."""
    seed: int = 0
    """Seed of the camera jitter."""
    layout_seed: int = 0
    """Seed of the objects' layout (0: the fixed one; see :func:`~nerfmeta.collection.forward.layout_offsets`) and of the walls' texture."""
    supersample: int = 2
    """Anti-aliasing rays per pixel along each axis at edges (see RenderConfig)."""

    def __post_init__(self) -> None:
        check_views("unbounded scene", self.width, self.height, self.fov_degrees)
        if self.views < 3:
            raise ValueError(f"unbounded scene: views must be at least 3, got {self.views}")
        if not (2.0 <= self.radius and 0.2 <= self.camera_height <= 3.0 and self.room >= self.radius + 2.0
                and self.jitter >= 0):
            raise ValueError("unbounded scene: radius >= 2 (clear of the objects), camera_height in 0.2..3, "
                             "room >= radius + 2 and jitter >= 0 are required")

    @property
    def focal(self) -> float:
        return focal_from_angle(math.radians(self.fov_degrees), self.width)


def unbounded_shape(room: float, layout_seed: int = 0) -> Shape:
    """The scene's geometry: a checkered floor, four walls with value noise (coarser the further, so it keeps about
    the same size in the images; as tall as the room is wide, so no view sees over them) and three textured objects
    standing on the floor, their centres within 1.3 of the middle (moved by ``layout_seed``)."""
    thick = 0.1
    floor = Part("floor", Box((room + thick, room + thick, thick)),
                 Material((0.8, 0.78, 0.72), "checker", (0.45, 0.42, 0.4), frequency=1.0), position=(0.0, 0.0, -thick))
    walls = tuple(
        Part(f"wall_{k}", Box((thick, room, room) if axis == 0 else (room, thick, room)),
             Material((0.85, 0.8, 0.7), "noise", (0.3, 0.4, 0.55), frequency=12.0 / room, seed=7 + 4 * layout_seed + k),
             position=tuple(float(sign * (room + thick)) if a == axis else (room if a == 2 else 0.0) for a in range(3)))
        for k, (axis, sign) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1))))
    moved = np.array([(-0.6, 0.3, 0.45), (0.55, -0.35, 0.35), (0.15, 0.6, 0.45)])  # each standing on the floor
    moved[:, :2] += layout_offsets(layout_seed)[:, :2]
    return Shape("unbounded", (floor, *walls, *object_parts(moved)))


def ring_poses(config: UnboundedSceneConfig) -> torch.Tensor:
    """(V, 4, 4) float64 camera-to-world poses on a ring around the middle, in order round it (a walk), each looking
    at the point 0.3 above the middle of the floor."""
    gen = np.random.default_rng(config.seed)
    angle = 2.0 * math.pi * np.arange(config.views) / config.views
    eye = np.stack([config.radius * np.cos(angle), config.radius * np.sin(angle), np.full_like(angle, config.camera_height)], -1)
    eye = torch.tensor(eye + gen.uniform(-1.0, 1.0, eye.shape) * config.jitter, dtype=torch.float64)
    target = torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64).expand_as(eye)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(eye)
    return look_at(eye, target, up)


def ring_bounds(config: UnboundedSceneConfig, poses: torch.Tensor) -> np.ndarray:
    """(V, 2) near and far depth of each view along its optical axis: a lower bound on anything seen (no surface
    comes within 0.8 x ``camera_height`` of a camera) and the room's farthest corner."""
    axis = -poses[:, :3, 2].double()
    centres = poses[:, :3, 3].double()
    r = config.room
    corners = torch.tensor([[x, y, z] for x in (-r, r) for y in (-r, r) for z in (0.0, 2.0 * r)], dtype=torch.float64)
    far = ((corners[None] - centres[:, None]) * axis[:, None]).sum(-1).amax(1)
    near = torch.full_like(far, 0.8 * config.camera_height)
    return torch.stack([near, far], -1).numpy()


def render_unbounded_scene(config: UnboundedSceneConfig) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """Render the scene: images (V, H, W, 3) uint8, poses (V, 4, 4) float64, bounds (V, 2) depths."""
    shape = unbounded_shape(config.room, config.layout_seed)
    poses = ring_poses(config)
    images = render_capture(shape, poses, config.focal, config.height, config.width, config.supersample)
    return images, poses, ring_bounds(config, poses)


def make_unbounded_scene(folder: str | os.PathLike, config: UnboundedSceneConfig = UnboundedSceneConfig()) -> Path:
    """Render and write an unbounded scene into ``folder`` (absent or empty); returns the folder."""
    return make_llff_folder(folder, lambda: render_unbounded_scene(config), config.focal)
