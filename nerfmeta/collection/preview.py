"""Contact sheet of a collection: one view of the first few scenes of every category."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from nerfmeta.collection.generate import load_collection
from nerfmeta.io import write_bytes_atomic


def contact_sheet_tiles(
    root: str | os.PathLike, per_category: int = 4, split: str = "test", background: float = 1.0
) -> tuple[list[str], np.ndarray]:
    """Tile the first view of ``split`` of the first ``per_category`` scenes of each category.

    Returns:
        the category names (one per row, in collection order) and an (R * H, C * W, 3) uint8
        image composited on a grey level ``background``; a category with fewer scenes leaves
        its last tiles blank.
    """
    collection = load_collection(root)
    categories = list(dict.fromkeys(s.category for s in collection.scenes))
    rows = []
    size = None
    for category in categories:
        tiles = []
        for record in sorted(collection.by_category(category), key=lambda r: r.index)[:per_category]:
            folder = collection.scene_path(record)
            frames = json.loads((folder / f"transforms_{split}.json").read_text())["frames"]
            rgba = iio.imread(folder / (frames[0]["file_path"] + ".png")).astype(np.float32) / 255.0
            rgb = rgba[..., :3] * rgba[..., 3:] + background * (1.0 - rgba[..., 3:]) if rgba.shape[-1] == 4 else rgba
            tiles.append(np.round(rgb * 255.0).astype(np.uint8))
            size = rgb.shape[:2]
        rows.append(tiles)
    h, w = size
    sheet = np.full((len(rows) * h, per_category * w, 3), int(round(background * 255)), dtype=np.uint8)
    for i, tiles in enumerate(rows):
        for j, tile in enumerate(tiles):
            sheet[i * h : (i + 1) * h, j * w : (j + 1) * w] = tile
    return categories, sheet


def write_contact_sheet(root: str | os.PathLike, path: str | os.PathLike, per_category: int = 4, split: str = "test") -> Path:
    """Write the contact sheet of the collection at ``root`` as a PNG with category labels."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    labels, sheet = contact_sheet_tiles(root, per_category, split)
    tile_h = sheet.shape[0] // len(labels)
    label_w = 90
    dpi = 100
    fig = Figure(figsize=((sheet.shape[1] + label_w) / dpi, sheet.shape[0] / dpi), dpi=dpi)
    ax = fig.add_axes((label_w / (sheet.shape[1] + label_w), 0.0, sheet.shape[1] / (sheet.shape[1] + label_w), 1.0))
    ax.imshow(sheet, interpolation="nearest")
    ax.set_axis_off()
    for i, name in enumerate(labels):
        fig.text(0.01, 1.0 - (i + 0.5) * tile_h / sheet.shape[0], name, va="center", ha="left", fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    path = Path(path)
    write_bytes_atomic(path, buf.getvalue())
    return path
