"""Pieces shared by the scene parsers: load options, validation, image stacks, scene assembly.

Every check raises :class:`~nerfmeta.errors.SceneError` (bad files) or
:class:`~nerfmeta.errors.ConfigError` (bad options) with one line naming the file or value.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
import torch

from nerfmeta.data.bounds import frustum_bounds
from nerfmeta.data.images import (
    DEFAULT_MAX_PIXELS,
    check_pixel_limit,
    composite_,
    decode_array,
    downscale_image,
    downscaled_size,
    image_shape,
    to_float_images,
)
from nerfmeta.data.normalize import normalization_for
from nerfmeta.data.ranges import check_depth_range, check_geometry, check_intrinsics
from nerfmeta.data.scene import Normalization, Scene
from nerfmeta.data.scene_type import SCENE_TYPES, detect_scene_type
from nerfmeta.errors import ConfigError, SceneError

HOLDOUT_EVERY = 8
HOLDOUT_EVERY_TEXT = f"every {HOLDOUT_EVERY}th view (no test split in the files)"
ROTATION_TOLERANCE = 1e-3


@dataclass(frozen=True)
class LoadOptions:
    """How to read a scene (the same for every format)."""

    downscale: float = 1.0
    """Reduce images by this factor (>= 1) with area filtering; intrinsics follow."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """RGB in [0, 1] that images with an alpha channel are composited on."""
    max_pixels: int = DEFAULT_MAX_PIXELS
    """Refuse any image with more pixels than this (checked from the header, before decoding)."""
    normalize: bool = True
    """Bring a scene of extreme scale or far from the origin into range (a similarity transform,
    the identity for scenes already in range; rule in :mod:`nerfmeta.data.normalize`)."""
    scene_type: str = "auto"
    """``auto`` (detected from the cameras and image borders) or ``object``, ``forward``,
    ``unbounded`` (rule in :mod:`nerfmeta.data.scene_type`)."""
    max_side: int = 0
    """0: no limit. Else images whose longest side is still over this after ``downscale`` are reduced
    further, by the smallest power of two that brings them within it (:func:`side_factor`)."""

    def __post_init__(self) -> None:
        if not math.isfinite(self.downscale) or self.downscale < 1:
            raise ConfigError(f"downscale must be a number >= 1, got {self.downscale}")
        bg = tuple(self.background)
        if len(bg) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in bg):
            raise ConfigError(f"background must be three values in [0, 1], got {self.background}")
        object.__setattr__(self, "background", tuple(float(v) for v in bg))
        if int(self.max_pixels) < 1:
            raise ConfigError(f"max_pixels must be >= 1, got {self.max_pixels}")
        if int(self.max_side) < 0:
            raise ConfigError(f"max_side must be >= 0 (0: no limit), got {self.max_side}")
        if self.scene_type != "auto" and self.scene_type not in SCENE_TYPES:
            raise ConfigError(f"scene type must be auto, {', '.join(SCENE_TYPES)}; got {self.scene_type!r}")


# --- files -------------------------------------------------------------------------------------


MAX_JSON_BYTES = 256 << 20
"""Largest scene JSON file read (a transforms.json of 100k frames is about 50 MB)."""


def read_json(path: Path) -> dict[str, Any]:
    """A JSON object from ``path``; SceneError when missing, unreadable, over :data:`MAX_JSON_BYTES`,
    invalid, nested too deeply for the parser, or not an object."""
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise SceneError(f"{path}: {size / 2**20:.0f} MiB is too large for a scene file (limit {MAX_JSON_BYTES >> 20} MiB)")
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise SceneError(f"{path}: cannot read file ({err})") from err
    except json.JSONDecodeError as err:
        raise SceneError(f"{path}: invalid JSON at line {err.lineno} column {err.colno}: {err.msg}") from err
    except RecursionError:
        raise SceneError(f"{path}: JSON nested too deeply to be a scene file") from None
    if not isinstance(doc, dict):
        raise SceneError(f"{path}: expected a JSON object at the top level, got {type(doc).__name__}")
    return doc


def safe_relative(folder: Path, rel: Any, *, where: str) -> Path:
    """``folder / rel`` for a relative path that stays inside ``folder``.

    Checked on the path text (``..`` and absolute paths are refused), so symbolic links inside the
    scene folder are allowed.
    """
    if not isinstance(rel, str) or not rel.strip():
        raise SceneError(f"{where}: file_path must be a non-empty string, got {rel!r}")
    text = rel.replace("\\", "/")
    pure = PurePosixPath(text)
    if pure.is_absolute() or os.path.isabs(rel) or (len(text) > 1 and text[1] == ":"):
        raise SceneError(f"{where}: file_path {rel!r} is absolute; it must be relative to the scene folder")
    if ".." in pure.parts:
        raise SceneError(f"{where}: file_path {rel!r} leaves the scene folder")
    return folder.joinpath(*[p for p in pure.parts if p not in (".", "")])


def find_frame_image(folder: Path, rel: Any, *, where: str) -> Path:
    """The image a frame's ``file_path`` names, trying ``.png`` when the extension is omitted."""
    path = safe_relative(folder, rel, where=where)
    with_png = path.with_name(path.name + ".png")
    if path.is_file():
        return path
    if with_png.is_file():
        return with_png
    raise SceneError(f"{where}: image {rel!r} not found in {folder}")


