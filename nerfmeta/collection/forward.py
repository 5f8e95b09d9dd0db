"""A generated forward-facing scene in the LLFF format, for tests and benchmarks.

The layout of an LLFF capture (Mildenhall et al., "Local Light Field Fusion"): a few textured
objects at different depths in front of a textured wall, photographed from a small grid of
camera positions on a plane, every camera looking one way (at a point behind the objects, as a
hand-held capture aims at its subject). World frame: z up, the cameras at ``y = 0`` looking
along +y, the wall a plane facing them at ``y = wall_distance``. Rendered by the collection's
sphere tracer (:func:`~nerfmeta.collection.render.render_shape`), written as ``images/`` plus
``poses_bounds.npy`` (each view's near and far depth along its optical axis, from the known
geometry, where LLFF takes them from the sparse points), so it goes through the real loader
(:mod:`nerfmeta.data.llff`). Same config, same bytes.
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from nerfmeta.collection.generate import to_uint8
from nerfmeta.collection.render import RenderConfig, render_shape
from nerfmeta.collection.shapes import Box, Cylinder, Material, Part, Shape, Sphere, shape_part_bounds
from nerfmeta.data.blender import focal_from_angle
from nerfmeta.data.write import encode_png
from nerfmeta.io import write_bytes_atomic
from nerfmeta.render.cameras import look_at


@dataclass(frozen=True)
class ForwardSceneConfig:
    """A generated forward-facing scene (defaults: 20 views of 160 x 120, as LLFF's 20-view captures)."""

    width: int = 160
    """Image width in pixels."""
    height: int = 120
    """Image height in pixels."""
    fov_degrees: float = 60.0
    """Horizontal field of view."""
    grid: tuple[int, int] = (5, 4)
    """Camera positions across and up the capture plane (views = product)."""
    spacing: float = 0.15
    """Distance between neighbouring camera positions (world units; the objects are 1.5-3 away)."""
    wall_distance: float = 16.0
    """Distance from the capture plane to the wall (LLFF captures span about ten times the nearest depth)."""
    jitter: float = 0.02
    """Largest random offset of each camera position along each axis, world units (LLFF captures are hand-held)."""
    seed: int = 0
    """Seed of the camera jitter."""
    layout_seed: int = 0
    """Seed of the objects' layout: 0 the fixed layout, any other value moves each object (up to 0.4 across, 0.6 in depth, 0.25 up) and reseeds the wall's texture."""
    supersample: int = 2
    """Anti-aliasing rays per pixel along each axis at edges (see RenderConfig)."""

    def __post_init__(self) -> None:
        check_views("forward scene", self.width, self.height, self.fov_degrees)
        if len(self.grid) != 2 or min(self.grid) < 1 or self.grid[0] * self.grid[1] < 2:
            raise ValueError(f"forward scene: grid must be two positive counts with at least 2 views, got {self.grid}")
        if self.spacing <= 0 or self.wall_distance <= 3.5 or self.jitter < 0:
            raise ValueError("forward scene: spacing > 0, wall_distance > 3.5 and jitter >= 0 are required")

    @property
    def focal(self) -> float:
        return focal_from_angle(math.radians(self.fov_degrees), self.width)


def check_views(what: str, width: int, height: int, fov_degrees: float) -> None:
    """ValueError naming ``what`` unless the views are at least 4 x 4 pixels with a horizontal field of view in 1..120
    degrees (the generated captures' common checks)."""
    if width < 4 or height < 4:
        raise ValueError(f"{what}: images must be at least 4x4 pixels, got {width}x{height}")
    if not 1.0 <= fov_degrees <= 120.0:
        raise ValueError(f"{what}: fov_degrees must be in 1..120, got {fov_degrees}")


def layout_offsets(layout_seed: int) -> np.ndarray:
    """(3, 3) offsets (across, depth, up) of the sphere, box and column: zeros for layout 0, else seeded
    uniform draws within (0.4, 0.6, 0.25)."""
    if layout_seed == 0:
        return np.zeros((3, 3))
    return np.random.default_rng(layout_seed).uniform(-1.0, 1.0, (3, 3)) * np.array([0.4, 0.6, 0.25])


def forward_shape(wall_distance: float, layout_seed: int = 0) -> Shape:
    """The scene's geometry: three textured objects 1.6-3.8 units in front of the capture plane (1.2-4.4 with a
    ``layout_seed``, see :func:`layout_offsets`) and a wall.

    The wall is wide and tall enough to fill a 120-degree view from anywhere on the capture plane; its
    texture is coarser the further it is, so it keeps about the same size in the images.
    """
    half = 2.0 * wall_distance
    wall = Part("wall", Box((half, 0.1, half)),
                Material((0.85, 0.8, 0.7), "noise", (0.25, 0.35, 0.55), frequency=12.0 / wall_distance, seed=7 + layout_seed),
                position=(0.0, wall_distance + 0.1, 0.0))
    moved = np.array([(-0.9, 2.6, 0.35), (0.95, 3.4, 0.3), (0.05, 1.8, -0.55)]) + layout_offsets(layout_seed)
    return Shape("forward", (wall, *object_parts(moved)))


def object_parts(positions: np.ndarray) -> tuple[Part, Part, Part]:
    """The three textured objects of the generated captures at (3, 3) ``positions``: a sphere of radius 0.45 with
    value noise, a rounded box of half-side 0.35 with a checkerboard, a column (radius 0.16, half-height 0.45) with
    stripes."""
    sphere = Part("sphere", Sphere(0.45), Material((0.9, 0.3, 0.2), "noise", (0.95, 0.85, 0.3), frequency=4.0, seed=3),
                  position=tuple(positions[0].tolist()))
    box = Part("box", Box((0.35, 0.35, 0.35), rounding=0.03),
               Material((0.2, 0.5, 0.9), "checker", (0.95, 0.95, 0.95), frequency=4.0),
               position=tuple(positions[1].tolist()))
    column = Part("column", Cylinder(0.16, 0.45), Material((0.2, 0.7, 0.3), "stripes", (0.1, 0.15, 0.1), frequency=5.0),
                  position=tuple(positions[2].tolist()))
    return sphere, box, column


def capture_poses(config: ForwardSceneConfig) -> torch.Tensor:
    """(V, 4, 4) float64 camera-to-world poses on the plane ``y = 0``, row by row from the top left.

    Each camera looks at a point on the axis behind the objects (3 units ahead): views converge a
    few degrees, as a hand-held capture does.
    """
    nx, nz = config.grid
    gen = np.random.default_rng(config.seed)
    xs = (np.arange(nx) - 0.5 * (nx - 1)) * config.spacing
    zs = (0.5 * (nz - 1) - np.arange(nz)) * config.spacing
    eye = np.array([[x, 0.0, z] for z in zs for x in xs]) + gen.uniform(-1.0, 1.0, (nx * nz, 3)) * config.jitter
    eye = torch.tensor(eye, dtype=torch.float64)
    target = torch.tensor([0.0, 3.0, 0.0], dtype=torch.float64).expand_as(eye)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(eye)
    return look_at(eye, target, up)


def opengl_to_llff(poses: torch.Tensor, height: int, width: int, focal: float) -> np.ndarray:
    """(V, 4, 4) OpenGL camera-to-world -> (V, 3, 5) LLFF ``[down, right, back | t | (h, w, f)]``.

    The inverse of :func:`nerfmeta.data.llff.llff_to_opengl` (which maps ``[c0, c1, c2]`` to ``[c1, -c0, c2]``).
    """
    p = poses.double().numpy()
    out = np.zeros((len(p), 3, 5))
    out[:, :, 0] = -p[:, :3, 1]
    out[:, :, 1] = p[:, :3, 0]
    out[:, :, 2] = p[:, :3, 2]
    out[:, :, 3] = p[:, :3, 3]
    out[:, :, 4] = (height, width, focal)
    return out


def depth_bounds(shape: Shape, poses: torch.Tensor) -> np.ndarray:
    """(V, 2) near and far depth of each view along its optical axis: the nearest object box corner, the wall.

    The wall is the shape's first part; its near face bounds the far depth (nothing behind it is seen).
    """
    axis = -poses[:, :3, 2].double()  # (V, 3) viewing directions
    centres = poses[:, :3, 3].double()
    objects = torch.tensor(shape_part_bounds(shape.parts[1:]))  # (2, 3)
    corners = torch.stack(torch.meshgrid(*[objects[:, a] for a in range(3)], indexing="ij"), -1).reshape(-1, 3)
    near = ((corners[None] - centres[:, None]) * axis[:, None]).sum(-1).amin(1)
    wall_y = float(shape.parts[0].bounds()[0, 1])
    far = (wall_y - centres[:, 1]) / axis[:, 1]
    return torch.stack([near, far], -1).numpy()


def render_capture(shape: Shape, poses: torch.Tensor, focal: float, height: int, width: int, supersample: int) -> np.ndarray:
    """(V, H, W, 3) uint8 views of ``shape`` from ``poses`` (V, 4, 4), by :func:`~nerfmeta.collection.render.render_shape`."""
    return to_uint8(render_shape(shape, poses, focal, height, width, RenderConfig(supersample=supersample))[..., :3])


def render_forward_scene(config: ForwardSceneConfig) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """Render the scene: images (V, H, W, 3) uint8, poses (V, 4, 4) float64, bounds (V, 2) depths."""
    shape = forward_shape(config.wall_distance, config.layout_seed)
    poses = capture_poses(config)
    images = render_capture(shape, poses, config.focal, config.height, config.width, config.supersample)
    return images, poses, depth_bounds(shape, poses)


def write_llff_scene(folder: str | os.PathLike, images: np.ndarray, poses: torch.Tensor, bounds: np.ndarray, focal: float) -> None:
    """Write ``folder/images/view_XXX.png`` and ``folder/poses_bounds.npy`` (LLFF's (V, 17) layout).

    Args:
        images: (V, H, W, 3) uint8.
        poses: (V, 4, 4) OpenGL camera-to-world.
        bounds: (V, 2) near and far depth per view.
        focal: focal length in pixels.
    """
    folder = Path(folder)
    n, h, w = images.shape[:3]
    rows = np.concatenate([opengl_to_llff(poses, h, w, focal).reshape(n, 15), bounds], axis=1)
    for k, image in enumerate(images):
        write_bytes_atomic(folder / "images" / f"view_{k:03d}.png", encode_png(image))
    buf = io.BytesIO()
    np.save(buf, rows.astype(np.float64))
    write_bytes_atomic(folder / "poses_bounds.npy", buf.getvalue())


def make_forward_scene(folder: str | os.PathLike, config: ForwardSceneConfig = ForwardSceneConfig()) -> Path:
    """Render and write a forward-facing scene into ``folder`` (absent or empty); returns the folder."""
    return make_llff_folder(folder, lambda: render_forward_scene(config), config.focal)


def make_llff_folder(folder: str | os.PathLike, render: Callable[[], tuple[np.ndarray, torch.Tensor, np.ndarray]],
                     focal: float) -> Path:
    """Check that ``folder`` is absent or empty (else FileExistsError, before any work), then write what ``render()``
    returns (images, poses, bounds) into it with :func:`write_llff_scene`; returns the folder."""
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        raise FileExistsError(f"{folder}: not empty; choose a new folder")
    images, poses, bounds = render()
    write_llff_scene(folder, images, poses, bounds, focal)
    return folder
