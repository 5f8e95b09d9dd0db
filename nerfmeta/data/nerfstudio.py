"""nerfstudio / instant-ngp scenes: one ``transforms.json``.

Intrinsics come from ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, given at the top level or
per frame (a frame's values override the top level). Without ``fl_x``, ``camera_angle_x`` gives
``fl_x = 0.5 * w / tan(camera_angle_x / 2)``; ``fl_y`` defaults to ``camera_angle_y`` the same way,
then to ``fl_x``; ``cx``, ``cy`` default to the image centre and ``w``, ``h`` to the image size (when
given they must match it). Lens distortion (``k1 k2 k3 p1 p2``, OpenCV's model) is removed on load: the
images are resampled into pinhole ones (:mod:`nerfmeta.data.distortion`); fisheye and equirectangular cameras
are refused. Poses are OpenGL camera-to-world ``transform_matrix``.

Images read at a reduced size (``--downscale``, ``--max-side``) by a whole factor N come from ``images_N/`` when
it holds a copy of every ``images/`` file at that size, as ``ns-process-data`` writes them (decoding a quarter-size
copy instead of a 12-megapixel photo); otherwise ``images/`` is reduced on load.

Splits: every 8th view (0, 8, 16, ...) is held out as the test split.

``near``/``far``: the top-level keys when present. Otherwise a heuristic (see
:func:`~nerfmeta.data.bounds.near_far_from_cameras`): the point the optical axes pass closest to (least squares) is
taken as the centre of interest, and with ``d`` the camera distances to it,
``near = 0.5 * min(d)`` and ``far = 1.5 * max(d)`` (which gives 2 and 6 for NeRF-synthetic
cameras at radius 4). When the cameras do not look at a common point (e.g. forward-facing
captures) the file must give ``near`` and ``far``. ``category`` and ``aabb`` are read as in the
Blender format.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerfmeta.data.bounds import near_far_from_cameras
from nerfmeta.data.common import (
    HOLDOUT_EVERY_TEXT,
    LoadOptions,
    build_scene,
    check_image_sizes,
    check_pose,
    every_nth_splits,
    find_frame_image,
    finite_number,
    near_far,
    parse_aabb,
    parse_category,
    read_json,
    read_views,
    scale_intrinsics,
    side_factor,
)
from nerfmeta.data.distortion import COEFFICIENTS, undistort_views_
from nerfmeta.data.images import downscaled_size, image_shape
from nerfmeta.data.scene import Scene
from nerfmeta.errors import SceneError

log = logging.getLogger(__name__)

NAME = "nerfstudio"
EXPECTS = "transforms.json with fl_x/fl_y/cx/cy/w/h (or camera_angle_x) and frames"
FILE_NAME = "transforms.json"
UNSUPPORTED_CAMERAS = ("OPENCV_FISHEYE", "FISHEYE624", "EQUIRECTANGULAR")


def detect(path: Path) -> bool:
    """True for a folder holding ``transforms.json``."""
    return path.is_dir() and (path / FILE_NAME).is_file()


def _get(frame: dict[str, Any], doc: dict[str, Any], key: str) -> Any:
    return frame[key] if key in frame else doc.get(key)


def _frame_intrinsics(
    frame: dict[str, Any], doc: dict[str, Any], height: int, width: int, *, where: str
) -> list[float]:
    """``[fx, fy, cx, cy]`` of one frame for an image of ``height`` x ``width`` pixels."""
    for key, actual in (("w", width), ("h", height)):
        value = _get(frame, doc, key)
        if value is not None and finite_number(value, where=f"{where}: {key}", positive=True) != actual:
            raise SceneError(f"{where}: {key} is {value} but the image is {width}x{height}")
    fl_x = _get(frame, doc, "fl_x")
    if fl_x is not None:
        fx = finite_number(fl_x, where=f"{where}: fl_x", positive=True)
    else:
        angle = _get(frame, doc, "camera_angle_x")
        if angle is None:
            raise SceneError(f"{where}: needs fl_x or camera_angle_x")
        fx = _focal_from_angle(angle, width, where=f"{where}: camera_angle_x")
    fl_y = _get(frame, doc, "fl_y")
    if fl_y is not None:
        fy = finite_number(fl_y, where=f"{where}: fl_y", positive=True)
    elif _get(frame, doc, "camera_angle_y") is not None:
        fy = _focal_from_angle(_get(frame, doc, "camera_angle_y"), height, where=f"{where}: camera_angle_y")
    else:
        fy = fx
    cx = _get(frame, doc, "cx")
    cy = _get(frame, doc, "cy")
    cx = width / 2 if cx is None else finite_number(cx, where=f"{where}: cx")
    cy = height / 2 if cy is None else finite_number(cy, where=f"{where}: cy")
    return [fx, fy, cx, cy]


def _focal_from_angle(angle: Any, size: int, *, where: str) -> float:
    value = finite_number(angle, where=where, positive=True)
    if value >= math.pi:
        raise SceneError(f"{where} must be below pi radians, got {value:g}")
    return 0.5 * size / math.tan(0.5 * value)


def reduced_copies(path: Path, image_paths: list[Path], factor: float, size: tuple[int, int]) -> list[Path] | None:
    """The ``images_N/`` copies of ``image_paths`` (``images/...`` under ``path``) for the whole-number ``factor`` N,
    as nerfstudio's ``ns-process-data`` writes ``images_2/``, ``images_4/`` and ``images_8/`` beside ``images/``:
    None unless every one exists and the first is ``size`` = (height, width) reduced by N (to a pixel); a copy folder
    that is incomplete or of another size is passed over with a warning (as the LLFF loader's ``images_N/``)."""
    if factor <= 1 or not float(factor).is_integer():
        return None
    folder = path / f"images_{int(factor)}"
    if not folder.is_dir():
        return None
    copies = []
    for image in image_paths:
        parts = image.relative_to(path).parts
        if len(parts) < 2 or parts[0] != "images":
            return None
        copies.append(folder.joinpath(*parts[1:]))
    held = sum(copy.is_file() for copy in copies)
    if held < len(copies):
        log.warning("%s holds %d of the %d frames' images: reading images/ and downscaling it instead", folder, held,
                    len(copies))
        return None
    want, got = downscaled_size(*size, factor), image_shape(copies[0])
    if abs(want[0] - got[0]) > 1 or abs(want[1] - got[1]) > 1:
        log.warning("%s holds %d x %d images, not images/ reduced %d times (%d x %d): reading images/ instead", folder,
                    got[1], got[0], int(factor), want[1], want[0])
        return None
    return copies


def load(path: Path, options: LoadOptions) -> Scene:
    """Read a nerfstudio / instant-ngp ``transforms.json`` scene (see the module docstring)."""
    file = path / FILE_NAME
    return load_document(path, read_json(file), options, file=file)


def load_document(path: Path, doc: dict[str, Any], options: LoadOptions, *, file: Path, scene_format: str = NAME,
                  near_far_source: str = "from file") -> Scene:
    """The scene of a ``transforms.json`` document ``doc`` whose ``file_path`` are relative to ``path`` (read from
    ``file``, or made from another format's files, as :mod:`nerfmeta.data.colmap` does: ``file`` then names where
    it came from in messages, ``scene_format`` the scene's format and ``near_far_source`` where its near/far came
    from)."""
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SceneError(f"{file}: 'frames' must be a non-empty list")
    image_paths: list[Path] = []
    poses = []
    for k, frame in enumerate(frames):
        where = f"{file}: frame {k}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise SceneError(f"{where}: needs file_path and transform_matrix")
        model = _get(frame, doc, "camera_model")
        if model in UNSUPPORTED_CAMERAS:
            raise SceneError(f"{where}: camera_model {model} is not supported (pinhole cameras only)")
        image_paths.append(find_frame_image(path, frame["file_path"], where=where))
        poses.append(check_pose(frame["transform_matrix"], where=where))
    poses_np = np.stack(poses)

    height, width = check_image_sizes(image_paths, options.max_pixels)
    intrinsics = torch.tensor(
        [_frame_intrinsics(f, doc, height, width, where=f"{file}: frame {k}") for k, f in enumerate(frames)],
        dtype=torch.float64,
    )
    coeffs = torch.tensor([[finite_number(_get(f, doc, key) or 0.0, where=f"{file}: frame {k}: {key}")
                            for key in COEFFICIENTS] for k, f in enumerate(frames)], dtype=torch.float64)
    if any(_get(f, doc, "k4") not in (None, 0, 0.0) for f in frames):
        log.warning("%s: the fisheye coefficient k4 is ignored (k1, k2, k3, p1, p2 are removed on load)", file)

    where = str(file)
    if "near" in doc or "far" in doc:
        if "near" not in doc or "far" not in doc:
            raise SceneError(f"{where}: give both near and far, or neither")
        near, far = near_far(doc["near"], doc["far"], where=where)
    else:
        guess = near_far_from_cameras(poses_np)
        if guess is None:
            raise SceneError(
                f"{where}: cannot guess near/far because the cameras do not look at a common point; "
                "add top-level 'near' and 'far' keys"
            )
        near, far = guess
        near_far_source = "derived from the cameras (not in the file): 0.5 x nearest and 1.5 x farthest camera distance to the point they look at"
    aabb = parse_aabb(doc["aabb"], where=where) if "aabb" in doc else None
    category = parse_category(doc.get("category"), where=where)

    factor = side_factor(height, width, options.downscale, options.max_side)
    copies = reduced_copies(path, image_paths, factor, (height, width))
    views = read_views(image_paths if copies is None else copies, options, downscale=None if copies is None else 1.0)
    intrinsics = scale_intrinsics(intrinsics, views.width / width, views.height / height)
    if bool((coeffs != 0).any()):  # resampled into pinhole images: every ray cast is a straight pinhole ray
        views = undistort_views_(views, intrinsics, coeffs)
        log.info("%s: lens distortion removed on load (%d views)", file, int((coeffs != 0).any(dim=1).sum()))
    return build_scene(
        views=views,
        poses=poses_np,
        intrinsics=intrinsics,
        near=near,
        far=far,
        splits=every_nth_splits(len(image_paths)),
        holdout=HOLDOUT_EVERY_TEXT,
        source=path,
        format=scene_format,
        options=options,
        downscale=views.factor if copies is None else factor,
        aabb=aabb,
        category=category,
        image_names=[p.relative_to(path).as_posix() for p in image_paths],
        where=str(file),
        near_far_source=near_far_source,
    )
