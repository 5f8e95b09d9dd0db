"""A classic LLFF folder for tests: images/ at full size (48 x 36), images_4/ reduced, (h, w, f) of the full size."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfmeta.collection.forward import ForwardSceneConfig, render_forward_scene, write_llff_scene
from nerfmeta.data.write import encode_png
from nerfmeta.io import write_bytes_atomic

CONFIG = ForwardSceneConfig(width=48, height=36, grid=(3, 3), supersample=1)


def write_classic_llff(folder: Path, *, reduced_offset: int = 0) -> np.ndarray:
    """Write the scene into ``folder``; returns its ``images_4/`` pixels (9, 9, 12, 3) uint8, which are the 4 x 4 means
    of the full images plus ``reduced_offset`` (to tell which folder a load read)."""
    images, poses, bounds = render_forward_scene(CONFIG)
    write_llff_scene(folder, images, poses, bounds, CONFIG.focal)
    small = images.reshape(9, 9, 4, 12, 4, 3).mean(axis=(2, 4)).round().astype("uint8") + reduced_offset
    for k, image in enumerate(small):
        write_bytes_atomic(folder / "images_4" / f"view_{k:03d}.png", encode_png(image))
    return small
