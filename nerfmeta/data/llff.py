"""LLFF scenes: ``poses_bounds.npy`` with ``images/`` (and optionally ``images_N/``).

``poses_bounds.npy`` is (n_views, 17): per view a row-major 3x5 matrix ``[R | t | (h, w, f)]``
followed by the near and far scene depths. LLFF's rotation columns are [down, right, back]; they
are reordered to the OpenGL [right, up, back] (``[c1, -c0, c2]``). ``(h, w, f)`` describe the
full-resolution images; the intrinsics ``(f, f, w/2, h/2)`` are scaled to the size actually read.

Images are the files of ``images/``, sorted by name, one per row. With an integer downscale ``N``
and an ``images_N/`` folder holding one image per pose, that folder is read as is (LLFF's
pre-reduced images); otherwise ``images/`` is read and area-downscaled.

``near = 0.9 * min(near depths)`` and ``far = 1.1 * max(far depths)`` (the depths are along the
optical axis; the margin covers the longer corner rays). Splits: every 8th view (0, 8, 16, ...)
is held out as the test split. Poses are kept in the file's world units (no re-centring, no NDC).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from nerfmeta.data.arrays import npy_header
from nerfmeta.data.common import (
    HOLDOUT_EVERY_TEXT,
    LoadOptions,
    build_scene,
    check_pose,
    every_nth_splits,
    near_far,
    read_views,
    side_factor,
)
from nerfmeta.data.images import list_images
from nerfmeta.data.scene import Scene
from nerfmeta.errors import SceneError

log = logging.getLogger(__name__)

NAME = "llff"
EXPECTS = "poses_bounds.npy (N x 17) with images/ or images_N/"
FILE_NAME = "poses_bounds.npy"
ASPECT_TOLERANCE = 0.02
MAX_SIDE = 1e6
"""Largest image side (pixels) a poses_bounds.npy row may describe."""


def detect(path: Path) -> bool:
    """True for a folder holding ``poses_bounds.npy``."""
    return path.is_dir() and (path / FILE_NAME).is_file()


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """(n, 3, 4) LLFF ``[down, right, back | t]`` to (n, 4, 4) OpenGL ``[right, up, back | t]``."""
    out = np.zeros((len(poses), 4, 4), dtype=np.float64)
    out[:, :3, 0] = poses[:, :, 1]
    out[:, :3, 1] = -poses[:, :, 0]
    out[:, :3, 2] = poses[:, :, 2]
    out[:, :3, 3] = poses[:, :, 3]
    out[:, 3, 3] = 1.0
    return out


def _image_folder(path: Path, downscale: float, n_poses: int) -> tuple[Path, float]:
    """The folder to read and the downscale still to apply to its images.

    A pre-reduced ``images_N/`` is used only when it holds one image per pose; an incomplete one
    (a partial copy) is passed over for ``images/``, downscaled on load, with a warning.
    """
    if downscale > 1 and float(downscale).is_integer():
        reduced = path / f"images_{int(downscale)}"
        found = list_images(reduced)
        if len(found) == n_poses:
            return reduced, 1.0
        if found:
            log.warning("%s holds %d images for %d poses: reading images/ and downscaling it instead",
                        reduced, len(found), n_poses)
    full = path / "images"
    if not list_images(full):
        others = sorted(p.name for p in path.glob("images_*") if list_images(p))
        hint = f" (found {', '.join(others)}: use that factor as the downscale)" if others else ""
        raise SceneError(f"{path}: LLFF scene has no images in images/{hint}")
    return full, downscale


def load(path: Path, options: LoadOptions) -> Scene:
    """Read an LLFF scene folder (see the module docstring)."""
    file = path / FILE_NAME
    declared = npy_header(file).shape  # checked before reading: a forged header cannot make us allocate
    if len(declared) != 2 or declared[1] != 17 or declared[0] < 1:
        raise SceneError(f"{file}: expected an (N, 17) array, got shape {declared}")
    try:
        data = np.load(file, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise SceneError(f"{file}: cannot read as a .npy array ({err})") from err
    if data.ndim != 2 or data.shape[1] != 17 or data.shape[0] < 1:
        raise SceneError(f"{file}: expected an (N, 17) array, got shape {data.shape}")
    if not np.issubdtype(data.dtype, np.number):
        raise SceneError(f"{file}: expected numbers, got dtype {data.dtype}")
    data = data.astype(np.float64)
    if not np.isfinite(data).all():
        raise SceneError(f"{file}: contains NaN or inf")
    mats = data[:, :15].reshape(-1, 3, 5)
    hwf = mats[:, :, 4]
    if (hwf <= 0).any():
        raise SceneError(f"{file}: image height, width and focal (column 5) must be > 0")
    if (hwf[:, :2] < 1).any() or (hwf[:, :2] > MAX_SIDE).any():
        raise SceneError(f"{file}: image height and width (column 5) must be between 1 and {MAX_SIDE:g} pixels")
    poses = llff_to_opengl(mats[:, :, :4])
    for k, pose in enumerate(poses):
        check_pose(pose, where=f"{file}: view {k}")
    depths = data[:, 15:17]
    if (depths[:, 0] <= 0).any() or (depths[:, 1] <= depths[:, 0]).any():
        raise SceneError(f"{file}: per-view bounds must satisfy 0 < near < far")
    near, far = near_far(0.9 * depths[:, 0].min(), 1.1 * depths[:, 1].max(), where=str(file))

    # The factor the declared full size needs picks images_N/; images/ itself is sized by its files (they may
    # already be smaller than column 5 says), in read_views.
    factor = side_factor(int(hwf[:, 0].max()), int(hwf[:, 1].max()), options.downscale, options.max_side)
    folder, remaining = _image_folder(path, factor, len(poses))
    reduced_by = factor / remaining  # N for images_N/, 1 for images/
    image_paths = list_images(folder)
    if len(image_paths) != len(poses):
        raise SceneError(f"{file}: has {len(poses)} poses but {folder} holds {len(image_paths)} images")
    views = read_views(image_paths, options, downscale=1.0 if reduced_by > 1 else options.downscale)
    sx = views.width / hwf[:, 1]
    sy = views.height / hwf[:, 0]
    bad = np.abs(sx / sy - 1.0) > ASPECT_TOLERANCE
    if bad.any():
        k = int(np.argmax(bad))
        raise SceneError(
            f"{image_paths[k]}: image aspect {views.source_width}x{views.source_height} does not match "
            f"{int(hwf[k, 1])}x{int(hwf[k, 0])} in {FILE_NAME} (rotated images?)"
        )
    full = torch.tensor(np.stack([hwf[:, 2], hwf[:, 2], hwf[:, 1] / 2, hwf[:, 0] / 2], axis=-1))
    intrinsics = full * torch.tensor(np.stack([sx, sy, sx, sy], axis=-1))
    return build_scene(
        views=views,
        poses=poses,
        intrinsics=intrinsics,
        near=near,
        far=far,
        splits=every_nth_splits(len(poses)),
        holdout=HOLDOUT_EVERY_TEXT,
        source=path,
        format=NAME,
        options=options,
        downscale=reduced_by * views.factor,
        image_names=[p.relative_to(path).as_posix() for p in image_paths],
        where=str(file),
        near_far_source="from file (0.9 x nearest and 1.1 x farthest depth bound)",
    )
