"""Reading what ``nerfmeta classify`` is given: a scene folder, a folder of images, or one image.

- A scene in any format :func:`nerfmeta.data.load_scene` reads (Blender, nerfstudio, LLFF, NPZ):
  **all of its views, every split**, are used. Large images are area-downscaled while they are
  read (the factor comes from the first image's header), so memory stays small.
- A folder of PNG/JPEG files without camera poses (or with them in ``images/``): every image,
  in name order; sizes may differ.
- A single PNG or JPEG file: one view.

Images may be any size, RGB or RGBA, 8- or 16-bit PNG or JPEG. Each view becomes premultiplied
RGBA at the classifier's input size (see :mod:`classifier.data`), to be composited on the
background the classifier was trained with.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from nerfmeta.data.images import DEFAULT_MAX_PIXELS, IMAGE_SUFFIXES, downscale_image, image_shape, list_photos, read_image
from nerfmeta.data.registry import FORMATS, load_scene
from nerfmeta.errors import SceneError

from classifier.data import RGB, scene_premultiplied, to_input_size


def image_premultiplied(image: torch.Tensor) -> torch.Tensor:
    """(H, W, 3|4) straight-alpha float image -> (4, H, W) premultiplied RGBA (alpha 1 for RGB)."""
    chw = image.permute(2, 0, 1)
    if chw.shape[0] == 3:
        return torch.cat([chw, torch.ones_like(chw[:1])], dim=0)
    alpha = chw[3:4]
    return torch.cat([chw[:3] * alpha, alpha], dim=0)


def _first_image(folder: Path) -> Path | None:
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
            return path
    return None


def _downscale_for(path: Path | None, size: int) -> float:
    """Factor that brings the longer side of the image at ``path`` down to about ``size``."""
    if path is None:
        return 1.0
    try:
        height, width = image_shape(path)
    except SceneError:
        return 1.0  # the scene loader reports the bad file with its own message
    return max(1.0, max(height, width) / size)


def read_image_views(paths: list[Path], size: int, max_pixels: int = DEFAULT_MAX_PIXELS) -> torch.Tensor:
    """Image files of any sizes -> (n, 4, size, size) premultiplied RGBA."""
    views = []
    for path in paths:
        view = image_premultiplied(read_image(path, max_pixels=max_pixels))
        factor = max(view.shape[1:]) / size
        if factor > 1.0:
            view = downscale_image(view.permute(1, 2, 0), factor).permute(2, 0, 1)
        views.append(to_input_size(view[None], size)[0])
    return torch.stack(views)


def read_scene_views(
    path: str | os.PathLike, *, size: int, background: RGB, max_pixels: int = DEFAULT_MAX_PIXELS
) -> torch.Tensor:
    """Every view of a scene folder, image folder or image file, ready for the classifier.

    Args:
        path: see the module docstring for what is accepted.
        size: the classifier's input size.
        background: the classifier's training background (RGBA files are composited on it).
        max_pixels: refuse images larger than this.

    Returns:
        (n_views, 4, size, size) premultiplied RGBA, n_views >= 1.

    Raises:
        SceneError: the path is missing, holds no readable image, or a file cannot be read.
    """
    path = Path(path)
    if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
        return read_image_views([path], size, max_pixels)
    if path.is_dir():
        if any(fmt.detect(path) for fmt in FORMATS):
            factor = _downscale_for(_first_image(path), size)
            scene = load_scene(path, downscale=factor, background=background, max_pixels=max_pixels)
            return to_input_size(scene_premultiplied(scene), size)
        images = list_photos(path)
        if images:
            return read_image_views(images, size, max_pixels)
        if not any(path.iterdir()):
            raise SceneError(f"{path}: folder is empty; expected a scene, a folder of images or an image file")
    if path.is_file() and not any(fmt.detect(path) for fmt in FORMATS):
        raise SceneError(f"{path}: not a scene or an image (expected a scene folder, an .npz, or an image file: "
                         f"{', '.join(IMAGE_SUFFIXES)})")
    # a .npz scene, or anything else: the loader reads it or raises its own one-line error
    return to_input_size(scene_premultiplied(load_scene(path, background=background, max_pixels=max_pixels)), size)
