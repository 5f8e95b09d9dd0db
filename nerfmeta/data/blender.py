"""Blender / NeRF-synthetic scenes: ``transforms_{train,val,test}.json``.

Each file holds ``camera_angle_x`` (horizontal field of view, radians) and ``frames`` with a
``file_path`` (relative to the folder, extension optional: ``.png`` is tried) and a 4x4
camera-to-world ``transform_matrix`` in the OpenGL convention. Intrinsics are
``fx = fy = 0.5 * W / tan(camera_angle_x / 2)`` and ``(cx, cy) = (W / 2, H / 2)``;
``camera_angle_y``, when present, sets ``fy`` the same way.

nerfmeta's optional top-level keys (read from ``transforms_train.json``): ``near``, ``far`` (ray
distances), ``category`` and ``aabb``.

Without ``near``/``far`` in the file (:func:`~nerfmeta.data.bounds.default_near_far`), the
cameras give them as for nerfstudio scenes: with ``d`` the camera distances to the point their
optical axes pass closest to, ``0.5 * min(d)`` and ``1.5 * max(d)``. When those lie within a
factor 1.5 of NeRF-synthetic's 2 and 6 (cameras at its scale, as in lego: radius 4.03 gives
2.02 / 6.05), the scene keeps exactly 2 and 6, so NeRF-synthetic scenes load as they always did;
a scene at another scale (cameras 0.004 from a 0.002-unit object, or 4000 units away) gets the
derived values, and the load-time normalisation then follows from them. Cameras that share no
point of focus keep 2 and 6.

Splits: the files' own; when there is no ``transforms_test.json``, every 8th training view
(0, 8, 16, ...) is held out as the test split.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nerfmeta.data.bounds import FAR_SYNTHETIC, NEAR_SYNTHETIC, default_near_far
from nerfmeta.data.common import (
    HOLDOUT_EVERY_TEXT,
    LoadOptions,
    build_scene,
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
)
from nerfmeta.data.scene import SPLITS, Scene
from nerfmeta.errors import SceneError

NAME = "blender"
EXPECTS = "transforms_train.json (+ transforms_val.json, transforms_test.json) with camera_angle_x and frames"
DEFAULT_NEAR = NEAR_SYNTHETIC
DEFAULT_FAR = FAR_SYNTHETIC


def detect(path: Path) -> bool:
    """True for a folder holding any ``transforms_{train,val,test}.json``."""
    return path.is_dir() and any((path / f"transforms_{s}.json").is_file() for s in SPLITS)


def field_of_view(doc: dict[str, Any], key: str, *, where: str) -> float:
    """A field-of-view angle in (0, pi) radians from ``doc[key]``."""
    angle = finite_number(doc[key], where=f"{where}: {key}", positive=True)
    if angle >= math.pi:
        raise SceneError(f"{where}: {key} must be below pi radians, got {angle:g}")
    return angle


def focal_from_angle(angle: float, size: int) -> float:
    """Focal length in pixels of a field of view ``angle`` (radians) across ``size`` pixels."""
    return 0.5 * size / math.tan(0.5 * angle)


def load(path: Path, options: LoadOptions) -> Scene:
    """Read a Blender-format scene folder (see the module docstring)."""
    train_file = path / "transforms_train.json"
    if not train_file.is_file():
        raise SceneError(f"{path}: has no transforms_train.json (Blender format needs the training split)")
    image_paths: list[Path] = []
    poses = []
    angles: list[tuple[float, float | None]] = []
    splits: dict[str, tuple[int, ...]] = {}
    head: dict[str, Any] = {}
    for split in SPLITS:
        file = path / f"transforms_{split}.json"
        if not file.is_file():
            continue
        doc = read_json(file)
        if split == "train":
            head = doc
        if "camera_angle_x" not in doc:
            raise SceneError(f"{file}: missing camera_angle_x")
        angle_x = field_of_view(doc, "camera_angle_x", where=str(file))
        angle_y = field_of_view(doc, "camera_angle_y", where=str(file)) if "camera_angle_y" in doc else None
        frames = doc.get("frames")
        if not isinstance(frames, list) or not frames:
            raise SceneError(f"{file}: 'frames' must be a non-empty list")
        start = len(image_paths)
        for k, frame in enumerate(frames):
            where = f"{file}: frame {k}"
            if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
                raise SceneError(f"{where}: needs file_path and transform_matrix")
            image_paths.append(find_frame_image(path, frame["file_path"], where=where))
            poses.append(check_pose(frame["transform_matrix"], where=where))
            angles.append((angle_x, angle_y))
        splits[split] = tuple(range(start, len(image_paths)))

    holdout = "from file"
    if "test" not in splits:
        within = every_nth_splits(len(splits["train"]))
        train = splits["train"]
        splits["train"] = tuple(train[i] for i in within["train"])
        splits["test"] = tuple(train[i] for i in within["test"])
        holdout = HOLDOUT_EVERY_TEXT

    where = str(train_file)
    if "near" in head or "far" in head:
        near, far = near_far(head.get("near", DEFAULT_NEAR), head.get("far", DEFAULT_FAR), where=where)
        near_far_source = "from file"
    else:
        near, far, near_far_source = default_near_far(np.stack(poses))
    aabb = parse_aabb(head["aabb"], where=where) if "aabb" in head else None
    category = parse_category(head.get("category"), where=where)

    views = read_views(image_paths, options)
    w0, h0 = views.source_width, views.source_height
    rows = []
    for ax, ay in angles:
        fx = focal_from_angle(ax, w0)
        rows.append([fx, fx if ay is None else focal_from_angle(ay, h0), w0 / 2, h0 / 2])
    intrinsics = torch.tensor(rows, dtype=torch.float64)
    intrinsics = scale_intrinsics(intrinsics, views.width / w0, views.height / h0)
    return build_scene(
        views=views,
        poses=np.stack(poses),
        intrinsics=intrinsics,
        near=near,
        far=far,
        splits=splits,
        holdout=holdout,
        source=path,
        format=NAME,
        options=options,
        downscale=views.factor,
        aabb=aabb,
        category=category,
        image_names=[p.relative_to(path).as_posix() for p in image_paths],
        where=str(train_file),
        near_far_source=near_far_source,
    )