# --- values ------------------------------------------------------------------------------------


def finite_number(value: Any, *, where: str, positive: bool = False) -> float:
    """``value`` as a float; SceneError when it is not a finite number (or not > 0 if ``positive``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise SceneError(f"{where} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise SceneError(f"{where} must be finite, got {number}")
    if positive and number <= 0:
        raise SceneError(f"{where} must be > 0, got {number:g}")
    return number


def check_pose(matrix: Any, *, where: str) -> np.ndarray:
    """A validated (4, 4) float64 rigid camera-to-world matrix.

    Refuses wrong shapes, NaN/inf, a bottom row other than ``[0, 0, 0, 1]``, and rotations that
    are not orthonormal (``|R^T R - I| > 1e-3``) or are reflections.
    """
    try:
        pose = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise SceneError(f"{where}: pose is not a 4x4 matrix of numbers") from err
    if pose.shape != (4, 4):
        raise SceneError(f"{where}: pose must be 4x4, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise SceneError(f"{where}: pose contains NaN or inf")
    if np.abs(pose[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise SceneError(f"{where}: pose bottom row must be [0, 0, 0, 1], got {pose[3].tolist()}")
    rot = pose[:3, :3]
    if np.abs(rot).max() > 1.0 + ROTATION_TOLERANCE:  # before the product, which would overflow for huge entries
        raise SceneError(f"{where}: pose is not rigid (rotation entry {float(np.abs(rot).max()):g} outside [-1, 1])")
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if err > ROTATION_TOLERANCE:
        raise SceneError(f"{where}: pose is not rigid (rotation not orthonormal, error {err:.3g})")
    if np.linalg.det(rot) < 0:
        raise SceneError(f"{where}: pose rotation is a reflection (determinant < 0)")
    return pose


def near_far(near: Any, far: Any, *, where: str) -> tuple[float, float]:
    """Validated ``0 <= near < far``, both finite."""
    n = finite_number(near, where=f"{where}: near")
    f = finite_number(far, where=f"{where}: far")
    if n < 0 or f <= n:
        raise SceneError(f"{where}: need 0 <= near < far, got near={n:g} far={f:g}")
    return n, f


def parse_aabb(value: Any, *, where: str) -> torch.Tensor:
    """A (2, 3) float64 box ``[[min xyz], [max xyz]]`` with min < max (float64 so that a box far from
    the origin keeps its size through load-time normalisation; the scene stores float32)."""
    try:
        box = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise SceneError(f"{where}: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]") from err
    if box.shape != (2, 3) or not np.isfinite(box).all() or not (box[0] < box[1]).all():
        raise SceneError(f"{where}: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max")
    return torch.tensor(box, dtype=torch.float64)


def parse_category(value: Any, *, where: str) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str):
        raise SceneError(f"{where}: category must be a string, got {value!r}")
    return value


def every_nth_splits(n_views: int, every: int = HOLDOUT_EVERY) -> dict[str, tuple[int, ...]]:
    """Views 0, every, 2*every, ... as ``test`` and the rest as ``train``."""
    test = tuple(range(0, n_views, every))
    train = tuple(i for i in range(n_views) if i % every != 0)
    return {"train": train, "test": test}


def scale_intrinsics(intrinsics: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """(n, 4) ``(fx, fy, cx, cy)`` for images resized by ``sx`` horizontally and ``sy`` vertically.

    Exact for the pixel-centre convention: the image edges map to the new edges.
    """
    scale = torch.tensor([sx, sy, sx, sy], dtype=intrinsics.dtype)
    return intrinsics * scale


# --- images ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewStack:
    """Images of all views, read, composited and downscaled.

    Attributes:
        images: (n, h, w, 3) float32 RGB composited on the background.
        alphas: (n, h, w) float32, or None when no image had an alpha channel.
        height, width: size after downscaling.
        source_height, source_width: size of the files.
        factor: the downscale applied to the files (the one asked for, or more under ``max_side``).
    """

    images: torch.Tensor
    alphas: torch.Tensor | None
    height: int
    width: int
    source_height: int
    source_width: int
    factor: float = 1.0


READ_CHUNK = 8
"""Images converted, composited and downscaled together (fewer, larger tensor operations)."""


def check_image_sizes(paths: Sequence[Path], max_pixels: int) -> tuple[int, int]:
    """Read every header; all images must exist, fit ``max_pixels`` and share the first one's size."""
    if not paths:
        raise SceneError("no images to read")
    first: tuple[int, int] | None = None
    for path in paths:
        height, width = image_shape(path)
        check_pixel_limit(path, height, width, max_pixels)
        if first is None:
            first = (height, width)
        elif (height, width) != first:
            raise SceneError(
                f"{path}: image is {width}x{height} but {paths[0].name} is {first[1]}x{first[0]}; "
                "all views must have the same size"
            )
    assert first is not None
    return first


