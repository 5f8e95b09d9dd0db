"""Write scenes in the Blender/NeRF-synthetic format that :func:`nerfmeta.data.load_scene` reads.

Layout written (the same as the NeRF synthetic data)::

    folder/transforms_train.json   {"camera_angle_x", "frames": [{"file_path": "./train/r_0", "transform_matrix"}]}
    folder/transforms_test.json
    folder/train/r_0.png ...       RGBA, 8-bit

nerfmeta adds optional top-level keys that its reader understands: ``near``, ``far`` (ray
distances), ``category`` and ``aabb`` ([[min xyz], [max xyz]], where the content is known to lie).
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any, Mapping

import imageio.v3 as iio
import numpy as np
import torch

from nerfmeta.io import write_bytes_atomic


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, C) uint8 image; deterministic for identical input."""
    buf = io.BytesIO()
    iio.imwrite(buf, image, extension=".png")
    return buf.getvalue()


def write_blender_scene(
    folder: str | os.PathLike,
    splits: Mapping[str, tuple[np.ndarray, torch.Tensor]],
    camera_angle_x: float,
    extra: Mapping[str, Any] | None = None,
) -> None:
    """Write one scene in the Blender format.

    Args:
        folder: destination folder (created).
        splits: split name (``train``/``val``/``test``) -> (images, poses): images (N, H, W, 4)
            uint8 RGBA (or 3 channels for opaque images), poses (N, 4, 4) camera-to-world.
        camera_angle_x: horizontal field of view in radians.
        extra: additional top-level JSON keys (``near``, ``far``, ``category``, ``aabb``...).
    """
    folder = Path(folder)
    for split, (images, poses) in splits.items():
        if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] not in (3, 4):
            raise ValueError(f"{split}: images must be (N, H, W, 3|4) uint8, got {images.shape} {images.dtype}")
        if len(images) != len(poses):
            raise ValueError(f"{split}: {len(images)} images but {len(poses)} poses")
        frames = []
        for k, (image, pose) in enumerate(zip(images, poses)):
            rel = f"./{split}/r_{k}"
            write_bytes_atomic(folder / split / f"r_{k}.png", encode_png(image))
            frames.append({"file_path": rel, "transform_matrix": pose.double().tolist()})
        doc = {"camera_angle_x": float(camera_angle_x), **dict(extra or {}), "frames": frames}
        write_bytes_atomic(folder / f"transforms_{split}.json", (json.dumps(doc, indent=1) + "\n").encode())
