"""NeRF "tiny" NPZ scenes (``tiny_nerf_data.npz``): one ``.npz`` file.

Arrays: ``images`` (N, H, W, 3) uint8 or float in [0, 1] (4 channels are composited as RGBA),
``poses`` (N, 4, 4) OpenGL camera-to-world, ``focal`` (scalar, pixels). Intrinsics are
``(focal, focal, W/2, H/2)``, ``near``/``far`` come from the cameras as for a Blender file without
them (:func:`~nerfmeta.data.bounds.default_near_far`: 2 and 6 for the tiny scene, which is the
NeRF-synthetic lego), and every 8th view (0, 8, 16, ...) is held out as the test split.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import torch

from nerfmeta.data.arrays import ArrayHeader, npz_headers
from nerfmeta.data.bounds import default_near_far
from nerfmeta.data.common import (
    HOLDOUT_EVERY_TEXT,
    LoadOptions,
    build_scene,
    check_pose,
    check_stack_memory,
    every_nth_splits,
    finite_number,
    image_arrays_to_views,
    scale_intrinsics,
)
from nerfmeta.data.images import check_pixel_limit
from nerfmeta.data.scene import Scene
from nerfmeta.errors import SceneError

NAME = "npz"
EXPECTS = "a .npz file with images (N, H, W, 3), poses (N, 4, 4) and focal"
KEYS = ("images", "poses", "focal")


def detect(path: Path) -> bool:
    """True for a file whose name ends in ``.npz``."""
    return path.is_file() and path.suffix.lower() == ".npz"


def check_declared_shapes(path: Path, headers: dict[str, ArrayHeader], max_pixels: int) -> None:
    """Refuse missing arrays, wrong shapes and images over ``max_pixels`` from the headers alone."""
    missing = [k for k in KEYS if k not in headers]
    if missing:
        raise SceneError(f"{path}: missing array(s) {', '.join(missing)} (needs {', '.join(KEYS)})")
    images, poses, focal = (headers[k].shape for k in KEYS)
    if len(images) != 4 or images[-1] not in (3, 4) or images[0] < 1:
        raise SceneError(f"{path}: images must be (N, H, W, 3) with N >= 1, got shape {images}")
    check_pixel_limit(f"{path}: images", images[1], images[2], max_pixels)
    check_stack_memory(images[0], images[1], images[2], 1.0, where=f"{path}: images")
    if poses != (images[0], 4, 4):
        raise SceneError(f"{path}: poses must be (N, 4, 4) with N = {images[0]} images, got shape {poses}")
    if math.prod(focal) != 1:
        raise SceneError(f"{path}: focal must be a single number, got shape {focal}")


def load(path: Path, options: LoadOptions) -> Scene:
    """Read a tiny-NeRF ``.npz`` scene (see the module docstring).

    The declared shapes are checked (from the ``.npy`` headers, see :mod:`nerfmeta.data.arrays`)
    before any array is read.
    """
    check_declared_shapes(path, npz_headers(path), options.max_pixels)
    try:
        with np.load(path, allow_pickle=False) as archive:
            missing = [k for k in KEYS if k not in archive.files]
            if missing:
                raise SceneError(f"{path}: missing array(s) {', '.join(missing)} (needs {', '.join(KEYS)})")
            images, poses, focal = (archive[k] for k in KEYS)
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise SceneError(f"{path}: cannot read as a .npz archive ({err})") from err
    if images.ndim != 4 or images.shape[-1] not in (3, 4) or len(images) < 1:
        raise SceneError(f"{path}: images must be (N, H, W, 3) with N >= 1, got shape {images.shape}")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(images):
        raise SceneError(f"{path}: poses must be (N, 4, 4) with N = {len(images)} images, got shape {poses.shape}")
    checked = np.stack([check_pose(p, where=f"{path}: poses[{k}]") for k, p in enumerate(poses)])
    if focal.size != 1:
        raise SceneError(f"{path}: focal must be a single number, got shape {focal.shape}")
    f = finite_number(focal.reshape(()).item(), where=f"{path}: focal", positive=True)

    near, far, near_far_source = default_near_far(checked)
    views = image_arrays_to_views(images, options, name=str(path))
    w0, h0 = views.source_width, views.source_height
    intrinsics = torch.tensor([[f, f, w0 / 2, h0 / 2]] * len(checked), dtype=torch.float64)
    intrinsics = scale_intrinsics(intrinsics, views.width / w0, views.height / h0)
    return build_scene(
        views=views,
        poses=checked,
        intrinsics=intrinsics,
        near=near,
        far=far,
        splits=every_nth_splits(len(checked)),
        holdout=HOLDOUT_EVERY_TEXT,
        source=path,
        format=NAME,
        options=options,
        downscale=views.factor,
        image_names=[f"{path.name}[{k}]" for k in range(len(checked))],
        where=str(path),
        near_far_source=near_far_source,
    )