def memory_limit_bytes() -> int:
    """This machine's physical memory: a scene whose images need more cannot be loaded."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # not a POSIX system: no limit known
        return 1 << 62


def side_factor(height: int, width: int, factor: float, max_side: int) -> float:
    """``factor`` times the smallest power of two (1, 2, 4, ...) that brings images of ``height`` x ``width`` reduced
    by it to a longest side of at most ``max_side`` (0: ``factor`` unchanged). Powers of two, as nerfstudio's
    automatic downscale, so that LLFF's ``images_2``/``images_4``/``images_8`` folders can serve them."""
    if max_side <= 0:
        return factor
    scale = 1
    while max(height, width) / (factor * scale) > max_side:
        scale *= 2
    return factor * scale


def check_stack_memory(n: int, height: int, width: int, factor: float, *, where: str) -> None:
    """Refuse, before anything is decoded, ``n`` views of ``height`` x ``width`` whose float32 stack
    (RGB + alpha, after downscaling by ``factor``) would not fit in :func:`memory_limit_bytes`."""
    out_h, out_w = downscaled_size(height, width, factor)
    need = n * out_h * out_w * 4 * 4
    limit = memory_limit_bytes()
    if need > limit:
        raise SceneError(f"{where}: {n} views of {width}x{height} need {need / 2**20:,.0f} MiB loaded, more than this "
                         f"machine's {limit / 2**20:,.0f} MiB of memory (use --downscale or fewer views)")


def stack_views(
    batches: Iterable[tuple[torch.Tensor, int]], n: int, height: int, width: int, options: LoadOptions, factor: float
) -> ViewStack:
    """Composite (at full size), downscale and store batches of float images.

    Args:
        batches: (images (B, H, W, 3|4) float in [0, 1], index of the first) in any order; the
            batches are overwritten (composited in place).
        n: total number of views.
        height, width: size of the source images.
    """
    out_h, out_w = downscaled_size(height, width, factor)
    images = torch.empty(n, out_h, out_w, 3, dtype=torch.float32)
    alphas: torch.Tensor | None = None
    for batch, start in batches:
        end = start + batch.shape[0]
        if batch.shape[-1] == 3:
            images[start:end] = downscale_image(batch, factor)
            continue
        small = downscale_image(composite_(batch, options.background), factor)
        images[start:end] = small[..., :3]
        if alphas is None:
            alphas = torch.ones(n, out_h, out_w, dtype=torch.float32)
        alphas[start:end] = small[..., 3]
    return ViewStack(images, alphas, out_h, out_w, height, width, factor)


def read_views(paths: Sequence[Path], options: LoadOptions, *, downscale: float | None = None) -> ViewStack:
    """Read, composite and downscale images that must all have the same size.

    Every header is checked (existence, pixel limit, equal sizes) before any pixel is decoded.
    Compositing happens at full size, then RGB and alpha are area-downscaled.

    Args:
        paths: one image file per view.
        options: background, pixel limit and (unless ``downscale`` is given) the factor.
        downscale: factor to apply instead of ``options.downscale`` (1 when the files are already
            reduced, as LLFF's ``images_N``).
    """
    height, width = check_image_sizes(paths, options.max_pixels)
    factor = side_factor(height, width, options.downscale if downscale is None else downscale, options.max_side)
    check_stack_memory(len(paths), height, width, factor, where=str(paths[0].parent))

    def batches() -> Iterator[tuple[torch.Tensor, int]]:
        for start in range(0, len(paths), READ_CHUNK):
            chunk = list(paths[start : start + READ_CHUNK])
            arrays = [decode_array(p) for p in chunk]
            for path, array in zip(chunk, arrays):
                if array.shape[:2] != (height, width):  # a header that lied
                    raise SceneError(f"{path}: decoded size {array.shape[:2]} differs from its header")
            yield to_float_images(arrays, names=[str(p) for p in chunk]), start

    return stack_views(batches(), len(paths), height, width, options, factor)


def image_arrays_to_views(array: np.ndarray, options: LoadOptions, *, name: str) -> ViewStack:
    """A ViewStack from an in-memory (n, H, W, 3|4) uint8 or float [0, 1] array (NPZ scenes)."""
    if array.ndim != 4 or array.shape[-1] not in (3, 4) or array.shape[0] < 1:
        raise SceneError(f"{name}: images must be (N, H, W, 3) or (N, H, W, 4), got shape {array.shape}")
    height, width = int(array.shape[1]), int(array.shape[2])
    check_pixel_limit(name, height, width, options.max_pixels)

    def batches() -> Iterator[tuple[torch.Tensor, int]]:
        for start in range(0, len(array), READ_CHUNK):
            chunk = [np.asarray(a) for a in array[start : start + READ_CHUNK]]
            names = [f"{name}: images[{start + k}]" for k in range(len(chunk))]
            yield to_float_images(chunk, names=names), start

    return stack_views(batches(), len(array), height, width, options,
                       side_factor(height, width, options.downscale, options.max_side))


# --- scene -------------------------------------------------------------------------------------


def build_scene(
    *,
    views: ViewStack,
    poses: np.ndarray | torch.Tensor,
    intrinsics: torch.Tensor,
    near: float,
    far: float,
    splits: dict[str, tuple[int, ...]],
    holdout: str,
    source: Path,
    format: str,
    options: LoadOptions,
    downscale: float,
    aabb: torch.Tensor | None = None,
    category: str | None = None,
    image_names: Sequence[str] = (),
    where: str | None = None,
    near_far_source: str = "from file",
) -> Scene:
    """Assemble a :class:`Scene`, computing bounds from the camera frusta unless ``aabb`` is given.

    Poses, ``near``/``far`` and ``aabb`` are in the file's frame; unless ``options.normalize`` is
    off, the scene is then moved into range by :func:`~nerfmeta.data.normalize.normalization_for`
    (the identity for scenes already in range) and the transform is kept in ``Scene.normalization``.

    Numbers that are finite but out of proportion (:mod:`nerfmeta.data.ranges`) are refused first.

    Args:
        intrinsics: (n, 4) ``(fx, fy, cx, cy)`` for the images as read (after downscaling).
        where: the file to name in errors (default ``source``).
        near_far_source: where ``near``/``far`` came from (see :class:`Scene`).
    """
    poses_t = torch.as_tensor(np.asarray(poses), dtype=torch.float64)
    n = views.images.shape[0]
    if poses_t.shape != (n, 4, 4) or intrinsics.shape != (n, 4):
        raise ValueError(f"{n} views but poses {tuple(poses_t.shape)}, intrinsics {tuple(intrinsics.shape)}")
    where = str(source) if where is None else where
    check_depth_range(near, far, where=where)
    check_intrinsics(intrinsics, views.height, views.width, where=where)
    check_geometry(poses_t, far, aabb, where=where)
    if not splits.get("train"):
        raise SceneError(f"{source}: no training views (a scene needs at least 2 views)")
    if aabb is None:
        bounds = frustum_bounds(poses_t, intrinsics.double(), views.height, views.width, near, far)
    else:
        bounds = aabb.double()
    norm = normalization_for(bounds, far) if options.normalize else Normalization()
    if not norm.is_identity:
        poses_t = norm.apply_poses(poses_t)
        bounds = norm.apply_points(bounds)
        near, far = near * norm.scale, far * norm.scale
    return Scene(
        images=views.images,
        poses=poses_t.float(),
        intrinsics=intrinsics.float(),
        near=float(near),
        far=float(far),
        bounds=bounds.float(),
        splits={k: tuple(int(i) for i in v) for k, v in splits.items()},
        holdout=holdout,
        source=source,
        format=format,
        category=category,
        background=options.background if views.alphas is not None else None,
        alphas=views.alphas,
        image_names=tuple(image_names),
        downscale=float(downscale),
        normalization=norm,
        near_far_source=near_far_source,
        scene_type=detect_scene_type(poses_t, views.images, views.alphas, options.scene_type),
    )
